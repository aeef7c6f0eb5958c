//! [`InPort`]: receives typed values into a bounded buffer.
//!
//! The port consumes the profile's queue with acknowledgements and a
//! prefetch limit. Each message's sender and sequence number are checked
//! (dropping duplicates, counting gaps and late arrivals), it is decoded,
//! the registered callbacks run, it goes into the buffer according to the
//! [`FullPolicy`], and only then is it acknowledged. That intake runs on
//! the connection's reader, as each message is read (the consumer's sink):
//! no task stands between the connection and the buffer; in process, on
//! the embedded broker's thread that dispatches the message (an in-process
//! out-port's putting thread, when its publish took the fast path),
//! whenever the reader has nothing before it (the client's inline
//! deliveries). A message the
//! reader cannot take at once (the buffer is full and the policy is to
//! wait, or there is no room for its ack in the connection's outbox) goes
//! through the consumer's buffer to the port's task, which waits for room;
//! until the task has taken it, the messages after it follow the same way,
//! so none overtakes another.
//!
//! The port's task owns the connection: when the link drops it reconnects
//! with backoff, declares the topology again and consumes anew; messages
//! redelivered after the reconnection are recognised by their sequence
//! number and dropped, so the reader sees every message once and in order.
//!
//! The buffer is read three ways: [`InPort::read`] (the newest value,
//! skipping older ones, as a control loop wants), [`InPort::recv`] or the
//! [`futures_core::Stream`] (every value in order), and
//! [`InPort::on_receive`] callbacks.
//!
//! Uses the client's consumers (with a `DeliverySink`), the link and
//! announcement helpers of this module's siblings, and the profile.

use super::announce::{self, Announcer};
use super::cdr::CdrOptions;
use super::data::{DataError, PortData};
use super::latency::LatencyStats;
use super::link::{self, Link, LinkStatus, Stamp};
use super::openrtm::PortRole;
use super::profile::{Connector, FullPolicy, PortProfile};
use super::spin::AdaptiveSpin;
use leveret_client::DeliverySink;
use leveret_client::{
    BasicConsumeOptions, BasicQosOptions, Channel, Connection, Consumer, ConsumerEnd, Delivery,
    FieldTable, QueueDeleteOptions, ShortStr,
};
use leveret_client::{Error, Result};
use std::collections::{BTreeSet, HashMap, VecDeque};
use std::pin::Pin;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Condvar, Mutex, MutexGuard};
use std::task::{Context, Poll, Waker};
use std::time::{Duration, SystemTime, UNIX_EPOCH};
use tokio::sync::{watch, Notify};
use tokio::task::JoinHandle;

/// How long closing a port waits for the broker's close-ok.
const CLOSE_TIMEOUT: Duration = Duration::from_secs(5);

/// Missing sequence numbers remembered per sender, to recognise late
/// arrivals; older gaps are only counted.
const MAX_REMEMBERED_GAPS: usize = 4096;

/// A received value with what its headers said.
#[derive(Debug, Clone, PartialEq)]
pub struct Sample<T> {
    /// The value.
    pub value: T,
    /// The sender's sequence number (`x-seq`), if it sent one.
    pub seq: Option<u64>,
    /// When it was put (`x-sent-ns`), if the sender said.
    pub sent_at: Option<SystemTime>,
    /// From put to the moment the application took it (`recv`, `read`,
    /// `try_recv`, `recv_blocking`, the stream), by the two hosts'
    /// clocks; `None` in the callbacks, which run before that.
    pub latency: Option<Duration>,
    /// The broker delivered it before (to this port, before a reconnection).
    pub redelivered: bool,
}

/// An in-port's counters: the paper's reliability figures and what
/// became of each message. Every distinct message that arrives has one
/// fate, so `arrived == received + buffered + stale + decode_errors +
/// dropped + skipped` at every moment (an invariant the tests check).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct InPortStats {
    /// Distinct messages the broker delivered (duplicates excluded).
    pub arrived: u64,
    /// Values handed to the application: taken by `recv`, `try_recv`,
    /// `recv_blocking`, `read` or the stream.
    pub received: u64,
    /// Values waiting in the buffer now.
    pub buffered: u64,
    /// Values older than the profile's lifespan on arrival (by their
    /// `x-sent-ns`), dropped.
    pub stale: u64,
    /// Messages whose body did not decode (acknowledged and dropped).
    pub decode_errors: u64,
    /// Values the buffer's full policy discarded.
    pub dropped: u64,
    /// Values passed over by [`InPort::read`] for a newer one.
    pub skipped: u64,
    /// Messages received again (redelivered or resent) and dropped; not
    /// counted as arrived.
    pub duplicates: u64,
    /// Arrived messages that came after a later one of the same sender.
    pub out_of_order: u64,
    /// Messages missing: gaps in a sender's sequence not (yet) filled.
    pub lost: u64,
    /// Latency from put to the application taking the value.
    pub latency: LatencyStats,
}

