//! Queues: ready messages in FIFO order (by priority first when
//! `x-max-priority` is set), the consumers with their round-robin cursor,
//! and dispatch. One `std::sync::Mutex` per queue guards its state; it is
//! held for a few instructions per operation and never across an await, and
//! no other lock is taken inside it except a channel's delivery bookkeeping
//! (always in that order: queue, then channel).
//!
//! Dead-lettering routes messages into other queues, so it happens after the
//! lock is released: operations collect [`DeadLetter`]s and hand them to the
//! vhost afterwards.

use crate::consumer::{ChannelLink, Consumer, Unacked};
use crate::error::{AmqpError, AmqpResult};
use crate::memory::MemoryGauge;
use crate::message::{Message, Stored};
use crate::outbox::Outbound;
use crate::stats::{BrokerCounters, QueueCounters};
use crate::store::{EntryBody, Persistence, StoreOp};
use crate::vhost::Vhost;
use leveret_protocol::{BasicCancel, FieldTable, FieldValue, ShortStr};
use std::collections::VecDeque;
use std::sync::{Arc, Mutex, MutexGuard, Weak};
use std::time::{Duration, Instant};

/// Ready messages in a queue with consumers above which publishers to it
/// are slowed down (RabbitMQ's flow control, in spirit): reading from a
/// publishing connection pauses until the queue is back under
/// [`FLOW_LOW`], so consumers keep the CPU they need and the backlog (and
/// latency) stays bounded. Queues without consumers are never crowded.
pub const FLOW_HIGH: usize = 20_000;
/// See [`FLOW_HIGH`].
pub const FLOW_LOW: usize = 10_000;

/// A message in a queue, with its place in the queue's order.
#[derive(Debug, Clone)]
pub struct QueuedMessage {
    /// Position in publish order; requeued messages go back by it.
    pub seq: u64,
    /// Effective priority (0 unless the queue has x-max-priority).
    pub priority: u8,
    /// The message.
    pub message: Arc<Message>,
    /// Delivered before.
    pub redelivered: bool,
    /// When it expires (queue or per-message TTL).
    pub expires_at: Option<Instant>,
}

impl QueuedMessage {
    fn order_key(&self) -> (std::cmp::Reverse<u8>, u64) {
        (std::cmp::Reverse(self.priority), self.seq)
    }
}

/// What happens when a queue reaches x-max-length or x-max-length-bytes.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Overflow {
    /// Drop (or dead-letter) the oldest messages.
    #[default]
    DropHead,
    /// Refuse the new message (nack with confirms).
    RejectPublish,
    /// As reject-publish, and dead-letter the refused message.
    RejectPublishDlx,
}

/// The RabbitMQ queue arguments the broker acts on, validated.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct QueueArgs {
    /// x-message-ttl, ms.
    pub message_ttl: Option<u64>,
    /// x-expires, ms unused before the queue is deleted.
    pub expires: Option<u64>,
    /// x-max-length, messages.
    pub max_length: Option<u64>,
    /// x-max-length-bytes, body bytes.
    pub max_length_bytes: Option<u64>,
    /// x-overflow.
    pub overflow: Overflow,
    /// x-dead-letter-exchange.
    pub dead_letter_exchange: Option<ShortStr>,
    /// x-dead-letter-routing-key.
    pub dead_letter_routing_key: Option<ShortStr>,
    /// x-max-priority.
    pub max_priority: Option<u8>,
}

