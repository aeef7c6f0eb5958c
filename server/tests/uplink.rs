//! The binary's shovels (issue 16), configured in its TOML file: a robot's
//! `leveret` forwards its durable `telemetry` queue to a fleet broker.
//! The fleet broker is down while the robot takes 500 confirmed persistent
//! messages, then the robot is killed with SIGKILL; restarted from its
//! config and data, it forwards every one of them once the fleet broker
//! returns (a power cut on the edge board does not stop the link for good,
//! lavinmq#1862).

mod common;

use common::BrokerProcess;
use futures_lite::StreamExt;
use lapin::options::{
    BasicConsumeOptions, BasicPublishOptions, ConfirmSelectOptions, QueueDeclareOptions,
};
use lapin::types::FieldTable;
use lapin::{BasicProperties, Connection, ConnectionProperties};
use leveret_broker::{Broker, BrokerHandle};
use std::collections::BTreeSet;
use std::net::SocketAddr;
use std::path::Path;
use std::time::Duration;

async fn fleet(addr: SocketAddr, dir: &Path) -> BrokerHandle {
    Broker::builder()
        .listen(addr)
        .data_dir(dir)
        .start()
        .await
        .expect("fleet broker")
}

fn durable() -> QueueDeclareOptions {
    QueueDeclareOptions {
        durable: true,
        ..Default::default()
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_configured_shovel_forwards_everything_confirmed_across_kill_9() {
    let root = std::env::temp_dir().join(format!("leveret-uplink-bin-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&root);
    std::fs::create_dir_all(&root).expect("dir");
    let addr = std::net::TcpListener::bind("127.0.0.1:0")
        .and_then(|l| l.local_addr())
        .expect("free port");
    let fleet_url = format!("amqp://guest:guest@{addr}/%2f");
    let first = fleet(addr, &root.join("fleet")).await;
    {
        let conn = Connection::connect(&fleet_url, ConnectionProperties::default())
            .await
            .expect("fleet");
        let ch = conn.create_channel().await.expect("channel");
        ch.queue_declare("fleet.telemetry", durable(), FieldTable::default())
            .await
            .expect("declare");
    }
    first.shutdown().await;

    let config = root.join("leveret.toml");
    std::fs::write(
        &config,
        format!(
            "[shovels.up]\nsrc-uri = \"amqp://\"\nsrc-queue = \"telemetry\"\n\
             dest-uri = [\"{fleet_url}\"]\ndest-queue = \"fleet.telemetry\"\nreconnect-delay = 0.1\n"
        ),
    )
    .expect("config");
    let args = [std::ffi::OsStr::new("--config"), config.as_os_str()];
    let robot = BrokerProcess::start_with(&root.join("robot"), args).await;
    let conn = Connection::connect(&robot.url(), ConnectionProperties::default())
        .await
        .expect("robot");
    let ch = conn.create_channel().await.expect("channel");
    ch.confirm_select(ConfirmSelectOptions::default())
        .await
        .expect("confirms");
    ch.queue_declare("telemetry", durable(), FieldTable::default())
        .await
        .expect("declare");
    for n in 0..500u32 {
        let confirm = ch
            .basic_publish(
                "",
                "telemetry",
                BasicPublishOptions::default(),
                n.to_string().as_bytes(),
                BasicProperties::default().with_delivery_mode(2),
            )
            .await
            .expect("publish")
            .await
            .expect("confirm");
        assert!(confirm.is_ack());
    }
    robot.kill9();

    let robot = BrokerProcess::start_with(&root.join("robot"), args).await;
    let second = fleet(addr, &root.join("fleet")).await;
    let conn = Connection::connect(&fleet_url, ConnectionProperties::default())
        .await
        .expect("fleet");
    let ch = conn.create_channel().await.expect("channel");
    let mut consumer = ch
        .basic_consume(
            "fleet.telemetry",
            "check",
            BasicConsumeOptions {
                no_ack: true,
                ..Default::default()
            },
            FieldTable::default(),
        )
        .await
        .expect("consume");
    let mut first_seen = Vec::new();
    let mut seen = BTreeSet::new();
    while seen.len() < 500 {
        let delivery = tokio::time::timeout(Duration::from_secs(30), consumer.next())
            .await
            .unwrap_or_else(|_| panic!("{} of 500 arrived", seen.len()))
            .expect("open")
            .expect("delivery");
        let n: u32 = String::from_utf8_lossy(&delivery.data)
            .parse()
            .expect("number");
        assert!(delivery
            .properties
            .headers()
            .as_ref()
            .is_some_and(|h| h.inner().contains_key("x-leveret-seq")));
        if seen.insert(n) {
            first_seen.push(n);
        }
    }
    assert_eq!(first_seen, (0..500).collect::<Vec<_>>(), "all, in order");
    drop(robot);
    second.shutdown().await;
    let _ = std::fs::remove_dir_all(&root);
}

/// Shovels through the management API, as RabbitMQ's dynamic shovels:
/// `PUT /api/parameters/shovel/VHOST/NAME` starts one, `/api/shovels`
/// lists it running, the Prometheus scrape shows its state and counts, the
/// definitions export carries it as a parameter, and DELETE stops it.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn shovels_are_managed_listed_and_exported_as_rabbitmqs_parameters() {
    use common::ops::{basic, request, OpsBroker};
    use serde_json::{json, Value};
    let root = std::env::temp_dir().join(format!("leveret-uplink-api-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&root);
    let addr = std::net::TcpListener::bind("127.0.0.1:0")
        .and_then(|l| l.local_addr())
        .expect("free port");
    let fleet_url = format!("amqp://guest:guest@{addr}/%2f");
    let fleet_broker = fleet(addr, &root.join("fleet")).await;
    let robot = OpsBroker::start("uplink-api", &[]);
    let auth = basic("guest", "guest");
    let headers = [
        ("Authorization", auth.as_str()),
        ("Content-Type", "application/json"),
    ];
    let parameters = json!({"value": {
        "src-uri": "amqp://", "src-exchange": "amq.topic", "src-exchange-key": "pose.#",
        "dest-uri": fleet_url, "dest-queue": "poses", "reconnect-delay": 0.1,
    }});
    let put = request(
        robot.http,
        "PUT",
        "/api/parameters/shovel/%2F/poses",
        &headers,
        parameters.to_string().as_bytes(),
    )
    .await;
    assert_eq!(put.status, 201, "{}", put.text());
    let bad = request(
        robot.http,
        "PUT",
        "/api/parameters/shovel/%2F/bad",
        &headers,
        br#"{"value": {"src-uri": "amqp://"}}"#,
    )
    .await;
    assert_eq!(bad.status, 400, "{}", bad.text());

    // The shovel's own queue on the robot takes amq.topic's pose.# messages.
    let fleet_conn = Connection::connect(&fleet_url, ConnectionProperties::default())
        .await
        .expect("fleet");
    let fleet_ch = fleet_conn.create_channel().await.expect("channel");
    fleet_ch
        .queue_declare("poses", durable(), FieldTable::default())
        .await
        .expect("declare");
    let deadline = std::time::Instant::now() + Duration::from_secs(20);
    loop {
        let listed = request(robot.http, "GET", "/api/shovels", &headers, b"").await;
        let listed: Value = serde_json::from_slice(&listed.body).expect("JSON");
        if listed[0]["state"] == "running" {
            assert_eq!(listed[0]["name"], "poses");
            assert_eq!(listed[0]["src_exchange"], "amq.topic");
            break;
        }
        assert!(std::time::Instant::now() < deadline, "{listed}");
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    let robot_conn = Connection::connect(&robot.amqp_url(), ConnectionProperties::default())
        .await
        .expect("robot");
    let robot_ch = robot_conn.create_channel().await.expect("channel");
    robot_ch
        .basic_publish(
            "amq.topic",
            "pose.arm",
            BasicPublishOptions::default(),
            b"p1",
            BasicProperties::default(),
        )
        .await
        .expect("publish");
    let mut consumer = fleet_ch
        .basic_consume(
            "poses",
            "c",
            BasicConsumeOptions::default(),
            FieldTable::default(),
        )
        .await
        .expect("consume");
    let delivery = tokio::time::timeout(Duration::from_secs(20), consumer.next())
        .await
        .expect("forwarded")
        .expect("open")
        .expect("delivery");
    assert_eq!(delivery.data, b"p1");

    // The shovel in the Prometheus scrape (promtool-clean where installed).
    let deadline = std::time::Instant::now() + Duration::from_secs(10);
    let scrape = loop {
        let scrape = request(robot.metrics, "GET", "/metrics", &[], b"")
            .await
            .text();
        if scrape.contains("leveret_shovel_forwarded_total{shovel=\"poses\",vhost=\"/\"} 1") {
            break scrape;
        }
        assert!(std::time::Instant::now() < deadline, "{scrape}");
        tokio::time::sleep(Duration::from_millis(50)).await;
    };
    assert!(
        scrape.contains("leveret_shovel_state{shovel=\"poses\",vhost=\"/\",state=\"running\"} 1"),
        "{scrape}"
    );
    if let Some(checked) = common::ops::promtool_check(&scrape) {
        checked.expect("promtool check metrics");
    }
    let exported = request(robot.http, "GET", "/api/definitions", &headers, b"").await;
    let exported: Value = serde_json::from_slice(&exported.body).expect("JSON");
    assert_eq!(exported["parameters"][0]["component"], "shovel");
    assert_eq!(exported["parameters"][0]["value"]["dest-queue"], "poses");

    let deleted = request(
        robot.http,
        "DELETE",
        "/api/parameters/shovel/%2F/poses",
        &headers,
        b"",
    )
    .await;
    assert_eq!(deleted.status, 204, "{}", deleted.text());
    let listed = request(robot.http, "GET", "/api/shovels", &headers, b"").await;
    assert_eq!(listed.text(), "[]");
    drop(robot);
    fleet_broker.shutdown().await;
    let _ = std::fs::remove_dir_all(&root);
}