/// One sender's sequence.
#[derive(Debug, Default)]
struct Sequence {
    last: u64,
    missing: BTreeSet<u64>,
}

/// Where a sequence number falls.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Verdict {
    /// Next or later (`gap` numbers skipped).
    New { gap: u64 },
    /// Fills an earlier gap.
    Late,
    /// Seen before.
    Duplicate,
}

impl Sequence {
    /// A sender's first message sets where its sequence starts: what it
    /// sent before this port existed was not meant for it.
    fn starting_at(seq: u64) -> Self {
        Sequence {
            last: seq.saturating_sub(1),
            missing: BTreeSet::new(),
        }
    }

    fn observe(&mut self, seq: u64) -> Verdict {
        if seq > self.last {
            let gap = seq - self.last - 1;
            for missing in (self.last + 1)..seq {
                if self.missing.len() >= MAX_REMEMBERED_GAPS {
                    break;
                }
                self.missing.insert(missing);
            }
            self.last = seq;
            Verdict::New { gap }
        } else if self.missing.remove(&seq) {
            Verdict::Late
        } else {
            Verdict::Duplicate
        }
    }
}

type Callback<T> = Box<dyn FnMut(&Sample<T>) + Send>;

struct Buffer<T> {
    queue: VecDeque<Sample<T>>,
    waker: Option<Waker>,
    /// Threads waiting in `recv_blocking`: the condition variable is
    /// signalled only for them (a signal costs a system call even when
    /// nobody waits).
    blocked_readers: usize,
    closed: bool,
}

/// The intake's state: what it knows of the senders, and the deliveries
/// handed to the port's task.
#[derive(Default)]
struct Receiving {
    senders: HashMap<String, Sequence>,
    /// Deliveries of the current link given back to go through the port's
    /// task and not yet taken by it: while any is, the intake gives back
    /// every later one too.
    deferred: usize,
    /// Counts the links consumed: deliveries of an earlier one are left
    /// unacknowledged (its channel is gone; the broker redelivers them).
    generation: u64,
}

/// What a delivery's checks made of it.
enum Checked<T> {
    /// Counted and done with (a duplicate, stale, undecodable).
    Settled,
    /// A value for the buffer; the counters take it once it is there.
    Value(Sample<T>, Count),
}

/// What a message's arrival adds to the counters, counted together with
/// its fate.
#[derive(Clone, Copy)]
struct Count {
    verdict: Option<Verdict>,
}

impl Count {
    fn arrived(self, stats: &mut InPortStats) {
        stats.arrived += 1;
        match self.verdict {
            Some(Verdict::New { gap }) => stats.lost += gap,
            Some(Verdict::Late) => {
                stats.lost = stats.lost.saturating_sub(1);
                stats.out_of_order += 1;
            }
            _ => {}
        }
    }
}

/// What the port, its task and the intake share.
struct Shared<T> {
    profile: Arc<PortProfile>,
    receiving: Mutex<Receiving>,
    buffer: Mutex<Buffer<T>>,
    /// Signalled with the buffer's lock when a value arrives or the port
    /// closes, for [`InPort::recv_blocking`].
    arrived: Condvar,
    /// Counts the values buffered and the port's closing: what a spinning
    /// [`InPort::recv_blocking`] watches without taking the buffer's lock.
    arrivals: AtomicU64,
    /// Signalled when the reader makes room.
    room: Notify,
    stats: watch::Sender<InPortStats>,
    callbacks: Mutex<Vec<Callback<T>>>,
    link: Link,
    queue: Mutex<ShortStr>,
    /// Set when the port closes: the task stops, the intake takes no more.
    stop: watch::Sender<bool>,
}

