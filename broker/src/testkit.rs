//! A harness for unit tests of the core without sockets, in the spirit of
//! raft-rs's: a [`Harness`] is a vhost (optionally with a persister over a
//! [`MemoryStore`]) driven by direct calls, and a [`FakeChannel`] stands
//! where a client's channel would be: it consumes, gets, acks and rejects
//! through the same `Queue` operations the real channel uses, and its
//! outbox is read back as a list of [`Delivered`] items instead of frames
//! on a socket. Time is passed in (`expire_at`, `sweep_at`) rather than
//! waited for.

use crate::alarm::memory::MemoryGauge;
use crate::exchange::{ExchangeKind, ExchangeOptions};
use crate::message::Message;
use crate::outbox::{Outbound, Outbox};
use crate::queue::{ChannelLink, Consumer, DeadLetters, Enqueued, Queue, QueueOptions};
use crate::store::{
    KvOp, KvPair, MemoryStore, Persistence, Recovered, Store, StoreError, WriteMode,
};
use crate::vhost::{BindingChange, ExchangeDeclaration, QueueDeclaration, Vhost};
use bytes::{Bytes, BytesMut};
use leveret_protocol::{BasicProperties, FieldTable, FieldValue, ShortStr};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;

/// A short string from a literal.
pub fn s(text: &str) -> ShortStr {
    ShortStr::try_from(text).expect("a short string")
}

/// A field table from pairs.
pub fn table(pairs: &[(&str, FieldValue)]) -> FieldTable {
    pairs
        .iter()
        .map(|(key, value)| (s(key), value.clone()))
        .collect()
}

/// A vhost driven directly.
pub struct Harness {
    /// The vhost under test.
    pub vhost: Arc<Vhost>,
    /// Its persister, if it has a store.
    pub persistence: Option<Arc<Persistence>>,
    /// The store under the persister, if any.
    store: Option<Arc<dyn Store>>,
    next_connection: AtomicU64,
}

impl Harness {
    /// A vhost `/` without storage.
    pub fn new() -> Self {
        Self::build(None)
    }

    /// A vhost `/` whose durable queues persist into a [`MemoryStore`].
    pub fn durable() -> Self {
        Self::durable_over(Arc::new(MemoryStore::default()))
    }

    /// A vhost `/` whose durable queues persist into `store`.
    pub fn durable_over(store: Arc<dyn Store>) -> Self {
        let persistence = Persistence::start(Arc::clone(&store), &Recovered::default())
            .expect("the persister starts");
        Self::build(Some((persistence, store)))
    }

    fn build(storage: Option<(Arc<Persistence>, Arc<dyn Store>)>) -> Self {
        let gauge = Arc::new(MemoryGauge::new(usize::MAX));
        let (persistence, store) = storage.unzip();
        Harness {
            vhost: Vhost::new(s("/"), gauge, persistence.clone(), Default::default()),
            persistence,
            store,
            next_connection: AtomicU64::new(1),
        }
    }

    /// What a restart would recover from the store now (empty without one).
    pub fn stored(&self) -> Recovered {
        self.store
            .as_ref()
            .map_or_else(Recovered::default, |store| {
                Recovered::from_scan(store.scan().expect("the store scans"))
                    .expect("the store decodes")
            })
    }

    /// Declares a non-durable queue with `arguments`.
    pub fn queue(&self, name: &str, arguments: &[(&str, FieldValue)]) -> Arc<Queue> {
        self.declare_queue(name, false, arguments)
    }

    /// Declares a queue.
    pub fn declare_queue(
        &self,
        name: &str,
        durable: bool,
        arguments: &[(&str, FieldValue)],
    ) -> Arc<Queue> {
        let declaration = QueueDeclaration {
            name: s(name),
            passive: false,
            server_named: false,
            max_queues: None,
            options: QueueOptions {
                durable,
                exclusive_owner: None,
                auto_delete: false,
                arguments: table(arguments),
            },
        };
        let (queue, _) = self
            .vhost
            .declare_queue(declaration, 0)
            .expect("queue.declare");
        queue
    }

