//! `leveretctl port record` and `port replay` against a running
//! `leveret` (issue 33, item 3): a port's messages recorded to a stream,
//! replayed printed (everything, offsets, at a rate), republished into
//! another topic with the original sequence numbers and send times, and
//! into the recorded topic itself (the replay stops at its own output
//! instead of chasing it); the refusals. Asserts counts, values and
//! order, never wall-clock figures.

mod common;

use common::ops::OpsBroker;
use leveret_ports::{ExchangeKind, InPort, OutPort, PortProfile, PortStatus, Time, TimedLong};
use std::process::{Command, Output, Stdio};
use std::sync::Arc;
use std::time::{Duration, Instant, UNIX_EPOCH};

/// How long one `leveretctl` run may take before the test fails (a hang
/// limit: a replay that chased its own output would never end).
const CTL_LIMIT: Duration = Duration::from_secs(60);

/// `leveretctl -q port ARGS` against the AMQP listener of `broker`, off
/// the runtime's threads (the ports keep running); killed and failed
/// after [`CTL_LIMIT`]. Its output is read at the end: these runs print
/// far less than a pipe holds.
async fn port_ctl(broker: &Arc<OpsBroker>, args: &[&str]) -> Output {
    let broker = Arc::clone(broker);
    let args: Vec<String> = args.iter().map(|arg| (*arg).to_owned()).collect();
    tokio::task::spawn_blocking(move || {
        let mut child = Command::new(env!("CARGO_BIN_EXE_leveretctl"))
            .arg("--amqp-url")
            .arg(broker.amqp_url())
            .args(["-q", "port"])
            .args(&args)
            .stdout(Stdio::piped())
            .stderr(Stdio::piped())
            .spawn()
            .expect("run leveretctl");
        let started = Instant::now();
        while child.try_wait().expect("wait for leveretctl").is_none() {
            if started.elapsed() > CTL_LIMIT {
                let _ = child.kill();
                panic!("leveretctl port {args:?} still running after {CTL_LIMIT:?}");
            }
            std::thread::sleep(Duration::from_millis(20));
        }
        child.wait_with_output().expect("leveretctl output")
    })
    .await
    .expect("leveretctl")
}

/// `port_ctl`, which must succeed: its standard output's lines.
async fn port_lines(broker: &Arc<OpsBroker>, args: &[&str]) -> Vec<String> {
    let output = port_ctl(broker, args).await;
    assert!(output.status.success(), "port {args:?}: {output:?}");
    String::from_utf8_lossy(&output.stdout)
        .lines()
        .map(str::to_owned)
        .collect()
}

/// The value of `key=` in a replay line.
fn field<'a>(line: &'a str, key: &str) -> &'a str {
    line.split(' ')
        .find_map(|part| part.strip_prefix(key)?.strip_prefix('='))
        .unwrap_or_else(|| panic!("{key} in {line}"))
}

/// Each line's `key=` values, as numbers.
fn numbers(lines: &[String], key: &str) -> Vec<u128> {
    lines
        .iter()
        .map(|line| field(line, key).parse().expect("a number"))
        .collect()
}

