//! Start-up recovery: rebuilds durable exchanges, queues (with their
//! persistent messages in order, redelivered where they had been delivered)
//! and bindings from what the store read back, and removes what a crash
//! left half-deleted (entries of deleted queues, bodies no queue holds).

use crate::core::Core;
use crate::message::{Message, StoredBody};
use crate::queue::QueuedMessage;
use crate::store::{Recovered, StoreOp};
use leveret_protocol::BasicProperties;
use std::collections::HashMap;
use std::sync::Arc;

/// Counts of what was recovered, for the log.
#[derive(Debug, Default, Clone, Copy)]
pub struct RecoveryReport {
    /// Durable exchanges.
    pub exchanges: usize,
    /// Durable queues.
    pub queues: usize,
    /// Bindings.
    pub bindings: usize,
    /// Queued message copies.
    pub messages: usize,
}

/// Applies `recovered` to `core`.
pub fn recover(core: &Core, mut recovered: Recovered) -> RecoveryReport {
    let mut report = RecoveryReport::default();
    let mut cleanup = Vec::new();
    for record in &recovered.exchanges {
        core.vhost_or_create(&record.vhost).restore_exchange(record);
        report.exchanges += 1;
    }
    // References per body, from the queues that still exist.
    let known: std::collections::HashSet<u64> = recovered.queues.iter().map(|q| q.id).collect();
    let mut refs: HashMap<u64, usize> = HashMap::new();
    for (queue, entries) in &recovered.entries {
        for entry in entries {
            if known.contains(queue) && recovered.messages.contains_key(&entry.message) {
                *refs.entry(entry.message).or_default() += 1;
            } else {
                cleanup.push(StoreOp::Dequeue {
                    queue: *queue,
                    seq: entry.seq,
                });
            }
        }
    }
    let mut bodies: HashMap<u64, Arc<Message>> = HashMap::new();
    for record in &recovered.queues {
        let vhost = core.vhost_or_create(&record.vhost);
        let Some(queue) = vhost.restore_queue(record) else {
            continue;
        };
        report.queues += 1;
        let entries = recovered.entries.remove(&record.id).unwrap_or_default();
        let mut restored = Vec::with_capacity(entries.len());
        for entry in entries {
            let Some(count) = refs.get(&entry.message).copied() else {
                continue;
            };
            let message = bodies.entry(entry.message).or_insert_with(|| {
                let stored = &recovered.messages[&entry.message];
                let properties = BasicProperties::decode(&stored.properties).unwrap_or_default();
                Arc::new(Message {
                    exchange: stored.exchange.clone(),
                    routing_key: stored.routing_key.clone(),
                    properties: stored.properties.clone(),
                    body: stored.body.clone(),
                    persistent: true,
                    priority: properties.priority.unwrap_or(0),
                    ttl_ms: properties
                        .expiration
                        .as_ref()
                        .and_then(|e| e.as_str())
                        .and_then(|e| e.parse().ok()),
                    stored: Some(StoredBody::new(entry.message, count)),
                })
            });
            let ttl = match (queue.args.message_ttl, message.ttl_ms) {
                (Some(a), Some(b)) => Some(a.min(b)),
                (a, b) => a.or(b),
            };
            restored.push(QueuedMessage {
                seq: entry.seq,
                priority: queue
                    .args
                    .max_priority
                    .map_or(0, |max| message.priority.min(max)),
                message: Arc::clone(message),
                redelivered: entry.delivered,
                expires_at: ttl
                    .map(|ms| std::time::Instant::now() + std::time::Duration::from_millis(ms)),
            });
        }
        report.messages += restored.len();
        queue.restore(restored);
    }
    for id in recovered.messages.keys() {
        if !refs.contains_key(id) {
            cleanup.push(StoreOp::DeleteMessage { id: *id });
        }
    }
    for record in &recovered.bindings {
        if core.vhost_or_create(&record.vhost).restore_binding(record) {
            report.bindings += 1;
        } else {
            cleanup.push(StoreOp::DeleteBinding(record.clone()));
        }
    }
    if let (Some(persistence), false) = (&core.persistence, cleanup.is_empty()) {
        tracing::info!(
            entries = cleanup.len(),
            "removing what an interrupted delete left behind"
        );
        persistence.submit(cleanup);
    }
    report
}
