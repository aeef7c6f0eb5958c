//! Policies, operator policies, the cluster name and the MQTT vhost
//! mappings (global parameters) through the `leveret` binary's surfaces: rabbitmqadmin 3.10's `declare policy` and `list
//! policies`, the management API (RabbitMQ's paths and permissions),
//! leveretctl's rabbitmqctl-style commands, definitions export and
//! import; what they set acts on queues at once and outlasts a SIGKILL.

mod common;

use common::ops::{basic, request, tool_available, OpsBroker};
use serde_json::{json, Value};
use std::process::{Command, Output};

fn rabbitmqadmin(broker: &OpsBroker, args: &[&str]) -> Output {
    Command::new("rabbitmqadmin")
        .args(["-H", "127.0.0.1", "-P", &broker.http.port().to_string()])
        .args(["-u", "guest", "-p", "guest"])
        .args(args)
        .output()
        .expect("run rabbitmqadmin")
}

fn admin_ok(broker: &OpsBroker, args: &[&str]) -> String {
    let output = rabbitmqadmin(broker, args);
    let text = String::from_utf8_lossy(&output.stdout).into_owned();
    assert!(
        output.status.success(),
        "rabbitmqadmin {args:?}: {text}{}",
        String::from_utf8_lossy(&output.stderr)
    );
    text
}

fn admin_json(broker: &OpsBroker, args: &[&str]) -> Value {
    let mut all = vec!["-f", "raw_json"];
    all.extend_from_slice(args);
    let text = admin_ok(broker, &all);
    serde_json::from_str(&text).unwrap_or_else(|e| panic!("{args:?}: {e}: {text}"))
}

fn ctl(broker: &OpsBroker, args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_leveretctl"))
        .arg("--url")
        .arg(format!("http://{}", broker.http))
        .args(args)
        .output()
        .expect("run leveretctl")
}

fn ctl_ok(broker: &OpsBroker, args: &[&str]) -> String {
    let output = ctl(broker, args);
    assert!(
        output.status.success(),
        "leveretctl {args:?}: {}{}",
        String::from_utf8_lossy(&output.stdout),
        String::from_utf8_lossy(&output.stderr)
    );
    String::from_utf8_lossy(&output.stdout).into_owned()
}

async fn api(
    broker: &OpsBroker,
    method: &str,
    path: &str,
    user: (&str, &str),
    body: &Value,
) -> (u16, Value) {
    let auth = basic(user.0, user.1);
    let headers = [
        ("Authorization", auth.as_str()),
        ("Content-Type", "application/json"),
    ];
    let body = if body.is_null() {
        Vec::new()
    } else {
        body.to_string().into_bytes()
    };
    let answer = request(broker.http, method, path, &headers, &body).await;
    let value = serde_json::from_str(&answer.text()).unwrap_or(Value::Null);
    (answer.status, value)
}

const GUEST: (&str, &str) = ("guest", "guest");

fn queue<'a>(list: &'a Value, name: &str) -> &'a Value {
    list.as_array()
        .expect("a list")
        .iter()
        .find(|q| q["name"] == name)
        .unwrap_or_else(|| panic!("no {name} in {list}"))
}

