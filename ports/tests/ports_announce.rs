//! Ports announcing themselves on `leveret.ports`, and the reader of the
//! announcements (`PortDirectory`): what an out-port and an in-port say of
//! themselves, their counters advancing as values flow, the last word of a
//! closed port, `put` unaffected by announcing through a frozen link, a
//! reader unbroken by garbage on the exchange, and the same against a real
//! RabbitMQ node (skipped without one, outside CI).
//!
//! Each test runs against an embedded Leveret over TCP (the connections'
//! names are read from its admin handle), the RabbitMQ one against a
//! RabbitMQ node of its own.

mod common;

use bytes::Bytes;
use common::{unique, within, without_waiting, TIMEOUT};
use leveret_broker::{Broker, BrokerHandle};
use leveret_client::{
    BasicGetOptions, BasicProperties, BasicPublishOptions, Channel, Connection, FieldTable,
    FieldValue, QueueBindOptions, QueueDeclareOptions, ShortStr,
};
use leveret_ports::{
    Backpressure, CdrOptions, ExchangeKind, FullPolicy, InPort, LinkStatus, OutPort,
    PortAnnouncement, PortDirectory, PortProfile, PortRole, PortState, PortStatus, Pose2D, Replay,
    Time, TimedLong, TimedPose2D, PORTS_EXCHANGE,
};
use leveret_tests::both_runtimes;
use leveret_tests::fault_proxy::FaultProxy as Proxy;
use leveret_tests::rabbit_node::{self, RabbitNode};
use std::net::SocketAddr;
use std::time::{Duration, Instant};

/// How often the tests' ports announce themselves.
const INTERVAL: Duration = Duration::from_millis(100);

/// An embedded Leveret on a loopback port.
async fn leveret() -> (BrokerHandle, SocketAddr) {
    let handle = Broker::builder()
        .listen("127.0.0.1:0".parse().unwrap())
        .start()
        .await
        .expect("start an embedded Leveret");
    let addr = handle.local_addrs()[0];
    (handle, addr)
}

fn uri(addr: SocketAddr) -> String {
    format!("amqp://guest:guest@{addr}/%2f")
}

/// A profile announcing every [`INTERVAL`], on an exchange of its own.
fn profile(uri: &str, kind: ExchangeKind) -> PortProfile {
    let mut profile = PortProfile::new(uri)
        .expect("broker URI")
        .backoff(Duration::from_millis(10), Duration::from_millis(200))
        .exchange(unique("announced"), kind)
        .announce_interval(Some(INTERVAL));
    profile
        .queue_arguments
        .insert(ShortStr::from_static("x-expires"), FieldValue::I32(120_000));
    profile
}

/// A reader of the announcements on a connection of its own.
async fn directory(uri: &str) -> (Connection, PortDirectory) {
    let connection = within("connect", Connection::connect(uri))
        .await
        .expect("connect");
    let directory = within("watch", PortDirectory::watch(&connection))
        .await
        .expect("watch the ports");
    (connection, directory)
}

/// The next announcement of the port `id` that satisfies `condition`.
async fn heard(
    directory: &mut PortDirectory,
    id: &str,
    mut condition: impl FnMut(&PortAnnouncement) -> bool,
) -> PortAnnouncement {
    within(&format!("an announcement of {id}"), async {
        loop {
            let announcement = directory
                .next()
                .await
                .expect("the reader's channel is open");
            if announcement.id == id && condition(&announcement) {
                return announcement;
            }
        }
    })
    .await
}

/// The next announcement of a port named `name` in `role`.
async fn heard_named(
    directory: &mut PortDirectory,
    name: &str,
    role: PortRole,
) -> PortAnnouncement {
    within(&format!("an announcement of {name}"), async {
        loop {
            let announcement = directory
                .next()
                .await
                .expect("the reader's channel is open");
            if announcement.name == name && announcement.role == role {
                return announcement;
            }
        }
    })
    .await
}

fn counter_names(announcement: &PortAnnouncement) -> Vec<&str> {
    announcement
        .stats
        .iter()
        .map(|(name, _)| name.as_str())
        .collect()
}

fn pose(n: u32) -> TimedPose2D {
    TimedPose2D {
        tm: Time::now(),
        data: Pose2D {
            heading: f64::from(n),
            ..Default::default()
        },
    }
}

