//! A damaged store is reported, never silently forgotten: after a clean
//! shutdown of the `leveret` binary its database (sled) or its message log
//! is damaged as an operator or a failing disk would (files deleted,
//! truncated to 0, 4 KB or half, one byte flipped mid-file or near the
//! end, an older copy put back).
//! Each time, the next start either refuses with an error naming the data
//! directory and what is wrong, or starts with every confirmed message
//! and every declared queue; the definite losses must refuse. With
//! `--recover` it starts anyway, keeps a copy of the damaged files and
//! what is readable. A kill -9 is no damage: no false alarm after it.

use lapin::options::{BasicPublishOptions, ConfirmSelectOptions, QueueDeclareOptions};
use lapin::types::FieldTable;
use lapin::{BasicProperties, Connection, ConnectionProperties};
use std::io::{BufRead, BufReader};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::Duration;

mod common;

use common::damage::copy_dir;
use common::BrokerProcess;

const QUEUES: usize = 20;
const MESSAGES: u32 = 200;

fn temp_dir(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("leveret-damage-{}-{name}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    dir
}

const DURABLE: QueueDeclareOptions = QueueDeclareOptions {
    passive: false,
    durable: true,
    exclusive: false,
    auto_delete: false,
    nowait: false,
};

async fn connect(broker: &BrokerProcess) -> Connection {
    tokio::time::timeout(
        Duration::from_secs(10),
        Connection::connect(&broker.url(), ConnectionProperties::default()),
    )
    .await
    .expect("connect in time")
    .expect("connect")
}

/// Declares the queues and publishes `MESSAGES` confirmed persistent
/// messages to the first, named after `prefix`.
async fn fill(broker: &BrokerProcess, prefix: &str) {
    let conn = connect(broker).await;
    let channel = conn.create_channel().await.expect("channel");
    for q in 0..QUEUES {
        channel
            .queue_declare(&format!("{prefix}-{q}"), DURABLE, FieldTable::default())
            .await
            .expect("declare");
    }
    channel
        .confirm_select(ConfirmSelectOptions::default())
        .await
        .expect("confirms");
    for i in 0..MESSAGES {
        let confirm = channel
            .basic_publish(
                "",
                &format!("{prefix}-0"),
                BasicPublishOptions::default(),
                format!("message {i} with some padding to take some room").as_bytes(),
                BasicProperties::default().with_delivery_mode(2),
            )
            .await
            .expect("publish")
            .await
            .expect("confirm");
        assert!(confirm.is_ack());
    }
    conn.close(200, "done").await.expect("close");
}

/// Whether every queue named after `prefix` is there, the first with all
/// its messages.
async fn intact(broker: &BrokerProcess, prefix: &str) -> bool {
    let conn = connect(broker).await;
    for q in 0..QUEUES {
        let channel = conn.create_channel().await.expect("channel");
        let passive = QueueDeclareOptions {
            passive: true,
            ..DURABLE
        };
        match channel
            .queue_declare(&format!("{prefix}-{q}"), passive, FieldTable::default())
            .await
        {
            Ok(queue) if q > 0 || queue.message_count() == MESSAGES => {}
            _ => return false,
        }
    }
    true
}

/// `leveret` on `dir`, every listener on a free port, logging at `log`
/// to a pipe.
fn spawn_on(dir: &Path, log: &str) -> Child {
    Command::new(env!("CARGO_BIN_EXE_leveret"))
        .args(["--listen", "127.0.0.1:0", "--metrics-listen", "127.0.0.1:0"])
        .args(["--mqtt-listen", "none"])
        .args(["--http-listen", "127.0.0.1:0", "--log", log])
        .arg("--data-dir")
        .arg(dir)
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .expect("start leveret")
}

/// Runs the binary on `dir` and expects it to refuse: a failed exit with
/// a log naming the directory and the damage.
fn assert_refused(dir: &Path, case: &str) {
    let mut child = spawn_on(dir, "warn");
    let deadline = std::time::Instant::now() + Duration::from_secs(10);
    while child.try_wait().expect("wait").is_none() {
        if std::time::Instant::now() > deadline {
            let _ = child.kill();
            let _ = child.wait();
            panic!("{case}: started on a damaged store");
        }
        std::thread::sleep(Duration::from_millis(10));
    }
    let output = child.wait_with_output().expect("leveret exits");
    let log = String::from_utf8_lossy(&output.stderr);
    assert!(
        !output.status.success(),
        "{case}: exited 0 on a damaged store"
    );
    assert!(
        log.contains("is damaged") && log.contains(&dir.display().to_string()),
        "{case}: the error names the directory and the damage: {log}"
    );
    assert!(
        log.contains("--recover"),
        "{case}: says how to recover: {log}"
    );
}

fn database_file(dir: &Path) -> PathBuf {
    dir.join("store").join("db")
}

/// How much of a segment file is data: up to its last non-zero byte (the
/// log keeps zeros ahead of its data).
fn data_len(segment: &Path) -> u64 {
    let bytes = std::fs::read(segment).expect("read the segment");
    bytes
        .iter()
        .rposition(|&b| b != 0)
        .map_or(0, |at| at as u64 + 1)
}

/// The message log's newest segment file.
fn newest_segment(dir: &Path) -> PathBuf {
    let mut segments: Vec<PathBuf> = std::fs::read_dir(dir.join("messages"))
        .expect("read the message log")
        .filter_map(Result::ok)
        .map(|e| e.path())
        .filter(|p| p.extension().is_some_and(|e| e == "seg"))
        .collect();
    segments.sort();
    segments.pop().expect("a segment")
}

fn truncate(file: &Path, to: impl Fn(u64) -> u64) {
    let f = std::fs::OpenOptions::new()
        .write(true)
        .open(file)
        .expect("open");
    let len = f.metadata().expect("metadata").len();
    f.set_len(to(len)).expect("truncate");
}

fn flip(file: &Path, at: impl Fn(u64) -> u64) {
    let mut bytes = std::fs::read(file).expect("read");
    let at = at(bytes.len() as u64) as usize;
    bytes[at] ^= 0x5a;
    std::fs::write(file, bytes).expect("write");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn damage_refuses_the_start_or_loses_nothing_and_recover_salvages() {
    // A store with an older clean generation, then a newer one.
    let origin = temp_dir("origin");
    let broker = BrokerProcess::start(&origin).await;
    fill(&broker, "old").await;
    broker.terminate();
    let older = temp_dir("older");
    copy_dir(&origin, &older);
    let broker = BrokerProcess::start(&origin).await;
    fill(&broker, "new").await;
    broker.terminate();
    let broker = BrokerProcess::start(&origin).await;
    assert!(
        intact(&broker, "new").await,
        "a clean restart keeps everything"
    );
    broker.terminate();

    type Damage = Box<dyn Fn(&Path)>;
    let must_refuse: Vec<(&str, Damage)> = vec![
        (
            "database deleted",
            Box::new(|d| std::fs::remove_dir_all(d.join("store")).expect("rm")),
        ),
        (
            "truncated to 0",
            Box::new(|d| truncate(&database_file(d), |_| 0)),
        ),
        (
            "truncated to 4 KB",
            Box::new(|d| truncate(&database_file(d), |_| 4096)),
        ),
        (
            "an older copy put back",
            Box::new({
                let older = older.clone();
                move |d| {
                    std::fs::remove_dir_all(d.join("store")).expect("rm");
                    copy_dir(&older.join("store"), &d.join("store"));
                }
            }),
        ),
        (
            "message log deleted",
            Box::new(|d| std::fs::remove_dir_all(d.join("messages")).expect("rm")),
        ),
        (
            "message log segment truncated to 0",
            Box::new(|d| truncate(&newest_segment(d), |_| 0)),
        ),
        (
            "message log segment truncated to half its data",
            Box::new(|d| {
                let segment = newest_segment(d);
                let data = data_len(&segment);
                truncate(&segment, |_| data / 2)
            }),
        ),
        (
            "a byte flipped mid message log data",
            Box::new(|d| {
                let segment = newest_segment(d);
                let data = data_len(&segment);
                flip(&segment, |_| data / 2)
            }),
        ),
        (
            "an older message log put back",
            Box::new({
                let older = older.clone();
                move |d| {
                    std::fs::remove_dir_all(d.join("messages")).expect("rm");
                    copy_dir(&older.join("messages"), &d.join("messages"));
                }
            }),
        ),
    ];
    let refuse_or_intact: Vec<(&str, Damage)> = vec![
        (
            "truncated to half",
            Box::new(|d| truncate(&database_file(d), |len| len / 2)),
        ),
        (
            "a byte flipped mid-file",
            Box::new(|d| flip(&database_file(d), |len| len / 2)),
        ),
        (
            "a byte flipped near the end",
            Box::new(|d| flip(&database_file(d), |len| len - 100)),
        ),
    ];
    for (index, (case, damage)) in must_refuse.iter().enumerate() {
        let dir = temp_dir(&format!("refuse-{index}"));
        copy_dir(&origin, &dir);
        damage(&dir);
        assert_refused(&dir, case);
        // --recover starts, keeps a copy of what there was.
        let broker = BrokerProcess::start_with(&dir, ["--recover"]).await;
        let _ = connect(&broker).await;
        broker.terminate();
        if dir.join("store").exists() && *case != "database deleted" {
            let copies = std::fs::read_dir(&dir)
                .expect("read dir")
                .filter_map(Result::ok)
                .filter(|e| {
                    e.file_name()
                        .to_string_lossy()
                        .starts_with("store.damaged-")
                })
                .count();
            assert_eq!(copies, 1, "{case}: a copy of the damaged files is kept");
        }
        // After the recovered run's clean shutdown, it starts normally.
        let broker = BrokerProcess::start(&dir).await;
        broker.terminate();
        let _ = std::fs::remove_dir_all(&dir);
    }
    for (index, (case, damage)) in refuse_or_intact.iter().enumerate() {
        let dir = temp_dir(&format!("either-{index}"));
        copy_dir(&origin, &dir);
        damage(&dir);
        let started = starts(&dir);
        if started {
            let broker = BrokerProcess::start(&dir).await;
            assert!(
                intact(&broker, "new").await,
                "{case}: started, so nothing may be missing"
            );
            broker.terminate();
        } else {
            assert_refused(&dir, case);
        }
        let _ = std::fs::remove_dir_all(&dir);
    }
    let _ = std::fs::remove_dir_all(&origin);
    let _ = std::fs::remove_dir_all(&older);
}

/// Whether `leveret` starts on `dir` (then stops it) or refuses: its log
/// says it accepts AMQP connections, or it exits first.
fn starts(dir: &Path) -> bool {
    let mut child = spawn_on(dir, "info");
    let stderr = child.stderr.take().expect("stderr");
    let (outcome, seen) = std::sync::mpsc::channel();
    std::thread::spawn(move || {
        let accepting = BufReader::new(stderr)
            .lines()
            .map_while(Result::ok)
            .any(|line| line.contains("accepting AMQP"));
        let _ = outcome.send(accepting);
    });
    let started = seen.recv_timeout(Duration::from_secs(20));
    let _ = child.kill();
    let _ = child.wait();
    started.expect("leveret neither started nor refused within 20 s")
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_kill_9_is_no_damage() {
    let dir = temp_dir("kill9");
    let broker = BrokerProcess::start(&dir).await;
    fill(&broker, "k").await;
    broker.terminate();
    let broker = BrokerProcess::start(&dir).await;
    broker.kill9();
    let broker = BrokerProcess::start(&dir).await;
    assert!(intact(&broker, "k").await);
    broker.terminate();
    let _ = std::fs::remove_dir_all(&dir);
}
