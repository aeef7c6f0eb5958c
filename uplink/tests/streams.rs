//! Streams at either end of the uplink, between Leveret brokers on both
//! runtimes: a shovel reading a stream from `first` and from an absolute
//! offset (`src-consumer-args`), every message once and in order with its
//! `x-stream-offset`; what it does after a lost link (reads again from the
//! configured offset, as RabbitMQ's shovel does, with the same
//! `x-leveret-seq` ids) and when the destination refuses (nothing nacked,
//! the stream keeps it); consumer arguments the source refuses (a clear
//! `last_error`, nothing forwarded); a shovel into a stream; a federated
//! exchange feeding a stream. And against a real RabbitMQ 3.10 node: its
//! stream shovelled down from an offset, and shovelled into (skips
//! loudly outside CI when rabbitmq-server is not installed).

mod common;

use common::*;
use leveret_broker::{Broker, BrokerHandle};
use leveret_client::{
    BasicAckOptions, BasicConsumeOptions, BasicGetOptions, BasicProperties, BasicQosOptions,
    Channel, Dedupe, Delivery, ExchangeDeclareOptions, FieldTable, FieldValue, GetMessage,
    QueueBindOptions, QueueDeclareOptions, ShortStr,
};
use leveret_test_macros::both_runtimes;
use leveret_tests::rabbit_node::{self, RabbitNode};
use leveret_tests::reserved_port::reserved_addr;
use leveret_uplink::{
    FederationLink, LinkState, LocalExchange, Shovel, ShovelConfig, ShovelState, UpstreamConfig,
    RECEIVED_FROM, SEQ_HEADER,
};
use serde_json::json;
use std::net::SocketAddr;
use std::path::Path;
use std::sync::Arc;
use std::time::Duration;

/// A broker keeping its data (streams need it) in `dir`, listening on
/// `addr` if given.
async fn broker(dir: &Path, addr: Option<SocketAddr>) -> BrokerHandle {
    let builder = Broker::builder().data_dir(dir);
    let builder = match addr {
        Some(addr) => builder.listen(addr),
        None => builder,
    };
    builder.start().await.expect("broker")
}

fn table(entries: &[(&'static str, FieldValue)]) -> FieldTable {
    let mut table = FieldTable::new();
    for (key, value) in entries {
        table.insert(ShortStr::from_static(key), value.clone());
    }
    table
}

async fn declare_stream(channel: &Channel, stream: &str) {
    let arguments = table(&[("x-queue-type", FieldValue::string("stream"))]);
    declare(channel, stream, arguments).await;
}

fn number(body: &[u8]) -> u32 {
    String::from_utf8_lossy(body).parse().expect("a number")
}

fn header<'a>(properties: &'a BasicProperties, name: &str) -> Option<&'a FieldValue> {
    properties.headers.as_ref()?.get(name)
}

fn stream_offset(properties: &BasicProperties) -> i64 {
    header(properties, "x-stream-offset")
        .and_then(FieldValue::as_i64)
        .unwrap_or_else(|| panic!("no x-stream-offset: {properties:?}"))
}

fn seq(properties: &BasicProperties) -> String {
    let value = header(properties, SEQ_HEADER).and_then(FieldValue::as_bytes);
    String::from_utf8_lossy(value.expect("x-leveret-seq")).into_owned()
}

/// Takes `count` messages from `queue` (waiting for them), then checks
/// that no more come within a short while.
async fn take(channel: &Channel, queue: &str, count: usize) -> Vec<GetMessage> {
    let mut got = Vec::new();
    let deadline = tokio::time::Instant::now() + WAIT;
    while got.len() < count {
        assert!(
            tokio::time::Instant::now() < deadline,
            "{} of {count} in {queue}",
            got.len()
        );
        match channel
            .basic_get(queue, BasicGetOptions { no_ack: true })
            .await
            .expect("get")
        {
            Some(message) => got.push(message),
            None => tokio::time::sleep(Duration::from_millis(20)).await,
        }
    }
    tokio::time::sleep(Duration::from_millis(200)).await;
    let more = channel
        .basic_get(queue, BasicGetOptions { no_ack: true })
        .await
        .expect("get");
    assert!(
        more.is_none(),
        "more than {count} in {queue}: {:?}",
        more.map(|m| m.body.clone())
    );
    got
}

