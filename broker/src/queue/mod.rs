//! Queues: ready messages in FIFO order (by priority first when
//! `x-max-priority` is set), the consumers with their round-robin cursor,
//! and dispatch. One `std::sync::Mutex` per queue guards its state; it is
//! held for a few instructions per operation and never across an await, and
//! no other lock is taken inside it except a channel's delivery bookkeeping
//! (always in that order: queue, then channel).
//!
//! A queue knows nothing above it: operations that make messages leave
//! for a dead-letter exchange return them as [`DeadLetters`], and the
//! caller (which knows the vhost) routes them. It uses the consumer layer,
//! whose delivery bookkeeping it fixes to what an unacked delivery keeps of
//! its queue ([`Origin`]; the layers above name [`Consumer`],
//! [`ChannelLink`] and [`Unacked`] from here), the outbox (where a queue
//! that found no room waits, as a `WaitsForRoom`, to dispatch again), the
//! store and the shared pieces.
//!
//! Layout: `args` validates the queue and consumer arguments; `consumers`
//! holds the consumers by priority and chooses the next one (single active
//! consumer included); `dispatch` is the FIFO
//! (taking messages in, max-length, expiry) and delivery to consumers;
//! `durable` writes a durable queue's index entries and delivery mark;
//! `leaving` makes the dead letters and the cancels of a deleted queue;
//! `stream` is the other kind of queue, a stream (`x-queue-type: stream`),
//! whose operations this file's hand over to it.
//! This file holds the state and the operations the layers above call.

mod args;
mod consumers;
mod dispatch;
mod durable;
mod leaving;
mod policies;
mod ready;
mod stream;

pub use args::{ConsumerArgs, Overflow, QueueArgs};
pub use leaving::{DeadLetter, DeadLetterReason, DeadLetters, Deleted};
pub use stream::{is_stream, start_at, StartAt, Stream, StreamArgs, StreamFigures};

use crate::alarm::memory::MemoryGauge;
use crate::error::{AmqpError, AmqpResult};
use crate::message::Message;
use crate::outbox::{Outbound, OutboxPermit, WaitsForRoom};
use crate::policy::Applied;
use crate::slice::{finish_in_background, Progress, Slice};
use crate::stats::{BrokerCounters, QueueCounters};
use crate::store::Persistence;
use consumers::Consumers;
use leveret_protocol::{FieldTable, ShortStr};
use ready::Ready;
use std::sync::{Arc, Mutex, MutexGuard};
use std::time::{Duration, Instant};

/// Ready messages in a queue with consumers above which publishers to it
/// are slowed down (RabbitMQ's flow control, in spirit): reading from a
/// publishing connection pauses until the queue is back under
/// [`FLOW_LOW`], so consumers keep the CPU they need and the backlog (and
/// latency) stays bounded. Queues without consumers are never crowded.
pub const FLOW_HIGH: usize = 20_000;

/// See [`FLOW_HIGH`].
pub const FLOW_LOW: usize = 10_000;

/// Most dead letters one step of expiry makes before its caller routes
/// them: routing one costs microseconds, so a step stays within a slice.
pub const DEAD_LETTERS_PER_STEP: usize = 64;

pub(crate) use crate::arguments::POSITION_HEADER;

/// A random number fixed for this run of the process (another run gets
/// another): names made with it never repeat an earlier run's.
pub fn process_nonce() -> u64 {
    use std::hash::{BuildHasher, Hasher};
    static NONCE: std::sync::OnceLock<u64> = std::sync::OnceLock::new();
    *NONCE.get_or_init(|| {
        let mut hasher = std::collections::hash_map::RandomState::new().build_hasher();
        hasher.write_u128(
            std::time::SystemTime::now()
                .duration_since(std::time::UNIX_EPOCH)
                .map_or(0, |d| d.as_nanos()),
        );
        hasher.finish()
    })
}

/// A position name unique to one non-durable queue in this process: the
/// process's nonce and a count.
fn transient_position_name() -> String {
    use std::sync::atomic::{AtomicU64, Ordering};
    static COUNT: AtomicU64 = AtomicU64::new(0);
    format!(
        "t{:x}-{}",
        process_nonce(),
        COUNT.fetch_add(1, Ordering::Relaxed)
    )
}

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