impl<T: PortData> Shared<T> {
    fn new(profile: PortProfile, queue: &QueueName) -> Arc<Self> {
        Arc::new(Shared {
            profile: Arc::new(profile),
            receiving: Mutex::new(Receiving::default()),
            arrived: Condvar::new(),
            arrivals: AtomicU64::new(0),
            buffer: Mutex::new(Buffer {
                queue: VecDeque::new(),
                waker: None,
                blocked_readers: 0,
                closed: false,
            }),
            room: Notify::new(),
            stats: watch::Sender::new(InPortStats::default()),
            callbacks: Mutex::new(Vec::new()),
            link: Link::new(),
            queue: Mutex::new(ShortStr::try_from(queue.name.as_str()).unwrap_or_default()),
            stop: watch::Sender::new(false),
        })
    }

    /// Checks a delivery's sender and sequence number, age and body, and
    /// runs the callbacks for a value. Called with the intake's state, so
    /// deliveries are checked one at a time, in order.
    fn check(&self, senders: &mut HashMap<String, Sequence>, delivery: &Delivery) -> Checked<T> {
        let stamp = Stamp::read(delivery.properties.headers.as_ref());
        let verdict = match (&stamp.port, stamp.seq) {
            (Some(port), Some(seq)) => Some(match senders.get_mut(port.as_str()) {
                Some(sequence) => sequence.observe(seq),
                None => senders
                    .entry(port.clone())
                    .or_insert_with(|| Sequence::starting_at(seq))
                    .observe(seq),
            }),
            _ => None,
        };
        if verdict == Some(Verdict::Duplicate) {
            self.stats.send_modify(|s| s.duplicates += 1);
            return Checked::Settled;
        }
        let count = Count { verdict };
        if let (Some(lifespan), Some(age)) = (self.profile.lifespan, stamp.sent_ns.and_then(age)) {
            if age > lifespan {
                self.stats.send_modify(|s| {
                    count.arrived(s);
                    s.stale += 1;
                });
                return Checked::Settled;
            }
        }
        let value = match decode::<T>(delivery, self.profile.cdr) {
            Ok(value) => value,
            Err(error) => {
                tracing::warn!(%error, "in-port dropped a message that does not decode");
                self.stats.send_modify(|s| {
                    count.arrived(s);
                    s.decode_errors += 1;
                });
                return Checked::Settled;
            }
        };
        let sample = Sample {
            value,
            seq: stamp.seq,
            sent_at: stamp
                .sent_ns
                .and_then(|ns| u64::try_from(ns).ok())
                .map(|ns| UNIX_EPOCH + Duration::from_nanos(ns)),
            latency: None,
            redelivered: delivery.redelivered,
        };
        for callback in lock(&self.callbacks).iter_mut() {
            callback(&sample);
        }
        Checked::Value(sample, count)
    }

    /// Whether the buffer has room for another value.
    fn has_room(&self) -> bool {
        lock(&self.buffer).queue.len() < self.profile.buffer_size.max(1)
    }

    /// Puts a value in the buffer and counts it. A full buffer drops one
    /// by the full policy; with [`FullPolicy::BlockBroker`] the caller has
    /// made sure there is room (only the intake, one delivery at a time,
    /// adds values). The counters change under the buffer's lock, as
    /// they do when a value is taken, so they always add up.
    fn store(&self, sample: Sample<T>, count: Count) {
        let capacity = self.profile.buffer_size.max(1);
        let mut buffer = lock(&self.buffer);
        if buffer.queue.len() >= capacity {
            match self.profile.full_policy {
                FullPolicy::BlockBroker => {}
                FullPolicy::DropOldest => {
                    buffer.queue.pop_front();
                    self.stats.send_modify(|s| {
                        s.dropped += 1;
                        s.buffered -= 1;
                    });
                }
                FullPolicy::DropNewest => {
                    self.stats.send_modify(|s| {
                        count.arrived(s);
                        s.dropped += 1;
                    });
                    return;
                }
            }
        }
        buffer.queue.push_back(sample);
        self.stats.send_modify(|s| {
            count.arrived(s);
            s.buffered += 1;
        });
        self.arrivals.fetch_add(1, Ordering::Release);
        let waker = buffer.waker.take();
        let blocked = buffer.blocked_readers > 0;
        // Woken after the lock is let go, so the reader woken does not
        // find it still held.
        drop(buffer);
        if let Some(waker) = waker {
            waker.wake();
        }
        if blocked {
            self.arrived.notify_one();
        }
    }

