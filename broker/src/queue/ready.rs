//! A queue's ready messages in delivery order: by priority (highest
//! first) and then by publish order, with every operation's cost bounded
//! whatever the queue holds.
//!
//! Messages arriving in order (the usual case: each publish is later than
//! everything of its priority) go to the back of their priority level's
//! FIFO in O(1). Messages arriving out of order (requeued deliveries, a
//! transaction's reserved places) go to an ordered map in O(log n), never
//! into the middle of a FIFO, which would move up to the whole queue per
//! message. The head is the smaller of the highest non-empty level's front
//! and the map's first entry.
//!
//! Used only by the queue; uses nothing of the broker but the queued
//! message.

use super::QueuedMessage;
use std::collections::{BTreeMap, VecDeque};

type OrderKey = (std::cmp::Reverse<u8>, u64);

/// Entries a priority level's FIFO keeps room for after a burst drains,
/// while the queue is in use (an idle one gives all its room back:
/// [`Ready::release_idle_room`]).
const SPARE_READY: usize = 1024;

/// The ready messages of one queue.
#[derive(Debug, Default)]
pub(super) struct Ready {
    /// One FIFO per priority level, indexed by priority, each in publish
    /// order. Only level 0 without `x-max-priority`.
    levels: Vec<VecDeque<QueuedMessage>>,
    /// The highest level that may hold messages.
    top: usize,
    /// Messages that arrived out of order, by their order key.
    out_of_order: BTreeMap<OrderKey, QueuedMessage>,
    len: usize,
    bytes: usize,
    /// Persistent messages (delivery-mode 2).
    persistent: usize,
    /// Messages with an expiry time.
    expiring: usize,
    /// Whether a message came in since the last
    /// [`Ready::release_idle_room`].
    inserted_since_check: bool,
}

impl Ready {
    /// How many messages.
    pub(super) fn len(&self) -> usize {
        self.len
    }

    /// Whether there are none.
    pub(super) fn is_empty(&self) -> bool {
        self.len == 0
    }

    /// Bytes of body held.
    pub(super) fn bytes(&self) -> usize {
        self.bytes
    }

    /// How many are persistent (delivery-mode 2).
    pub(super) fn persistent(&self) -> usize {
        self.persistent
    }

    /// Whether some message has an expiry time.
    pub(super) fn has_expiring(&self) -> bool {
        self.expiring > 0
    }

    /// Adds a message at its place.
    pub(super) fn insert(&mut self, queued: QueuedMessage) {
        self.inserted_since_check = true;
        self.len += 1;
        self.bytes += queued.message.body.len();
        self.persistent += usize::from(queued.message.persistent);
        if queued.expires_at.is_some() {
            self.expiring += 1;
        }
        let level = usize::from(queued.priority);
        if self.levels.len() <= level {
            self.levels.resize_with(level + 1, VecDeque::new);
        }
        self.top = self.top.max(level);
        let fifo = &mut self.levels[level];
        if fifo.back().is_none_or(|last| last.seq < queued.seq) {
            fifo.push_back(queued);
        } else {
            self.out_of_order.insert(queued.order_key(), queued);
        }
    }

    /// Gives back the FIFOs' room if the queue is empty and nothing came
    /// in since the last call (called periodically: an idle queue holds
    /// none, a busy one that keeps emptying keeps its [`SPARE_READY`]
    /// entries instead of reallocating at every burst).
    pub(super) fn release_idle_room(&mut self) {
        let idle = self.len == 0 && !self.inserted_since_check;
        self.inserted_since_check = false;
        if idle {
            for fifo in self.levels.iter_mut().filter(|fifo| fifo.capacity() > 0) {
                *fifo = VecDeque::new();
            }
        }
    }

    /// The head message, without taking it.
    pub(super) fn front(&mut self) -> Option<&QueuedMessage> {
        match self.head()? {
            Head::Level(level) => self.levels[level].front(),
            Head::OutOfOrder => self.out_of_order.first_key_value().map(|(_, m)| m),
        }
    }

    /// Takes the head message.
    pub(super) fn pop_front(&mut self) -> Option<QueuedMessage> {
        let queued = match self.head()? {
            Head::Level(level) => {
                let fifo = &mut self.levels[level];
                let queued = fifo.pop_front()?;
                give_back_spare(fifo);
                queued
            }
            Head::OutOfOrder => self.out_of_order.pop_first()?.1,
        };
        self.len -= 1;
        self.bytes -= queued.message.body.len();
        self.persistent -= usize::from(queued.message.persistent);
        if queued.expires_at.is_some() {
            self.expiring -= 1;
        }
        Some(queued)
    }

