//! Crash safety of the `leveret` binary, as a real process: kill -9 while
//! clients publish with confirms and while they commit transactions,
//! restart on the same data directory, and check that every confirmed
//! message is there once and in order, that transactions are all or
//! nothing, that every durable declaration and binding answered -ok just
//! before the kill is there, and that a clean shutdown keeps definitions,
//! messages, order, and forgets what was acked. For a stream queue: every
//! confirmed publish is in the stream after a kill -9, in order, at the
//! offset a reader saw before the kill, and a reader resumes from the
//! offset after the last one it was delivered.

use futures_lite::StreamExt;
use lapin::options::{
    BasicAckOptions, BasicConsumeOptions, BasicGetOptions, BasicPublishOptions, BasicQosOptions,
    ConfirmSelectOptions, ExchangeDeclareOptions, QueueBindOptions, QueueDeclareOptions,
};
use lapin::types::{AMQPValue, FieldTable};
use lapin::{BasicProperties, Channel, Connection, ConnectionProperties, ExchangeKind};
use std::collections::{HashMap, VecDeque};
use std::path::PathBuf;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Duration;

mod common;

use common::BrokerProcess;

const QUEUE: &str = "crash-test";

/// A fresh directory for a test's broker with `workers` threads.
fn temp_dir(name: &str, workers: usize) -> PathBuf {
    let dir = std::env::temp_dir().join(format!(
        "leveret-crash-{}-{name}-{workers}",
        std::process::id()
    ));
    let _ = std::fs::remove_dir_all(&dir);
    dir
}

async fn connect(broker: &BrokerProcess) -> Connection {
    tokio::time::timeout(
        Duration::from_secs(10),
        Connection::connect(&broker.url(), ConnectionProperties::default()),
    )
    .await
    .expect("connect in time")
    .expect("connect")
}

async fn declare(channel: &Channel) {
    let durable = QueueDeclareOptions {
        durable: true,
        ..Default::default()
    };
    channel
        .queue_declare(QUEUE, durable, FieldTable::default())
        .await
        .expect("declare durable queue");
}

fn persistent() -> BasicProperties {
    BasicProperties::default().with_delivery_mode(2)
}

/// Takes every message off the queue, in order.
async fn drain(channel: &Channel) -> Vec<String> {
    let mut bodies = Vec::new();
    loop {
        let got = tokio::time::timeout(
            Duration::from_secs(10),
            channel.basic_get(QUEUE, BasicGetOptions { no_ack: true }),
        )
        .await
        .expect("get in time")
        .expect("get");
        match got {
            Some(message) => bodies.push(String::from_utf8(message.delivery.data).expect("utf-8")),
            None => return bodies,
        }
    }
}

/// Publishes `c{id}:{seq}` with confirms (64 in flight), recording
/// confirmed seqs, until the connection dies.
async fn publish_until_killed(
    channel: Channel,
    id: usize,
    confirmed: Arc<Mutex<Vec<u64>>>,
    total: Arc<AtomicU64>,
) {
    if channel
        .confirm_select(ConfirmSelectOptions::default())
        .await
        .is_err()
    {
        return;
    }
    let mut window = VecDeque::new();
    for seq in 0u64.. {
        let body = format!("c{id}:{seq}");
        let Ok(confirm) = channel
            .basic_publish(
                "",
                QUEUE,
                BasicPublishOptions::default(),
                body.as_bytes(),
                persistent(),
            )
            .await
        else {
            return;
        };
        window.push_back((seq, confirm));
        if window.len() >= 64 {
            let Some((seq, confirm)) = window.pop_front() else {
                return;
            };
            match confirm.await {
                Ok(c) if c.is_ack() => {
                    confirmed.lock().expect("lock").push(seq);
                    total.fetch_add(1, Ordering::Relaxed);
                }
                _ => return,
            }
        }
    }
}

async fn wait_until(what: &str, counter: &AtomicU64, target: u64) {
    tokio::time::timeout(Duration::from_secs(60), async {
        while counter.load(Ordering::Acquire) < target {
            tokio::time::sleep(Duration::from_millis(1)).await;
        }
    })
    .await
    .unwrap_or_else(|_| panic!("{what}: did not reach {target} in time"));
}

/// Each crash test runs twice: against a broker on one thread (the
/// default) and on tokio's multi-thread runtime with four workers.
macro_rules! on_both_runtimes {
    ($($name:ident),* $(,)?) => {
        $(
            mod $name {
                #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
                async fn broker_on_one_thread() {
                    super::$name(1).await
                }

                #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
                async fn broker_on_four_worker_threads() {
                    super::$name(4).await
                }
            }
        )*
    };
}