    /// Declares a non-durable exchange.
    pub fn exchange(&self, name: &str, kind: ExchangeKind) {
        self.vhost
            .declare_exchange(ExchangeDeclaration {
                name: s(name),
                kind: s(kind.name()),
                passive: false,
                options: ExchangeOptions::default(),
            })
            .expect("exchange.declare");
    }

    /// Binds `queue` to `exchange` with `key`.
    pub fn bind(&self, queue: &Arc<Queue>, exchange: &str, key: &str) {
        self.vhost
            .bind_queue(
                queue,
                &s(exchange),
                s(key),
                FieldTable::new(),
                BindingChange::Bind,
            )
            .expect("queue.bind");
    }

    /// Publishes a transient message with no properties.
    pub fn publish(&self, exchange: &str, key: &str, body: &str) -> Vec<Enqueued> {
        self.publish_with(exchange, key, body, BasicProperties::default())
    }

    /// Publishes a message as a channel would: routes it, offers it to
    /// every queue it reaches, routes the dead letters that causes.
    /// Returns each queue's answer.
    pub fn publish_with(
        &self,
        exchange: &str,
        key: &str,
        body: &str,
        properties: BasicProperties,
    ) -> Vec<Enqueued> {
        let exchange = self.vhost.exchange_or_404(&s(exchange)).expect("exchange");
        let mut queues = Vec::new();
        self.vhost.route(
            &exchange,
            &s(key),
            properties.headers.as_ref(),
            &mut queues,
            &mut None,
        );
        let message = message(&exchange.name, key, body, &properties);
        let mut dead = DeadLetters::default();
        let mut answers = Vec::new();
        for queue in queues {
            let (enqueued, dead_here) = queue.publish(Arc::clone(&message));
            answers.push(enqueued);
            dead.append(dead_here);
        }
        self.vhost.dead_letter(dead);
        answers
    }

    /// The vhost's sweep as of `now` (message TTLs, x-expires).
    #[cfg(test)]
    pub fn sweep_at(&self, now: std::time::Instant) {
        self.vhost.sweep_at(now);
    }

    /// A channel on a new connection.
    pub fn channel(&self) -> FakeChannel {
        let connection = self.next_connection.fetch_add(1, Ordering::Relaxed);
        let (outbox, inbox) = Outbox::new(connection);
        FakeChannel {
            link: Arc::new(ChannelLink::new(1, outbox)),
            inbox,
            vhost: Arc::clone(&self.vhost),
        }
    }
}

/// A message as a publisher would send it.
pub fn message(
    exchange: &ShortStr,
    key: &str,
    body: &str,
    properties: &BasicProperties,
) -> Arc<Message> {
    let mut encoded = BytesMut::new();
    properties.encode(&mut encoded);
    Arc::new(Message {
        exchange: exchange.clone(),
        routing_key: s(key),
        properties: encoded.freeze(),
        body: Bytes::copy_from_slice(body.as_bytes()),
        persistent: properties.is_persistent(),
        priority: properties.priority.unwrap_or(0),
        ttl_ms: properties
            .expiration
            .as_ref()
            .and_then(|e| e.as_str())
            .and_then(|e| e.parse().ok()),
        stored: None,
    })
}

/// What a [`FakeChannel`]'s outbox received, decoded.
#[derive(Debug, Clone, PartialEq)]
pub struct Delivered {
    /// The delivery tag.
    pub tag: u64,
    /// The consumer tag (empty for basic.get).
    pub consumer: String,
    /// The body.
    pub body: String,
    /// Delivered before.
    pub redelivered: bool,
    /// The properties' headers.
    pub headers: Option<FieldTable>,
}