/// Reads `count` records of `stream` from `offset`, acknowledging each.
async fn read_stream(
    channel: &Channel,
    stream: &str,
    offset: FieldValue,
    count: usize,
) -> Vec<Delivery> {
    channel
        .basic_qos(100, BasicQosOptions::default())
        .await
        .expect("qos");
    let mut consumer = channel
        .basic_consume(
            stream,
            "",
            BasicConsumeOptions::default(),
            table(&[("x-stream-offset", offset)]),
        )
        .await
        .expect("consume the stream");
    let mut got = Vec::new();
    while got.len() < count {
        let delivery = tokio::time::timeout(WAIT, consumer.next())
            .await
            .unwrap_or_else(|_| panic!("{} of {count} from {stream}", got.len()))
            .expect("consumer open");
        channel
            .basic_ack(delivery.delivery_tag, BasicAckOptions::default())
            .await
            .expect("ack");
        got.push(delivery);
    }
    got
}

fn shovel_config(value: serde_json::Value) -> ShovelConfig {
    ShovelConfig::from_json(&value).expect("valid parameters")
}

/// `got` is `from..from + got.len()` in order, each with its body's
/// number as its `x-stream-offset` and the shovel's stable id.
fn assert_stream_order(got: &[GetMessage], from: u32, shovel: &str) {
    for (i, message) in got.iter().enumerate() {
        let n = from + i as u32;
        assert_eq!(number(&message.body), n, "in order, each once");
        let properties = &message.delivery.properties;
        assert_eq!(stream_offset(properties), i64::from(n));
        assert_eq!(seq(properties), format!("{shovel}:log@{n}"));
    }
}

#[both_runtimes]
async fn a_stream_is_shovelled_from_first_and_from_an_offset_and_read_again_after_a_lost_link() {
    let dir = scratch("from-offsets");
    let robot = Arc::new(broker(&dir.join("robot"), None).await);
    let (_local, publisher) = local_channel(&robot).await;
    publisher.confirm_select().await.expect("confirms");
    declare_stream(&publisher, "log").await;
    publish_confirmed(&publisher, "", "log", 0, 1000).await;

    let addr = reserved_addr();
    let fleet_uri = format!("amqp://guest:guest@{addr}/%2f");
    let fleet = broker(&dir.join("fleet"), Some(addr)).await;
    let (_fleet_conn, fleet_ch) = channel_to(&fleet_uri).await;
    declare(&fleet_ch, "from-first", FieldTable::new()).await;
    declare(&fleet_ch, "from-500", FieldTable::new()).await;

    let from_first = shovel_config(json!({
        "src-uri": "amqp://", "src-queue": "log", "src-prefetch-count": 100,
        "src-consumer-args": {"x-stream-offset": "first"},
        "dest-uri": fleet_uri, "dest-queue": "from-first", "reconnect-delay": 0.1,
    }));
    let first = Shovel::start("first", from_first, Some(&robot));
    let from_500 = shovel_config(json!({
        "src-uri": "amqp://", "src-queue": "log", "src-prefetch-count": 64,
        "src-consumer-args": {"x-stream-offset": 500}, "ack-mode": "on-publish",
        "dest-uri": fleet_uri, "dest-queue": "from-500", "reconnect-delay": 0.1,
    }));
    let at_500 = Shovel::start("at-500", from_500, Some(&robot));
    wait_status(&first, "1000 forwarded", |s| s.forwarded >= 1000).await;
    wait_status(&at_500, "500 forwarded", |s| s.forwarded >= 500).await;
    let got = take(&fleet_ch, "from-first", 1000).await;
    assert_stream_order(&got, 0, "first");
    let got = take(&fleet_ch, "from-500", 500).await;
    assert_stream_order(&got, 500, "at-500");
    assert_eq!(first.status().forwarded, 1000);
    assert_eq!(at_500.status().forwarded, 500);
    assert_eq!(first.status().restarts, 0);
    at_500.stop().await;
    let mut dedupe = Dedupe::new(4096);
    for message in &got {
        assert!(dedupe.first_time(&message.delivery.properties));
    }

    // New records follow.
    publish_confirmed(&publisher, "", "log", 1000, 1010).await;
    let got = take(&fleet_ch, "from-first", 10).await;
    assert_stream_order(&got, 1000, "first");

    // The link lost: the next one reads from the configured offset again,
    // as RabbitMQ's shovel does, and the re-reads carry the same ids.
    drop(fleet_ch);
    drop(_fleet_conn);
    fleet.shutdown().await;
    wait_status(&first, "the loss noticed", |s| {
        s.state != ShovelState::Running
    })
    .await;
    let fleet = broker(&dir.join("fleet"), Some(addr)).await;
    wait_status(&first, "all forwarded again", |s| s.forwarded >= 2020).await;
    let (_fleet_conn, fleet_ch) = channel_to(&fleet_uri).await;
    let got = take(&fleet_ch, "from-first", 1010).await;
    assert_stream_order(&got, 0, "first");
    let mut dedupe = Dedupe::new(4096);
    let firsts = got
        .iter()
        .filter(|m| dedupe.first_time(&m.delivery.properties))
        .count();
    assert_eq!(firsts, 1010);
    assert!(
        got.iter()
            .all(|m| !dedupe.first_time(&m.delivery.properties)),
        "a second read of the same records is dropped by its ids"
    );
    first.stop().await;
    drop(publisher);
    drop(_local);
    Arc::try_unwrap(robot)
        .unwrap_or_else(|_| panic!("robot still shared"))
        .shutdown()
        .await;
    fleet.shutdown().await;
    let _ = std::fs::remove_dir_all(&dir);
}