/// What an unacked delivery keeps of the queue it came from, so that
/// settling it (ack, reject, requeue) goes back there. The consumer
/// layer's types carry it as their type parameter; the aliases below fix
/// it, and the layers above name them.
#[derive(Debug)]
pub struct Origin {
    /// The queue it came from.
    pub queue: Arc<Queue>,
    /// The message and its place in the queue.
    pub message: QueuedMessage,
}

/// A consumer of a queue ([`crate::consumer::Consumer`]).
pub type Consumer = crate::consumer::Consumer<Origin>;

/// What queues need of a channel to deliver to its consumers
/// ([`crate::consumer::ChannelLink`]).
pub type ChannelLink = crate::consumer::ChannelLink<Origin>;

/// A delivery from a queue waiting for ack, nack or reject
/// ([`crate::consumer::Unacked`]).
pub type Unacked = crate::consumer::Unacked<Origin>;

/// Where direct replies to one channel's requests go
/// ([`crate::consumer::ReplyTarget`]).
pub(crate) type ReplyTarget = crate::consumer::ReplyTarget<Origin>;

/// Result of offering a message to a queue.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Enqueued {
    /// The queue took it; on disk once the persister has flushed
    /// submission `sync` (0 when nothing was written).
    Accepted {
        /// Submission number to wait for.
        sync: u64,
    },
    /// The queue is full and its overflow mode refuses publishes (or a
    /// stream could not append it).
    Refused {
        /// Submission that removes what the publish had already stored
        /// for this queue (its reserved index entry, a shared record no
        /// queue keeps), 0 when none: a transaction's commit waits for it,
        /// so a refused message is never left on disk behind a commit-ok.
        sync: u64,
    },
}

#[derive(Debug, Default)]
struct QueueState {
    ready: Ready,
    next_seq: u64,
    consumers: Consumers,
    exclusive_consumer: bool,
    /// Highest seq delivered (persisted for durable queues, see `store`).
    delivered_mark: u64,
    last_used: Option<Instant>,
    /// MQTT shared subscription members that have joined the queue and
    /// whose consume has not arrived yet ([`Queue::join`]): while there
    /// are some, it counts as used and is not auto-deleted.
    #[cfg(feature = "mqtt")]
    joining: usize,
    /// An auto-delete queue due to go once no join is pending: its last
    /// consumer left while one was, or it was created for a join.
    #[cfg(feature = "mqtt")]
    auto_delete_due: bool,
    /// The queue has been found to go, its deletion to follow: auto-delete
    /// ([`Queue::remove_consumer`], [`Queue::leave_join`]), x-expires
    /// ([`Queue::take_expired`]) or an if-unused delete
    /// ([`Queue::take_unused`]). No consumer may come, nor member join,
    /// any more.
    going: bool,
    deleted: bool,
    /// Dead letters found by a dispatch whose caller cannot route them
    /// (a connection's writer), waiting for the vhost's next sweep.
    deferred_dead: Vec<DeadLetter>,
    /// The arguments acted on: the declared ones with the policies'.
    effective: QueueArgs,
    /// The policies that apply.
    applied: Applied,
    /// The queue's own `x-expires` (ms): as declared, or as set since
    /// ([`Queue::set_expires`]).
    own_expires: Option<u64>,
    /// The arguments as they stand once [`Queue::set_expires`] has
    /// changed them (`None`: as declared, `QueueOptions::arguments`).
    changed_arguments: Option<FieldTable>,
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
    /// Validated arguments, as declared (what the queue acts on is these
    /// with its policies': `QueueState::effective`).
    pub args: QueueArgs,
    /// The effective dead-letter exchange and routing key, read when a
    /// message dies (also outside the state's lock, by a reject); written
    /// with `QueueState::effective`, under the state's lock.
    dead_lettering: std::sync::RwLock<(Option<ShortStr>, Option<ShortStr>)>,
    /// The name of the vhost it belongs to, for error texts.
    vhost: ShortStr,
    gauge: Arc<MemoryGauge>,
    /// Set while the queue is over [`FLOW_HIGH`] with consumers.
    crowded: std::sync::atomic::AtomicBool,
    /// Wakes publishers waiting for the queue to drain.
    drained: tokio::sync::Notify,
    /// The store and this queue's id in it, for durable queues.
    durable_store: Option<(Arc<Persistence>, u64)>,
    /// What names this queue in [`POSITION_HEADER`] (`d` and its store id
    /// for a durable queue, whose positions are unique for the store's
    /// life; otherwise unique to this queue in this process).
    position_name: String,
    /// Message counters (`stats`).
    pub(crate) stats: QueueCounters,
    state: Mutex<QueueState>,
    /// Set for a stream, whose operations `stream` handles.
    stream: Option<Stream>,
}

