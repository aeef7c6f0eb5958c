//! The management API's JSON: AMQP field tables and message properties
//! to and from JSON as RabbitMQ renders them, the lenient readers of
//! request bodies (`rabbitmqadmin` sends booleans and numbers as strings),
//! and the objects the listings return, field by field as RabbitMQ names
//! them.

use super::rates::{QueueRates, Rate};
use base64::Engine;
use leveret_broker::{
    BindingInfo, ChannelInfo, ConnectionInfo, ConsumerInfo, ExchangeInfo, QueueInfo,
};
use leveret_protocol::{BasicProperties, FieldArray, FieldTable, FieldValue, ShortStr};
use serde_json::{json, Map, Value};
use std::time::UNIX_EPOCH;

/// A field value as RabbitMQ's management API shows it.
pub fn field_value(value: &FieldValue) -> Value {
    match value {
        FieldValue::Bool(b) => json!(b),
        FieldValue::I8(n) => json!(n),
        FieldValue::U8(n) => json!(n),
        FieldValue::I16(n) => json!(n),
        FieldValue::U16(n) => json!(n),
        FieldValue::I32(n) => json!(n),
        FieldValue::U32(n) => json!(n),
        FieldValue::I64(n) => json!(n),
        FieldValue::F32(n) => json!(n),
        FieldValue::F64(n) => json!(n),
        FieldValue::Decimal(d) => json!(format!("{d:?}")),
        FieldValue::LongStr(s) => json!(String::from_utf8_lossy(s)),
        FieldValue::ByteArray(b) => json!(String::from_utf8_lossy(b)),
        FieldValue::Array(items) => Value::Array(items.iter().map(field_value).collect()),
        FieldValue::Timestamp(t) => json!(t),
        FieldValue::Table(t) => table(t),
        FieldValue::Void => Value::Null,
    }
}

/// A field table as a JSON object.
pub fn table(table: &FieldTable) -> Value {
    Value::Object(
        table
            .iter()
            .map(|(k, v)| (k.to_string_lossy().into_owned(), field_value(v)))
            .collect(),
    )
}

/// Why a request body could not be used.
pub type BodyError = String;

/// A JSON value as an AMQP field value (integers as signed 64-bit, as
/// RabbitMQ's API converts them).
pub fn to_field_value(value: &Value) -> Result<FieldValue, BodyError> {
    Ok(match value {
        Value::Null => FieldValue::Void,
        Value::Bool(b) => FieldValue::Bool(*b),
        Value::Number(n) => match n.as_i64() {
            Some(i) => FieldValue::I64(i),
            None => FieldValue::F64(n.as_f64().ok_or("number out of range")?),
        },
        Value::String(s) => FieldValue::string(s),
        Value::Array(items) => FieldValue::Array(
            items
                .iter()
                .map(to_field_value)
                .collect::<Result<FieldArray, _>>()?,
        ),
        Value::Object(_) => FieldValue::Table(to_table(value)?),
    })
}

/// A JSON object (or null) as a field table.
pub fn to_table(value: &Value) -> Result<FieldTable, BodyError> {
    match value {
        Value::Null => Ok(FieldTable::new()),
        Value::Object(map) => map
            .iter()
            .map(|(k, v)| {
                let key = ShortStr::try_from(k.as_str())
                    .map_err(|_| format!("argument name longer than 255 bytes: {k:.40}"))?;
                Ok((key, to_field_value(v)?))
            })
            .collect(),
        other => Err(format!("arguments must be an object, not {other}")),
    }
}

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

fn short(value: &Value, key: &str) -> Result<ShortStr, BodyError> {
    match value {
        Value::String(s) => {
            ShortStr::try_from(s.as_str()).map_err(|_| format!("{key} longer than 255 bytes"))
        }
        Value::Number(n) => ShortStr::try_from(n.to_string()).map_err(|_| key.to_owned()),
        other => Err(format!("{key} must be a string, not {other}")),
    }
}

fn small(value: &Value, key: &str, max: u64) -> Result<u64, BodyError> {
    let n = match value {
        Value::Number(n) => n.as_u64(),
        Value::String(s) => s.parse().ok(),
        _ => None,
    };
    n.filter(|n| *n <= max)
        .ok_or_else(|| format!("{key} must be an integer from 0 to {max}"))
}

