//! The broker's counters, with RabbitMQ's meanings (its
//! `rabbit_global_counters` and per-queue `message_stats`): what they
//! count, and the one-line hooks the hot path calls. Every hook is a
//! relaxed atomic add on a counter that nothing else writes in the same
//! instruction sequence; nothing here takes a lock. Reading them into
//! plain structs (`inspect`'s) for the embedding API and the HTTP
//! listeners is the operator layer's job (`admin::inspect`).

use crate::message::Message;
use std::sync::atomic::{AtomicI64, AtomicU64, Ordering};
use std::sync::Arc;

/// A monotonic counter.
#[derive(Debug, Default)]
pub(crate) struct Counter(AtomicU64);

impl Counter {
    /// Adds one.
    #[inline]
    pub fn inc(&self) {
        self.0.fetch_add(1, Ordering::Relaxed);
    }

    /// Adds `n`.
    #[inline]
    pub fn add(&self, n: u64) {
        self.0.fetch_add(n, Ordering::Relaxed);
    }

    /// The current value.
    pub fn get(&self) -> u64 {
        self.0.load(Ordering::Relaxed)
    }
}

/// A histogram with fixed bucket bounds, as Prometheus has them: each
/// observation is one relaxed add to its bucket, the count and the sum.
#[derive(Debug)]
pub(crate) struct Histogram {
    bounds: &'static [f64],
    /// Observations in each bucket (not cumulative); the last is `+Inf`.
    buckets: Vec<AtomicU64>,
    /// The sum, in units of `1 / scale`.
    sum: AtomicU64,
    scale: f64,
}

/// A histogram read at one moment, cumulative as Prometheus writes it.
#[derive(Debug, Clone, PartialEq)]
pub struct HistogramFigures {
    /// (upper bound, observations at or below it), `+Inf` last.
    pub buckets: Vec<(f64, u64)>,
    /// The sum of the observations.
    pub sum: f64,
    /// How many there were.
    pub count: u64,
}

impl Histogram {
    /// A histogram over `bounds` (ascending) whose sum is kept to
    /// `1 / scale` (1e9 for seconds kept to nanoseconds).
    pub fn new(bounds: &'static [f64], scale: f64) -> Self {
        Histogram {
            bounds,
            buckets: (0..=bounds.len()).map(|_| AtomicU64::new(0)).collect(),
            sum: AtomicU64::new(0),
            scale,
        }
    }

    /// Records one observation.
    pub fn observe(&self, value: f64) {
        let bucket = self
            .bounds
            .iter()
            .position(|bound| value <= *bound)
            .unwrap_or(self.bounds.len());
        self.buckets[bucket].fetch_add(1, Ordering::Relaxed);
        self.sum
            .fetch_add((value * self.scale) as u64, Ordering::Relaxed);
    }

    /// Its figures now.
    pub fn figures(&self) -> HistogramFigures {
        let mut running = 0;
        let buckets: Vec<(f64, u64)> = self
            .bounds
            .iter()
            .copied()
            .chain(std::iter::once(f64::INFINITY))
            .zip(&self.buckets)
            .map(|(bound, count)| {
                running += count.load(Ordering::Relaxed);
                (bound, running)
            })
            .collect();
        HistogramFigures {
            count: running,
            buckets,
            sum: self.sum.load(Ordering::Relaxed) as f64 / self.scale,
        }
    }
}

/// A value that goes up and down (consumers, publishers, unacked).
#[derive(Debug, Default)]
pub(crate) struct Level(AtomicI64);

impl Level {
    #[inline]
    fn add(&self, n: i64) {
        self.0.fetch_add(n, Ordering::Relaxed);
    }

    /// The current value (never below zero, even if a decrement raced ahead).
    pub fn get(&self) -> u64 {
        self.0.load(Ordering::Relaxed).max(0) as u64
    }
}

