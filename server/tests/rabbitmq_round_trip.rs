//! Definitions round trip with a real RabbitMQ 3.10 (Debian's
//! `rabbitmq-server`): a topology is imported into a RabbitMQ node and
//! exported with `rabbitmqctl export_definitions`; Leveret loads that file
//! with `--definitions` and exports its own; the node is reset and imports
//! Leveret's export; its export then has the same vhosts, users (hashes
//! and tags), permissions, topic permissions, exchanges, queues and
//! bindings, and the same policy, as the first.
//!
//! Skips loudly outside CI when rabbitmq-server is not installed; fails
//! under CI. The node runs as this user from Debian's unprivileged
//! scripts (`/usr/lib/rabbitmq/bin`), with every directory, port and the
//! Erlang cookie of its own.

mod common;

use common::ops::{request, tool_available, OpsBroker};
use leveret_tests::rabbit_node::{RabbitNode, BIN};
use serde_json::{json, Value};
use std::time::{Duration, Instant};

/// Starts the test's node, with its directory as its `HOME`.
fn start_node() -> RabbitNode {
    let dir = std::env::temp_dir().join(format!("leveret-rabbitmq-{}", std::process::id()));
    RabbitNode::start("leveret-test", &dir, &dir)
}

/// The round trip's own uses of the node.
trait RoundTrip {
    fn import_then_export(&self, definitions: &Value, name: &str) -> Value;
    fn reset(&self);
}

impl RoundTrip for RabbitNode {
    /// Imports `definitions` and waits until an export shows all of its
    /// bindings (the import runs asynchronously); returns that export.
    fn import_then_export(&self, definitions: &Value, name: &str) -> Value {
        let input = self.file(&format!("{name}-in.json"));
        std::fs::write(&input, definitions.to_string()).expect("write definitions");
        self.must(&["import_definitions", input.to_str().expect("utf-8")]);
        let wanted = definitions["bindings"].as_array().map_or(0, Vec::len);
        let output = self.file(&format!("{name}-out.json"));
        let deadline = Instant::now() + Duration::from_secs(60);
        loop {
            self.must(&["export_definitions", output.to_str().expect("utf-8")]);
            let exported: Value =
                serde_json::from_slice(&std::fs::read(&output).expect("read export"))
                    .expect("RabbitMQ's export is JSON");
            if exported["bindings"].as_array().map_or(0, Vec::len) >= wanted {
                return exported;
            }
            assert!(Instant::now() < deadline, "the import never completed");
            std::thread::sleep(Duration::from_millis(200));
        }
    }

    /// A fresh node: everything it held is gone.
    fn reset(&self) {
        self.must(&["stop_app"]);
        self.must(&["reset"]);
        self.must(&["start_app"]);
        self.await_startup();
    }
}

/// The topology of a definitions document, each list in a fixed order
/// and each object with only the keys both brokers write.
fn topology(definitions: &Value) -> Value {
    let pick = |key: &str, fields: &[&str]| -> Value {
        let mut items: Vec<Value> = definitions[key]
            .as_array()
            .unwrap_or(&Vec::new())
            .iter()
            .map(|item| {
                let mut kept = serde_json::Map::new();
                for field in fields {
                    let mut value = item[*field].clone();
                    if let Value::Array(list) = &mut value {
                        list.sort_by_key(|v| v.to_string());
                    }
                    kept.insert((*field).to_owned(), value);
                }
                Value::Object(kept)
            })
            .collect();
        items.sort_by_key(|v| v.to_string());
        Value::Array(items)
    };
    json!({
        "vhosts": pick("vhosts", &["name"]),
        "users": pick("users", &["name", "password_hash", "hashing_algorithm", "tags"]),
        "permissions": pick("permissions", &["user", "vhost", "configure", "write", "read"]),
        "topic_permissions": pick("topic_permissions", &["user", "vhost", "exchange", "write", "read"]),
        "exchanges": pick("exchanges", &["name", "vhost", "type", "durable", "auto_delete", "arguments"]),
        "queues": pick("queues", &["name", "vhost", "type", "durable", "auto_delete", "arguments"]),
        "bindings": pick("bindings", &["source", "vhost", "destination", "destination_type", "routing_key", "arguments"]),
    })
}

