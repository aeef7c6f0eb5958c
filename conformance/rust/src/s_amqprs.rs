//! Scenarios driven by amqprs, the other common Rust client.

use crate::{check, e, reply_name, scenarios, wait_until, HANG, R, T};
use amqprs::callbacks::{ChannelCallback, DefaultConnectionCallback};
type CbResult<V> = std::result::Result<V, amqprs::error::Error>;
use amqprs::channel::*;
use amqprs::connection::{Connection, OpenConnectionArguments};
use amqprs::security::SecurityCredentials;
use amqprs::{Ack, BasicProperties, Cancel, CloseChannel, FieldTable, FieldValue, Nack, Return};
use async_trait::async_trait;
use serde_json::{json, Value};
use std::sync::{Arc, Mutex};
use std::time::Duration;

scenarios!("amqprs":
    "connection.plain_and_capabilities" => open_caps,
    "connection.amqplain" => amqplain,
    "connection.bad_password" => bad_password,
    "connection.heartbeat" => heartbeat,
    "exchange.fanout_get" => fanout_get,
    "queue.passive_missing_close_code" => passive_missing,
    "consume.rx_manual_ack_redelivery" => consume_rx,
    "consume.server_cancel" => server_cancel,
    "prefetch.global_qos" => global_qos,
    "confirm.acks_via_callback" => confirms,
    "mandatory.return_callback" => returns,
    "tx.commit" => tx,
    "properties.headers_and_fields" => props,
);

#[derive(Default, Clone)]
struct Events {
    closes: Arc<Mutex<Vec<(u16, String)>>>,
    cancels: Arc<Mutex<Vec<String>>>,
    acks: Arc<Mutex<Vec<(u64, bool)>>>,
    nacks: Arc<Mutex<Vec<(u64, bool)>>>,
    returns: Arc<Mutex<Vec<(u16, String, String, Vec<u8>)>>>,
}

struct Recorder(Events);

#[async_trait]
impl ChannelCallback for Recorder {
    async fn close(&mut self, _ch: &Channel, close: CloseChannel) -> CbResult<()> {
        self.0
            .closes
            .lock()
            .unwrap()
            .push((close.reply_code(), close.reply_text().clone()));
        Ok(())
    }
    async fn cancel(&mut self, _ch: &Channel, cancel: Cancel) -> CbResult<()> {
        self.0
            .cancels
            .lock()
            .unwrap()
            .push(cancel.consumer_tag().to_string());
        Ok(())
    }
    async fn flow(&mut self, _ch: &Channel, active: bool) -> CbResult<bool> {
        Ok(active)
    }
    async fn publish_ack(&mut self, _ch: &Channel, ack: Ack) {
        self.0
            .acks
            .lock()
            .unwrap()
            .push((ack.delivery_tag(), ack.mutiple()));
    }
    async fn publish_nack(&mut self, _ch: &Channel, nack: Nack) {
        self.0
            .nacks
            .lock()
            .unwrap()
            .push((nack.delivery_tag(), nack.multiple()));
    }
    async fn publish_return(
        &mut self,
        _ch: &Channel,
        ret: Return,
        _props: BasicProperties,
        content: Vec<u8>,
    ) {
        self.0.returns.lock().unwrap().push((
            ret.reply_code(),
            ret.reply_text().clone(),
            ret.routing_key().clone(),
            content,
        ));
    }
}

