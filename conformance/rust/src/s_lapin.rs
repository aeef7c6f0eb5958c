//! Scenarios driven by lapin, the most used Rust client.

use crate::{check, e, reply_name, scenarios, wait_until, HANG, R, T};
use futures_lite::StreamExt;
use lapin::message::Delivery;
use lapin::options::*;
use lapin::publisher_confirm::Confirmation;
use lapin::types::{AMQPValue, DecimalValue, FieldArray, FieldTable, LongString, ShortString};
use lapin::{BasicProperties, Channel, Connection, ConnectionProperties, Consumer, ExchangeKind};
use serde_json::{json, Value};
use std::sync::Arc;
use std::time::Duration;

scenarios!("lapin":
    "connection.tune_and_open" => connection_tune,
    "connection.bad_password" => bad_password,
    "connection.unknown_vhost" => unknown_vhost,
    "exchange.topic_bind_unbind" => topic_bind_unbind,
    "exchange.e2e_and_alternate" => e2e_alternate,
    "queue.passive_and_exclusive_errors" => queue_errors,
    "queue.dead_letter_x_death" => dead_letter,
    "consume.stream_ack_nack" => consume_ack_nack,
    "consume.prefetch" => prefetch,
    "confirm.ack_and_mandatory_return" => confirm_return,
    "confirm.nack_on_overflow" => confirm_nack,
    "tx.commit_rollback" => tx,
    "properties.field_table_types" => field_types,
    "body.large_and_empty" => bodies,
    "get.empty_and_counts" => get_counts,
    "error.channel_reuse_after_close" => channel_after_close,
);

async fn connect(t: &T) -> Result<Connection, String> {
    e(
        Connection::connect(&t.url, ConnectionProperties::default()).await,
        "connect",
    )
}

async fn chan(c: &Connection) -> Result<Channel, String> {
    e(c.create_channel().await, "channel.open")
}

async fn temp_queue(ch: &Channel, args: FieldTable) -> Result<String, String> {
    let q = e(
        ch.queue_declare(
            "",
            QueueDeclareOptions {
                exclusive: true,
                ..Default::default()
            },
            args,
        )
        .await,
        "queue.declare",
    )?;
    Ok(q.name().as_str().to_string())
}

/// Declares an auto-delete exchange; `label` names the step in a failure.
async fn auto_delete_exchange(
    ch: &Channel,
    name: &str,
    kind: ExchangeKind,
    args: FieldTable,
    label: &str,
) -> R {
    let options = ExchangeDeclareOptions {
        auto_delete: true,
        ..Default::default()
    };
    e(ch.exchange_declare(name, kind, options, args).await, label)
}

/// Binds queue `q` to exchange `ex` with `key`.
async fn bind(ch: &Channel, q: &str, ex: &str, key: &str) -> R {
    let bound = ch
        .queue_bind(
            q,
            ex,
            key,
            QueueBindOptions::default(),
            FieldTable::default(),
        )
        .await;
    e(bound, "bind")
}

/// Puts the channel in confirm mode.
async fn confirm_mode(ch: &Channel) -> R {
    e(
        ch.confirm_select(ConfirmSelectOptions::default()).await,
        "confirm.select",
    )
}

fn code_of(err: &lapin::Error) -> Value {
    match err {
        lapin::Error::ProtocolError(p) => json!([p.get_id(), reply_name(p.get_message().as_str())]),
        other => json!(["other", format!("{other}")]),
    }
}

fn expect_code<V>(t: &T, label: &str, r: Result<V, lapin::Error>, code: u16) -> R {
    match r {
        Ok(_) => Err(format!("{label}: expected error {code}, call succeeded")),
        Err(err) => {
            let v = code_of(&err);
            t.obs(label, v.clone());
            check!(v[0] == json!(code), "{label}: expected {code}, got {err}");
            Ok(())
        }
    }
}

async fn publish(
    ch: &Channel,
    ex: &str,
    key: &str,
    body: &[u8],
    props: BasicProperties,
) -> Result<Confirmation, String> {
    let pc = e(
        ch.basic_publish(ex, key, BasicPublishOptions::default(), body, props)
            .await,
        "publish",
    )?;
    e(pc.await, "confirm")
}

async fn get_all(ch: &Channel, q: &str) -> Result<Vec<String>, String> {
    let mut out = vec![];
    while let Some(m) = e(
        ch.basic_get(q, BasicGetOptions { no_ack: true }).await,
        "get",
    )? {
        out.push(String::from_utf8_lossy(&m.delivery.data).into_owned());
    }
    Ok(out)
}