#[both_runtimes]
async fn a_refusing_destination_leaves_the_stream_whole_and_the_next_link_offers_it_again() {
    let dir = scratch("refused");
    let robot = Arc::new(broker(&dir.join("robot"), None).await);
    let (_local, publisher) = local_channel(&robot).await;
    publisher.confirm_select().await.expect("confirms");
    declare_stream(&publisher, "log").await;
    publish_confirmed(&publisher, "", "log", 0, 30).await;
    let fleet = broker(&dir.join("fleet"), Some("127.0.0.1:0".parse().unwrap())).await;
    let fleet_uri = format!("amqp://guest:guest@{}/%2f", fleet.local_addrs()[0]);
    let (_fleet_conn, fleet_ch) = channel_to(&fleet_uri).await;
    let full = table(&[
        ("x-max-length", FieldValue::I64(10)),
        ("x-overflow", FieldValue::string("reject-publish")),
    ]);
    declare(&fleet_ch, "small", full).await;
    let shovel = Shovel::start(
        "up",
        shovel_config(json!({
            "src-uri": "amqp://", "src-queue": "log", "src-prefetch-count": 5,
            "src-consumer-args": {"x-stream-offset": "first"},
            "dest-uri": fleet_uri, "dest-queue": "small", "reconnect-delay": 0.1,
        })),
        Some(&robot),
    );
    wait_status(&shovel, "a refusal", |s| {
        s.refused > 0 && s.last_error.is_some()
    })
    .await;
    let status = shovel.status();
    assert!(
        status
            .last_error
            .as_deref()
            .is_some_and(|e| e.contains("kept in the stream")),
        "{status:?}"
    );
    // A consumer on the destination lets the next links through: every
    // record arrives (with re-reads from `first`, which the ids tell
    // apart).
    let mut consumer = fleet_ch
        .basic_consume(
            "small",
            "",
            BasicConsumeOptions {
                no_ack: true,
                ..Default::default()
            },
            FieldTable::new(),
        )
        .await
        .expect("consume");
    let mut seen = std::collections::BTreeSet::new();
    while seen.len() < 30 {
        let delivery = tokio::time::timeout(WAIT, consumer.next())
            .await
            .unwrap_or_else(|_| panic!("{seen:?} and {:?}", shovel.status()))
            .expect("consumer open");
        let n = number(&delivery.body);
        assert_eq!(stream_offset(&delivery.properties), i64::from(n));
        assert_eq!(seq(&delivery.properties), format!("up:log@{n}"));
        seen.insert(n);
    }
    shovel.stop().await;
    // The stream still holds all 30: a refusal takes nothing from it.
    let (_reader, reader_ch) = local_channel(&robot).await;
    let all = read_stream(&reader_ch, "log", FieldValue::string("first"), 30).await;
    let bodies: Vec<u32> = all.iter().map(|d| number(&d.body)).collect();
    assert_eq!(bodies, (0..30).collect::<Vec<_>>());
    fleet.shutdown().await;
    let _ = std::fs::remove_dir_all(&dir);
}

