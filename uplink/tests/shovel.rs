//! Shovels between two Leveret brokers (the robot's, in process, and a
//! "fleet" broker over TCP), on both runtimes: everything confirmed to
//! the local publisher arrives, in order, across the destination going
//! away and coming back; a destination that refuses (a full
//! reject-publish queue, an exchange that routes nowhere) never drains the
//! source and the shovel resumes when it takes messages again; a dead
//! first URI fails over to the next.

mod common;

use common::*;
use leveret_broker::{Broker, BrokerHandle};
use leveret_client::{
    BasicGetOptions, BasicProperties, BasicPublishOptions, Channel, FieldTable, FieldValue,
    ShortStr,
};
use leveret_test_macros::both_runtimes;
use leveret_tests::reserved_port::reserved_addr;
use leveret_uplink::{Shovel, ShovelConfig, ShovelState};
use serde_json::json;
use std::net::SocketAddr;
use std::sync::Arc;
use std::time::Duration;

async fn fleet(addr: SocketAddr, dir: &std::path::Path) -> BrokerHandle {
    Broker::builder()
        .listen(addr)
        .data_dir(dir)
        .start()
        .await
        .expect("fleet broker")
}

/// Takes every message from `queue` now there.
async fn drain(channel: &Channel, queue: &str) -> Vec<u32> {
    let mut got = Vec::new();
    while let Some(message) = channel
        .basic_get(queue, BasicGetOptions { no_ack: true })
        .await
        .expect("get")
    {
        got.push(
            String::from_utf8_lossy(&message.body)
                .parse()
                .expect("a number"),
        );
    }
    got
}