    /// Takes the oldest buffered value for the application, counting it
    /// received (with its latency, measured now), under the buffer's lock.
    fn hand_over(&self, buffer: &mut Buffer<T>) -> Option<Sample<T>> {
        let mut sample = buffer.queue.pop_front()?;
        self.received(&mut sample, 0);
        Some(sample)
    }

    /// Counts `sample` handed to the application, `skipped` older ones
    /// passed over for it; call it with the buffer's lock held.
    fn received(&self, sample: &mut Sample<T>, skipped: u64) {
        sample.latency = sample
            .sent_at
            .and_then(|sent| SystemTime::now().duration_since(sent).ok());
        self.stats.send_modify(|s| {
            s.received += 1;
            s.skipped += skipped;
            s.buffered -= 1 + skipped;
            if let Some(latency) = sample.latency {
                s.latency.record(latency);
            }
        });
    }
}

/// The intake on the connection's reader: takes one link's deliveries as
/// they are read (see the module's docs).
struct Intake<T> {
    shared: Arc<Shared<T>>,
    generation: u64,
}

impl<T: PortData> DeliverySink for Intake<T> {
    fn take(&self, delivery: &Delivery) -> bool {
        let shared = &self.shared;
        let mut receiving = lock(&shared.receiving);
        if receiving.generation != self.generation || *shared.stop.borrow() {
            // A link the port has left, or a port closing: unacknowledged,
            // the delivery goes back to its queue when its channel closes.
            return true;
        }
        if receiving.deferred == 0 && self.take_now(&mut receiving, delivery) {
            return true;
        }
        receiving.deferred += 1;
        false
    }

    /// Inline only while no `on_receive` callback is registered: the
    /// intake's own work is a few locks of the port's and a wake, but a
    /// callback is the application's code, which could call into the
    /// broker and wait on the queue whose lock the dispatching thread
    /// holds. A callback registered while a delivery is being offered
    /// runs on that delivery inline once.
    fn runs_inline(&self) -> bool {
        lock(&self.shared.callbacks).is_empty()
    }
}

impl<T: PortData> Intake<T> {
    /// Takes a delivery if there is room for its value (where the policy
    /// is to wait for it) and for its ack; false if the task must wait for
    /// them.
    fn take_now(&self, receiving: &mut Receiving, delivery: &Delivery) -> bool {
        let shared = &self.shared;
        if shared.profile.full_policy == FullPolicy::BlockBroker && !shared.has_room() {
            return false;
        }
        let slot = match delivery.try_reserve_ack() {
            Ok(Some(slot)) => slot,
            Ok(None) => return false,
            // The connection is closing: the consumer ends with it.
            Err(_) => return true,
        };
        if let Checked::Value(sample, count) = shared.check(&mut receiving.senders, delivery) {
            shared.store(sample, count);
        }
        // A failed ack means a closing channel: the task sees the consumer
        // end.
        let _ = delivery.ack_in(slot);
        true
    }
}

fn lock<T>(mutex: &Mutex<T>) -> MutexGuard<'_, T> {
    mutex.lock().unwrap_or_else(|e| e.into_inner())
}

/// What a look at the buffer found.
enum Taken<T> {
    Sample(Sample<T>),
    Closed,
    Empty,
}

/// A typed receiver with a bounded buffer, reconnection and duplicate
/// suppression. Implements [`futures_core::Stream`] of [`Sample`]s.
pub struct InPort<T> {
    shared: Arc<Shared<T>>,
    /// The profile's busy-poll window.
    busy_poll: Option<Duration>,
    /// How long `recv_blocking` spins before sleeping, without a busy-poll
    /// window, if the profile asks for a spin.
    spin: Option<AdaptiveSpin>,
    task: Option<JoinHandle<()>>,
}

impl<T> std::fmt::Debug for InPort<T> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("InPort")
            .field("queue", &*lock(&self.shared.queue))
            .field("stats", &*self.shared.stats.borrow())
            .finish_non_exhaustive()
    }
}

