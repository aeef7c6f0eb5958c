//! Transactions (tx.select, commit, rollback) and publisher confirms
//! (confirm.select, and the acks and nacks that answer publishes). Acks
//! are coalesced: consecutive positive confirms are sent as one basic.ack
//! with `multiple` once the connection has no more input buffered.

use super::basic::{apply_settles, requeue_all, Settle};
use super::{Channel, Publish};
use crate::consumer::Unacked;
use crate::error::{AmqpError, AmqpResult};
use leveret_protocol::{
    BasicAck, BasicNack, ConfirmSelectOk, TxCommitOk, TxRollbackOk, TxSelectOk,
};

/// Work held by a transactional channel until commit.
#[derive(Debug, Default)]
pub(crate) struct Transaction {
    pub(super) publishes: Vec<Publish>,
    pub(super) settles: Vec<(Unacked, Settle)>,
}

/// Publisher-confirm state of a channel.
#[derive(Debug, Default)]
pub(crate) struct Confirms {
    last_tag: u64,
    /// Highest tag acked but not yet sent, and the lowest in that run.
    pending: Option<(u64, u64)>,
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
            self.tx = Some(Transaction::default());
        }
        self.reply(TxSelectOk {}).await;
        Ok(())
    }

    pub(super) async fn tx_commit(&mut self) -> AmqpResult<()> {
        let Some(tx) = self.tx.replace(Transaction::default()) else {
            return Err(AmqpError::precondition_failed(
                "channel is not transactional",
            ));
        };
        for publish in tx.publishes {
            self.route_and_enqueue(publish).await;
        }
        apply_settles(tx.settles);
        self.reply(TxCommitOk {}).await;
        Ok(())
    }

    pub(super) async fn tx_rollback(&mut self) -> AmqpResult<()> {
        let Some(tx) = self.tx.replace(Transaction::default()) else {
            return Err(AmqpError::precondition_failed(
                "channel is not transactional",
            ));
        };
        // Rolled-back acks leave their deliveries unacked on the channel.
        self.link
            .deliveries()
            .restore(tx.settles.into_iter().map(|(u, _)| u));
        self.reply(TxRollbackOk {}).await;
        Ok(())
    }

    /// Drops uncommitted work; held acks go back to their queues with the
    /// channel's other unacked messages.
    pub(super) fn abandon_tx(&mut self) {
        if let Some(tx) = self.tx.take() {
            requeue_all(tx.settles.into_iter().map(|(u, _)| u).collect());
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
        }
        if !no_wait {
            self.reply(ConfirmSelectOk {}).await;
        }
        Ok(())
    }

    /// Records the outcome of publish `tag`: acks wait to be coalesced,
    /// a nack flushes them and goes out at once.
    pub(super) async fn confirm(&mut self, tag: u64, accepted: bool) {
        let Some(confirms) = &mut self.confirms else {
            return;
        };
        if accepted {
            confirms.pending = Some(match confirms.pending {
                Some((low, _)) => (low, tag),
                None => (tag, tag),
            });
            return;
        }
        self.flush_confirms().await;
        self.reply(BasicNack {
            delivery_tag: tag,
            multiple: false,
            requeue: false,
        })
        .await;
    }

    /// Sends the coalesced acks.
    pub async fn flush_confirms(&mut self) {
        let Some(confirms) = &mut self.confirms else {
            return;
        };
        let Some((low, high)) = confirms.pending.take() else {
            return;
        };
        self.reply(BasicAck {
            delivery_tag: high,
            multiple: high > low,
        })
        .await;
    }
}
