//! A queue's FIFO and dispatch: taking a message in (TTL, priority,
//! max-length with its overflow modes), the ready list in order, expiry at
//! the head, and delivery to the consumers `consumers` chooses (by
//! `x-priority`, round-robin among equals, or the single active one),
//! under the queue's lock.

use super::{
    DeadLetter, DeadLetterReason, DeadLetters, Enqueued, Origin, Overflow, Queue, QueueState,
    QueuedMessage, Unacked, DEAD_LETTERS_PER_STEP, FLOW_HIGH, FLOW_LOW, POSITION_HEADER,
};
use crate::message::Message;
use crate::outbox::Outbound;
use crate::slice::{Progress, Slice};
use bytes::BytesMut;
use leveret_protocol::{BasicProperties, FieldTable, FieldValue, ShortStr};
use std::sync::Arc;
use std::time::{Duration, Instant};

/// Most expired messages one pop skips; see [`Queue::pop_live`].
const EXPIRED_PER_POP: usize = 256;

impl Queue {
    pub(super) fn offer(
        self: &Arc<Self>,
        message: Arc<Message>,
        reserved: Option<u64>,
    ) -> (Enqueued, DeadLetters) {
        let mut dead = Vec::new();
        let outcome = {
            let mut st = self.lock();
            if st.deleted {
                let sync = self.unlog(&message, reserved);
                return (Enqueued::Accepted { sync }, DeadLetters::default());
            }
            let now = Instant::now();
            let ttl = match (st.effective.message_ttl, message.ttl_ms) {
                (Some(a), Some(b)) => Some(a.min(b)),
                (a, b) => a.or(b),
            };
            let priority = match self.args.max_priority {
                Some(max) => message.priority.min(max),
                None => 0,
            };
            if self.is_full_for(&st, &message) {
                match st.effective.overflow {
                    Overflow::DropHead => {}
                    Overflow::RejectPublish => {
                        let sync = self.unlog(&message, reserved);
                        return (Enqueued::Refused { sync }, DeadLetters::default());
                    }
                    Overflow::RejectPublishDlx => {
                        let sync = self.unlog(&message, reserved);
                        self.dead_letter(message, DeadLetterReason::MaxLen, &mut dead);
                        return (Enqueued::Refused { sync }, DeadLetters(dead));
                    }
                }
            }
            let seq = reserved.unwrap_or_else(|| {
                st.next_seq += 1;
                st.next_seq
            });
            let queued = QueuedMessage {
                seq,
                priority,
                message,
                redelivered: false,
                expires_at: ttl.map(|ms| now + Duration::from_millis(ms)),
            };
            self.gauge.add(queued.message.weight());
            // Logged under the queue lock, so no dequeue of this message
            // (which needs it delivered first) can reach the store before it.
            let sync = match reserved {
                Some(_) => 0,
                None => self.log(&queued),
            };
            self.insert_ready(&mut st, queued);
            self.stats.published();
            self.enforce_max_length(&mut st, &mut dead);
            // Dispatched as of the publish instant, so a message with TTL 0
            // still reaches a consumer that can take it at once (as in RabbitMQ).
            self.dispatch_published(&mut st, &mut dead, now);
            Enqueued::Accepted { sync }
        };
        (outcome, DeadLetters(dead))
    }

    pub(super) fn is_full_for(&self, st: &QueueState, message: &Message) -> bool {
        let by_count = st
            .effective
            .max_length
            .is_some_and(|max| st.ready.len() as u64 >= max);
        let by_bytes = st
            .effective
            .max_length_bytes
            .is_some_and(|max| (st.ready.bytes() + message.body.len()) as u64 > max);
        by_count || by_bytes
    }

    pub(super) fn enforce_max_length(&self, st: &mut QueueState, dead: &mut Vec<DeadLetter>) {
        self.drop_over_length(st, dead, usize::MAX);
    }

