//! Consumers and the per-channel delivery bookkeeping shared between a
//! channel (which handles acks) and the queues (which deliver): delivery
//! tags, the unacked list, prefetch credit and channel.flow.
//!
//! It uses the outbox (a channel's way to its connection's writer) and
//! nothing of the queues: what a queue keeps of a delivery until it is
//! settled is the type parameter `O` of these types (its origin), which the
//! queue layer fixes (`queue::Origin`, and `queue::Consumer` and the other
//! aliases there). [`credit`] holds the lock-free counting.

mod credit;

use crate::outbox::Outbox;
use leveret_protocol::ShortStr;
use std::collections::VecDeque;
use std::sync::atomic::{AtomicBool, AtomicU32, AtomicU64, Ordering};
use std::sync::{Arc, Mutex, MutexGuard};

/// Unacked deliveries a channel's buffer keeps room for however few are
/// outstanding, while some are (64 KiB of entries).
const SPARE_UNACKED: usize = 1024;
/// The room a channel's buffer keeps once nothing is outstanding: every
/// delivery settled, its room beyond this goes back (a burst's room kept
/// for good was 8 KiB in every MQTT subscriber and up to 64 KiB in every
/// AMQP consumer's channel); regrowing it at the next burst is amortized
/// over the burst.
const IDLE_UNACKED: usize = 16;

/// A delivery waiting for ack, nack or reject.
#[derive(Debug)]
pub struct Unacked<O> {
    /// Its delivery tag.
    pub tag: u64,
    /// What its queue needs to settle it: the queue and the message as it
    /// held it.
    pub origin: O,
    /// The consumer it went to (None for basic.get).
    pub consumer: Option<Arc<Consumer<O>>>,
}

/// Delivery tags and unacked deliveries of one channel, in tag order.
#[derive(Debug)]
pub struct Deliveries<O> {
    last_tag: u64,
    unacked: VecDeque<Unacked<O>>,
}

impl<O> Default for Deliveries<O> {
    fn default() -> Self {
        Deliveries {
            last_tag: 0,
            unacked: VecDeque::new(),
        }
    }
}

impl<O> Deliveries<O> {
    /// Hands out the next delivery tag.
    pub fn next_tag(&mut self) -> u64 {
        self.last_tag += 1;
        self.last_tag
    }

    /// Records an unacked delivery (its tag must be the newest).
    pub fn push(&mut self, unacked: Unacked<O>) {
        self.unacked.push_back(unacked);
    }

    /// Takes the deliveries `tag` settles: that one, or with `multiple`
    /// every one up to it (tag 0 with multiple means all). As in RabbitMQ,
    /// the tag itself must be outstanding, even with `multiple`; `None`
    /// means it is unknown or already settled.
    pub fn take(&mut self, tag: u64, multiple: bool) -> Option<VecDeque<Unacked<O>>> {
        if multiple && tag == 0 {
            return Some(self.take_all());
        }
        let index = self.unacked.binary_search_by_key(&tag, |u| u.tag).ok()?;
        let settled = if multiple {
            // Moves only the settled head (the caller visits each of them
            // anyway); the unsettled tail stays in a buffer that keeps its
            // capacity for the deliveries to come (splitting the tail off
            // instead made every later push regrow a fresh one).
            self.unacked.drain(..=index).collect()
        } else {
            self.unacked.remove(index).into_iter().collect()
        };
        self.give_back_spare();
        Some(settled)
    }

    /// Gives back a buffer a burst grew once it is mostly empty (copying
    /// what is left, at most a quarter of it), keeping room for a steady
    /// window of deliveries; once it is empty, all but [`IDLE_UNACKED`].
    fn give_back_spare(&mut self) {
        let capacity = self.unacked.capacity();
        if self.unacked.is_empty() {
            if capacity > IDLE_UNACKED {
                self.unacked = VecDeque::new();
            }
        } else if capacity > SPARE_UNACKED && capacity > 4 * self.unacked.len() {
            self.unacked
                .shrink_to((2 * self.unacked.len()).max(SPARE_UNACKED));
        }
    }