#[both_runtimes]
async fn consumer_arguments_the_source_refuses_stop_the_link_with_the_reason() {
    let dir = scratch("source-refuses");
    let robot = Arc::new(broker(&dir.join("robot"), None).await);
    let (_local, publisher) = local_channel(&robot).await;
    publisher.confirm_select().await.expect("confirms");
    declare(&publisher, "classic", FieldTable::new()).await;
    declare_stream(&publisher, "log").await;
    publish_confirmed(&publisher, "", "classic", 0, 5).await;
    publish_confirmed(&publisher, "", "log", 0, 5).await;
    let fleet = broker(&dir.join("fleet"), Some("127.0.0.1:0".parse().unwrap())).await;
    let fleet_uri = format!("amqp://guest:guest@{}/%2f", fleet.local_addrs()[0]);
    let (_fleet_conn, fleet_ch) = channel_to(&fleet_uri).await;
    declare(&fleet_ch, "in", FieldTable::new()).await;
    for (source, more, reason) in [
        // A stream offset on a classic queue: RabbitMQ's 406.
        (
            "classic",
            json!({"src-consumer-args": {"x-stream-offset": "first"}}),
            "invalid arg 'x-stream-offset'",
        ),
        // A stream read without acknowledgements: refused by the stream.
        (
            "log",
            json!({"ack-mode": "no-ack"}),
            "automatic acknowledgement not supported by stream queues",
        ),
        // A consumer priority on a stream: RabbitMQ's 406.
        (
            "log",
            json!({"src-consumer-args": {"x-priority": 3}}),
            "invalid arg 'x-priority'",
        ),
    ] {
        let mut value = json!({
            "src-uri": "amqp://", "src-queue": source,
            "dest-uri": fleet_uri, "dest-queue": "in", "reconnect-delay": 0.1,
        });
        value
            .as_object_mut()
            .unwrap()
            .extend(more.as_object().unwrap().clone());
        let shovel = Shovel::start("refused", shovel_config(value), Some(&robot));
        wait_status(&shovel, "the reason", |s| {
            s.last_error.as_deref().is_some_and(|e| e.contains(reason))
        })
        .await;
        let status = shovel.status();
        assert_ne!(status.state, ShovelState::Running, "{status:?}");
        assert_eq!(status.forwarded, 0, "{status:?}");
        shovel.stop().await;
    }
    assert!(fleet_ch
        .basic_get("in", BasicGetOptions { no_ack: true })
        .await
        .expect("get")
        .is_none());
    let kept = publisher
        .queue_declare(
            "classic",
            QueueDeclareOptions {
                passive: true,
                ..Default::default()
            },
            FieldTable::new(),
        )
        .await
        .expect("passive");
    assert_eq!(kept.message_count, 5, "the classic queue kept its messages");
    fleet.shutdown().await;
    let _ = std::fs::remove_dir_all(&dir);
}