impl<T: PortData> InPort<T> {
    /// Connects over TCP to the profile's broker, declares its topology
    /// and starts consuming; fails if this first attempt does.
    pub async fn connect(profile: PortProfile) -> Result<Self> {
        InPort::connect_with(Connector::from(&profile), profile).await
    }

    /// [`InPort::connect`] through `connector`.
    pub async fn connect_with(connector: Connector, profile: PortProfile) -> Result<Self> {
        let connector = connector.naming(announce::connection_name(PortRole::InPort, &profile));
        let queue = QueueName::of(&profile);
        let shared = Shared::new(profile, &queue);
        let first = open(&connector, &shared, &queue).await?;
        *lock(&shared.queue) = first.queue.clone();
        shared.link.connected();
        Ok(InPort::spawn(connector, shared, queue, Some(first)))
    }

    /// Starts the port at once, whether or not the broker is reachable:
    /// it connects in the background, retrying with backoff (watch
    /// [`InPort::link`]). Must be called within a tokio runtime.
    pub fn start(profile: PortProfile) -> Self {
        InPort::start_with(Connector::from(&profile), profile)
    }

    /// [`InPort::start`] through `connector`.
    pub fn start_with(connector: Connector, profile: PortProfile) -> Self {
        let connector = connector.naming(announce::connection_name(PortRole::InPort, &profile));
        let queue = QueueName::of(&profile);
        let shared = Shared::new(profile, &queue);
        InPort::spawn(connector, shared, queue, None)
    }

    fn spawn(
        connector: Connector,
        shared: Arc<Shared<T>>,
        queue: QueueName,
        first: Option<InLink>,
    ) -> Self {
        let busy_poll = shared.profile.busy_poll.filter(|window| !window.is_zero());
        let spin = shared.profile.spin.and_then(AdaptiveSpin::up_to);
        let announcer = Announcer::start::<T, _>(
            PortRole::InPort,
            &shared.profile,
            &link::port_id(),
            Some(&queue.name),
            shared.stats.subscribe(),
            shared.link.subscribe(),
        );
        let task = Task {
            shared: Arc::clone(&shared),
            connector,
            queue,
            stop: shared.stop.subscribe(),
            announcer,
        };
        let task = tokio::spawn(task.run(first));
        InPort {
            shared,
            busy_poll,
            spin,
            task: Some(task),
        }
    }

    /// Takes the newest buffered value, discarding older ones (counted as
    /// `skipped`); `None` if nothing arrived since the last read.
    pub fn read(&self) -> Option<Sample<T>> {
        let newest = {
            let mut buffer = lock(&self.shared.buffer);
            let mut newest = buffer.queue.pop_back()?;
            let skipped = buffer.queue.len() as u64;
            buffer.queue.clear();
            self.shared.received(&mut newest, skipped);
            newest
        };
        self.shared.room.notify_one();
        Some(newest)
    }

    /// Whether a value is waiting.
    pub fn is_new(&self) -> bool {
        !lock(&self.shared.buffer).queue.is_empty()
    }

    /// Takes the oldest buffered value, if any.
    pub fn try_recv(&self) -> Option<Sample<T>> {
        match self.take() {
            Taken::Sample(sample) => Some(sample),
            Taken::Closed | Taken::Empty => None,
        }
    }

