//! A routed message's publish step, the one owner of its durable write:
//! every publisher (a channel's basic.publish and tx.commit, dead-lettering,
//! `Admin::publish`) hands the message and the queues it was routed to
//! here, and gets back what its confirm waits for ([`Published`]).
//!
//! The step writes the message's shared record (when several durable
//! queues keep it), then offers it to each queue, which writes its own
//! index entry. The two writes stay apart on purpose, in this order:
//! - the record is submitted before any entry that names it, so a group
//!   on disk that holds an entry holds its record or follows one that did;
//! - an entry is submitted by its queue under the queue's lock, so no
//!   dequeue of the message (which needs it delivered first, under the
//!   same lock) can reach the store before it.
//!
//! A transaction's commit ([`Vhost::publish_all_or_none`]) instead reserves
//! each queue's place, writes every record and entry of the commit in one
//! atomic submission, and only then offers the messages at their places:
//! no consumer can see (and ack) them before the submission is made.
//!
//! A fanout to thousands of queues is offered a slice at a time
//! ([`Vhost::publish_step`]); the caller yields between slices.

use super::Vhost;
use crate::message::{Message, Stored};
use crate::queue::{DeadLetters, Enqueued, Queue};
use crate::slice::{yield_if_spent, Progress, Slice};
use crate::store::Written;
use std::sync::Arc;

/// What a publish left for its confirm.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct Published {
    /// A queue refused it (overflow `reject-publish`): nack.
    pub refused: bool,
    /// The store writes it made, on disk before it may be confirmed.
    pub written: Written,
}

impl Published {
    fn add(&mut self, enqueued: Enqueued) {
        match enqueued {
            Enqueued::Accepted { sync } => self.written.add(sync),
            Enqueued::Refused { sync } => {
                self.refused = true;
                self.written.add(sync);
            }
        }
    }
}

/// A publish under way: the message, the queues it was routed to, and
/// how far it has got.
#[derive(Debug)]
pub struct Publishing {
    message: Arc<Message>,
    queues: Vec<Arc<Queue>>,
    /// How many of `queues` have been offered it.
    next: usize,
    outcome: Published,
    dead: DeadLetters,
    /// The first queue it reached that is over the flow limit.
    crowded: Option<Arc<Queue>>,
}

impl Publishing {
    /// `message` routed to `queues` (a buffer the caller gets back from
    /// [`Vhost::published`]), not yet offered to any.
    pub fn new(message: Arc<Message>, queues: Vec<Arc<Queue>>) -> Self {
        Publishing {
            message,
            queues,
            next: 0,
            outcome: Published::default(),
            dead: DeadLetters::default(),
            crowded: None,
        }
    }

    /// A queue it reached that is over the flow limit, once: the
    /// publisher's connection waits for it to drain before reading more.
    pub fn take_crowded(&mut self) -> Option<Arc<Queue>> {
        self.crowded.take()
    }

    /// The dead letters its queues have returned so far.
    pub fn take_dead_letters(&mut self) -> DeadLetters {
        std::mem::take(&mut self.dead)
    }
}

impl Vhost {
    /// How a message routed to `queues` is kept in the store: as nothing
    /// unless it is persistent and a queue stores messages, inline in the
    /// index entry of its one durable queue, or as a record of its own
    /// shared by several. Decided before the message is built.
    pub fn storage(&self, persistent: bool, queues: &[Arc<Queue>]) -> Option<Stored> {
        match &self.persistence {
            Some(persistence) if persistent => Stored::for_queues(
                persistence,
                queues.iter().filter(|q| q.stores_messages()).count(),
            ),
            _ => None,
        }
    }

    /// Offers the message to its next queues until all have been offered
    /// it or `slice` is spent; the first step writes its shared record
    /// first (see the module's docs for the order).
    pub fn publish_step(&self, publishing: &mut Publishing, slice: &mut Slice) -> Progress {
        if publishing.next == 0 {
            if let (Some(persistence), Some(op)) =
                (&self.persistence, publishing.message.record_op())
            {
                publishing.outcome.written.add(persistence.submit(vec![op]));
            }
        }
        while let Some(queue) = publishing.queues.get(publishing.next) {
            publishing.next += 1;
            let (enqueued, dead_here) = queue.publish(Arc::clone(&publishing.message));
            publishing.outcome.add(enqueued);
            publishing.dead.append(dead_here);
            if publishing.crowded.is_none() && queue.is_crowded() {
                publishing.crowded = Some(Arc::clone(queue));
            }
            if slice.step() && publishing.next < publishing.queues.len() {
                return Progress::More;
            }
        }
        Progress::Done
    }