/// Message properties from the `properties` object of a publish.
pub fn properties(value: Option<&Value>) -> Result<BasicProperties, BodyError> {
    let mut p = BasicProperties::default();
    let map = match value {
        None | Some(Value::Null) => return Ok(p),
        Some(Value::Object(map)) => map,
        Some(other) => return Err(format!("properties must be an object, not {other}")),
    };
    for (key, value) in map {
        match key.as_str() {
            "content_type" => p.content_type = Some(short(value, key)?),
            "content_encoding" => p.content_encoding = Some(short(value, key)?),
            "headers" => p.headers = Some(to_table(value)?),
            "delivery_mode" => p.delivery_mode = Some(small(value, key, 2)? as u8),
            "priority" => p.priority = Some(small(value, key, 255)? as u8),
            "correlation_id" => p.correlation_id = Some(short(value, key)?),
            "reply_to" => p.reply_to = Some(short(value, key)?),
            "expiration" => p.expiration = Some(short(value, key)?),
            "message_id" => p.message_id = Some(short(value, key)?),
            "timestamp" => p.timestamp = Some(small(value, key, u64::MAX)?),
            "type" => p.kind = Some(short(value, key)?),
            "user_id" => p.user_id = Some(short(value, key)?),
            "app_id" => p.app_id = Some(short(value, key)?),
            "cluster_id" => p.cluster_id = Some(short(value, key)?),
            other => return Err(format!("unknown message property {other}")),
        }
    }
    Ok(p)
}

/// Message properties as RabbitMQ shows them (only those set).
pub fn properties_json(p: &BasicProperties) -> Value {
    let mut out = Map::new();
    let mut put = |key: &str, value: Option<Value>| {
        if let Some(value) = value {
            out.insert(key.to_owned(), value);
        }
    };
    let s = |v: &Option<ShortStr>| v.as_ref().map(|s| json!(s.to_string_lossy()));
    put("content_type", s(&p.content_type));
    put("content_encoding", s(&p.content_encoding));
    put("headers", p.headers.as_ref().map(table));
    put("delivery_mode", p.delivery_mode.map(|m| json!(m)));
    put("priority", p.priority.map(|m| json!(m)));
    put("correlation_id", s(&p.correlation_id));
    put("reply_to", s(&p.reply_to));
    put("expiration", s(&p.expiration));
    put("message_id", s(&p.message_id));
    put("timestamp", p.timestamp.map(|t| json!(t)));
    put("type", s(&p.kind));
    put("user_id", s(&p.user_id));
    put("app_id", s(&p.app_id));
    put("cluster_id", s(&p.cluster_id));
    Value::Object(out)
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
    json!({
        "name": q.name,
        "vhost": q.vhost,
        "durable": q.durable,
        "auto_delete": q.auto_delete,
        "exclusive": q.exclusive_owner.is_some(),
        "arguments": table(&q.arguments),
        "node": node,
        "state": "running",
        "type": "classic",
        "policy": null,
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
    })
}

/// An exchange object.
pub fn exchange(e: &ExchangeInfo) -> Value {
    json!({
        "name": e.name,
        "vhost": e.vhost,
        "type": e.kind,
        "durable": e.durable,
        "auto_delete": e.auto_delete,
        "internal": e.internal,
        "arguments": table(&e.arguments),
        "policy": null,
    })
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
        "protocol": "AMQP 0-9-1",
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

fn channel_name(connection_id: u64, peer: &str, number: u16) -> String {
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
        "active": true,
        "activity_status": "up",
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
    fn arguments_round_trip_through_json() {
        let value = json!({"x-message-ttl": 60000, "x-dead-letter-exchange": "dlx",
                           "flag": true, "ratio": 0.5, "list": [1, "a"], "nested": {"k": null}});
        let table = to_table(&value).unwrap();
        assert_eq!(table.get("x-message-ttl"), Some(&FieldValue::I64(60000)));
        assert_eq!(super::table(&table), value);
        assert!(to_table(&json!([1])).is_err());
        assert!(to_table(&json!({"x".repeat(300): 1})).is_err());
    }

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
    fn properties_round_trip_and_unknown_ones_are_refused() {
        let value = json!({"content_type": "text/plain", "delivery_mode": 2,
                           "headers": {"a": 1}, "type": "kind", "priority": "5"});
        let p = properties(Some(&value)).unwrap();
        assert!(p.is_persistent());
        assert_eq!(p.priority, Some(5));
        let back = properties_json(&p);
        assert_eq!(back["type"], json!("kind"));
        assert_eq!(back["headers"], json!({"a": 1}));
        assert!(properties(Some(&json!({"colour": "red"}))).is_err());
        assert!(properties(Some(&json!({"delivery_mode": 7}))).is_err());
    }

    #[test]
    fn payloads_are_text_when_they_can_be() {
        assert_eq!(payload(b"hello", false), (json!("hello"), "string"));
        assert_eq!(payload(&[0xff, 0], false), (json!("/wA="), "base64"));
        assert_eq!(payload(b"hi", true), (json!("aGk="), "base64"));
    }
}
