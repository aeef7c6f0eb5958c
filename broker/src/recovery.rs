//! Start-up recovery: rebuilds durable exchanges, queues (with their
//! persistent messages in order, redelivered where they had been delivered)
//! and bindings from what the store read back, and removes what a crash
//! left half-deleted (entries of deleted queues, bodies no queue holds).

use crate::core::Core;
use crate::message::{Message, Stored};
use crate::queue::QueuedMessage;
use crate::store::{EntryBody, MessageRecord, Recovered, StoreOp};
use leveret_protocol::BasicProperties;
use std::collections::{HashMap, HashSet};
use std::sync::Arc;
use std::time::{Duration, Instant};

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

/// Builds a recovered message.
fn message(record: &MessageRecord, stored: Stored) -> Arc<Message> {
    // Properties were validated when the message was first published.
    let properties = BasicProperties::decode(&record.properties).unwrap_or_default();
    Arc::new(Message {
        exchange: record.exchange.clone(),
        routing_key: record.routing_key.clone(),
        properties: record.properties.clone(),
        body: record.body.clone(),
        persistent: true,
        priority: properties.priority.unwrap_or(0),
        ttl_ms: properties
            .expiration
            .as_ref()
            .and_then(|e| e.as_str())
            .and_then(|e| e.parse().ok()),
        stored: Some(stored),
    })
}

/// Applies `recovered` to `core`; a damaged stream is the error (what is
/// wrong, naming its file), unless the broker was told to recover.
pub fn recover(core: &Core, mut recovered: Recovered) -> Result<RecoveryReport, String> {
    let mut report = RecoveryReport::default();
    let mut cleanup = Vec::new();
    for record in &recovered.exchanges {
        core.vhost_or_create(&record.vhost).restore_exchange(record);
        report.exchanges += 1;
    }
    // Shared records: how many entries of existing queues refer to each.
    let known: HashSet<u64> = recovered.queues.iter().map(|q| q.id).collect();
    let mut refs: HashMap<u64, usize> = HashMap::new();
    let mut orphans = 0;
    for (queue, entries) in &mut recovered.entries {
        if !known.contains(queue) {
            orphans += entries.len();
        }
        entries.retain(|entry| {
            let keep = known.contains(queue)
                && match &entry.body {
                    EntryBody::Inline(_) => true,
                    EntryBody::Shared(id) => recovered.messages.contains_key(id),
                };
            if keep {
                if let EntryBody::Shared(id) = &entry.body {
                    *refs.entry(*id).or_default() += 1;
                }
            } else {
                cleanup.push(StoreOp::Dequeue {
                    queue: *queue,
                    seq: entry.seq,
                });
            }
            keep
        });
    }
    let mut shared: HashMap<u64, Arc<Message>> = HashMap::new();
    let now = Instant::now();
    for record in &recovered.queues {
        let vhost = core.vhost_or_create(&record.vhost);
        let Some(queue) = vhost.restore_queue(record)? else {
            continue;
        };
        report.queues += 1;
        let mark = recovered.delivered.get(&record.id).copied().unwrap_or(0);
        let entries = recovered.entries.remove(&record.id).unwrap_or_default();
        let mut restored = Vec::with_capacity(entries.len());
        for entry in entries {
            let message = match &entry.body {
                EntryBody::Inline(stored) => message(stored, Stored::Inline),
                EntryBody::Shared(id) => Arc::clone(shared.entry(*id).or_insert_with(|| {
                    message(&recovered.messages[id], Stored::shared(*id, refs[id]))
                })),
            };
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
                message,
                redelivered: entry.seq <= mark,
                expires_at: ttl.map(|ms| now + Duration::from_millis(ms)),
            });
        }
        report.messages += restored.len();
        queue.restore(restored, mark);
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
    if orphans > 0 {
        // After a clean stop this is damage, refused before (see
        // `store::integrity`); after a crash, a queue deleted just before
        // it whose messages' removal had not reached the disk.
        tracing::warn!(
            messages = orphans,
            "dropping stored messages of queues the database does not hold (a queue deleted \
             just before a crash)"
        );
    }
    if let (Some(persistence), false) = (&core.persistence, cleanup.is_empty()) {
        tracing::info!(
            entries = cleanup.len(),
            "removing what an interrupted delete left behind"
        );
        persistence.submit(cleanup);
    }
    Ok(report)
}
