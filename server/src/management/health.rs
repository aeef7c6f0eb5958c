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
//! - `certificate-expiration/{within}/{unit}` (`days`, `weeks`, `months`
//!   of 30 days, `years` of 365): fails when a certificate of the TLS
//!   listeners' `certfile` or `cacertfile` expires within that time,
//!   listing each with its listener and `expires_on` (UTC, ISO 8601).
//!
//! And the older `/api/aliveness-test/{vhost}`: a message published to
//! and got from a queue of the vhost as the caller (`{"status": "ok"}`,
//! or the refusal as RabbitMQ words it). Uses `common`, `caller` and the
//! broker through `Admin`.

use super::api::{ApiError, Context};
use super::caller::Caller;
use super::common::{require_vhost, ApiResult, Ctx};
use axum::extract::{Path, State};
use axum::http::StatusCode;
use axum::response::{IntoResponse, Response};
use axum::Extension;
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

fn alarm_check(c: &Context, reason: &str) -> Response {
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

/// Seconds in one `unit` of certificate-expiration.
fn unit_seconds(unit: &str) -> Option<i64> {
    const DAY: i64 = 86_400;
    match unit.trim_end_matches('s') {
        "day" => Some(DAY),
        "week" => Some(7 * DAY),
        "month" => Some(30 * DAY),
        "year" => Some(365 * DAY),
        _ => None,
    }
}

/// `2026-11-27T10:00:00Z` for seconds since the Unix epoch (the civil
/// calendar from a day count, Howard Hinnant's algorithm).
fn iso8601(seconds: i64) -> String {
    let (days, of_day) = (seconds.div_euclid(86_400), seconds.rem_euclid(86_400));
    let z = days + 719_468;
    let era = z.div_euclid(146_097);
    let doe = z - era * 146_097;
    let yoe = (doe - doe / 1460 + doe / 36_524 - doe / 146_096) / 365;
    let doy = doe - (365 * yoe + yoe / 4 - yoe / 100);
    let mp = (5 * doy + 2) / 153;
    let day = doy - (153 * mp + 2) / 5 + 1;
    let month = if mp < 10 { mp + 3 } else { mp - 9 };
    let year = yoe + era * 400 + i64::from(month <= 2);
    format!(
        "{year:04}-{month:02}-{day:02}T{:02}:{:02}:{:02}Z",
        of_day / 3600,
        of_day % 3600 / 60,
        of_day % 60
    )
}

pub async fn certificate_expiration(
    State(c): Ctx,
    Path((within, unit)): Path<(String, String)>,
) -> Response {
    let (Ok(within), Some(unit)) = (within.parse::<u32>(), unit_seconds(&unit)) else {
        return ApiError::bad_request(format!(
            "expected a number of days, weeks, months or years, not '{within}/{unit}'"
        ))
        .into_response();
    };
    let Some(tls) = &c.tls else {
        return ok(json!({}));
    };
    let now = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |elapsed| {
            i64::try_from(elapsed.as_secs()).unwrap_or(i64::MAX)
        });
    let deadline = now.saturating_add(i64::from(within) * unit);
    let files = std::iter::once(&tls.certfile).chain(tls.cacertfile.as_ref());
    let mut expiring = Vec::new();
    for file in files {
        let expiries = match leveret_broker::certificate_expiry(file) {
            Ok(expiries) => expiries,
            Err(e) => return failed(&format!("cannot read the certificates: {e}"), json!({})),
        };
        for expires in expiries.into_iter().filter(|at| *at <= deadline) {
            for (_, addr) in c.listeners.iter().filter(|(p, _)| *p == "amqp/ssl") {
                expiring.push(json!({
                    "node": c.node, "protocol": "amqp/ssl",
                    "interface": addr.ip().to_string(), "port": addr.port(),
                    "certfile": tls.certfile, "cacertfile": tls.cacertfile,
                    "expires_on": iso8601(expires),
                }));
            }
        }
    }
    if expiring.is_empty() {
        ok(json!({}))
    } else {
        failed("Certificates expiring", json!({ "expired": expiring }))
    }
}

/// The aliveness test: a round trip through a queue of the vhost.
pub async fn aliveness_test(
    State(c): Ctx,
    Extension(caller): Extension<Caller>,
    Path(vhost): Path<String>,
) -> ApiResult<Json<Value>> {
    require_vhost(&c, &vhost)?;
    c.admin
        .as_user(&caller.user)
        .aliveness_test(&vhost)
        .await
        .map_err(ApiError::refused_with_text)?;
    Ok(Json(json!({ "status": "ok" })))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn dates_and_units_are_read_and_written_as_expected() {
        assert_eq!(iso8601(0), "1970-01-01T00:00:00Z");
        assert_eq!(iso8601(951_782_400), "2000-02-29T00:00:00Z");
        assert_eq!(iso8601(1_795_735_445), "2026-11-26T23:24:05Z");
        assert_eq!(unit_seconds("weeks"), Some(604_800));
        assert_eq!(unit_seconds("month"), Some(2_592_000));
        assert_eq!(unit_seconds("fortnights"), None);
    }
}
