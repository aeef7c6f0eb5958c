//! Durable state: what is persisted (durable exchanges, queues and bindings,
//! persistent messages in durable queues), how it is keyed, the group-commit
//! persister that batches writes from every connection into one atomic,
//! flushed batch, and recovery.
//!
//! Storage engines implement the small key-value [`Store`] trait (`sled.rs`
//! on disk, `memory.rs` for tests and transient brokers); everything about
//! keys and values lives here, once.
//!
//! Keys, in one keyspace so a batch is atomic:
//! - `e` vhost 0 name → exchange definition
//! - `q` vhost 0 name → queue definition (with the queue's numeric id)
//! - `b` vhost 0 source 0 kind destination 0 key 0 args → binding
//! - `m` message-id (8 bytes BE) → message (routing, properties, body)
//! - `i` queue-id (8 BE) seq (8 BE) → message-id (8 BE) + delivered flag
//!
//! Message bodies are stored once however many durable queues hold them;
//! the last queue to drop its copy deletes the body.

mod memory;
mod sled;

pub use self::memory::MemoryStore;
pub use self::sled::SledStore;

use bytes::{Buf, BufMut, Bytes, BytesMut};
use leveret_protocol::{FieldTable, ShortStr};
use std::collections::VecDeque;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;
use tokio::sync::{mpsc, watch};

/// A storage engine failure.
#[derive(Debug, Clone, thiserror::Error)]
#[error("storage: {0}")]
pub struct StoreError(pub String);

/// One key-value change.
pub type KvOp = (Vec<u8>, Option<Vec<u8>>);

/// One stored key and its value.
pub type KvPair = (Vec<u8>, Vec<u8>);

/// A key-value engine with atomic, durable batches.
pub trait Store: Send + Sync + std::fmt::Debug + 'static {
    /// Applies `ops` atomically and makes them durable before returning.
    fn apply(&self, ops: Vec<KvOp>) -> Result<(), StoreError>;
    /// Every key and value, in key order.
    fn scan(&self) -> Result<Vec<KvPair>, StoreError>;
}

/// A durable exchange's definition.
#[derive(Debug, Clone, PartialEq)]
pub struct ExchangeRecord {
    /// Vhost.
    pub vhost: ShortStr,
    /// Name.
    pub name: ShortStr,
    /// Kind (`direct`…).
    pub kind: ShortStr,
    /// Auto-delete.
    pub auto_delete: bool,
    /// Internal.
    pub internal: bool,
    /// Arguments.
    pub arguments: FieldTable,
}

/// A durable queue's definition.
#[derive(Debug, Clone, PartialEq)]
pub struct QueueRecord {
    /// Vhost.
    pub vhost: ShortStr,
    /// Name.
    pub name: ShortStr,
    /// Numeric id keying its messages.
    pub id: u64,
    /// Auto-delete.
    pub auto_delete: bool,
    /// Arguments.
    pub arguments: FieldTable,
}

/// A binding between durable ends.
#[derive(Debug, Clone, PartialEq)]
pub struct BindingRecord {
    /// Vhost.
    pub vhost: ShortStr,
    /// Source exchange.
    pub source: ShortStr,
    /// Destination is a queue (else an exchange).
    pub to_queue: bool,
    /// Destination name.
    pub destination: ShortStr,
    /// Binding key.
    pub routing_key: ShortStr,
    /// Arguments.
    pub arguments: FieldTable,
}

/// A persistent message as stored.
#[derive(Debug, Clone, PartialEq)]
pub struct MessageRecord {
    /// Exchange it was published to.
    pub exchange: ShortStr,
    /// Routing key.
    pub routing_key: ShortStr,
    /// Encoded properties.
    pub properties: Bytes,
    /// Body.
    pub body: Bytes,
}