/// The `connection_name` client property of every connection to `broker`.
fn connection_names(broker: &BrokerHandle) -> Vec<String> {
    broker
        .admin()
        .connections()
        .iter()
        .filter_map(|connection| {
            let name = connection.client_properties.get("connection_name")?;
            Some(String::from_utf8_lossy(name.as_bytes()?).into_owned())
        })
        .collect()
}

#[both_runtimes]
async fn ports_announce_who_they_are() {
    let (broker, addr) = leveret().await;
    let (connection, mut directory) = directory(&uri(addr)).await;
    // A raw queue on the out-port's routing key, to see the message itself.
    let tap = connection.open_channel().await.expect("channel");
    let tapped = tap
        .queue_declare("", QueueDeclareOptions::default(), FieldTable::new())
        .await
        .expect("queue");
    tap.queue_bind(
        &tapped.name,
        PORTS_EXCHANGE,
        "out.pose-out",
        QueueBindOptions::default(),
        FieldTable::new(),
    )
    .await
    .expect("bind");

    let base = profile(&uri(addr), ExchangeKind::Topic)
        .routing_key("robot1.pose")
        .binding_key("robot1.*")
        .lifespan(Duration::from_millis(500))
        .backpressure(Backpressure::DropNewest)
        .replay(Replay::Latest)
        .buffer(10, FullPolicy::DropNewest)
        .prefetch(20);
    let mut out_profile = base.clone().name("pose-out");
    out_profile.max_unconfirmed = 32;
    let input = InPort::<TimedPose2D>::connect(base.clone())
        .await
        .expect("in-port");
    let output = OutPort::<TimedPose2D>::connect(out_profile)
        .await
        .expect("out-port");

    let out = heard(&mut directory, output.id(), |_| true).await;
    assert_eq!(out.name, "pose-out");
    assert_eq!((out.role, out.state), (PortRole::OutPort, PortState::Up));
    assert_eq!(out.interval, INTERVAL);
    assert_eq!(out.data_type, "IDL:RTC/TimedPose2D:1.0");
    assert_eq!(out.content_type, "application/x-omg-cdr; endian=little");
    assert_eq!(out.cdr, Some(CdrOptions::default()));
    assert_eq!(out.exchange, base.exchange);
    assert_eq!(out.exchange_kind, ExchangeKind::Topic);
    assert_eq!((out.key.as_str(), out.queue.as_str()), ("robot1.pose", ""));
    assert!(out.confirms && !out.durable);
    assert_eq!(out.lifespan, Some(Duration::from_millis(500)));
    assert_eq!(out.backpressure, Some(Backpressure::DropNewest));
    assert_eq!(out.replay, Some(Replay::Latest));
    assert_eq!(out.window, Some(32));
    assert_eq!(
        (out.full_policy, out.buffer, out.prefetch),
        (None, None, None)
    );
    assert_eq!(
        out.link,
        LinkStatus {
            up: true,
            connects: 1,
            losses: 0,
            last_error: None,
            degraded: false,
        }
    );
    assert_eq!(
        counter_names(&out),
        [
            "accepted",
            "confirmed",
            "sent_unconfirmed",
            "rejected",
            "unroutable",
            "dropped_unsent",
            "expired",
            "lost",
            "pending",
            "in_flight",
            "resent",
            "send_full",
            "stalls",
            "returned_after_send"
        ]
    );
    assert!(out.stats.iter().all(|(_, value)| *value == 0), "{out:?}");
    assert_eq!(out.latency, None);

    // Without a name or a queue, an in-port is named after its exchange
    // and binding key.
    let in_name = format!("{}/robot1.*", base.exchange);
    let announced = heard_named(&mut directory, &in_name, PortRole::InPort).await;
    assert_eq!(announced.key, "robot1.*");
    assert_eq!(announced.queue, input.queue().to_string_lossy());
    assert_eq!(announced.full_policy, Some(FullPolicy::DropNewest));
    assert_eq!((announced.buffer, announced.prefetch), (Some(10), Some(20)));
    assert_eq!((announced.backpressure, announced.replay), (None, None));
    assert_eq!(
        counter_names(&announced),
        [
            "arrived",
            "received",
            "buffered",
            "stale",
            "decode_errors",
            "dropped",
            "skipped",
            "duplicates",
            "out_of_order",
            "lost"
        ]
    );
    assert_eq!(announced.latency.map(|l| l.count), Some(0));
    assert!(announced.link.up);

    let listed: Vec<(String, PortRole)> = directory
        .ports()
        .iter()
        .map(|port| (port.name.clone(), port.role))
        .collect();
    assert_eq!(
        listed,
        [
            (in_name.clone(), PortRole::InPort),
            ("pose-out".to_owned(), PortRole::OutPort)
        ]
    );

    // The message itself: transient, empty, expiring after three
    // intervals, on `out.NAME`.
    let message = within("the tapped announcement", async {
        loop {
            if let Some(message) = tap
                .basic_get(&tapped.name, BasicGetOptions { no_ack: true })
                .await
                .expect("get")
            {
                return message;
            }
            tokio::time::sleep(Duration::from_millis(10)).await;
        }
    })
    .await;
    let properties = &message.delivery.properties;
    assert_eq!(message.delivery.routing_key.as_str(), Some("out.pose-out"));
    assert!(message.body.is_empty());
    assert_eq!(properties.delivery_mode, Some(1));
    assert_eq!(
        properties.expiration.as_ref().and_then(|e| e.as_str()),
        Some("300")
    );
    assert_eq!(
        properties.kind.as_ref().and_then(|k| k.as_str()),
        Some("leveret.port.announcement")
    );

    let mut names = connection_names(&broker);
    names.sort();
    assert_eq!(
        names,
        [
            format!("leveret port in {in_name}"),
            "leveret port out pose-out".to_owned()
        ]
    );
    output.close().await;
    input.close().await;
}

