//! Federation downstream: a fleet exchange federated to the robot's own
//! exchange, against a real RabbitMQ 3.10 node (Debian's
//! `rabbitmq-server`, unprivileged, its own ports) and against a Leveret
//! upstream on both runtimes. What the robot's bindings want crosses the
//! link, and nothing else (binding propagation, kept in step as local
//! bindings come and go); each message arrives with its `x-received-from`
//! entry; messages past `max-hops` or back from this node are dropped;
//! what the fleet publishes while the link is down waits upstream and
//! arrives when it returns.
//!
//! The RabbitMQ test skips loudly outside CI when rabbitmq-server is not
//! installed; fails under CI (`.ci/run` installs it).

use leveret_broker::{Broker, BrokerHandle};
use leveret_client::{
    BasicGetOptions, BasicProperties, BasicPublishOptions, Channel, Connection,
    ExchangeDeclareOptions, FieldTable, FieldValue, QueueBindOptions, QueueDeclareOptions,
    ShortStr,
};
use leveret_test_macros::both_runtimes;
use leveret_tests::rabbit_node::{self, RabbitNode};
use leveret_uplink::{
    FederationLink, LinkState, LinkStatus, LocalExchange, UpstreamConfig, RECEIVED_FROM,
};
use serde_json::json;
use std::sync::Arc;
use std::time::Duration;

const WAIT: Duration = Duration::from_secs(30);
const NODE: &str = "leveret@robot-7";

async fn wait_status(link: &FederationLink, what: &str, done: impl Fn(&LinkStatus) -> bool) {
    let mut watch = link.watch();
    tokio::time::timeout(WAIT, watch.wait_for(|s| done(s)))
        .await
        .unwrap_or_else(|_| panic!("waited for {what}: {:?}", link.status()))
        .expect("link alive");
}

async fn publish(channel: &Channel, key: &str, body: &str, headers: Option<FieldTable>) {
    let properties = BasicProperties {
        headers,
        ..Default::default()
    };
    let confirm = channel
        .basic_publish(
            "fleet.commands",
            key,
            BasicPublishOptions::default(),
            properties,
            body.as_bytes().to_vec().into(),
        )
        .await
        .expect("publish");
    assert!(confirm.await.expect("confirm").is_ack());
}