impl Queue {
    /// A new, empty queue.
    pub(crate) fn new(
        name: ShortStr,
        vhost: ShortStr,
        options: QueueOptions,
        args: QueueArgs,
        gauge: Arc<MemoryGauge>,
        durable_store: Option<(Arc<Persistence>, u64)>,
        counters: Arc<BrokerCounters>,
    ) -> Self {
        // No policies until the vhost gives it some (`apply_policies`).
        let effective = args.clone();
        let single_active = args.single_active_consumer;
        let own_expires = args.expires;
        let (position_name, next_seq) = match &durable_store {
            Some((persistence, id)) => (format!("d{id}"), persistence.seq_floor()),
            None => (transient_position_name(), 0),
        };
        Queue {
            name,
            dead_lettering: std::sync::RwLock::new((
                effective.dead_letter_exchange.clone(),
                effective.dead_letter_routing_key.clone(),
            )),
            options,
            args,
            vhost,
            gauge,
            crowded: std::sync::atomic::AtomicBool::new(false),
            drained: tokio::sync::Notify::new(),
            durable_store,
            position_name,
            stats: QueueCounters::new(counters),
            state: Mutex::new(QueueState {
                last_used: Some(Instant::now()),
                next_seq,
                consumers: Consumers::new(single_active),
                own_expires,
                effective,
                ..QueueState::default()
            }),
            stream: None,
        }
    }

    /// A stream queue (`x-queue-type: stream`) on `stream`, durable with
    /// store id `id` (its definition is stored; its records are the
    /// stream's own).
    #[allow(clippy::too_many_arguments)]
    pub(crate) fn new_stream(
        name: ShortStr,
        vhost: ShortStr,
        options: QueueOptions,
        stream: Stream,
        gauge: Arc<MemoryGauge>,
        durable_store: (Arc<Persistence>, u64),
        counters: Arc<BrokerCounters>,
    ) -> Self {
        Queue {
            stream: Some(stream),
            ..Queue::new(
                name,
                vhost,
                options,
                QueueArgs::default(),
                gauge,
                Some(durable_store),
                counters,
            )
        }
    }

    /// A stream's offsets and files; `None` for a classic queue.
    pub fn stream_figures(&self) -> Option<StreamFigures> {
        self.stream.as_ref().map(Stream::figures)
    }

    /// Whether this queue is a stream.
    pub fn is_stream(&self) -> bool {
        self.stream.is_some()
    }

    /// RabbitMQ 3.10's refusal of `what` (`basic.get`, `queue.purge`, ...)
    /// on a stream: 540 NOT_IMPLEMENTED, which closes the connection.
    pub fn refuse_on_stream(&self, what: &str) -> AmqpResult<()> {
        if self.stream.is_none() {
            return Ok(());
        }
        Err(AmqpError::not_implemented(format_args!(
            "{what} not supported by stream queues queue '{}' in vhost '{}'",
            self.name, self.vhost
        )))
    }

    /// Whether this queue keeps persistent messages routed to it in the
    /// store (a durable classic queue; a stream keeps its own log).
    pub fn stores_messages(&self) -> bool {
        self.durable_store.is_some() && self.stream.is_none()
    }

    fn lock(&self) -> MutexGuard<'_, QueueState> {
        self.state.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// Offers a message; dispatches it at once if a consumer has credit.
    pub fn publish(self: &Arc<Self>, message: Arc<Message>) -> (Enqueued, DeadLetters) {
        if self.stream.is_some() {
            return (self.stream_publish(&message), DeadLetters::default());
        }
        self.offer(message, None)
    }

    /// Offers a message at a place from [`Queue::reserve`], whose index
    /// entry is already written.
    pub fn publish_reserved(
        self: &Arc<Self>,
        message: Arc<Message>,
        seq: u64,
    ) -> (Enqueued, DeadLetters) {
        self.offer(message, Some(seq))
    }