impl QueueArgs {
    /// Validates and reads the arguments RabbitMQ defines; the error texts
    /// follow RabbitMQ's (`invalid arg 'x-message-ttl' for queue 'q' ...`).
    pub fn parse(arguments: &FieldTable, queue: &ShortStr, vhost: &ShortStr) -> AmqpResult<Self> {
        let invalid = |name: &str, why: String| {
            AmqpError::precondition_failed(format_args!(
                "invalid arg '{name}' for queue '{queue}' in vhost '{vhost}': {why}"
            ))
        };
        let non_negative = |name: &str, v: &FieldValue| -> AmqpResult<u64> {
            match v.as_i64() {
                Some(n) if n >= 0 => Ok(n as u64),
                Some(n) => Err(invalid(name, format!("{{value_negative,{n}}}"))),
                None => Err(invalid(name, format!("{{unacceptable_type,{:?}}}", v))),
            }
        };
        let text = |name: &str, v: &FieldValue| -> AmqpResult<ShortStr> {
            v.as_bytes()
                .and_then(|b| ShortStr::try_from(bytes::Bytes::copy_from_slice(b)).ok())
                .ok_or_else(|| invalid(name, format!("{{unacceptable_type,{:?}}}", v)))
        };
        let mut args = QueueArgs::default();
        for (key, value) in arguments.iter() {
            match key.as_bytes() {
                b"x-message-ttl" => args.message_ttl = Some(non_negative("x-message-ttl", value)?),
                b"x-expires" => match non_negative("x-expires", value)? {
                    0 => return Err(invalid("x-expires", "{value_zero,0}".into())),
                    n => args.expires = Some(n),
                },
                b"x-max-length" => args.max_length = Some(non_negative("x-max-length", value)?),
                b"x-max-length-bytes" => {
                    args.max_length_bytes = Some(non_negative("x-max-length-bytes", value)?)
                }
                b"x-overflow" => {
                    args.overflow = match value.as_bytes() {
                        Some(b"drop-head") => Overflow::DropHead,
                        Some(b"reject-publish") => Overflow::RejectPublish,
                        Some(b"reject-publish-dlx") => Overflow::RejectPublishDlx,
                        _ => {
                            return Err(invalid(
                                "x-overflow",
                                format!("{{unacceptable_value,{:?}}}", value),
                            ))
                        }
                    }
                }
                b"x-dead-letter-exchange" => {
                    args.dead_letter_exchange = Some(text("x-dead-letter-exchange", value)?)
                }
                b"x-dead-letter-routing-key" => {
                    args.dead_letter_routing_key = Some(text("x-dead-letter-routing-key", value)?)
                }
                b"x-max-priority" => match non_negative("x-max-priority", value)? {
                    n @ 0..=255 => args.max_priority = Some(n as u8),
                    n => {
                        return Err(invalid(
                            "x-max-priority",
                            format!("{{value_out_of_range,{n}}}"),
                        ))
                    }
                },
                _ => {}
            }
        }
        if args.dead_letter_routing_key.is_some() && args.dead_letter_exchange.is_none() {
            return Err(invalid(
                "x-dead-letter-routing-key",
                "Key 'x-dead-letter-exchange' is mandatory if 'x-dead-letter-routing-key' is defined".into(),
            ));
        }
        Ok(args)
    }
}

/// Why a message was dead-lettered (the `reason` in `x-death`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum DeadLetterReason {
    /// basic.reject or basic.nack with requeue false.
    Rejected,
    /// Its TTL passed.
    Expired,
    /// Dropped by x-max-length or x-max-length-bytes.
    MaxLen,
}

impl DeadLetterReason {
    fn as_str(self) -> &'static str {
        match self {
            DeadLetterReason::Rejected => "rejected",
            DeadLetterReason::Expired => "expired",
            DeadLetterReason::MaxLen => "maxlen",
        }
    }
}

/// A message leaving a queue for its dead-letter exchange.
#[derive(Debug)]
pub struct DeadLetter {
    message: Arc<Message>,
    reason: DeadLetterReason,
}

/// A deleted queue's ready-message count and the consumers it had.
#[derive(Debug, Default)]
#[must_use = "the deleted queue's consumers must be notified"]
pub struct Deleted {
    /// Ready messages the queue held.
    pub messages: u32,
    consumers: Vec<Arc<Consumer>>,
}

impl Deleted {
    /// Sends basic.cancel to the consumers whose clients announced
    /// consumer_cancel_notify; returns the message count.
    pub fn notify(self) -> u32 {
        for consumer in self.consumers {
            let outbox = &consumer.channel.outbox;
            if outbox.cancel_notify() {
                let cancel = BasicCancel {
                    consumer_tag: consumer.tag.clone(),
                    no_wait: true,
                };
                if !outbox.try_send(Outbound::Method {
                    channel: consumer.channel.id,
                    method: cancel.into(),
                }) {
                    tracing::warn!(consumer = %consumer.tag, "no room to tell a consumer its queue was deleted");
                }
            }
        }
        self.messages
    }
}

/// Result of offering a message to a queue.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Enqueued {
    /// The queue took it; on disk once the persister has flushed
    /// submission `sync` (0 when nothing was written).
    Accepted {
        /// Submission number to wait for.
        sync: u64,
    },
    /// The queue is full and its overflow mode refuses publishes.
    Refused,
}