    /// Under `drop-head`, drops (or dead-letters) head messages while the
    /// queue is over its length limits, at most `most` of them: whether
    /// it is still over.
    pub(super) fn drop_over_length(
        &self,
        st: &mut QueueState,
        dead: &mut Vec<DeadLetter>,
        most: usize,
    ) -> bool {
        let over = |st: &QueueState| {
            st.effective.overflow == Overflow::DropHead
                && (st
                    .effective
                    .max_length
                    .is_some_and(|max| st.ready.len() as u64 > max)
                    || st
                        .effective
                        .max_length_bytes
                        .is_some_and(|max| st.ready.bytes() as u64 > max))
        };
        for _ in 0..most {
            if !over(st) {
                return false;
            }
            match self.pop_ready(st) {
                Some(head) => self.discard(head, DeadLetterReason::MaxLen, dead),
                None => return false,
            }
        }
        over(st)
    }

    pub(super) fn insert_ready(&self, st: &mut QueueState, queued: QueuedMessage) {
        if st.ready.len() >= FLOW_HIGH && !st.consumers.is_empty() {
            self.crowded
                .store(true, std::sync::atomic::Ordering::Release);
        }
        st.ready.insert(queued);
    }

    /// Wakes waiting publishers once the queue has drained enough (or has
    /// no consumers left to drain it).
    pub(super) fn check_drained(&self, st: &QueueState) {
        if (st.ready.len() <= FLOW_LOW || st.consumers.is_empty())
            && self
                .crowded
                .swap(false, std::sync::atomic::Ordering::AcqRel)
        {
            self.drained.notify_waiters();
        }
    }

    pub(super) fn pop_ready(&self, st: &mut QueueState) -> Option<QueuedMessage> {
        let head = st.ready.pop_front()?;
        if self.crowded.load(std::sync::atomic::Ordering::Relaxed) {
            self.check_drained(st);
        }
        Some(head)
    }

    /// Takes the head message that has not expired, expiring those that
    /// have: at most [`EXPIRED_PER_POP`] of them, after which it gives up
    /// (None) and leaves the rest to the sweeper, which dispatches again.
    pub(super) fn pop_live(
        &self,
        st: &mut QueueState,
        now: Instant,
        dead: &mut Vec<DeadLetter>,
    ) -> Option<QueuedMessage> {
        for _ in 0..EXPIRED_PER_POP {
            let head = self.pop_ready(st)?;
            if head.expires_at.is_some_and(|at| at < now) {
                self.discard(head, DeadLetterReason::Expired, dead);
            } else {
                return Some(head);
            }
        }
        None
    }

    /// Expires messages at the head, one step of `slice` each; see
    /// [`Queue::expire_at`].
    pub(super) fn expire_head(
        &self,
        st: &mut QueueState,
        dead: &mut Vec<DeadLetter>,
        now: Instant,
        slice: &mut Slice,
    ) -> Progress {
        if !st.ready.has_expiring() {
            return Progress::Done;
        }
        while st
            .ready
            .front()
            .is_some_and(|m| m.expires_at.is_some_and(|at| at < now))
        {
            if let Some(head) = self.pop_ready(st) {
                self.discard(head, DeadLetterReason::Expired, dead);
            }
            if slice.step() || dead.len() >= DEAD_LETTERS_PER_STEP {
                return Progress::More;
            }
        }
        Progress::Done
    }

    /// Delivers ready messages to consumers with credit and room; the
    /// highest stored position it delivered raises the store's delivery
    /// mark once, not once per message. For every caller but a publish:
    /// credit may have come back, so every consumer is looked at again.
    pub(super) fn dispatch_locked(
        self: &Arc<Self>,
        st: &mut QueueState,
        dead: &mut Vec<DeadLetter>,
        now: Instant,
    ) {
        st.consumers.reopen();
        self.dispatch_published(st, dead, now);
    }