/// Broker-wide counters: `rabbitmq_global_*` and the churn totals
/// (`rabbitmq_*_opened_total` and so on).
#[derive(Debug, Default)]
pub(crate) struct BrokerCounters {
    /// Messages received from publishers (complete, valid publishes).
    pub received: Counter,
    /// Of those, received on channels in confirm mode.
    pub received_confirm: Counter,
    /// Messages routed to at least one queue (or a direct reply-to consumer).
    pub routed: Counter,
    /// Non-mandatory messages no queue took.
    pub unroutable_dropped: Counter,
    /// Mandatory messages returned as unroutable.
    pub unroutable_returned: Counter,
    /// Publisher confirms (acks) sent.
    pub confirmed: Counter,
    /// Deliveries to basic.consume consumers that must ack.
    pub delivered_consume_manual_ack: Counter,
    /// Deliveries to basic.consume consumers with no-ack.
    pub delivered_consume_auto_ack: Counter,
    /// basic.get answers that must be acked.
    pub delivered_get_manual_ack: Counter,
    /// basic.get answers with no-ack.
    pub delivered_get_auto_ack: Counter,
    /// basic.get that found the queue empty.
    pub get_empty: Counter,
    /// Deliveries (consume or get) of messages delivered before.
    pub redelivered: Counter,
    /// Messages acknowledged by consumers.
    pub acknowledged: Counter,
    /// Connections that completed the handshake.
    pub connections_opened: Counter,
    /// Of those, closed since.
    pub connections_closed: Counter,
    /// Channels opened.
    pub channels_opened: Counter,
    /// Channels closed.
    pub channels_closed: Counter,
    /// queue.declare calls (not passive), successful or not, as RabbitMQ counts.
    pub queues_declared: Counter,
    /// Queues created.
    pub queues_created: Counter,
    /// Queues deleted (by a client, auto-delete, exclusive owner gone, x-expires).
    pub queues_deleted: Counter,
    /// Consumers now subscribed.
    pub consumers: Level,
    /// Channels that have published (RabbitMQ's "publishers").
    pub publishers: Level,
    /// Bytes and reads on every client socket since start (connections
    /// closed since included).
    pub socket_traffic: SocketTraffic,
    /// Logins that passed and failed, by protocol ([`AuthProtocol`]).
    pub auth_attempts: [AuthAttempts; 2],
    /// Messages that left a queue for good by expiry, rejection or
    /// overflow, by [`DeadLetterStrategy`] then reason (expired,
    /// rejected, maxlen): RabbitMQ's `messages_dead_lettered_*` of
    /// classic queues.
    pub dead_lettered: [[Counter; 3]; 2],
}

/// What went through a client socket: RabbitMQ's `recv_oct`,
/// `recv_cnt`, `send_oct` and `send_cnt` (bytes, and the reads and
/// writes that moved them).
#[derive(Debug, Default)]
pub(crate) struct SocketTraffic {
    pub received_bytes: Counter,
    pub reads: Counter,
    pub sent_bytes: Counter,
    pub writes: Counter,
}

impl SocketTraffic {
    /// A read of `bytes` from the socket.
    #[inline]
    fn read(&self, bytes: usize) {
        self.received_bytes.add(bytes as u64);
        self.reads.inc();
    }

    /// A write of `bytes` to the socket.
    #[inline]
    fn wrote(&self, bytes: usize) {
        self.sent_bytes.add(bytes as u64);
        self.writes.inc();
    }
}

/// One connection's socket traffic, also added into the broker-wide
/// totals.
#[derive(Debug)]
pub(crate) struct ConnectionTraffic {
    global: Arc<BrokerCounters>,
    pub own: SocketTraffic,
}

impl ConnectionTraffic {
    /// Traffic of a new connection, adding into `global`.
    pub fn new(global: Arc<BrokerCounters>) -> Self {
        ConnectionTraffic {
            global,
            own: SocketTraffic::default(),
        }
    }

    /// A read of `bytes` from the socket.
    #[inline]
    pub fn read(&self, bytes: usize) {
        self.own.read(bytes);
        self.global.socket_traffic.read(bytes);
    }

    /// A write of `bytes` to the socket.
    #[inline]
    pub fn wrote(&self, bytes: usize) {
        self.own.wrote(bytes);
        self.global.socket_traffic.wrote(bytes);
    }
}

/// The protocols whose logins are counted apart, as RabbitMQ labels them.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum AuthProtocol {
    /// AMQP 0-9-1 clients (`amqp091`).
    Amqp091 = 0,
    /// MQTT clients (`mqtt`).
    Mqtt = 1,
}

/// One protocol's logins.
#[derive(Debug, Default)]
pub(crate) struct AuthAttempts {
    /// Logins that passed.
    pub succeeded: Counter,
    /// Logins that were refused (unknown user, wrong password, no
    /// certificate, or a user not allowed from that address).
    pub failed: Counter,
}