on_both_runtimes!(
    confirmed_messages_survive_kill_9_once_and_in_order,
    transactions_are_all_or_nothing_across_kill_9,
    clean_restart_keeps_definitions_messages_and_order_and_forgets_acked,
    durable_declarations_survive_kill_9_right_after_their_ok,
    stream_keeps_confirmed_publishes_and_offsets_across_kill_9
);

/// `leveret` with its data in `dir`, serving on `workers` threads.
async fn start(dir: &std::path::Path, workers: usize) -> BrokerProcess {
    BrokerProcess::start_with(dir, ["--worker-threads", &workers.to_string()]).await
}

async fn confirmed_messages_survive_kill_9_once_and_in_order(workers: usize) {
    // Kill points spread over a run; each round kills while confirms
    // are in flight, so a broker confirming before its flush loses
    // messages in (nearly) every round.
    for (round, kill_after) in [150u64, 700, 1_100, 2_300, 3_700].into_iter().enumerate() {
        let dir = temp_dir(&format!("confirms-{round}"), workers);
        let broker = start(&dir, workers).await;
        let conn = connect(&broker).await;
        declare(&conn.create_channel().await.expect("channel")).await;
        let total = Arc::new(AtomicU64::new(0));
        let mut confirmed = Vec::new();
        let mut tasks = Vec::new();
        for id in 0..3 {
            let log = Arc::new(Mutex::new(Vec::new()));
            confirmed.push(Arc::clone(&log));
            let channel = conn.create_channel().await.expect("channel");
            tasks.push(tokio::spawn(publish_until_killed(
                channel,
                id,
                log,
                Arc::clone(&total),
            )));
        }
        wait_until("confirmed publishes", &total, kill_after).await;
        broker.kill9();
        for task in tasks {
            let _ = task.await;
        }
        drop(conn);

        let broker = start(&dir, workers).await;
        let conn = connect(&broker).await;
        let channel = conn.create_channel().await.expect("channel");
        let bodies = drain(&channel).await;
        let mut per_channel: HashMap<usize, Vec<u64>> = HashMap::new();
        for body in &bodies {
            let (id, seq) = body[1..].split_once(':').expect("c{id}:{seq}");
            per_channel
                .entry(id.parse().expect("id"))
                .or_default()
                .push(seq.parse().expect("seq"));
        }
        for (id, log) in confirmed.iter().enumerate() {
            let got = per_channel.remove(&id).unwrap_or_default();
            assert!(
                got.windows(2).all(|w| w[0] < w[1]),
                "round {round}: channel {id} out of order or duplicated"
            );
            let confirmed = log.lock().expect("lock");
            let missing: Vec<_> = confirmed
                .iter()
                .filter(|s| got.binary_search(s).is_err())
                .collect();
            assert!(
                missing.is_empty(),
                "round {round}: channel {id} lost {} of {} confirmed messages, first {:?}",
                missing.len(),
                confirmed.len(),
                missing.first()
            );
        }
        broker.kill9();
        let _ = std::fs::remove_dir_all(&dir);
    }
}

async fn transactions_are_all_or_nothing_across_kill_9(workers: usize) {
    const BATCH: usize = 40;
    let dir = temp_dir("tx", workers);
    let broker = start(&dir, workers).await;
    let conn = connect(&broker).await;
    let channel = conn.create_channel().await.expect("channel");
    declare(&channel).await;
    channel.tx_select().await.expect("tx.select");
    let committed = Arc::new(AtomicU64::new(0));
    let counter = Arc::clone(&committed);
    let publisher = tokio::spawn(async move {
        for batch in 0u64.. {
            for i in 0..BATCH {
                let body = format!("b{batch}:{i}");
                if channel
                    .basic_publish(
                        "",
                        QUEUE,
                        BasicPublishOptions::default(),
                        body.as_bytes(),
                        persistent(),
                    )
                    .await
                    .is_err()
                {
                    return;
                }
            }
            if channel.tx_commit().await.is_err() {
                return;
            }
            counter.store(batch + 1, Ordering::Release);
        }
    });
    wait_until("committed batches", &committed, 25).await;
    // Commits run back to back, so the kill lands in or between commits.
    broker.kill9();
    let _ = publisher.await;
    let committed = committed.load(Ordering::Acquire);

    let broker = start(&dir, workers).await;
    let conn = connect(&broker).await;
    let bodies = drain(&conn.create_channel().await.expect("channel")).await;
    let mut batches: Vec<(u64, usize)> = Vec::new();
    for body in &bodies {
        let (batch, i) = body[1..].split_once(':').expect("b{batch}:{i}");
        let (batch, i): (u64, usize) = (batch.parse().expect("batch"), i.parse().expect("i"));
        match batches.last_mut() {
            Some((b, count)) if *b == batch => {
                assert_eq!(i, *count, "batch {batch} out of order");
                *count += 1;
            }
            _ => {
                assert_eq!(i, 0, "batch {batch} starts with its first message");
                batches.push((batch, 1));
            }
        }
    }
    for (batch, count) in &batches {
        assert_eq!(
            *count, BATCH,
            "batch {batch} is partial: {count} of {BATCH}"
        );
    }
    let recovered: Vec<u64> = batches.iter().map(|(b, _)| *b).collect();
    assert_eq!(
        recovered,
        (0..recovered.len() as u64).collect::<Vec<_>>(),
        "batches come back in commit order"
    );
    assert!(
        recovered.len() as u64 >= committed,
        "all {committed} committed batches survive, got {}",
        recovered.len()
    );
    broker.kill9();
    let _ = std::fs::remove_dir_all(&dir);
}

