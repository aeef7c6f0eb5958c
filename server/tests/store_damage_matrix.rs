//! The damage matrix (issue 29): no start ever loses a confirmed message
//! silently. A durable queue takes confirmed persistent messages over
//! several message log segments; the broker stops cleanly or is killed
//! with SIGKILL (every confirm already received); then one file is
//! damaged: the oldest, a middle or the newest segment, the database
//! (sled's file) or the manifest, each deleted, truncated to half, with a
//! byte flipped, or with 64 KB zeroed. The next start must either refuse,
//! naming the data directory and the damaged file, or start with every
//! confirmed message, which a real client (lapin) consumes and counts.
//! `--recover` then keeps every readable batch, not just what precedes
//! the damage, and reports exactly how many messages it lost.

use lapin::options::{
    BasicConsumeOptions, BasicPublishOptions, BasicQosOptions, ConfirmSelectOptions,
    QueueDeclareOptions,
};
use lapin::types::FieldTable;
use lapin::{BasicProperties, Connection, ConnectionProperties};
use std::collections::{BTreeSet, VecDeque};
use std::path::{Path, PathBuf};
use std::time::Duration;

mod common;

use common::damage::{copy_dir, refusal};
use common::ops::OpsBroker;

const QUEUE: &str = "matrix";
/// Confirmed messages, and their bodies' size: enough for four 16 MB
/// segments, so there is an oldest, a middle and a newest.
const MESSAGES: usize = 3000;
const BODY: usize = 20 * 1024;

fn temp_dir(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("leveret-matrix-{}-{name}", std::process::id()));
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

fn body(n: usize) -> Vec<u8> {
    let mut body = format!("{n:06}").into_bytes();
    body.resize(BODY, b'.');
    body
}

/// Declares the queue and publishes `MESSAGES` persistent messages with
/// confirms (128 in flight), each confirmed.
async fn fill(broker: &OpsBroker) {
    let conn = connect(broker).await;
    let channel = conn.create_channel().await.expect("channel");
    let durable = QueueDeclareOptions {
        durable: true,
        ..Default::default()
    };
    channel
        .queue_declare(QUEUE, durable, FieldTable::default())
        .await
        .expect("declare");
    channel
        .confirm_select(ConfirmSelectOptions::default())
        .await
        .expect("confirms");
    let mut window = VecDeque::new();
    for n in 0..MESSAGES {
        let confirm = channel
            .basic_publish(
                "",
                QUEUE,
                BasicPublishOptions::default(),
                &body(n),
                BasicProperties::default().with_delivery_mode(2),
            )
            .await
            .expect("publish");
        window.push_back(confirm);
        if window.len() >= 128 || n + 1 == MESSAGES {
            while let Some(confirm) = window.pop_front() {
                assert!(confirm.await.expect("confirm").is_ack(), "confirmed");
            }
        }
    }
    conn.close(200, "done").await.expect("close");
}

/// Consumes the queue and returns the numbers of the messages it held.
async fn consume_all(broker: &OpsBroker) -> BTreeSet<usize> {
    use futures_lite::StreamExt;
    let conn = connect(broker).await;
    let channel = conn.create_channel().await.expect("channel");
    // A queue the start lost holds none of them.
    let passive = QueueDeclareOptions {
        passive: true,
        durable: true,
        ..Default::default()
    };
    let Ok(queue) = channel
        .queue_declare(QUEUE, passive, FieldTable::default())
        .await
    else {
        return BTreeSet::new();
    };
    let ready = queue.message_count() as usize;
    channel
        .basic_qos(500, BasicQosOptions::default())
        .await
        .expect("qos");
    let mut consumer = channel
        .basic_consume(
            QUEUE,
            "count",
            BasicConsumeOptions {
                no_ack: true,
                ..Default::default()
            },
            FieldTable::default(),
        )
        .await
        .expect("consume");
    // Every message the queue said it holds, each counted once; then a
    // moment more, for any it did not count.
    let mut seen = BTreeSet::new();
    loop {
        let patience = if seen.len() < ready { 30 } else { 1 };
        let next = tokio::time::timeout(Duration::from_secs(patience), consumer.next()).await;
        let Ok(Some(delivery)) = next else {
            break;
        };
        let delivery = delivery.expect("delivery");
        let n: usize = std::str::from_utf8(&delivery.data[..6])
            .expect("utf-8")
            .parse()
            .expect("number");
        assert_eq!(delivery.data, body(n), "message {n} intact");
        assert!(seen.insert(n), "message {n} delivered twice");
    }
    assert_eq!(seen.len(), ready, "the queue delivers what it counts");
    let _ = conn.close(200, "done").await;
    seen
}

