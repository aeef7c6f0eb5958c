//! Robot data ports end to end: typed round trips for every `PortData`
//! impl, broadcast through a fanout exchange, and reliability across a
//! broker restart and a dropped TCP link (zero lost, zero duplicated, zero
//! out of order, as the paper's reliability test counts them).
//!
//! By default each test runs against an embedded Leveret (over TCP, and
//! over the in-process pipe where the test says so); with
//! LEVERET_TEST_AMQP_URL set, against that broker over TCP (the restart
//! test, which must restart the broker, then runs only on Leveret).

mod common;

use bytes::Bytes;
use common::{unique, within};
use leveret_broker::{Broker, BrokerHandle};
use leveret_client::{FieldValue, ShortStr};
use leveret_ports::{
    Backpressure, Connector, ExchangeKind, FullPolicy, InPort, OutPort, Point2D, PortData,
    PortProfile, PortStatus, Pose2D, Postcard, Sample, Time, TimedDouble, TimedDoubleSeq,
    TimedLong, TimedPose2D, TimedString, TimedVelocity2D, Velocity2D,
};
use leveret_tests::fault_proxy::FaultProxy as Proxy;
use std::fmt::Debug;
use std::net::SocketAddr;
use std::sync::{Arc, Mutex};
use std::time::Duration;

/// The broker the port tests use.
struct Env {
    uri: String,
    /// The embedded Leveret, when not testing an external broker.
    leveret: Option<Arc<BrokerHandle>>,
}

impl Env {
    async fn new() -> Env {
        if let Ok(uri) = std::env::var("LEVERET_TEST_AMQP_URL") {
            if !uri.is_empty() {
                return Env { uri, leveret: None };
            }
        }
        let handle = Broker::builder()
            .listen("127.0.0.1:0".parse().unwrap())
            .start()
            .await
            .expect("start an embedded Leveret");
        let addr = handle.local_addrs()[0];
        Env {
            uri: format!("amqp://guest:guest@{addr}/%2f"),
            leveret: Some(Arc::new(handle)),
        }
    }

    /// A profile for this broker with quick reconnection.
    fn profile(&self) -> PortProfile {
        profile(&self.uri)
    }

    /// The transports to test: TCP, and in-process on an embedded Leveret.
    fn transports(&self) -> Vec<(&'static str, Connector)> {
        let mut transports = vec![("tcp", Connector::from(&self.profile()))];
        if let Some(leveret) = &self.leveret {
            transports.push(("in-process", Connector::in_process(leveret)));
        }
        transports
    }
}

fn profile(uri: &str) -> PortProfile {
    let mut profile = PortProfile::new(uri)
        .expect("broker URI")
        .backoff(Duration::from_millis(10), Duration::from_millis(200))
        .put_timeout(Duration::from_secs(2))
        // These tests count every value: a full window waits for room.
        .backpressure(Backpressure::Block);
    // Named queues expire once unused, so failed runs leave nothing behind
    // on an external broker.
    profile
        .queue_arguments
        .insert(ShortStr::from_static("x-expires"), FieldValue::I32(120_000));
    profile
}

/// A point-to-point pair over the default exchange: the out-port publishes
/// with the in-port's queue name as routing key.
async fn pair<T: PortData>(connector: &Connector, profile: PortProfile) -> (OutPort<T>, InPort<T>) {
    let queue = unique("port");
    let profile = profile.queue(&queue).routing_key(&queue);
    let input = within(
        "in-port connect",
        InPort::<T>::connect_with(connector.clone(), profile.clone()),
    )
    .await
    .expect("in-port");
    let output = within(
        "out-port connect",
        OutPort::<T>::connect_with(connector.clone(), profile),
    )
    .await
    .expect("out-port");
    (output, input)
}