/// One change to durable state.
#[derive(Debug, Clone)]
pub enum StoreOp {
    /// Declare (or redeclare) a durable exchange.
    PutExchange(ExchangeRecord),
    /// Delete a durable exchange.
    DeleteExchange {
        /// Vhost.
        vhost: ShortStr,
        /// Name.
        name: ShortStr,
    },
    /// Declare a durable queue.
    PutQueue(QueueRecord),
    /// Delete a durable queue (its messages are deleted with their own ops).
    DeleteQueue {
        /// Vhost.
        vhost: ShortStr,
        /// Name.
        name: ShortStr,
    },
    /// Add a binding.
    PutBinding(BindingRecord),
    /// Remove a binding.
    DeleteBinding(BindingRecord),
    /// Store a message body once.
    PutMessage {
        /// Message id.
        id: u64,
        /// The message.
        record: MessageRecord,
    },
    /// Delete a message body (its last queue dropped it).
    DeleteMessage {
        /// Message id.
        id: u64,
    },
    /// A queue holds a message at `seq`.
    Enqueue {
        /// Queue id.
        queue: u64,
        /// Position.
        seq: u64,
        /// Message id.
        message: u64,
        /// Delivered before (a requeue keeps the flag).
        delivered: bool,
    },
    /// A queue no longer holds the message at `seq`.
    Dequeue {
        /// Queue id.
        queue: u64,
        /// Position.
        seq: u64,
    },
}

fn put_short(buf: &mut BytesMut, s: &ShortStr) {
    buf.put_u8(s.len() as u8);
    buf.put_slice(s.as_bytes());
}

fn take_short(buf: &mut Bytes) -> Result<ShortStr, StoreError> {
    if buf.is_empty() {
        return Err(corrupt("short string"));
    }
    let len = usize::from(buf.get_u8());
    if buf.len() < len {
        return Err(corrupt("short string"));
    }
    ShortStr::try_from(buf.split_to(len)).map_err(|_| corrupt("short string"))
}

fn put_long(buf: &mut BytesMut, b: &[u8]) {
    buf.put_u32(b.len() as u32);
    buf.put_slice(b);
}

fn take_long(buf: &mut Bytes) -> Result<Bytes, StoreError> {
    if buf.len() < 4 {
        return Err(corrupt("long string"));
    }
    let len = buf.get_u32() as usize;
    if buf.len() < len {
        return Err(corrupt("long string"));
    }
    Ok(buf.split_to(len))
}

fn take_table(buf: &mut Bytes) -> Result<FieldTable, StoreError> {
    if buf.len() < 4 {
        return Err(corrupt("table"));
    }
    let len = u32::from_be_bytes([buf[0], buf[1], buf[2], buf[3]]) as usize;
    if buf.len() < 4 + len {
        return Err(corrupt("table"));
    }
    FieldTable::decode(&buf.split_to(4 + len)).map_err(|e| corrupt(&e.to_string()))
}

fn take_u8(buf: &mut Bytes) -> Result<u8, StoreError> {
    if buf.is_empty() {
        return Err(corrupt("octet"));
    }
    Ok(buf.get_u8())
}

fn take_u64(buf: &mut Bytes) -> Result<u64, StoreError> {
    if buf.len() < 8 {
        return Err(corrupt("u64"));
    }
    Ok(buf.get_u64())
}

fn corrupt(what: &str) -> StoreError {
    StoreError(format!("corrupt record ({what})"))
}

fn name_key(tag: u8, vhost: &ShortStr, name: &ShortStr) -> Vec<u8> {
    let mut key = Vec::with_capacity(2 + vhost.len() + name.len());
    key.push(tag);
    key.extend_from_slice(vhost.as_bytes());
    key.push(0);
    key.extend_from_slice(name.as_bytes());
    key
}

fn binding_key(b: &BindingRecord) -> Vec<u8> {
    let mut buf = BytesMut::new();
    buf.put_u8(b'b');
    put_short(&mut buf, &b.vhost);
    put_short(&mut buf, &b.source);
    buf.put_u8(u8::from(b.to_queue));
    put_short(&mut buf, &b.destination);
    put_short(&mut buf, &b.routing_key);
    b.arguments.encode(&mut buf);
    buf.to_vec()
}