async fn next(consumer: &mut Consumer) -> Result<Delivery, String> {
    match tokio::time::timeout(HANG, consumer.next()).await {
        Ok(Some(Ok(d))) => Ok(d),
        Ok(Some(Err(err))) => Err(format!("consumer error: {err}")),
        Ok(None) => Err("consumer ended".into()),
        Err(_) => Err(format!("no delivery within {HANG:?}")),
    }
}

async fn count(ch: &Channel, q: &str) -> u32 {
    ch.queue_declare(
        q,
        QueueDeclareOptions {
            passive: true,
            ..Default::default()
        },
        FieldTable::default(),
    )
    .await
    .map(|q| q.message_count())
    .unwrap_or(u32::MAX)
}

async fn connection_tune(t: Arc<T>) -> R {
    let c = connect(&t).await?;
    let cfg = c.configuration();
    t.obs(
        "negotiated",
        json!([cfg.channel_max() > 0, cfg.frame_max() >= 4096]),
    );
    check!(cfg.frame_max() >= 4096, "frame_max {}", cfg.frame_max());
    let ch = chan(&c).await?;
    let q = temp_queue(&ch, FieldTable::default()).await?;
    t.eq(
        "queue named by broker",
        json!(q.starts_with("amq.gen-")),
        json!(true),
    )?;
    e(c.close(200, "bye").await, "close")?;
    wait_until(HANG, "closed state", || async { c.status().closed() }).await?;
    t.obs("closed", json!(true));
    Ok(())
}

async fn bad_password(t: Arc<T>) -> R {
    let r = Connection::connect(
        &t.url_with(None, Some("wrong"), None),
        ConnectionProperties::default(),
    )
    .await;
    match r {
        Ok(_) => Err("connected with a wrong password".into()),
        Err(err) => t.eq("refused", code_of(&err), json!([403, "ACCESS_REFUSED"])),
    }
}

async fn unknown_vhost(t: Arc<T>) -> R {
    let r = Connection::connect(
        &t.url_with(None, None, Some("no-such-vhost")),
        ConnectionProperties::default(),
    )
    .await;
    match r {
        Ok(_) => Err("connected to an unknown vhost".into()),
        Err(err) => t.eq("refused", code_of(&err), json!([530, "NOT_ALLOWED"])),
    }
}

async fn topic_bind_unbind(t: Arc<T>) -> R {
    let c = connect(&t).await?;
    let ch = chan(&c).await?;
    let ex = t.n("lapin-topic");
    auto_delete_exchange(
        &ch,
        &ex,
        ExchangeKind::Topic,
        FieldTable::default(),
        "declare",
    )
    .await?;
    let q = temp_queue(&ch, FieldTable::default()).await?;
    for k in ["log.*.error", "log.#"] {
        bind(&ch, &q, &ex, k).await?;
    }
    confirm_mode(&ch).await?;
    for k in ["log.app.error", "log.app.info", "other"] {
        publish(&ch, &ex, k, k.as_bytes(), BasicProperties::default()).await?;
    }
    t.eq(
        "two bindings, one copy each",
        json!(get_all(&ch, &q).await?),
        json!(["log.app.error", "log.app.info"]),
    )?;
    e(
        ch.queue_unbind(&q, &ex, "log.#", FieldTable::default())
            .await,
        "unbind",
    )?;
    for k in ["log.app.error", "log.app.info"] {
        publish(&ch, &ex, k, k.as_bytes(), BasicProperties::default()).await?;
    }
    t.eq(
        "after unbind",
        json!(get_all(&ch, &q).await?),
        json!(["log.app.error"]),
    )
}