async fn round_trip<T>(connector: &Connector, base: PortProfile, values: Vec<T>)
where
    T: PortData + PartialEq + Debug,
{
    let (output, input) = pair::<T>(connector, base).await;
    for value in &values {
        assert_eq!(output.put(value).await, PortStatus::Ok, "put {value:?}");
    }
    for (i, expected) in values.iter().enumerate() {
        let sample = within("sample", input.recv()).await.expect("sample");
        assert_eq!(&sample.value, expected);
        assert_eq!(sample.seq, Some(i as u64 + 1));
        assert!(sample.latency.is_some());
    }
    let stats = input.stats();
    assert_eq!(
        (stats.arrived, stats.received, stats.buffered),
        (values.len() as u64, values.len() as u64, 0)
    );
    assert_eq!(
        (stats.lost, stats.out_of_order, stats.duplicates),
        (0, 0, 0)
    );
    assert_eq!(stats.decode_errors, 0);
    let latency = stats.latency;
    assert!(latency.percentile(0.5) > Duration::ZERO, "{latency:?}");
    assert!(latency.min <= latency.percentile(0.5));
    assert!(latency.percentile(0.5) <= latency.percentile(0.99));
    assert!(latency.percentile(0.99) <= latency.max);
    // A value may reach the in-port before its confirm reaches the
    // out-port (in process, the put hands it over on its own thread).
    within("every confirm", output.flush()).await;
    let out = output.stats();
    assert_eq!(out.accepted, values.len() as u64);
    assert_eq!(out.confirmed, values.len() as u64);
    output.close().await;
    input.close().await;
}

fn tm(sec: u32) -> Time {
    Time {
        sec,
        nsec: 123_456_789,
    }
}

#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
struct Command {
    id: u32,
    speed: f32,
    label: String,
    waypoints: Vec<(f64, f64)>,
}

#[tokio::test]
async fn typed_round_trips_over_every_transport() {
    let env = Env::new().await;
    for (name, connector) in env.transports() {
        eprintln!("transport: {name}");
        let p = env.profile();
        round_trip(
            &connector,
            p.clone(),
            vec![Bytes::from_static(b"\x00\x01raw"), Bytes::new()],
        )
        .await;
        round_trip(&connector, p.clone(), vec![vec![1u8, 2, 3], vec![]]).await;
        round_trip(
            &connector,
            p.clone(),
            vec!["pose ok".to_owned(), "é".into()],
        )
        .await;
        round_trip(&connector, p.clone(), vec![0u8, 255]).await;
        round_trip(&connector, p.clone(), vec![i8::MIN, -1]).await;
        round_trip(&connector, p.clone(), vec![u16::MAX, 7]).await;
        round_trip(&connector, p.clone(), vec![i16::MIN, 7]).await;
        round_trip(&connector, p.clone(), vec![u32::MAX, 7]).await;
        round_trip(&connector, p.clone(), vec![i32::MIN, 7]).await;
        round_trip(&connector, p.clone(), vec![u64::MAX, 7]).await;
        round_trip(&connector, p.clone(), vec![i64::MIN, 7]).await;
        round_trip(&connector, p.clone(), vec![u128::MAX, 7]).await;
        round_trip(&connector, p.clone(), vec![i128::MIN, 7]).await;
        round_trip(&connector, p.clone(), vec![1.5f32, f32::MIN_POSITIVE]).await;
        round_trip(&connector, p.clone(), vec![std::f64::consts::PI, -0.0]).await;
        round_trip(&connector, p.clone(), vec![true, false]).await;
        round_trip(
            &connector,
            p.clone(),
            vec![Postcard(Command {
                id: 9,
                speed: 0.25,
                label: "dock".into(),
                waypoints: vec![(1.0, 2.0), (3.0, -4.5)],
            })],
        )
        .await;
        round_trip(
            &connector,
            p.clone(),
            vec![TimedDouble {
                tm: tm(1),
                data: 2.5,
            }],
        )
        .await;
        round_trip(
            &connector,
            p.clone(),
            vec![TimedLong {
                tm: tm(2),
                data: -42,
            }],
        )
        .await;
        round_trip(
            &connector,
            p.clone(),
            vec![TimedString {
                tm: tm(3),
                data: "hello robot".into(),
            }],
        )
        .await;
        round_trip(
            &connector,
            p.clone(),
            vec![
                TimedDoubleSeq {
                    tm: tm(4),
                    data: vec![0.5, 1.5, -2.0],
                },
                TimedDoubleSeq {
                    tm: tm(5),
                    data: vec![],
                },
            ],
        )
        .await;
        round_trip(
            &connector,
            p.clone(),
            vec![TimedPose2D {
                tm: tm(6),
                data: Pose2D {
                    position: Point2D { x: 1.0, y: -2.0 },
                    heading: 0.75,
                },
            }],
        )
        .await;
        round_trip(
            &connector,
            p.clone(),
            vec![TimedVelocity2D {
                tm: tm(7),
                data: Velocity2D {
                    vx: 0.3,
                    vy: 0.0,
                    va: -0.1,
                },
            }],
        )
        .await;
    }
}

