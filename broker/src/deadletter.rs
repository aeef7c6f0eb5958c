//! Dead-lettering: the copy of a message that goes to a dead-letter
//! exchange, with RabbitMQ's `x-death` history and `x-first-death-*`
//! headers, and without its `expiration` (so it does not expire again).

use crate::message::Message;
use bytes::BytesMut;
use leveret_protocol::{BasicProperties, FieldTable, FieldValue, ShortStr};
use std::sync::Arc;
use std::time::{SystemTime, UNIX_EPOCH};

fn long_str(s: &ShortStr) -> FieldValue {
    FieldValue::LongStr(s.clone().into_bytes())
}

/// The dead-lettered copy of `message`, leaving `queue` for `reason`,
/// to be routed through `exchange` with `routing_key`.
pub fn with_death(
    message: &Message,
    queue: &ShortStr,
    reason: &str,
    exchange: &ShortStr,
    routing_key: &ShortStr,
) -> Arc<Message> {
    // The properties were validated when the message was published.
    let mut props = BasicProperties::decode(&message.properties).unwrap_or_default();
    // The expiration moves into x-death, so the copy does not expire again.
    let original_expiration = props.expiration.take();
    let mut headers = props.headers.take().unwrap_or_default();
    let now = SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map(|d| d.as_secs())
        .unwrap_or(0);
    let mut deaths = match headers.remove("x-death") {
        Some(FieldValue::Array(values)) => values,
        _ => Vec::new(),
    };
    let same = |entry: &FieldValue| match entry {
        FieldValue::Table(t) => {
            t.get("queue").and_then(FieldValue::as_bytes) == Some(queue.as_bytes())
                && t.get("reason").and_then(FieldValue::as_bytes) == Some(reason.as_bytes())
        }
        _ => false,
    };
    let entry = match deaths.iter().position(same) {
        Some(index) => {
            let mut entry = match deaths.remove(index) {
                FieldValue::Table(t) => t,
                _ => FieldTable::new(),
            };
            let count = entry.get("count").and_then(FieldValue::as_i64).unwrap_or(0);
            entry.insert(ShortStr::from_static("count"), FieldValue::I64(count + 1));
            entry.insert(ShortStr::from_static("time"), FieldValue::Timestamp(now));
            entry
        }
        None => {
            let mut entry: FieldTable = [
                (ShortStr::from_static("count"), FieldValue::I64(1)),
                (ShortStr::from_static("reason"), FieldValue::string(reason)),
                (ShortStr::from_static("queue"), long_str(queue)),
                (ShortStr::from_static("time"), FieldValue::Timestamp(now)),
                (
                    ShortStr::from_static("exchange"),
                    long_str(&message.exchange),
                ),
                (
                    ShortStr::from_static("routing-keys"),
                    FieldValue::Array(vec![long_str(&message.routing_key)]),
                ),
            ]
            .into_iter()
            .collect();
            if let Some(expiration) = &original_expiration {
                entry.insert(
                    ShortStr::from_static("original-expiration"),
                    long_str(expiration),
                );
            }
            entry
        }
    };
    deaths.insert(0, FieldValue::Table(entry));
    headers.insert(ShortStr::from_static("x-death"), FieldValue::Array(deaths));
    if headers.get("x-first-death-reason").is_none() {
        headers.insert(
            ShortStr::from_static("x-first-death-reason"),
            FieldValue::string(reason),
        );
        headers.insert(
            ShortStr::from_static("x-first-death-queue"),
            long_str(queue),
        );
        headers.insert(
            ShortStr::from_static("x-first-death-exchange"),
            long_str(&message.exchange),
        );
    }
    props.headers = Some(headers);
    let mut encoded = BytesMut::new();
    props.encode(&mut encoded);
    Arc::new(Message {
        exchange: exchange.clone(),
        routing_key: routing_key.clone(),
        properties: encoded.freeze(),
        body: message.body.clone(),
        persistent: message.persistent,
        priority: message.priority,
        ttl_ms: None,
        stored: None,
    })
}
