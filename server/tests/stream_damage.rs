//! Damage to a stream's segments at start (issue 33), as the damage
//! matrix does for the message log: a stream takes confirmed messages over
//! several segments, the broker stops cleanly, then one segment is
//! damaged: the oldest or a middle one cut to half, a middle one deleted,
//! the newest with a byte flipped. The next start must refuse,
//! naming the data directory and the damaged file; `--recover` starts,
//! copies the damaged file aside, keeps every readable record at its
//! offset and serves nothing else; a start after that needs no
//! `--recover`. A torn append at the end of the newest segment (what a
//! crash leaves) starts with every confirmed message. A byte flipped in a
//! closed (sealed) segment is not read at start: the start goes on, the
//! damaged record and what follows it in its segment are never served,
//! and readers from later offsets read on.

use futures_lite::StreamExt;
use lapin::options::{
    BasicConsumeOptions, BasicPublishOptions, BasicQosOptions, ConfirmSelectOptions,
    QueueDeclareOptions,
};
use lapin::types::{AMQPValue, FieldTable};
use lapin::{BasicProperties, Connection, ConnectionProperties};
use std::collections::BTreeSet;
use std::path::{Path, PathBuf};
use std::time::Duration;

mod common;

use common::damage::{copy_dir, refusal};
use common::ops::OpsBroker;

const STREAM: &str = "recorder";
const MESSAGES: i64 = 80;

fn temp_dir(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!(
        "leveret-stream-damage-{}-{name}",
        std::process::id()
    ));
    let _ = std::fs::remove_dir_all(&dir);
    dir
}

async fn connect(broker: &OpsBroker) -> Connection {
    tokio::time::timeout(
        Duration::from_secs(10),
        Connection::connect(&broker.amqp_url(), ConnectionProperties::default()),
    )
    .await
    .expect("connect in time")
    .expect("connect")
}

fn stream_args() -> FieldTable {
    let mut args = FieldTable::default();
    args.insert(
        "x-queue-type".into(),
        AMQPValue::LongString("stream".into()),
    );
    args.insert(
        "x-stream-max-segment-size-bytes".into(),
        AMQPValue::LongInt(2_000),
    );
    args
}

/// Declares the stream and publishes `MESSAGES` confirmed messages.
async fn fill(broker: &OpsBroker) {
    let conn = connect(broker).await;
    let channel = conn.create_channel().await.expect("channel");
    let durable = QueueDeclareOptions {
        durable: true,
        ..Default::default()
    };
    channel
        .queue_declare(STREAM, durable, stream_args())
        .await
        .expect("declare");
    channel
        .confirm_select(ConfirmSelectOptions::default())
        .await
        .expect("confirms");
    for n in 0..MESSAGES {
        let body = format!("{n:06}{}", ".".repeat(100));
        let confirm = channel
            .basic_publish(
                "",
                STREAM,
                BasicPublishOptions::default(),
                body.as_bytes(),
                BasicProperties::default(),
            )
            .await
            .expect("publish");
        assert!(confirm.await.expect("confirm").is_ack(), "confirmed");
    }
    conn.close(200, "done").await.expect("close");
}

/// The offsets a reader from `first` gets, each checked against its body.
async fn read_all(broker: &OpsBroker) -> Vec<i64> {
    read_from(broker, AMQPValue::LongString("first".into())).await
}

/// The offsets a reader from `offset` gets, each checked against its body.
async fn read_from(broker: &OpsBroker, offset: AMQPValue) -> Vec<i64> {
    let conn = connect(broker).await;
    let channel = conn.create_channel().await.expect("channel");
    channel
        .basic_qos(200, BasicQosOptions::default())
        .await
        .expect("qos");
    let mut args = FieldTable::default();
    args.insert("x-stream-offset".into(), offset);
    let mut consumer = channel
        .basic_consume(STREAM, "all", BasicConsumeOptions::default(), args)
        .await
        .expect("consume");
    let mut offsets = Vec::new();
    while let Ok(Some(Ok(d))) = tokio::time::timeout(Duration::from_secs(2), consumer.next()).await
    {
        let offset = match d
            .properties
            .headers()
            .as_ref()
            .and_then(|h| h.inner().get("x-stream-offset").cloned())
        {
            Some(AMQPValue::LongLongInt(n)) => n,
            other => panic!("no offset header: {other:?}"),
        };
        assert_eq!(&d.data[..6], format!("{offset:06}").as_bytes());
        offsets.push(offset);
    }
    conn.close(200, "done").await.expect("close");
    offsets
}

/// The stream's segment files, oldest first.
fn segments(dir: &Path) -> Vec<PathBuf> {
    let root = dir.join("streams");
    let mut found = Vec::new();
    for stream in std::fs::read_dir(&root).expect("streams dir") {
        for file in std::fs::read_dir(stream.unwrap().path()).unwrap() {
            let path = file.unwrap().path();
            if path.extension().is_some_and(|e| e == "seg") {
                found.push(path);
            }
        }
    }
    found.sort();
    found
}

#[derive(Debug, Clone, Copy)]
enum Harm {
    FlipByte,
    CutToHalf,
    Delete,
}