#[tokio::test]
async fn a_mismatched_type_is_counted_not_misread() {
    let env = Env::new().await;
    let connector = Connector::from(&env.profile());
    let queue = unique("mismatch");
    let profile = env.profile().queue(&queue).routing_key(&queue);
    let input = InPort::<TimedLong>::connect_with(connector.clone(), profile.clone())
        .await
        .unwrap();
    let doubles = OutPort::<TimedDouble>::connect_with(connector.clone(), profile.clone())
        .await
        .unwrap();
    let longs = OutPort::<TimedLong>::connect_with(connector, profile)
        .await
        .unwrap();
    let double = TimedDouble {
        tm: tm(1),
        data: 1.0,
    };
    assert_eq!(doubles.put(&double).await, PortStatus::Ok);
    let long = TimedLong { tm: tm(2), data: 5 };
    assert_eq!(longs.put(&long).await, PortStatus::Ok);
    let sample = within("sample", input.recv()).await.unwrap();
    assert_eq!(sample.value, long);
    let stats = input.stats();
    assert_eq!(
        (stats.arrived, stats.decode_errors, stats.received),
        (2, 1, 1)
    );
}

#[tokio::test]
async fn read_takes_the_newest_and_callbacks_see_everything() {
    let env = Env::new().await;
    let connector = env.transports().pop().unwrap().1;
    let (output, input) = pair::<u32>(&connector, env.profile()).await;
    let seen = Arc::new(Mutex::new(Vec::new()));
    let log = Arc::clone(&seen);
    input.on_receive(move |sample: &Sample<u32>| log.lock().unwrap().push(sample.value));
    assert!(input.read().is_none());
    for i in 1..=10u32 {
        assert_eq!(output.put(&i).await, PortStatus::Ok);
    }
    // Take the first through the stream, then wait (on the counters) for
    // the other nine to be buffered behind it.
    let first = within("first", input.recv()).await.unwrap();
    assert_eq!(first.value, 1);
    let mut stats = input.watch_stats();
    within("all ten", stats.wait_for(|s| s.arrived == 10))
        .await
        .unwrap();
    let newest = input.read().expect("a new value");
    assert_eq!(newest.value, 10);
    let stats = input.stats();
    assert_eq!((stats.received, stats.skipped, stats.buffered), (2, 8, 0));
    assert_eq!(stats.latency.count, 2, "measured as each was taken");
    assert!(input.read().is_none());
    assert_eq!(*seen.lock().unwrap(), (1..=10).collect::<Vec<_>>());
}