/// Takes `count` values from `input`: their sequence numbers and send
/// times (ns).
async fn take(input: &InPort<TimedLong>, count: usize) -> Vec<(u64, u128)> {
    let mut taken = Vec::new();
    for _ in 0..count {
        let sample = tokio::time::timeout(Duration::from_secs(10), input.recv())
            .await
            .expect("a value within 10 s")
            .expect("port open");
        let sent = sample.sent_at.expect("sent_at").duration_since(UNIX_EPOCH);
        taken.push((
            sample.seq.expect("seq"),
            sent.expect("after 1970").as_nanos(),
        ));
    }
    taken
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn port_record_and_replay_a_ports_messages() {
    const VALUES: usize = 50;
    let broker = Arc::new(OpsBroker::start("ctl-recorder", &[]));
    let base = PortProfile::new(&broker.amqp_url())
        .expect("URI")
        .announce_interval(Some(Duration::from_millis(200)));
    let poses = base.clone().exchange("ticks", ExchangeKind::Fanout);
    let live = InPort::<TimedLong>::connect(poses.clone().name("ticks-in"))
        .await
        .expect("in-port");
    let output = OutPort::<TimedLong>::connect(poses.name("ticks-out"))
        .await
        .expect("out-port");

    let recording = port_lines(
        &broker,
        &[
            "record",
            "ticks-out",
            "--stream",
            "ticks.rec",
            "--max-age",
            "1h",
        ],
    )
    .await;
    assert!(recording.is_empty(), "{recording:?}");
    for data in 1..=VALUES as i32 {
        let value = TimedLong {
            tm: Time::now(),
            data,
        };
        assert_eq!(output.put(&value).await, PortStatus::Ok);
    }
    let original = take(&live, VALUES).await;

    // Everything, printed: offsets from 0, the original seq and send times.
    let everything = port_lines(&broker, &["replay", "ticks.rec", "--fast"]).await;
    assert_eq!(everything.len(), VALUES, "{everything:?}");
    assert_eq!(
        numbers(&everything, "offset"),
        (0..VALUES as u128).collect::<Vec<_>>()
    );
    let printed: Vec<(u64, u128)> = numbers(&everything, "seq")
        .into_iter()
        .zip(numbers(&everything, "sent_ns"))
        .map(|(seq, sent)| (seq as u64, sent))
        .collect();
    assert_eq!(printed, original);
    assert!(everything.iter().all(|l| field(l, "topic") == "ticks/"));

    // Offsets 10 to 19, paced at 10x.
    let window = port_lines(
        &broker,
        &[
            "replay",
            "ticks.rec",
            "--start",
            "10",
            "--end",
            "19",
            "--rate",
            "10",
        ],
    )
    .await;
    assert_eq!(
        numbers(&window, "seq"),
        (11..=20).collect::<Vec<_>>(),
        "{window:?}"
    );
    // Topic selection: nothing was published to another exchange.
    let other = port_lines(
        &broker,
        &["replay", "ticks.rec", "--fast", "--topic", "elsewhere"],
    )
    .await;
    assert!(other.is_empty(), "{other:?}");

    // Republished into another topic: a reader there gets the original
    // sequence numbers and send times.
    let copy = InPort::<TimedLong>::connect(
        base.clone()
            .exchange("ticks-copy", ExchangeKind::Fanout)
            .name("copy-in"),
    )
    .await
    .expect("copy in-port");
    let published = port_lines(
        &broker,
        &[
            "replay",
            "ticks.rec",
            "--fast",
            "--publish",
            "--into",
            "ticks-copy",
        ],
    )
    .await;
    assert!(published.is_empty(), "{published:?}");
    assert_eq!(take(&copy, VALUES).await, original);

    // Republished into the recorded topic: the replay ends where its own
    // output begins in the stream (it does not chase it), the live reader
    // recognises every value as a duplicate, and the stream holds both.
    port_lines(&broker, &["replay", "ticks.rec", "--fast", "--publish"]).await;
    let mut stats = live.watch_stats();
    tokio::time::timeout(
        Duration::from_secs(10),
        stats.wait_for(|s| s.duplicates == VALUES as u64),
    )
    .await
    .expect("duplicates within 10 s")
    .expect("port open");
    assert_eq!(live.stats().arrived, VALUES as u64);
    let twice = port_lines(&broker, &["replay", "ticks.rec", "--fast"]).await;
    assert_eq!(twice.len(), 2 * VALUES, "{twice:?}");

    // Refusals: a port on the default exchange (status 1), bad positions
    // and rates (status 64).
    let _direct = OutPort::<TimedLong>::connect(
        base.clone()
            .routing_key("direct-q")
            .queue("direct-q")
            .name("direct-out"),
    )
    .await
    .expect("direct out-port");
    let refused = port_ctl(&broker, &["record", "direct-out", "--stream", "d.rec"]).await;
    assert_eq!(refused.status.code(), Some(1), "{refused:?}");
    for bad in [
        &["replay", "ticks.rec", "--rate", "0"][..],
        &["replay", "ticks.rec", "--start", "soon"],
        &["replay", "ticks.rec", "--end", "first"],
        &["replay", "ticks.rec", "--into", "x"],
    ] {
        let refused = port_ctl(&broker, bad).await;
        assert_eq!(refused.status.code(), Some(64), "{bad:?}: {refused:?}");
    }
    output.close().await;
    live.close().await;
    copy.close().await;
}