fn message_key(id: u64) -> Vec<u8> {
    let mut key = Vec::with_capacity(9);
    key.push(b'm');
    key.extend_from_slice(&id.to_be_bytes());
    key
}

fn index_key(queue: u64, seq: u64) -> Vec<u8> {
    let mut key = Vec::with_capacity(17);
    key.push(b'i');
    key.extend_from_slice(&queue.to_be_bytes());
    key.extend_from_slice(&seq.to_be_bytes());
    key
}

impl StoreOp {
    /// The key-value change this op makes.
    pub fn to_kv(&self) -> KvOp {
        match self {
            StoreOp::PutExchange(x) => {
                let mut v = BytesMut::new();
                put_short(&mut v, &x.kind);
                v.put_u8(u8::from(x.auto_delete) | (u8::from(x.internal) << 1));
                x.arguments.encode(&mut v);
                (name_key(b'e', &x.vhost, &x.name), Some(v.to_vec()))
            }
            StoreOp::DeleteExchange { vhost, name } => (name_key(b'e', vhost, name), None),
            StoreOp::PutQueue(q) => {
                let mut v = BytesMut::new();
                v.put_u64(q.id);
                v.put_u8(u8::from(q.auto_delete));
                q.arguments.encode(&mut v);
                (name_key(b'q', &q.vhost, &q.name), Some(v.to_vec()))
            }
            StoreOp::DeleteQueue { vhost, name } => (name_key(b'q', vhost, name), None),
            StoreOp::PutBinding(b) => (binding_key(b), Some(Vec::new())),
            StoreOp::DeleteBinding(b) => (binding_key(b), None),
            StoreOp::PutMessage { id, record } => {
                let mut v =
                    BytesMut::with_capacity(record.body.len() + record.properties.len() + 64);
                put_short(&mut v, &record.exchange);
                put_short(&mut v, &record.routing_key);
                put_long(&mut v, &record.properties);
                put_long(&mut v, &record.body);
                (message_key(*id), Some(v.to_vec()))
            }
            StoreOp::DeleteMessage { id } => (message_key(*id), None),
            StoreOp::Enqueue {
                queue,
                seq,
                message,
                delivered,
            } => {
                let mut v = Vec::with_capacity(9);
                v.extend_from_slice(&message.to_be_bytes());
                v.push(u8::from(*delivered));
                (index_key(*queue, *seq), Some(v))
            }
            StoreOp::Dequeue { queue, seq } => (index_key(*queue, *seq), None),
        }
    }
}

/// A queue's message as recovered.
#[derive(Debug, Clone)]
pub struct RecoveredEntry {
    /// Position in the queue.
    pub seq: u64,
    /// Message id.
    pub message: u64,
    /// Delivered before the restart.
    pub delivered: bool,
}

/// Everything read back at start.
#[derive(Debug, Default)]
pub struct Recovered {
    /// Durable exchanges.
    pub exchanges: Vec<ExchangeRecord>,
    /// Durable queues.
    pub queues: Vec<QueueRecord>,
    /// Bindings.
    pub bindings: Vec<BindingRecord>,
    /// Message bodies by id.
    pub messages: std::collections::HashMap<u64, MessageRecord>,
    /// Each queue's entries in order, by queue id.
    pub entries: std::collections::HashMap<u64, Vec<RecoveredEntry>>,
}