/// The message log's segment files, oldest first.
fn segments(dir: &Path) -> Vec<PathBuf> {
    let mut segments: Vec<PathBuf> = std::fs::read_dir(dir.join("messages"))
        .expect("read the message log")
        .filter_map(Result::ok)
        .map(|e| e.path())
        .filter(|p| p.extension().is_some_and(|e| e == "seg"))
        .collect();
    segments.sort();
    segments
}

#[derive(Debug, Clone, Copy)]
enum Target {
    Oldest,
    Middle,
    Newest,
    Database,
    Manifest,
}

#[derive(Debug, Clone, Copy)]
enum Harm {
    Delete,
    Truncate,
    Flip,
    Zero,
}

impl Target {
    fn file(self, dir: &Path) -> PathBuf {
        let segments = segments(dir);
        match self {
            Target::Oldest => segments[0].clone(),
            Target::Middle => segments[segments.len() / 2].clone(),
            Target::Newest => segments[segments.len() - 1].clone(),
            Target::Database => dir.join("store").join("db"),
            Target::Manifest => dir.join("leveret-store.manifest"),
        }
    }

    /// What a refusal must name.
    fn name(self, file: &Path) -> String {
        match self {
            Target::Database => "database".into(),
            Target::Manifest => "manifest".into(),
            _ => file.file_name().expect("name").to_string_lossy().into(),
        }
    }
}

/// How much of a file is data: a segment's up to its last non-zero byte
/// (the log keeps zeros ahead of its data), any other file's all.
fn data_len(file: &Path) -> u64 {
    let bytes = std::fs::read(file).expect("read");
    if file.extension().is_some_and(|e| e == "seg") {
        bytes
            .iter()
            .rposition(|&b| b != 0)
            .map_or(0, |at| at as u64 + 1)
    } else {
        bytes.len() as u64
    }
}

fn harm(file: &Path, harm: Harm) {
    use std::os::unix::fs::FileExt;
    let data = data_len(file);
    let open = || {
        std::fs::OpenOptions::new()
            .write(true)
            .open(file)
            .expect("open")
    };
    match harm {
        Harm::Delete => std::fs::remove_file(file).expect("delete"),
        Harm::Truncate => open().set_len(data / 2).expect("truncate"),
        Harm::Flip => {
            let mut bytes = std::fs::read(file).expect("read");
            bytes[(data / 10) as usize] ^= 0x5a;
            std::fs::write(file, bytes).expect("write");
        }
        Harm::Zero => {
            let at = if data > 640 * 1024 { data / 10 } else { 0 };
            open().write_all_at(&vec![0; 64 * 1024], at).expect("zero");
        }
    }
}

/// A data directory holding the confirmed messages, after a clean stop or
/// a kill -9.
async fn origin(name: &str, kill: bool) -> PathBuf {
    let dir = temp_dir(name);
    let broker = OpsBroker::on_data_dir(&dir, &[] as &[&str]);
    fill(&broker).await;
    if kill {
        broker.kill9();
    } else {
        broker.terminate();
    }
    assert!(
        segments(&dir).len() >= 3,
        "an oldest, a middle and a newest segment: {:?}",
        segments(&dir)
    );
    dir
}

/// Starts on `dir` (as it is): a refusal naming the directory, the damage
/// and `name` (`Ok` with its reason), or a start with every confirmed
/// message (`Ok`); anything else is `Err` saying what went wrong.
async fn refused_or_intact(dir: &Path, name: &str) -> Result<String, String> {
    match refusal(dir) {
        Some(log) => {
            let reason = log
                .lines()
                .find(|line| line.contains("is damaged"))
                .and_then(|line| line.split("is damaged: ").nth(1))
                .and_then(|rest| rest.split("; the broker does not start").next())
                .map(str::to_owned);
            match reason {
                Some(reason)
                    if log.contains(&dir.display().to_string()) && reason.contains(name) =>
                {
                    Ok(format!("refused: {reason}"))
                }
                _ => Err(format!(
                    "refused without naming the damage and {name}: {log}"
                )),
            }
        }
        None => {
            let broker = OpsBroker::on_data_dir(dir, &[] as &[&str]);
            let seen = consume_all(&broker).await;
            broker.terminate();
            if seen.len() == MESSAGES {
                Ok("started with every confirmed message".to_owned())
            } else {
                Err(format!(
                    "started with {} of the {MESSAGES} confirmed messages",
                    seen.len()
                ))
            }
        }
    }
}