/// The next message in the robot's queue (waiting for it), or `None`
/// after `patience` without one.
async fn next_local(channel: &Channel, patience: Duration) -> Option<leveret_client::GetMessage> {
    let deadline = tokio::time::Instant::now() + patience;
    loop {
        if let Some(message) = channel
            .basic_get("robot-7.commands", BasicGetOptions { no_ack: true })
            .await
            .expect("get")
        {
            return Some(message);
        }
        if tokio::time::Instant::now() > deadline {
            return None;
        }
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
}

fn text(message: &leveret_client::GetMessage) -> String {
    String::from_utf8_lossy(&message.body).into_owned()
}

/// `x-received-from` with one entry whose `cluster-name` is `cluster`.
fn hops(cluster: &str) -> FieldTable {
    let mut entry = FieldTable::new();
    entry.insert(
        ShortStr::from_static("cluster-name"),
        FieldValue::string(cluster),
    );
    let mut headers = FieldTable::new();
    headers.insert(
        ShortStr::from_static(RECEIVED_FROM),
        FieldValue::Array(vec![FieldValue::Table(entry)]),
    );
    headers
}

/// The scenario, against the upstream broker at `upstream_uri`.
async fn federate_from(upstream_uri: &str) {
    let fleet = Connection::connect(upstream_uri).await.expect("fleet");
    let fleet_channel = fleet.open_channel().await.expect("channel");
    fleet_channel.confirm_select().await.expect("confirms");
    fleet_channel
        .exchange_declare(
            "fleet.commands",
            "topic",
            ExchangeDeclareOptions {
                durable: true,
                ..Default::default()
            },
            FieldTable::new(),
        )
        .await
        .expect("upstream exchange");

    let robot: Arc<BrokerHandle> = Arc::new(Broker::builder().start().await.expect("robot"));
    let local = Connection::in_process(&robot).await.expect("in process");
    let channel = local.open_channel().await.expect("channel");
    channel
        .exchange_declare(
            "commands",
            "topic",
            ExchangeDeclareOptions::default(),
            FieldTable::new(),
        )
        .await
        .expect("local exchange");
    channel
        .queue_declare(
            "robot-7.commands",
            QueueDeclareOptions::default(),
            FieldTable::new(),
        )
        .await
        .expect("local queue");
    let bind = |key: &'static str| {
        let channel = channel.clone();
        async move {
            channel
                .queue_bind(
                    "robot-7.commands",
                    "commands",
                    key,
                    QueueBindOptions::default(),
                    FieldTable::new(),
                )
                .await
                .expect("bind")
        }
    };
    bind("robot-7.#").await;

    let config = UpstreamConfig::from_json(&json!({
        "uri": upstream_uri, "exchange": "fleet.commands", "expires": 600_000,
        "reconnect-delay": 0.2,
    }))
    .expect("upstream parameters");
    let target = LocalExchange {
        vhost: "/".into(),
        exchange: "commands".into(),
        node: NODE.into(),
    };
    let link = FederationLink::start("fleet", config.clone(), target.clone(), &robot);
    wait_status(&link, "running with one binding", |s| {
        s.state == LinkState::Running && s.bindings == 1
    })
    .await;

    publish(&fleet_channel, "robot-8.move", "not for robot 7", None).await;
    publish(&fleet_channel, "robot-7.move", "forward 1 m", None).await;
    let message = next_local(&channel, WAIT).await.expect("a command");
    assert_eq!(text(&message), "forward 1 m", "only what robot 7 binds");
    assert_eq!(message.delivery.routing_key.as_bytes(), b"robot-7.move");
    let received = message
        .delivery
        .properties
        .headers
        .as_ref()
        .and_then(|h| h.get(RECEIVED_FROM))
        .cloned();
    let Some(FieldValue::Array(entries)) = received else {
        panic!("no {RECEIVED_FROM}: {:?}", message.delivery.properties);
    };
    let FieldValue::Table(entry) = &entries[0] else {
        panic!("{entries:?}");
    };
    assert_eq!(entries.len(), 1);
    assert_eq!(
        entry.get("exchange").and_then(FieldValue::as_bytes),
        Some(&b"fleet.commands"[..])
    );
    assert_eq!(entry.get("redelivered"), Some(&FieldValue::Bool(false)));
    let uri = entry
        .get("uri")
        .and_then(FieldValue::as_bytes)
        .expect("uri");
    assert!(
        !String::from_utf8_lossy(uri).contains("guest:guest"),
        "no credentials in {uri:?}"
    );

    // A binding added on the robot crosses the link.
    bind("all.#").await;
    wait_status(&link, "two bindings", |s| s.bindings == 2).await;
    publish(&fleet_channel, "all.stop", "stop", None).await;
    assert_eq!(
        next_local(&channel, WAIT)
            .await
            .map(|m| text(&m))
            .as_deref(),
        Some("stop")
    );

    // Past max-hops (1), or back from this node: dropped, counted.
    publish(
        &fleet_channel,
        "robot-7.move",
        "two hops",
        Some(hops("elsewhere")),
    )
    .await;
    wait_status(&link, "a drop for hops", |s| s.dropped_hops == 1).await;
    let looping = UpstreamConfig {
        max_hops: 5,
        ..config.clone()
    };
    link.stop().await;
    let link = FederationLink::start("fleet", looping, target.clone(), &robot);
    wait_status(&link, "running", |s| s.state == LinkState::Running).await;
    publish(
        &fleet_channel,
        "robot-7.move",
        "came back",
        Some(hops(NODE)),
    )
    .await;
    wait_status(&link, "a drop for the loop", |s| s.dropped_hops == 1).await;
    publish(
        &fleet_channel,
        "robot-7.move",
        "one hop",
        Some(hops("elsewhere")),
    )
    .await;
    assert_eq!(
        next_local(&channel, WAIT)
            .await
            .map(|m| text(&m))
            .as_deref(),
        Some("one hop"),
        "within max-hops 5"
    );

    // The link down: what the fleet publishes waits upstream.
    link.stop().await;
    for n in 0..5 {
        publish(&fleet_channel, "robot-7.move", &format!("later {n}"), None).await;
    }
    assert!(next_local(&channel, Duration::from_millis(300))
        .await
        .is_none());
    let link = FederationLink::start("fleet", config, target, &robot);
    for n in 0..5 {
        assert_eq!(
            next_local(&channel, WAIT)
                .await
                .map(|m| text(&m))
                .as_deref(),
            Some(format!("later {n}").as_str()),
            "in order, after the link came back"
        );
    }
    assert!(
        next_local(&channel, Duration::from_millis(300))
            .await
            .is_none(),
        "robot-8's never came"
    );

    // A binding removed on the robot is removed upstream.
    channel
        .queue_unbind("robot-7.commands", "commands", "all.#", FieldTable::new())
        .await
        .expect("unbind");
    wait_status(&link, "one binding again", |s| s.bindings == 1).await;
    link.stop().await;
    drop(channel);
    drop(local);
    Arc::try_unwrap(robot)
        .unwrap_or_else(|_| panic!("robot still shared"))
        .shutdown()
        .await;
}

#[both_runtimes]
async fn federation_from_a_leveret_upstream() {
    let upstream = Broker::builder()
        .listen("127.0.0.1:0".parse().unwrap())
        .start()
        .await
        .expect("upstream");
    let uri = format!("amqp://guest:guest@{}/%2f", upstream.local_addrs()[0]);
    federate_from(&uri).await;
    upstream.shutdown().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn federation_from_a_rabbitmq_node() {
    if !rabbit_node::installed() {
        return;
    }
    let root = std::env::temp_dir().join(format!("leveret-federation-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&root);
    std::fs::create_dir_all(&root).expect("root");
    let home = root.clone();
    let node = tokio::task::spawn_blocking(move || {
        RabbitNode::start("federation", &home.join("node"), &home)
    })
    .await
    .expect("node");
    federate_from(&node.uri()).await;
    drop(node);
    let _ = std::fs::remove_dir_all(&root);
}