#[both_runtimes]
async fn a_shovel_delivers_into_a_stream_with_the_streams_own_offsets() {
    let dir = scratch("into-stream");
    let robot = Arc::new(broker(&dir.join("robot"), None).await);
    let (_local, publisher) = local_channel(&robot).await;
    publisher.confirm_select().await.expect("confirms");
    declare(&publisher, "telemetry", FieldTable::new()).await;
    declare_stream(&publisher, "log").await;
    let fleet = broker(&dir.join("fleet"), Some("127.0.0.1:0".parse().unwrap())).await;
    let fleet_uri = format!("amqp://guest:guest@{}/%2f", fleet.local_addrs()[0]);
    let (_fleet_conn, fleet_ch) = channel_to(&fleet_uri).await;
    declare_stream(&fleet_ch, "recorder").await;
    declare_stream(&fleet_ch, "replica").await;

    // A classic queue into a stream.
    publish_confirmed(&publisher, "", "telemetry", 0, 300).await;
    let up = Shovel::start(
        "up",
        shovel_config(json!({
            "src-uri": "amqp://", "src-queue": "telemetry", "src-prefetch-count": 50,
            "dest-uri": fleet_uri, "dest-queue": "recorder", "reconnect-delay": 0.1,
        })),
        Some(&robot),
    );
    wait_status(&up, "300 forwarded", |s| s.forwarded >= 300).await;
    let recorded = read_stream(&fleet_ch, "recorder", FieldValue::string("first"), 300).await;
    for (i, delivery) in recorded.iter().enumerate() {
        assert_eq!(number(&delivery.body), i as u32, "in order");
        assert_eq!(stream_offset(&delivery.properties), i as i64);
    }
    up.stop().await;

    // A stream from offset 100 into another stream: the destination's
    // deliveries carry its own offsets, not the source's.
    publish_confirmed(&publisher, "", "log", 0, 200).await;
    let replica = Shovel::start(
        "replica",
        shovel_config(json!({
            "src-uri": "amqp://", "src-queue": "log",
            "src-consumer-args": {"x-stream-offset": 100},
            "dest-uri": fleet_uri, "dest-queue": "replica", "reconnect-delay": 0.1,
        })),
        Some(&robot),
    );
    wait_status(&replica, "100 forwarded", |s| s.forwarded >= 100).await;
    let (_c, replica_ch) = channel_to(&fleet_uri).await;
    let copied = read_stream(&replica_ch, "replica", FieldValue::string("first"), 100).await;
    for (i, delivery) in copied.iter().enumerate() {
        assert_eq!(number(&delivery.body), 100 + i as u32, "in order");
        assert_eq!(stream_offset(&delivery.properties), i as i64);
        assert_eq!(
            seq(&delivery.properties),
            format!("replica:log@{}", 100 + i)
        );
    }
    assert_eq!(replica.status().forwarded, 100);
    replica.stop().await;
    fleet.shutdown().await;
    let _ = std::fs::remove_dir_all(&dir);
}