impl Delivered {
    /// Its `x-death` entries as (queue, reason, count), newest first.
    pub fn deaths(&self) -> Vec<(String, String, i64)> {
        let Some(FieldValue::Array(entries)) = self.headers.as_ref().and_then(|h| h.get("x-death"))
        else {
            return Vec::new();
        };
        entries
            .iter()
            .map(|entry| {
                let FieldValue::Table(death) = entry else {
                    panic!("x-death entries are tables, got {entry:?}");
                };
                let text = |key: &str| {
                    let bytes = death.get(key).and_then(FieldValue::as_bytes);
                    String::from_utf8_lossy(bytes.unwrap_or_default()).into_owned()
                };
                let count = death.get("count").and_then(FieldValue::as_i64);
                (text("queue"), text("reason"), count.unwrap_or(0))
            })
            .collect()
    }

    /// A header's text value.
    pub fn header_text(&self, key: &str) -> Option<String> {
        let value = self.headers.as_ref()?.get(key)?.as_bytes()?;
        Some(String::from_utf8_lossy(value).into_owned())
    }
}

/// An `x-death` entry as [`Delivered::deaths`] lists it.
pub fn death(queue: &str, reason: &str, count: i64) -> (String, String, i64) {
    (queue.to_owned(), reason.to_owned(), count)
}

/// Options of [`FakeChannel::consume`].
#[derive(Debug, Clone, Copy, Default)]
pub struct Consume {
    /// No acks.
    pub no_ack: bool,
    /// Per-consumer prefetch (0 = none).
    pub prefetch: u32,
}

/// A client's channel, without a client: consumers and acks on a
/// [`ChannelLink`] whose outbox the test reads.
pub struct FakeChannel {
    /// The link queues deliver through.
    pub link: Arc<ChannelLink>,
    inbox: leveret_protocol::handoff::Receiver<Outbound>,
    vhost: Arc<Vhost>,
}

impl FakeChannel {
    /// basic.consume with `tag` on `queue`, active at once.
    pub fn consume(&self, queue: &Arc<Queue>, tag: &str, options: Consume) -> Arc<Consumer> {
        let consumer = Arc::new(Consumer {
            tag: s(tag),
            channel: Arc::clone(&self.link),
            no_ack: options.no_ack,
            exclusive: false,
            prefetch: options.prefetch,
            priority: 0,
            wants_position: false,
            in_flight: Default::default(),
            active: Default::default(),
        });
        let dead = queue
            .add_consumer(Arc::clone(&consumer))
            .expect("basic.consume");
        self.vhost.dead_letter(dead);
        consumer.activate();
        self.vhost.dead_letter(queue.dispatch());
        consumer
    }

    /// basic.get; the get-ok is in the outbox ([`FakeChannel::drain`]).
    pub fn get(&self, queue: &Arc<Queue>, no_ack: bool) -> bool {
        let permit = self.link.outbox.try_reserve().expect("room in the outbox");
        let (delivered, dead) = queue.get(&self.link, no_ack, permit);
        self.vhost.dead_letter(dead);
        delivered
    }

    /// Everything the outbox holds, in order (then lets queues that were
    /// waiting for room dispatch again, as a writer does after draining).
    pub fn drain(&mut self) -> Vec<Delivered> {
        let mut out = Vec::new();
        while let Some(item) = self.inbox.try_recv() {
            match item {
                Outbound::Deliver {
                    consumer_tag,
                    delivery_tag,
                    redelivered,
                    message,
                    ..
                } => out.push(decode(
                    delivery_tag,
                    consumer_tag.as_str().unwrap_or_default(),
                    redelivered,
                    &message,
                )),
                Outbound::GetOk {
                    delivery_tag,
                    redelivered,
                    message,
                    ..
                } => out.push(decode(delivery_tag, "", redelivered, &message)),
                other => panic!("expected deliveries only, got {other:?}"),
            }
        }
        self.link.outbox.wake_blocked();
        out
    }

    /// Drops everything the outbox holds and counts it (for benches,
    /// which need the room back but not the deliveries decoded).
    #[cfg(feature = "bench-internals")]
    pub fn discard(&mut self) -> usize {
        let mut count = 0;
        while self.inbox.try_recv().is_some() {
            count += 1;
        }
        self.link.outbox.wake_blocked();
        count
    }

