//! Definitions both ways between `leveret` and a real RabbitMQ 3.10 node
//! (Debian's `rabbitmq-server`, run as in `rabbitmq_round_trip.rs`):
//!
//! - Leveret's export, with users whose hashes are argon2id, imports into
//!   RabbitMQ without error (`rabbitmqctl import_definitions`, RabbitMQ's
//!   own importer, the one `POST /api/definitions` calls): those users and
//!   their permissions are in the `leveret` section RabbitMQ ignores, said
//!   in the section's warnings and Leveret's log; the queues, exchanges,
//!   bindings, the other users and their permissions arrive unchanged.
//! - Re-importing Leveret's own export changes nothing.
//! - RabbitMQ's export with users without a password (`clear_password`,
//!   `guest` among them), user limits, vhost limits, a policy, an operator
//!   policy, `cluster_name` and another global parameter loads into
//!   Leveret: the users exist with their permissions and limits but no
//!   password logs them in (AMQP or HTTP); the policy, operator policy,
//!   cluster name and vhost limits apply (the limits exported as RabbitMQ
//!   exports them); every item Leveret does not apply is named in its log.
//!
//! Skips loudly outside CI when rabbitmq-server is not installed; fails
//! under CI.

mod common;

use base64::Engine;
use common::ops::{basic, request, tool_available, OpsBroker};
use lapin::{Connection, ConnectionProperties};
use leveret_tests::rabbit_node::{RabbitNode, BIN};
use serde_json::{json, Value};
use sha2::{Digest, Sha256};
use std::net::SocketAddr;
use std::time::{Duration, Instant};

/// RabbitMQ's stored form of `password` with salt `salt`.
fn rabbitmq_hash(salt: [u8; 4], password: &str) -> String {
    let mut sha = Sha256::new();
    sha.update(salt);
    sha.update(password.as_bytes());
    let mut bytes = salt.to_vec();
    bytes.extend_from_slice(&sha.finalize());
    base64::engine::general_purpose::STANDARD.encode(bytes)
}

/// Starts the test's node, with its directory as its `HOME`.
fn start_node() -> RabbitNode {
    let dir = std::env::temp_dir().join(format!("leveret-both-ways-{}", std::process::id()));
    RabbitNode::start("leveret-both-ways", &dir, &dir)
}