/// Drains the consumers' channels until `at_least` deliveries came (10 s
/// at most), then a little longer, so that one too many has had time to
/// arrive: how many came, and the highest delivery tag.
async fn settled(
    receivers: &mut [&mut tokio::sync::mpsc::UnboundedReceiver<ConsumerMessage>],
    at_least: usize,
) -> (usize, u64) {
    let (mut count, mut last) = (0, 0);
    let mut drain =
        |receivers: &mut [&mut tokio::sync::mpsc::UnboundedReceiver<ConsumerMessage>]| {
            for rx in receivers.iter_mut() {
                while let Ok(m) = rx.try_recv() {
                    count += 1;
                    last = last.max(m.deliver.map_or(0, |d| d.delivery_tag()));
                }
            }
            count
        };
    let deadline = tokio::time::Instant::now() + HANG;
    while drain(receivers) < at_least && tokio::time::Instant::now() < deadline {
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    tokio::time::sleep(Duration::from_millis(200)).await;
    drain(receivers);
    (count, last)
}

fn args(t: &T) -> OpenConnectionArguments {
    let mut a = OpenConnectionArguments::new(&t.host, t.port, &t.user, &t.password);
    a.virtual_host(&t.vhost);
    a
}

async fn connect(t: &T) -> Result<Connection, String> {
    let c = e(Connection::open(&args(t)).await, "connect")?;
    e(
        c.register_callback(DefaultConnectionCallback).await,
        "callback",
    )?;
    Ok(c)
}

async fn chan(c: &Connection) -> Result<(Channel, Events), String> {
    let ch = e(c.open_channel(None).await, "channel.open")?;
    let ev = Events::default();
    e(
        ch.register_callback(Recorder(ev.clone())).await,
        "channel callback",
    )?;
    Ok((ch, ev))
}

async fn temp_queue(ch: &Channel) -> Result<String, String> {
    let (q, _, _) = e(
        ch.queue_declare(QueueDeclareArguments::exclusive_server_named())
            .await,
        "queue.declare",
    )?
    .ok_or("no declare-ok")?;
    Ok(q)
}

/// Consumes `q` with manual acks under `tag`: the tag the server gave,
/// and the deliveries.
async fn consume_manual(
    ch: &Channel,
    q: &str,
    tag: &str,
) -> Result<
    (
        String,
        tokio::sync::mpsc::UnboundedReceiver<ConsumerMessage>,
    ),
    String,
> {
    let args = BasicConsumeArguments::new(q, tag).manual_ack(true).finish();
    e(ch.basic_consume_rx(args).await, "consume")
}

async fn publish(ch: &Channel, ex: &str, key: &str, body: &[u8]) -> R {
    e(
        ch.basic_publish(
            BasicProperties::default(),
            body.to_vec(),
            BasicPublishArguments::new(ex, key),
        )
        .await,
        "publish",
    )
}

async fn count(ch: &Channel, q: &str) -> u32 {
    match ch
        .queue_declare(QueueDeclareArguments::new(q).passive(true).finish())
        .await
    {
        Ok(Some((_, n, _))) => n,
        _ => u32::MAX,
    }
}

async fn get_all(ch: &Channel, q: &str) -> Result<Vec<String>, String> {
    let mut out = vec![];
    while let Some((_, _, body)) = e(
        ch.basic_get(BasicGetArguments::new(q).no_ack(true).finish())
            .await,
        "get",
    )? {
        out.push(String::from_utf8_lossy(&body).into_owned());
    }
    Ok(out)
}

async fn open_caps(t: Arc<T>) -> R {
    let c = connect(&t).await?;
    let caps = c.server_properties().capabilities();
    t.eq(
        "capabilities",
        json!([
            caps.publisher_confirms(),
            caps.basic_nack(),
            caps.consumer_cancel_notify(),
            caps.exchange_exchange_bindings(),
            caps.per_consumer_qos(),
            caps.authentication_failure_close()
        ]),
        json!([true, true, true, true, true, true]),
    )?;
    check!(c.frame_max() >= 4096, "frame_max {}", c.frame_max());
    let (ch, _) = chan(&c).await?;
    let q = temp_queue(&ch).await?;
    t.eq(
        "server-named",
        json!(q.starts_with("amq.gen-")),
        json!(true),
    )?;
    e(c.close().await, "close")
}

async fn amqplain(t: Arc<T>) -> R {
    let mut a = args(&t);
    a.credentials(SecurityCredentials::new_amqplain(&t.user, &t.password));
    let c = e(Connection::open(&a).await, "connect with AMQPLAIN")?;
    let (ch, _) = chan(&c).await?;
    temp_queue(&ch).await?;
    t.obs("opened with AMQPLAIN", json!(true));
    e(c.close().await, "close")
}

async fn bad_password(t: Arc<T>) -> R {
    let a = OpenConnectionArguments::new(&t.host, t.port, &t.user, "wrong-password");
    let r = Connection::open(&a).await;
    // amqprs reports a refused login without the reply code.
    t.eq("refused", json!(r.is_err()), json!(true))
}

async fn heartbeat(t: Arc<T>) -> R {
    let mut a = args(&t);
    a.heartbeat(1);
    let c = e(Connection::open(&a).await, "connect")?;
    t.eq("negotiated", json!(c.heartbeat()), json!(1))?;
    tokio::time::sleep(Duration::from_millis(3500)).await;
    t.eq("open after idle", json!(c.is_open()), json!(true))?;
    let (ch, _) = chan(&c).await?;
    temp_queue(&ch).await?;
    e(c.close().await, "close")
}

async fn fanout_get(t: Arc<T>) -> R {
    let c = connect(&t).await?;
    let (ch, _) = chan(&c).await?;
    let ex = t.n("amqprs-fan");
    e(
        ch.exchange_declare(
            ExchangeDeclareArguments::new(&ex, "fanout")
                .auto_delete(true)
                .finish(),
        )
        .await,
        "declare",
    )?;
    let q1 = temp_queue(&ch).await?;
    let q2 = temp_queue(&ch).await?;
    e(
        ch.queue_bind(QueueBindArguments::new(&q1, &ex, "")).await,
        "bind",
    )?;
    e(
        ch.queue_bind(QueueBindArguments::new(&q2, &ex, "x")).await,
        "bind",
    )?;
    publish(&ch, &ex, "k", b"to both").await?;
    wait_until(HANG, "fanout", || async { count(&ch, &q2).await == 1 }).await?;
    let m = e(
        ch.basic_get(BasicGetArguments::new(&q1).no_ack(true).finish())
            .await,
        "get",
    )?
    .ok_or("no message")?;
    t.eq(
        "get-ok",
        json!([
            m.0.delivery_tag(),
            m.0.redelivered(),
            m.0.exchange(),
            m.0.routing_key(),
            m.0.message_count(),
            String::from_utf8_lossy(&m.2)
        ]),
        json!([1, false, ex, "k", 0, "to both"]),
    )?;
    t.eq(
        "second queue",
        json!(get_all(&ch, &q2).await?),
        json!(["to both"]),
    )?;
    e(c.close().await, "close")
}

async fn passive_missing(t: Arc<T>) -> R {
    let c = connect(&t).await?;
    let (ch, ev) = chan(&c).await?;
    let r = ch
        .queue_declare(
            QueueDeclareArguments::new(&t.n("amqprs-missing"))
                .passive(true)
                .finish(),
        )
        .await;
    t.eq("declare failed", json!(r.is_err()), json!(true))?;
    wait_until(HANG, "channel.close", || async {
        !ev.closes.lock().unwrap().is_empty()
    })
    .await?;
    let (code, text) = ev.closes.lock().unwrap()[0].clone();
    t.eq(
        "close",
        json!([code, reply_name(&text)]),
        json!([404, "NOT_FOUND"]),
    )?;
    let (ch2, _) = chan(&c).await?;
    temp_queue(&ch2).await?;
    e(c.close().await, "close")
}

async fn consume_rx(t: Arc<T>) -> R {
    let c = connect(&t).await?;
    let (ch, _) = chan(&c).await?;
    let q = temp_queue(&ch).await?;
    let (tag, mut rx) = consume_manual(&ch, &q, "amqprs-c").await?;
    t.eq("tag", json!(tag), json!("amqprs-c"))?;
    publish(&ch, "", &q, b"m").await?;
    let mut seen = vec![];
    for i in 0..2 {
        let m = tokio::time::timeout(HANG, rx.recv())
            .await
            .map_err(|_| "no delivery")?
            .ok_or("consumer ended")?;
        let d = m.deliver.ok_or("no deliver")?;
        seen.push(json!([
            d.delivery_tag(),
            d.redelivered(),
            String::from_utf8_lossy(&m.content.unwrap_or_default())
        ]));
        if i == 0 {
            e(
                ch.basic_nack(BasicNackArguments::new(d.delivery_tag(), false, true))
                    .await,
                "nack",
            )?;
        } else {
            e(
                ch.basic_ack(BasicAckArguments::new(d.delivery_tag(), false))
                    .await,
                "ack",
            )?;
        }
    }
    t.eq(
        "delivered then redelivered",
        json!(seen),
        json!([[1, false, "m"], [2, true, "m"]]),
    )?;
    e(
        ch.basic_cancel(BasicCancelArguments::new("amqprs-c")).await,
        "cancel",
    )?;
    t.eq("acked", json!(count(&ch, &q).await), json!(0))?;
    e(c.close().await, "close")
}

async fn server_cancel(t: Arc<T>) -> R {
    let c = connect(&t).await?;
    let (ch, ev) = chan(&c).await?;
    let q = t.n("amqprs-cancel");
    e(
        ch.queue_declare(QueueDeclareArguments::new(&q)).await,
        "declare",
    )?;
    let (_tag, _rx) = e(
        ch.basic_consume_rx(BasicConsumeArguments::new(&q, "watched"))
            .await,
        "consume",
    )?;
    let (other, _) = chan(&c).await?;
    e(
        other.queue_delete(QueueDeleteArguments::new(&q)).await,
        "delete",
    )?;
    wait_until(HANG, "basic.cancel", || async {
        !ev.cancels.lock().unwrap().is_empty()
    })
    .await?;
    t.eq(
        "cancelled",
        json!(ev.cancels.lock().unwrap().clone()),
        json!(["watched"]),
    )?;
    e(c.close().await, "close")
}

async fn global_qos(t: Arc<T>) -> R {
    let c = connect(&t).await?;
    let (ch, _) = chan(&c).await?;
    let q = temp_queue(&ch).await?;
    e(
        ch.basic_qos(BasicQosArguments::new(0, 2, true)).await,
        "qos",
    )?;
    for i in 0..5 {
        publish(&ch, "", &q, format!("{i}").as_bytes()).await?;
    }
    let (_t1, mut rx1) = consume_manual(&ch, &q, "a").await?;
    let (_t2, mut rx2) = consume_manual(&ch, &q, "b").await?;
    let (n, last) = settled(&mut [&mut rx1, &mut rx2], 2).await;
    t.eq("two in flight across both consumers", json!(n), json!(2))?;
    e(
        ch.basic_ack(BasicAckArguments::new(last, true)).await,
        "ack",
    )?;
    let (more, _) = settled(&mut [&mut rx1, &mut rx2], 2).await;
    t.eq("two more after ack", json!(more), json!(2))?;
    e(c.close().await, "close")
}

async fn confirms(t: Arc<T>) -> R {
    let c = connect(&t).await?;
    let (ch, ev) = chan(&c).await?;
    let q = temp_queue(&ch).await?;
    e(
        ch.confirm_select(ConfirmSelectArguments::default()).await,
        "confirm.select",
    )?;
    for i in 0..100 {
        publish(&ch, "", &q, format!("{i}").as_bytes()).await?;
    }
    wait_until(Duration::from_secs(10), "acks", || async {
        ev.acks.lock().unwrap().last().map(|a| a.0) == Some(100)
    })
    .await?;
    let acks = ev.acks.lock().unwrap().clone();
    let mut prev = 0;
    for (tag, _) in &acks {
        check!(*tag > prev, "ack tags must increase: {acks:?}");
        prev = *tag;
    }
    t.eq("no nacks", json!(ev.nacks.lock().unwrap().len()), json!(0))?;
    t.eq("queued", json!(count(&ch, &q).await), json!(100))?;
    e(c.close().await, "close")
}

async fn returns(t: Arc<T>) -> R {
    let c = connect(&t).await?;
    let (ch, ev) = chan(&c).await?;
    let key = t.n("amqprs-nowhere");
    e(
        ch.basic_publish(
            BasicProperties::default(),
            b"ret".to_vec(),
            BasicPublishArguments::new("amq.direct", &key)
                .mandatory(true)
                .finish(),
        )
        .await,
        "publish",
    )?;
    wait_until(HANG, "basic.return", || async {
        !ev.returns.lock().unwrap().is_empty()
    })
    .await?;
    let r = ev.returns.lock().unwrap()[0].clone();
    t.eq(
        "return",
        json!([r.0, r.1, r.2, String::from_utf8_lossy(&r.3)]),
        json!([312, "NO_ROUTE", key, "ret"]),
    )?;
    e(c.close().await, "close")
}

async fn tx(t: Arc<T>) -> R {
    let c = connect(&t).await?;
    let (ch, _) = chan(&c).await?;
    let q = temp_queue(&ch).await?;
    e(ch.tx_select().await, "tx.select")?;
    publish(&ch, "", &q, b"1").await?;
    publish(&ch, "", &q, b"2").await?;
    e(ch.tx_rollback().await, "rollback")?;
    publish(&ch, "", &q, b"3").await?;
    e(ch.tx_commit().await, "commit")?;
    t.eq(
        "committed only",
        json!(get_all(&ch, &q).await?),
        json!(["3"]),
    )?;
    e(c.close().await, "close")
}

async fn props(t: Arc<T>) -> R {
    let c = connect(&t).await?;
    let (ch, _) = chan(&c).await?;
    let q = temp_queue(&ch).await?;
    let mut h = FieldTable::new();
    h.insert("s".try_into().unwrap(), FieldValue::from("text"));
    h.insert("b".try_into().unwrap(), FieldValue::from(true));
    h.insert("i".try_into().unwrap(), FieldValue::I(-12));
    h.insert("l".try_into().unwrap(), FieldValue::l(1 << 40));
    h.insert("d".try_into().unwrap(), FieldValue::d(0.5));
    h.insert("T".try_into().unwrap(), FieldValue::T(1_700_000_000));
    h.insert(
        "x".try_into().unwrap(),
        FieldValue::x(vec![1u8, 2, 3].try_into().unwrap()),
    );
    let props = BasicProperties::default()
        .with_content_type("application/octet-stream")
        .with_correlation_id("corr")
        .with_message_id("mid")
        .with_reply_to("rq")
        .with_priority(4)
        .with_persistence(true)
        .with_headers(h)
        .with_app_id("amqprs")
        .finish();
    e(
        ch.basic_publish(props, b"p".to_vec(), BasicPublishArguments::new("", &q))
            .await,
        "publish",
    )?;
    wait_until(HANG, "message", || async { count(&ch, &q).await == 1 }).await?;
    let (_, p, _) = e(
        ch.basic_get(BasicGetArguments::new(&q).no_ack(true).finish())
            .await,
        "get",
    )?
    .ok_or("no message")?;
    let hv = |k: &str| -> Value {
        json!(format!(
            "{:?}",
            p.headers().and_then(|h| h.get(&k.try_into().unwrap()))
        ))
    };
    t.eq(
        "properties",
        json!([
            p.content_type(),
            p.correlation_id(),
            p.message_id(),
            p.reply_to(),
            p.priority(),
            p.delivery_mode(),
            p.app_id()
        ]),
        json!([
            "application/octet-stream",
            "corr",
            "mid",
            "rq",
            4,
            2,
            "amqprs"
        ]),
    )?;
    t.eq(
        "headers",
        json!([
            hv("s"),
            hv("b"),
            hv("i"),
            hv("l"),
            hv("d"),
            hv("T"),
            hv("x")
        ]),
        json!([
            format!("{:?}", Some(&FieldValue::from("text"))),
            format!("{:?}", Some(&FieldValue::from(true))),
            format!("{:?}", Some(&FieldValue::I(-12))),
            format!("{:?}", Some(&FieldValue::l(1 << 40))),
            format!("{:?}", Some(&FieldValue::d(0.5))),
            format!("{:?}", Some(&FieldValue::T(1_700_000_000))),
            format!(
                "{:?}",
                Some(&FieldValue::x(vec![1u8, 2, 3].try_into().unwrap()))
            ),
        ]),
    )?;
    e(c.close().await, "close")
}