#[both_runtimes]
async fn announced_counters_follow_the_values() {
    const COUNT: u32 = 20;
    let (_broker, addr) = leveret().await;
    let (_connection, mut directory) = directory(&uri(addr)).await;
    let base = profile(&uri(addr), ExchangeKind::Fanout);
    let input = InPort::<TimedPose2D>::connect(base.clone().name("poses-in"))
        .await
        .expect("in-port");
    let output = OutPort::<TimedPose2D>::connect(base.name("poses-out"))
        .await
        .expect("out-port");
    let before = heard(&mut directory, output.id(), |_| true).await;
    assert_eq!(before.counter("accepted"), Some(0));

    for n in 1..=COUNT {
        assert_eq!(output.put(&pose(n)).await, PortStatus::Ok);
    }
    for _ in 1..=COUNT {
        within("a value", input.recv()).await.expect("open");
    }
    let out = heard(&mut directory, output.id(), |a| {
        a.counter("confirmed") == Some(u64::from(COUNT))
    })
    .await;
    assert_eq!(out.counter("accepted"), Some(u64::from(COUNT)));
    assert_eq!(out.counter("pending"), Some(0));
    let announced = heard_named(&mut directory, "poses-in", PortRole::InPort).await;
    let announced = if announced.counter("received") == Some(u64::from(COUNT)) {
        announced
    } else {
        heard(&mut directory, &announced.id, |a| {
            a.counter("received") == Some(u64::from(COUNT))
        })
        .await
    };
    assert_eq!(announced.counter("lost"), Some(0));
    let latency = announced.latency.expect("an in-port's latencies");
    assert_eq!(latency.count, u64::from(COUNT));
    assert!(latency.p50 > Duration::ZERO, "{latency:?}");
    assert!(latency.min <= latency.p50 && latency.p50 <= latency.p99 && latency.p99 <= latency.max);
    assert!(latency.min <= latency.mean && latency.mean <= latency.max);

    // Several announcements later, the ports' own counters hold only the
    // values: announcing is not counted.
    let later = heard(&mut directory, output.id(), |a| a.sent_ns > out.sent_ns).await;
    heard(&mut directory, output.id(), |a| a.sent_ns > later.sent_ns).await;
    assert_eq!(output.stats().accepted, u64::from(COUNT));
    assert_eq!(output.stats().confirmed, u64::from(COUNT));
    assert_eq!(input.stats().received, u64::from(COUNT));
    assert!(input.try_recv().is_none(), "nothing but the values arrived");
}