async fn clean_restart_keeps_definitions_messages_and_order_and_forgets_acked(workers: usize) {
    let dir = temp_dir("clean", workers);
    let broker = start(&dir, workers).await;
    let conn = connect(&broker).await;
    let channel = conn.create_channel().await.expect("channel");
    declare(&channel).await;
    let durable = ExchangeDeclareOptions {
        durable: true,
        ..Default::default()
    };
    channel
        .exchange_declare(
            "crash-x",
            ExchangeKind::Topic,
            durable,
            FieldTable::default(),
        )
        .await
        .expect("durable exchange");
    channel
        .queue_bind(
            QUEUE,
            "crash-x",
            "robot.#",
            QueueBindOptions::default(),
            FieldTable::default(),
        )
        .await
        .expect("bind");
    for i in 0..100 {
        channel
            .basic_publish(
                "crash-x",
                "robot.cmd",
                BasicPublishOptions::default(),
                format!("m{i}").as_bytes(),
                persistent(),
            )
            .await
            .expect("publish");
    }
    for _ in 0..30 {
        let got = channel
            .basic_get(QUEUE, BasicGetOptions::default())
            .await
            .expect("get")
            .expect("a message");
        channel
            .basic_ack(got.delivery.delivery_tag, BasicAckOptions::default())
            .await
            .expect("ack");
    }
    // A synchronous round trip after the acks: the broker has handled them.
    declare(&channel).await;
    broker.terminate();

    let broker = start(&dir, workers).await;
    let conn = connect(&broker).await;
    let channel = conn.create_channel().await.expect("channel");
    // The durable exchange and binding came back: publishing through them routes.
    channel
        .basic_publish(
            "crash-x",
            "robot.more",
            BasicPublishOptions::default(),
            b"m100",
            persistent(),
        )
        .await
        .expect("publish after restart");
    let bodies = drain(&channel).await;
    let expected: Vec<String> = (30..=100).map(|i| format!("m{i}")).collect();
    assert_eq!(bodies, expected);
    broker.terminate();
    let _ = std::fs::remove_dir_all(&dir);
}

async fn durable_declarations_survive_kill_9_right_after_their_ok(workers: usize) {
    const COUNT: usize = 20;
    for round in 0..3 {
        let dir = temp_dir(&format!("declares-{round}"), workers);
        let broker = start(&dir, workers).await;
        let conn = connect(&broker).await;
        let channel = conn.create_channel().await.expect("channel");
        let durable_queue = QueueDeclareOptions {
            durable: true,
            ..Default::default()
        };
        let durable_exchange = ExchangeDeclareOptions {
            durable: true,
            ..Default::default()
        };
        for i in 0..COUNT {
            channel
                .exchange_declare(
                    &format!("x{i}"),
                    ExchangeKind::Direct,
                    durable_exchange,
                    FieldTable::default(),
                )
                .await
                .expect("exchange.declare");
            channel
                .queue_declare(&format!("q{i}"), durable_queue, FieldTable::default())
                .await
                .expect("queue.declare");
            channel
                .queue_bind(
                    &format!("q{i}"),
                    &format!("x{i}"),
                    "k",
                    QueueBindOptions::default(),
                    FieldTable::default(),
                )
                .await
                .expect("queue.bind");
        }
        // Right after the last -ok.
        broker.kill9();
        drop(conn);

        let broker = start(&dir, workers).await;
        let conn = connect(&broker).await;
        let mut missing = Vec::new();
        for i in 0..COUNT {
            let channel = conn.create_channel().await.expect("channel");
            let passive = QueueDeclareOptions {
                passive: true,
                ..Default::default()
            };
            if channel
                .queue_declare(&format!("q{i}"), passive, FieldTable::default())
                .await
                .is_err()
            {
                missing.push(format!("q{i}"));
                continue;
            }
            let passive = ExchangeDeclareOptions {
                passive: true,
                ..Default::default()
            };
            if channel
                .exchange_declare(
                    &format!("x{i}"),
                    ExchangeKind::Direct,
                    passive,
                    FieldTable::default(),
                )
                .await
                .is_err()
            {
                missing.push(format!("x{i}"));
                continue;
            }
            channel
                .confirm_select(ConfirmSelectOptions::default())
                .await
                .expect("confirms");
            channel
                .basic_publish(
                    &format!("x{i}"),
                    "k",
                    BasicPublishOptions::default(),
                    b"routed",
                    BasicProperties::default(),
                )
                .await
                .expect("publish")
                .await
                .expect("confirm");
            let got = channel
                .basic_get(&format!("q{i}"), BasicGetOptions { no_ack: true })
                .await
                .expect("get");
            if got.is_none() {
                missing.push(format!("x{i}->q{i}"));
            }
        }
        assert!(
            missing.is_empty(),
            "round {round}: lost after their -ok: {missing:?}"
        );
        broker.kill9();
        let _ = std::fs::remove_dir_all(&dir);
    }
}