#[tokio::test]
async fn full_policies() {
    let env = Env::new().await;
    let connector = env.transports().pop().unwrap().1;
    for policy in [FullPolicy::DropOldest, FullPolicy::DropNewest] {
        let (output, input) = pair::<u32>(&connector, env.profile().buffer(3, policy)).await;
        let arrived = Arc::new(tokio::sync::Notify::new());
        let signal = Arc::clone(&arrived);
        input.on_receive(move |sample: &Sample<u32>| {
            if sample.value == 6 {
                signal.notify_one();
            }
        });
        for i in 1..=6u32 {
            assert_eq!(output.put(&i).await, PortStatus::Ok);
        }
        within("sixth value", arrived.notified()).await;
        // The callback runs before buffering: wait on the counters too.
        let mut stats = input.watch_stats();
        within("sixth handled", stats.wait_for(|s| s.arrived == 6))
            .await
            .unwrap();
        let mut kept = Vec::new();
        while let Some(sample) = input.try_recv() {
            kept.push(sample.value);
        }
        match policy {
            FullPolicy::DropOldest => assert_eq!(kept, [4, 5, 6]),
            _ => assert_eq!(kept, [1, 2, 3]),
        }
        let stats = input.stats();
        assert_eq!(
            (stats.arrived, stats.dropped, stats.received, stats.buffered),
            (6, 3, 3, 0)
        );
    }
    // BlockBroker: nothing is dropped; the broker keeps what the buffer
    // cannot hold until the reader catches up.
    let (output, input) = pair::<u32>(
        &connector,
        env.profile().buffer(2, FullPolicy::BlockBroker).prefetch(1),
    )
    .await;
    for i in 1..=50u32 {
        assert_eq!(output.put(&i).await, PortStatus::Ok);
    }
    for i in 1..=50u32 {
        assert_eq!(within("value", input.recv()).await.unwrap().value, i);
    }
    assert_eq!(input.stats().dropped, 0);
}

/// An in-port takes messages on its connection's reader while its buffer
/// has room, and hands them to its task while a full buffer holds the
/// broker back (`FullPolicy::BlockBroker`); the two ways take turns as a
/// reader that pauses now and then lets the buffer fill and then drains
/// it. Neither may reorder, lose or repeat a message, nor skip a
/// callback, on either runtime and either transport.
async fn a_reader_that_pauses_behind_a_full_buffer(flavor: &str) {
    const COUNT: u32 = 600;
    let env = Env::new().await;
    for (transport, connector) in env.transports() {
        let profile = env
            .profile()
            .buffer(4, FullPolicy::BlockBroker)
            .prefetch(32);
        let (output, input) = pair::<u32>(&connector, profile).await;
        let seen = Arc::new(Mutex::new(Vec::new()));
        let log = Arc::clone(&seen);
        input.on_receive(move |sample: &Sample<u32>| log.lock().unwrap().push(sample.value));
        for i in 1..=COUNT {
            assert_eq!(output.put(&i).await, PortStatus::Ok);
        }
        for i in 1..=COUNT {
            if i % 50 == 0 {
                tokio::time::sleep(Duration::from_millis(2)).await;
            }
            let sample = within("value", input.recv()).await.expect("in-port open");
            assert_eq!(
                sample.value, i,
                "{flavor}, {transport}: in order, exactly once"
            );
        }
        let stats = input.stats();
        assert_eq!(stats.received, u64::from(COUNT), "{flavor}, {transport}");
        assert_eq!(
            (
                stats.lost,
                stats.out_of_order,
                stats.duplicates,
                stats.dropped
            ),
            (0, 0, 0, 0),
            "{flavor}, {transport}: {stats:?}"
        );
        assert_eq!(*seen.lock().unwrap(), (1..=COUNT).collect::<Vec<_>>());
        output.close().await;
        input.close().await;
    }
}

#[test]
fn a_full_buffer_hands_over_in_order_on_either_runtime() {
    let current = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .unwrap();
    current.block_on(a_reader_that_pauses_behind_a_full_buffer("current-thread"));
    let multi = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()
        .unwrap();
    multi.block_on(a_reader_that_pauses_behind_a_full_buffer("multi-thread"));
}

/// Puts `range` as `TimedLong`s, retrying any value the port did not
/// accept (a full window during an outage), so the sequence has no gap.
async fn put_all(
    output: &OutPort<TimedLong>,
    range: std::ops::RangeInclusive<i32>,
) -> Vec<PortStatus> {
    let mut statuses = Vec::new();
    for i in range {
        let value = TimedLong {
            tm: Time::now(),
            data: i,
        };
        loop {
            let status = output.put(&value).await;
            statuses.push(status);
            if status.is_accepted() {
                break;
            }
            assert_eq!(status, PortStatus::SendFull, "put {i}");
        }
    }
    statuses
}