    /// Puts taken deliveries back (a rolled-back transaction's acks), in
    /// one merge by tag.
    pub fn restore(&mut self, deliveries: impl IntoIterator<Item = Unacked<O>>) {
        let mut returned: Vec<Unacked<O>> = deliveries.into_iter().collect();
        if returned.is_empty() {
            return;
        }
        returned.sort_by_key(|u| u.tag);
        let mut current = std::mem::take(&mut self.unacked).into_iter().peekable();
        let mut returned = returned.into_iter().peekable();
        let mut merged = VecDeque::with_capacity(current.len() + returned.len());
        loop {
            let next = match (current.peek(), returned.peek()) {
                (Some(a), Some(b)) if a.tag < b.tag => current.next(),
                (Some(_), Some(_)) | (None, Some(_)) => returned.next(),
                (Some(_), None) => current.next(),
                (None, None) => break,
            };
            merged.extend(next);
        }
        self.unacked = merged;
    }

    /// How many deliveries are unacked.
    pub fn unacked_count(&self) -> usize {
        self.unacked.len()
    }

    /// Takes every unacked delivery (channel close, recover), in O(1).
    pub fn take_all(&mut self) -> VecDeque<Unacked<O>> {
        std::mem::take(&mut self.unacked)
    }
}

/// What queues need of a channel to deliver to its consumers.
#[derive(Debug)]
pub struct ChannelLink<O> {
    /// Channel number.
    pub id: u16,
    /// The connection's writer.
    pub outbox: Arc<Outbox>,
    deliveries: Mutex<Deliveries<O>>,
    /// basic.qos global prefetch count (0 = none), RabbitMQ's meaning:
    /// shared by all consumers on the channel.
    pub global_prefetch: AtomicU32,
    /// Unacked deliveries to consumers of this channel.
    pub global_in_flight: AtomicU32,
    /// channel.flow state: false stops deliveries.
    pub flow_active: AtomicBool,
    /// Direct replies dropped because the connection had no room.
    dropped_replies: AtomicU64,
}

impl<O> ChannelLink<O> {
    /// A link for channel `id` of the connection writing to `outbox`.
    pub fn new(id: u16, outbox: Arc<Outbox>) -> Self {
        ChannelLink {
            id,
            outbox,
            deliveries: Mutex::new(Deliveries::default()),
            global_prefetch: AtomicU32::new(0),
            global_in_flight: AtomicU32::new(0),
            flow_active: AtomicBool::new(true),
            dropped_replies: AtomicU64::new(0),
        }
    }

    /// Counts one direct reply dropped for want of room; returns how many
    /// have been dropped on this channel.
    pub fn count_dropped_reply(&self) -> u64 {
        self.dropped_replies.fetch_add(1, Ordering::Relaxed) + 1
    }

    /// Locks the delivery bookkeeping. The lock is held for a few
    /// instructions (tag, push, or take) and never across an await, except
    /// by a stream's burst delivery, which holds it for a whole burst (up
    /// to about one and a half reads' worth of records, or the outbox's
    /// free room: tag, credit, decode and send each), so a channel's acks,
    /// `basic.get` and close may wait that long behind a stream reader.
    pub fn deliveries(&self) -> MutexGuard<'_, Deliveries<O>> {
        self.deliveries.lock().unwrap_or_else(|e| e.into_inner())
    }
}

/// One basic.consume subscription.
#[derive(Debug)]
pub struct Consumer<O> {
    /// Consumer tag.
    pub tag: ShortStr,
    /// Its channel.
    pub channel: Arc<ChannelLink<O>>,
    /// Deliveries need no ack.
    pub no_ack: bool,
    /// Exclusive consumer of its queue.
    pub exclusive: bool,
    /// Per-consumer prefetch count (0 = unlimited).
    pub prefetch: u32,
    /// `x-priority` (RabbitMQ): higher-priority consumers are served first.
    pub priority: i64,
    /// `x-leveret-position`: each delivery carries the queue's
    /// [`POSITION_HEADER`](crate::arguments::POSITION_HEADER).
    pub wants_position: bool,
    /// Unacked deliveries to this consumer.
    pub in_flight: AtomicU32,
    /// Set once basic.consume-ok is on its way, so no delivery overtakes it.
    pub active: AtomicBool,
}