/// A robot fleet's topology, as an operator would keep it.
fn fleet() -> Value {
    // guest/guest and robot/secret, hashed as RabbitMQ stores them.
    json!({
        "vhosts": [{"name": "/"}, {"name": "robots"}],
        "users": [
            {"name": "guest", "password_hash": "BMfxN8drrYcIqXZMr+pWTpDT0nMcOagMduLX0bjr4jwud/pN",
             "hashing_algorithm": "rabbit_password_hashing_sha256", "tags": ["administrator"], "limits": {}},
            {"name": "robot", "password_hash": "kI3GCqW5JLMJa4iX1lo7X4D6XbYqlLgxIs30+P6tENUV2POR",
             "hashing_algorithm": "rabbit_password_hashing_sha256", "tags": ["monitoring"], "limits": {}}
        ],
        "permissions": [
            {"user": "guest", "vhost": "/", "configure": ".*", "write": ".*", "read": ".*"},
            {"user": "guest", "vhost": "robots", "configure": ".*", "write": ".*", "read": ".*"},
            {"user": "robot", "vhost": "robots", "configure": "^robot\\.", "write": ".*", "read": "^robot\\."}
        ],
        "topic_permissions": [
            {"user": "robot", "vhost": "robots", "exchange": "telemetry", "write": "^pose\\.", "read": ".*"}
        ],
        "policies": [
            {"vhost": "robots", "name": "short-lived", "pattern": "^robot\\.", "apply-to": "queues",
             "definition": {"message-ttl": 1000}, "priority": 0}
        ],
        "exchanges": [
            {"name": "telemetry", "vhost": "robots", "type": "topic", "durable": true,
             "auto_delete": false, "internal": false, "arguments": {}},
            {"name": "fan", "vhost": "robots", "type": "fanout", "durable": true,
             "auto_delete": false, "internal": false, "arguments": {"alternate-exchange": "telemetry"}},
            // Not internal: RabbitMQ 3.10's export leaves internal
            // exchanges out (and writes no `internal` key at all).
            {"name": "by-model", "vhost": "robots", "type": "headers", "durable": true,
             "auto_delete": false, "internal": false, "arguments": {}},
            {"name": "orders", "vhost": "/", "type": "direct", "durable": true,
             "auto_delete": false, "internal": false, "arguments": {}}
        ],
        "queues": [
            {"name": "robot.pose", "vhost": "robots", "durable": true, "auto_delete": false,
             "arguments": {"x-message-ttl": 60000, "x-max-length": 1000, "x-dead-letter-exchange": "fan",
                           "x-overflow": "reject-publish"}},
            {"name": "robot.alerts", "vhost": "robots", "durable": true, "auto_delete": false,
             "arguments": {"x-max-priority": 5, "x-dead-letter-exchange": "", "x-dead-letter-routing-key": "dead"}},
            {"name": "work", "vhost": "/", "durable": true, "auto_delete": false, "arguments": {}}
        ],
        "bindings": [
            {"source": "telemetry", "vhost": "robots", "destination": "robot.pose",
             "destination_type": "queue", "routing_key": "pose.#", "arguments": {}},
            {"source": "fan", "vhost": "robots", "destination": "telemetry",
             "destination_type": "exchange", "routing_key": "", "arguments": {}},
            {"source": "fan", "vhost": "robots", "destination": "by-model",
             "destination_type": "exchange", "routing_key": "", "arguments": {}},
            {"source": "by-model", "vhost": "robots", "destination": "robot.alerts",
             "destination_type": "queue", "routing_key": "",
             "arguments": {"x-match": "any", "model": "arm-7", "level": 3}},
            {"source": "orders", "vhost": "/", "destination": "work",
             "destination_type": "queue", "routing_key": "order.new", "arguments": {}}
        ]
    })
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn definitions_go_from_rabbitmq_through_leveret_to_a_fresh_rabbitmq() {
    if !tool_available(&format!("{BIN}/rabbitmq-server"), "rabbitmq-server") {
        return;
    }
    let rabbit = tokio::task::block_in_place(start_node);
    let from_rabbitmq =
        tokio::task::block_in_place(|| rabbit.import_then_export(&fleet(), "first"));
    assert_eq!(
        from_rabbitmq["queues"].as_array().map(Vec::len),
        Some(3),
        "RabbitMQ took the fleet: {from_rabbitmq}"
    );
    assert_eq!(from_rabbitmq["policies"].as_array().map(Vec::len), Some(1));

    let exported_file = rabbit.file("from-rabbitmq.json");
    std::fs::write(&exported_file, from_rabbitmq.to_string()).expect("write");
    let leveret = OpsBroker::start(
        "round-trip",
        &["--definitions", exported_file.to_str().expect("utf-8")],
    );
    let auth = common::ops::basic("guest", "guest");
    let response = request(
        leveret.http,
        "GET",
        "/api/definitions",
        &[("Authorization", &auth)],
        b"",
    )
    .await;
    assert_eq!(response.status, 200, "{}", response.text());
    let from_leveret: Value = serde_json::from_slice(&response.body).expect("JSON");
    assert_eq!(from_leveret["policies"], from_rabbitmq["policies"]);
    assert_eq!(topology(&from_leveret), topology(&from_rabbitmq));

    tokio::task::block_in_place(|| rabbit.reset());
    let again = tokio::task::block_in_place(|| rabbit.import_then_export(&from_leveret, "second"));
    assert_eq!(
        topology(&again),
        topology(&from_rabbitmq),
        "a fresh RabbitMQ has the topology back from Leveret's export"
    );
    assert_eq!(again["policies"], from_rabbitmq["policies"]);
}