/// rabbitmqadmin declares a policy that shortens a queue it matches at
/// once; listings show it (`policy`, `effective_policy_definition`); a key
/// Leveret does not act on is refused with 400; the policy and an
/// operator policy outlast a SIGKILL and still act.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn rabbitmqadmin_declares_policies_that_act_and_outlast_a_crash() {
    if !tool_available("rabbitmqadmin", "rabbitmq-server") {
        return;
    }
    let broker = OpsBroker::start("policies", &[]);
    admin_ok(
        &broker,
        &["declare", "queue", "name=short.q", "durable=true"],
    );
    for i in 0..5 {
        let payload = format!("payload={i}");
        admin_ok(&broker, &["publish", "routing_key=short.q", &payload]);
    }
    admin_ok(
        &broker,
        &[
            "declare",
            "policy",
            "name=short",
            "pattern=^short\\.",
            r#"definition={"max-length":2}"#,
            "apply-to=queues",
            "priority=1",
        ],
    );
    let policies = admin_json(&broker, &["list", "policies"]);
    assert_eq!(
        policies,
        json!([{"vhost": "/", "name": "short", "pattern": "^short\\.", "apply-to": "queues",
                "definition": {"max-length": 2}, "priority": 1}])
    );
    let queues = admin_json(&broker, &["list", "queues"]);
    let q = queue(&queues, "short.q");
    assert_eq!(q["messages"], 2, "{q}");
    assert_eq!(q["policy"], "short");
    assert_eq!(q["operator_policy"], Value::Null);
    assert_eq!(q["effective_policy_definition"], json!({"max-length": 2}));

    // RabbitMQ refuses max-priority in a policy; so does Leveret.
    let refused = rabbitmqadmin(
        &broker,
        &[
            "declare",
            "policy",
            "name=prio",
            "pattern=.*",
            r#"definition={"max-priority":5}"#,
        ],
    );
    assert!(!refused.status.success());
    let (status, _) = api(
        &broker,
        "PUT",
        "/api/policies/%2F/prio",
        GUEST,
        &json!({"pattern": ".*", "definition": {"max-priority": 5}}),
    )
    .await;
    assert_eq!(status, 400);

    let (status, _) = api(
        &broker,
        "PUT",
        "/api/operator-policies/%2F/cap",
        GUEST,
        &json!({"pattern": "^short", "apply-to": "queues", "definition": {"max-length": 1}}),
    )
    .await;
    assert_eq!(status, 201);
    let queues = admin_json(&broker, &["list", "queues"]);
    let q = queue(&queues, "short.q");
    assert_eq!(
        (q["messages"].clone(), q["operator_policy"].clone()),
        (json!(1), json!("cap")),
        "{q}"
    );

    let broker = broker.kill_and_restart(&[]);
    assert_eq!(
        admin_json(&broker, &["list", "policies"])
            .as_array()
            .unwrap()
            .len(),
        1
    );
    assert_eq!(
        admin_json(&broker, &["list", "operator_policies"])
            .as_array()
            .unwrap()
            .len(),
        1
    );
    for i in 0..3 {
        let payload = format!("payload=again-{i}");
        admin_ok(&broker, &["publish", "routing_key=short.q", &payload]);
    }
    let queues = admin_json(&broker, &["list", "queues"]);
    let q = queue(&queues, "short.q");
    assert_eq!(q["messages"], 1, "{q}");
    assert_eq!(
        (q["policy"].clone(), q["operator_policy"].clone()),
        (json!("short"), json!("cap"))
    );

    admin_ok(&broker, &["delete", "policy", "name=short"]);
    let (status, _) = api(
        &broker,
        "DELETE",
        "/api/operator-policies/%2F/cap",
        GUEST,
        &Value::Null,
    )
    .await;
    assert_eq!(status, 204);
    let broker = broker.kill_and_restart(&[]);
    assert_eq!(admin_json(&broker, &["list", "policies"]), json!([]));
    assert_eq!(
        admin_json(&broker, &["list", "operator_policies"]),
        json!([])
    );
}