#[both_runtimes]
async fn closing_a_port_announces_closed() {
    let (_broker, addr) = leveret().await;
    let (_connection, mut directory) = directory(&uri(addr)).await;
    let base = profile(&uri(addr), ExchangeKind::Fanout);
    let input = InPort::<TimedLong>::connect(base.clone().name("closing-in"))
        .await
        .expect("in-port");
    let output = OutPort::<TimedLong>::connect(base.name("closing-out"))
        .await
        .expect("out-port");
    let id = output.id().to_owned();
    heard(&mut directory, &id, |_| true).await;
    let input_id = heard_named(&mut directory, "closing-in", PortRole::InPort)
        .await
        .id;
    assert_eq!(directory.ports().len(), 2);
    let value = TimedLong {
        tm: Time::now(),
        data: 7,
    };
    assert_eq!(output.put(&value).await, PortStatus::Ok);
    within("confirmed", output.flush()).await;

    output.close().await;
    let last = heard(&mut directory, &id, |a| a.state == PortState::Closed).await;
    assert_eq!(last.counter("confirmed"), Some(1), "the final counters");
    assert!(
        directory.named("closing-out").is_empty(),
        "a closed port leaves the table at once"
    );
    // Dropping an in-port closes it the same way.
    drop(input);
    heard(&mut directory, &input_id, |a| a.state == PortState::Closed).await;
    assert!(directory.ports().is_empty());
}

/// Taken by the tests whose timing another test's load would upset: the
/// 100 Hz loop below, and RabbitMQ's boot.
static ALONE: tokio::sync::Mutex<()> = tokio::sync::Mutex::const_new(());

/// A 100 Hz loop putting through a frozen link while its port tries to
/// announce itself every 20 ms: `put` never waits, and the announcements,
/// which stop while the link is frozen (the port drops out of the table
/// after three intervals), come back after it on the same link.
async fn puts_while_announcements_are_stuck(flavor: &str) {
    let announce_every = Duration::from_millis(20);
    let (_broker, addr) = leveret().await;
    let proxy = Proxy::start(addr).await;
    let (_connection, mut directory) = directory(&uri(addr)).await;
    let base = profile(&uri(addr), ExchangeKind::Fanout)
        .announce_interval(Some(announce_every))
        .buffer(1024, FullPolicy::BlockBroker);
    let input = InPort::<TimedLong>::connect(base.clone().name("frozen-in"))
        .await
        .expect("in-port");
    let proxied = PortProfile::new(&uri(proxy.addr))
        .expect("proxy URI")
        .exchange(base.exchange.clone(), ExchangeKind::Fanout)
        .announce_interval(Some(announce_every))
        .name("frozen-out");
    let output = OutPort::<TimedLong>::connect(proxied)
        .await
        .expect("out-port");
    heard(&mut directory, output.id(), |_| true).await;

    // Phases by what was seen, not by the clock alone (a loaded machine
    // skips ticks): puts while the port is listed, then at least a second
    // with the link frozen (looked at once 900 ms in, thirty silent
    // intervals), then 300 ms more; the hang limit ends a phase that
    // never comes, and the assertions below say which.
    let mut tick = tokio::time::interval(Duration::from_millis(10));
    let started = Instant::now();
    let mut count = 0;
    let (mut listed_before, mut listed_while_frozen) = (None, None);
    let (mut frozen_at, mut thawed_at) = (None::<Instant>, None::<Instant>);
    while thawed_at.is_none_or(|at| at.elapsed() < Duration::from_millis(300))
        && started.elapsed() < TIMEOUT * 3
    {
        tick.tick().await;
        // Whatever announcements have arrived (next() is cancel-safe).
        while let Ok(Some(_)) = tokio::time::timeout(Duration::ZERO, directory.next()).await {}
        match (frozen_at, thawed_at) {
            (None, _) => {
                let listed = directory.named("frozen-out").len();
                listed_before = listed_before.max(Some(listed));
                if listed > 0 && started.elapsed() >= Duration::from_millis(200) {
                    proxy.freeze(true);
                    frozen_at = Some(Instant::now());
                }
            }
            (Some(at), None) if at.elapsed() >= Duration::from_millis(900) => {
                listed_while_frozen.get_or_insert_with(|| directory.named("frozen-out").len());
                if at.elapsed() >= Duration::from_millis(1000) {
                    proxy.freeze(false);
                    thawed_at = Some(Instant::now());
                }
            }
            _ => {}
        }
        count += 1;
        let value = TimedLong {
            tm: Time::now(),
            data: count,
        };
        // Done at its first poll: it never waited, on the frozen link
        // or anything else.
        let status = without_waiting(output.put(&value))
            .unwrap_or_else(|| panic!("{flavor}: put {count} waited"));
        assert!(status.is_accepted(), "put {count}: {status:?}");
    }
    proxy.freeze(false);
    assert_eq!(
        (listed_before, listed_while_frozen),
        (Some(1), Some(0)),
        "listed while heard from, not after three silent intervals"
    );
    let after = heard(&mut directory, output.id(), |a| {
        a.counter("confirmed") == Some(count as u64)
    })
    .await;
    assert_eq!(after.link.connects, 1, "the same link: {:?}", after.link);
    within("confirmed", output.flush()).await;
    for expected in 1..=count {
        let sample = within("every value", input.recv()).await.expect("open");
        assert_eq!(sample.value.data, expected);
    }
    let stats = output.stats();
    assert_eq!(
        (stats.accepted, stats.confirmed),
        (count as u64, count as u64)
    );
    assert_eq!(input.stats().received, count as u64);
}