const STREAM: &str = "crash-stream";

/// Declares the durable stream `STREAM`.
async fn declare_stream(channel: &Channel) {
    let mut args = FieldTable::default();
    args.insert(
        "x-queue-type".into(),
        AMQPValue::LongString("stream".into()),
    );
    let durable = QueueDeclareOptions {
        durable: true,
        ..Default::default()
    };
    channel
        .queue_declare(STREAM, durable, args)
        .await
        .expect("declare stream");
}

/// A consumer of `STREAM` from `offset` (an `x-stream-offset` value) with a
/// prefetch of 200, on a channel of its own.
async fn stream_reader(conn: &Connection, offset: AMQPValue) -> lapin::Consumer {
    let channel = conn.create_channel().await.expect("channel");
    channel
        .basic_qos(200, BasicQosOptions::default())
        .await
        .expect("basic.qos");
    let mut args = FieldTable::default();
    args.insert("x-stream-offset".into(), offset);
    channel
        .basic_consume(STREAM, "", BasicConsumeOptions::default(), args)
        .await
        .expect("consume the stream")
}

/// The next delivery as (its `x-stream-offset`, its body), acked; `None`
/// when nothing comes within `quiet` or the connection is gone.
async fn next_record(reader: &mut lapin::Consumer, quiet: Duration) -> Option<(i64, String)> {
    let delivery = tokio::time::timeout(quiet, reader.next())
        .await
        .ok()??
        .ok()?;
    let offset = delivery
        .properties
        .headers()
        .as_ref()
        .and_then(|h| {
            h.inner()
                .iter()
                .find(|(k, _)| k.as_str() == "x-stream-offset")
                .map(|(_, v)| v.clone())
        })
        .and_then(|v| match v {
            AMQPValue::LongLongInt(o) => Some(o),
            _ => None,
        })
        .expect("every delivery from a stream carries an x-stream-offset long");
    // An ack that fails means the connection is gone (the kill): the end.
    delivery.ack(BasicAckOptions::default()).await.ok()?;
    Some((offset, String::from_utf8(delivery.data).expect("utf-8")))
}

/// `s{seq}` of a stream record's body.
fn stream_seq(body: &str) -> u64 {
    body.strip_prefix('s')
        .and_then(|s| s.parse().ok())
        .expect("s{seq}")
}

