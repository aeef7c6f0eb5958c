//! Transactions (tx.select, commit, rollback) and publisher confirms
//! (confirm.select, and the acks and nacks that answer publishes). Acks
//! are coalesced: consecutive positive confirms are sent as one basic.ack
//! with `multiple` once the connection has no more input buffered.

use super::basic::{apply_settles, requeue_all, Outcome, Settle};
use super::{Channel, Publish};
use crate::alarm::memory::MemoryGauge;
use crate::error::{AmqpError, AmqpResult};
use crate::queue::{DeadLetters, Enqueued, Queue, Unacked};
use crate::registry::ChannelMode;
use crate::slice::{yield_if_spent, Slice};
use leveret_protocol::{
    BasicAck, BasicNack, ConfirmSelectOk, TxCommitOk, TxRollbackOk, TxSelectOk,
};
use std::collections::VecDeque;
use std::sync::Arc;

/// Work held by a transactional channel until commit. The publishes it
/// holds count in the broker's memory gauge, as queued messages do, and
/// one transaction may hold at most a quarter of the memory watermark: a
/// client publishing without ever committing gets a channel error instead
/// of growing the broker without bound, and cannot by itself keep the
/// memory alarm (which stops reading its connection, commit included) set.
#[derive(Debug)]
pub(crate) struct Transaction {
    publishes: Vec<Publish>,
    pub(super) settles: Vec<(Unacked, Settle)>,
    gauge: Arc<MemoryGauge>,
    held_bytes: usize,
}

impl Transaction {
    fn new(gauge: &Arc<MemoryGauge>) -> Self {
        Transaction {
            publishes: Vec::new(),
            settles: Vec::new(),
            gauge: Arc::clone(gauge),
            held_bytes: 0,
        }
    }

    /// Holds a publish until commit, if the transaction stays within
    /// `limit` bytes.
    pub(super) fn hold(&mut self, publish: Publish, limit: usize) -> AmqpResult<()> {
        let weight = publish.weight();
        if self.held_bytes + weight > limit {
            return Err(AmqpError::precondition_failed(format_args!(
                "transaction too large: more than {limit} bytes of uncommitted publishes"
            )));
        }
        self.gauge.add(weight);
        self.held_bytes += weight;
        self.publishes.push(publish);
        Ok(())
    }
}

impl Drop for Transaction {
    fn drop(&mut self) {
        self.gauge.sub(self.held_bytes);
    }
}

/// Publisher-confirm state of a channel.
#[derive(Debug, Default)]
pub(crate) struct Confirms {
    last_tag: u64,
    /// Publishes not yet confirmed, in tag order, with what they wait for.
    waiting: VecDeque<(u64, Outcome)>,
}

impl Confirms {
    pub(super) fn next_tag(&mut self) -> u64 {
        self.last_tag += 1;
        self.last_tag
    }
}

impl Channel {
    pub(super) async fn tx_select(&mut self) -> AmqpResult<()> {
        if self.confirms.is_some() {
            return Err(AmqpError::precondition_failed(
                "cannot switch from confirm to tx mode",
            ));
        }
        if self.tx.is_none() {
            self.tx = Some(Transaction::new(&self.core.gauge));
            self.registration.set_mode(ChannelMode::Transactional);
        }
        self.reply(TxSelectOk {}).await;
        Ok(())
    }

    pub(super) async fn tx_commit(&mut self) -> AmqpResult<()> {
        let Some(mut tx) = self.tx.replace(Transaction::new(&self.core.gauge)) else {
            return Err(AmqpError::precondition_failed(
                "channel is not transactional",
            ));
        };
        self.note_pending();
        // Route everything first and write every stored message of the
        // commit in one submission, so it reaches the disk in one atomic
        // batch; only then do the messages become visible to consumers
        // (whose acks must reach the store after the entries they remove).
        let mut ops = Vec::new();
        let publishes = std::mem::take(&mut tx.publishes);
        let mut placed = Vec::with_capacity(publishes.len());
        let mut slice = Slice::start();
        for publish in publishes {
            yield_if_spent(&mut slice).await;
            let mut queues = Vec::new();
            // An exchange deleted before the commit: RabbitMQ drops the message.
            let Some(exchange) = self.vhost.exchange(&publish.method.exchange) else {
                continue;
            };
            let (message, returned) = self.route(&exchange, publish, &mut queues);
            if let Some(returned) = returned {
                self.send_return(returned).await;
            }
            ops.extend(message.record_op());
            let targets: Vec<(Arc<Queue>, Option<u64>)> = queues
                .into_iter()
                .map(|queue| {
                    let stored_here = queue.stores_messages() && message.stored.is_some();
                    let seq = stored_here.then(|| queue.reserve());
                    if let Some(seq) = seq {
                        ops.extend(queue.index_entry(seq, &message));
                    }
                    (queue, seq)
                })
                .collect();
            placed.push((message, targets));
        }
        let sync = match (&self.core.persistence, ops.is_empty()) {
            (Some(persistence), false) => persistence.submit_atomic(ops),
            _ => 0,
        };
        let mut dead = DeadLetters::default();
        // A stream appends at its publish and names the sync to wait for.
        let mut sync = sync;
        for (message, targets) in placed {
            for (queue, seq) in targets {
                let (enqueued, dead_here) = match seq {
                    Some(seq) => queue.publish_reserved(Arc::clone(&message), seq),
                    None => queue.publish(Arc::clone(&message)),
                };
                if let Enqueued::Accepted { sync: own } = enqueued {
                    sync = sync.max(own);
                }
                dead.append(dead_here);
                yield_if_spent(&mut slice).await;
            }
        }
        dead.append(apply_settles(std::mem::take(&mut tx.settles)));
        self.vhost.dead_letter(dead);
        self.after_settles();
        if let (Some(persistence), true) = (&self.core.persistence, sync > 0) {
            if !persistence.wait(sync).await {
                return Err(AmqpError::resource_error(
                    "could not write the transaction to disk",
                ));
            }
        }
        self.reply(TxCommitOk {}).await;
        Ok(())
    }