async fn e2e_alternate(t: Arc<T>) -> R {
    let c = connect(&t).await?;
    let ch = chan(&c).await?;
    let (src, dst, ae) = (t.n("lapin-src"), t.n("lapin-dst"), t.n("lapin-ae"));
    let mut args = FieldTable::default();
    args.insert(
        "alternate-exchange".into(),
        AMQPValue::LongString(ae.clone().into()),
    );
    auto_delete_exchange(&ch, &ae, ExchangeKind::Fanout, FieldTable::default(), "ae").await?;
    auto_delete_exchange(&ch, &src, ExchangeKind::Direct, args, "src").await?;
    auto_delete_exchange(
        &ch,
        &dst,
        ExchangeKind::Fanout,
        FieldTable::default(),
        "dst",
    )
    .await?;
    e(
        ch.exchange_bind(
            &dst,
            &src,
            "to-dst",
            ExchangeBindOptions::default(),
            FieldTable::default(),
        )
        .await,
        "exchange.bind",
    )?;
    let qd = temp_queue(&ch, FieldTable::default()).await?;
    let qa = temp_queue(&ch, FieldTable::default()).await?;
    bind(&ch, &qd, &dst, "").await?;
    bind(&ch, &qa, &ae, "").await?;
    confirm_mode(&ch).await?;
    publish(&ch, &src, "to-dst", b"via e2e", BasicProperties::default()).await?;
    publish(
        &ch,
        &src,
        "elsewhere",
        b"via ae",
        BasicProperties::default(),
    )
    .await?;
    t.eq(
        "destination",
        json!(get_all(&ch, &qd).await?),
        json!(["via e2e"]),
    )?;
    t.eq(
        "alternate",
        json!(get_all(&ch, &qa).await?),
        json!(["via ae"]),
    )
}

async fn queue_errors(t: Arc<T>) -> R {
    let c = connect(&t).await?;
    let ch = chan(&c).await?;
    let r = ch
        .queue_declare(
            &t.n("lapin-missing"),
            QueueDeclareOptions {
                passive: true,
                ..Default::default()
            },
            FieldTable::default(),
        )
        .await;
    expect_code(&t, "passive missing", r, 404)?;
    let ch = chan(&c).await?;
    let q = t.n("lapin-excl");
    e(
        ch.queue_declare(
            &q,
            QueueDeclareOptions {
                exclusive: true,
                ..Default::default()
            },
            FieldTable::default(),
        )
        .await,
        "declare",
    )?;
    let c2 = connect(&t).await?;
    let ch2 = chan(&c2).await?;
    let r = ch2
        .queue_declare(&q, QueueDeclareOptions::default(), FieldTable::default())
        .await;
    expect_code(&t, "exclusive from other connection", r, 405)?;
    let ch3 = chan(&c).await?;
    let mut args = FieldTable::default();
    args.insert("x-max-length".into(), AMQPValue::LongInt(5));
    let r = ch3
        .queue_declare(
            &q,
            QueueDeclareOptions {
                exclusive: true,
                ..Default::default()
            },
            args,
        )
        .await;
    expect_code(&t, "inequivalent arg", r, 406)
}

async fn dead_letter(t: Arc<T>) -> R {
    let c = connect(&t).await?;
    let ch = chan(&c).await?;
    let dlq = temp_queue(&ch, FieldTable::default()).await?;
    let mut args = FieldTable::default();
    args.insert(
        "x-dead-letter-exchange".into(),
        AMQPValue::LongString("".into()),
    );
    args.insert(
        "x-dead-letter-routing-key".into(),
        AMQPValue::LongString(dlq.clone().into()),
    );
    args.insert("x-message-ttl".into(), AMQPValue::LongInt(30));
    let q = temp_queue(&ch, args).await?;
    confirm_mode(&ch).await?;
    publish(&ch, "", &q, b"ttl", BasicProperties::default()).await?;
    wait_until(HANG, "dead letter", || async {
        count(&ch, &dlq).await == 1
    })
    .await?;
    let m = e(
        ch.basic_get(&dlq, BasicGetOptions { no_ack: true }).await,
        "get",
    )?
    .ok_or("no message")?;
    let headers = m.delivery.properties.headers().clone().unwrap_or_default();
    let xd = match headers.inner().get("x-death") {
        Some(AMQPValue::FieldArray(a)) => a.as_slice().to_vec(),
        _ => vec![],
    };
    let first = match xd.first() {
        Some(AMQPValue::FieldTable(ft)) => ft.clone(),
        _ => return Err(format!("no x-death table: {headers:?}")),
    };
    let s = |k: &str| match first.inner().get(k) {
        Some(AMQPValue::LongString(v)) => json!(v.to_string()),
        Some(AMQPValue::LongLongInt(v)) => json!(v),
        Some(other) => json!(format!("{other:?}")),
        None => Value::Null,
    };
    t.eq(
        "x-death",
        json!([s("reason"), s("queue"), s("count"), s("exchange")]),
        json!(["expired", q, 1, ""]),
    )?;
    t.eq(
        "routing",
        json!([
            m.delivery.exchange.as_str(),
            m.delivery.routing_key.as_str()
        ]),
        json!(["", dlq]),
    )
}