async fn stream_keeps_confirmed_publishes_and_offsets_across_kill_9(workers: usize) {
    for (round, kill_after) in [200u64, 1_500].into_iter().enumerate() {
        let dir = temp_dir(&format!("stream-{round}"), workers);
        let broker = start(&dir, workers).await;
        let conn = connect(&broker).await;
        declare_stream(&conn.create_channel().await.expect("channel")).await;
        // A reader from the first offset records where each record sits
        // while the publisher runs, until the kill ends its connection.
        let reader_conn = connect(&broker).await;
        let mut reader = stream_reader(&reader_conn, AMQPValue::LongString("first".into())).await;
        let seen_before = tokio::spawn(async move {
            let mut seen = Vec::new();
            while let Some(record) = next_record(&mut reader, Duration::from_secs(60)).await {
                seen.push(record);
            }
            seen
        });
        let confirmed = Arc::new(Mutex::new(Vec::new()));
        let total = Arc::new(AtomicU64::new(0));
        let channel = conn.create_channel().await.expect("channel");
        let publisher = tokio::spawn(publish_stream_until_killed(
            channel,
            Arc::clone(&confirmed),
            Arc::clone(&total),
        ));
        wait_until("confirmed stream publishes", &total, kill_after).await;
        broker.kill9();
        let _ = publisher.await;
        let seen_before = seen_before.await.expect("reader task");
        drop((conn, reader_conn));
        let confirmed = confirmed.lock().expect("lock").clone();
        let last_confirmed = *confirmed.last().expect("something was confirmed");

        let broker = start(&dir, workers).await;
        let conn = connect(&broker).await;
        let mut reader = stream_reader(&conn, AMQPValue::LongString("first".into())).await;
        let mut after = Vec::new();
        while after
            .last()
            .is_none_or(|(_, body): &(i64, String)| stream_seq(body) < last_confirmed)
        {
            let record = next_record(&mut reader, Duration::from_secs(30)).await;
            after.push(record.unwrap_or_else(|| {
                panic!(
                    "round {round}: the stream ends after {} records, before confirmed s{last_confirmed}",
                    after.len()
                )
            }));
        }
        // Anything published but unconfirmed at the kill may follow.
        while let Some(record) = next_record(&mut reader, Duration::from_millis(500)).await {
            after.push(record);
        }
        let seqs: Vec<u64> = after.iter().map(|(_, b)| stream_seq(b)).collect();
        assert!(
            seqs.windows(2).all(|w| w[0] < w[1]),
            "round {round}: records out of order or duplicated after the restart"
        );
        assert!(
            after.windows(2).all(|w| w[0].0 < w[1].0),
            "round {round}: offsets do not increase after the restart"
        );
        let missing: Vec<_> = confirmed
            .iter()
            .filter(|s| seqs.binary_search(s).is_err())
            .collect();
        assert!(
            missing.is_empty(),
            "round {round}: lost {} of {} confirmed publishes, first s{}",
            missing.len(),
            confirmed.len(),
            missing.first().map_or(0, |s| **s)
        );
        // What the reader was delivered before the kill is where it was:
        // every confirmed record at the same offset, and no offset it saw
        // holding anything else (an unconfirmed record may be gone).
        for (offset, body) in &seen_before {
            let now = after.iter().find(|(o, _)| o == offset);
            if stream_seq(body) <= last_confirmed || now.is_some() {
                assert_eq!(
                    now.map(|(_, b)| b),
                    Some(body),
                    "round {round}: offset {offset} held {body} before the kill"
                );
            }
        }
        // A reader resumes after the last confirmed offset it was delivered.
        let (last_offset, _) = seen_before
            .iter()
            .rfind(|(_, body)| stream_seq(body) <= last_confirmed)
            .cloned()
            .unwrap_or_else(|| panic!("round {round}: the reader saw nothing before the kill"));
        let next = after
            .iter()
            .position(|(offset, _)| *offset == last_offset)
            .map(|i| after.get(i + 1).cloned());
        let mut resumed = stream_reader(&conn, AMQPValue::LongLongInt(last_offset + 1)).await;
        let first = next_record(&mut resumed, Duration::from_secs(10)).await;
        assert_eq!(
            Some(first),
            next,
            "round {round}: a reader resuming at offset {} gets the record after {last_offset}",
            last_offset + 1
        );
        broker.kill9();
        let _ = std::fs::remove_dir_all(&dir);
    }
}

/// Publishes `s{seq}` to `STREAM` with confirms (64 in flight), recording
/// confirmed seqs in order, until the connection dies.
async fn publish_stream_until_killed(
    channel: Channel,
    confirmed: Arc<Mutex<Vec<u64>>>,
    total: Arc<AtomicU64>,
) {
    if channel
        .confirm_select(ConfirmSelectOptions::default())
        .await
        .is_err()
    {
        return;
    }
    let mut window = VecDeque::new();
    for seq in 0u64.. {
        let body = format!("s{seq}");
        let Ok(confirm) = channel
            .basic_publish(
                "",
                STREAM,
                BasicPublishOptions::default(),
                body.as_bytes(),
                BasicProperties::default(),
            )
            .await
        else {
            return;
        };
        window.push_back((seq, confirm));
        if window.len() >= 64 {
            let Some((seq, confirm)) = window.pop_front() else {
                return;
            };
            match confirm.await {
                Ok(c) if c.is_ack() => {
                    confirmed.lock().expect("lock").push(seq);
                    total.fetch_add(1, Ordering::Relaxed);
                }
                _ => return,
            }
        }
    }
}