impl Recovered {
    /// Decodes a full scan of a store.
    pub fn from_scan(pairs: Vec<KvPair>) -> Result<Recovered, StoreError> {
        let mut out = Recovered::default();
        for (key, value) in pairs {
            let Some((&tag, rest)) = key.split_first() else {
                continue;
            };
            let mut value = Bytes::from(value);
            match tag {
                b'e' | b'q' => {
                    let split = rest
                        .iter()
                        .position(|&b| b == 0)
                        .ok_or_else(|| corrupt("name key"))?;
                    let vhost = ShortStr::try_from(Bytes::copy_from_slice(&rest[..split]))
                        .map_err(|_| corrupt("vhost"))?;
                    let name = ShortStr::try_from(Bytes::copy_from_slice(&rest[split + 1..]))
                        .map_err(|_| corrupt("name"))?;
                    if tag == b'e' {
                        let kind = take_short(&mut value)?;
                        let flags = take_u8(&mut value)?;
                        let arguments = take_table(&mut value)?;
                        out.exchanges.push(ExchangeRecord {
                            vhost,
                            name,
                            kind,
                            auto_delete: flags & 1 != 0,
                            internal: flags & 2 != 0,
                            arguments,
                        });
                    } else {
                        let id = take_u64(&mut value)?;
                        let auto_delete = take_u8(&mut value)? != 0;
                        let arguments = take_table(&mut value)?;
                        out.queues.push(QueueRecord {
                            vhost,
                            name,
                            id,
                            auto_delete,
                            arguments,
                        });
                    }
                }
                b'b' => {
                    let mut k = Bytes::copy_from_slice(rest);
                    out.bindings.push(BindingRecord {
                        vhost: take_short(&mut k)?,
                        source: take_short(&mut k)?,
                        to_queue: take_u8(&mut k)? != 0,
                        destination: take_short(&mut k)?,
                        routing_key: take_short(&mut k)?,
                        arguments: take_table(&mut k)?,
                    });
                }
                b'm' => {
                    let id =
                        u64::from_be_bytes(rest.try_into().map_err(|_| corrupt("message key"))?);
                    let record = MessageRecord {
                        exchange: take_short(&mut value)?,
                        routing_key: take_short(&mut value)?,
                        properties: take_long(&mut value)?,
                        body: take_long(&mut value)?,
                    };
                    out.messages.insert(id, record);
                }
                b'i' => {
                    if rest.len() != 16 {
                        return Err(corrupt("index key"));
                    }
                    let queue =
                        u64::from_be_bytes(rest[..8].try_into().map_err(|_| corrupt("index key"))?);
                    let seq =
                        u64::from_be_bytes(rest[8..].try_into().map_err(|_| corrupt("index key"))?);
                    let message = take_u64(&mut value)?;
                    let delivered = take_u8(&mut value)? != 0;
                    out.entries.entry(queue).or_default().push(RecoveredEntry {
                        seq,
                        message,
                        delivered,
                    });
                }
                _ => return Err(corrupt("unknown key tag")),
            }
        }
        Ok(out)
    }

    /// The highest message id in use.
    pub fn max_message_id(&self) -> u64 {
        self.messages.keys().copied().max().unwrap_or(0)
    }

    /// The highest queue id in use.
    pub fn max_queue_id(&self) -> u64 {
        self.queues.iter().map(|q| q.id).max().unwrap_or(0)
    }
}

/// A request to the persister: ops to write, and the sequence number the
/// caller can wait on.
struct Submission {
    ops: Vec<StoreOp>,
}

/// How far the persister has got: every submission numbered up to
/// `flushed` has been attempted, and is on disk unless its batch failed
/// (see [`Persistence::succeeded`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Durable {
    /// Highest submission number attempted.
    pub flushed: u64,
}

/// The most recent failed batches remembered, as submission ranges. A
/// waiting publish checks its number against them within moments of the
/// failure, so a short history is enough.
const FAILED_HISTORY: usize = 4096;

/// The broker's handle on durable storage: submit ops, learn when they are
/// on disk. Submissions are numbered; [`Persistence::durable`] reports the
/// highest number flushed.
#[derive(Debug)]
pub struct Persistence {
    submit: mpsc::UnboundedSender<Submission>,
    submitted: AtomicU64,
    durable: watch::Receiver<Durable>,
    failed: Arc<std::sync::Mutex<VecDeque<(u64, u64)>>>,
    next_message_id: AtomicU64,
    next_queue_id: AtomicU64,
}