    /// Delivers ready messages to consumers with credit, round-robin.
    pub fn dispatch(self: &Arc<Self>) -> DeadLetters {
        if self.stream.is_some() {
            self.stream_dispatch();
            return DeadLetters::default();
        }
        let mut dead = Vec::new();
        let mut st = self.lock();
        self.dispatch_locked(&mut st, &mut dead, Instant::now());
        DeadLetters(dead)
    }

    /// basic.get: sends the head message with basic.get-ok through
    /// `permit`, recorded as unacked on `link` unless `no_ack`. False if
    /// the queue had no message (the permit is given back).
    pub fn get(
        self: &Arc<Self>,
        link: &ChannelLink,
        no_ack: bool,
        permit: OutboxPermit<'_>,
    ) -> (bool, DeadLetters) {
        if self.stream.is_some() {
            // Refused before this by every caller (`refuse_on_stream`).
            return (false, DeadLetters::default());
        }
        let mut dead = Vec::new();
        let mut st = self.lock();
        st.last_used = Some(Instant::now());
        let Some(queued) = self.pop_live(&mut st, Instant::now(), &mut dead) else {
            self.stats.got_nothing();
            return (false, DeadLetters(dead));
        };
        self.stats.got(no_ack, queued.redelivered, &queued.message);
        if no_ack {
            self.release(&queued);
        } else {
            self.log_delivery(&mut st, &queued);
        }
        // As in dispatch: the tag and the send are one step.
        let mut deliveries = link.deliveries();
        let delivery_tag = deliveries.next_tag();
        permit.send(Outbound::GetOk {
            channel: link.id,
            delivery_tag,
            redelivered: queued.redelivered,
            message_count: st.ready.len() as u32,
            message: Arc::clone(&queued.message),
        });
        if !no_ack {
            deliveries.push(Unacked {
                tag: delivery_tag,
                origin: Origin {
                    queue: Arc::clone(self),
                    message: queued,
                },
                consumer: None,
            });
        }
        (true, DeadLetters(dead))
    }

    /// Puts delivered messages back in their original places, marked
    /// redelivered, and dispatches them again: as many as a slice allows
    /// now (the dead letters that dispatch finds are returned), the rest
    /// in the background (theirs wait for the next sweep).
    pub fn requeue(self: &Arc<Self>, messages: Vec<QueuedMessage>) -> DeadLetters {
        if self.stream.is_some() {
            // Nothing left the stream: the credit is back, read on.
            for queued in &messages {
                self.stats.unacked_returned(&queued.message);
            }
            self.stream_dispatch();
            return DeadLetters::default();
        }
        let mut messages = messages.into_iter();
        let mut slice = Slice::start();
        let (dead, progress) = self.requeue_some(&mut messages, &mut slice);
        if progress == Progress::More {
            let queue = Arc::clone(self);
            finish_in_background(move |slice| {
                let (dead, progress) = queue.requeue_some(&mut messages, slice);
                queue.defer(dead);
                progress
            });
        }
        dead
    }

    /// One slice of [`Queue::requeue`].
    fn requeue_some(
        self: &Arc<Self>,
        messages: &mut impl Iterator<Item = QueuedMessage>,
        slice: &mut Slice,
    ) -> (DeadLetters, Progress) {
        let mut dead = Vec::new();
        let mut progress = Progress::Done;
        let mut st = self.lock();
        for mut queued in messages.by_ref() {
            self.stats.unacked_returned(&queued.message);
            if st.deleted {
                self.release(&queued);
            } else {
                queued.redelivered = true;
                self.insert_ready(&mut st, queued);
            }
            if slice.step() {
                progress = Progress::More;
                break;
            }
        }
        self.dispatch_locked(&mut st, &mut dead, Instant::now());
        (DeadLetters(dead), progress)
    }

    /// Keeps dead letters found where nobody can route them (a writer's
    /// dispatch, work finishing in the background) for the vhost's next
    /// sweep ([`Queue::expire_at`]).
    pub fn defer(&self, dead: DeadLetters) {
        if !dead.is_empty() {
            self.lock().deferred_dead.extend(dead);
        }
    }

    /// Unacked messages were acked (or rejected without dead-lettering).
    pub fn settle(&self, settled: &[QueuedMessage]) {
        self.stats
            .acked(settled.iter().map(|queued| &*queued.message));
        if self.stream.is_none() {
            self.release_all(settled);
        }
    }

