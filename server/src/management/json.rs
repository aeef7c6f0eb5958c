//! The management API's JSON: the lenient readers of request bodies (`rabbitmqadmin` sends booleans and numbers as strings),
//! and the objects the listings return, field by field as RabbitMQ names
//! them.

use super::rates::{QueueRates, Rate};
use base64::Engine;
use leveret_broker::{
    BindingInfo, ChannelInfo, ConnectionInfo, ConsumerInfo, ExchangeInfo, QueueInfo,
};
use leveret_protocol::json::table;
use serde_json::{json, Map, Value};
use std::time::UNIX_EPOCH;

/// Why a request body could not be used.
pub type BodyError = String;

/// A request body as a JSON object.
pub fn object(body: &[u8]) -> Result<Map<String, Value>, BodyError> {
    if body.iter().all(u8::is_ascii_whitespace) {
        return Ok(Map::new());
    }
    match serde_json::from_slice(body) {
        Ok(Value::Object(map)) => Ok(map),
        Ok(other) => Err(format!("expected a JSON object, got {other}")),
        Err(e) => Err(format!("malformed JSON: {e}")),
    }
}

/// A boolean field: `true`/`false` or their strings; `default` if absent.
pub fn flag(body: &Map<String, Value>, key: &str, default: bool) -> Result<bool, BodyError> {
    match body.get(key) {
        None | Some(Value::Null) => Ok(default),
        Some(Value::Bool(b)) => Ok(*b),
        Some(Value::String(s)) if s == "true" => Ok(true),
        Some(Value::String(s)) if s == "false" => Ok(false),
        Some(other) => Err(format!("{key} must be true or false, not {other}")),
    }
}

/// A non-negative integer field, or its string; `default` if absent.
pub fn count(body: &Map<String, Value>, key: &str, default: u64) -> Result<u64, BodyError> {
    match body.get(key) {
        None | Some(Value::Null) => Some(default),
        Some(Value::Number(n)) => n.as_u64(),
        Some(Value::String(s)) => s.trim().parse().ok(),
        Some(_) => None,
    }
    .ok_or_else(|| format!("{key} must be a non-negative integer"))
}

/// A text field; `default` if absent.
pub fn text<'a>(
    body: &'a Map<String, Value>,
    key: &str,
    default: &'a str,
) -> Result<&'a str, BodyError> {
    match body.get(key) {
        None | Some(Value::Null) => Ok(default),
        Some(Value::String(s)) => Ok(s),
        Some(other) => Err(format!("{key} must be a string, not {other}")),
    }
}

/// A body as `payload` and `payload_encoding`: text when it is UTF-8 and
/// `auto` allows it, base64 otherwise.
pub fn payload(body: &[u8], force_base64: bool) -> (Value, &'static str) {
    match std::str::from_utf8(body) {
        Ok(text) if !force_base64 => (json!(text), "string"),
        _ => (
            json!(base64::engine::general_purpose::STANDARD.encode(body)),
            "base64",
        ),
    }
}

/// `{"rate": r}`.
fn details(rate: Rate) -> Value {
    json!({ "rate": rate })
}

/// A queue object.
pub fn queue(q: &QueueInfo, node: &str, rates: &QueueRates) -> Value {
    let m = &q.message_stats;
    let mut queue = json!({
        "name": q.name,
        "vhost": q.vhost,
        "durable": q.durable,
        "auto_delete": q.auto_delete,
        "exclusive": q.exclusive_owner.is_some(),
        "arguments": table(&q.arguments),
        "node": node,
        "state": "running",
        "type": q.kind(),
        "messages": q.messages(),
        "messages_details": details(rates.messages),
        "messages_ready": q.messages_ready,
        "messages_ready_details": details(rates.messages_ready),
        "messages_unacknowledged": q.messages_unacknowledged,
        "messages_unacknowledged_details": details(rates.messages_unacknowledged),
        "message_bytes_ready": q.message_bytes_ready,
        "consumers": q.consumers,
        "message_stats": {
            "publish": m.publish, "publish_details": details(rates.publish),
            "deliver": m.deliver, "deliver_details": details(rates.deliver),
            "deliver_no_ack": m.deliver_no_ack, "deliver_no_ack_details": details(rates.deliver_no_ack),
            "get": m.get, "get_details": details(rates.get),
            "get_no_ack": m.get_no_ack, "get_no_ack_details": details(rates.get_no_ack),
            "get_empty": m.get_empty, "get_empty_details": details(rates.get_empty),
            "deliver_get": m.deliver_get(), "deliver_get_details": details(rates.deliver_get),
            "redeliver": m.redeliver, "redeliver_details": details(rates.redeliver),
            "ack": m.ack, "ack_details": details(rates.ack),
        },
    });
    with_policies(&mut queue, &q.policies);
    if let (Some(stream), Some(map)) = (&q.stream, queue.as_object_mut()) {
        // Leveret's: a stream's offsets and files.
        map.insert(
            "stream".to_owned(),
            json!({"first_offset": stream.first_offset, "last_offset": stream.last_offset,
                   "segments": stream.segments, "bytes": stream.bytes}),
        );
    }
    queue
}