impl<O> Consumer<O> {
    /// Whether prefetch and flow allow one more delivery now. A hint for
    /// choosing among consumers: another queue of the channel may take the
    /// last unit of shared credit first, so a delivery needs
    /// [`Consumer::try_take_credit`].
    pub fn has_credit(&self) -> bool {
        if !self.may_deliver() {
            return false;
        }
        if self.no_ack {
            return true;
        }
        let global = self.channel.global_prefetch.load(Ordering::Relaxed);
        let within = |in_flight: &AtomicU32, limit: u32| {
            limit == 0 || in_flight.load(Ordering::Relaxed) < limit
        };
        within(&self.in_flight, self.prefetch) && within(&self.channel.global_in_flight, global)
    }

    /// Takes the credit for one delivery, checking and counting it against
    /// both the consumer's prefetch and the channel's `global` prefetch in
    /// one atomic step each; None if flow or either limit refuses. The
    /// credit goes back when the [`Credit`] is dropped unless it is kept.
    /// Deliveries without acks take no credit (RabbitMQ ignores prefetch
    /// for them).
    pub fn try_take_credit(&self) -> Option<Credit<'_, O>> {
        if !self.may_deliver() {
            return None;
        }
        if self.no_ack {
            return Some(Credit {
                consumer: self,
                give_back_on_drop: false,
            });
        }
        let global = self.channel.global_prefetch.load(Ordering::Relaxed);
        let taken = credit::try_take_both(
            &self.in_flight,
            self.prefetch,
            &self.channel.global_in_flight,
            global,
        );
        // Built only once taken: a Credit dropped gives back its unit.
        if taken {
            Some(Credit {
                consumer: self,
                give_back_on_drop: true,
            })
        } else {
            None
        }
    }

    /// Active (consume-ok sent) and the channel's flow is on.
    fn may_deliver(&self) -> bool {
        self.active.load(Ordering::Acquire) && self.channel.flow_active.load(Ordering::Relaxed)
    }

    /// Lets the queue deliver to this consumer.
    pub fn activate(&self) {
        self.active.store(true, Ordering::Release);
    }

    /// Counts one settled delivery.
    pub fn settled_one(&self) {
        credit::give_back(&self.in_flight);
        credit::give_back(&self.channel.global_in_flight);
    }
}

/// Prefetch credit for one delivery, taken by [`Consumer::try_take_credit`].
/// Dropped without [`Credit::keep`] (no message was delivered after all) it
/// is given back.
#[derive(Debug)]
#[must_use = "credit not kept is given back at once"]
pub struct Credit<'a, O> {
    consumer: &'a Consumer<O>,
    /// A unit is counted and no delivery holds it yet.
    give_back_on_drop: bool,
}

impl<O> Credit<'_, O> {
    /// The delivery went out: the credit stays taken until the delivery is
    /// settled ([`Consumer::settled_one`]).
    pub fn keep(mut self) {
        self.give_back_on_drop = false;
    }
}