    /// The next value in order for a thread outside the async runtime:
    /// blocks the thread up to `timeout`; `None` if none came or the port
    /// is closed. Never call it on a runtime thread. Before the thread
    /// sleeps it spins for the profile's busy-poll window, if it has one,
    /// or else for the profile's adaptive spin, if it has one (2 µs up to
    /// its ceiling, then two yields: [`PortProfile::spin`]): a value that
    /// comes meanwhile is taken with no wake. A zero timeout looks once.
    pub fn recv_blocking(&self, timeout: Duration) -> Option<Sample<T>> {
        let start = std::time::Instant::now();
        let deadline = start + timeout;
        if let Some(window) = self.busy_poll {
            let spin_until = start + window.min(timeout);
            while std::time::Instant::now() < spin_until {
                match self.take() {
                    Taken::Sample(sample) => return Some(sample),
                    Taken::Closed => return None,
                    Taken::Empty => std::hint::spin_loop(),
                }
            }
        } else if let Some(spin) = self.spin.as_ref().filter(|_| !timeout.is_zero()) {
            // Read before the first look: whatever arrives after it
            // changes the count the spin watches.
            let mut seen = self.shared.arrivals.load(Ordering::Acquire);
            match self.take() {
                Taken::Sample(sample) => return Some(sample),
                Taken::Closed => return None,
                Taken::Empty => {}
            }
            let taken = spin.wait(deadline, || {
                let arrivals = self.shared.arrivals.load(Ordering::Acquire);
                if arrivals == seen {
                    return None;
                }
                seen = arrivals;
                match self.take() {
                    Taken::Sample(sample) => Some(Some(sample)),
                    Taken::Closed => Some(None),
                    // Another reader took it.
                    Taken::Empty => None,
                }
            });
            if let Some(taken) = taken {
                return taken;
            }
        }
        let mut buffer = lock(&self.shared.buffer);
        loop {
            if let Some(sample) = self.shared.hand_over(&mut buffer) {
                drop(buffer);
                self.shared.room.notify_one();
                return Some(sample);
            }
            let now = std::time::Instant::now();
            if buffer.closed || now >= deadline {
                return None;
            }
            buffer.blocked_readers += 1;
            buffer = self
                .shared
                .arrived
                .wait_timeout(buffer, deadline - now)
                .unwrap_or_else(|e| e.into_inner())
                .0;
            buffer.blocked_readers -= 1;
        }
    }

    /// The next value in order, waiting for one (polling first for the
    /// profile's busy-poll window, if any, yielding to the runtime's other
    /// tasks between looks); `None` once the port is closed.
    pub async fn recv(&self) -> Option<Sample<T>> {
        if let Some(window) = self.busy_poll {
            let spin_until = tokio::time::Instant::now() + window;
            while tokio::time::Instant::now() < spin_until {
                match self.take() {
                    Taken::Sample(sample) => return Some(sample),
                    Taken::Closed => return None,
                    Taken::Empty => tokio::task::yield_now().await,
                }
            }
        }
        std::future::poll_fn(|cx| self.poll_recv(cx)).await
    }

    /// The oldest buffered value, without waiting.
    fn take(&self) -> Taken<T> {
        let mut buffer = lock(&self.shared.buffer);
        match self.shared.hand_over(&mut buffer) {
            Some(sample) => {
                drop(buffer);
                self.shared.room.notify_one();
                Taken::Sample(sample)
            }
            None if buffer.closed => Taken::Closed,
            None => Taken::Empty,
        }
    }

    fn poll_recv(&self, cx: &mut Context<'_>) -> Poll<Option<Sample<T>>> {
        let mut buffer = lock(&self.shared.buffer);
        if let Some(sample) = self.shared.hand_over(&mut buffer) {
            drop(buffer);
            self.shared.room.notify_one();
            return Poll::Ready(Some(sample));
        }
        if buffer.closed {
            return Poll::Ready(None);
        }
        buffer.waker = Some(cx.waker().clone());
        Poll::Pending
    }

    /// Calls `callback` with every new value before it is buffered, on the
    /// connection's reader (or the port's task, for a value that waited
    /// for room); keep it short: the port waits for it. An in-process
    /// port with a callback takes its values through the reader, never on
    /// the embedded broker's dispatching thread, so the callback may call
    /// into the broker.
    pub fn on_receive(&self, callback: impl FnMut(&Sample<T>) + Send + 'static) {
        lock(&self.shared.callbacks).push(Box::new(callback));
    }

    /// The counters so far.
    pub fn stats(&self) -> InPortStats {
        *self.shared.stats.borrow()
    }

    /// The counters as they change (after each message is handled), to
    /// wait for a condition on them.
    pub fn watch_stats(&self) -> watch::Receiver<InPortStats> {
        self.shared.stats.subscribe()
    }

    /// The link's state, to watch for losses and reconnections.
    pub fn link(&self) -> watch::Receiver<LinkStatus> {
        self.shared.link.subscribe()
    }

    /// The queue consumed (the broker's name for a server-named one).
    pub fn queue(&self) -> ShortStr {
        lock(&self.shared.queue).clone()
    }

    /// Stops consuming and closes the connection. Values still buffered
    /// are dropped; unacknowledged deliveries go back to the queue, or,
    /// for the port's own queue (the profile named none), the queue is
    /// deleted. Dropping the port does the same without waiting.
    pub async fn close(mut self) {
        self.shared.stop.send_replace(true);
        if let Some(task) = self.task.take() {
            let _ = task.await;
        }
    }
}

