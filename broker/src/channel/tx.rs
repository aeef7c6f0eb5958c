//! Transactions: tx.select, commit (through the vhost's all-or-none
//! publish) and rollback.

use super::basic::{apply_settles, requeue_all, Settle};
use super::confirms::Confirms;
use super::{Channel, Publish};
use crate::alarm::memory::MemoryGauge;
use crate::error::{AmqpError, AmqpResult};
use crate::queue::Unacked;
use crate::registry::ChannelMode;
use crate::slice::{yield_if_spent, Slice};
use leveret_protocol::{TxCommitOk, TxRollbackOk, TxSelectOk};
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
        // Route everything first; the vhost writes every stored message of
        // the commit in one atomic submission before any becomes visible
        // to consumers (whose acks must reach the store after the entries
        // they remove).
        let publishes = std::mem::take(&mut tx.publishes);
        let mut batch = Vec::with_capacity(publishes.len());
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
            batch.push((message, queues));
        }
        let written = self.vhost.publish_all_or_none(batch).await;
        self.vhost
            .dead_letter(apply_settles(std::mem::take(&mut tx.settles)));
        self.after_settles();
        if let Some(persistence) = &self.core.persistence {
            if !persistence.wait_written(written).await {
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

    /// Shows the listings what the channel holds: publishes awaiting
    /// their confirm, publishes and acks held by its transaction.
    pub(super) fn note_pending(&self) {
        let unconfirmed = self.confirms.as_ref().map_or(0, Confirms::len);
        let (messages, acks) = self
            .tx
            .as_ref()
            .map_or((0, 0), |tx| (tx.publishes.len(), tx.settles.len()));
        self.registration.set_pending(unconfirmed, messages, acks);
    }
}