    /// A message was rejected without requeue: dead-letter it if configured.
    pub fn reject(&self, queued: QueuedMessage) -> DeadLetters {
        self.stats.unacked_returned(&queued.message);
        if self.stream.is_some() {
            return DeadLetters::default();
        }
        let mut dead = Vec::new();
        self.discard(queued, DeadLetterReason::Rejected, &mut dead);
        DeadLetters(dead)
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

    /// Adds a consumer; 403 if an exclusive consumer is in the way, 404 if
    /// the queue is deleted or going. On a single-active-consumer queue it
    /// waits unless none is active.
    pub fn add_consumer(self: &Arc<Self>, consumer: Arc<Consumer>) -> AmqpResult<DeadLetters> {
        if self.stream.is_some() {
            self.add_stream_consumer(consumer, StartAt::Next)?;
            return Ok(self.dispatch());
        }
        {
            let mut st = self.lock();
            // Deleted, or about to be (auto-delete, x-expires, if-unused):
            // consuming it is consuming a queue that is gone.
            if st.deleted || st.going {
                return Err(self.gone());
            }
            if st.exclusive_consumer || (consumer.exclusive && !st.consumers.is_empty()) {
                return Err(AmqpError::access_refused(format_args!(
                    "queue '{}' in vhost '{}' in exclusive use",
                    self.name, self.vhost
                )));
            }
            st.exclusive_consumer = consumer.exclusive;
            st.consumers.add(consumer);
            self.stats.consumer_added();
            st.last_used = None;
        }
        Ok(self.dispatch())
    }

    /// Removes a consumer (cancelled, or its channel closed); if it was the
    /// active one of a single-active-consumer queue, the next waiting one
    /// becomes active, and gets messages once the removed one holds none
    /// unacked (the caller dispatches: after requeueing what the channel
    /// held, when it closes). Returns whether the queue should now be
    /// auto-deleted.
    pub fn remove_consumer(&self, consumer: &Arc<Consumer>) -> bool {
        if self.stream.is_some() {
            return self.remove_stream_consumer(consumer);
        }
        let mut st = self.lock();
        if st.consumers.remove(consumer).is_none() {
            return false;
        }
        self.stats.consumers_removed(1);
        if consumer.exclusive {
            st.exclusive_consumer = false;
        }
        self.check_drained(&st);
        if st.consumers.is_empty() {
            st.last_used = Some(Instant::now());
        }
        let goes = self.options.auto_delete && st.consumers.is_empty() && !st.deleted;
        #[cfg(feature = "mqtt")]
        if goes && st.joining > 0 {
            // A member's consume is on its way: it goes, if at all, once
            // no join is pending (`Queue::leave_join`).
            st.auto_delete_due = true;
            return false;
        }
        st.going |= goes;
        goes
    }

    /// Ready messages, as of the last expiry ([`Queue::expire_at`]): what
    /// queue.declare-ok says and queue.delete's if-empty judges. None for
    /// a stream, whose consumers take nothing away (RabbitMQ 3.10 says 0
    /// too, and deletes a stream under if-empty); listings give a stream's
    /// records ([`Queue::depth`]).
    pub fn message_count(&self) -> u32 {
        if self.stream.is_some() {
            return 0;
        }
        self.lock().ready.len() as u32
    }

    /// Number of consumers.
    pub fn consumer_count(&self) -> u32 {
        if let Some(stream) = &self.stream {
            return stream.reader_count() as u32;
        }
        self.lock().consumers.len() as u32
    }

    /// Marks the queue used (a redeclare), for x-expires.
    pub fn touch(&self) {
        let mut st = self.lock();
        if st.consumers.is_empty() {
            st.last_used = Some(Instant::now());
        }
    }

    /// An MQTT shared subscription's member joins the queue (`created`:
    /// declared for it) and is about to bind and consume it: until its
    /// [`Queue::leave_join`] the queue counts as used (x-expires does not
    /// run) and is not auto-deleted, however long the consume takes. False
    /// (nothing held) if the queue is going: deleted, auto-deleted by its
    /// last consumer's leaving, or expired.
    #[cfg(feature = "mqtt")]
    pub fn join(&self, created: bool) -> bool {
        let mut st = self.lock();
        if st.deleted || st.going {
            return false;
        }
        st.joining += 1;
        st.auto_delete_due |= created && self.options.auto_delete;
        true
    }

    /// A [`Queue::join`]'s member has consumed the queue, or gone without:
    /// x-expires runs from now if no consumer is left; returns whether the
    /// queue should now be auto-deleted (no consumer, no join pending, and
    /// its last consumer left meanwhile or none ever came).
    #[cfg(feature = "mqtt")]
    pub fn leave_join(&self) -> bool {
        let mut st = self.lock();
        st.joining = st.joining.saturating_sub(1);
        if st.joining > 0 || !st.consumers.is_empty() {
            return false;
        }
        st.last_used = Some(Instant::now());
        let goes = st.auto_delete_due && !st.deleted;
        st.going |= goes;
        goes
    }

    /// Drops every ready message; returns how many. They are released
    /// (memory, store) a slice at a time, the first slice now.
    pub fn purge(self: &Arc<Self>) -> u32 {
        if self.stream.is_some() {
            // Refused before this by every caller (`refuse_on_stream`).
            return 0;
        }
        let mut purged = {
            let mut st = self.lock();
            let purged = std::mem::take(&mut st.ready);
            self.check_drained(&st);
            purged
        };
        let count = purged.len() as u32;
        let queue = Arc::clone(self);
        finish_in_background(move |slice| {
            while let Some(queued) = purged.pop_front() {
                queue.release(&queued);
                if slice.step() {
                    return Progress::More;
                }
            }
            Progress::Done
        });
        count
    }

    /// Marks the queue deleted and drops its messages. Its consumers are
    /// handed back to be told with basic.cancel ([`Deleted::notify`]) once
    /// the caller has answered whoever deleted it: RabbitMQ sends
    /// queue.delete-ok before the cancels.
    pub fn delete(self: &Arc<Self>) -> Deleted {
        if self.stream.is_some() {
            self.lock().deleted = true;
            return self.stream_delete();
        }
        let consumers = {
            let mut st = self.lock();
            st.deleted = true;
            st.consumers.take_all()
        };
        self.stats.queue_deleted(consumers.len());
        Deleted {
            messages: self.purge(),
            consumers,
        }
    }

    /// The 404 a consume of a deleted or going queue gets, as RabbitMQ
    /// answers a consume of a queue that is gone.
    fn gone(&self) -> AmqpError {
        AmqpError::no_queue(&self.name, &self.vhost)
    }

    /// Whether the queue has been deleted.
    pub fn is_deleted(&self) -> bool {
        self.lock().deleted
    }

    /// queue.delete's if-unused, decided and acted on in one lock hold:
    /// whether the queue is unused (no consumer, and no MQTT shared
    /// subscription's member that joined it with its consume on its way,
    /// [`Queue::join`]); if so it is marked going, so that no consumer
    /// (404) nor member (it declares the queue anew) comes before the
    /// caller deletes it, which it does at once, with no await between
    /// (RabbitMQ decides and deletes in one step of the queue's process).
    /// A stream's readers are counted, and it is marked, under the
    /// stream's own lock, which its consumers are added under.
    pub fn take_unused(&self) -> bool {
        if let Some(stream) = &self.stream {
            return stream.take_unused();
        }
        let mut st = self.lock();
        #[cfg(feature = "mqtt")]
        if st.joining > 0 {
            return false;
        }
        if !st.consumers.is_empty() {
            return false;
        }
        st.going = true;
        true
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

    /// Drops the messages at the head that expired by `now`, as many as
    /// `slice` allows (and at most [`DEAD_LETTERS_PER_STEP`] dead
    /// letters, which the caller routes before the next step); called by
    /// the vhost's sweeper. Returns them as dead letters, with any a
    /// writer's dispatch deferred, and whether more may have expired.
    pub fn expire_at(&self, now: Instant, slice: &mut Slice) -> (DeadLetters, Progress) {
        if let Some(stream) = &self.stream {
            stream.retain();
            return (DeadLetters::default(), Progress::Done);
        }
        let mut st = self.lock();
        let mut dead = std::mem::take(&mut st.deferred_dead);
        let progress = self.expire_head(&mut st, &mut dead, now, slice);
        (DeadLetters(dead), progress)
    }

    /// Gives back the ready FIFOs' room if the queue was empty and took
    /// no message since the last call: the sweep's, every
    /// `SWEEP_PERIOD` (a drained burst otherwise kept room for up to
    /// 1,024 messages, 40 KiB, in every queue that had one).
    pub fn release_idle_room(&self) {
        if self.stream.is_none() {
            self.lock().ready.release_idle_room();
        }
    }

    /// Whether x-expires has run out by `now`: unused (no consumers, no
    /// get, no redeclare, no join pending) for longer than it allows. If
    /// so the queue is marked as going under the same hold of its lock, so
    /// no member can join it between this decision and its deletion, which
    /// the caller then does (a member finding it going declares it anew).
    pub fn take_expired(&self, now: Instant) -> bool {
        let st = &mut *self.lock();
        let Some(expires) = st.effective.expires else {
            return false;
        };
        #[cfg(feature = "mqtt")]
        if st.joining > 0 {
            return false;
        }
        if st.going {
            return false;
        }
        let expired = st.consumers.is_empty()
            && st.last_used.is_some_and(|at| {
                now.saturating_duration_since(at) >= Duration::from_millis(expires)
            });
        st.going |= expired;
        expired
    }
}

/// A dispatch that found a consumer's writer full leaves the queue waiting
/// in that outbox ([`wait_for_room`](crate::outbox::Outbox::wait_for_room)); once the writer has drained,
/// the queue dispatches again. The writer cannot route dead letters: those
/// this dispatch finds (messages that expired at the head) wait in the
/// queue for the vhost's next sweep ([`Queue::expire_at`]).
impl WaitsForRoom for Queue {
    fn room_again(self: Arc<Self>) {
        if self.stream.is_some() {
            return self.stream_dispatch();
        }
        let mut dead = Vec::new();
        let mut st = self.lock();
        self.dispatch_locked(&mut st, &mut dead, Instant::now());
        st.deferred_dead.append(&mut dead);
    }
}

/// The ready part of a queue, read under its lock.
#[derive(Debug, Clone, Copy)]
pub(crate) struct QueueDepth {
    pub ready: u64,
    /// Read under the same hold of the queue's lock as `ready`: a requeue
    /// moves a message from one to the other under it, so their sum never
    /// dips while messages come back.
    pub unacked: u64,
    pub ready_bytes: u64,
    /// Persistent messages, ready and unacked (none in a stream).
    pub persistent: u64,
    /// Body bytes of the unacked messages.
    pub unacked_bytes: u64,
    pub consumers: u64,
}

/// Reading a queue's state for listings (`inspect`).
impl Queue {
    /// Ready messages, their body bytes, and consumers, read under the lock.
    pub(crate) fn depth(&self) -> QueueDepth {
        if let Some(stream) = &self.stream {
            return QueueDepth {
                ready: stream.len(),
                unacked: self.stats.unacked.get(),
                ready_bytes: stream.bytes(),
                persistent: 0,
                unacked_bytes: self.stats.unacked_bytes.get(),
                consumers: stream.reader_count() as u64,
            };
        }
        let st = self.lock();
        QueueDepth {
            ready: st.ready.len() as u64,
            unacked: self.stats.unacked.get(),
            ready_bytes: st.ready.bytes() as u64,
            persistent: st.ready.persistent() as u64 + self.stats.unacked_persistent.get(),
            unacked_bytes: self.stats.unacked_bytes.get(),
            consumers: st.consumers.len() as u64,
        }
    }

    /// The `timestamp` property of the message at the head, if it has
    /// one (none for a stream).
    pub(crate) fn head_timestamp(&self) -> Option<u64> {
        if self.stream.is_some() {
            return None;
        }
        let properties = self.lock().ready.front()?.message.properties.clone();
        leveret_protocol::BasicProperties::decode(&properties)
            .ok()?
            .timestamp
    }

    /// The consumers now, in registration order, each with whether it is
    /// active (see [`Consumers::snapshot`]).
    pub(crate) fn consumers_snapshot(&self) -> Vec<(Arc<Consumer>, bool)> {
        if let Some(stream) = &self.stream {
            return stream.consumers().into_iter().map(|c| (c, true)).collect();
        }
        self.lock().consumers.snapshot()
    }
}

#[cfg(test)]
mod tests;