/// Receives until `count` values arrived, checking they are `first..`
/// in order, each once.
async fn expect_in_order(input: &mut InPort<TimedLong>, first: i32, count: i32) {
    for expected in first..first + count {
        let sample = within(&format!("value {expected}"), input.recv())
            .await
            .expect("in-port open");
        assert_eq!(sample.value.data, expected, "in order, exactly once");
    }
}

#[tokio::test]
async fn one_out_port_broadcasts_to_four_in_ports() {
    const COUNT: i32 = 2_000;
    let env = Env::new().await;
    let exchange = unique("broadcast");
    let base = env
        .profile()
        .exchange(&exchange, ExchangeKind::Fanout)
        .buffer(256, FullPolicy::BlockBroker);
    let connector = Connector::from(&base);
    let mut inputs = Vec::new();
    for _ in 0..4 {
        let input = within(
            "in-port",
            InPort::<TimedLong>::connect_with(connector.clone(), base.clone()),
        )
        .await
        .expect("in-port");
        inputs.push(input);
    }
    let output = OutPort::<TimedLong>::connect_with(connector, base)
        .await
        .expect("out-port");
    let publisher = async {
        let statuses = put_all(&output, 1..=COUNT).await;
        assert!(statuses.iter().all(|s| s.is_ok()));
    };
    let receivers = inputs.iter_mut().map(|input| async move {
        expect_in_order(input, 1, COUNT).await;
    });
    tokio::join!(publisher, futures_join_all(receivers));
    for input in &inputs {
        let stats = input.stats();
        assert_eq!(stats.received, COUNT as u64);
        assert_eq!(
            (
                stats.lost,
                stats.out_of_order,
                stats.duplicates,
                stats.dropped
            ),
            (0, 0, 0, 0),
            "{stats:?}"
        );
        assert_eq!(stats.latency.count, COUNT as u64);
        assert!(stats.latency.max >= stats.latency.min);
    }
}

/// Runs the futures concurrently (without a futures-util dependency).
async fn futures_join_all<F: std::future::Future<Output = ()>>(futures: impl Iterator<Item = F>) {
    let mut set = Vec::new();
    for future in futures {
        set.push(Box::pin(future));
    }
    std::future::poll_fn(|cx| {
        set.retain_mut(|f| f.as_mut().poll(cx).is_pending());
        if set.is_empty() {
            std::task::Poll::Ready(())
        } else {
            std::task::Poll::Pending
        }
    })
    .await
}

/// Waits until the port's link has come back `connects` times in all.
async fn wait_connected(
    mut link: tokio::sync::watch::Receiver<leveret_ports::LinkStatus>,
    connects: u64,
) {
    within(
        "the port to reconnect",
        link.wait_for(|s| s.up && s.connects >= connects),
    )
    .await
    .expect("port alive");
}

