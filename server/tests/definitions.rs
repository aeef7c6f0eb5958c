//! RabbitMQ's definitions.json with the `leveret` binary: export through
//! `GET /api/definitions`, import at start (`--definitions`) and at run
//! time (`POST /api/definitions`, `rabbitmqadmin import`), a RabbitMQ
//! 3.10-style export (users with SHA-256 hashes, permissions, global
//! parameters) loading with everything it cannot apply reported.

mod common;

use base64::Engine;
use common::ops::{basic, request, tool_available, OpsBroker};
use lapin::{Connection, ConnectionProperties};
use serde_json::{json, Value};
use sha2::{Digest, Sha256};
use std::net::SocketAddr;

/// RabbitMQ's stored form of `password` with salt `salt`.
fn rabbitmq_hash(salt: [u8; 4], password: &str) -> String {
    let mut sha = Sha256::new();
    sha.update(salt);
    sha.update(password.as_bytes());
    let mut bytes = salt.to_vec();
    bytes.extend_from_slice(&sha.finalize());
    base64::engine::general_purpose::STANDARD.encode(bytes)
}

/// A file as RabbitMQ 3.10's `rabbitmqctl export_definitions` writes one.
fn rabbitmq_export() -> Value {
    json!({
        "rabbit_version": "3.10.8",
        "rabbitmq_version": "3.10.8",
        "product_name": "RabbitMQ",
        "product_version": "3.10.8",
        "users": [
            {"name": "robot", "password_hash": rabbitmq_hash([1, 2, 3, 4], "beep"),
             "hashing_algorithm": "rabbit_password_hashing_sha256", "tags": ["monitoring"], "limits": {}},
            {"name": "guest", "password_hash": rabbitmq_hash([9, 9, 9, 9], "guest"),
             "hashing_algorithm": "rabbit_password_hashing_sha256", "tags": ["administrator"], "limits": {}}
        ],
        "vhosts": [{"name": "/"}, {"name": "fleet", "description": "", "tags": [], "metadata": {"description": "", "tags": []}}],
        "permissions": [{"user": "robot", "vhost": "fleet", "configure": "", "write": "telemetry", "read": ""}],
        "topic_permissions": [],
        "parameters": [],
        "global_parameters": [{"name": "internal_cluster_id", "value": "rabbitmq-cluster-id-abc"}],
        "policies": [],
        "queues": [
            {"name": "telemetry", "vhost": "fleet", "durable": true, "auto_delete": false,
             "arguments": {"x-max-length": 1000, "x-queue-type": "classic"}},
            {"name": "commands", "vhost": "fleet", "durable": true, "auto_delete": false,
             "arguments": {"x-queue-type": "quorum"}}
        ],
        "exchanges": [
            {"name": "sensors", "vhost": "fleet", "type": "topic", "durable": true,
             "auto_delete": false, "internal": false, "arguments": {}}
        ],
        "bindings": [
            {"source": "sensors", "vhost": "fleet", "destination": "telemetry",
             "destination_type": "queue", "routing_key": "lidar.#", "arguments": {}}
        ]
    })
}