async fn consume_ack_nack(t: Arc<T>) -> R {
    let c = connect(&t).await?;
    let ch = chan(&c).await?;
    let q = temp_queue(&ch, FieldTable::default()).await?;
    let mut consumer = e(
        ch.basic_consume(
            &q,
            "lapin-c",
            BasicConsumeOptions::default(),
            FieldTable::default(),
        )
        .await,
        "consume",
    )?;
    t.eq("tag", json!(consumer.tag().as_str()), json!("lapin-c"))?;
    for i in 0..3 {
        publish(
            &ch,
            "",
            &q,
            format!("{i}").as_bytes(),
            BasicProperties::default(),
        )
        .await?;
    }
    let mut seen = vec![];
    for _ in 0..3 {
        let d = next(&mut consumer).await?;
        seen.push(json!([
            String::from_utf8_lossy(&d.data),
            d.delivery_tag,
            d.redelivered
        ]));
        if d.delivery_tag == 2 {
            e(
                d.nack(BasicNackOptions {
                    requeue: true,
                    multiple: false,
                })
                .await,
                "nack",
            )?;
        } else {
            e(d.ack(BasicAckOptions::default()).await, "ack")?;
        }
    }
    let d = next(&mut consumer).await?;
    seen.push(json!([
        String::from_utf8_lossy(&d.data),
        d.delivery_tag,
        d.redelivered
    ]));
    e(d.ack(BasicAckOptions::default()).await, "ack")?;
    t.eq(
        "deliveries",
        json!(seen),
        json!([
            ["0", 1, false],
            ["1", 2, false],
            ["2", 3, false],
            ["1", 4, true]
        ]),
    )?;
    e(
        ch.basic_cancel("lapin-c", BasicCancelOptions::default())
            .await,
        "cancel",
    )?;
    t.eq("empty", json!(count(&ch, &q).await), json!(0))
}

async fn prefetch(t: Arc<T>) -> R {
    let c = connect(&t).await?;
    let ch = chan(&c).await?;
    let q = temp_queue(&ch, FieldTable::default()).await?;
    e(ch.basic_qos(2, BasicQosOptions::default()).await, "qos")?;
    for i in 0..5 {
        publish(
            &ch,
            "",
            &q,
            format!("{i}").as_bytes(),
            BasicProperties::default(),
        )
        .await?;
    }
    let mut consumer = e(
        ch.basic_consume(
            &q,
            "",
            BasicConsumeOptions::default(),
            FieldTable::default(),
        )
        .await,
        "consume",
    )?;
    let a = next(&mut consumer).await?;
    let b = next(&mut consumer).await?;
    let extra = tokio::time::timeout(Duration::from_millis(300), consumer.next())
        .await
        .is_ok();
    t.eq("no third before ack", json!(extra), json!(false))?;
    e(b.ack(BasicAckOptions { multiple: true }).await, "ack")?;
    let _ = a;
    let c3 = next(&mut consumer).await?;
    let c4 = next(&mut consumer).await?;
    t.eq(
        "next two",
        json!([
            String::from_utf8_lossy(&c3.data),
            String::from_utf8_lossy(&c4.data)
        ]),
        json!(["2", "3"]),
    )
}

async fn confirm_return(t: Arc<T>) -> R {
    let c = connect(&t).await?;
    let ch = chan(&c).await?;
    let q = temp_queue(&ch, FieldTable::default()).await?;
    confirm_mode(&ch).await?;
    let conf = publish(&ch, "", &q, b"ok", BasicProperties::default()).await?;
    t.eq(
        "routed ack",
        json!(matches!(conf, Confirmation::Ack(None))),
        json!(true),
    )?;
    let pc = e(
        ch.basic_publish(
            "",
            &t.n("nowhere"),
            BasicPublishOptions {
                mandatory: true,
                ..Default::default()
            },
            b"back",
            BasicProperties::default(),
        )
        .await,
        "publish",
    )?;
    match e(pc.await, "confirm")? {
        Confirmation::Ack(Some(ret)) => t.eq(
            "return then ack",
            json!([
                ret.reply_code,
                ret.reply_text.as_str(),
                String::from_utf8_lossy(&ret.delivery.data)
            ]),
            json!([312, "NO_ROUTE", "back"]),
        ),
        other => Err(format!("expected ack with a return, got {other:?}")),
    }
}