/// leveretctl's rabbitmqctl-style commands; RabbitMQ's permissions:
/// `policymaker` sets policies on its vhosts, `management` cannot even
/// read them, operator policies and the cluster name are the
/// administrator's; definitions carry policies, operator policies and the
/// cluster name both ways without warnings.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn leveretctl_permissions_and_definitions_carry_policies() {
    let broker = OpsBroker::start("policies-ctl", &[]);
    ctl_ok(
        &broker,
        &[
            "set_policy",
            "--priority",
            "2",
            "--apply-to",
            "queues",
            "ttl",
            "^t\\.",
            r#"{"message-ttl":60000}"#,
        ],
    );
    ctl_ok(
        &broker,
        &[
            "set_operator_policy",
            "--apply-to",
            "queues",
            "cap",
            ".*",
            r#"{"max-length-bytes":1000000}"#,
        ],
    );
    let listed = ctl_ok(&broker, &["-q", "--no-table-headers", "list_policies"]);
    assert_eq!(
        listed.trim(),
        "/\tttl\t^t\\.\tqueues\t{\"message-ttl\":60000}\t2"
    );
    let listed = ctl_ok(
        &broker,
        &["-q", "--no-table-headers", "list_operator_policies"],
    );
    assert!(listed.starts_with("/\tcap\t.*\tqueues"), "{listed}");
    assert!(!ctl(
        &broker,
        &["set_policy", "bad", ".*", r#"{"ha-mode":"all"}"#]
    )
    .status
    .success());
    ctl_ok(&broker, &["set_cluster_name", "edge-7"]);
    let (_, overview) = api(&broker, "GET", "/api/overview", GUEST, &Value::Null).await;
    assert_eq!(overview["cluster_name"], "edge-7");
    let (_, name) = api(&broker, "GET", "/api/cluster-name", GUEST, &Value::Null).await;
    assert_eq!(name, json!({"name": "edge-7"}));
    // And in Prometheus' identity, as RabbitMQ labels it.
    let scrape = request(broker.metrics, "GET", "/metrics", &[], b"").await;
    let identity = String::from_utf8_lossy(&scrape.body)
        .lines()
        .find(|l| l.starts_with("rabbitmq_identity_info{"))
        .map(str::to_owned)
        .expect("rabbitmq_identity_info");
    assert!(
        identity.contains(r#"rabbitmq_cluster="edge-7""#),
        "{identity}"
    );

    for (user, tags) in [("maker", "policymaker"), ("viewer", "management")] {
        let (status, _) = api(
            &broker,
            "PUT",
            &format!("/api/users/{user}"),
            GUEST,
            &json!({"password": "pw", "tags": tags}),
        )
        .await;
        assert_eq!(status, 201);
        let (status, _) = api(
            &broker,
            "PUT",
            &format!("/api/permissions/%2F/{user}"),
            GUEST,
            &json!({"configure": ".*", "write": ".*", "read": ".*"}),
        )
        .await;
        assert_eq!(status, 201);
    }
    let policy = json!({"pattern": "^m", "definition": {"max-length": 3}});
    let (status, _) = api(
        &broker,
        "PUT",
        "/api/policies/%2F/made",
        ("maker", "pw"),
        &policy,
    )
    .await;
    assert_eq!(status, 201);
    let (status, _) = api(
        &broker,
        "GET",
        "/api/policies",
        ("viewer", "pw"),
        &Value::Null,
    )
    .await;
    assert_eq!(status, 401);
    let (status, _) = api(
        &broker,
        "PUT",
        "/api/operator-policies/%2F/x",
        ("maker", "pw"),
        &json!({"pattern": ".*", "definition": {"max-length": 3}}),
    )
    .await;
    assert_eq!(status, 401);
    let (status, _) = api(
        &broker,
        "PUT",
        "/api/cluster-name",
        ("maker", "pw"),
        &json!({"name": "x"}),
    )
    .await;
    assert_eq!(status, 401);

    let (_, exported) = api(&broker, "GET", "/api/definitions", GUEST, &Value::Null).await;
    assert_eq!(
        exported["policies"].as_array().unwrap().len(),
        2,
        "{exported}"
    );
    assert_eq!(exported["operator_policies"].as_array().unwrap().len(), 1);
    assert_eq!(
        exported["global_parameters"],
        json!([{"name": "cluster_name", "value": "edge-7"}])
    );

    let other = OpsBroker::start("policies-import", &[]);
    let (status, answer) = api(&other, "POST", "/api/definitions", GUEST, &exported).await;
    assert!(status < 300, "{status} {answer}");
    assert_eq!(answer["applied"]["policies"], 3, "{answer}");
    assert_eq!(answer["warnings"], json!([]), "{answer}");
    let (_, imported) = api(&other, "GET", "/api/definitions", GUEST, &Value::Null).await;
    for key in ["policies", "operator_policies", "global_parameters"] {
        assert_eq!(imported[key], exported[key], "{key}");
    }
}

/// Stored policies are in force before the listeners accept anyone: a
/// client that connects the moment the broker restarts (retrying from
/// before the port is bound) finds a stored `max-length` 1 with
/// `reject-publish` already applied to the recovered queue at its limit:
/// its publish is refused. Five hundred other stored policies and two
/// thousand queues make the setting-up take long enough that a client
/// served before it ends would see the queue without its policy (as
/// Leveret before the listeners were held did: the policy whose name
/// sorts last was applied seconds after the port accepted).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn stored_policies_are_in_force_before_the_first_client_is_served() {
    use lapin::options::{BasicPublishOptions, ConfirmSelectOptions, QueueDeclareOptions};
    use lapin::types::FieldTable;
    use lapin::{BasicProperties, Connection, ConnectionProperties};
    use std::time::{Duration, Instant};

    let dir = std::env::temp_dir().join(format!("leveret-policies-boot-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    let broker = OpsBroker::on_data_dir(&dir, &[] as &[&str]);
    let mut policies = vec![
        json!({"vhost": "/", "name": "zz-boot", "pattern": "^boot\\.",
        "apply-to": "queues", "priority": 0,
        "definition": {"max-length": 1, "overflow": "reject-publish"}}),
    ];
    let mut queues = vec![json!({"vhost": "/", "name": "boot.q", "durable": true,
        "auto_delete": false, "arguments": {}})];
    for i in 0..500 {
        policies.push(json!({"vhost": "/", "name": format!("filler{i}"),
            "pattern": format!("^filler{i}\\."), "apply-to": "queues", "priority": 0,
            "definition": {"max-length": 100}}));
    }
    for i in 0..2000 {
        queues.push(
            json!({"vhost": "/", "name": format!("filler{}.q{i}", i % 500),
            "durable": true, "auto_delete": false, "arguments": {}}),
        );
    }
    let (status, report) = api(
        &broker,
        "POST",
        "/api/definitions",
        GUEST,
        &json!({"policies": policies, "queues": queues}),
    )
    .await;
    assert_eq!(status, 200, "{report}");
    let first = Connection::connect(&broker.amqp_url(), ConnectionProperties::default())
        .await
        .expect("connect");
    let ch = first.create_channel().await.expect("channel");
    ch.confirm_select(ConfirmSelectOptions::default())
        .await
        .expect("confirm.select");
    let kept = ch
        .basic_publish(
            "",
            "boot.q",
            BasicPublishOptions::default(),
            b"kept",
            BasicProperties::default().with_delivery_mode(2),
        )
        .await
        .expect("publish")
        .await
        .expect("confirm");
    assert!(kept.is_ack(), "{kept:?}");
    let _ = first.close(200, "done").await;
    broker.kill9();

    let port = std::net::TcpListener::bind("127.0.0.1:0")
        .and_then(|l| l.local_addr())
        .expect("a free port")
        .port();
    let mut child = Command::new(env!("CARGO_BIN_EXE_leveret"))
        .args(["--listen", &format!("127.0.0.1:{port}")])
        .args([
            "--metrics-listen",
            "127.0.0.1:0",
            "--http-listen",
            "127.0.0.1:0",
            "--mqtt-listen",
            "none",
        ])
        .arg("--data-dir")
        .arg(&dir)
        .stdout(std::process::Stdio::null())
        .stderr(std::process::Stdio::null())
        .spawn()
        .expect("start leveret");
    let url = format!("amqp://guest:guest@127.0.0.1:{port}/%2f");
    let deadline = Instant::now() + Duration::from_secs(60);
    let conn = loop {
        match Connection::connect(&url, ConnectionProperties::default()).await {
            Ok(conn) => break conn,
            Err(e) if Instant::now() > deadline => panic!("never connected: {e}"),
            Err(_) => tokio::time::sleep(Duration::from_millis(5)).await,
        }
    };
    let ch = conn.create_channel().await.expect("channel");
    ch.confirm_select(ConfirmSelectOptions::default())
        .await
        .expect("confirm.select");
    let confirm = ch
        .basic_publish(
            "",
            "boot.q",
            BasicPublishOptions::default(),
            b"one too many",
            BasicProperties::default().with_delivery_mode(2),
        )
        .await
        .expect("publish")
        .await
        .expect("confirm");
    let ready = ch
        .queue_declare(
            "boot.q",
            QueueDeclareOptions {
                passive: true,
                ..Default::default()
            },
            FieldTable::default(),
        )
        .await
        .expect("passive declare")
        .message_count();
    let _ = conn.close(200, "done").await;
    let _ = child.kill();
    let _ = child.wait();
    let _ = std::fs::remove_dir_all(&dir);
    assert!(
        confirm.is_nack(),
        "the first client's publish went past the stored max-length: {confirm:?}"
    );
    assert_eq!(ready, 1);
}

/// RabbitMQ's global parameter `mqtt_port_to_vhost_mapping` through
/// `/api/global-parameters`: a malformed value is a 400 with the reason and
/// is not stored (nor is one in imported definitions); a well-formed one
/// sends `mosquitto_pub` on the mapped port to its vhost, where a lapin
/// consumer gets the message; it is listed, exported, and deleted.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn global_parameters_map_an_mqtt_port_to_a_vhost() {
    if !tool_available("mosquitto_pub", "mosquitto-clients") {
        return;
    }
    let broker = OpsBroker::start("global-parameters", &["--mqtt-listen", "127.0.0.1:0"]);
    let port = broker.mqtt_addr().port();
    let path = "/api/global-parameters/mqtt_port_to_vhost_mapping";
    let (status, _) = api(&broker, "PUT", "/api/vhosts/robots", GUEST, &json!({})).await;
    assert!(status < 300, "{status}");
    let full = json!({"configure": ".*", "write": ".*", "read": ".*"});
    let (status, _) = api(
        &broker,
        "PUT",
        "/api/permissions/robots/guest",
        GUEST,
        &full,
    )
    .await;
    assert!(status < 300, "{status}");

    for bad in [
        json!({"mqtt": "robots"}),
        json!({"1883": 7}),
        json!("robots"),
    ] {
        let (status, answer) = api(&broker, "PUT", path, GUEST, &json!({"value": bad})).await;
        assert_eq!(status, 400, "{bad}: {answer}");
        assert!(
            answer["reason"]
                .as_str()
                .unwrap()
                .contains("mqtt_port_to_vhost_mapping"),
            "{answer}"
        );
    }
    let (status, _) = api(&broker, "GET", path, GUEST, &Value::Null).await;
    assert_eq!(status, 404);
    let bad_import = json!({"global_parameters": [
        {"name": "mqtt_default_vhosts", "value": {"CN=sensor": ["robots"]}}]});
    let (status, answer) = api(&broker, "POST", "/api/definitions", GUEST, &bad_import).await;
    assert_eq!(status, 400, "{answer}");
    let (_, listed) = api(
        &broker,
        "GET",
        "/api/global-parameters",
        GUEST,
        &Value::Null,
    )
    .await;
    assert_eq!(
        listed.as_array().unwrap().len(),
        1,
        "only cluster_name: {listed}"
    );

    let mapping = json!({port.to_string(): "robots"});
    let (status, _) = api(&broker, "PUT", path, GUEST, &json!({"value": mapping})).await;
    assert_eq!(status, 204);
    let (_, one) = api(&broker, "GET", path, GUEST, &Value::Null).await;
    assert_eq!(
        one,
        json!({"name": "mqtt_port_to_vhost_mapping", "value": mapping})
    );
    let (_, exported) = api(&broker, "GET", "/api/definitions", GUEST, &Value::Null).await;
    assert!(
        exported["global_parameters"]
            .as_array()
            .unwrap()
            .contains(&one),
        "{exported}"
    );

    let url = format!("amqp://guest:guest@{}/robots", broker.amqp);
    let amqp = lapin::Connection::connect(&url, Default::default())
        .await
        .unwrap();
    let channel = amqp.create_channel().await.unwrap();
    channel
        .queue_declare("readings", Default::default(), Default::default())
        .await
        .unwrap();
    channel
        .queue_bind(
            "readings",
            "amq.topic",
            "cells.*",
            Default::default(),
            Default::default(),
        )
        .await
        .unwrap();
    let published = Command::new("mosquitto_pub")
        .args([
            "-h",
            "127.0.0.1",
            "-p",
            &port.to_string(),
            "-u",
            "guest",
            "-P",
            "guest",
        ])
        .args(["-i", "mapped", "-t", "cells/7", "-m", "21.5", "-q", "1"])
        .output()
        .expect("mosquitto_pub runs");
    assert!(published.status.success(), "{published:?}");
    let got = channel
        .basic_get("readings", lapin::options::BasicGetOptions { no_ack: true })
        .await
        .unwrap()
        .expect("the MQTT publish reached the mapped vhost");
    assert_eq!(got.delivery.data, b"21.5");

    let (status, _) = api(&broker, "DELETE", path, GUEST, &Value::Null).await;
    assert_eq!(status, 204);
    let (status, _) = api(&broker, "DELETE", path, GUEST, &Value::Null).await;
    assert_eq!(status, 404);

    // leveretctl, with rabbitmqctl's commands: a malformed value fails
    // with the reason; a good one is listed, then cleared.
    let refused = ctl(
        &broker,
        &[
            "set_global_parameter",
            "mqtt_default_vhosts",
            r#"{"CN=a": 5}"#,
        ],
    );
    assert!(!refused.status.success(), "{refused:?}");
    assert!(
        String::from_utf8_lossy(&refused.stderr).contains("mqtt_default_vhosts"),
        "{refused:?}"
    );
    let certificates = r#"{"O=client,CN=sensor-9":"robots"}"#;
    ctl_ok(
        &broker,
        &["set_global_parameter", "mqtt_default_vhosts", certificates],
    );
    let listed = ctl_ok(
        &broker,
        &["-q", "--formatter", "json", "list_global_parameters"],
    );
    let listed: Value = serde_json::from_str(&listed).expect("JSON");
    assert!(
        listed.as_array().unwrap().contains(
            &json!({"name": "mqtt_default_vhosts", "value": {"O=client,CN=sensor-9": "robots"}})
        ),
        "{listed}"
    );
    ctl_ok(&broker, &["clear_global_parameter", "mqtt_default_vhosts"]);
    let (status, _) = api(
        &broker,
        "GET",
        "/api/global-parameters/mqtt_default_vhosts",
        GUEST,
        &Value::Null,
    )
    .await;
    assert_eq!(status, 404);
}
