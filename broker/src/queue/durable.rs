//! A durable queue's side of persistence: the index entries of the
//! messages it holds, its delivery mark, and releasing what leaves it (see
//! `store` for the keys). Every write goes through the persister, whose
//! submission number says when it is on disk.

use super::{Queue, QueueState, QueuedMessage};
use crate::message::{Message, Stored};
use crate::store::{EntryBody, StoreOp};

impl Queue {
    /// Reserves the next place in this queue for a message whose index
    /// entry the caller writes itself ([`Queue::index_entry`]), so that a
    /// whole transaction reaches the disk in one batch. Places are taken in
    /// order by sequence number, whatever order they are filled in.
    pub fn reserve(&self) -> u64 {
        let mut st = self.lock();
        st.next_seq += 1;
        st.next_seq
    }

    /// The index entry for `message` at place `seq`, if this queue stores it.
    pub fn index_entry(&self, seq: u64, message: &Message) -> Option<StoreOp> {
        let (_, queue) = self.durable_store.as_ref()?;
        let body = match message.stored.as_ref()? {
            Stored::Inline => EntryBody::Inline(message.to_record()),
            Stored::Shared { id, .. } => EntryBody::Shared(*id),
        };
        Some(StoreOp::Enqueue {
            queue: *queue,
            seq,
            body,
        })
    }

    /// This queue's id in the store, if it is durable and persisted.
    pub fn store_id(&self) -> Option<u64> {
        self.durable_store.as_ref().map(|(_, id)| *id)
    }

    /// Writes the index entry of a stored message; returns the submission
    /// number (0 if the message is not stored in this queue).
    pub(super) fn log(&self, queued: &QueuedMessage) -> u64 {
        match (
            &self.durable_store,
            self.index_entry(queued.seq, &queued.message),
        ) {
            (Some((persistence, _)), Some(op)) => persistence.submit(vec![op]),
            _ => 0,
        }
    }

    /// Raises the delivery mark, so a restart brings this message back
    /// flagged redelivered.
    pub(super) fn log_delivery(&self, st: &mut QueueState, queued: &QueuedMessage) {
        if let Some(seq) = self.raise_delivery_mark(st, queued) {
            self.log_delivery_mark(seq);
        }
    }

    /// Raises the delivery mark in memory; the position to record in the
    /// store, if the mark rose over a stored message. A dispatch records
    /// only the highest of its deliveries ([`Queue::log_delivery_mark`]),
    /// after it has sent them: an ack of one of them taken by another
    /// thread meanwhile may reach the disk first, so a crash between the
    /// two can bring back an earlier message of that pass not flagged
    /// redelivered (the flag is a hint; no message is lost).
    pub(super) fn raise_delivery_mark(
        &self,
        st: &mut QueueState,
        queued: &QueuedMessage,
    ) -> Option<u64> {
        if queued.seq <= st.delivered_mark {
            return None;
        }
        st.delivered_mark = queued.seq;
        (self.durable_store.is_some() && queued.message.stored.is_some()).then_some(queued.seq)
    }

    /// Records the delivery mark at `seq` in the store.
    pub(super) fn log_delivery_mark(&self, seq: u64) {
        if let Some((persistence, queue)) = &self.durable_store {
            persistence.submit(vec![StoreOp::Delivered { queue: *queue, seq }]);
        }
    }

    /// A message this queue was offered but does not keep: removes its
    /// index entry if one was written at a reserved place, and the shared
    /// record if this was its last queue. Returns the removal's submission
    /// number (0 if nothing was removed).
    pub(super) fn unlog(&self, message: &Message, reserved: Option<u64>) -> u64 {
        let (Some((persistence, queue)), Some(stored)) = (&self.durable_store, &message.stored)
        else {
            return 0;
        };
        let mut ops = Vec::new();
        if let Some(seq) = reserved {
            ops.push(StoreOp::Dequeue { queue: *queue, seq });
        }
        if let Some(id) = stored.release() {
            ops.push(StoreOp::DeleteMessage { id });
        }
        if ops.is_empty() {
            return 0;
        }
        persistence.submit(ops)
    }

    /// A message leaves this queue for good: release its memory and its
    /// index entry (and the shared record, if no other queue holds it).
    pub(super) fn release(&self, queued: &QueuedMessage) {
        self.release_all(std::slice::from_ref(queued));
    }

    /// Messages leave this queue for good (an ack of several): each as
    /// [`Queue::release`] says, in one submission.
    pub(super) fn release_all(&self, leaving: &[QueuedMessage]) {
        let mut ops = Vec::new();
        for (at, queued) in leaving.iter().enumerate() {
            self.gauge.sub(queued.message.weight());
            let (Some((_, queue)), Some(stored)) = (&self.durable_store, &queued.message.stored)
            else {
                continue;
            };
            if ops.is_empty() {
                // Sized for the usual one op per message (growing it
                // showed in profiles under persistent load).
                ops.reserve(leaving.len() - at);
            }
            ops.push(StoreOp::Dequeue {
                queue: *queue,
                seq: queued.seq,
            });
            if let Some(id) = stored.release() {
                ops.push(StoreOp::DeleteMessage { id });
            }
        }
        if let (Some((persistence, _)), false) = (&self.durable_store, ops.is_empty()) {
            persistence.submit(ops);
        }
    }
}