/// Imports `definitions` into the node, which must take them without
/// error, and waits until its export shows `bindings` bindings (the import
/// finishes asynchronously); returns that export.
fn rabbitmq_import(node: &RabbitNode, definitions: &Value, bindings: usize) -> Value {
    let input = node.file("from-leveret.json");
    std::fs::write(&input, definitions.to_string()).expect("write definitions");
    let out = node.ctl(&["import_definitions", input.to_str().expect("utf-8")]);
    assert!(
        out.status.success(),
        "RabbitMQ imports Leveret's export: {}{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
    let deadline = Instant::now() + Duration::from_secs(60);
    loop {
        let exported = rabbitmq_export(node);
        if exported["bindings"].as_array().map_or(0, Vec::len) >= bindings {
            return exported;
        }
        assert!(Instant::now() < deadline, "the import never completed");
        std::thread::sleep(Duration::from_millis(200));
    }
}

fn rabbitmq_export(node: &RabbitNode) -> Value {
    let output = node.file("from-rabbitmq.json");
    node.must(&["export_definitions", output.to_str().expect("utf-8")]);
    serde_json::from_slice(&std::fs::read(&output).expect("read export")).expect("JSON")
}

/// `key`'s items with only `fields`, in a fixed order.
fn pick(definitions: &Value, key: &str, fields: &[&str]) -> Vec<Value> {
    let mut items: Vec<Value> = definitions[key]
        .as_array()
        .unwrap_or(&Vec::new())
        .iter()
        .map(|item| {
            Value::Object(
                fields
                    .iter()
                    .map(|f| ((*f).to_owned(), item[*f].clone()))
                    .collect(),
            )
        })
        .collect();
    items.sort_by_key(|v| v.to_string());
    items
}

async fn call(http: SocketAddr, auth: (&str, &str), method: &str, path: &str, body: &Value) -> u16 {
    let auth = basic(auth.0, auth.1);
    let body = if body.is_null() {
        Vec::new()
    } else {
        body.to_string().into_bytes()
    };
    let response = request(
        http,
        method,
        path,
        &[
            ("Authorization", &auth),
            ("Content-Type", "application/json"),
        ],
        &body,
    )
    .await;
    assert!(
        response.status < 300 || response.status == 401,
        "{method} {path}: {} {}",
        response.status,
        response.text()
    );
    response.status
}

async fn get_json(http: SocketAddr, auth: (&str, &str), path: &str) -> Value {
    let header = basic(auth.0, auth.1);
    let response = request(http, "GET", path, &[("Authorization", &header)], b"").await;
    assert_eq!(response.status, 200, "{path}: {}", response.text());
    serde_json::from_slice(&response.body).expect("JSON")
}

/// Whether `user` with `password` opens an AMQP connection to `vhost`.
async fn amqp_login(broker: &OpsBroker, user: &str, password: &str, vhost: &str) -> bool {
    let url = format!("amqp://{user}:{password}@{}/{vhost}", broker.amqp);
    match Connection::connect(&url, ConnectionProperties::default()).await {
        Ok(conn) => {
            let _ = conn.close(200, "bye").await;
            true
        }
        Err(_) => false,
    }
}

/// The topology a Leveret broker is given before its export goes to
/// RabbitMQ: a user with a RabbitMQ hash and one with an argon2id hash
/// (set through the API, as Leveret hashes new passwords).
fn leveret_topology() -> Value {
    json!({
        "vhosts": [{"name": "robots"}],
        "users": [{"name": "robot", "password_hash": rabbitmq_hash([1, 2, 3, 4], "beep"),
                   "hashing_algorithm": "rabbit_password_hashing_sha256", "tags": ["monitoring"],
                   "limits": {}}],
        "permissions": [
            {"user": "robot", "vhost": "robots", "configure": "^robot\\.", "write": ".*", "read": ".*"}
        ],
        "exchanges": [{"name": "telemetry", "vhost": "robots", "type": "topic", "durable": true,
                       "auto_delete": false, "internal": false, "arguments": {}}],
        "queues": [{"name": "robot.pose", "vhost": "robots", "durable": true, "auto_delete": false,
                    "arguments": {"x-message-ttl": 60000, "x-max-length": 100}}],
        "bindings": [{"source": "telemetry", "vhost": "robots", "destination": "robot.pose",
                      "destination_type": "queue", "routing_key": "pose.#", "arguments": {}}]
    })
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn definitions_go_both_ways_between_leveret_and_rabbitmq() {
    if !tool_available(&format!("{BIN}/rabbitmq-server"), "rabbitmq-server") {
        return;
    }
    let rabbit = tokio::task::block_in_place(start_node);
    let guest = ("guest", "guest");

    // Leveret → RabbitMQ.
    let leveret = OpsBroker::start("both-ways-out", &[]);
    call(
        leveret.http,
        guest,
        "POST",
        "/api/definitions",
        &leveret_topology(),
    )
    .await;
    call(
        leveret.http,
        guest,
        "PUT",
        "/api/users/arm",
        &json!({"password": "arm-pw", "tags": ""}),
    )
    .await;
    call(
        leveret.http,
        guest,
        "PUT",
        "/api/permissions/robots/arm",
        &json!({"configure": "", "write": ".*", "read": ""}),
    )
    .await;
    let export = get_json(leveret.http, guest, "/api/definitions").await;
    let names = |list: &Value| -> Vec<String> {
        let mut names: Vec<String> = list
            .as_array()
            .expect("list")
            .iter()
            .map(|u| u["name"].as_str().expect("name").to_owned())
            .collect();
        names.sort();
        names
    };
    assert_eq!(names(&export["users"]), ["robot"]);
    assert_eq!(names(&export["leveret"]["users"]), ["arm", "guest"]);
    assert!(export["leveret"]["permissions"]
        .as_array()
        .expect("list")
        .iter()
        .any(|p| p["user"] == "arm" && p["vhost"] == "robots"));
    assert!(export["permissions"]
        .as_array()
        .expect("list")
        .iter()
        .all(|p| p["user"] == "robot"));
    let warnings = export["leveret"]["warnings"].to_string();
    assert!(
        warnings.contains("user 'arm' is in the 'leveret' section"),
        "{warnings}"
    );
    assert!(
        leveret
            .log()
            .join("\n")
            .contains("user 'arm' is in the 'leveret' section"),
        "the export's warning is logged"
    );

    let in_rabbitmq = tokio::task::block_in_place(|| rabbitmq_import(&rabbit, &export, 1));
    for (key, fields) in [
        (
            "queues",
            &["name", "vhost", "durable", "auto_delete", "arguments"][..],
        ),
        (
            "exchanges",
            &[
                "name",
                "vhost",
                "type",
                "durable",
                "auto_delete",
                "arguments",
            ],
        ),
        (
            "bindings",
            &[
                "source",
                "vhost",
                "destination",
                "destination_type",
                "routing_key",
                "arguments",
            ],
        ),
    ] {
        assert_eq!(
            pick(&in_rabbitmq, key, fields),
            pick(&export, key, fields),
            "{key} in RabbitMQ as in Leveret"
        );
    }
    let user_fields = ["name", "password_hash", "hashing_algorithm", "tags"];
    let rabbit_users = pick(&in_rabbitmq, "users", &user_fields);
    for user in pick(&export, "users", &user_fields) {
        assert!(rabbit_users.contains(&user), "{user} in {rabbit_users:?}");
    }
    let permission_fields = ["user", "vhost", "configure", "write", "read"];
    let rabbit_permissions = pick(&in_rabbitmq, "permissions", &permission_fields);
    for permission in pick(&export, "permissions", &permission_fields) {
        assert!(rabbit_permissions.contains(&permission), "{permission}");
    }
    assert!(
        !rabbit_users.iter().any(|u| u["name"] == "arm"),
        "RabbitMQ ignored the leveret section"
    );

    // Re-importing Leveret's own export changes nothing.
    call(leveret.http, guest, "POST", "/api/definitions", &export).await;
    let again = get_json(leveret.http, guest, "/api/definitions").await;
    assert_eq!(again, export, "re-import is idempotent");
    let queues = get_json(leveret.http, guest, "/api/queues/robots").await;
    assert_eq!(queues.as_array().map(Vec::len), Some(1));
    assert!(
        amqp_login(&leveret, "arm", "arm-pw", "robots").await,
        "the argon2id user still logs in"
    );
    drop(leveret);

    // RabbitMQ → Leveret.
    tokio::task::block_in_place(|| {
        for args in [
            &["add_user", "alice", "unused"][..],
            &["clear_password", "alice"],
            &["set_permissions", "-p", "robots", "alice", ".*", ".*", ".*"],
            &["add_user", "admin", "admin-pw"],
            &["set_user_tags", "admin", "administrator"],
            &["set_permissions", "-p", "/", "admin", ".*", ".*", ".*"],
            &["clear_password", "guest"],
            &["set_user_limits", "robot", "{\"max-connections\": 3}"],
            &["set_vhost_limits", "-p", "robots", "{\"max-queues\": 10}"],
            &[
                "set_policy",
                "-p",
                "robots",
                "--apply-to",
                "queues",
                "ttl",
                "^robot\\.",
                "{\"message-ttl\": 1000}",
            ],
            &[
                "set_operator_policy",
                "-p",
                "robots",
                "--apply-to",
                "queues",
                "cap",
                "^robot\\.",
                "{\"max-length\": 50}",
            ],
            &["set_cluster_name", "rabbit-fleet"],
            &["set_global_parameter", "fleet_note", "\"kept elsewhere\""],
        ] {
            rabbit.must(args);
        }
    });
    let from_rabbitmq = tokio::task::block_in_place(|| rabbitmq_export(&rabbit));
    let file = rabbit.file("for-leveret.json");
    std::fs::write(&file, from_rabbitmq.to_string()).expect("write");
    let leveret = OpsBroker::start(
        "both-ways-in",
        &["--definitions", file.to_str().expect("utf-8")],
    );
    let admin = ("admin", "admin-pw");
    let log = leveret.log().join("\n");
    let expected = "global_parameters: 'fleet_note'";
    assert!(log.contains(expected), "the log names {expected}:\n{log}");
    for line in log.lines().filter(|line| line.contains("not imported")) {
        assert!(
            ["'ttl'", "'cap'", "'cluster_name'", "vhost-limits"]
                .iter()
                .all(|name| !line.contains(name)),
            "applied, not reported: {line}"
        );
    }
    let policies = get_json(leveret.http, admin, "/api/policies/robots").await;
    assert_eq!(
        policies[0]["definition"],
        json!({"message-ttl": 1000}),
        "{policies}"
    );
    let operator = get_json(leveret.http, admin, "/api/operator-policies/robots").await;
    assert_eq!(
        operator[0]["definition"],
        json!({"max-length": 50}),
        "{operator}"
    );
    let cluster = get_json(leveret.http, admin, "/api/cluster-name").await;
    assert_eq!(cluster, json!({"name": "rabbit-fleet"}));
    // Users without a password exist, with their permissions, and no
    // password logs them in.
    for (user, password) in [("alice", ""), ("alice", "unused"), ("guest", "guest")] {
        assert!(
            !amqp_login(&leveret, user, password, "robots").await,
            "{user}/{password} over AMQP"
        );
        let status = call(
            leveret.http,
            (user, password),
            "GET",
            "/api/whoami",
            &Value::Null,
        )
        .await;
        assert_eq!(status, 401, "{user}/{password} over HTTP");
    }
    assert!(amqp_login(&leveret, "admin", "admin-pw", "%2f").await);
    let permissions = get_json(leveret.http, admin, "/api/permissions").await;
    assert!(
        permissions
            .as_array()
            .expect("list")
            .iter()
            .any(|p| p["user"] == "alice" && p["vhost"] == "robots" && p["configure"] == ".*"),
        "{permissions}"
    );
    let export = get_json(leveret.http, admin, "/api/definitions").await;
    let user = |name: &str| -> Value {
        export["users"]
            .as_array()
            .expect("users")
            .iter()
            .find(|u| u["name"] == name)
            .cloned()
            .unwrap_or_else(|| panic!("{name} exported: {export}"))
    };
    assert_eq!(user("alice")["password_hash"], "");
    assert_eq!(user("guest")["password_hash"], "");
    assert_eq!(user("robot")["limits"], json!({"max-connections": 3}));
    // Vhost limits are applied, and exported as RabbitMQ exports them.
    assert_eq!(
        get_json(leveret.http, admin, "/api/vhost-limits/robots").await,
        json!([{"vhost": "robots", "value": {"max-queues": 10}}])
    );
    let limits = |export: &Value| -> Vec<Value> {
        (export["parameters"].as_array().into_iter().flatten())
            .filter(|p| p["component"] == "vhost-limits")
            .cloned()
            .collect()
    };
    assert_eq!(limits(&export), limits(&from_rabbitmq));
    assert_eq!(limits(&export).len(), 1);
    let user_fields = ["name", "password_hash", "hashing_algorithm", "tags"];
    assert_eq!(
        pick(&export, "users", &user_fields),
        pick(&from_rabbitmq, "users", &user_fields),
        "users as RabbitMQ had them"
    );
}