    /// Where the head is; lowers `top` past empty levels on the way (at
    /// most 256 levels, each passed once per time it empties).
    fn head(&mut self) -> Option<Head> {
        if self.len == 0 {
            return None;
        }
        while self.top > 0 && self.levels[self.top].is_empty() {
            self.top -= 1;
        }
        let level_front = self.levels.get(self.top).and_then(VecDeque::front);
        let map_first = self.out_of_order.first_key_value().map(|(key, _)| *key);
        Some(match (level_front, map_first) {
            (Some(front), Some(first)) if first < front.order_key() => Head::OutOfOrder,
            (Some(_), _) => Head::Level(self.top),
            (None, _) => Head::OutOfOrder,
        })
    }
}

/// Gives back the room a burst grew once the FIFO is mostly empty: a
/// VecDeque never shrinks by itself, so a drained backlog kept all the
/// room it grew. Copies what is left, at most a quarter of the
/// capacity (a growth copies all of it), keeping room for twice that.
fn give_back_spare(fifo: &mut VecDeque<QueuedMessage>) {
    let capacity = fifo.capacity();
    if capacity > SPARE_READY && capacity > 4 * fifo.len() {
        fifo.shrink_to((2 * fifo.len()).max(SPARE_READY));
    }
}

enum Head {
    Level(usize),
    OutOfOrder,
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::testkit::{message, s};
    use leveret_protocol::BasicProperties;
    use proptest::prelude::*;

    fn queued(seq: u64, priority: u8) -> QueuedMessage {
        QueuedMessage {
            seq,
            priority,
            message: message(&s(""), "k", "x", &BasicProperties::default()),
            redelivered: false,
            expires_at: None,
        }
    }

    /// A backlog's room goes back once it drains, and a steady small
    /// queue keeps its spare room instead of shrinking and regrowing.
    #[test]
    fn a_drained_burst_gives_back_its_room() {
        let body = message(&s(""), "k", "x", &BasicProperties::default());
        let mut ready = Ready::default();
        for seq in 0..100_000 {
            ready.insert(QueuedMessage {
                message: body.clone(),
                ..queued(seq, 0)
            });
        }
        assert!(ready.levels[0].capacity() >= 100_000);
        while ready.len() > 10_000 {
            ready.pop_front();
        }
        assert!(ready.levels[0].capacity() <= 4 * 10_000 + 1);
        while ready.pop_front().is_some() {}
        assert!(ready.levels[0].capacity() <= 2 * SPARE_READY);
        assert!(ready.levels[0].capacity() >= SPARE_READY);
    }

    /// An empty queue gives all its room back at the second check with
    /// nothing inserted in between, not while messages keep coming.
    #[test]
    fn an_idle_empty_queue_gives_back_all_its_room() {
        let mut ready = Ready::default();
        let mut seq = 0;
        let mut burst = |ready: &mut Ready| {
            for _ in 0..500 {
                ready.insert(queued(seq, 0));
                seq += 1;
            }
            while ready.pop_front().is_some() {}
        };
        burst(&mut ready);
        ready.release_idle_room();
        assert!(
            ready.levels[0].capacity() >= 500,
            "in use since the last check"
        );
        burst(&mut ready);
        ready.release_idle_room();
        assert!(
            ready.levels[0].capacity() >= 500,
            "in use since the last check"
        );
        ready.insert(queued(seq, 0));
        ready.release_idle_room();
        ready.release_idle_room();
        assert!(ready.levels[0].capacity() >= 1, "not empty");
        ready.pop_front();
        ready.release_idle_room();
        assert_eq!(ready.levels[0].capacity(), 0, "empty, nothing in since");
    }

    proptest! {
        /// Whatever the order of arrival, messages leave by priority and
        /// then by publish order, as a sorted list would give them.
        #[test]
        fn leaves_in_the_order_of_a_sorted_list(
            arrivals in proptest::collection::vec((0u64..200, 0u8..4), 0..100),
            pops in proptest::collection::vec(any::<bool>(), 0..100),
        ) {
            let mut ready = Ready::default();
            let mut reference: Vec<QueuedMessage> = Vec::new();
            let mut pops = pops.into_iter();
            for (index, (seq, priority)) in arrivals.into_iter().enumerate() {
                // Unique sequence numbers, as a queue hands out.
                let seq = seq * 1000 + index as u64;
                ready.insert(queued(seq, priority));
                reference.push(queued(seq, priority));
                reference.sort_by_key(QueuedMessage::order_key);
                if pops.next() == Some(true) {
                    let expected = (!reference.is_empty()).then(|| reference.remove(0));
                    prop_assert_eq!(ready.pop_front().map(|m| m.seq), expected.map(|m| m.seq));
                }
                prop_assert_eq!(ready.len(), reference.len());
            }
            while let Some(expected) = (!reference.is_empty()).then(|| reference.remove(0)) {
                prop_assert_eq!(ready.front().map(|m| m.seq), Some(expected.seq));
                prop_assert_eq!(ready.pop_front().map(|m| m.seq), Some(expected.seq));
            }
            prop_assert!(ready.pop_front().is_none());
            prop_assert_eq!(ready.bytes(), 0);
        }
    }
}