impl std::fmt::Debug for Submission {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "Submission({} ops)", self.ops.len())
    }
}

impl Persistence {
    /// Starts the persister thread for `store`, after `recovered` told the
    /// ids in use.
    pub fn start(store: Arc<dyn Store>, recovered: &Recovered) -> Arc<Persistence> {
        // Unbounded on purpose: submissions are bounded upstream (publishers
        // wait for confirms and are blocked by the memory alarm), and a
        // bounded channel here would block a queue's lock holder.
        let (submit, mut inbox) = mpsc::unbounded_channel::<Submission>();
        let (durable_tx, durable) = watch::channel(Durable { flushed: 0 });
        let failed = Arc::new(std::sync::Mutex::new(VecDeque::new()));
        let failed_log = Arc::clone(&failed);
        std::thread::Builder::new()
            .name("leveret-persister".into())
            .spawn(move || {
                let mut flushed = 0u64;
                let mut ops = Vec::new();
                while let Some(first) = inbox.blocking_recv() {
                    let mut count = 1u64;
                    ops.extend(first.ops.iter().map(StoreOp::to_kv));
                    // Group commit: everything already waiting joins this batch.
                    while let Ok(next) = inbox.try_recv() {
                        count += 1;
                        ops.extend(next.ops.iter().map(StoreOp::to_kv));
                        if ops.len() >= 65_536 {
                            break;
                        }
                    }
                    let result = store.apply(std::mem::take(&mut ops));
                    let first = flushed + 1;
                    flushed += count;
                    if let Err(e) = result {
                        tracing::error!(error = %e, "persisting failed; affected publishes are nacked");
                        // Held only to push or search, never across an await.
                        let mut log = failed_log.lock().unwrap_or_else(|e| e.into_inner());
                        if log.len() == FAILED_HISTORY {
                            log.pop_front();
                        }
                        log.push_back((first, flushed));
                    }
                    durable_tx.send_replace(Durable { flushed });
                }
            })
            .expect("spawning the persister thread");
        Arc::new(Persistence {
            submit,
            submitted: AtomicU64::new(0),
            durable,
            failed,
            next_message_id: AtomicU64::new(recovered.max_message_id() + 1),
            next_queue_id: AtomicU64::new(recovered.max_queue_id() + 1),
        })
    }

    /// Queues ops for the next batch; returns their submission number.
    pub fn submit(&self, ops: Vec<StoreOp>) -> u64 {
        let number = self.submitted.fetch_add(1, Ordering::AcqRel) + 1;
        // The persister thread lives as long as the process; a send error
        // only happens at exit.
        let _ = self.submit.send(Submission { ops });
        number
    }

    /// Watches what is on disk.
    pub fn durable(&self) -> watch::Receiver<Durable> {
        self.durable.clone()
    }

    /// Highest submission number the persister has attempted.
    pub fn flushed(&self) -> u64 {
        self.durable.borrow().flushed
    }

    /// Whether submission `number` (already attempted) reached the disk.
    pub fn succeeded(&self, number: u64) -> bool {
        let log = self.failed.lock().unwrap_or_else(|e| e.into_inner());
        !log.iter().any(|&(from, to)| (from..=to).contains(&number))
    }

    /// Waits until submission `number` is on disk; false if its batch failed.
    pub async fn wait(&self, number: u64) -> bool {
        let mut durable = self.durable.clone();
        if durable.wait_for(|d| d.flushed >= number).await.is_err() {
            return false;
        }
        self.succeeded(number)
    }

    /// Waits until everything submitted so far is on disk.
    pub async fn sync(&self) -> bool {
        self.wait(self.submitted.load(Ordering::Acquire)).await
    }

    /// A fresh message id.
    pub fn next_message_id(&self) -> u64 {
        self.next_message_id.fetch_add(1, Ordering::Relaxed)
    }

