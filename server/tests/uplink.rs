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
    let addr = leveret_tests::reserved_port::reserved_addr();
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
/// definitions export carries it as a parameter; shovels are keyed by
/// vhost and name, outlast a SIGKILL (runtime parameters in the store),
/// and DELETE stops one for good, as does deleting its vhost.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn shovels_are_managed_listed_and_exported_as_rabbitmqs_parameters() {
    use common::ops::{basic, request, OpsBroker};
    use serde_json::{json, Value};
    let root = std::env::temp_dir().join(format!("leveret-uplink-api-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&root);
    let addr = leveret_tests::reserved_port::reserved_addr();
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
    // A shovel from a queue into itself would spin for ever: refused (the
    // same local vhost written two ways), and logged.
    let looped = json!({"value": {
        "src-uri": "amqp://", "src-queue": "poses", "dest-uri": "amqp://robot:pw@/%2f", "dest-queue": "poses",
    }});
    let looped = request(
        robot.http,
        "PUT",
        "/api/parameters/shovel/%2F/looped",
        &headers,
        looped.to_string().as_bytes(),
    )
    .await;
    assert_eq!(looped.status, 400, "{}", looped.text());
    assert!(
        looped.text().contains("the shovel would loop"),
        "{}",
        looped.text()
    );
    robot.wait_for_log("shovel declaration refused");

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
            assert_eq!(listed[0]["dropped_loops"], 0);
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
    assert!(
        scrape.contains("leveret_shovel_dropped_loops_total{shovel=\"poses\",vhost=\"/\"} 0"),
        "{scrape}"
    );
    if let Some(checked) = common::ops::promtool_check(&scrape) {
        checked.expect("promtool check metrics");
    }
    let exported = request(robot.http, "GET", "/api/definitions", &headers, b"").await;
    let exported: Value = serde_json::from_slice(&exported.body).expect("JSON");
    assert_eq!(exported["parameters"][0]["component"], "shovel");
    assert_eq!(exported["parameters"][0]["value"]["dest-queue"], "poses");

    // A shovel of the same name in another vhost is another shovel.
    let vhost = request(robot.http, "PUT", "/api/vhosts/cell", &headers, b"").await;
    assert_eq!(vhost.status, 201, "{}", vhost.text());
    let cell = json!({"value": {
        "src-uri": "amqp:///cell", "src-exchange": "amq.direct", "src-exchange-key": "out",
        "dest-uri": fleet_url, "dest-queue": "poses", "reconnect-delay": 0.1,
    }});
    let put = request(
        robot.http,
        "PUT",
        "/api/parameters/shovel/cell/poses",
        &headers,
        cell.to_string().as_bytes(),
    )
    .await;
    assert_eq!(put.status, 201, "{}", put.text());

    // Declared shovels are runtime parameters: they outlast a SIGKILL and
    // forward again after it.
    drop(robot_ch);
    drop(robot_conn);
    let robot = robot.kill_and_restart(&[]);
    let running = |listed: &Value| -> Vec<(String, String)> {
        let mut running: Vec<_> = listed
            .as_array()
            .unwrap()
            .iter()
            .filter(|s| s["state"] == "running")
            .map(|s| {
                (
                    s["vhost"].as_str().unwrap().to_owned(),
                    s["name"].as_str().unwrap().to_owned(),
                )
            })
            .collect();
        running.sort();
        running
    };
    let both = [
        ("/".to_owned(), "poses".to_owned()),
        ("cell".to_owned(), "poses".to_owned()),
    ];
    let deadline = std::time::Instant::now() + Duration::from_secs(20);
    loop {
        let listed = request(robot.http, "GET", "/api/shovels", &headers, b"").await;
        let listed: Value = serde_json::from_slice(&listed.body).expect("JSON");
        if running(&listed) == both {
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
            b"p2",
            BasicProperties::default(),
        )
        .await
        .expect("publish");
    let delivery = tokio::time::timeout(Duration::from_secs(20), consumer.next())
        .await
        .expect("forwarded after the restart")
        .expect("open")
        .expect("delivery");
    assert_eq!(delivery.data, b"p2");

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
    let listed: Value = serde_json::from_slice(&listed.body).expect("JSON");
    assert_eq!(listed.as_array().unwrap().len(), 1, "{listed}");
    assert_eq!(listed[0]["vhost"], "cell", "{listed}");
    let again = request(
        robot.http,
        "DELETE",
        "/api/parameters/shovel/%2F/poses",
        &headers,
        b"",
    )
    .await;
    assert_eq!(again.status, 404, "{}", again.text());
    drop(robot_ch);
    drop(robot_conn);
    let robot = robot.kill_and_restart(&[]);
    // Once the shovel that stays runs again, the deleted one, had it
    // lasted, would be listed too (both start from the stored parameters).
    let deadline = std::time::Instant::now() + Duration::from_secs(30);
    let listed = loop {
        let listed = request(robot.http, "GET", "/api/shovels", &headers, b"").await;
        let listed: Value = serde_json::from_slice(&listed.body).expect("JSON");
        if running(&listed).contains(&both[1]) {
            break listed;
        }
        assert!(std::time::Instant::now() < deadline, "{listed}");
        tokio::time::sleep(Duration::from_millis(50)).await;
    };
    assert_eq!(
        listed.as_array().unwrap().len(),
        1,
        "the deletion lasts: {listed}"
    );
    // Deleting its vhost stops and forgets the other shovel, after a
    // restart too.
    let deleted = request(robot.http, "DELETE", "/api/vhosts/cell", &headers, b"").await;
    assert_eq!(deleted.status, 204, "{}", deleted.text());
    let listed = request(robot.http, "GET", "/api/shovels", &headers, b"").await;
    assert_eq!(listed.text(), "[]");
    let robot = robot.kill_and_restart(&[]);
    let listed = request(robot.http, "GET", "/api/shovels", &headers, b"").await;
    assert_eq!(listed.text(), "[]");

    // A shovel that has forwarded all src-delete-after asked for deletes
    // itself, parameter and all (here: a source that was empty).
    let queue = request(robot.http, "PUT", "/api/queues/%2F/empty", &headers, b"{}").await;
    assert_eq!(queue.status, 201, "{}", queue.text());
    let once = json!({"value": {
        "src-uri": "amqp://", "src-queue": "empty", "src-delete-after": "queue-length",
        "dest-uri": fleet_url, "dest-queue": "poses",
    }});
    let put = request(
        robot.http,
        "PUT",
        "/api/parameters/shovel/%2F/once",
        &headers,
        once.to_string().as_bytes(),
    )
    .await;
    assert_eq!(put.status, 201, "{}", put.text());
    let deadline = std::time::Instant::now() + Duration::from_secs(20);
    loop {
        let listed = request(robot.http, "GET", "/api/shovels", &headers, b"").await;
        let listed: Value = serde_json::from_slice(&listed.body).expect("JSON");
        if listed
            .as_array()
            .unwrap()
            .iter()
            .all(|s| s["name"] != "once")
        {
            break;
        }
        assert!(std::time::Instant::now() < deadline, "{listed}");
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    let gone = request(
        robot.http,
        "GET",
        "/api/parameters/shovel/%2F/once",
        &headers,
        b"",
    )
    .await;
    assert_eq!(gone.status, 404, "{}", gone.text());
    drop(robot);
    fleet_broker.shutdown().await;
    let _ = std::fs::remove_dir_all(&root);
}

/// Federation in the binary, declared with Debian's `rabbitmqadmin` as on
/// RabbitMQ: a `federation-upstream` parameter and a policy with
/// `federation-upstream-set` federate the fleet's `fleet.commands` to the
/// robot's `commands` exchange, declared after the policy (a policy also
/// covers exchanges declared later); `/api/federation-links` shows the
/// link running; a command the robot binds for arrives; the upstream and
/// the policy are runtime parameters that outlast a SIGKILL, are exported
/// in the definitions, and deleting the policy stops the link.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn federation_is_declared_like_rabbitmqs_and_outlasts_a_crash() {
    use common::ops::{basic, request, tool_available, OpsBroker};
    use lapin::options::{ExchangeDeclareOptions, QueueBindOptions};
    use serde_json::{json, Value};
    use std::process::Command;
    if !tool_available("rabbitmqadmin", "rabbitmq-server") {
        return;
    }
    let root = std::env::temp_dir().join(format!("leveret-federation-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&root);
    let addr = leveret_tests::reserved_port::reserved_addr();
    let fleet_url = format!("amqp://guest:guest@{addr}/%2f");
    let fleet_broker = fleet(addr, &root.join("fleet")).await;
    let fleet_conn = Connection::connect(&fleet_url, ConnectionProperties::default())
        .await
        .expect("fleet");
    let fleet_ch = fleet_conn.create_channel().await.expect("channel");
    fleet_ch
        .exchange_declare(
            "fleet.commands",
            lapin::ExchangeKind::Topic,
            ExchangeDeclareOptions {
                durable: true,
                ..Default::default()
            },
            FieldTable::default(),
        )
        .await
        .expect("upstream exchange");

    let robot = OpsBroker::start("federation", &[]);
    let admin = |broker: &OpsBroker, args: &[&str]| {
        let port = broker.http.port().to_string();
        let output = Command::new("rabbitmqadmin")
            .args(["-H", "127.0.0.1", "-P", &port, "-u", "guest", "-p", "guest"])
            .args(args)
            .output()
            .expect("rabbitmqadmin");
        assert!(
            output.status.success(),
            "rabbitmqadmin {args:?}: {}{}",
            String::from_utf8_lossy(&output.stdout),
            String::from_utf8_lossy(&output.stderr)
        );
    };
    let upstream = json!({"uri": fleet_url, "exchange": "fleet.commands", "reconnect-delay": 0.2});
    admin(
        &robot,
        &[
            "declare",
            "parameter",
            "component=federation-upstream",
            "name=fleet",
            &format!("value={upstream}"),
        ],
    );
    admin(
        &robot,
        &[
            "declare",
            "policy",
            "name=federate-commands",
            "pattern=^commands$",
            "definition={\"federation-upstream-set\": \"all\"}",
            "apply-to=exchanges",
        ],
    );
    let robot_conn = Connection::connect(&robot.amqp_url(), ConnectionProperties::default())
        .await
        .expect("robot");
    let robot_ch = robot_conn.create_channel().await.expect("channel");
    robot_ch
        .exchange_declare(
            "commands",
            lapin::ExchangeKind::Topic,
            ExchangeDeclareOptions {
                durable: true,
                ..Default::default()
            },
            FieldTable::default(),
        )
        .await
        .expect("local exchange");
    robot_ch
        .queue_declare("robot-7.commands", durable(), FieldTable::default())
        .await
        .expect("queue");
    robot_ch
        .queue_bind(
            "robot-7.commands",
            "commands",
            "robot-7.#",
            QueueBindOptions::default(),
            FieldTable::default(),
        )
        .await
        .expect("bind");
    let auth = basic("guest", "guest");
    let headers = [("Authorization", auth.as_str())];
    let running = |broker_http: SocketAddr| async move {
        let deadline = std::time::Instant::now() + Duration::from_secs(20);
        loop {
            let links = request(broker_http, "GET", "/api/federation-links", &headers, b"").await;
            let links: Value = serde_json::from_slice(&links.body).expect("JSON");
            if links[0]["status"] == "running" && links[0]["bindings"] == 1 {
                assert_eq!(links[0]["exchange"], "commands", "{links}");
                assert_eq!(links[0]["upstream_exchange"], "fleet.commands", "{links}");
                assert_eq!(links[0]["upstream"], "fleet", "{links}");
                return;
            }
            assert!(std::time::Instant::now() < deadline, "{links}");
            tokio::time::sleep(Duration::from_millis(50)).await;
        }
    };
    running(robot.http).await;
    let command = |body: &'static [u8]| {
        let fleet_ch = fleet_ch.clone();
        async move {
            fleet_ch
                .basic_publish(
                    "fleet.commands",
                    "robot-7.move",
                    BasicPublishOptions::default(),
                    body,
                    BasicProperties::default(),
                )
                .await
                .expect("publish")
                .await
                .expect("sent");
        }
    };
    // The next command to arrive is `body`; forwarding is at least once, so
    // `redelivered` (a command the robot took just before a kill -9, whose
    // upstream ack had not gone out yet) may come once before it.
    let arrives_after = |channel: lapin::Channel,
                         redelivered: Option<&'static [u8]>,
                         body: &'static [u8]| async move {
        let mut consumer = channel
            .basic_consume(
                "robot-7.commands",
                "",
                BasicConsumeOptions {
                    no_ack: true,
                    ..Default::default()
                },
                FieldTable::default(),
            )
            .await
            .expect("consume");
        let mut taken = 0;
        let delivery = loop {
            let delivery = tokio::time::timeout(Duration::from_secs(20), consumer.next())
                .await
                .expect("a command")
                .expect("open")
                .expect("delivery");
            taken += 1;
            if taken == 1 && redelivered.is_some_and(|again| delivery.data == again) {
                continue;
            }
            break delivery;
        };
        assert_eq!(delivery.data, body);
    };
    command(b"forward").await;
    arrives_after(robot_ch.clone(), None, b"forward").await;

    drop(robot_ch);
    drop(robot_conn);
    let robot = robot.kill_and_restart(&[]);
    running(robot.http).await;
    command(b"after the crash").await;
    let robot_conn = Connection::connect(&robot.amqp_url(), ConnectionProperties::default())
        .await
        .expect("robot");
    let robot_ch = robot_conn.create_channel().await.expect("channel");
    arrives_after(robot_ch.clone(), Some(b"forward"), b"after the crash").await;

    let exported = request(robot.http, "GET", "/api/definitions", &headers, b"").await;
    let exported: Value = serde_json::from_slice(&exported.body).expect("JSON");
    let parameters = exported["parameters"].as_array().expect("parameters");
    assert!(
        parameters
            .iter()
            .any(|p| p["component"] == "federation-upstream" && p["name"] == "fleet"),
        "{exported}"
    );
    assert_eq!(
        exported["policies"][0]["name"], "federate-commands",
        "{exported}"
    );
    assert_eq!(
        exported["policies"][0]["definition"]["federation-upstream-set"], "all",
        "{exported}"
    );
    // A policy key Leveret does not act on is refused, not ignored.
    let refused = request(
        robot.http,
        "PUT",
        "/api/policies/%2F/mirror",
        &[
            ("Authorization", auth.as_str()),
            ("Content-Type", "application/json"),
        ],
        br#"{"pattern": ".*", "definition": {"ha-mode": "all"}}"#,
    )
    .await;
    assert_eq!(refused.status, 400, "{}", refused.text());
    admin(&robot, &["delete", "policy", "name=federate-commands"]);
    let links = request(robot.http, "GET", "/api/federation-links", &headers, b"").await;
    assert_eq!(links.text(), "[]");
    drop(robot_ch);
    drop(robot_conn);
    drop(robot);
    fleet_broker.shutdown().await;
    let _ = std::fs::remove_dir_all(&root);
}

/// Streams in the binary's shovels and federation (issue 33): a shovel
/// declared through the API reads the robot's stream from an offset
/// (`src-consumer-args`, kept and exported as given); what the shovel
/// could not honour is refused with 400 and the reason, by the API and by
/// a definitions import. A federation policy matching a stream does not
/// apply to it (RabbitMQ 3.10 lists no policy for a stream either: its
/// keys are not stream keys), so no link federates a stream; an upstream
/// naming a queue (queue federation) is refused.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn streams_in_shovels_and_federation_through_the_api() {
    use common::ops::{basic, request, OpsBroker};
    use lapin::options::{ExchangeDeclareOptions, QueueBindOptions};
    use lapin::types::AMQPValue;
    use serde_json::{json, Value};
    let root = std::env::temp_dir().join(format!("leveret-uplink-streams-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&root);
    let addr = leveret_tests::reserved_port::reserved_addr();
    let fleet_url = format!("amqp://guest:guest@{addr}/%2f");
    let fleet_broker = fleet(addr, &root.join("fleet")).await;
    let fleet_conn = Connection::connect(&fleet_url, ConnectionProperties::default())
        .await
        .expect("fleet");
    let fleet_ch = fleet_conn.create_channel().await.expect("channel");
    fleet_ch
        .queue_declare("log", durable(), FieldTable::default())
        .await
        .expect("declare");
    let robot = OpsBroker::start("uplink-streams", &[]);
    let robot_conn = Connection::connect(&robot.amqp_url(), ConnectionProperties::default())
        .await
        .expect("robot");
    let robot_ch = robot_conn.create_channel().await.expect("channel");
    robot_ch
        .confirm_select(ConfirmSelectOptions::default())
        .await
        .expect("confirms");
    let mut stream = FieldTable::default();
    stream.insert(
        "x-queue-type".into(),
        AMQPValue::LongString("stream".into()),
    );
    robot_ch
        .queue_declare("log", durable(), stream)
        .await
        .expect("stream");
    for n in 0..20 {
        robot_ch
            .basic_publish(
                "",
                "log",
                BasicPublishOptions::default(),
                n.to_string().as_bytes(),
                BasicProperties::default(),
            )
            .await
            .expect("publish")
            .await
            .expect("confirmed");
    }

    let auth = basic("guest", "guest");
    let headers = [
        ("Authorization", auth.as_str()),
        ("Content-Type", "application/json"),
    ];
    let put = |path: String, body: Value| async move {
        request(
            robot.http,
            "PUT",
            &path,
            &headers,
            body.to_string().as_bytes(),
        )
        .await
    };
    let shovel = json!({
        "src-uri": "amqp://", "src-queue": "log", "src-consumer-args": {"x-stream-offset": 10},
        "dest-uri": fleet_url, "dest-queue": "log", "reconnect-delay": 0.1,
    });
    let created = put(
        "/api/parameters/shovel/%2F/log-up".into(),
        json!({ "value": shovel }),
    )
    .await;
    assert_eq!(created.status, 201, "{}", created.text());
    let mut consumer = fleet_ch
        .basic_consume(
            "log",
            "",
            BasicConsumeOptions {
                no_ack: true,
                ..Default::default()
            },
            FieldTable::default(),
        )
        .await
        .expect("consume");
    for n in 10..20i64 {
        let delivery = tokio::time::timeout(Duration::from_secs(20), consumer.next())
            .await
            .expect("forwarded")
            .expect("open")
            .expect("delivery");
        assert_eq!(
            delivery.data,
            n.to_string().as_bytes(),
            "from offset 10, in order"
        );
        let offset = delivery
            .properties
            .headers()
            .as_ref()
            .and_then(|h| h.inner().get("x-stream-offset").cloned());
        assert_eq!(offset, Some(AMQPValue::LongLongInt(n)));
    }
    let stored = request(
        robot.http,
        "GET",
        "/api/parameters/shovel/%2F/log-up",
        &headers,
        b"",
    )
    .await;
    let stored: Value = serde_json::from_slice(&stored.body).expect("JSON");
    assert_eq!(stored["value"], shovel, "kept as given");
    let exported = request(robot.http, "GET", "/api/definitions", &headers, b"").await;
    let exported: Value = serde_json::from_slice(&exported.body).expect("JSON");
    assert!(
        exported["parameters"]
            .as_array()
            .expect("parameters")
            .iter()
            .any(|p| p["name"] == "log-up" && p["value"] == shovel),
        "{exported}"
    );
    for (args, more, reason) in [
        (
            json!({"x-stream-offset": "bogus"}),
            json!({}),
            "is not an offset",
        ),
        (
            json!({"x-offset": 10}),
            json!({}),
            "x-offset is not a consumer argument",
        ),
        (
            json!({"x-stream-offset": "first"}),
            json!({"ack-mode": "no-ack"}),
            "no-ack cannot read a stream",
        ),
    ] {
        let mut value = json!({
            "src-uri": "amqp://", "src-queue": "log", "src-consumer-args": args,
            "dest-uri": fleet_url, "dest-queue": "log",
        });
        value
            .as_object_mut()
            .unwrap()
            .extend(more.as_object().unwrap().clone());
        let refused = put(
            "/api/parameters/shovel/%2F/refused".into(),
            json!({ "value": value }),
        )
        .await;
        assert_eq!(refused.status, 400, "{}", refused.text());
        assert!(refused.text().contains(reason), "{}", refused.text());
        let definitions = json!({"parameters": [
            {"component": "shovel", "vhost": "/", "name": "refused", "value": value},
        ]});
        let imported = request(
            robot.http,
            "POST",
            "/api/definitions",
            &headers,
            definitions.to_string().as_bytes(),
        )
        .await;
        assert_eq!(imported.status, 400, "{}", imported.text());
        assert!(imported.text().contains(reason), "{}", imported.text());
    }
    let listed = request(robot.http, "GET", "/api/shovels", &headers, b"").await;
    let listed: Value = serde_json::from_slice(&listed.body).expect("JSON");
    assert_eq!(listed.as_array().map(Vec::len), Some(1), "{listed}");

    // Federation: a policy for `^log$` matches the stream and the
    // exchange; only the exchange is federated.
    fleet_ch
        .exchange_declare(
            "fleet.log",
            lapin::ExchangeKind::Topic,
            ExchangeDeclareOptions {
                durable: true,
                ..Default::default()
            },
            FieldTable::default(),
        )
        .await
        .expect("upstream exchange");
    let by_queue = put(
        "/api/parameters/federation-upstream/%2F/by-queue".into(),
        json!({"value": {"uri": fleet_url, "queue": "log"}}),
    )
    .await;
    assert_eq!(by_queue.status, 400, "{}", by_queue.text());
    assert!(
        by_queue
            .text()
            .contains("queue federation is not supported"),
        "{}",
        by_queue.text()
    );
    let upstream = put(
        "/api/parameters/federation-upstream/%2F/fleet".into(),
        json!({"value": {"uri": fleet_url, "exchange": "fleet.log", "reconnect-delay": 0.2}}),
    )
    .await;
    assert_eq!(upstream.status, 201, "{}", upstream.text());
    robot_ch
        .exchange_declare(
            "log",
            lapin::ExchangeKind::Topic,
            ExchangeDeclareOptions {
                durable: true,
                ..Default::default()
            },
            FieldTable::default(),
        )
        .await
        .expect("local exchange");
    robot_ch
        .queue_bind(
            "log",
            "log",
            "#",
            QueueBindOptions::default(),
            FieldTable::default(),
        )
        .await
        .expect("bind the stream to the federated exchange");
    // Leveret has no queue federation: a federation policy for queues
    // alone is refused; one for all (RabbitMQ's default) federates the
    // exchange and never applies to the stream of the same name (a policy
    // applies to a stream only if all its keys are stream keys).
    let refused = put(
        "/api/policies/%2F/federate-log".into(),
        json!({"pattern": "^log$", "apply-to": "queues",
               "definition": {"federation-upstream-set": "all"}}),
    )
    .await;
    assert_eq!(refused.status, 400, "{}", refused.text());
    assert!(
        refused.text().contains("federates exchanges only"),
        "{}",
        refused.text()
    );
    let policy = put(
        "/api/policies/%2F/federate-log".into(),
        json!({"pattern": "^log$", "apply-to": "all", "definition": {"federation-upstream-set": "all"}}),
    )
    .await;
    assert!(policy.status < 300, "{}", policy.text());
    let deadline = std::time::Instant::now() + Duration::from_secs(20);
    let links = loop {
        let links = request(robot.http, "GET", "/api/federation-links", &headers, b"").await;
        let links: Value = serde_json::from_slice(&links.body).expect("JSON");
        if links[0]["status"] == "running" {
            break links;
        }
        assert!(std::time::Instant::now() < deadline, "{links}");
        tokio::time::sleep(Duration::from_millis(50)).await;
    };
    assert_eq!(links.as_array().map(Vec::len), Some(1), "{links}");
    assert_eq!(links[0]["type"], "exchange", "{links}");
    assert_eq!(links[0]["exchange"], "log", "{links}");
    let exchange = request(robot.http, "GET", "/api/exchanges/%2F/log", &headers, b"").await;
    let exchange: Value = serde_json::from_slice(&exchange.body).expect("JSON");
    assert_eq!(exchange["policy"], "federate-log", "{exchange}");
    let queue = request(robot.http, "GET", "/api/queues/%2F/log", &headers, b"").await;
    let queue: Value = serde_json::from_slice(&queue.body).expect("JSON");
    assert_eq!(queue["type"], "stream", "{queue}");
    assert_eq!(
        queue.get("policy"),
        Some(&Value::Null),
        "no policy on the stream: {queue}"
    );
    drop(robot_ch);
    drop(robot_conn);
    drop(robot);
    drop(fleet_ch);
    drop(fleet_conn);
    fleet_broker.shutdown().await;
    let _ = std::fs::remove_dir_all(&root);
}