/// Adds `policy`, `operator_policy` and `effective_policy_definition`.
fn with_policies(object: &mut Value, applied: &leveret_broker::AppliedPolicies) {
    if let Some(map) = object.as_object_mut() {
        for (key, value) in crate::policies::applied_json(applied) {
            map.insert(key.to_owned(), value);
        }
    }
}

/// An exchange object.
pub fn exchange(e: &ExchangeInfo) -> Value {
    let mut exchange = json!({
        "name": e.name,
        "vhost": e.vhost,
        "type": e.kind,
        "durable": e.durable,
        "auto_delete": e.auto_delete,
        "internal": e.internal,
        "arguments": table(&e.arguments),
    });
    with_policies(&mut exchange, &e.policies);
    exchange
}

/// A binding object.
pub fn binding(b: &BindingInfo) -> Value {
    json!({
        "source": b.source,
        "vhost": b.vhost,
        "destination": b.destination,
        "destination_type": b.destination_kind.as_str(),
        "routing_key": b.routing_key,
        "arguments": table(&b.arguments),
        "properties_key": b.properties_key(),
    })
}

/// A connection's name in listings and in `DELETE /api/connections/NAME`:
/// its peer address and its id (unique even for in-process connections).
pub fn connection_name(id: u64, peer: &str) -> String {
    format!("{peer} #{id}")
}

fn peer_parts(peer: &str) -> (Value, Value) {
    match peer.parse::<std::net::SocketAddr>() {
        Ok(addr) => (json!(addr.ip().to_string()), json!(addr.port())),
        Err(_) => (json!(peer), Value::Null),
    }
}

/// A connection object.
pub fn connection(c: &ConnectionInfo, node: &str) -> Value {
    let (peer_host, peer_port) = peer_parts(&c.peer);
    let connected_at = c
        .connected_at
        .duration_since(UNIX_EPOCH)
        .map(|d| d.as_millis() as u64)
        .unwrap_or(0);
    json!({
        "name": connection_name(c.id, &c.peer),
        "node": node,
        "user": c.user,
        "vhost": c.vhost,
        "channels": c.channels,
        "state": "running",
        "type": "network",
        "protocol": c.protocol,
        "peer_host": peer_host,
        "peer_port": peer_port,
        "ssl": false,
        "connected_at": connected_at,
        "frame_max": c.frame_max,
        "channel_max": c.channel_max,
        "timeout": c.heartbeat_secs,
        "client_properties": table(&c.client_properties),
    })
}

pub fn channel_name(connection_id: u64, peer: &str, number: u16) -> String {
    format!("{} ({number})", connection_name(connection_id, peer))
}

/// A channel object.
pub fn channel(c: &ChannelInfo, node: &str) -> Value {
    let (peer_host, peer_port) = peer_parts(&c.connection_peer);
    json!({
        "name": channel_name(c.connection_id, &c.connection_peer, c.number),
        "number": c.number,
        "node": node,
        "user": c.user,
        "vhost": c.vhost,
        "state": "running",
        "consumer_count": c.consumers,
        "messages_unacknowledged": c.messages_unacknowledged,
        "prefetch_count": c.prefetch_count,
        "global_prefetch_count": c.global_prefetch_count,
        "confirm": c.confirm,
        "transactional": c.transactional,
        "connection_details": {
            "name": connection_name(c.connection_id, &c.connection_peer),
            "peer_host": peer_host,
            "peer_port": peer_port,
        },
    })
}