    /// A fresh queue id.
    pub fn next_queue_id(&self) -> u64 {
        self.next_queue_id.fetch_add(1, Ordering::Relaxed)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use leveret_protocol::FieldValue;

    fn s(v: &'static str) -> ShortStr {
        ShortStr::from_static(v)
    }

    #[test]
    fn every_record_round_trips_through_keys_and_values() {
        let store = MemoryStore::default();
        let mut args = FieldTable::new();
        args.insert(s("x-max-length"), FieldValue::I64(5));
        let ops = [
            StoreOp::PutExchange(ExchangeRecord {
                vhost: s("/"),
                name: s("ex"),
                kind: s("topic"),
                auto_delete: false,
                internal: true,
                arguments: args.clone(),
            }),
            StoreOp::PutQueue(QueueRecord {
                vhost: s("/"),
                name: s("q"),
                id: 7,
                auto_delete: true,
                arguments: args.clone(),
            }),
            StoreOp::PutBinding(BindingRecord {
                vhost: s("/"),
                source: s("ex"),
                to_queue: true,
                destination: s("q"),
                routing_key: s("a.#"),
                arguments: args,
            }),
            StoreOp::PutMessage {
                id: 3,
                record: MessageRecord {
                    exchange: s("ex"),
                    routing_key: s("a.b"),
                    properties: Bytes::from_static(b"\x10\x00\x02"),
                    body: Bytes::from_static(b"hello"),
                },
            },
            StoreOp::Enqueue {
                queue: 7,
                seq: 2,
                message: 3,
                delivered: false,
            },
            StoreOp::Enqueue {
                queue: 7,
                seq: 1,
                message: 3,
                delivered: true,
            },
        ];
        store
            .apply(ops.iter().map(StoreOp::to_kv).collect())
            .unwrap();
        let recovered = Recovered::from_scan(store.scan().unwrap()).unwrap();
        assert_eq!(recovered.exchanges.len(), 1);
        assert!(recovered.exchanges[0].internal);
        assert_eq!(recovered.queues[0].id, 7);
        assert_eq!(recovered.bindings[0].routing_key, s("a.#"));
        assert_eq!(recovered.messages[&3].body, Bytes::from_static(b"hello"));
        let entries = &recovered.entries[&7];
        assert_eq!(
            entries.iter().map(|e| e.seq).collect::<Vec<_>>(),
            vec![1, 2]
        );
        assert!(entries[0].delivered);
        assert_eq!(recovered.max_message_id(), 3);

        store
            .apply(vec![
                StoreOp::Dequeue { queue: 7, seq: 1 }.to_kv(),
                StoreOp::Dequeue { queue: 7, seq: 2 }.to_kv(),
                StoreOp::DeleteMessage { id: 3 }.to_kv(),
            ])
            .unwrap();
        let recovered = Recovered::from_scan(store.scan().unwrap()).unwrap();
        assert!(recovered.messages.is_empty());
        assert!(recovered.entries.is_empty());
    }

    #[test]
    fn corrupt_values_are_errors_not_panics() {
        let pairs = vec![(b"m\0\0\0\0\0\0\0\x01".to_vec(), vec![200, 1, 2])];
        assert!(Recovered::from_scan(pairs).is_err());
        let pairs = vec![(b"i\0\0".to_vec(), vec![])];
        assert!(Recovered::from_scan(pairs).is_err());
    }

    #[tokio::test]
    async fn persister_numbers_submissions_and_reports_them_flushed() {
        let store: Arc<dyn Store> = Arc::new(MemoryStore::default());
        let persistence = Persistence::start(Arc::clone(&store), &Recovered::default());
        let mut last = 0;
        for i in 0..100 {
            last = persistence.submit(vec![StoreOp::DeleteMessage { id: i }]);
        }
        assert_eq!(last, 100);
        assert!(persistence.wait(last).await);
        assert_eq!(persistence.next_queue_id(), 1);
    }
}