/// Both runtime flavours, one after the other (in parallel they would
/// preempt each other's loops).
#[test]
fn announcements_never_delay_put() {
    let _alone = ALONE.blocking_lock();
    let current = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .unwrap();
    current.block_on(puts_while_announcements_are_stuck("current-thread"));
    let multi = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()
        .unwrap();
    multi.block_on(puts_while_announcements_are_stuck("multi-thread"));
}

/// The wire contract's required fields, for a fake port `id`.
fn fake_announcement(id: &str) -> FieldTable {
    let text = FieldValue::string;
    [
        ("version", FieldValue::I64(1)),
        ("port", text(id)),
        ("name", text(id)),
        ("direction", text("out")),
        ("state", text("up")),
        ("interval_ms", FieldValue::I64(60_000)),
        ("sent_ns", FieldValue::I64(1)),
        ("from_a_later_version", text("ignored")),
    ]
    .into_iter()
    .map(|(key, value)| (ShortStr::try_from(key).unwrap(), value))
    .collect()
}

async fn publish_raw(
    channel: &Channel,
    key: &str,
    headers: Option<FieldTable>,
    body: &'static [u8],
) {
    let properties = BasicProperties {
        headers,
        ..Default::default()
    };
    channel
        .basic_publish(
            PORTS_EXCHANGE,
            key,
            BasicPublishOptions::default(),
            properties,
            Bytes::from_static(body),
        )
        .await
        .expect("publish");
}