/// A consumer object; `peer` is its connection's peer address.
pub fn consumer(c: &ConsumerInfo, peer: &str, node: &str) -> Value {
    let (peer_host, peer_port) = peer_parts(peer);
    let arguments = if c.priority == 0 {
        json!({})
    } else {
        json!({ "x-priority": c.priority })
    };
    json!({
        "consumer_tag": c.tag,
        "queue": { "name": c.queue, "vhost": c.vhost },
        "channel_details": {
            "name": channel_name(c.connection_id, peer, c.channel),
            "number": c.channel,
            "connection_name": connection_name(c.connection_id, peer),
            "peer_host": peer_host,
            "peer_port": peer_port,
            "node": node,
        },
        "ack_required": c.ack_required,
        "exclusive": c.exclusive,
        "prefetch_count": c.prefetch_count,
        "arguments": arguments,
        "active": c.active,
        "activity_status": c.activity_status,
    })
}

/// A shovel as RabbitMQ's shovel-management plugin lists it (`type`
/// dynamic, `state` starting, running, blocked or terminated, the ends),
/// with Leveret's counts and last error.
pub fn shovel(s: &crate::uplink::Listed, node: &str) -> Value {
    use leveret_uplink::ShovelState;
    let state = match s.status.state {
        ShovelState::Connecting => "starting",
        ShovelState::Running => "running",
        ShovelState::Blocked => "blocked",
        ShovelState::Terminated => "terminated",
    };
    let p = &s.parameters;
    let mut out = json!({
        "node": node,
        "name": s.name,
        "vhost": s.vhost,
        "type": "dynamic",
        "state": state,
        "src_protocol": "amqp091",
        "dest_protocol": "amqp091",
        "src_uri": hide_password(p["src-uri"].as_str().unwrap_or("")),
        "dest_uri": s.status.destination,
        "forwarded": s.status.forwarded,
        "refused": s.status.refused,
        "dropped_loops": s.status.dropped_loops,
        "restarts": s.status.restarts,
        "reason": s.status.last_error,
    });
    for key in ["src-queue", "src-exchange", "dest-queue", "dest-exchange"] {
        if let Some(value) = p.get(key) {
            out[key.replace('-', "_")] = value.clone();
        }
    }
    out
}

/// A URI without its password.
fn hide_password(uri: &str) -> String {
    match (uri.split_once("://"), uri.rfind('@')) {
        (Some((scheme, rest)), Some(at)) if rest.contains('@') => {
            let userinfo = &uri[scheme.len() + 3..at];
            let user = userinfo.split(':').next().unwrap_or("");
            format!("{scheme}://{user}@{}", &uri[at + 1..])
        }
        _ => uri.to_owned(),
    }
}

/// A user's `tags`: RabbitMQ exports a list; older files a comma-separated string.
pub fn user_tags(tags: Option<&Value>) -> Vec<String> {
    match tags {
        Some(Value::Array(list)) => list
            .iter()
            .filter_map(Value::as_str)
            .map(str::to_owned)
            .collect(),
        Some(Value::String(text)) => text
            .split(',')
            .map(str::trim)
            .filter(|t| !t.is_empty())
            .map(str::to_owned)
            .collect(),
        _ => Vec::new(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rabbitmqadmin_style_strings_are_accepted() {
        let body = object(br#"{"durable":"false","count":"3","auto_delete":true}"#).unwrap();
        assert!(!flag(&body, "durable", true).unwrap());
        assert!(flag(&body, "auto_delete", false).unwrap());
        assert!(flag(&body, "internal", true).unwrap());
        assert_eq!(count(&body, "count", 1).unwrap(), 3);
        assert!(object(b"{not json").is_err());
        assert!(object(b"[1,2]").is_err());
        assert!(object(b"  ").unwrap().is_empty());
    }

    #[test]
    fn payloads_are_text_when_they_can_be() {
        assert_eq!(payload(b"hello", false), (json!("hello"), "string"));
        assert_eq!(payload(&[0xff, 0], false), (json!("/wA="), "base64"));
        assert_eq!(payload(b"hi", true), (json!("aGk="), "base64"));
    }
}