impl<O> Drop for Credit<'_, O> {
    fn drop(&mut self) {
        if self.give_back_on_drop {
            self.consumer.settled_one();
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A consumer whose deliveries keep nothing of their queue.
    fn consumer(prefetch: u32, global: u32, no_ack: bool) -> Consumer<()> {
        let (outbox, _writer) = Outbox::new(1);
        let link = Arc::new(ChannelLink::new(1, outbox));
        link.global_prefetch.store(global, Ordering::Relaxed);
        let consumer = Consumer {
            tag: ShortStr::from_static("c"),
            channel: link,
            no_ack,
            exclusive: false,
            prefetch,
            priority: 0,
            wants_position: false,
            in_flight: AtomicU32::new(0),
            active: AtomicBool::new(false),
        };
        consumer.activate();
        consumer
    }

    fn counts(consumer: &Consumer<()>) -> (u32, u32) {
        (
            consumer.in_flight.load(Ordering::Relaxed),
            consumer.channel.global_in_flight.load(Ordering::Relaxed),
        )
    }

    #[test]
    fn kept_credit_stays_taken_until_settled_and_dropped_credit_goes_back() {
        let c = consumer(2, 0, false);
        c.try_take_credit().expect("credit").keep();
        assert_eq!(counts(&c), (1, 1));
        drop(c.try_take_credit().expect("credit"));
        assert_eq!(counts(&c), (1, 1));
        c.settled_one();
        assert_eq!(counts(&c), (0, 0));
    }

    /// A refusal changes nothing: no unit is taken, and none is given back
    /// (a credit built and dropped on refusal would give back a unit that
    /// another delivery holds, and underflow once that one is settled).
    #[test]
    fn refused_credit_leaves_the_counts_alone() {
        let per_consumer = consumer(1, 0, false);
        per_consumer.try_take_credit().expect("credit").keep();
        assert!(per_consumer.try_take_credit().is_none());
        assert_eq!(counts(&per_consumer), (1, 1));

        let global = consumer(0, 1, false);
        global.try_take_credit().expect("credit").keep();
        assert!(global.try_take_credit().is_none());
        assert_eq!(counts(&global), (1, 1));
    }

    #[test]
    fn no_ack_deliveries_take_no_credit_and_flow_stops_all() {
        let c = consumer(1, 1, true);
        for _ in 0..3 {
            c.try_take_credit().expect("no-ack credit").keep();
        }
        assert_eq!(counts(&c), (0, 0));
        c.channel.flow_active.store(false, Ordering::Relaxed);
        assert!(c.try_take_credit().is_none() && !c.has_credit());
    }

    /// A burst's buffer is given back once the burst is acknowledged,
    /// whether by one multiple ack or one ack at a time, and the
    /// deliveries settled are exactly the ones named.
    #[test]
    fn a_bursts_buffer_is_given_back_once_acknowledged() {
        for multiple in [true, false] {
            let mut deliveries = Deliveries::default();
            for _ in 0..20_000 {
                let tag = deliveries.next_tag();
                deliveries.push(Unacked {
                    tag,
                    origin: (),
                    consumer: None,
                });
            }
            let grown = deliveries.unacked.capacity();
            let settled: Vec<u64> = if multiple {
                let taken = deliveries.take(19_990, true).expect("outstanding");
                taken.iter().map(|u| u.tag).collect()
            } else {
                (1..=19_990)
                    .flat_map(|tag| deliveries.take(tag, false).expect("outstanding"))
                    .map(|u| u.tag)
                    .collect()
            };
            assert_eq!(settled, (1..=19_990).collect::<Vec<_>>());
            assert_eq!(deliveries.unacked_count(), 10);
            let kept = deliveries.unacked.capacity();
            assert!(
                grown >= 20_000 && kept <= 2 * SPARE_UNACKED,
                "{grown} then {kept}"
            );
            let last = deliveries.take(20_000, multiple);
            assert_eq!(
                last.map(|taken| taken.len()),
                Some(if multiple { 10 } else { 1 })
            );
            if !multiple {
                for tag in 19_991..20_000 {
                    deliveries.take(tag, false).expect("outstanding");
                }
            }
            assert_eq!(deliveries.unacked_count(), 0);
            assert_eq!(
                deliveries.unacked.capacity(),
                0,
                "all settled: no room kept"
            );
        }
    }
}

/// Where replies to one channel's requests go: the consumer of RabbitMQ's
/// direct reply-to pseudo-queue, which has no queue of its own.
#[derive(Debug)]
pub(crate) struct ReplyTarget<O> {
    /// The consuming channel.
    pub link: Arc<ChannelLink<O>>,
    /// Its reply consumer's tag.
    pub consumer_tag: ShortStr,
}

impl<O> Clone for ReplyTarget<O> {
    fn clone(&self) -> Self {
        ReplyTarget {
            link: Arc::clone(&self.link),
            consumer_tag: self.consumer_tag.clone(),
        }
    }
}