    /// basic.ack.
    pub fn ack(&self, tag: u64, multiple: bool) {
        self.settle(tag, multiple, |queue, message| {
            queue.settle(std::slice::from_ref(message));
            DeadLetters::default()
        });
    }

    /// basic.nack with `requeue`.
    pub fn nack(&self, tag: u64, multiple: bool, requeue: bool) {
        self.settle(tag, multiple, |queue, message| {
            if requeue {
                queue.requeue(vec![message.clone()])
            } else {
                queue.reject(message.clone())
            }
        });
    }

    fn settle(
        &self,
        tag: u64,
        multiple: bool,
        how: impl Fn(&Arc<Queue>, &crate::queue::QueuedMessage) -> DeadLetters,
    ) {
        let settled = self
            .link
            .deliveries()
            .take(tag, multiple)
            .expect("a known delivery tag");
        let mut dead = DeadLetters::default();
        for unacked in settled {
            if let Some(consumer) = &unacked.consumer {
                consumer.settled_one();
            }
            let origin = &unacked.origin;
            dead.append(how(&origin.queue, &origin.message));
            dead.append(origin.queue.dispatch());
        }
        self.vhost.dead_letter(dead);
    }
}

fn decode(tag: u64, consumer: &str, redelivered: bool, message: &Message) -> Delivered {
    let properties = BasicProperties::decode(&message.properties).expect("properties");
    Delivered {
        tag,
        consumer: consumer.to_owned(),
        body: String::from_utf8(message.body.to_vec()).expect("utf-8 body"),
        redelivered,
        headers: properties.headers,
    }
}

/// A store whose writes wait while it is held ([`Gated::hold`]), and fail
/// while `failing` is set: a test decides when the disk answers.
#[derive(Debug, Default)]
pub struct Gated {
    inner: MemoryStore,
    held: std::sync::Mutex<bool>,
    opened: std::sync::Condvar,
    /// Writes fail while set.
    pub failing: std::sync::atomic::AtomicBool,
}

impl Gated {
    /// Holds (true) or releases (false) the writes.
    pub fn hold(&self, held: bool) {
        *self.held.lock().unwrap() = held;
        self.opened.notify_all();
    }
}

impl Store for Gated {
    fn write(&self, ops: Vec<KvOp>, mode: WriteMode) -> Result<(), StoreError> {
        let held = self.held.lock().unwrap();
        drop(self.opened.wait_while(held, |held| *held).unwrap());
        if self.failing.load(Ordering::SeqCst) {
            return Err(StoreError::Engine("simulated failure".into()));
        }
        self.inner.write(ops, mode)
    }
    fn flush(&self) -> Result<(), StoreError> {
        self.inner.flush()
    }
    fn scan(&self) -> Result<Vec<KvPair>, StoreError> {
        self.inner.scan()
    }
}

/// A [`MemoryStore`] that also lists the writes it is asked for, in order:
/// each operation's key, and whether it puts a value (or deletes one).
#[derive(Debug, Default)]
pub struct RecordingStore {
    inner: MemoryStore,
    written: std::sync::Mutex<Vec<(Vec<u8>, bool)>>,
}

impl RecordingStore {
    /// The writes so far: `(key, puts a value)`, in order.
    pub fn written(&self) -> Vec<(Vec<u8>, bool)> {
        self.written.lock().unwrap().clone()
    }
}

impl Store for RecordingStore {
    fn write(&self, ops: Vec<KvOp>, mode: WriteMode) -> Result<(), StoreError> {
        let listed = ops
            .iter()
            .map(|(key, value)| (key.clone(), value.is_some()));
        self.written.lock().unwrap().extend(listed);
        self.inner.write(ops, mode)
    }
    fn flush(&self) -> Result<(), StoreError> {
        self.inner.flush()
    }
    fn scan(&self) -> Result<Vec<KvPair>, StoreError> {
        self.inner.scan()
    }
}