/// Collects `count` messages from `queue` on the fleet broker, in order of
/// arrival (duplicates kept).
async fn collect(channel: &Channel, queue: &str, count: usize) -> Vec<u32> {
    let mut got = Vec::new();
    let deadline = tokio::time::Instant::now() + WAIT;
    while got.iter().collect::<std::collections::BTreeSet<_>>().len() < count {
        assert!(
            tokio::time::Instant::now() < deadline,
            "{} distinct of {count}",
            got.len()
        );
        let more = drain(channel, queue).await;
        if more.is_empty() {
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
        got.extend(more);
    }
    got
}

fn shovel_config(dest_uris: &[String], destination: serde_json::Value) -> ShovelConfig {
    let mut value = json!({
        "src-uri": "amqp://", "src-queue": "telemetry", "src-prefetch-count": 50,
        "dest-uri": dest_uris, "reconnect-delay": 0.1,
    });
    value
        .as_object_mut()
        .unwrap()
        .extend(destination.as_object().unwrap().clone());
    ShovelConfig::from_json(&value).expect("valid parameters")
}

#[both_runtimes]
async fn nothing_confirmed_is_lost_across_a_destination_outage() {
    let robot = Arc::new(Broker::builder().start().await.expect("robot broker"));
    let (_local, publisher) = local_channel(&robot).await;
    publisher.confirm_select().await.expect("confirms");
    declare(&publisher, "telemetry", FieldTable::new()).await;
    let addr = reserved_addr();
    let dir = scratch("outage");
    let fleet_uri = format!("amqp://guest:guest@{addr}/%2f");
    let first = fleet(addr, &dir).await;
    {
        let (_c, ch) = channel_to(&fleet_uri).await;
        declare(&ch, "fleet.telemetry", FieldTable::new()).await;
    }
    let shovel = Shovel::start(
        "up",
        shovel_config(
            std::slice::from_ref(&fleet_uri),
            json!({"dest-queue": "fleet.telemetry"}),
        ),
        Some(&robot),
    );
    publish_confirmed(&publisher, "", "telemetry", 0, 300).await;
    wait_status(&shovel, "300 forwarded", |s| s.forwarded >= 300).await;

    // The fleet broker goes away; the robot keeps publishing.
    first.shutdown().await;
    publish_confirmed(&publisher, "", "telemetry", 300, 600).await;
    wait_status(&shovel, "the loss noticed", |s| {
        s.state != ShovelState::Running
    })
    .await;
    let second = fleet(addr, &dir).await;
    wait_status(&shovel, "all forwarded", |s| s.forwarded >= 600).await;

    let (_c, ch) = channel_to(&fleet_uri).await;
    let got = collect(&ch, "fleet.telemetry", 600).await;
    let distinct: std::collections::BTreeSet<u32> = got.iter().copied().collect();
    assert_eq!(
        distinct,
        (0..600).collect(),
        "every confirmed message arrived"
    );
    let mut last = None;
    for n in got.iter().copied() {
        assert!(last.is_none_or(|l| n > l || distinct.contains(&n)), "order");
        last = Some(n);
    }
    let first_seen: Vec<u32> = {
        let mut seen = std::collections::HashSet::new();
        got.iter().copied().filter(|n| seen.insert(*n)).collect()
    };
    assert!(
        first_seen.windows(2).all(|w| w[0] < w[1]),
        "in order per source"
    );
    assert!(shovel.status().restarts >= 1);
    shovel.stop().await;
    second.shutdown().await;
    let _ = std::fs::remove_dir_all(&dir);
}

#[both_runtimes]
async fn a_refusing_destination_never_drains_the_source() {
    let robot = Arc::new(Broker::builder().start().await.expect("robot broker"));
    let (_local, publisher) = local_channel(&robot).await;
    publisher.confirm_select().await.expect("confirms");
    declare(&publisher, "telemetry", FieldTable::new()).await;
    let addr = reserved_addr();
    let dir = scratch("refusing");
    let fleet_uri = format!("amqp://guest:guest@{addr}/%2f");
    let _fleet = fleet(addr, &dir).await;
    let (_c, fleet_channel) = channel_to(&fleet_uri).await;
    let mut bounded = FieldTable::new();
    bounded.insert(ShortStr::from_static("x-max-length"), FieldValue::I32(10));
    bounded.insert(
        ShortStr::from_static("x-overflow"),
        FieldValue::string("reject-publish"),
    );
    declare(&fleet_channel, "bounded", bounded).await;
    publish_confirmed(&publisher, "", "telemetry", 0, 50).await;
    let shovel = Shovel::start(
        "bounded",
        shovel_config(
            std::slice::from_ref(&fleet_uri),
            json!({"dest-queue": "bounded"}),
        ),
        Some(&robot),
    );
    wait_status(&shovel, "a refusal", |s| s.refused >= 1).await;
    assert_eq!(shovel.status().forwarded, 10);
    // What the destination did not take stays on the robot (the first
    // ten's acks may still be on their way to the robot's broker).
    let deadline = tokio::time::Instant::now() + WAIT;
    while held_at_source(&robot) != 40 {
        assert!(held_at_source(&robot) > 40, "the source was drained");
        assert!(
            tokio::time::Instant::now() < deadline,
            "{}",
            held_at_source(&robot)
        );
        tokio::time::sleep(Duration::from_millis(10)).await;
    }
    wait_status(&shovel, "tried again after reconnect-delay", |s| {
        s.refused >= 2
    })
    .await;
    assert_eq!(held_at_source(&robot), 40, "and stays there while refused");
    // Consuming at the destination makes room: the rest follows, each
    // once. A refused message that is retried arrives after later ones
    // the destination took meanwhile.
    let mut got = collect(&fleet_channel, "bounded", 50).await;
    tokio::time::sleep(Duration::from_millis(300)).await;
    got.extend(drain(&fleet_channel, "bounded").await);
    let mut sorted = got.clone();
    sorted.sort_unstable();
    assert_eq!(
        sorted,
        (0..50).collect::<Vec<_>>(),
        "nothing lost, nothing twice"
    );
    assert_eq!(&got[..10], &(0..10).collect::<Vec<_>>()[..]);
    shovel.stop().await;
    let _ = std::fs::remove_dir_all(&dir);
}

/// Messages in the robot's `telemetry` queue, ready or held by the shovel.
fn held_at_source(robot: &BrokerHandle) -> u64 {
    robot
        .queues()
        .iter()
        .find(|q| q.name == "telemetry")
        .map_or(0, |q| q.messages_ready + q.messages_unacknowledged)
}

#[both_runtimes]
async fn unroutable_messages_stay_and_a_dead_node_fails_over() {
    let robot = Arc::new(Broker::builder().start().await.expect("robot broker"));
    let (_local, publisher) = local_channel(&robot).await;
    publisher.confirm_select().await.expect("confirms");
    declare(&publisher, "telemetry", FieldTable::new()).await;
    let addr = reserved_addr();
    let dir = scratch("unroutable");
    let fleet_uri = format!("amqp://guest:guest@{addr}/%2f");
    let _fleet = fleet(addr, &dir).await;
    let dead = format!("amqp://guest:guest@{}/%2f", reserved_addr());
    publish_confirmed(&publisher, "", "telemetry", 0, 20).await;
    let shovel = Shovel::start(
        "routes",
        shovel_config(
            &[dead, fleet_uri.clone()],
            json!({"dest-exchange": "amq.direct", "dest-exchange-key": "robots"}),
        ),
        Some(&robot),
    );
    wait_status(&shovel, "a return", |s| s.refused >= 1).await;
    assert_eq!(
        shovel.status().forwarded,
        0,
        "nothing routed, nothing acked"
    );
    let (_c, fleet_channel) = channel_to(&fleet_uri).await;
    declare(&fleet_channel, "robots", FieldTable::new()).await;
    fleet_channel
        .queue_bind(
            "robots",
            "amq.direct",
            "robots",
            Default::default(),
            FieldTable::new(),
        )
        .await
        .expect("bind");
    wait_status(&shovel, "all forwarded", |s| s.forwarded >= 20).await;
    assert_eq!(
        collect(&fleet_channel, "robots", 20).await,
        (0..20).collect::<Vec<_>>()
    );
    assert!(shovel
        .status()
        .destination
        .is_some_and(|d| d.contains(&addr.to_string())));
    shovel.stop().await;
    let _ = std::fs::remove_dir_all(&dir);
}

/// `bandwidth-limit` holds: 200 kB of bodies at 100 kB/s take at least
/// 1.9 s less 10% (the first tenth of a second is a burst), however fast
/// the link.
#[both_runtimes]
async fn the_bandwidth_cap_holds() {
    let robot = Arc::new(Broker::builder().start().await.expect("robot broker"));
    let (_local, publisher) = local_channel(&robot).await;
    publisher.confirm_select().await.expect("confirms");
    declare(&publisher, "telemetry", FieldTable::new()).await;
    for _ in 0..100 {
        publisher
            .basic_publish(
                "",
                "telemetry",
                BasicPublishOptions::default(),
                BasicProperties::default(),
                vec![7u8; 2000].into(),
            )
            .await
            .expect("publish")
            .await
            .expect("confirm");
    }
    let addr = reserved_addr();
    let dir = scratch("bandwidth");
    let fleet_uri = format!("amqp://guest:guest@{addr}/%2f");
    let _fleet = fleet(addr, &dir).await;
    let (_c, fleet_channel) = channel_to(&fleet_uri).await;
    declare(&fleet_channel, "paced", FieldTable::new()).await;
    let mut config = shovel_config(
        std::slice::from_ref(&fleet_uri),
        json!({"dest-queue": "paced"}),
    );
    config.bandwidth_limit = Some(100_000);
    let started = tokio::time::Instant::now();
    let shovel = Shovel::start("paced", config, Some(&robot));
    wait_status(&shovel, "all forwarded", |s| s.forwarded >= 100).await;
    let elapsed = started.elapsed();
    assert!(
        elapsed >= Duration::from_millis(1710),
        "200 kB at 100 kB/s took {elapsed:?}"
    );
    shovel.stop().await;
    let _ = std::fs::remove_dir_all(&dir);
}

/// Commands come down the same way: a shovel whose source is the fleet's
/// queue and whose destination is the robot's own exchange (`amqp://`),
/// so the robot's consumers get the fleet's commands through its broker.
#[both_runtimes]
async fn commands_come_down_from_the_fleet_to_a_local_exchange() {
    let robot = Arc::new(Broker::builder().start().await.expect("robot broker"));
    let (_local, robot_channel) = local_channel(&robot).await;
    declare(&robot_channel, "arm.commands", FieldTable::new()).await;
    // Without dest-exchange-key each message keeps its routing key: here
    // the fleet's queue name, which the robot binds.
    robot_channel
        .queue_bind(
            "arm.commands",
            "amq.topic",
            "robot-7.commands",
            Default::default(),
            FieldTable::new(),
        )
        .await
        .expect("bind");
    let addr = reserved_addr();
    let dir = scratch("down");
    let fleet_uri = format!("amqp://guest:guest@{addr}/%2f");
    let _fleet = fleet(addr, &dir).await;
    let (_c, fleet_channel) = channel_to(&fleet_uri).await;
    fleet_channel.confirm_select().await.expect("confirms");
    declare(&fleet_channel, "robot-7.commands", FieldTable::new()).await;
    let config = ShovelConfig::from_json(&json!({
        "src-uri": fleet_uri, "src-queue": "robot-7.commands",
        "dest-uri": "amqp://", "dest-exchange": "amq.topic", "reconnect-delay": 0.1,
    }))
    .expect("parameters");
    let shovel = Shovel::start("down", config, Some(&robot));
    for n in 0..20u32 {
        let confirm = fleet_channel
            .basic_publish(
                "",
                "robot-7.commands",
                BasicPublishOptions::default(),
                BasicProperties::default(),
                n.to_string().into_bytes().into(),
            )
            .await
            .expect("publish");
        assert!(confirm.await.expect("confirm").is_ack());
    }
    wait_status(&shovel, "20 forwarded", |s| s.forwarded >= 20).await;
    assert_eq!(
        collect(&robot_channel, "arm.commands", 20).await,
        (0..20).collect::<Vec<_>>()
    );
    shovel.stop().await;
    let _ = std::fs::remove_dir_all(&dir);
}

/// `src-delete-after`: a shovel forwards exactly the count it was given
/// (or the source's length when it started) under each ack mode, leaves
/// the rest at the source (none taken beyond the count, even under
/// no-ack), and ends `completed`; `dest-publish-properties` are set over
/// each forwarded message's own.
#[both_runtimes]
async fn a_shovel_forwards_its_count_and_completes() {
    let robot = Arc::new(Broker::builder().start().await.expect("robot broker"));
    let (_local, publisher) = local_channel(&robot).await;
    publisher.confirm_select().await.expect("confirms");
    declare(&publisher, "telemetry", FieldTable::new()).await;
    let addr = reserved_addr();
    let dir = scratch("delete-after");
    let fleet_uri = format!("amqp://guest:guest@{addr}/%2f");
    let _fleet = fleet(addr, &dir).await;
    let (_c, fleet_channel) = channel_to(&fleet_uri).await;
    declare(&fleet_channel, "archive", FieldTable::new()).await;
    let mut next = 0;
    for (ack_mode, delete_after, expected) in [
        ("on-confirm", json!(7), 7),
        ("on-publish", json!(5), 5),
        ("no-ack", json!(3), 3),
        ("on-confirm", json!("queue-length"), 30 - 7 - 5 - 3),
    ] {
        if next == 0 {
            publish_confirmed(&publisher, "", "telemetry", 0, 30).await;
        }
        let config = shovel_config(
            std::slice::from_ref(&fleet_uri),
            json!({
                "dest-queue": "archive", "ack-mode": ack_mode, "src-delete-after": delete_after,
                "dest-publish-properties": {"app_id": "robot-7", "delivery_mode": 2},
            }),
        );
        let shovel = Shovel::start("once", config, Some(&robot));
        wait_status(&shovel, "completed", |s| s.completed).await;
        let status = shovel.status();
        assert_eq!(status.forwarded, expected, "{ack_mode}: {status:?}");
        assert_eq!(status.state, ShovelState::Terminated);
        let got = collect(&fleet_channel, "archive", expected as usize).await;
        assert_eq!(
            got,
            (next..next + expected as u32).collect::<Vec<_>>(),
            "{ack_mode}"
        );
        next += expected as u32;
        assert_eq!(held_at_source(&robot), u64::from(30 - next), "{ack_mode}");
        shovel.stop().await;
    }
    // The properties were set on each message (checked on one more).
    publish_confirmed(&publisher, "", "telemetry", 100, 101).await;
    let config = shovel_config(
        std::slice::from_ref(&fleet_uri),
        json!({
            "dest-queue": "archive", "src-delete-after": 1,
            "dest-publish-properties": {"app_id": "robot-7", "priority": 3},
        }),
    );
    let shovel = Shovel::start("props", config, Some(&robot));
    wait_status(&shovel, "completed", |s| s.completed).await;
    let message = loop {
        if let Some(message) = fleet_channel
            .basic_get("archive", BasicGetOptions { no_ack: true })
            .await
            .expect("get")
        {
            break message;
        }
        tokio::time::sleep(Duration::from_millis(20)).await;
    };
    assert_eq!(message.body.as_ref(), b"100");
    let properties = &message.properties;
    assert_eq!(
        properties.app_id.as_ref().map(|s| s.as_bytes()),
        Some(&b"robot-7"[..])
    );
    assert_eq!(properties.priority, Some(3));
    assert_eq!(properties.delivery_mode, Some(2), "the message's own, kept");
    assert!(
        properties
            .headers
            .as_ref()
            .is_some_and(|h| h.get(leveret_uplink::SEQ_HEADER).is_some()),
        "the shovel's id header is still added"
    );
    shovel.stop().await;
    let _ = std::fs::remove_dir_all(&dir);
}

/// The header of `name` on a message, as text.
fn header(properties: &BasicProperties, name: &str) -> Option<String> {
    let value = properties.headers.as_ref()?.get(name)?;
    Some(String::from_utf8_lossy(value.as_bytes()?).into_owned())
}

/// Consumes `count` messages from `queue` asking for positions; acks
/// those after the first `keep` (the others stay unacknowledged); their
/// positions in order.
async fn positions(channel: &Channel, queue: &str, count: usize, keep: usize) -> Vec<String> {
    let mut wants = FieldTable::new();
    wants.insert(
        ShortStr::from_static(leveret_broker::POSITION_HEADER),
        FieldValue::Bool(true),
    );
    let mut consumer = channel
        .basic_consume(queue, "positions", Default::default(), wants)
        .await
        .expect("consume");
    let mut got = Vec::new();
    while got.len() < count {
        let delivery = tokio::time::timeout(WAIT, consumer.next())
            .await
            .expect("a delivery")
            .expect("open");
        got.push(
            header(&delivery.properties, leveret_broker::POSITION_HEADER).expect("a position"),
        );
        if got.len() > keep {
            delivery.ack().await.expect("ack");
        }
    }
    got
}

/// A queue position names one message for the store's whole life: the
/// same message keeps it when delivered again, after a requeue and after a
/// restart, and no later message, in this run or the next, gets one used
/// before (so a shovel's downstream can deduplicate by it). A consumer
/// that does not ask sees no header; a bad argument is refused.
#[both_runtimes]
async fn positions_name_one_message_across_restarts() {
    let dir = scratch("positions");
    let start = || Broker::builder().data_dir(&dir).start();
    let robot = Arc::new(start().await.expect("robot broker"));
    let (connection, publisher) = local_channel(&robot).await;
    publisher.confirm_select().await.expect("confirms");
    declare(&publisher, "telemetry", FieldTable::new()).await;
    // Four messages: the last two acknowledged (gone), the first two held.
    publish_confirmed(&publisher, "", "telemetry", 0, 4).await;
    let first = positions(&publisher, "telemetry", 4, 2).await;
    let distinct: std::collections::HashSet<_> = first.iter().collect();
    assert_eq!(distinct.len(), 4, "{first:?}");
    drop(publisher);
    drop(connection);
    Arc::into_inner(robot)
        .expect("the only handle")
        .shutdown()
        .await;

    let robot = Arc::new(start().await.expect("robot broker again"));
    let (_connection, channel) = local_channel(&robot).await;
    channel.confirm_select().await.expect("confirms");
    assert_eq!(
        positions(&channel, "telemetry", 2, 2).await,
        first[..2],
        "the same messages, the same positions"
    );
    let plain = channel
        .basic_get("telemetry", BasicGetOptions { no_ack: false })
        .await
        .expect("get");
    assert!(plain.is_none(), "both are held by the consumer");
    let (_c2, other) = local_channel(&robot).await;
    other.confirm_select().await.expect("confirms");
    publish_confirmed(&other, "", "telemetry", 4, 6).await;
    let later = positions(&other, "telemetry", 2, 2).await;
    for position in &later {
        assert!(!first.contains(position), "{position} was used before");
    }
    let mut bad = FieldTable::new();
    bad.insert(
        ShortStr::from_static(leveret_broker::POSITION_HEADER),
        FieldValue::string("yes"),
    );
    let refused = other
        .basic_consume("telemetry", "bad", Default::default(), bad)
        .await
        .expect_err("not a boolean");
    assert!(refused.to_string().contains("406"), "{refused}");
    drop(channel);
    Arc::into_inner(robot)
        .expect("the only handle")
        .shutdown()
        .await;
    let _ = std::fs::remove_dir_all(&dir);
}

/// A message whose confirm a cut link lost is forwarded again on the next
/// link, with the same `x-leveret-seq` (its source position), so the
/// client's `Dedupe` keeps one copy, although it has no message-id.
#[both_runtimes]
async fn a_message_forwarded_twice_carries_one_id() {
    let robot = Arc::new(Broker::builder().start().await.expect("robot broker"));
    let (_local, publisher) = local_channel(&robot).await;
    publisher.confirm_select().await.expect("confirms");
    declare(&publisher, "telemetry", FieldTable::new()).await;
    let addr = reserved_addr();
    let dir = scratch("twice");
    let fleet_broker = fleet(addr, &dir).await;
    let fleet_uri = format!("amqp://guest:guest@{addr}/%2f");
    let (_c, fleet_channel) = channel_to(&fleet_uri).await;
    declare(&fleet_channel, "archive", FieldTable::new()).await;
    let proxy = leveret_tests::fault_proxy::FaultProxy::start(addr).await;
    let shovel = Shovel::start(
        "twice",
        shovel_config(
            &[format!("amqp://guest:guest@{}/%2f", proxy.addr)],
            json!({"dest-queue": "archive"}),
        ),
        Some(&robot),
    );
    wait_status(&shovel, "running", |s| s.state == ShovelState::Running).await;
    // Each chunk now waits this long each way: the message reaches the
    // fleet after it, and the fleet's confirm would come back after it
    // again, time enough for this test to cut the link first however
    // loaded the machine.
    proxy.set(|f| f.latency = Duration::from_secs(10));
    publish_confirmed(&publisher, "", "telemetry", 0, 1).await;
    // The fleet has it; its confirm is seconds away: cut the link now.
    let deadline = tokio::time::Instant::now() + WAIT;
    while fleet_broker
        .queues()
        .iter()
        .find(|q| q.name == "archive")
        .is_none_or(|q| q.messages_ready == 0)
    {
        assert!(tokio::time::Instant::now() < deadline, "never arrived");
        tokio::time::sleep(Duration::from_millis(5)).await;
    }
    proxy.set(|f| f.latency = Duration::ZERO);
    assert!(proxy.cut() > 0);
    wait_status(&shovel, "forwarded again", |s| s.forwarded >= 1).await;
    assert!(shovel.status().restarts >= 1);
    let mut copies = Vec::new();
    let deadline = tokio::time::Instant::now() + WAIT;
    while copies.len() < 2 {
        assert!(
            tokio::time::Instant::now() < deadline,
            "{} copies arrived",
            copies.len()
        );
        if let Some(message) = fleet_channel
            .basic_get("archive", BasicGetOptions { no_ack: true })
            .await
            .expect("get")
        {
            copies.push(message);
        } else {
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
    }
    let ids: Vec<_> = copies
        .iter()
        .map(|m| header(&m.properties, leveret_uplink::SEQ_HEADER).expect("an id"))
        .collect();
    assert_eq!(ids[0], ids[1], "one message, one id");
    assert!(copies[0].properties.message_id.is_none());
    let mut dedupe = leveret_client::Dedupe::new(16);
    assert!(dedupe.first_time(&copies[0].properties));
    assert!(
        !dedupe.first_time(&copies[1].properties),
        "the second copy is dropped"
    );
    shovel.stop().await;
    fleet_broker.shutdown().await;
    let _ = std::fs::remove_dir_all(&dir);
}

/// The robot's own bound while the link is down: a source queue with
/// `x-max-length` and `overflow: reject-publish` takes what fits, nacks
/// the rest to the publisher (who knows exactly what will not be
/// forwarded), and everything it confirmed is forwarded, in order, when
/// the link returns; with `drop-head` the newest messages are kept and
/// forwarded instead.
#[both_runtimes]
async fn the_local_bound_and_its_overflow_policy_hold_across_an_outage() {
    for (overflow, kept) in [("reject-publish", 0..100u32), ("drop-head", 50..150u32)] {
        let robot = Arc::new(Broker::builder().start().await.expect("robot broker"));
        let (_local, publisher) = local_channel(&robot).await;
        publisher.confirm_select().await.expect("confirms");
        let mut bound = FieldTable::new();
        bound.insert(ShortStr::from_static("x-max-length"), FieldValue::I64(100));
        bound.insert(
            ShortStr::from_static("x-overflow"),
            FieldValue::string(overflow),
        );
        declare(&publisher, "telemetry", bound).await;
        // The fleet's queue exists before the outage (declared after it,
        // the shovel could forward part of the backlog before the queue
        // is there, and those returned messages would come after the
        // rest); then the link is down: the fleet broker is away.
        let addr = reserved_addr();
        let dir = scratch(&format!("bound-{overflow}"));
        let fleet_uri = format!("amqp://guest:guest@{addr}/%2f");
        {
            let fleet_broker = fleet(addr, &dir).await;
            let (_c, ch) = channel_to(&fleet_uri).await;
            declare(&ch, "fleet.telemetry", FieldTable::new()).await;
            fleet_broker.shutdown().await;
        }
        let shovel = Shovel::start(
            "up",
            shovel_config(
                std::slice::from_ref(&fleet_uri),
                json!({"dest-queue": "fleet.telemetry"}),
            ),
            Some(&robot),
        );
        let mut nacked = Vec::new();
        for n in 0..150u32 {
            let confirm = publisher
                .basic_publish(
                    "",
                    "telemetry",
                    BasicPublishOptions::default(),
                    BasicProperties {
                        delivery_mode: Some(2),
                        ..Default::default()
                    },
                    n.to_string().into_bytes().into(),
                )
                .await
                .expect("publish");
            if !confirm.await.expect("confirm").is_ack() {
                nacked.push(n);
            }
        }
        match overflow {
            "reject-publish" => assert_eq!(nacked, (100..150).collect::<Vec<_>>()),
            _ => assert!(nacked.is_empty(), "drop-head takes every publish"),
        }
        assert_eq!(held_at_source(&robot), 100, "{overflow}: the bound holds");
        let fleet_broker = fleet(addr, &dir).await;
        let (_c, ch) = channel_to(&fleet_uri).await;
        wait_status(&shovel, "the backlog forwarded", |s| s.forwarded >= 100).await;
        let got = collect(&ch, "fleet.telemetry", 100).await;
        assert_eq!(got, kept.collect::<Vec<_>>(), "{overflow}");
        shovel.stop().await;
        fleet_broker.shutdown().await;
        let _ = std::fs::remove_dir_all(&dir);
    }
}

/// Messages in all the robot's queues, ready or unacknowledged.
fn held_anywhere(robot: &BrokerHandle) -> u64 {
    robot
        .queues()
        .iter()
        .map(|q| q.messages_ready + q.messages_unacknowledged)
        .sum()
}

/// Messages the shovels moved, summed.
fn moved(shovels: &[&Shovel]) -> u64 {
    shovels.iter().map(|s| s.status().forwarded).sum()
}

/// Waits until `moved` has not changed for half a second, then checks it
/// stays put for one more second: the loop has stopped moving messages
/// (before loops were caught, 10 messages went round for ever, hundreds
/// of thousands of moves a minute on a core).
async fn settled_moves(shovels: &[&Shovel]) -> u64 {
    let deadline = tokio::time::Instant::now() + WAIT;
    let mut last = moved(shovels);
    loop {
        tokio::time::sleep(Duration::from_millis(500)).await;
        let now = moved(shovels);
        if now == last {
            break;
        }
        assert!(
            tokio::time::Instant::now() < deadline,
            "still moving after {WAIT:?}: {now} moves"
        );
        last = now;
    }
    tokio::time::sleep(Duration::from_secs(1)).await;
    assert_eq!(moved(shovels), last, "the loop moves messages again");
    last
}

/// Two shovels in a loop (a → b, b → a) on one broker, which no check at
/// declaration can see: each message goes round once, then the shovel it
/// already passed drops it (acknowledged, counted, logged) instead of
/// forwarding it again for ever.
#[both_runtimes]
async fn two_shovels_in_a_loop_stop_after_one_round() {
    let robot = Arc::new(Broker::builder().start().await.expect("robot broker"));
    let (_local, publisher) = local_channel(&robot).await;
    publisher.confirm_select().await.expect("confirms");
    declare(&publisher, "loop.a", FieldTable::new()).await;
    declare(&publisher, "loop.b", FieldTable::new()).await;
    let one_way = |from: &str, to: &str| {
        ShovelConfig::from_json(&json!({
            "src-uri": "amqp://", "src-queue": from, "dest-uri": "amqp://", "dest-queue": to,
            "reconnect-delay": 0.1,
        }))
        .expect("valid parameters")
    };
    let there = Shovel::start("there", one_way("loop.a", "loop.b"), Some(&robot));
    let back = Shovel::start("back", one_way("loop.b", "loop.a"), Some(&robot));
    publish_confirmed(&publisher, "", "loop.a", 0, 10).await;
    let moves = settled_moves(&[&there, &back]).await;
    assert_eq!(moves, 20, "each message went a → b → a once");
    wait_status(&there, "10 looped messages dropped", |s| {
        s.dropped_loops == 10
    })
    .await;
    assert_eq!(back.status().dropped_loops, 0);
    assert_eq!(
        held_anywhere(&robot),
        0,
        "the dropped messages were acknowledged"
    );
    there.stop().await;
    back.stop().await;
}

/// One shovel whose destination routes back into its source through an
/// exchange (not a queue-to-itself declaration, which is refused): each
/// message is forwarded once, then dropped when it comes back.
#[both_runtimes]
async fn a_shovel_into_its_own_source_through_an_exchange_forwards_once() {
    let robot = Arc::new(Broker::builder().start().await.expect("robot broker"));
    let (_local, publisher) = local_channel(&robot).await;
    publisher.confirm_select().await.expect("confirms");
    declare(&publisher, "circle", FieldTable::new()).await;
    publisher
        .queue_bind(
            "circle",
            "amq.direct",
            "circle",
            Default::default(),
            FieldTable::new(),
        )
        .await
        .expect("bind");
    let config = ShovelConfig::from_json(&json!({
        "src-uri": "amqp://", "src-queue": "circle", "dest-uri": "amqp://",
        "dest-exchange": "amq.direct", "dest-exchange-key": "circle", "reconnect-delay": 0.1,
        "dest-publish-properties": {"headers": {"replaced": "yes"}},
    }))
    .expect("not detectable at declaration");
    let shovel = Shovel::start("circle", config, Some(&robot));
    publish_confirmed(&publisher, "", "circle", 0, 10).await;
    let moves = settled_moves(&[&shovel]).await;
    assert_eq!(moves, 10, "each message forwarded once");
    wait_status(&shovel, "10 looped messages dropped", |s| {
        s.dropped_loops == 10
    })
    .await;
    assert_eq!(held_anywhere(&robot), 0);
    shovel.stop().await;
}
