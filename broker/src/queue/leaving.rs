//! What leaves a queue for somewhere else: dead letters (the copy of a
//! message bound for the queue's dead-letter exchange, with RabbitMQ's
//! `x-death` history and `x-first-death-*` headers and without its
//! `expiration`, so it does not expire again), returned to the caller to
//! route; and the basic.cancel a deleted queue's consumers are sent.

use super::{Consumer, Queue, QueuedMessage};
use crate::message::Message;
use crate::outbox::Outbound;
pub use crate::stats::DeadLetterReason;
use crate::stats::DeadLetterStrategy;
use bytes::BytesMut;
use leveret_protocol::{BasicCancel, BasicProperties, FieldTable, FieldValue, ShortStr};
use std::sync::Arc;
use std::time::{SystemTime, UNIX_EPOCH};

/// A message leaving a queue for its dead-letter exchange.
#[derive(Debug)]
pub struct DeadLetter {
    message: Arc<Message>,
    reason: DeadLetterReason,
    /// The queue it leaves.
    queue: ShortStr,
    /// The queue's dead-letter exchange.
    exchange: ShortStr,
    /// The routing key it is dead-lettered with.
    routing_key: ShortStr,
}

impl DeadLetter {
    /// The exchange it is to be published to.
    pub fn exchange(&self) -> &ShortStr {
        &self.exchange
    }

    /// Why it left its queue.
    pub fn reason(&self) -> DeadLetterReason {
        self.reason
    }

    /// The copy to route: the message with RabbitMQ's `x-death` history
    /// (see [`with_death`]), and that copy's headers.
    pub fn into_copy(self) -> (Arc<Message>, FieldTable) {
        with_death(
            &self.message,
            &self.queue,
            self.reason.as_str(),
            &self.exchange,
            &self.routing_key,
        )
    }
}

/// Messages that left a queue for its dead-letter exchange, returned by
/// the operation that made them leave: the caller routes them
/// (`Vhost::dead_letter`), since a queue does not know its vhost.
#[derive(Debug, Default)]
#[must_use = "dead letters must be routed by the caller (Vhost::dead_letter)"]
pub struct DeadLetters(pub(super) Vec<DeadLetter>);

impl DeadLetters {
    /// Whether there are none (the usual case).
    pub fn is_empty(&self) -> bool {
        self.0.is_empty()
    }

    /// Adds `other`'s dead letters after these.
    pub fn append(&mut self, mut other: DeadLetters) {
        self.0.append(&mut other.0);
    }
}

impl IntoIterator for DeadLetters {
    type Item = DeadLetter;
    type IntoIter = std::vec::IntoIter<DeadLetter>;

    fn into_iter(self) -> Self::IntoIter {
        self.0.into_iter()
    }
}

/// A deleted queue's ready-message count and the consumers it had.
#[derive(Debug, Default)]
#[must_use = "the deleted queue's consumers must be notified"]
pub struct Deleted {
    /// Ready messages the queue held.
    pub messages: u32,
    pub(super) consumers: Vec<Arc<Consumer>>,
}

impl Deleted {
    /// Sends basic.cancel to the consumers whose clients announced
    /// consumer_cancel_notify; returns the message count.
    pub fn notify(self) -> u32 {
        for consumer in self.consumers {
            let outbox = &consumer.channel.outbox;
            if outbox.cancel_notify() {
                let cancel = BasicCancel {
                    consumer_tag: consumer.tag.clone(),
                    no_wait: true,
                };
                if !outbox.try_send(Outbound::method(consumer.channel.id, cancel.into())) {
                    tracing::warn!(consumer = %consumer.tag, "could not tell a consumer its queue was deleted (no room, or its connection is closing)");
                }
            }
        }
        self.messages
    }
}

impl Queue {
    /// A message leaves the queue for good: dead-letter it if the queue has a
    /// dead-letter exchange, and release it.
    pub(super) fn discard(
        &self,
        queued: QueuedMessage,
        reason: DeadLetterReason,
        dead: &mut Vec<DeadLetter>,
    ) {
        self.release(&queued);
        self.dead_letter(queued.message, reason, dead);
    }

    /// Adds `message` to `dead` if the queue has a dead-letter exchange;
    /// counts it as dropped otherwise (`deadletter` counts the others).
    pub(super) fn dead_letter(
        &self,
        message: Arc<Message>,
        reason: DeadLetterReason,
        dead: &mut Vec<DeadLetter>,
    ) {
        let (exchange, routing_key) = {
            let target = self
                .dead_lettering
                .read()
                .unwrap_or_else(|e| e.into_inner());
            let Some(exchange) = target.0.clone() else {
                self.stats
                    .dead_lettered(reason, DeadLetterStrategy::Disabled);
                return;
            };
            let routing_key = target
                .1
                .clone()
                .unwrap_or_else(|| message.routing_key.clone());
            (exchange, routing_key)
        };
        dead.push(DeadLetter {
            message,
            reason,
            queue: self.name.clone(),
            exchange,
            routing_key,
        });
    }
}

fn long_str(s: &ShortStr) -> FieldValue {
    FieldValue::LongStr(s.clone().into_bytes())
}

/// The dead-lettered copy of `message`, leaving `queue` for `reason`,
/// to be routed through `exchange` with `routing_key`, and its headers.
fn with_death(
    message: &Message,
    queue: &ShortStr,
    reason: &str,
    exchange: &ShortStr,
    routing_key: &ShortStr,
) -> (Arc<Message>, FieldTable) {
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
    let headers = props.headers.take().unwrap_or_default();
    let copy = Arc::new(Message {
        exchange: exchange.clone(),
        routing_key: routing_key.clone(),
        properties: encoded.freeze(),
        body: message.body.clone(),
        persistent: message.persistent,
        priority: message.priority,
        ttl_ms: None,
        stored: None,
    });
    (copy, headers)
}