#[derive(Debug, Default)]
struct QueueState {
    ready: VecDeque<QueuedMessage>,
    ready_bytes: usize,
    next_seq: u64,
    consumers: Vec<Arc<Consumer>>,
    cursor: usize,
    /// Some consumer has a non-zero `x-priority`.
    prioritised: bool,
    exclusive_consumer: bool,
    expiring: usize,
    /// Highest seq delivered (persisted for durable queues, see `store`).
    delivered_mark: u64,
    last_used: Option<Instant>,
    deleted: bool,
}

/// Declared properties of a queue.
#[derive(Debug, Clone, Default)]
pub struct QueueOptions {
    /// Survives a restart.
    pub durable: bool,
    /// The connection that owns it, if exclusive.
    pub exclusive_owner: Option<u64>,
    /// Deleted when its last consumer goes.
    pub auto_delete: bool,
    /// Arguments as declared.
    pub arguments: FieldTable,
}

/// One queue.
#[derive(Debug)]
pub struct Queue {
    /// Its name.
    pub name: ShortStr,
    /// Declared properties.
    pub options: QueueOptions,
    /// Validated arguments.
    pub args: QueueArgs,
    vhost: Weak<Vhost>,
    gauge: Arc<MemoryGauge>,
    /// Set while the queue is over [`FLOW_HIGH`] with consumers.
    crowded: std::sync::atomic::AtomicBool,
    /// Wakes publishers waiting for the queue to drain.
    drained: tokio::sync::Notify,
    /// The store and this queue's id in it, for durable queues.
    durable_store: Option<(Arc<Persistence>, u64)>,
    /// Message counters (`stats`).
    pub(crate) stats: QueueCounters,
    state: Mutex<QueueState>,
}

impl Queue {
    /// A new, empty queue.
    pub fn new(
        name: ShortStr,
        options: QueueOptions,
        args: QueueArgs,
        vhost: Weak<Vhost>,
        gauge: Arc<MemoryGauge>,
        durable_store: Option<(Arc<Persistence>, u64)>,
        counters: Arc<BrokerCounters>,
    ) -> Self {
        Queue {
            name,
            options,
            args,
            vhost,
            gauge,
            crowded: std::sync::atomic::AtomicBool::new(false),
            drained: tokio::sync::Notify::new(),
            durable_store,
            stats: QueueCounters::new(counters),
            state: Mutex::new(QueueState {
                last_used: Some(Instant::now()),
                ..QueueState::default()
            }),
        }
    }

    fn lock(&self) -> MutexGuard<'_, QueueState> {
        self.state.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// Offers a message; dispatches it at once if a consumer has credit.
    pub fn publish(self: &Arc<Self>, message: Arc<Message>) -> Enqueued {
        self.offer(message, None)
    }

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

    /// Offers a message at a place from [`Queue::reserve`], whose index
    /// entry is already written.
    pub fn publish_reserved(self: &Arc<Self>, message: Arc<Message>, seq: u64) -> Enqueued {
        self.offer(message, Some(seq))
    }