    /// A publish offered to all its queues: routes its dead letters, and
    /// returns its outcome and the emptied queue buffer, for reuse.
    pub fn published(self: &Arc<Self>, publishing: Publishing) -> (Published, Vec<Arc<Queue>>) {
        let Publishing {
            mut queues,
            outcome,
            dead,
            ..
        } = publishing;
        queues.clear();
        self.dead_letter(dead);
        (outcome, queues)
    }

    /// A whole publish, yielding between slices.
    pub async fn publish(
        self: &Arc<Self>,
        message: Arc<Message>,
        queues: Vec<Arc<Queue>>,
    ) -> Published {
        let mut publishing = Publishing::new(message, queues);
        while self.publish_step(&mut publishing, &mut Slice::start()) == Progress::More {
            tokio::task::yield_now().await;
        }
        self.published(publishing).0
    }

    /// A transaction's publishes, each message with the queues it was
    /// routed to: every shared record and index entry goes to the store in
    /// one atomic submission, made before any queue takes its message
    /// (see the module's docs). A refusal is not reported: a transaction
    /// has no nack; the returned span covers the removal a refusal submits.
    /// Yields when a slice is spent.
    pub async fn publish_all_or_none(
        self: &Arc<Self>,
        batch: Vec<(Arc<Message>, Vec<Arc<Queue>>)>,
    ) -> Written {
        let mut slice = Slice::start();
        let mut ops = Vec::new();
        let mut placed = Vec::with_capacity(batch.len());
        for (message, queues) in batch {
            ops.extend(message.record_op());
            let mut targets = Vec::with_capacity(queues.len());
            for queue in queues {
                let stored_here = queue.stores_messages() && message.stored.is_some();
                let seq = stored_here.then(|| queue.reserve());
                if let Some(seq) = seq {
                    ops.extend(queue.index_entry(seq, &message));
                }
                targets.push((queue, seq));
                yield_if_spent(&mut slice).await;
            }
            placed.push((message, targets));
        }
        let mut written = Written::default();
        if let (Some(persistence), false) = (&self.persistence, ops.is_empty()) {
            written.add(persistence.submit_atomic(ops));
        }
        let mut dead = DeadLetters::default();
        for (message, targets) in placed {
            for (queue, seq) in targets {
                let (enqueued, dead_here) = match seq {
                    Some(seq) => queue.publish_reserved(Arc::clone(&message), seq),
                    None => queue.publish(Arc::clone(&message)),
                };
                // A stream appends at its publish and names the sync to
                // wait for; a refusal (or a queue deleted meanwhile) names
                // the removal of the entry reserved above, which the
                // commit must not outrun.
                let (Enqueued::Accepted { sync } | Enqueued::Refused { sync }) = enqueued;
                written.add(sync);
                dead.append(dead_here);
                yield_if_spent(&mut slice).await;
            }
        }
        self.dead_letter(dead);
        written
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::exchange::ExchangeKind;
    use crate::queue::Queue;
    use crate::store::{EntryBody, Recovered, Store};
    use crate::testkit::{message, s, Gated, Harness, RecordingStore};
    use leveret_protocol::{BasicProperties, FieldValue};
    use std::collections::HashMap;

    fn persistent() -> BasicProperties {
        BasicProperties {
            delivery_mode: Some(2),
            ..BasicProperties::default()
        }
    }

    /// A persistent message routed to `queues`, marked for storage as a
    /// publisher marks it.
    fn stored_message(h: &Harness, queues: &[Arc<Queue>], body: &str) -> Arc<Message> {
        let copy = message(&s("fan"), "", body, &persistent());
        let stored = h.vhost.storage(true, queues);
        Arc::new(copy.stored_as(stored))
    }

    /// A fanout exchange `fan` bound to two durable queues and a
    /// transient one.
    fn fanout(h: &Harness) -> Vec<Arc<Queue>> {
        h.exchange("fan", ExchangeKind::Fanout);
        let queues = vec![
            h.declare_queue("kept-a", true, &[]),
            h.declare_queue("kept-b", true, &[]),
            h.declare_queue("passing", false, &[]),
        ];
        for queue in &queues {
            h.bind(queue, "fan", "");
        }
        queues
    }

    fn entries_of(recovered: &Recovered, queue: &Queue) -> Vec<EntryBody> {
        let id = queue.store_id().expect("a durable queue");
        recovered
            .entries
            .get(&id)
            .map(|entries| entries.iter().map(|e| e.body.clone()).collect())
            .unwrap_or_default()
    }

    /// The one owner of the durable write: once the outcome says written,
    /// the shared record and every durable queue's entry are in the store,
    /// and nothing else is (the transient queue writes none).
    #[tokio::test]
    async fn a_publish_is_on_disk_when_its_outcome_is_written() {
        let store = Arc::new(Gated::default());
        store.hold(true);
        let h = Harness::durable_over(Arc::clone(&store) as Arc<dyn Store>);
        let queues = fanout(&h);
        let message = stored_message(&h, &queues, "kept");
        let Some(Stored::Shared { id, .. }) = &message.stored else {
            panic!("two durable queues share one record: {:?}", message.stored);
        };
        let id = *id;
        let published = h.vhost.publish(message, queues.clone()).await;
        assert!(!published.refused);
        assert!(published.written.last() > 0, "it wrote something");
        let persistence = h.persistence.as_ref().expect("a persister");
        assert_eq!(
            persistence.written(published.written),
            None,
            "not written while the store holds the write"
        );
        store.hold(false);
        assert!(persistence.wait_written(published.written).await);
        let recovered = h.stored();
        assert_eq!(recovered.messages.len(), 1);
        assert!(recovered.messages.contains_key(&id));
        for queue in &queues[..2] {
            assert!(matches!(
                entries_of(&recovered, queue)[..],
                [EntryBody::Shared(entry)] if entry == id
            ));
        }
        for queue in &queues {
            assert_eq!(queue.message_count(), 1, "{} has it", queue.name);
        }
    }

    /// A fanout offered in slices: each step stops when its slice is
    /// spent, the record is written once, at the first step, and the
    /// outcome covers every queue's entry.
    #[tokio::test]
    async fn a_fanout_goes_a_slice_at_a_time_and_writes_its_record_once() {
        let store = Arc::new(RecordingStore::default());
        let h = Harness::durable_over(Arc::clone(&store) as Arc<dyn Store>);
        let queues = fanout(&h);
        let mut publishing = Publishing::new(stored_message(&h, &queues, "sliced"), queues.clone());
        let spent = || {
            let mut slice = Slice::start();
            assert!(!slice.is_spent(), "the clock starts at the first reading");
            std::thread::sleep(crate::slice::SLICE + std::time::Duration::from_millis(1));
            assert!(slice.is_spent());
            slice
        };
        assert_eq!(
            h.vhost.publish_step(&mut publishing, &mut spent()),
            Progress::More
        );
        let counts = || queues.iter().map(|q| q.message_count()).collect::<Vec<_>>();
        assert_eq!(counts(), [1, 0, 0], "one queue per spent slice");
        assert_eq!(
            h.vhost.publish_step(&mut publishing, &mut spent()),
            Progress::More
        );
        assert_eq!(
            h.vhost.publish_step(&mut publishing, &mut spent()),
            Progress::Done
        );
        assert_eq!(counts(), [1, 1, 1]);
        let (published, buffer) = h.vhost.published(publishing);
        assert!(buffer.is_empty(), "the buffer comes back empty, for reuse");
        let persistence = h.persistence.as_ref().expect("a persister");
        assert!(persistence.wait_written(published.written).await);
        let recovered = h.stored();
        assert_eq!(recovered.messages.len(), 1, "one shared record");
        // The record, both entries and the queues' declarations: each key
        // once (a record written at every step would be counted thrice).
        let mut puts: HashMap<Vec<u8>, usize> = HashMap::new();
        for (key, _) in store.written().into_iter().filter(|(_, put)| *put) {
            *puts.entry(key).or_default() += 1;
        }
        assert!(puts.len() >= 3, "{puts:?}");
        assert!(
            puts.values().all(|&count| count == 1),
            "each key is written once: {puts:?}"
        );
        assert_eq!(entries_of(&recovered, &queues[0]).len(), 1);
        assert_eq!(entries_of(&recovered, &queues[1]).len(), 1);
    }

    /// Queues that refuse the publish make the outcome a refusal (a
    /// nack), keep no entry of it, and the last to refuse removes the
    /// shared record written before they were offered it.
    #[tokio::test]
    async fn a_refusal_is_in_the_outcome_and_leaves_no_entry() {
        let h = Harness::durable();
        let limited = [
            ("x-max-length", FieldValue::I32(1)),
            ("x-overflow", FieldValue::string("reject-publish")),
        ];
        let full = h.declare_queue("full", true, &limited);
        let full_too = h.declare_queue("full-too", true, &limited);
        let queues = vec![Arc::clone(&full), Arc::clone(&full_too)];
        let first = h
            .vhost
            .publish(stored_message(&h, &queues, "one"), queues.clone())
            .await;
        let second = h
            .vhost
            .publish(stored_message(&h, &queues, "two"), queues.clone())
            .await;
        assert!(!first.refused);
        assert!(second.refused);
        let persistence = h.persistence.as_ref().expect("a persister");
        assert!(persistence.sync().await);
        let recovered = h.stored();
        assert_eq!(entries_of(&recovered, &full).len(), 1);
        assert_eq!(entries_of(&recovered, &full_too).len(), 1);
        assert_eq!(recovered.messages.len(), 1, "only the kept one's record");
        assert_eq!(full.message_count(), 1);
    }

    /// A transaction's publishes reach the store in one atomic submission,
    /// and the queues have them once the call returns.
    #[tokio::test]
    async fn a_commit_writes_every_record_and_entry_in_one_submission() {
        let h = Harness::durable();
        let queues = fanout(&h);
        let batch = vec![
            (stored_message(&h, &queues, "m1"), queues.clone()),
            (stored_message(&h, &queues, "m2"), queues.clone()),
        ];
        let written = h.vhost.publish_all_or_none(batch).await;
        assert!(written.last() > 0);
        let mut one = Written::default();
        one.add(written.last());
        assert_eq!(written, one, "one submission");
        let persistence = h.persistence.as_ref().expect("a persister");
        assert!(persistence.wait_written(written).await);
        let recovered = h.stored();
        assert_eq!(recovered.messages.len(), 2);
        assert_eq!(entries_of(&recovered, &queues[0]).len(), 2);
        assert_eq!(entries_of(&recovered, &queues[1]).len(), 2);
        assert_eq!(queues[2].message_count(), 2);
    }

    /// A transaction's message refused by a full durable queue: its entry,
    /// written in the atomic submission, is removed by a later one, and
    /// the commit's span covers that removal, so commit-ok never goes out
    /// while the refused entry is the last word on disk. The queue that
    /// took it keeps its entry and the shared record.
    #[tokio::test]
    async fn a_commit_waits_for_the_removal_of_what_a_queue_refused() {
        let h = Harness::durable();
        let full = h.declare_queue(
            "full",
            true,
            &[
                ("x-max-length", FieldValue::I32(1)),
                ("x-overflow", FieldValue::string("reject-publish")),
            ],
        );
        let other = h.declare_queue("other", true, &[]);
        let held = vec![Arc::clone(&full)];
        let before = h
            .vhost
            .publish(stored_message(&h, &held, "held"), held)
            .await;
        assert!(!before.refused);
        let queues = vec![Arc::clone(&full), Arc::clone(&other)];
        let message = stored_message(&h, &queues, "m");
        let Some(Stored::Shared { id, .. }) = &message.stored else {
            panic!("two durable queues share one record: {:?}", message.stored);
        };
        let id = *id;
        let written = h.vhost.publish_all_or_none(vec![(message, queues)]).await;
        let persistence = h.persistence.as_ref().expect("a persister");
        // The removal is the last submission made: the span must reach it.
        let next = persistence.submit(Vec::new());
        assert_eq!(written.last(), next - 1, "the commit waits for the removal");
        let mut atomic_only = Written::default();
        atomic_only.add(written.last() - 1);
        assert_ne!(written, atomic_only);
        assert!(persistence.wait_written(written).await);
        let recovered = h.stored();
        assert_eq!(entries_of(&recovered, &full).len(), 1, "only the held one");
        assert!(matches!(
            entries_of(&recovered, &other)[..],
            [EntryBody::Shared(entry)] if entry == id
        ));
        assert!(
            recovered.messages.contains_key(&id),
            "other keeps the record"
        );
        assert_eq!(full.message_count(), 1);
        assert_eq!(other.message_count(), 1);
    }

    /// A transient message or one reaching no durable queue writes nothing:
    /// its confirm waits for no disk.
    #[tokio::test]
    async fn a_publish_that_stores_nothing_waits_for_nothing() {
        let h = Harness::durable();
        let queues = fanout(&h);
        assert!(h.vhost.storage(false, &queues).is_none());
        assert!(h.vhost.storage(true, &queues[2..]).is_none());
        assert!(matches!(
            h.vhost.storage(true, &queues[..1]),
            Some(Stored::Inline)
        ));
        let transient = message(&s("fan"), "", "t", &BasicProperties::default());
        let published = h.vhost.publish(transient, queues.clone()).await;
        assert_eq!(published, Published::default());
        assert!(h.stored().messages.is_empty());
    }
}