fn harm(path: &Path, how: Harm) {
    match how {
        Harm::FlipByte => {
            let mut bytes = std::fs::read(path).unwrap();
            // Inside the first record's payload.
            bytes[16 + 25 + 20] ^= 0xff;
            std::fs::write(path, bytes).unwrap();
        }
        Harm::CutToHalf => {
            let len = std::fs::metadata(path).unwrap().len();
            std::fs::OpenOptions::new()
                .write(true)
                .open(path)
                .unwrap()
                .set_len(len / 2)
                .unwrap();
        }
        Harm::Delete => std::fs::remove_file(path).unwrap(),
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_damaged_stream_segment_refuses_the_start_and_recover_keeps_every_readable_record() {
    let origin = temp_dir("origin");
    {
        let broker = OpsBroker::on_data_dir(&origin, &[] as &[&str]);
        fill(&broker).await;
        broker.terminate();
    }
    let count = segments(&origin).len();
    assert!(count >= 4, "several segments: {count}");
    let all: Vec<i64> = (0..MESSAGES).collect();
    let cells = [
        ("oldest-half", 0, Harm::CutToHalf),
        ("middle-half", count / 2, Harm::CutToHalf),
        ("middle-delete", count / 2, Harm::Delete),
        ("newest-flip", count - 1, Harm::FlipByte),
        // Synced, so confirmed: the newest segment's records are no
        // crash's torn tail.
        ("newest-half", count - 1, Harm::CutToHalf),
        ("newest-delete", count - 1, Harm::Delete),
    ];
    for (name, index, how) in cells {
        let dir = temp_dir(name);
        copy_dir(&origin, &dir);
        let target = segments(&dir)[index].clone();
        let file_name = target.file_name().unwrap().to_string_lossy().into_owned();
        harm(&target, how);

        let log = refusal(&dir).unwrap_or_else(|| panic!("{name}: started on damage"));
        let named = log
            .lines()
            .find(|l| l.contains("is damaged") && l.contains("--recover"))
            .unwrap_or_else(|| panic!("{name}: no refusal naming the damage: {log}"));
        assert!(
            named.contains(&dir.display().to_string()),
            "{name}: {named}"
        );
        assert!(
            named.contains(&file_name) || matches!(how, Harm::Delete),
            "{name}: the file is named: {named}"
        );
        assert!(
            named.contains(STREAM),
            "{name}: the stream is named: {named}"
        );

        let broker = OpsBroker::on_data_dir(&dir, &["--recover"]);
        let read = read_all(&broker).await;
        let recovered_log = broker.log().join("\n");
        broker.terminate();
        assert!(
            read.windows(2).all(|w| w[0] < w[1]),
            "{name}: in order: {read:?}"
        );
        assert!(read.len() < all.len(), "{name}: something was lost");
        assert!(
            read.iter().all(|o| all.contains(o)),
            "{name}: only what was written"
        );
        // Every record outside the harmed segment's span is kept.
        let lost: BTreeSet<i64> = all.iter().filter(|o| !read.contains(o)).copied().collect();
        let (low, high) = (*lost.first().unwrap(), *lost.last().unwrap());
        assert!(
            (low..=high).all(|o| lost.contains(&o)),
            "{name}: one lost stretch: {lost:?}"
        );
        assert!(
            high - low < 30,
            "{name}: at most a segment's records lost: {lost:?}"
        );
        if !matches!(how, Harm::Delete) {
            assert!(
                recovered_log.contains("copied aside"),
                "{name}: {recovered_log}"
            );
            assert_eq!(
                std::fs::read_dir(target.parent().unwrap())
                    .unwrap()
                    .filter(|e| e
                        .as_ref()
                        .unwrap()
                        .file_name()
                        .to_string_lossy()
                        .starts_with(&format!("{file_name}.damaged-")))
                    .count(),
                1,
                "{name}: the damaged file is kept aside"
            );
        }
        // Recovered once: the next start needs no --recover.
        assert!(refusal(&dir).is_none(), "{name}: refused after recovery");
        let _ = std::fs::remove_dir_all(&dir);
    }

    // A flipped byte in a sealed segment: found on read, never served.
    let dir = temp_dir("sealed-flip");
    copy_dir(&origin, &dir);
    let sealed = segments(&dir);
    harm(&sealed[0], Harm::FlipByte);
    let second: i64 = sealed[1]
        .file_stem()
        .unwrap()
        .to_string_lossy()
        .parse()
        .unwrap();
    let broker = OpsBroker::on_data_dir(&dir, &[] as &[&str]);
    assert_eq!(read_all(&broker).await, Vec::<i64>::new());
    assert_eq!(
        read_from(&broker, AMQPValue::LongLongInt(second)).await,
        (second..MESSAGES).collect::<Vec<_>>()
    );
    assert!(
        broker
            .log()
            .iter()
            .any(|l| l.contains("stream record damaged: not served")),
        "the damage is logged"
    );
    broker.terminate();
    let _ = std::fs::remove_dir_all(&dir);

    // A torn append at the end of the newest segment: a crash's tail.
    let dir = temp_dir("torn-tail");
    copy_dir(&origin, &dir);
    let newest = segments(&dir).last().unwrap().clone();
    let mut bytes = std::fs::read(&newest).unwrap();
    let torn = bytes[16..16 + 30].to_vec();
    bytes.extend_from_slice(&torn);
    std::fs::write(&newest, bytes).unwrap();
    let broker = OpsBroker::on_data_dir(&dir, &[] as &[&str]);
    assert_eq!(read_all(&broker).await, all);
    broker.terminate();
    let _ = std::fs::remove_dir_all(&dir);
    let _ = std::fs::remove_dir_all(&origin);
}