/// Why a message was dead-lettered (the `reason` in `x-death`, and the
/// dead-letter counters' label).
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
    /// Its name in `x-death`.
    pub fn as_str(self) -> &'static str {
        match self {
            DeadLetterReason::Rejected => "rejected",
            DeadLetterReason::Expired => "expired",
            DeadLetterReason::MaxLen => "maxlen",
        }
    }
}

/// What became of a message a queue let go (RabbitMQ 3.10's
/// `dead_letter_strategy` label for classic queues).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum DeadLetterStrategy {
    /// The queue has no dead-letter exchange, or it does not exist: the
    /// message is dropped (`disabled`).
    Disabled = 0,
    /// Republished to the queue's dead-letter exchange, without
    /// confirmation (`at_most_once`).
    AtMostOnce = 1,
}

impl BrokerCounters {
    /// A complete, valid publish arrived on a channel.
    #[inline]
    pub fn received(&self, confirm_mode: bool) {
        self.received.inc();
        if confirm_mode {
            self.received_confirm.inc();
        }
    }

    /// Where a routed publish went.
    #[inline]
    pub fn routed(&self, reached: bool, mandatory: bool) {
        match (reached, mandatory) {
            (true, _) => self.routed.inc(),
            (false, true) => self.unroutable_returned.inc(),
            (false, false) => self.unroutable_dropped.inc(),
        }
    }

    /// The channel started publishing: one more publisher.
    pub fn publisher_added(&self) {
        self.publishers.add(1);
    }

    /// A publishing channel closed.
    pub fn publisher_removed(&self) {
        self.publishers.add(-1);
    }

    /// A login over `protocol` passed or failed.
    pub fn login(&self, protocol: AuthProtocol, passed: bool) {
        let attempts = &self.auth_attempts[protocol as usize];
        if passed {
            attempts.succeeded.inc();
        } else {
            attempts.failed.inc();
        }
    }

    /// A message left a queue for good, for `reason`, and `strategy`
    /// says where it went.
    pub fn dead_lettered(&self, reason: DeadLetterReason, strategy: DeadLetterStrategy) {
        let reason = match reason {
            DeadLetterReason::Expired => 0,
            DeadLetterReason::Rejected => 1,
            DeadLetterReason::MaxLen => 2,
        };
        self.dead_lettered[strategy as usize][reason].inc();
    }
}

/// What a run of messages adds to the unacked levels.
#[derive(Debug, Default)]
struct Held {
    messages: i64,
    bytes: i64,
    persistent: i64,
}

impl Held {
    fn of<'a>(messages: impl IntoIterator<Item = &'a Message>) -> Held {
        let mut held = Held::default();
        for message in messages {
            held.messages += 1;
            held.bytes += message.body.len() as i64;
            held.persistent += i64::from(message.persistent);
        }
        held
    }
}

/// One queue's counters (its `message_stats` in RabbitMQ's management
/// API), each also counted in the broker-wide totals.
#[derive(Debug)]
pub(crate) struct QueueCounters {
    global: Arc<BrokerCounters>,
    /// Messages that entered the queue.
    pub published: Counter,
    /// Deliveries to consumers that must ack.
    pub delivered_manual_ack: Counter,
    /// Deliveries to no-ack consumers.
    pub delivered_auto_ack: Counter,
    /// basic.get answers that must be acked.
    pub got_manual_ack: Counter,
    /// basic.get answers with no-ack.
    pub got_auto_ack: Counter,
    /// basic.get that found nothing.
    pub get_empty: Counter,
    /// Redeliveries.
    pub redelivered: Counter,
    /// Acks.
    pub acknowledged: Counter,
    /// Delivered and not yet acked, rejected or requeued.
    pub unacked: Level,
    /// Their body bytes.
    pub unacked_bytes: Level,
    /// How many of them are persistent (delivery-mode 2).
    pub unacked_persistent: Level,
}

impl QueueCounters {
    /// Counters for a new queue, adding into `global`.
    pub fn new(global: Arc<BrokerCounters>) -> Self {
        QueueCounters {
            global,
            published: Counter::default(),
            delivered_manual_ack: Counter::default(),
            delivered_auto_ack: Counter::default(),
            got_manual_ack: Counter::default(),
            got_auto_ack: Counter::default(),
            get_empty: Counter::default(),
            redelivered: Counter::default(),
            acknowledged: Counter::default(),
            unacked: Level::default(),
            unacked_bytes: Level::default(),
            unacked_persistent: Level::default(),
        }
    }