impl<T: PortData> futures_core::Stream for InPort<T> {
    type Item = Sample<T>;

    fn poll_next(self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<Option<Sample<T>>> {
        self.get_mut().poll_recv(cx)
    }
}

impl<T> Drop for InPort<T> {
    fn drop(&mut self) {
        self.shared.stop.send_replace(true);
    }
}

/// A consuming connection.
struct InLink {
    connection: Connection,
    consumer: Consumer,
    queue: ShortStr,
}

/// The queue an in-port consumes.
#[derive(Debug, Clone)]
struct QueueName {
    name: String,
    /// The port's own queue (the profile names none): not exclusive, and
    /// expiring once unused.
    own: bool,
}

impl QueueName {
    fn of(profile: &PortProfile) -> Self {
        if profile.queue.is_empty() {
            QueueName {
                name: format!("leveret.port.{}", link::port_id()),
                own: true,
            }
        } else {
            QueueName {
                name: profile.queue.clone(),
                own: false,
            }
        }
    }
}

/// Connects, declares the topology and starts consuming into a new
/// intake.
async fn open<T: PortData>(
    connector: &Connector,
    shared: &Arc<Shared<T>>,
    queue: &QueueName,
) -> Result<InLink> {
    let profile = &*shared.profile;
    let setup = async {
        let connection = connector.connect().await?;
        let channel = connection.open_channel().await?;
        if profile.prefetch > 0 {
            channel
                .basic_qos(profile.prefetch, BasicQosOptions::default())
                .await?;
        }
        // As OpenRTM's module: the queue is always declared; `bind`
        // declares the exchange and binds the queue to it.
        let bind = profile.declare_queue;
        if bind {
            link::declare_exchange(&channel, profile).await?;
        }
        let queue = link::declare_queue(&channel, profile, &queue.name, queue.own, bind).await?;
        let generation = {
            let mut receiving = lock(&shared.receiving);
            receiving.generation += 1;
            receiving.deferred = 0;
            receiving.generation
        };
        let intake = Arc::new(Intake {
            shared: Arc::clone(shared),
            generation,
        });
        let consumer = channel
            .basic_consume_into(
                &queue,
                BasicConsumeOptions::default(),
                FieldTable::new(),
                intake,
            )
            .await?;
        Ok(InLink {
            connection,
            consumer,
            queue,
        })
    };
    match tokio::time::timeout(profile.broker.connection_timeout, setup).await {
        Ok(result) => result,
        Err(_) => Err(Error::ConnectTimeout),
    }
}

struct Task<T> {
    shared: Arc<Shared<T>>,
    connector: Connector,
    queue: QueueName,
    stop: watch::Receiver<bool>,
    announcer: Announcer,
}

impl<T: PortData> Task<T> {
    async fn run(mut self, first: Option<InLink>) {
        let mut link = first;
        let mut failures = 0u32;
        loop {
            if let Some(mut current) = link.take() {
                self.announcer.link_up(&current.connection);
                let error = match self.consume(&mut current).await {
                    Some(error) => error,
                    None => {
                        self.announcer.close().await;
                        // Closed on purpose: the port's own queue goes
                        // too (x-expires is for a port that vanished).
                        let own = self.queue.own;
                        let finish = async {
                            if own {
                                let channel = current.consumer.channel();
                                let options = QueueDeleteOptions::default();
                                let _ = channel.queue_delete(&current.queue, options).await;
                            }
                            current.connection.close().await
                        };
                        let _ = tokio::time::timeout(CLOSE_TIMEOUT, finish).await;
                        break;
                    }
                };
                self.shared.link.lost(&error);
                failures = 0;
                continue;
            }
            if failures > 0 {
                let delay = self.shared.profile.backoff.delay(failures - 1);
                tokio::select! {
                    _ = tokio::time::sleep(delay) => {}
                    _ = self.stop.wait_for(|s| *s) => break,
                }
            }
            let opened = tokio::select! {
                opened = open(&self.connector, &self.shared, &self.queue) => opened,
                _ = self.stop.wait_for(|s| *s) => break,
            };
            match opened {
                Ok(opened) => {
                    *lock(&self.shared.queue) = opened.queue.clone();
                    self.shared.link.connected();
                    link = Some(opened);
                }
                Err(error) => {
                    self.shared.link.failed(&error);
                    failures = failures.saturating_add(1);
                }
            }
        }
        let mut buffer = lock(&self.shared.buffer);
        buffer.closed = true;
        self.shared.arrivals.fetch_add(1, Ordering::Release);
        if let Some(waker) = buffer.waker.take() {
            waker.wake();
        }
        self.shared.arrived.notify_all();
    }

