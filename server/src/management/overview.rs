//! The node-wide views: `/api/overview` (RabbitMQ's figures, with the
//! sampled history of `rates` when asked), `/api/nodes[/{node}]` (this
//! one node: memory, disk and file-descriptor headroom), `/api/environment`
//! (the effective configuration), and the status page at `/` that reads
//! them. Uses `common`, `rates`, the broker through `Admin`, the
//! process's own figures (`crate::process`) and the cluster name
//! (`crate::policies`).

use super::api::{ApiError, Context};
use super::common::{ApiResult, Ctx, Params};
use crate::process::ProcessFigures;
use axum::extract::{Path, Query, State};
use axum::Json;
use serde_json::{json, Value};
use std::collections::HashMap;

/// A window of samples asked for with RabbitMQ's `{prefix}_age` and
/// `{prefix}_incr` (seconds): `None` when neither is given.
fn sample_window(query: &HashMap<String, String>, prefix: &str) -> ApiResult<Option<(u64, u64)>> {
    let number = |key: String| -> ApiResult<Option<u64>> {
        query
            .get(&key)
            .map(|v| {
                v.parse::<u64>().map_err(|_| {
                    ApiError::bad_request(format!("{key} must be a whole number of seconds"))
                })
            })
            .transpose()
    };
    match (
        number(format!("{prefix}_age"))?,
        number(format!("{prefix}_incr"))?,
    ) {
        (None, None) => Ok(None),
        (Some(age), Some(incr)) if incr > 0 => Ok(Some((age, incr))),
        _ => Err(ApiError::bad_request(format!(
            "{prefix}_age needs {prefix}_incr (at least 1) beside it"
        ))),
    }
}
/// RabbitMQ's overview. With `msg_rates_age`/`msg_rates_incr` the message
/// rates' `*_details`, with `lengths_age`/`lengths_incr` the queue totals',
/// carry RabbitMQ's `samples`, `avg_rate` and `avg` (the last ten minutes
/// are kept, every 5 s: `rates::HISTORY`).
pub async fn overview(State(c): Ctx, Query(query): Params) -> ApiResult<Json<Value>> {
    use super::rates::OverviewFigure as F;
    let msg_rates = sample_window(&query, "msg_rates")?;
    let lengths = sample_window(&query, "lengths")?;
    let o = c.admin.overview();
    let r = c.rates.overview();
    let m = &o.message_stats;
    let q = &o.queue_totals;
    let t = &o.object_totals;
    let listeners: Vec<Value> = c
        .listeners
        .iter()
        .map(|(protocol, addr)| {
            json!({"node": c.node, "protocol": protocol, "ip_address": addr.ip().to_string(), "port": addr.port()})
        })
        .collect();
    let details = |rate: f64, figure: F, window: Option<(u64, u64)>| {
        let mut details = json!({ "rate": rate });
        if let Some((age, incr)) = window {
            let history = c.rates.history(figure, age, incr);
            let samples: Vec<Value> = history
                .samples
                .iter()
                .map(|(at, value)| json!({"sample": *value as u64, "timestamp": at}))
                .collect();
            details["samples"] = Value::Array(samples);
            details["avg_rate"] = json!(history.avg_rate);
            details["avg"] = json!(history.avg);
        }
        details
    };
    let d = |rate: f64, figure: F| details(rate, figure, msg_rates);
    let l = |rate: f64, figure: F| details(rate, figure, lengths);
    let exchange_types: Vec<Value> = ["direct", "fanout", "topic", "headers"]
        .iter()
        .map(|name| json!({"name": name, "enabled": true}))
        .collect();
    Ok(Json(json!({
        "management_version": o.version,
        "rates_mode": "basic",
        "exchange_types": exchange_types,
        "product_name": o.product,
        "product_version": o.version,
        "rabbitmq_version": o.version,
        "cluster_name": crate::policies::cluster_name(&c.admin, &c.node),
        "node": c.node,
        "disable_stats": false,
        "enable_queue_totals": true,
        "message_stats": {
            "publish": m.received, "publish_details": d(r.publish, F::Publish),
            "confirm": m.confirmed, "confirm_details": d(r.confirm, F::Confirm),
            "return_unroutable": m.unroutable_returned, "return_unroutable_details": d(r.return_unroutable, F::ReturnUnroutable),
            "drop_unroutable": m.unroutable_dropped, "drop_unroutable_details": d(r.drop_unroutable, F::DropUnroutable),
            "deliver": m.delivered_consume_manual_ack, "deliver_details": d(r.deliver, F::Deliver),
            "deliver_no_ack": m.delivered_consume_auto_ack, "deliver_no_ack_details": d(r.deliver_no_ack, F::DeliverNoAck),
            "get": m.delivered_get_manual_ack, "get_details": d(r.get, F::Get),
            "get_no_ack": m.delivered_get_auto_ack, "get_no_ack_details": d(r.get_no_ack, F::GetNoAck),
            "get_empty": m.get_empty, "get_empty_details": d(r.get_empty, F::GetEmpty),
            "deliver_get": m.delivered(), "deliver_get_details": d(r.deliver_get, F::DeliverGet),
            "redeliver": m.redelivered, "redeliver_details": d(r.redeliver, F::Redeliver),
            "ack": m.acknowledged, "ack_details": d(r.ack, F::Ack),
        },
        "churn_rates": {
            "connection_created": o.churn.connections_opened,
            "connection_closed": o.churn.connections_closed,
            "channel_created": o.churn.channels_opened,
            "channel_closed": o.churn.channels_closed,
            "queue_declared": o.churn.queues_declared,
            "queue_created": o.churn.queues_created,
            "queue_deleted": o.churn.queues_deleted,
        },
        "queue_totals": {
            "messages": q.messages(), "messages_details": l(r.messages, F::Messages),
            "messages_ready": q.messages_ready, "messages_ready_details": l(r.messages_ready, F::MessagesReady),
            "messages_unacknowledged": q.messages_unacknowledged, "messages_unacknowledged_details": l(r.messages_unacknowledged, F::MessagesUnacknowledged),
        },
        "object_totals": {
            "connections": t.connections, "channels": t.channels, "exchanges": t.exchanges,
            "queues": t.queues, "consumers": t.consumers,
        },
        "listeners": listeners,
    })))
}
fn node_json(c: &Context) -> Value {
    let o = c.admin.overview();
    let p = ProcessFigures::read(&c.data_dir);
    json!({
        "name": c.node,
        "type": "disc",
        "running": true,
        "os_pid": std::process::id().to_string(),
        "mem_used": p.resident_memory_bytes,
        "mem_limit": o.resident_memory_limit,
        "queued_bytes_limit": o.memory_high_watermark,
        "mem_alarm": o.memory_alarm,
        "disk_free": p.disk_free_bytes,
        "disk_free_limit": o.disk_free_limit,
        "disk_free_alarm": o.disk_alarm,
        "fd_used": p.open_fds,
        "fd_total": p.max_fds,
        "uptime": o.uptime.as_millis() as u64,
        "rates_mode": "basic",
    })
}
pub async fn nodes(State(c): Ctx) -> Json<Value> {
    Json(json!([node_json(&c)]))
}

pub async fn node(State(c): Ctx, Path(node): Path<String>) -> ApiResult<Json<Value>> {
    if node != c.node {
        return Err(ApiError::not_found(format!("no node '{node}'")));
    }
    Ok(Json(node_json(&c)))
}
/// The effective configuration (Leveret's; RabbitMQ shows its
/// application environment with `rabbitmqctl environment` only).
pub async fn environment(State(c): Ctx) -> Json<Value> {
    Json(c.environment.clone())
}
/// The status page: alarms, memory/disk/file-descriptor headroom, charts
/// of the overview's 10-minute history, listeners, queues, connections,
/// each linking to its JSON; it refreshes itself from the API.
pub async fn status_page() -> axum::response::Html<&'static str> {
    axum::response::Html(include_str!("status.html"))
}
