//! RabbitMQ 3.10's single-node health checks on `leveret`'s management
//! API (issue 31), asked with curl as an operator's probe would: each
//! passing check is 200 `{"status":"ok",...}`, each failing one 503
//! `{"status":"failed","reason":...}` with RabbitMQ's fields; a port that
//! is not a number is 400.

mod common;

use common::ops::OpsBroker;
use serde_json::{json, Value};
use std::process::Command;

/// GET `path` with curl: the status and the JSON body.
fn curl(broker: &OpsBroker, path: &str) -> (u16, Value) {
    let output = Command::new("curl")
        .args(["-s", "-u", "guest:guest", "-w", "\n%{http_code}"])
        .arg(format!("http://{}{path}", broker.http))
        .output()
        .expect("curl runs");
    let text = String::from_utf8_lossy(&output.stdout).into_owned();
    let (body, status) = text.rsplit_once('\n').expect("a status line");
    let status = status.trim().parse().expect("a status");
    let body = serde_json::from_str(body).unwrap_or_else(|e| panic!("{path}: {e}: {body}"));
    (status, body)
}

#[test]
fn listener_and_node_checks_answer_as_rabbitmq() {
    let broker = OpsBroker::start("health", &[]);
    let checks = "/api/health/checks";
    let amqp = broker.amqp.port();
    assert_eq!(
        curl(&broker, &format!("{checks}/port-listener/{amqp}")),
        (200, json!({"status": "ok", "port": amqp}))
    );
    let (status, body) = curl(&broker, &format!("{checks}/port-listener/1"));
    assert_eq!(status, 503, "{body}");
    assert_eq!(body["reason"], "No active listener");
    assert_eq!(body["missing"], 1);
    let ports = body["ports"].as_array().expect("ports");
    for port in [amqp, broker.http.port(), broker.metrics.port()] {
        assert!(ports.contains(&json!(port)), "{port} in {body}");
    }
    assert_eq!(
        curl(&broker, &format!("{checks}/port-listener/amqp")).0,
        400
    );
    for (asked, protocol) in [
        ("amqp", "amqp"),
        ("amqp091", "amqp"),
        ("http", "http"),
        ("http%2Fprometheus", "http/prometheus"),
    ] {
        assert_eq!(
            curl(&broker, &format!("{checks}/protocol-listener/{asked}")),
            (200, json!({"status": "ok", "protocol": protocol})),
            "{asked}"
        );
    }
    let (status, body) = curl(&broker, &format!("{checks}/protocol-listener/mqtt"));
    assert_eq!(status, 503, "{body}");
    assert_eq!(
        body,
        json!({"status": "failed", "reason": "No active listener", "missing": "mqtt",
               "protocols": ["amqp", "http", "http/prometheus"]})
    );
    for check in [
        "alarms",
        "local-alarms",
        "virtual-hosts",
        "node-is-quorum-critical",
        "node-is-mirror-sync-critical",
    ] {
        assert_eq!(
            curl(&broker, &format!("{checks}/{check}")),
            (200, json!({"status": "ok"})),
            "{check}"
        );
    }
}

#[test]
fn local_alarms_fail_during_a_disk_alarm() {
    let broker = OpsBroker::start(
        "health-alarm",
        &["--disk-free-limit", "1000000000000000000"],
    );
    let (status, body) = curl(&broker, "/api/health/checks/local-alarms");
    assert_eq!(status, 503, "{body}");
    assert_eq!(body["reason"], "There are alarms in effect on the node");
    assert_eq!(body["alarms"][0]["resource"], "disk", "{body}");
}