    /// Handles deliveries until the link fails (`Some(why)`) or the port
    /// is closed (`None`).
    async fn consume(&mut self, link: &mut InLink) -> Option<Error> {
        loop {
            let delivery = tokio::select! {
                biased;
                _ = self.stop.wait_for(|s| *s) => return None,
                delivery = link.consumer.next() => delivery,
            };
            let Some(delivery) = delivery else {
                return Some(match link.consumer.end_reason() {
                    Some(ConsumerEnd::ChannelClosed(error)) => error,
                    Some(ConsumerEnd::CancelledByBroker) => {
                        Error::Protocol("the broker cancelled the consumer".to_owned())
                    }
                    _ => Error::Closed,
                });
            };
            match self.handle(delivery, link.consumer.channel()).await {
                Ok(true) => {}
                Ok(false) => return None,
                Err(error) => return Some(error),
            }
        }
    }

    /// One delivery the intake gave back; `Ok(false)` if the port was
    /// closed while it waited for room.
    async fn handle(&mut self, delivery: Delivery, channel: &Channel) -> Result<bool> {
        // Room first, as the intake does: a delivery whose link fails
        // meanwhile has not been counted, and its redelivery is new.
        if self.shared.profile.full_policy == FullPolicy::BlockBroker
            && !self.wait_for_room(channel).await?
        {
            return Ok(false);
        }
        let checked = {
            let mut receiving = lock(&self.shared.receiving);
            self.shared.check(&mut receiving.senders, &delivery)
        };
        if let Checked::Value(sample, count) = checked {
            self.shared.store(sample, count);
        }
        {
            let mut receiving = lock(&self.shared.receiving);
            receiving.deferred = receiving.deferred.saturating_sub(1);
        }
        delivery.ack().await?;
        Ok(true)
    }

    /// Waits until the buffer has room; false if the port was closed
    /// meanwhile, an error if the link failed.
    async fn wait_for_room(&mut self, channel: &Channel) -> Result<bool> {
        loop {
            let room = self.shared.room.notified();
            if self.shared.has_room() {
                return Ok(true);
            }
            tokio::select! {
                _ = room => {}
                _ = self.stop.wait_for(|s| *s) => return Ok(false),
                error = channel.closed() => return Err(error),
            }
        }
    }
}

/// How long ago `sent_ns` (nanoseconds since the Unix epoch) was.
fn age(sent_ns: i64) -> Option<Duration> {
    u64::try_from(link::now_ns().saturating_sub(sent_ns))
        .ok()
        .map(Duration::from_nanos)
}

/// Decodes a delivery's body, refusing one whose `type` names another type.
pub(crate) fn decode<T: PortData>(
    delivery: &Delivery,
    options: CdrOptions,
) -> Result<T, DataError> {
    if let (Some(expected), Some(found)) = (T::TYPE_NAME, &delivery.properties.kind) {
        if found.as_bytes() != expected.as_bytes() {
            return Err(DataError::TypeMismatch {
                expected,
                found: found.to_string_lossy().into_owned(),
            });
        }
    }
    T::decode_with(delivery.body.clone(), options)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sequence_counts_gaps_late_arrivals_and_duplicates() {
        let mut seq = Sequence::starting_at(5);
        assert_eq!(seq.observe(5), Verdict::New { gap: 0 });
        assert_eq!(seq.observe(6), Verdict::New { gap: 0 });
        assert_eq!(seq.observe(9), Verdict::New { gap: 2 });
        assert_eq!(seq.observe(7), Verdict::Late);
        assert_eq!(seq.observe(7), Verdict::Duplicate);
        assert_eq!(seq.observe(9), Verdict::Duplicate);
        assert_eq!(seq.observe(4), Verdict::Duplicate);
        assert_eq!(seq.observe(8), Verdict::Late);
        assert_eq!(seq.observe(10), Verdict::New { gap: 0 });
    }
}