async fn confirm_nack(t: Arc<T>) -> R {
    let c = connect(&t).await?;
    let ch = chan(&c).await?;
    let mut args = FieldTable::default();
    args.insert("x-max-length".into(), AMQPValue::LongInt(1));
    args.insert(
        "x-overflow".into(),
        AMQPValue::LongString("reject-publish".into()),
    );
    let q = temp_queue(&ch, args).await?;
    confirm_mode(&ch).await?;
    let a = publish(&ch, "", &q, b"1", BasicProperties::default()).await?;
    let b = publish(&ch, "", &q, b"2", BasicProperties::default()).await?;
    t.eq(
        "ack then nack",
        json!([a.is_ack(), b.is_nack()]),
        json!([true, true]),
    )
}

async fn tx(t: Arc<T>) -> R {
    let c = connect(&t).await?;
    let ch = chan(&c).await?;
    let q = temp_queue(&ch, FieldTable::default()).await?;
    e(ch.tx_select().await, "tx.select")?;
    publish(&ch, "", &q, b"rolled back", BasicProperties::default()).await?;
    e(ch.tx_rollback().await, "rollback")?;
    publish(&ch, "", &q, b"committed", BasicProperties::default()).await?;
    t.eq(
        "nothing before commit",
        json!(count(&ch, &q).await),
        json!(0),
    )?;
    e(ch.tx_commit().await, "commit")?;
    t.eq(
        "after commit",
        json!(get_all(&ch, &q).await?),
        json!(["committed"]),
    )
}

fn fv(v: &AMQPValue) -> Value {
    match v {
        AMQPValue::Boolean(b) => json!({"bool": b}),
        AMQPValue::ShortShortInt(x) => json!({"i8": x}),
        AMQPValue::ShortShortUInt(x) => json!({"u8": x}),
        AMQPValue::ShortInt(x) => json!({"i16": x}),
        AMQPValue::ShortUInt(x) => json!({"u16": x}),
        AMQPValue::LongInt(x) => json!({"i32": x}),
        AMQPValue::LongUInt(x) => json!({"u32": x}),
        AMQPValue::LongLongInt(x) => json!({"i64": x}),
        AMQPValue::Float(x) => json!({"f32": x}),
        AMQPValue::Double(x) => json!({"f64": x}),
        AMQPValue::DecimalValue(d) => json!({"decimal": [d.scale, d.value]}),
        AMQPValue::ShortString(s) => json!({"shortstr": s.as_str()}),
        AMQPValue::LongString(s) => json!({"str": s.to_string()}),
        AMQPValue::FieldArray(a) => {
            json!({"array": a.as_slice().iter().map(fv).collect::<Vec<_>>()})
        }
        AMQPValue::Timestamp(x) => json!({"timestamp": x}),
        AMQPValue::FieldTable(t) => {
            json!({"table": t.inner().iter().map(|(k, v)| (k.to_string(), fv(v))).collect::<serde_json::Map<_, _>>()})
        }
        AMQPValue::ByteArray(b) => json!({"bytes": format!("{b:?}")}),
        AMQPValue::Void => json!("void"),
    }
}

async fn field_types(t: Arc<T>) -> R {
    let c = connect(&t).await?;
    let ch = chan(&c).await?;
    let q = temp_queue(&ch, FieldTable::default()).await?;
    let mut inner = FieldTable::default();
    inner.insert("k".into(), AMQPValue::LongString("v".into()));
    let mut h = FieldTable::default();
    h.insert("bool".into(), AMQPValue::Boolean(true));
    h.insert("i8".into(), AMQPValue::ShortShortInt(-5));
    h.insert("u8".into(), AMQPValue::ShortShortUInt(200));
    h.insert("i16".into(), AMQPValue::ShortInt(-300));
    h.insert("i32".into(), AMQPValue::LongInt(-70000));
    h.insert("u32".into(), AMQPValue::LongUInt(4_000_000_000));
    h.insert("i64".into(), AMQPValue::LongLongInt(-9_000_000_000));
    h.insert("f32".into(), AMQPValue::Float(0.25));
    h.insert("f64".into(), AMQPValue::Double(1e100));
    h.insert(
        "dec".into(),
        AMQPValue::DecimalValue(DecimalValue {
            scale: 2,
            value: 12345,
        }),
    );
    h.insert(
        "str".into(),
        AMQPValue::LongString(LongString::from("long string")),
    );
    h.insert(
        "arr".into(),
        AMQPValue::FieldArray(FieldArray::from(vec![
            AMQPValue::LongInt(1),
            AMQPValue::Boolean(false),
        ])),
    );
    h.insert("ts".into(), AMQPValue::Timestamp(1_700_000_000));
    h.insert("tbl".into(), AMQPValue::FieldTable(inner));
    h.insert("void".into(), AMQPValue::Void);
    let sent: serde_json::Map<String, Value> = h
        .inner()
        .iter()
        .map(|(k, v)| (k.to_string(), fv(v)))
        .collect();
    confirm_mode(&ch).await?;
    publish(
        &ch,
        "",
        &q,
        b"h",
        BasicProperties::default().with_headers(h),
    )
    .await?;
    let m = e(
        ch.basic_get(&q, BasicGetOptions { no_ack: true }).await,
        "get",
    )?
    .ok_or("no message")?;
    let got: serde_json::Map<String, Value> = m
        .delivery
        .properties
        .headers()
        .clone()
        .unwrap_or_default()
        .inner()
        .iter()
        .map(|(k, v)| (k.to_string(), fv(v)))
        .collect();
    t.eq(
        "headers with types",
        Value::Object(got),
        Value::Object(sent),
    )
}