async fn get_json(http: SocketAddr, user: &str, password: &str, path: &str) -> Value {
    let auth = basic(user, password);
    let response = request(http, "GET", path, &[("Authorization", &auth)], b"").await;
    assert_eq!(response.status, 200, "{path}: {}", response.text());
    serde_json::from_slice(&response.body).expect("JSON")
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_rabbitmq_export_loads_at_start_and_what_cannot_apply_is_logged() {
    let dir = std::env::temp_dir().join(format!("leveret-defs-{}", std::process::id()));
    std::fs::create_dir_all(&dir).expect("dir");
    let file = dir.join("definitions.json");
    std::fs::write(&file, rabbitmq_export().to_string()).expect("write");
    let broker = OpsBroker::start("defs-start", &["--definitions", file.to_str().unwrap()]);

    // The users log in with their RabbitMQ passwords, over AMQP and HTTP.
    let url = format!("amqp://robot:beep@{}/fleet", broker.amqp);
    let conn = Connection::connect(&url, ConnectionProperties::default())
        .await
        .expect("robot reaches vhost fleet");
    // Its permission (configure nothing, write `telemetry`) is enforced.
    let channel = conn.create_channel().await.expect("channel");
    let refused = channel
        .queue_declare("mine", Default::default(), Default::default())
        .await
        .expect_err("robot may configure nothing");
    assert!(
        refused.to_string().contains(
            "ACCESS_REFUSED - access to queue 'mine' in vhost 'fleet' refused for user 'robot'"
        ),
        "{refused}"
    );
    conn.close(200, "bye").await.expect("close");
    let queues = get_json(broker.http, "robot", "beep", "/api/queues/fleet").await;
    let names: Vec<&str> = queues
        .as_array()
        .unwrap()
        .iter()
        .map(|q| q["name"].as_str().unwrap())
        .collect();
    assert_eq!(names, ["commands", "telemetry"]);
    // Kept as declared, as RabbitMQ keeps it (a classic queue).
    assert_eq!(
        queues[1]["arguments"],
        json!({"x-max-length": 1000, "x-queue-type": "classic"})
    );
    let bindings = get_json(broker.http, "guest", "guest", "/api/bindings/fleet").await;
    assert!(bindings
        .as_array()
        .unwrap()
        .iter()
        .any(|b| b["source"] == "sensors" && b["routing_key"] == "lidar.#"));

    let log = broker.log().join("\n");
    for expected in [
        "global_parameters: 'internal_cluster_id' (\"rabbitmq-cluster-id-abc\") not imported",
        "queue type 'quorum' is not supported",
    ] {
        assert!(log.contains(expected), "log says {expected}:\n{log}");
    }

    // A malformed file stops the broker with status 2, naming it.
    std::fs::write(&file, "{\"queues\": 7}").expect("write");
    let output = std::process::Command::new(env!("CARGO_BIN_EXE_leveret"))
        .args([
            "--listen",
            "127.0.0.1:0",
            "--mqtt-listen",
            "none",
            "--metrics-listen",
            "127.0.0.1:0",
            "--http-listen",
            "127.0.0.1:0",
        ])
        .arg("--data-dir")
        .arg(dir.join("data"))
        .arg("--definitions")
        .arg(&file)
        .output()
        .expect("run leveret");
    assert_eq!(output.status.code(), Some(2), "{output:?}");
    assert!(String::from_utf8_lossy(&output.stderr).contains("'queues' must be a list"));
    let _ = std::fs::remove_dir_all(&dir);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn export_then_import_into_a_fresh_broker_keeps_the_topology() {
    let first = OpsBroker::start("defs-export", &[]);
    let guest = basic("guest", "guest");
    let headers = [
        ("Authorization", guest.as_str()),
        ("Content-Type", "application/json"),
    ];
    for (method, path, body) in [
        (
            "PUT",
            "/api/exchanges/%2F/events",
            &br#"{"type": "fanout", "durable": true}"#[..],
        ),
        (
            "PUT",
            "/api/exchanges/%2F/routed",
            br#"{"type": "headers", "durable": false}"#,
        ),
        (
            "PUT",
            "/api/queues/%2F/audit",
            br#"{"durable": true, "arguments": {"x-message-ttl": 60000}}"#,
        ),
        (
            "POST",
            "/api/bindings/%2F/e/events/q/audit",
            br#"{"routing_key": ""}"#,
        ),
        (
            "POST",
            "/api/bindings/%2F/e/events/e/routed",
            br#"{"routing_key": "r", "arguments": {"x-match": "any"}}"#,
        ),
    ] {
        let response = request(first.http, method, path, &headers, body).await;
        assert!(
            response.status == 201 || response.status == 204,
            "{path}: {}",
            response.text()
        );
    }
    let exported = get_json(first.http, "guest", "guest", "/api/definitions").await;
    assert_eq!(
        exported["queues"],
        json!([{"name": "audit", "vhost": "/", "type": "classic", "durable": true, "auto_delete": false, "arguments": {"x-message-ttl": 60000}}])
    );
    assert_eq!(
        exported["exchanges"].as_array().unwrap().len(),
        2,
        "no amq.* or default exchange"
    );
    assert_eq!(
        exported["bindings"].as_array().unwrap().len(),
        2,
        "no implicit bindings"
    );
    // Users Leveret hashed are argon2id; RabbitMQ cannot import those, so
    // they go to the `leveret` section, which RabbitMQ ignores.
    assert_eq!(exported["users"], json!([]));
    assert_eq!(
        exported["leveret"]["users"][0]["hashing_algorithm"],
        "leveret_password_hashing_argon2id"
    );

    let second = OpsBroker::start("defs-import", &[]);
    let body = exported.to_string();
    let imported = request(
        second.http,
        "POST",
        "/api/definitions",
        &headers,
        body.as_bytes(),
    )
    .await;
    assert_eq!(imported.status, 200, "{}", imported.text());
    let report: Value = serde_json::from_slice(&imported.body).unwrap();
    // guest's hash differs (another salt), so the import replaces it, as
    // RabbitMQ's does.
    assert_eq!(
        report["applied"],
        json!({"vhosts": 0, "users": 1, "exchanges": 2, "queues": 1, "bindings": 2, "shovels": 0,
               "federation_upstreams": 0, "policies": 0})
    );
    let again = get_json(second.http, "guest", "guest", "/api/definitions").await;
    for key in [
        "queues",
        "exchanges",
        "bindings",
        "vhosts",
        "permissions",
        "users",
        "leveret",
    ] {
        assert_eq!(again[key], exported[key], "{key}");
    }

    // A conflicting import is refused with a reason naming the object.
    let conflicting = json!({"queues": [{"name": "audit", "vhost": "/", "durable": false, "auto_delete": false, "arguments": {}}]});
    let refused = request(
        second.http,
        "POST",
        "/api/definitions",
        &headers,
        conflicting.to_string().as_bytes(),
    )
    .await;
    assert_eq!(refused.status, 400);
    assert!(
        refused.text().contains("queue 'audit'"),
        "{}",
        refused.text()
    );
    let malformed = request(
        second.http,
        "POST",
        "/api/definitions",
        &headers,
        b"{\"exchanges\": [",
    )
    .await;
    assert_eq!(malformed.status, 400);

    // rabbitmqadmin's export and import go through the same paths.
    let dir = std::env::temp_dir().join(format!("leveret-defs-admin-{}", std::process::id()));
    std::fs::create_dir_all(&dir).expect("dir");
    let file = dir.join("export.json");
    let port = first.http.port().to_string();
    let export = std::process::Command::new("rabbitmqadmin")
        .args([
            "-H",
            "127.0.0.1",
            "-P",
            &port,
            "-u",
            "guest",
            "-p",
            "guest",
            "export",
        ])
        .arg(&file)
        .output();
    match export {
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => {
            assert!(!tool_available("rabbitmqadmin", "rabbitmq-server"));
        }
        Err(e) => panic!("rabbitmqadmin: {e}"),
        Ok(output) => {
            assert!(output.status.success(), "{output:?}");
            let third = OpsBroker::start("defs-admin", &[]);
            let port = third.http.port().to_string();
            let import = std::process::Command::new("rabbitmqadmin")
                .args([
                    "-H",
                    "127.0.0.1",
                    "-P",
                    &port,
                    "-u",
                    "guest",
                    "-p",
                    "guest",
                    "import",
                ])
                .arg(&file)
                .output()
                .expect("rabbitmqadmin import");
            assert!(import.status.success(), "{import:?}");
            let imported = get_json(third.http, "guest", "guest", "/api/definitions").await;
            assert_eq!(imported["bindings"], exported["bindings"]);
        }
    }
    let _ = std::fs::remove_dir_all(&dir);
}

/// A stream exports as a stream (`type` and arguments kept) and an
/// import makes it a stream again, as RabbitMQ 3.10's definitions do.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_stream_exports_and_imports_as_a_stream() {
    let first = OpsBroker::start("defs-stream-export", &[]);
    let guest = basic("guest", "guest");
    let headers = [
        ("Authorization", guest.as_str()),
        ("Content-Type", "application/json"),
    ];
    let declared = request(
        first.http,
        "PUT",
        "/api/queues/%2F/flight",
        &headers,
        br#"{"durable": true, "arguments": {"x-queue-type": "stream", "x-max-age": "1D"}}"#,
    )
    .await;
    assert!(declared.status == 201, "{}", declared.text());
    let exported = get_json(first.http, "guest", "guest", "/api/definitions").await;
    assert_eq!(
        exported["queues"],
        json!([{"name": "flight", "vhost": "/", "type": "stream", "durable": true, "auto_delete": false,
                "arguments": {"x-queue-type": "stream", "x-max-age": "1D"}}])
    );
    assert_eq!(exported["warnings"], Value::Null, "{exported}");

    let second = OpsBroker::start("defs-stream-import", &[]);
    let imported = request(
        second.http,
        "POST",
        "/api/definitions",
        &headers,
        exported.to_string().as_bytes(),
    )
    .await;
    assert_eq!(imported.status, 200, "{}", imported.text());
    let queue = get_json(second.http, "guest", "guest", "/api/queues/%2F/flight").await;
    assert_eq!(queue["type"], "stream", "{queue}");
    assert_eq!(queue["arguments"]["x-max-age"], "1D", "{queue}");
}