    /// [`Queue::dispatch_locked`] after a publish, which frees no credit:
    /// consumers found blocked since credit last came back stay skipped.
    fn dispatch_published(
        self: &Arc<Self>,
        st: &mut QueueState,
        dead: &mut Vec<DeadLetter>,
        now: Instant,
    ) {
        let mut mark = None;
        self.deliver_ready(st, dead, now, &mut mark);
        if let Some(seq) = mark {
            self.log_delivery_mark(seq);
        }
    }

    fn deliver_ready(
        self: &Arc<Self>,
        st: &mut QueueState,
        dead: &mut Vec<DeadLetter>,
        now: Instant,
        mark: &mut Option<u64>,
    ) {
        let count = st.consumers.len();
        if count == 0 || st.ready.is_empty() {
            return;
        }
        // Consumers whose connection had no room during this dispatch, by
        // `Slot::flat` (allocated when the first one is found).
        let mut full: Vec<bool> = Vec::new();
        while !st.ready.is_empty() {
            let Some((slot, consumer)) = st.consumers.pick(&full) else {
                // No consumer can take a message now; credit or room will
                // trigger another dispatch.
                return;
            };
            let Some(permit) = consumer.channel.outbox.try_reserve() else {
                consumer.channel.outbox.wait_for_room(self);
                mark_full(&mut full, slot.flat, count);
                continue;
            };
            let Some(credit) = consumer.try_take_credit() else {
                mark_full(&mut full, slot.flat, count);
                continue;
            };
            st.consumers.delivered(slot);
            let Some(queued) = self.pop_live(st, now, dead) else {
                return;
            };
            self.stats
                .delivered(consumer.no_ack, queued.redelivered, &queued.message);
            if consumer.no_ack {
                self.release(&queued);
            } else {
                if let Some(seq) = self.raise_delivery_mark(st, &queued) {
                    *mark = Some(seq);
                }
                credit.keep();
            }
            // The tag is handed out and the delivery enters the outbox in
            // one step under the channel's delivery lock: whichever thread
            // dispatches, tags reach the client in the order they were
            // handed out.
            let mut deliveries = consumer.channel.deliveries();
            let delivery_tag = deliveries.next_tag();
            if !consumer.no_ack {
                deliveries.push(Unacked {
                    tag: delivery_tag,
                    origin: Origin {
                        queue: Arc::clone(self),
                        message: queued.clone(),
                    },
                    consumer: Some(Arc::clone(&consumer)),
                });
            }
            let message = if consumer.wants_position {
                self.with_position(&queued)
            } else {
                queued.message
            };
            permit.send(Outbound::Deliver {
                channel: consumer.channel.id,
                consumer_tag: consumer.tag.clone(),
                delivery_tag,
                redelivered: queued.redelivered,
                message,
            });
        }
    }

    /// The message as a consumer that asked for positions gets it: its
    /// properties with [`POSITION_HEADER`] added (decoded and encoded
    /// again, for that consumer only; the queue keeps the message as
    /// published).
    fn with_position(&self, queued: &QueuedMessage) -> Arc<Message> {
        let mut properties = match BasicProperties::decode(&queued.message.properties) {
            Ok(properties) => properties,
            // Checked when published: cannot happen; deliver it as it is.
            Err(_) => return Arc::clone(&queued.message),
        };
        let position = format!("{}.{}", self.position_name, queued.seq);
        properties
            .headers
            .get_or_insert_with(FieldTable::new)
            .insert(
                ShortStr::from_static(POSITION_HEADER),
                FieldValue::string(&position),
            );
        let mut encoded = BytesMut::with_capacity(queued.message.properties.len() + 64);
        properties.encode(&mut encoded);
        Arc::new(Message {
            properties: encoded.freeze(),
            ..queued.message.stored_as(None)
        })
    }
}

/// Marks consumer `index` (of `count`) as out of room for this dispatch.
fn mark_full(full: &mut Vec<bool>, index: usize, count: usize) {
    if full.is_empty() {
        full.resize(count, false);
    }
    full[index] = true;
}