#[both_runtimes]
async fn garbage_on_the_ports_exchange_does_not_break_the_reader() {
    const FAKES: usize = PortDirectory::CAPACITY + 500;
    let (_broker, addr) = leveret().await;
    let (_connection, mut directory) = directory(&uri(addr)).await;
    // Its own connection: the reader is not drained while the fakes go
    // out, and a full consumer buffer pauses its connection's reading.
    let publisher = within("connect", Connection::connect(&uri(addr)))
        .await
        .expect("connect");
    let channel = publisher.open_channel().await.expect("channel");
    let text = FieldValue::string;
    let table = |entries: Vec<(&str, FieldValue)>| -> FieldTable {
        entries
            .into_iter()
            .map(|(key, value)| (ShortStr::try_from(key).unwrap(), value))
            .collect()
    };
    let mut huge_stats = FieldTable::new();
    for n in 0..2000 {
        huge_stats.insert(
            ShortStr::try_from(format!("c{n}").as_str()).unwrap(),
            FieldValue::I64(n),
        );
    }
    let mut garbage: Vec<Option<FieldTable>> = vec![
        None,
        Some(FieldTable::new()),
        Some(table(vec![
            ("version", text("one")),
            ("port", FieldValue::I64(3)),
        ])),
        Some(table(vec![(
            "stats",
            FieldValue::Table(huge_stats.clone()),
        )])),
    ];
    for (key, value) in [
        ("direction", text("sideways")),
        ("state", FieldValue::Bool(true)),
        ("interval_ms", FieldValue::I64(-1)),
        ("interval_ms", FieldValue::I64(0)),
        ("version", FieldValue::I64(-7)),
        ("name", FieldValue::LongStr(Bytes::from_static(b"\xc3\x28"))),
        ("port", text("")),
        ("sent_ns", text("yesterday")),
    ] {
        let mut damaged = fake_announcement("damaged");
        damaged.insert(ShortStr::try_from(key).unwrap(), value);
        garbage.push(Some(damaged));
    }
    for headers in garbage {
        publish_raw(
            &channel,
            "out.garbage",
            headers,
            b"\x00\xffnot an announcement",
        )
        .await;
    }
    // Valid in form, absurd in content: kept, within bounds.
    let mut absurd = fake_announcement("absurd");
    absurd.insert(
        ShortStr::from_static("interval_ms"),
        FieldValue::I64(i64::MAX),
    );
    absurd.insert(
        ShortStr::from_static("stats"),
        FieldValue::Table(huge_stats),
    );
    absurd.insert(ShortStr::from_static("link"), text("not a table"));
    absurd.insert(
        ShortStr::from_static("latency"),
        FieldValue::Table(FieldTable::new()),
    );
    publish_raw(&channel, "anything", Some(absurd), b"").await;
    let kept = within("the absurd one", directory.next())
        .await
        .expect("open");
    assert_eq!(kept.id, "absurd", "every message before it was skipped");
    assert_eq!(
        kept.stats.len(),
        64,
        "counters kept from one announcement, at most"
    );
    assert_eq!((kept.latency, kept.link), (None, LinkStatus::default()));

    // More ports than the table holds, all routed (confirmed) before the
    // real port starts.
    channel.confirm_select().await.expect("confirm mode");
    for n in 0..FAKES {
        publish_raw(
            &channel,
            "out.fake",
            Some(fake_announcement(&format!("fake-{n}"))),
            b"",
        )
        .await;
    }
    assert!(within("the fakes confirmed", channel.wait_for_confirms())
        .await
        .expect("confirms"));
    let real = profile(&uri(addr), ExchangeKind::Fanout).name("real");
    let output = OutPort::<TimedLong>::connect(real).await.expect("out-port");
    let mut fakes_heard = 0;
    within("the real port after the fakes", async {
        loop {
            let announcement = directory.next().await.expect("open");
            if announcement.id == output.id() {
                break;
            }
            assert!(announcement.id.starts_with("fake-"), "{announcement:?}");
            fakes_heard += 1;
        }
    })
    .await;
    assert_eq!(fakes_heard, FAKES);
    let ports = directory.ports();
    assert_eq!(ports.len(), PortDirectory::CAPACITY);
    assert!(ports.iter().any(|port| port.name == "real"));
    assert!(
        !ports
            .iter()
            .any(|port| port.id == "absurd" || port.id == "fake-0"),
        "the ones heard from longest ago made room"
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn announcements_and_the_reader_work_against_rabbitmq() {
    let _alone = ALONE.lock().await;
    if !rabbit_node::installed() {
        return;
    }
    let root = std::env::temp_dir().join(format!("leveret-port-announce-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&root);
    std::fs::create_dir_all(&root).expect("root");
    let home = root.clone();
    let node = tokio::task::spawn_blocking(move || {
        RabbitNode::start("announce", &home.join("node"), &home)
    })
    .await
    .expect("node");
    let (_connection, mut directory) = directory(&node.uri()).await;
    let base = profile(&node.uri(), ExchangeKind::Fanout);
    let input = InPort::<TimedPose2D>::connect(base.clone().name("rabbit-in"))
        .await
        .expect("in-port");
    let output = OutPort::<TimedPose2D>::connect(base.name("rabbit-out"))
        .await
        .expect("out-port");
    for n in 1..=5 {
        assert_eq!(output.put(&pose(n)).await, PortStatus::Ok);
        within("a value", input.recv()).await.expect("open");
    }
    let out = heard(&mut directory, output.id(), |a| {
        a.counter("confirmed") == Some(5)
    })
    .await;
    assert_eq!(
        (out.name.as_str(), out.role),
        ("rabbit-out", PortRole::OutPort)
    );
    assert_eq!(out.data_type, "IDL:RTC/TimedPose2D:1.0");
    let announced = heard_named(&mut directory, "rabbit-in", PortRole::InPort).await;
    let announced = heard(&mut directory, &announced.id, |a| {
        a.counter("received") == Some(5)
    })
    .await;
    assert_eq!(announced.latency.map(|l| l.count), Some(5));
    let connections = node.must(&["list_connections", "client_properties"]);
    assert!(
        connections.contains("leveret port out rabbit-out")
            && connections.contains("leveret port in rabbit-in"),
        "{connections}"
    );
    output.close().await;
    heard(&mut directory, &out.id, |a| a.state == PortState::Closed).await;
    input.close().await;
    drop(node);
    let _ = std::fs::remove_dir_all(&root);
}
