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
        "certificate-expiration/1/days",
    ] {
        assert_eq!(
            curl(&broker, &format!("{checks}/{check}")),
            (200, json!({"status": "ok"})),
            "{check}"
        );
    }
}

#[test]
fn mqtt_listeners_are_protocol_listeners_by_rabbitmqs_names() {
    // `--mqtt-listen none` (the test default) then a port: MQTT on it.
    let extra = [
        "--mqtt-listen",
        "127.0.0.1:0",
        "--web-mqtt-listen",
        "127.0.0.1:0",
    ];
    let broker = OpsBroker::start("health-mqtt", &extra);
    let checks = "/api/health/checks";
    for (asked, protocol) in [("mqtt", "mqtt"), ("http%2Fweb-mqtt", "http/web-mqtt")] {
        assert_eq!(
            curl(&broker, &format!("{checks}/protocol-listener/{asked}")),
            (200, json!({"status": "ok", "protocol": protocol})),
            "{asked}"
        );
    }
    let (status, body) = curl(&broker, &format!("{checks}/protocol-listener/mqtt%2Fssl"));
    assert_eq!(status, 503, "{body}");
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

/// `certificate-expiration/{within}/{unit}` over the TLS listener's
/// certificate file (certificates made with rcgen): a certificate that
/// expired on 2021-01-01 fails the check with its listener and date; a
/// current one (rcgen's default validity runs to 4096) passes it; a unit
/// RabbitMQ does not have is 400.
#[test]
fn certificate_expiration_looks_at_the_tls_listeners_certificates() {
    let ca = leveret_tests::certs::Authority::new("health");
    for (expired, within, want) in [(true, "1/days", 503), (false, "10/years", 200)] {
        let name = format!("health-tls-{expired}");
        let dir = std::env::temp_dir().join(format!("leveret-{name}-{}", std::process::id()));
        std::fs::create_dir_all(&dir).expect("dir");
        let (leaf, key) = ca.sign("leveret", expired);
        let (cert_path, key_path) = (dir.join("cert.pem"), dir.join("key.pem"));
        std::fs::write(&cert_path, leaf.pem()).expect("cert");
        std::fs::write(&key_path, key.serialize_pem()).expect("key");
        let broker = OpsBroker::start(
            &name,
            &[
                "--tls-listen",
                "127.0.0.1:0",
                "--tls-certfile",
                cert_path.to_str().expect("utf-8"),
                "--tls-keyfile",
                key_path.to_str().expect("utf-8"),
            ],
        );
        let path = format!("/api/health/checks/certificate-expiration/{within}");
        let (status, body) = curl(&broker, &path);
        assert_eq!(status, want, "{body}");
        if expired {
            assert_eq!(body["reason"], "Certificates expiring", "{body}");
            let entry = &body["expired"][0];
            assert_eq!(entry["protocol"], "amqp/ssl");
            assert_eq!(entry["port"], broker.tls.expect("TLS listener").port());
            assert_eq!(entry["expires_on"], "2021-01-01T00:00:00Z");
            assert_eq!(
                curl(
                    &broker,
                    "/api/health/checks/certificate-expiration/1/fortnights"
                )
                .0,
                400
            );
        } else {
            assert_eq!(body, json!({"status": "ok"}));
        }
        drop(broker);
        let _ = std::fs::remove_dir_all(&dir);
    }
}
