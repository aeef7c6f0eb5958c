//! The uplink against a real three-node RabbitMQ 3.10 cluster (Debian's
//! `rabbitmq-server`, three unprivileged nodes on this machine with their
//! own ports, directories and a shared Erlang cookie, joined with
//! `rabbitmqctl join_cluster`), forwarding into a quorum queue: the
//! shovel's destination is the list of the three nodes; the node it is
//! connected to is stopped while the robot keeps publishing, and the
//! shovel fails over to another. Every message confirmed to the robot's
//! publisher is in the quorum queue afterwards, first arrivals in order.
//!
//! Skips loudly outside CI when rabbitmq-server is not installed; fails
//! under CI (`.ci/run` installs it).

use leveret_broker::Broker;
use leveret_client::{
    BasicGetOptions, BasicProperties, BasicPublishOptions, Channel, Connection, Dedupe, FieldTable,
    FieldValue, QueueDeclareOptions, ShortStr,
};
use leveret_tests::rabbit_node::{self, RabbitNode};
use leveret_uplink::{Shovel, ShovelConfig};
use serde_json::json;
use std::collections::BTreeSet;
use std::os::unix::fs::PermissionsExt;
use std::sync::Arc;
use std::time::Duration;

/// Every message in the quorum queue, and how many the client's
/// `Dedupe` (keyed by the publisher's message ids) let through.
async fn get_all(channel: &Channel) -> (Vec<u32>, usize) {
    let mut got = Vec::new();
    let mut dedupe = Dedupe::new(10_000);
    let mut unique = 0;
    while let Some(message) = channel
        .basic_get("telemetry", BasicGetOptions { no_ack: true })
        .await
        .expect("get")
    {
        unique += usize::from(dedupe.first_time(&message.delivery.properties));
        got.push(
            String::from_utf8_lossy(&message.body)
                .parse()
                .expect("number"),
        );
    }
    (got, unique)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn into_a_quorum_queue_of_a_three_node_cluster_across_a_node_loss() {
    if !rabbit_node::installed() {
        return;
    }
    let root = std::env::temp_dir().join(format!("leveret-uplink-cluster-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&root);
    std::fs::create_dir_all(&root).expect("root");
    let cookie = root.join(".erlang.cookie");
    std::fs::write(&cookie, "LEVERETUPLINKTESTCOOKIE").expect("cookie");
    std::fs::set_permissions(&cookie, std::fs::Permissions::from_mode(0o400)).expect("mode");
    let home = root.clone();
    let nodes: Vec<RabbitNode> = tokio::task::spawn_blocking(move || {
        (0..3)
            .map(|i| {
                RabbitNode::start(&format!("uplink{i}"), &home.join(format!("node{i}")), &home)
            })
            .collect()
    })
    .await
    .expect("nodes");
    for node in &nodes[1..] {
        node.must(&["stop_app"]);
        node.must(&["join_cluster", &nodes[0].name]);
        node.must(&["start_app"]);
        node.await_startup();
    }
    let status = String::from_utf8_lossy(&nodes[0].ctl(&["cluster_status"]).stdout).into_owned();
    assert!(nodes.iter().all(|n| status.contains(&n.name)), "{status}");

    // The destination: a quorum queue on the cluster.
    let fleet = Connection::connect(&nodes[0].uri()).await.expect("node 0");
    let fleet_channel = fleet.open_channel().await.expect("channel");
    let mut quorum = FieldTable::new();
    quorum.insert(
        ShortStr::from_static("x-queue-type"),
        FieldValue::string("quorum"),
    );
    let durable = QueueDeclareOptions {
        durable: true,
        ..Default::default()
    };
    fleet_channel
        .queue_declare("telemetry", durable, quorum)
        .await
        .expect("quorum queue");

    let robot = Arc::new(Broker::builder().start().await.expect("robot"));
    let local = Connection::in_process(&robot).await.expect("local");
    let publisher = local.open_channel().await.expect("channel");
    publisher.confirm_select().await.expect("confirms");
    publisher
        .queue_declare("telemetry", durable, FieldTable::new())
        .await
        .expect("robot queue");
    let uris: Vec<String> = nodes.iter().map(RabbitNode::uri).collect();
    let config = ShovelConfig::from_json(&json!({
        "src-uri": "amqp://", "src-queue": "telemetry", "src-prefetch-count": 100,
        "dest-uri": uris, "dest-queue": "telemetry", "reconnect-delay": 0.2,
    }))
    .expect("parameters");
    let shovel = Shovel::start("fleet", config, Some(&robot));
    let publish = |from: u32, to: u32| {
        let publisher = publisher.clone();
        async move {
            for n in from..to {
                let properties = BasicProperties {
                    delivery_mode: Some(2),
                    message_id: ShortStr::try_from(format!("m-{n}")).ok(),
                    ..Default::default()
                };
                let confirm = publisher
                    .basic_publish(
                        "",
                        "telemetry",
                        BasicPublishOptions::default(),
                        properties,
                        n.to_string().into_bytes().into(),
                    )
                    .await
                    .expect("publish");
                assert!(confirm.await.expect("confirm").is_ack());
            }
        }
    };
    publish(0, 1000).await;
    let mut watch = shovel.watch();
    tokio::time::timeout(
        Duration::from_secs(60),
        watch.wait_for(|s| s.forwarded >= 1000),
    )
    .await
    .unwrap_or_else(|_| panic!("{:?}", shovel.status()))
    .expect("alive");
    let connected = shovel.status().destination.expect("connected");
    let index = nodes
        .iter()
        .position(|n| connected.contains(&format!(":{}/", n.port)))
        .expect("one of the nodes");

    // The node the shovel uses goes away while the robot keeps publishing.
    nodes[index].must(&["stop_app"]);
    publish(1000, 2000).await;
    tokio::time::timeout(
        Duration::from_secs(120),
        watch.wait_for(|s| s.forwarded >= 2000),
    )
    .await
    .unwrap_or_else(|_| panic!("{:?}", shovel.status()))
    .expect("alive");
    let now = shovel.status();
    assert!(now.restarts >= 1, "{now:?}");
    assert!(!now
        .destination
        .expect("connected")
        .contains(&format!(":{}/", nodes[index].port)));

    // Everything confirmed to the robot is in the quorum queue.
    let reader = &nodes[(index + 1) % 3];
    let conn = Connection::connect(&reader.uri())
        .await
        .expect("another node");
    let channel = conn.open_channel().await.expect("channel");
    let (got, unique) = get_all(&channel).await;
    assert_eq!(unique, 2000, "after the client's Dedupe, each message once");
    let distinct: BTreeSet<u32> = got.iter().copied().collect();
    assert_eq!(distinct, (0..2000).collect(), "nothing lost");
    let mut seen = BTreeSet::new();
    let first: Vec<u32> = got.iter().copied().filter(|n| seen.insert(*n)).collect();
    assert!(first.windows(2).all(|w| w[0] < w[1]), "in order");
    let duplicates = got.len() - distinct.len();
    eprintln!("forwarded 2000 across a node loss: {duplicates} duplicates");
    assert!(
        duplicates <= 100,
        "at most one prefetch window again: {duplicates}"
    );
    shovel.stop().await;
    drop(nodes);
    let _ = std::fs::remove_dir_all(&root);
}