#[tokio::test]
async fn port_pair_survives_a_broker_restart() {
    if std::env::var("LEVERET_TEST_AMQP_URL").is_ok_and(|u| !u.is_empty()) {
        eprintln!("skipped: needs to restart the broker, so runs on Leveret only");
        return;
    }
    const BEFORE: i32 = 300;
    const DURING: i32 = 50;
    const AFTER: i32 = 300;
    let dir = tempfile::tempdir().expect("tempdir");
    let first = Broker::builder()
        .listen(leveret_tests::reserved_port::reserved_addr())
        .data_dir(dir.path())
        .start()
        .await
        .expect("start");
    let addr = first.local_addrs()[0];
    let queue = unique("restart");
    let profile = profile(&format!("amqp://guest:guest@{addr}/%2f"))
        .queue(&queue)
        .routing_key(&queue)
        .durable(true)
        .buffer(64, FullPolicy::BlockBroker);
    let mut input = InPort::<TimedLong>::connect(profile.clone())
        .await
        .expect("in-port");
    let output = OutPort::<TimedLong>::connect(profile)
        .await
        .expect("out-port");

    let statuses = put_all(&output, 1..=BEFORE).await;
    assert!(statuses.iter().all(|s| s.is_ok()));
    // Take some, leave the rest queued (and some delivered, unacked).
    expect_in_order(&mut input, 1, BEFORE / 2).await;

    first.shutdown().await;
    let (mut out_link, mut in_link) = (output.link(), input.link());
    within("out-port sees the loss", out_link.wait_for(|s| !s.up))
        .await
        .unwrap();
    within("in-port sees the loss", in_link.wait_for(|s| !s.up))
        .await
        .unwrap();
    // Puts during the outage are kept for the next link.
    let statuses = put_all(&output, BEFORE + 1..=BEFORE + DURING).await;
    assert!(
        statuses.iter().all(|s| *s == PortStatus::ConnectionLost),
        "{statuses:?}"
    );

    let second = restart(addr, dir.path()).await;
    wait_connected(output.link(), 2).await;
    wait_connected(input.link(), 2).await;
    put_all(&output, BEFORE + DURING + 1..=BEFORE + DURING + AFTER).await;
    within("every put confirmed", output.flush()).await;

    expect_in_order(&mut input, BEFORE / 2 + 1, BEFORE / 2 + DURING + AFTER).await;
    let stats = input.stats();
    assert_eq!(
        stats.received,
        (BEFORE + DURING + AFTER) as u64,
        "{stats:?}"
    );
    assert_eq!((stats.lost, stats.out_of_order), (0, 0), "{stats:?}");
    assert!(
        input.try_recv().is_none(),
        "no duplicate reached the reader"
    );
    output.close().await;
    input.close().await;
    second.shutdown().await;
}

/// Starts Leveret again on `addr` and `dir`, right after the previous
/// broker's shutdown (which releases the data directory before returning).
async fn restart(addr: SocketAddr, dir: &std::path::Path) -> BrokerHandle {
    Broker::builder()
        .listen(addr)
        .data_dir(dir)
        .start()
        .await
        .expect("restart on the same port and data directory")
}

#[tokio::test]
async fn port_pair_survives_a_dropped_tcp_link() {
    const COUNT: i32 = 3_000;
    let env = Env::new().await;
    let (options, broker) = upstream(&env).await;
    let proxy = Proxy::start(broker).await;
    let mut proxied = options.clone();
    proxied.host = "127.0.0.1".into();
    proxied.port = proxy.addr.port();
    let queue = unique("cut");
    let mut profile = env
        .profile()
        .queue(&queue)
        .routing_key(&queue)
        .buffer(64, FullPolicy::BlockBroker);
    profile.broker = proxied;
    let mut input = InPort::<TimedLong>::connect(profile.clone())
        .await
        .expect("in-port");
    let output = OutPort::<TimedLong>::connect(profile)
        .await
        .expect("out-port");

    // Cut mid-stream: once the in-port has a sixth of the values, while
    // the out-port is still putting.
    let part_way = Arc::new(tokio::sync::Notify::new());
    let signal = Arc::clone(&part_way);
    input.on_receive(move |sample: &Sample<TimedLong>| {
        if sample.value.data == COUNT / 6 {
            signal.notify_one();
        }
    });
    let publisher = async {
        let mut statuses = put_all(&output, 1..=COUNT / 3).await;
        within("a sixth received", part_way.notified()).await;
        assert_eq!(proxy.cut(), 2, "one connection per port");
        statuses.extend(put_all(&output, COUNT / 3 + 1..=COUNT).await);
        wait_connected(output.link(), 2).await;
        within("every put confirmed", output.flush()).await;
        statuses
    };
    let receiver = expect_in_order(&mut input, 1, COUNT);
    let (statuses, ()) = within_long(async { tokio::join!(publisher, receiver) }).await;
    let not_ok = statuses.iter().filter(|s| !s.is_ok()).count();
    wait_connected(input.link(), 2).await;
    let stats = input.stats();
    assert_eq!(stats.received, COUNT as u64, "{stats:?}");
    assert_eq!((stats.lost, stats.out_of_order), (0, 0), "{stats:?}");
    assert!(
        input.try_recv().is_none(),
        "no duplicate reached the reader"
    );
    let out = output.stats();
    assert_eq!(out.accepted, COUNT as u64);
    assert_eq!(out.confirmed, COUNT as u64);
    eprintln!("puts not Ok at once: {not_ok}\nin-port {stats:?}\nout-port {out:?}");
}