    /// A message entered the queue.
    #[inline]
    pub fn published(&self) {
        self.published.inc();
    }

    /// `message` was delivered and awaits its ack.
    #[inline]
    fn held(&self, message: &Message) {
        self.unacked.add(1);
        self.unacked_bytes.add(message.body.len() as i64);
        if message.persistent {
            self.unacked_persistent.add(1);
        }
    }

    /// `message`, delivered, was acked, rejected or came back.
    #[inline]
    fn let_go(&self, message: &Message) {
        self.unacked.add(-1);
        self.unacked_bytes.add(-(message.body.len() as i64));
        if message.persistent {
            self.unacked_persistent.add(-1);
        }
    }

    /// A delivery of `message` to a consumer.
    #[inline]
    pub fn delivered(&self, no_ack: bool, redelivered: bool, message: &Message) {
        if no_ack {
            self.delivered_auto_ack.inc();
            self.global.delivered_consume_auto_ack.inc();
        } else {
            self.delivered_manual_ack.inc();
            self.global.delivered_consume_manual_ack.inc();
            self.held(message);
        }
        if redelivered {
            self.redelivered();
        }
    }

    /// A basic.get answered with `message`.
    pub fn got(&self, no_ack: bool, redelivered: bool, message: &Message) {
        if no_ack {
            self.got_auto_ack.inc();
            self.global.delivered_get_auto_ack.inc();
        } else {
            self.got_manual_ack.inc();
            self.global.delivered_get_manual_ack.inc();
            self.held(message);
        }
        if redelivered {
            self.redelivered();
        }
    }

    fn redelivered(&self) {
        self.redelivered.inc();
        self.global.redelivered.inc();
    }

    /// A basic.get found the queue empty.
    pub fn got_nothing(&self) {
        self.get_empty.inc();
        self.global.get_empty.inc();
    }