async fn bodies(t: Arc<T>) -> R {
    let c = connect(&t).await?;
    let ch = chan(&c).await?;
    let q = temp_queue(&ch, FieldTable::default()).await?;
    confirm_mode(&ch).await?;
    let big: Vec<u8> = (0..5 * 1024 * 1024).map(|i| (i % 241) as u8).collect();
    publish(&ch, "", &q, &big, BasicProperties::default()).await?;
    publish(
        &ch,
        "",
        &q,
        b"",
        BasicProperties::default().with_content_type(ShortString::from("empty")),
    )
    .await?;
    let mut consumer = e(
        ch.basic_consume(
            &q,
            "",
            BasicConsumeOptions {
                no_ack: true,
                ..Default::default()
            },
            FieldTable::default(),
        )
        .await,
        "consume",
    )?;
    let a = next(&mut consumer).await?;
    let b = next(&mut consumer).await?;
    t.eq(
        "large",
        json!([a.data.len(), a.data == big]),
        json!([big.len(), true]),
    )?;
    t.eq(
        "empty",
        json!([
            b.data.len(),
            b.properties
                .content_type()
                .as_ref()
                .map(|s| s.as_str().to_string())
        ]),
        json!([0, "empty"]),
    )
}

async fn get_counts(t: Arc<T>) -> R {
    let c = connect(&t).await?;
    let ch = chan(&c).await?;
    let q = temp_queue(&ch, FieldTable::default()).await?;
    let none = e(ch.basic_get(&q, BasicGetOptions::default()).await, "get")?;
    t.eq("empty get", json!(none.is_none()), json!(true))?;
    confirm_mode(&ch).await?;
    for i in 0..4 {
        publish(
            &ch,
            "",
            &q,
            format!("{i}").as_bytes(),
            BasicProperties::default(),
        )
        .await?;
    }
    let m = e(ch.basic_get(&q, BasicGetOptions::default()).await, "get")?.ok_or("no message")?;
    t.eq(
        "get-ok",
        json!([
            m.message_count,
            m.delivery.delivery_tag,
            m.delivery.redelivered
        ]),
        json!([3, 1, false]),
    )?;
    e(
        m.delivery
            .reject(BasicRejectOptions { requeue: true })
            .await,
        "reject",
    )?;
    let m = e(
        ch.basic_get(&q, BasicGetOptions { no_ack: true }).await,
        "get",
    )?
    .ok_or("no message")?;
    t.eq(
        "requeued first",
        json!([
            String::from_utf8_lossy(&m.delivery.data),
            m.delivery.redelivered,
            m.message_count
        ]),
        json!(["0", true, 3]),
    )
}

async fn channel_after_close(t: Arc<T>) -> R {
    let c = connect(&t).await?;
    let ch = chan(&c).await?;
    let r = ch
        .exchange_declare(
            "amq.lapin-not-allowed",
            ExchangeKind::Direct,
            ExchangeDeclareOptions::default(),
            FieldTable::default(),
        )
        .await;
    expect_code(&t, "declare amq.*", r, 403)?;
    let r = ch
        .queue_declare("", QueueDeclareOptions::default(), FieldTable::default())
        .await;
    t.eq("closed channel refuses use", json!(r.is_err()), json!(true))?;
    let ch2 = chan(&c).await?;
    let q = temp_queue(&ch2, FieldTable::default()).await?;
    t.eq(
        "connection still fine",
        json!(q.starts_with("amq.gen-")),
        json!(true),
    )
}
