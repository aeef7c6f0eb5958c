//! RabbitMQ 3.10's health checks that apply to a single node
//! (`/api/health/checks/...`), with its status codes and bodies: 200
//! `{"status": "ok", ...}` when the check passes, 503 `{"status":
//! "failed", "reason": ...}` when it does not.
//!
//! - `alarms`, `local-alarms`: the memory and disk alarms in effect.
//! - `port-listener/{port}`, `protocol-listener/{protocol}`: whether a
//!   listener serves that port or protocol (`amqp`, `amqp/ssl`, `mqtt`,
//!   `http` for this API, `http/prometheus` for the metrics endpoint;
//!   `amqp091` and `prometheus` are taken as aliases).
//! - `virtual-hosts`: Leveret's vhosts have no "down" state (they are
//!   tables in this process, not processes of their own), so this passes
//!   whenever the API answers.
//! - `node-is-quorum-critical`, `node-is-mirror-sync-critical`: Leveret has
//!   no quorum queues and no mirrors, so no queue depends on this node for
//!   either; they pass.

use super::handlers::Ctx;
use super::ApiError;
use axum::extract::{Path, State};
use axum::http::StatusCode;
use axum::response::{IntoResponse, Response};
use axum::Json;
use serde_json::{json, Value};

fn ok(extra: Value) -> Response {
    let mut body = json!({"status": "ok"});
    if let (Some(body), Some(extra)) = (body.as_object_mut(), extra.as_object()) {
        body.extend(extra.clone());
    }
    Json(body).into_response()
}

fn failed(reason: &str, extra: Value) -> Response {
    let mut body = json!({"status": "failed", "reason": reason});
    if let (Some(body), Some(extra)) = (body.as_object_mut(), extra.as_object()) {
        body.extend(extra.clone());
    }
    (StatusCode::SERVICE_UNAVAILABLE, Json(body)).into_response()
}

fn alarm_check(c: &super::Context, reason: &str) -> Response {
    let o = c.admin.overview();
    let alarms: Vec<Value> = [("memory", o.memory_alarm), ("disk", o.disk_alarm)]
        .into_iter()
        .filter(|(_, on)| *on)
        .map(|(resource, _)| json!({"node": c.node, "resource": resource}))
        .collect();
    if alarms.is_empty() {
        ok(json!({}))
    } else {
        failed(reason, json!({ "alarms": alarms }))
    }
}

pub async fn alarms(State(c): Ctx) -> Response {
    alarm_check(&c, "There are alarms in effect in the cluster")
}

pub async fn local_alarms(State(c): Ctx) -> Response {
    alarm_check(&c, "There are alarms in effect on the node")
}

pub async fn port_listener(State(c): Ctx, Path(port): Path<String>) -> Response {
    let Ok(port) = port.parse::<u16>() else {
        return ApiError::bad_request(format!("invalid port '{port}'")).into_response();
    };
    let mut ports: Vec<u16> = c.listeners.iter().map(|(_, addr)| addr.port()).collect();
    ports.sort_unstable();
    ports.dedup();
    if ports.contains(&port) {
        ok(json!({ "port": port }))
    } else {
        failed(
            "No active listener",
            json!({"missing": port, "ports": ports}),
        )
    }
}

/// RabbitMQ's name of a listener protocol.
fn protocol_name(asked: &str) -> &str {
    match asked {
        "amqp091" | "amqp0-9-1" | "amqp0.9.1" => "amqp",
        "prometheus" => "http/prometheus",
        other => other,
    }
}

pub async fn protocol_listener(State(c): Ctx, Path(protocol): Path<String>) -> Response {
    let asked = protocol_name(&protocol);
    let mut protocols: Vec<&str> = c.listeners.iter().map(|(p, _)| *p).collect();
    protocols.sort_unstable();
    protocols.dedup();
    if protocols.contains(&asked) {
        ok(json!({ "protocol": asked }))
    } else {
        failed(
            "No active listener",
            json!({"missing": asked, "protocols": protocols}),
        )
    }
}

pub async fn virtual_hosts() -> Response {
    ok(json!({}))
}

pub async fn node_is_quorum_critical() -> Response {
    ok(json!({}))
}

pub async fn node_is_mirror_sync_critical() -> Response {
    ok(json!({}))
}