#[both_runtimes]
async fn a_federated_exchange_feeds_a_stream_downstream() {
    let dir = scratch("federated");
    let upstream = broker(&dir.join("fleet"), Some("127.0.0.1:0".parse().unwrap())).await;
    let upstream_uri = format!("amqp://guest:guest@{}/%2f", upstream.local_addrs()[0]);
    let (_fleet_conn, fleet_ch) = channel_to(&upstream_uri).await;
    fleet_ch.confirm_select().await.expect("confirms");
    let durable = ExchangeDeclareOptions {
        durable: true,
        ..Default::default()
    };
    fleet_ch
        .exchange_declare("fleet.maps", "topic", durable, FieldTable::new())
        .await
        .expect("upstream exchange");

    let robot = Arc::new(broker(&dir.join("robot"), None).await);
    let (_local, channel) = local_channel(&robot).await;
    channel
        .exchange_declare("maps", "topic", durable, FieldTable::new())
        .await
        .expect("local exchange");
    declare_stream(&channel, "maps.recorded").await;
    channel
        .queue_bind(
            "maps.recorded",
            "maps",
            "site-3.#",
            QueueBindOptions::default(),
            FieldTable::new(),
        )
        .await
        .expect("bind the stream");
    let config = UpstreamConfig::from_json(&json!({
        "uri": upstream_uri, "exchange": "fleet.maps", "reconnect-delay": 0.2,
    }))
    .expect("upstream parameters");
    let target = LocalExchange {
        vhost: "/".into(),
        exchange: "maps".into(),
        node: "leveret@robot-7".into(),
    };
    let link = FederationLink::start("fleet", config, target, &robot);
    let mut watch = link.watch();
    tokio::time::timeout(
        WAIT,
        watch.wait_for(|s| s.state == LinkState::Running && s.bindings == 1),
    )
    .await
    .unwrap_or_else(|_| panic!("the link running: {:?}", link.status()))
    .expect("link alive");

    publish_confirmed(&fleet_ch, "fleet.maps", "site-9.tile", 0, 5).await;
    publish_confirmed(&fleet_ch, "fleet.maps", "site-3.tile", 0, 200).await;
    let recorded = read_stream(&channel, "maps.recorded", FieldValue::string("first"), 200).await;
    for (i, delivery) in recorded.iter().enumerate() {
        assert_eq!(number(&delivery.body), i as u32, "in order, site 3 only");
        assert_eq!(stream_offset(&delivery.properties), i as i64);
        assert_eq!(delivery.routing_key.as_bytes(), b"site-3.tile");
        assert!(
            matches!(header(&delivery.properties, RECEIVED_FROM), Some(FieldValue::Array(hops)) if hops.len() == 1),
            "{:?}",
            delivery.properties
        );
    }
    let mut watch = link.watch();
    tokio::time::timeout(WAIT, watch.wait_for(|s| s.forwarded >= 200))
        .await
        .unwrap_or_else(|_| panic!("200 counted: {:?}", link.status()))
        .expect("link alive");
    link.stop().await;
    upstream.shutdown().await;
    let _ = std::fs::remove_dir_all(&dir);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_rabbitmq_stream_is_shovelled_down_from_an_offset_and_into() {
    if !rabbit_node::installed() {
        return;
    }
    let dir = scratch("rabbitmq");
    let home = dir.clone();
    let node = tokio::task::spawn_blocking(move || {
        RabbitNode::start("streams", &home.join("node"), &home)
    })
    .await
    .expect("node");
    let (_fleet_conn, fleet_ch) = channel_to(&node.uri()).await;
    fleet_ch.confirm_select().await.expect("confirms");
    declare_stream(&fleet_ch, "fleet.log").await;
    declare_stream(&fleet_ch, "fleet.recorder").await;
    publish_confirmed(&fleet_ch, "", "fleet.log", 0, 100).await;

    let robot = Arc::new(broker(&dir.join("robot"), None).await);
    let (_local, channel) = local_channel(&robot).await;
    channel.confirm_select().await.expect("confirms");
    declare(&channel, "down", FieldTable::new()).await;
    declare(&channel, "telemetry", FieldTable::new()).await;
    let down = Shovel::start(
        "down",
        shovel_config(json!({
            "src-uri": node.uri(), "src-queue": "fleet.log", "src-prefetch-count": 16,
            "src-consumer-args": {"x-stream-offset": 40},
            "dest-uri": "amqp://", "dest-queue": "down", "reconnect-delay": 0.2,
        })),
        Some(&robot),
    );
    wait_status(&down, "60 forwarded", |s| s.forwarded >= 60).await;
    let got = take(&channel, "down", 60).await;
    for (i, message) in got.iter().enumerate() {
        let n = 40 + i as u32;
        assert_eq!(
            number(&message.body),
            n,
            "from offset 40, in order, each once"
        );
        let properties = &message.delivery.properties;
        assert_eq!(stream_offset(properties), i64::from(n));
        assert_eq!(seq(properties), format!("down:fleet.log@{n}"));
    }
    down.stop().await;

    publish_confirmed(&channel, "", "telemetry", 0, 50).await;
    let up = Shovel::start(
        "up",
        shovel_config(json!({
            "src-uri": "amqp://", "src-queue": "telemetry",
            "dest-uri": node.uri(), "dest-queue": "fleet.recorder", "reconnect-delay": 0.2,
        })),
        Some(&robot),
    );
    wait_status(&up, "50 forwarded", |s| s.forwarded >= 50).await;
    let recorded = read_stream(&fleet_ch, "fleet.recorder", FieldValue::string("first"), 50).await;
    for (i, delivery) in recorded.iter().enumerate() {
        assert_eq!(number(&delivery.body), i as u32, "in order");
        assert_eq!(stream_offset(&delivery.properties), i as i64);
    }
    up.stop().await;
    drop(node);
    let _ = std::fs::remove_dir_all(&dir);
}