    fn offer(self: &Arc<Self>, message: Arc<Message>, reserved: Option<u64>) -> Enqueued {
        let mut dead = Vec::new();
        let outcome = {
            let mut st = self.lock();
            if st.deleted {
                self.unlog(&message, reserved);
                return Enqueued::Accepted { sync: 0 };
            }
            let now = Instant::now();
            let ttl = match (self.args.message_ttl, message.ttl_ms) {
                (Some(a), Some(b)) => Some(a.min(b)),
                (a, b) => a.or(b),
            };
            let priority = match self.args.max_priority {
                Some(max) => message.priority.min(max),
                None => 0,
            };
            if self.is_full_for(&st, &message) {
                match self.args.overflow {
                    Overflow::DropHead => {}
                    Overflow::RejectPublish => {
                        self.unlog(&message, reserved);
                        return Enqueued::Refused;
                    }
                    Overflow::RejectPublishDlx => {
                        self.unlog(&message, reserved);
                        dead.push(DeadLetter {
                            message,
                            reason: DeadLetterReason::MaxLen,
                        });
                        drop(st);
                        self.dead_letter(dead);
                        return Enqueued::Refused;
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
            self.dispatch_locked(&mut st, &mut dead, now);
            Enqueued::Accepted { sync }
        };
        self.dead_letter(dead);
        outcome
    }

    fn is_full_for(&self, st: &QueueState, message: &Message) -> bool {
        let by_count = self
            .args
            .max_length
            .is_some_and(|max| st.ready.len() as u64 >= max);
        let by_bytes = self
            .args
            .max_length_bytes
            .is_some_and(|max| (st.ready_bytes + message.body.len()) as u64 > max);
        by_count || by_bytes
    }

    fn enforce_max_length(&self, st: &mut QueueState, dead: &mut Vec<DeadLetter>) {
        if self.args.overflow != Overflow::DropHead {
            return;
        }
        loop {
            let over_count = self
                .args
                .max_length
                .is_some_and(|max| st.ready.len() as u64 > max);
            let over_bytes = self
                .args
                .max_length_bytes
                .is_some_and(|max| st.ready_bytes as u64 > max);
            if !(over_count || over_bytes) {
                return;
            }
            match self.pop_ready(st) {
                Some(head) => self.discard(head, DeadLetterReason::MaxLen, dead),
                None => return,
            }
        }
    }

    fn insert_ready(&self, st: &mut QueueState, queued: QueuedMessage) {
        if st.ready.len() >= FLOW_HIGH && !st.consumers.is_empty() {
            self.crowded
                .store(true, std::sync::atomic::Ordering::Release);
        }
        st.ready_bytes += queued.message.body.len();
        if queued.expires_at.is_some() {
            st.expiring += 1;
        }
        let key = queued.order_key();
        if st.ready.back().is_none_or(|last| last.order_key() < key) {
            st.ready.push_back(queued);
        } else {
            let at = st.ready.partition_point(|m| m.order_key() < key);
            st.ready.insert(at, queued);
        }
    }

    /// Wakes waiting publishers once the queue has drained enough (or has
    /// no consumers left to drain it).
    fn check_drained(&self, st: &QueueState) {
        if (st.ready.len() <= FLOW_LOW || st.consumers.is_empty())
            && self
                .crowded
                .swap(false, std::sync::atomic::Ordering::AcqRel)
        {
            self.drained.notify_waiters();
        }
    }

    /// Whether publishers to this queue should slow down.
    pub fn is_crowded(&self) -> bool {
        self.crowded.load(std::sync::atomic::Ordering::Acquire)
    }

    /// Resolves once the queue is no longer crowded.
    pub async fn uncrowded(&self) {
        loop {
            let drained = self.drained.notified();
            if !self.is_crowded() {
                return;
            }
            drained.await;
        }
    }

    fn pop_ready(&self, st: &mut QueueState) -> Option<QueuedMessage> {
        let head = st.ready.pop_front()?;
        if self.crowded.load(std::sync::atomic::Ordering::Relaxed) {
            self.check_drained(st);
        }
        st.ready_bytes -= head.message.body.len();
        if head.expires_at.is_some() {
            st.expiring -= 1;
        }
        Some(head)
    }

    /// Takes the head message that has not expired, expiring those that have.
    fn pop_live(
        &self,
        st: &mut QueueState,
        now: Instant,
        dead: &mut Vec<DeadLetter>,
    ) -> Option<QueuedMessage> {
        loop {
            let head = self.pop_ready(st)?;
            if head.expires_at.is_some_and(|at| at < now) {
                self.discard(head, DeadLetterReason::Expired, dead);
            } else {
                return Some(head);
            }
        }
    }

    /// Writes the index entry of a stored message; returns the submission
    /// number (0 if the message is not stored in this queue).
    fn log(&self, queued: &QueuedMessage) -> u64 {
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
    fn log_delivery(&self, st: &mut QueueState, queued: &QueuedMessage) {
        if queued.seq <= st.delivered_mark {
            return;
        }
        st.delivered_mark = queued.seq;
        if let (Some((persistence, queue)), Some(_)) = (&self.durable_store, &queued.message.stored)
        {
            persistence.submit(vec![StoreOp::Delivered {
                queue: *queue,
                seq: queued.seq,
            }]);
        }
    }

    /// A message this queue was offered but does not keep: removes its
    /// index entry if one was written at a reserved place, and the shared
    /// record if this was its last queue.
    fn unlog(&self, message: &Message, reserved: Option<u64>) {
        let (Some((persistence, queue)), Some(stored)) = (&self.durable_store, &message.stored)
        else {
            return;
        };
        let mut ops = Vec::new();
        if let Some(seq) = reserved {
            ops.push(StoreOp::Dequeue { queue: *queue, seq });
        }
        if let Some(id) = stored.release() {
            ops.push(StoreOp::DeleteMessage { id });
        }
        if !ops.is_empty() {
            persistence.submit(ops);
        }
    }

    /// A message leaves this queue for good: release its memory and its
    /// index entry (and the shared record, if no other queue holds it).
    fn release(&self, queued: &QueuedMessage) {
        self.gauge.sub(queued.message.weight());
        let (Some((persistence, queue)), Some(stored)) =
            (&self.durable_store, &queued.message.stored)
        else {
            return;
        };
        let mut ops = vec![StoreOp::Dequeue {
            queue: *queue,
            seq: queued.seq,
        }];
        if let Some(id) = stored.release() {
            ops.push(StoreOp::DeleteMessage { id });
        }
        persistence.submit(ops);
    }

    /// A message leaves the queue for good: dead-letter it if the queue has a
    /// dead-letter exchange, and release it.
    fn discard(&self, queued: QueuedMessage, reason: DeadLetterReason, dead: &mut Vec<DeadLetter>) {
        self.release(&queued);
        if self.args.dead_letter_exchange.is_some() {
            dead.push(DeadLetter {
                message: queued.message,
                reason,
            });
        }
    }

    /// Delivers ready messages to consumers with credit, round-robin.
    pub fn dispatch(self: &Arc<Self>) {
        let mut dead = Vec::new();
        {
            let mut st = self.lock();
            self.dispatch_locked(&mut st, &mut dead, Instant::now());
        }
        self.dead_letter(dead);
    }

    fn dispatch_locked(
        self: &Arc<Self>,
        st: &mut QueueState,
        dead: &mut Vec<DeadLetter>,
        now: Instant,
    ) {
        let count = st.consumers.len();
        if count == 0 || st.ready.is_empty() {
            return;
        }
        // Consumers whose connection had no room during this dispatch.
        let mut full: Vec<usize> = Vec::new();
        while !st.ready.is_empty() {
            let Some(index) = Self::next_consumer(st, &full) else {
                // No consumer can take a message now; credit or room will
                // trigger another dispatch.
                return;
            };
            let consumer = Arc::clone(&st.consumers[index]);
            let Some(permit) = consumer.channel.outbox.try_reserve() else {
                consumer.channel.outbox.wait_for_room(self);
                full.push(index);
                continue;
            };
            st.cursor = (index + 1) % count;
            let Some(queued) = self.pop_live(st, now, dead) else {
                return;
            };
            let delivery_tag = {
                let mut deliveries = consumer.channel.deliveries();
                let tag = deliveries.next_tag();
                if !consumer.no_ack {
                    deliveries.push(Unacked {
                        tag,
                        queue: Arc::clone(self),
                        message: queued.clone(),
                        consumer: Some(Arc::clone(&consumer)),
                    });
                }
                tag
            };
            self.stats.delivered(consumer.no_ack, queued.redelivered);
            if consumer.no_ack {
                self.release(&queued);
            } else {
                self.log_delivery(st, &queued);
                consumer.took_one();
            }
            permit.send(Outbound::Deliver {
                channel: consumer.channel.id,
                consumer_tag: consumer.tag.clone(),
                delivery_tag,
                redelivered: queued.redelivered,
                message: queued.message,
            });
        }
    }

    /// The consumer to deliver to next: among those with credit (and not
    /// known to be out of room), the highest `x-priority`, round-robin from
    /// the cursor among equals. Without priorities that is simply the first
    /// consumer with credit after the previous one.
    fn next_consumer(st: &QueueState, full: &[usize]) -> Option<usize> {
        let count = st.consumers.len();
        let mut best: Option<usize> = None;
        for offset in 0..count {
            let index = (st.cursor + offset) % count;
            let consumer = &st.consumers[index];
            if full.contains(&index) || !consumer.has_credit() {
                continue;
            }
            if !st.prioritised {
                return Some(index);
            }
            if best.is_none_or(|b| consumer.priority > st.consumers[b].priority) {
                best = Some(index);
            }
        }
        best
    }

    /// basic.get: the head message, recorded as unacked on `link` unless
    /// `no_ack`. Returns the delivery tag, the message and how many remain.
    pub fn get(
        self: &Arc<Self>,
        link: &ChannelLink,
        no_ack: bool,
    ) -> Option<(u64, QueuedMessage, u32)> {
        let mut dead = Vec::new();
        let got = {
            let mut st = self.lock();
            st.last_used = Some(Instant::now());
            let queued = self.pop_live(&mut st, Instant::now(), &mut dead);
            queued.map(|queued| {
                let mut deliveries = link.deliveries();
                let tag = deliveries.next_tag();
                self.stats.got(no_ack, queued.redelivered);
                if no_ack {
                    self.release(&queued);
                } else {
                    self.log_delivery(&mut st, &queued);
                    deliveries.push(Unacked {
                        tag,
                        queue: Arc::clone(self),
                        message: queued.clone(),
                        consumer: None,
                    });
                }
                (tag, queued, st.ready.len() as u32)
            })
        };
        if got.is_none() {
            self.stats.got_nothing();
        }
        self.dead_letter(dead);
        got
    }

    /// Puts delivered messages back in their original places, marked
    /// redelivered, and dispatches them again.
    pub fn requeue(self: &Arc<Self>, messages: impl IntoIterator<Item = QueuedMessage>) {
        let mut dead = Vec::new();
        {
            let mut st = self.lock();
            for mut queued in messages {
                self.stats.unacked_returned();
                if st.deleted {
                    self.release(&queued);
                    continue;
                }
                queued.redelivered = true;
                self.insert_ready(&mut st, queued);
            }
            self.dispatch_locked(&mut st, &mut dead, Instant::now());
        }
        self.dead_letter(dead);
    }

    /// An unacked message was acked (or rejected without dead-lettering).
    pub fn settle(&self, queued: &QueuedMessage) {
        self.stats.acked();
        self.release(queued);
    }

    /// A message was rejected without requeue: dead-letter it if configured.
    pub fn reject(&self, queued: QueuedMessage) {
        self.stats.unacked_returned();
        let mut dead = Vec::new();
        self.discard(queued, DeadLetterReason::Rejected, &mut dead);
        self.dead_letter(dead);
    }

    /// Puts recovered messages back after a restart, in their order, with
    /// the queue's delivery mark.
    pub fn restore(&self, messages: Vec<QueuedMessage>, delivered_mark: u64) {
        let mut st = self.lock();
        st.delivered_mark = delivered_mark;
        for queued in messages {
            st.next_seq = st.next_seq.max(queued.seq);
            self.gauge.add(queued.message.weight());
            self.insert_ready(&mut st, queued);
        }
    }

    /// This queue's id in the store, if it is durable and persisted.
    pub fn store_id(&self) -> Option<u64> {
        self.durable_store.as_ref().map(|(_, id)| *id)
    }

    /// Adds a consumer; 403 if an exclusive consumer is in the way.
    pub fn add_consumer(self: &Arc<Self>, consumer: Arc<Consumer>) -> AmqpResult<()> {
        {
            let mut st = self.lock();
            if st.exclusive_consumer || (consumer.exclusive && !st.consumers.is_empty()) {
                return Err(AmqpError::access_refused(format_args!(
                    "queue '{}' in vhost '{}' in exclusive use",
                    self.name,
                    self.vhost_name()
                )));
            }
            st.exclusive_consumer = consumer.exclusive;
            st.prioritised |= consumer.priority != 0;
            st.consumers.push(consumer);
            self.stats.consumer_added();
            st.last_used = None;
        }
        self.dispatch();
        Ok(())
    }

    /// Removes a consumer; true if the queue should now be auto-deleted.
    pub fn remove_consumer(&self, consumer: &Arc<Consumer>) -> bool {
        let mut st = self.lock();
        let before = st.consumers.len();
        st.consumers.retain(|c| !Arc::ptr_eq(c, consumer));
        if st.consumers.len() == before {
            return false;
        }
        self.stats.consumers_removed(1);
        if consumer.exclusive {
            st.exclusive_consumer = false;
        }
        st.prioritised = st.consumers.iter().any(|c| c.priority != 0);
        self.check_drained(&st);
        if st.consumers.is_empty() {
            st.last_used = Some(Instant::now());
        }
        st.cursor = 0;
        self.options.auto_delete && st.consumers.is_empty() && !st.deleted
    }

    /// Ready messages (expired ones at the head are dropped first).
    pub fn message_count(&self) -> u32 {
        let mut dead = Vec::new();
        let count = {
            let mut st = self.lock();
            self.expire_head(&mut st, &mut dead);
            st.ready.len() as u32
        };
        self.dead_letter(dead);
        count
    }

    /// Number of consumers.
    pub fn consumer_count(&self) -> u32 {
        self.lock().consumers.len() as u32
    }

    /// Marks the queue used (a redeclare), for x-expires.
    pub fn touch(&self) {
        let mut st = self.lock();
        if st.consumers.is_empty() {
            st.last_used = Some(Instant::now());
        }
    }

    /// Drops every ready message; returns how many.
    pub fn purge(&self) -> u32 {
        let mut st = self.lock();
        let count = st.ready.len() as u32;
        for queued in std::mem::take(&mut st.ready) {
            self.release(&queued);
        }
        st.ready_bytes = 0;
        st.expiring = 0;
        self.check_drained(&st);
        count
    }

    /// Marks the queue deleted and drops its messages. Its consumers are
    /// handed back to be told with basic.cancel ([`Deleted::notify`]) once
    /// the caller has answered whoever deleted it: RabbitMQ sends
    /// queue.delete-ok before the cancels.
    pub fn delete(&self) -> Deleted {
        let consumers = {
            let mut st = self.lock();
            st.deleted = true;
            std::mem::take(&mut st.consumers)
        };
        self.stats.queue_deleted(consumers.len());
        Deleted {
            messages: self.purge(),
            consumers,
        }
    }

    /// Whether the queue has been deleted.
    pub fn is_deleted(&self) -> bool {
        self.lock().deleted
    }

    /// Whether it has consumers (for if-unused).
    pub fn has_consumers(&self) -> bool {
        !self.lock().consumers.is_empty()
    }

    /// Drops expired messages at the head; called by the vhost's sweeper and
    /// before counting.
    pub fn expire(&self) {
        let mut dead = Vec::new();
        {
            let mut st = self.lock();
            self.expire_head(&mut st, &mut dead);
        }
        self.dead_letter(dead);
    }

    fn expire_head(&self, st: &mut QueueState, dead: &mut Vec<DeadLetter>) {
        if st.expiring == 0 {
            return;
        }
        let now = Instant::now();
        while st
            .ready
            .front()
            .is_some_and(|m| m.expires_at.is_some_and(|at| at < now))
        {
            if let Some(head) = self.pop_ready(st) {
                self.discard(head, DeadLetterReason::Expired, dead);
            }
        }
    }

    /// Whether x-expires has run out: unused (no consumers, no get, no
    /// redeclare) for longer than it allows.
    pub fn unused_expired(&self) -> bool {
        let Some(expires) = self.args.expires else {
            return false;
        };
        let st = self.lock();
        st.consumers.is_empty()
            && st
                .last_used
                .is_some_and(|at| at.elapsed() >= Duration::from_millis(expires))
    }

    fn vhost_name(&self) -> ShortStr {
        self.vhost
            .upgrade()
            .map(|v| v.name.clone())
            .unwrap_or_default()
    }

    /// Routes dead letters through the dead-letter exchange, with the
    /// `x-death` header RabbitMQ adds.
    fn dead_letter(&self, dead: Vec<DeadLetter>) {
        if dead.is_empty() {
            return;
        }
        let (Some(exchange), Some(vhost)) = (&self.args.dead_letter_exchange, self.vhost.upgrade())
        else {
            return;
        };
        for letter in dead {
            let routing_key = self
                .args
                .dead_letter_routing_key
                .clone()
                .unwrap_or_else(|| letter.message.routing_key.clone());
            let message = crate::deadletter::with_death(
                &letter.message,
                &self.name,
                letter.reason.as_str(),
                exchange,
                &routing_key,
            );
            vhost.publish_internal(exchange, message);
        }
    }
}

/// Reading a queue's state for listings (`inspect`).
impl Queue {
    /// Ready messages, their body bytes, and consumers, read under the lock.
    pub(crate) fn depth(&self) -> crate::inspect::QueueDepth {
        let st = self.lock();
        crate::inspect::QueueDepth {
            ready: st.ready.len() as u64,
            ready_bytes: st.ready_bytes as u64,
            consumers: st.consumers.len() as u64,
        }
    }

    /// The consumers now.
    pub(crate) fn consumers_snapshot(&self) -> Vec<Arc<Consumer>> {
        self.lock().consumers.clone()
    }
}