/// Every cell of the matrix after a clean stop or a kill -9 (each cell is
/// tried, then every failure is reported at once).
async fn matrix(kill: bool) {
    let mode = if kill { "kill9" } else { "clean" };
    let origin = origin(&format!("{mode}-origin"), kill).await;
    let control = temp_dir(&format!("{mode}-control"));
    copy_dir(&origin, &control);
    assert_eq!(
        refused_or_intact(&control, "").await,
        Ok("started with every confirmed message".to_owned()),
        "{mode}: an undamaged store starts"
    );
    let _ = std::fs::remove_dir_all(&control);
    let targets = [
        Target::Oldest,
        Target::Middle,
        Target::Newest,
        Target::Database,
        Target::Manifest,
    ];
    let harms = [Harm::Delete, Harm::Truncate, Harm::Flip, Harm::Zero];
    let mut outcomes = Vec::new();
    let mut failures = Vec::new();
    for target in targets {
        for how in harms {
            let case = format!("{mode}: {how:?} the {target:?}");
            let dir = temp_dir(&format!("{mode}-{target:?}-{how:?}"));
            copy_dir(&origin, &dir);
            let file = target.file(&dir);
            harm(&file, how);
            match refused_or_intact(&dir, &target.name(&file)).await {
                Ok(outcome) => outcomes.push(format!("{case}: {outcome}")),
                Err(failure) => failures.push(format!("{case}: {failure}")),
            }
            let _ = std::fs::remove_dir_all(&dir);
        }
    }
    eprintln!("{}", outcomes.join("\n"));
    let _ = std::fs::remove_dir_all(&origin);
    assert!(
        failures.is_empty(),
        "{} of {} cells lost confirmed messages or refused without a reason:\n{}",
        failures.len(),
        outcomes.len() + failures.len(),
        failures.join("\n")
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn after_a_clean_stop_damage_refuses_the_start_or_loses_nothing() {
    matrix(false).await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn after_a_kill_9_damage_refuses_the_start_or_loses_nothing() {
    matrix(true).await;
}

/// `--recover` after one flipped byte in the oldest segment keeps every
/// batch after the damaged one too, and its log says exactly how many
/// messages it lost.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn recover_keeps_the_batches_after_a_flipped_byte_and_counts_what_it_lost() {
    let dir = origin("recover", false).await;
    let oldest = Target::Oldest.file(&dir);
    harm(&oldest, Harm::Flip);
    assert!(refusal(&dir).is_some(), "a flipped byte refuses the start");
    let broker = OpsBroker::on_data_dir(&dir, &["--recover"]);
    let log = broker.log().join("\n");
    broker.terminate();
    // Recovered, it starts normally again, with what was kept.
    let broker = OpsBroker::on_data_dir(&dir, &[] as &[&str]);
    let kept = consume_all(&broker).await;
    broker.terminate();
    for line in log.lines().filter(|line| line.contains("salvage")) {
        eprintln!("{line}");
    }
    let lost: usize = log
        .lines()
        .find(|line| line.contains("salvaged the message log"))
        .and_then(|line| line.split("messages_lost=").nth(1))
        .and_then(|rest| rest.split_whitespace().next())
        .and_then(|n| n.parse().ok())
        .unwrap_or_else(|| panic!("a summary with messages_lost: {log}"));
    assert!(lost > 0, "the damaged batch held messages: {log}");
    assert!(
        lost < MESSAGES / 10,
        "one batch lost, not the rest of the segment: lost {lost}"
    );
    assert_eq!(kept.len() + lost, MESSAGES, "the report is exact");
    assert!(
        log.contains("salvage: lost an unreadable stretch")
            && log.contains("salvage: messages lost from a queue"),
        "names the segment's stretch and the queue's positions: {log}"
    );
    // The messages after the damaged batch are there: the newest, and
    // the lost ones are one run.
    assert!(kept.contains(&(MESSAGES - 1)));
    let missing: Vec<usize> = (0..MESSAGES).filter(|n| !kept.contains(n)).collect();
    assert_eq!(
        missing.last().expect("some lost") - missing[0] + 1,
        missing.len(),
        "one batch: one run of messages"
    );
    let _ = std::fs::remove_dir_all(&dir);
}