/// A longer [`within`] for a whole phase of a test.
async fn within_long<T>(future: impl std::future::Future<Output = T>) -> T {
    tokio::time::timeout(Duration::from_secs(60), future)
        .await
        .expect("phase timed out")
}

/// The broker's address behind the test URI.
async fn upstream(env: &Env) -> (leveret_client::ConnectionOptions, SocketAddr) {
    let options = leveret_client::ConnectionOptions::from_uri(&env.uri).unwrap();
    let addr = tokio::net::lookup_host((options.host.as_str(), options.port))
        .await
        .unwrap()
        .next()
        .expect("broker address");
    (options, addr)
}

#[tokio::test]
async fn put_statuses_while_the_broker_is_unreachable() {
    let env = Env::new().await;
    let (options, broker) = upstream(&env).await;
    let mut proxy = Proxy::start(broker).await;
    let queue = unique("away");
    let mut profile = env
        .profile()
        .queue(&queue)
        .routing_key(&queue)
        .put_timeout(Duration::from_millis(100));
    profile.max_unconfirmed = 2;
    // The in-port connects directly; only the out-port goes through the
    // proxy.
    let input = InPort::<TimedLong>::connect(profile.clone())
        .await
        .expect("in-port");
    let mut proxied = profile.clone();
    proxied.broker = leveret_client::ConnectionOptions {
        host: "127.0.0.1".into(),
        port: proxy.addr.port(),
        ..options
    };
    let output = OutPort::<TimedLong>::connect(proxied)
        .await
        .expect("out-port");
    let value = |data| TimedLong {
        tm: Time::now(),
        data,
    };
    assert_eq!(output.put(&value(1)).await, PortStatus::Ok);
    within("1 confirmed", output.flush()).await;

    proxy.stop().await;
    let mut link = output.link();
    within("the loss", link.wait_for(|s| !s.up)).await.unwrap();
    // Kept for later while the window has room, refused once it is full.
    assert_eq!(output.put(&value(2)).await, PortStatus::ConnectionLost);
    assert_eq!(output.put(&value(3)).await, PortStatus::ConnectionLost);
    assert_eq!(output.put(&value(4)).await, PortStatus::SendFull);
    let stats = output.stats();
    assert_eq!((stats.accepted, stats.send_full, stats.pending), (3, 1, 2));

    let _back = Proxy::start_at(proxy.addr, broker).await;
    wait_connected(output.link(), 2).await;
    within("the window sent", output.flush()).await;
    assert_eq!(output.put(&value(5)).await, PortStatus::Ok);
    // 4 was refused, so never numbered: no gap.
    for (expected_seq, expected) in [(1, 1), (2, 2), (3, 3), (4, 5)] {
        let sample = within("value", input.recv()).await.unwrap();
        assert_eq!(
            (sample.seq, sample.value.data),
            (Some(expected_seq), expected)
        );
    }
    assert_eq!(input.stats().lost, 0);
}