    /// Unacked deliveries of `messages` were acked: one add a counter for
    /// them all (a multiple ack settles many at once). The unacked level
    /// goes down before the acknowledged count goes up, so a reader
    /// sampling in between sees `acknowledged + unacked` under the truth
    /// by the batch, never over it.
    pub fn acked<'a>(&self, messages: impl IntoIterator<Item = &'a Message>) {
        let held = Held::of(messages);
        if held.messages == 0 {
            return;
        }
        self.unacked.add(-held.messages);
        self.unacked_bytes.add(-held.bytes);
        if held.persistent > 0 {
            self.unacked_persistent.add(-held.persistent);
        }
        self.acknowledged.add(held.messages as u64);
        self.global.acknowledged.add(held.messages as u64);
    }

    /// An unacked delivery of `message` was rejected, or came back to be
    /// requeued.
    #[inline]
    pub fn unacked_returned(&self, message: &Message) {
        self.let_go(message);
    }

    /// A consumer subscribed.
    pub fn consumer_added(&self) {
        self.global.consumers.add(1);
    }

    /// `count` consumers left.
    pub fn consumers_removed(&self, count: usize) {
        self.global.consumers.add(-(count as i64));
    }

    /// A message left the queue for good (see
    /// [`BrokerCounters::dead_lettered`]).
    pub fn dead_lettered(&self, reason: DeadLetterReason, strategy: DeadLetterStrategy) {
        self.global.dead_lettered(reason, strategy);
    }

    /// The queue was deleted with `consumers` still subscribed.
    pub fn queue_deleted(&self, consumers: usize) {
        self.global.queues_deleted.inc();
        self.consumers_removed(consumers);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_histogram_is_cumulative_with_inf_last() {
        static BOUNDS: [f64; 3] = [1.0, 10.0, 100.0];
        let h = Histogram::new(&BOUNDS, 1000.0);
        for value in [0.5, 1.0, 3.0, 50.0, 5000.0] {
            h.observe(value);
        }
        let f = h.figures();
        assert_eq!(
            f.buckets,
            [(1.0, 2), (10.0, 3), (100.0, 4), (f64::INFINITY, 5)]
        );
        assert_eq!(f.count, 5);
        assert!((f.sum - 5054.5).abs() < 1e-9);
    }

    #[test]
    fn queue_counters_add_into_the_global_ones() {
        let global = Arc::new(BrokerCounters::default());
        let a = QueueCounters::new(Arc::clone(&global));
        let b = QueueCounters::new(Arc::clone(&global));
        let persistent = crate::testkit::message(
            &leveret_protocol::ShortStr::from_static(""),
            "k",
            "twelve bytes",
            &leveret_protocol::BasicProperties {
                delivery_mode: Some(2),
                ..Default::default()
            },
        );
        let transient = crate::testkit::message(
            &leveret_protocol::ShortStr::from_static(""),
            "k",
            "five!",
            &Default::default(),
        );
        a.delivered(false, false, &persistent);
        a.delivered(false, false, &transient);
        assert_eq!(
            (
                a.unacked.get(),
                a.unacked_bytes.get(),
                a.unacked_persistent.get()
            ),
            (2, 17, 1)
        );
        a.delivered(true, true, &persistent);
        b.got(false, true, &transient);
        b.got(true, false, &transient);
        b.got_nothing();
        a.acked([&*persistent]);
        assert_eq!(
            (
                a.unacked.get(),
                a.unacked_bytes.get(),
                a.unacked_persistent.get()
            ),
            (1, 5, 0)
        );
        a.unacked_returned(&transient);
        b.unacked_returned(&transient);
        assert_eq!(a.unacked.get(), 0);
        assert_eq!(a.unacked_bytes.get(), 0);
        assert_eq!(b.unacked.get(), 0);
        assert_eq!(b.unacked_bytes.get(), 0);
        assert_eq!(global.delivered_consume_manual_ack.get(), 2);
        assert_eq!(global.delivered_consume_auto_ack.get(), 1);
        assert_eq!(global.delivered_get_manual_ack.get(), 1);
        assert_eq!(global.delivered_get_auto_ack.get(), 1);
        assert_eq!(global.get_empty.get(), 1);
        assert_eq!(global.redelivered.get(), 2);
        assert_eq!(global.acknowledged.get(), 1);
        assert_eq!(a.redelivered.get(), 1);
        // A multiple ack settles several in one step.
        a.delivered(false, false, &persistent);
        a.delivered(false, false, &transient);
        a.acked([&*persistent, &*transient]);
        assert_eq!(
            (
                a.unacked.get(),
                a.unacked_bytes.get(),
                a.unacked_persistent.get(),
                a.acknowledged.get(),
                global.acknowledged.get()
            ),
            (0, 0, 0, 3, 3)
        );
        a.consumer_added();
        a.consumer_added();
        a.queue_deleted(2);
        assert_eq!(global.consumers.get(), 0);
        assert_eq!(global.queues_deleted.get(), 1);
    }

    #[test]
    fn routing_outcomes_are_counted_apart() {
        let global = BrokerCounters::default();
        global.received(true);
        global.received(false);
        global.routed(true, true);
        global.routed(false, true);
        global.routed(false, false);
        assert_eq!(global.received.get(), 2);
        assert_eq!(global.received_confirm.get(), 1);
        assert_eq!(global.routed.get(), 1);
        assert_eq!(global.unroutable_returned.get(), 1);
        assert_eq!(global.unroutable_dropped.get(), 1);
    }

    #[test]
    fn logins_and_dead_letters_are_counted_by_their_labels() {
        let global = BrokerCounters::default();
        global.login(AuthProtocol::Amqp091, true);
        global.login(AuthProtocol::Amqp091, false);
        global.login(AuthProtocol::Mqtt, false);
        let amqp = &global.auth_attempts[AuthProtocol::Amqp091 as usize];
        let mqtt = &global.auth_attempts[AuthProtocol::Mqtt as usize];
        assert_eq!((amqp.succeeded.get(), amqp.failed.get()), (1, 1));
        assert_eq!((mqtt.succeeded.get(), mqtt.failed.get()), (0, 1));
        global.dead_lettered(DeadLetterReason::Expired, DeadLetterStrategy::Disabled);
        global.dead_lettered(DeadLetterReason::MaxLen, DeadLetterStrategy::AtMostOnce);
        global.dead_lettered(DeadLetterReason::MaxLen, DeadLetterStrategy::AtMostOnce);
        let figures: Vec<[u64; 3]> = global
            .dead_lettered
            .iter()
            .map(|by_reason| [0, 1, 2].map(|i| by_reason[i].get()))
            .collect();
        assert_eq!(figures, [[1, 0, 0], [0, 0, 2]]);
    }
}