    pub(super) async fn tx_rollback(&mut self) -> AmqpResult<()> {
        let Some(mut tx) = self.tx.replace(Transaction::new(&self.core.gauge)) else {
            return Err(AmqpError::precondition_failed(
                "channel is not transactional",
            ));
        };
        self.note_pending();
        // Rolled-back acks leave their deliveries unacked on the channel.
        self.link
            .deliveries()
            .restore(std::mem::take(&mut tx.settles).into_iter().map(|(u, _)| u));
        self.reply(TxRollbackOk {}).await;
        Ok(())
    }

    /// Drops uncommitted work; held acks go back to their queues with the
    /// channel's other unacked messages.
    pub(super) fn abandon_tx(&mut self) {
        if let Some(mut tx) = self.tx.take() {
            let settles = std::mem::take(&mut tx.settles);
            let dead = requeue_all(settles.into_iter().map(|(u, _)| u).collect());
            self.vhost.dead_letter(dead);
        }
    }

    pub(super) async fn confirm_select(&mut self, no_wait: bool) -> AmqpResult<()> {
        if self.tx.is_some() {
            return Err(AmqpError::precondition_failed(
                "cannot switch from tx to confirm mode",
            ));
        }
        if self.confirms.is_none() {
            self.confirms = Some(Confirms::default());
            self.registration.set_mode(ChannelMode::Confirm);
        }
        if !no_wait {
            self.reply(ConfirmSelectOk {}).await;
        }
        Ok(())
    }

    /// Records the outcome of publish `tag`; it is confirmed by the next
    /// [`Channel::flush_confirms`] that finds it (and all before it) settled.
    pub(super) fn confirm(&mut self, tag: u64, outcome: Outcome) {
        if let Some(confirms) = &mut self.confirms {
            confirms.waiting.push_back((tag, outcome));
        }
        self.note_pending();
    }

    /// Shows the listings what the channel holds: publishes awaiting
    /// their confirm, publishes and acks held by its transaction.
    pub(super) fn note_pending(&self) {
        let unconfirmed = self.confirms.as_ref().map_or(0, |c| c.waiting.len());
        let (messages, acks) = self
            .tx
            .as_ref()
            .map_or((0, 0), |tx| (tx.publishes.len(), tx.settles.len()));
        self.registration.set_pending(unconfirmed, messages, acks);
    }

    /// Whether publishes wait for their confirm.
    pub fn has_waiting_confirms(&self) -> bool {
        self.confirms
            .as_ref()
            .is_some_and(|c| !c.waiting.is_empty())
    }

    /// Sends the confirms that are due, in tag order: consecutive acks as
    /// one basic.ack with `multiple`, nacks one by one. A publish waiting
    /// for the disk holds back those after it, so a multiple ack never
    /// covers a message that is not yet safe.
    pub async fn flush_confirms(&mut self) {
        let persistence = self.core.persistence.clone();
        let mut acks: Option<(u64, u64)> = None;
        let mut nacks = Vec::new();
        if let Some(confirms) = &mut self.confirms {
            while let Some(&(tag, outcome)) = confirms.waiting.front() {
                let ack = if outcome.refused {
                    false
                } else if outcome.sync == 0 && outcome.record == 0 {
                    true
                } else {
                    match &persistence {
                        Some(p) if p.flushed() >= outcome.sync.max(outcome.record) => {
                            [outcome.sync, outcome.record]
                                .into_iter()
                                .all(|number| number == 0 || p.succeeded(number))
                        }
                        _ => break,
                    }
                };
                confirms.waiting.pop_front();
                if ack {
                    self.core.stats.confirmed.inc();
                    acks = Some(acks.map_or((tag, tag), |(low, _)| (low, tag)));
                } else {
                    nacks.push((acks.take(), tag));
                }
            }
        }
        self.note_pending();
        for (before, tag) in nacks {
            if let Some((low, high)) = before {
                self.send_ack(low, high).await;
            }
            self.reply(BasicNack {
                delivery_tag: tag,
                multiple: false,
                requeue: false,
            })
            .await;
        }
        if let Some((low, high)) = acks {
            self.send_ack(low, high).await;
        }
    }

    async fn send_ack(&self, low: u64, high: u64) {
        self.reply(BasicAck {
            delivery_tag: high,
            multiple: high > low,
        })
        .await;
    }
}