/// Busy polling: a value that comes while `recv` polls is taken without
/// the runtime parking; one that comes after the window is still taken
/// (by the wake-up); `recv_blocking` polls likewise on a thread of its
/// own; a closed port ends either. On both runtime flavours, in process
/// (where the broker's tasks share the polling runtime).
async fn busy_polling_in_port() {
    let env = Env::new().await;
    let leveret = env.leveret.clone().expect("an embedded Leveret");
    let connector = Connector::in_process(&leveret);
    let profile = env.profile().busy_poll(Duration::from_millis(200));
    let (output, input) = pair::<TimedLong>(&connector, profile).await;
    let value = |data: i32| TimedLong { tm: tm(1), data };

    // Within the window: recv polls while the broker's tasks run.
    let (got, status) = tokio::join!(within("recv", input.recv()), async {
        tokio::time::sleep(Duration::from_millis(20)).await;
        output.put(&value(1)).await
    });
    assert_eq!(status, PortStatus::Ok);
    assert_eq!(got.expect("a sample").value, value(1));

    // After the window: the waker takes over.
    let (got, status) = tokio::join!(within("recv", input.recv()), async {
        tokio::time::sleep(Duration::from_millis(400)).await;
        output.put(&value(2)).await
    });
    assert_eq!(status, PortStatus::Ok);
    assert_eq!(got.expect("a sample").value, value(2));

    // recv_blocking polls on a thread of its own.
    let input = Arc::new(input);
    let reader = {
        let input = Arc::clone(&input);
        std::thread::spawn(move || input.recv_blocking(Duration::from_secs(10)))
    };
    tokio::time::sleep(Duration::from_millis(20)).await;
    assert_eq!(output.put(&value(3)).await, PortStatus::Ok);
    let got = tokio::task::spawn_blocking(move || reader.join().expect("reader thread"))
        .await
        .expect("joined");
    assert_eq!(got.expect("a sample").value, value(3));

    let Ok(input) = Arc::try_unwrap(input) else {
        panic!("the reader thread still holds the port");
    };
    within("close", input.close()).await;
    drop(output);
}

#[tokio::test(flavor = "current_thread")]
async fn busy_polling_in_port_on_a_current_thread_runtime() {
    busy_polling_in_port().await;
}

/// How long the calling thread has been on the CPU, and how long it has
/// been runnable (on the CPU or waiting in the run queue for it), from
/// `/proc/thread-self/schedstat`. A thread that spins is runnable for its
/// whole window however busy the machine is; a sleeping one is on the CPU
/// for next to nothing, however long it waits for a core when it wakes.
fn thread_cpu_and_runnable_time() -> (Duration, Duration) {
    let stat = std::fs::read_to_string("/proc/thread-self/schedstat")
        .expect("/proc/thread-self/schedstat");
    let mut fields = stat
        .split_whitespace()
        .map(|f| f.parse::<u64>().expect("ns"));
    let (running, waiting) = (fields.next().expect("run"), fields.next().expect("wait"));
    (
        Duration::from_nanos(running),
        Duration::from_nanos(running + waiting),
    )
}

/// The poll really spins: on a current-thread runtime, a `recv` whose
/// value comes 300 ms into a 1 s window keeps the thread busy meanwhile
/// (without polling it would sleep, runnable for next to no time).
#[tokio::test(flavor = "current_thread")]
async fn a_busy_polling_in_port_spends_its_window_on_the_cpu() {
    let env = Env::new().await;
    let leveret = env.leveret.clone().expect("an embedded Leveret");
    let connector = Connector::in_process(&leveret);
    for (window, busy) in [(None, false), (Some(Duration::from_secs(1)), true)] {
        let mut profile = env.profile();
        profile.busy_poll = window;
        let (output, input) = pair::<TimedLong>(&connector, profile).await;
        let (cpu_before, runnable_before) = thread_cpu_and_runnable_time();
        let (got, _) = tokio::join!(within("recv", input.recv()), async {
            tokio::time::sleep(Duration::from_millis(300)).await;
            output.put(&TimedLong::default()).await
        });
        let (cpu_after, runnable_after) = thread_cpu_and_runnable_time();
        let (cpu, runnable) = (cpu_after - cpu_before, runnable_after - runnable_before);
        assert!(got.is_some());
        match busy {
            true => assert!(
                runnable >= Duration::from_millis(250),
                "polled for 300 ms, runnable for {runnable:?}"
            ),
            false => assert!(
                cpu < Duration::from_millis(100),
                "slept for 300 ms, on the CPU for {cpu:?}"
            ),
        }
        within("close", input.close()).await;
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn busy_polling_in_port_on_a_multi_thread_runtime() {
    busy_polling_in_port().await;
}
