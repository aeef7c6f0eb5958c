//! Durable state: what is persisted (durable exchanges, queues and bindings,
//! persistent messages in durable queues), how it is keyed, the group-commit
//! persister that batches writes from every connection into one atomic,
//! flushed batch, and recovery.
//!
//! Storage engines implement the small key-value [`Store`] trait (`sled.rs`
//! on disk, `memory.rs` for tests and transient brokers); everything about
//! keys and values lives here, once.
//!
//! Keys, in one keyspace so a transaction's batch is atomic:
//! - `e` vhost 0 name → exchange definition
//! - `q` vhost 0 name → queue definition (with the queue's numeric id)
//! - `b` vhost 0 source 0 kind destination 0 key 0 args → binding
//! - `i` queue-id (8 bytes BE) seq (8 BE) → the message inline (`0` +
//!   record), or a reference to a shared record (`1` + message-id)
//! - `m` message-id (8 BE) → a message held by several durable queues
//! - `d` queue-id (8 BE) → the highest seq delivered from the queue
//!
//! A message in one durable queue (the usual case) costs one key; one in
//! several is stored once and referenced, and the last queue to drop it
//! deletes it. Instead of rewriting an entry on every delivery, each queue
//! keeps a delivery mark: after a restart, entries at or below it come back
//! redelivered (they may have been delivered; the flag is a hint, and a
//! false positive only happens with priorities).
//!
//! sled costs a few microseconds per key, and very large atomic batches
//! make it hold a lot of memory, so the persister writes plain inserts and
//! removes, uses an atomic batch only for a transaction's commit, and
//! flushes once per group. Safety rests only on `flush`: everything written
//! before it is durable when it returns, and nothing is confirmed earlier.
//! Writes not yet flushed at a crash may survive in any combination, which
//! is harmless: an insert without its remove brings back a message that was
//! not confirmed gone (it is redelivered), and an entry whose shared record
//! was deleted belongs to a queue that had already acked it (recovery
//! skips it).

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

/// A key-value engine: ordered writes, atomic batches on request, and a
/// flush that makes everything written so far durable.
pub trait Store: Send + Sync + std::fmt::Debug + 'static {
    /// Applies `ops` in order; all or nothing when `atomic`. Not yet durable.
    fn write(&self, ops: Vec<KvOp>, atomic: bool) -> Result<(), StoreError>;
    /// Makes every write so far durable.
    fn flush(&self) -> Result<(), StoreError>;
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

/// What a queue's index entry holds.
#[derive(Debug, Clone, PartialEq)]
pub enum EntryBody {
    /// The message itself.
    Inline(MessageRecord),
    /// The id of a shared message record.
    Shared(u64),
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
    /// Store a message held by several durable queues, once.
    PutMessage {
        /// Message id.
        id: u64,
        /// The message.
        record: MessageRecord,
    },
    /// Delete a shared message (its last queue dropped it).
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
        /// The message, or its shared record.
        body: EntryBody,
    },
    /// Messages of a queue up to `seq` have been delivered.
    Delivered {
        /// Queue id.
        queue: u64,
        /// Highest seq delivered.
        seq: u64,
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

fn mark_key(queue: u64) -> Vec<u8> {
    let mut key = Vec::with_capacity(9);
    key.push(b'd');
    key.extend_from_slice(&queue.to_be_bytes());
    key
}

fn put_record(v: &mut BytesMut, record: &MessageRecord) {
    put_short(v, &record.exchange);
    put_short(v, &record.routing_key);
    put_long(v, &record.properties);
    put_long(v, &record.body);
}

fn take_record(value: &mut Bytes) -> Result<MessageRecord, StoreError> {
    Ok(MessageRecord {
        exchange: take_short(value)?,
        routing_key: take_short(value)?,
        properties: take_long(value)?,
        body: take_long(value)?,
    })
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
                put_record(&mut v, record);
                (message_key(*id), Some(v.to_vec()))
            }
            StoreOp::DeleteMessage { id } => (message_key(*id), None),
            StoreOp::Enqueue { queue, seq, body } => {
                let value = match body {
                    EntryBody::Inline(record) => {
                        let mut v = BytesMut::with_capacity(
                            record.body.len() + record.properties.len() + 64,
                        );
                        v.put_u8(0);
                        put_record(&mut v, record);
                        v.to_vec()
                    }
                    EntryBody::Shared(id) => {
                        let mut v = Vec::with_capacity(9);
                        v.push(1);
                        v.extend_from_slice(&id.to_be_bytes());
                        v
                    }
                };
                (index_key(*queue, *seq), Some(value))
            }
            StoreOp::Delivered { queue, seq } => {
                (mark_key(*queue), Some(seq.to_be_bytes().to_vec()))
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
    /// The message, or its shared record.
    pub body: EntryBody,
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
    /// Shared message records by id.
    pub messages: std::collections::HashMap<u64, MessageRecord>,
    /// Each queue's entries in order, by queue id.
    pub entries: std::collections::HashMap<u64, Vec<RecoveredEntry>>,
    /// Each queue's delivery mark, by queue id.
    pub delivered: std::collections::HashMap<u64, u64>,
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
                    out.messages.insert(id, take_record(&mut value)?);
                }
                b'd' => {
                    let queue =
                        u64::from_be_bytes(rest.try_into().map_err(|_| corrupt("mark key"))?);
                    out.delivered.insert(queue, take_u64(&mut value)?);
                }
                b'i' => {
                    if rest.len() != 16 {
                        return Err(corrupt("index key"));
                    }
                    let queue =
                        u64::from_be_bytes(rest[..8].try_into().map_err(|_| corrupt("index key"))?);
                    let seq =
                        u64::from_be_bytes(rest[8..].try_into().map_err(|_| corrupt("index key"))?);
                    let body = match take_u8(&mut value)? {
                        0 => EntryBody::Inline(take_record(&mut value)?),
                        1 => EntryBody::Shared(take_u64(&mut value)?),
                        _ => return Err(corrupt("index entry kind")),
                    };
                    out.entries
                        .entry(queue)
                        .or_default()
                        .push(RecoveredEntry { seq, body });
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

/// A request to the persister: ops to write, all or nothing if `atomic`;
/// or, with `close`, the last request: flush, release the store, answer.
struct Submission {
    ops: Vec<StoreOp>,
    atomic: bool,
    close: Option<tokio::sync::oneshot::Sender<()>>,
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

/// One group commit being assembled by the persister: plain writes in
/// order, atomic submissions applied as batches in their place, delivery
/// marks merged to one write per queue, then one flush.
#[derive(Default)]
struct Group {
    pending: Vec<KvOp>,
    marks: Vec<(u64, u64)>,
    submissions: u64,
    len: usize,
    error: Option<StoreError>,
}

impl Group {
    /// Adds a submission; returns its close request, if it is one.
    fn add(
        &mut self,
        store: &dyn Store,
        submission: Submission,
    ) -> Option<tokio::sync::oneshot::Sender<()>> {
        self.submissions += 1;
        self.len += submission.ops.len();
        if submission.atomic {
            self.write_pending(store);
            let ops = submission.ops.iter().map(StoreOp::to_kv).collect();
            let result = store.write(ops, true);
            self.record(result);
            return submission.close;
        }
        for op in &submission.ops {
            match op {
                StoreOp::Delivered { queue, seq } => {
                    match self.marks.iter_mut().find(|(q, _)| q == queue) {
                        Some((_, mark)) => *mark = (*mark).max(*seq),
                        None => self.marks.push((*queue, *seq)),
                    }
                }
                op => self.pending.push(op.to_kv()),
            }
        }
        submission.close
    }

    fn write_pending(&mut self, store: &dyn Store) {
        if !self.pending.is_empty() {
            let ops = std::mem::take(&mut self.pending);
            let result = store.write(ops, false);
            self.record(result);
        }
    }

    fn record(&mut self, result: Result<(), StoreError>) {
        if let (Err(e), None) = (result, &self.error) {
            self.error = Some(e);
        }
    }

    fn finish(mut self, store: &dyn Store) -> Result<(), StoreError> {
        let marks = std::mem::take(&mut self.marks);
        self.pending.extend(
            marks
                .into_iter()
                .map(|(queue, seq)| StoreOp::Delivered { queue, seq }.to_kv()),
        );
        self.write_pending(store);
        let flushed = store.flush();
        self.record(flushed);
        match self.error {
            Some(e) => Err(e),
            None => Ok(()),
        }
    }
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
                                while let Some(first) = inbox.blocking_recv() {
                    let mut group = Group::default();
                    let mut closing = group.add(&*store, first);
                    // Group commit: everything already waiting joins this
                    // group, up to a bound that keeps one flush short.
                    while closing.is_none() && group.len < 50_000 {
                        match inbox.try_recv() {
                            Ok(next) => closing = group.add(&*store, next),
                            Err(_) => break,
                        }
                    }
                    let first_number = flushed + 1;
                    flushed += group.submissions;
                    if let Err(e) = group.finish(&*store) {
                        tracing::error!(error = %e, "persisting failed; affected publishes are nacked");
                        // Held only to push or search, never across an await.
                        let mut log = failed_log.lock().unwrap_or_else(|e| e.into_inner());
                        if log.len() == FAILED_HISTORY {
                            log.pop_front();
                        }
                        log.push_back((first_number, flushed));
                    }
                                        durable_tx.send_replace(Durable { flushed });
                    if let Some(done) = closing {
                        // Releases the data directory (sled's lock) before
                        // answering, so a new broker can open it at once.
                        drop(store);
                        let _ = done.send(());
                        return;
                    }
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

    /// Queues ops for the next group; returns their submission number.
    pub fn submit(&self, ops: Vec<StoreOp>) -> u64 {
        self.send(Submission {
            ops,
            atomic: false,
            close: None,
        })
    }

    /// Queues ops that must reach the disk all together or not at all (a
    /// transaction's commit).
    pub fn submit_atomic(&self, ops: Vec<StoreOp>) -> u64 {
        self.send(Submission {
            ops,
            atomic: true,
            close: None,
        })
    }

    /// Writes and flushes everything submitted so far, then releases the
    /// store; later submissions are dropped. For shutdown.
    pub async fn close(&self) {
        let (done, closed) = tokio::sync::oneshot::channel();
        self.send(Submission {
            ops: Vec::new(),
            atomic: false,
            close: Some(done),
        });
        let _ = closed.await;
    }

    fn send(&self, submission: Submission) -> u64 {
        let number = self.submitted.fetch_add(1, Ordering::AcqRel) + 1;
        // The persister thread lives as long as the process; a send error
        // only happens at exit.
        let _ = self.submit.send(submission);
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
                body: EntryBody::Shared(3),
            },
            StoreOp::Enqueue {
                queue: 7,
                seq: 1,
                body: EntryBody::Inline(MessageRecord {
                    exchange: s(""),
                    routing_key: s("q"),
                    properties: Bytes::from_static(b"\x00\x00"),
                    body: Bytes::from_static(b"inline"),
                }),
            },
            StoreOp::Delivered { queue: 7, seq: 1 },
        ];
        store
            .write(ops.iter().map(StoreOp::to_kv).collect(), true)
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
        assert!(
            matches!(&entries[0].body, EntryBody::Inline(r) if r.body == Bytes::from_static(b"inline"))
        );
        assert_eq!(entries[1].body, EntryBody::Shared(3));
        assert_eq!(recovered.delivered[&7], 1);
        assert_eq!(recovered.max_message_id(), 3);

        store
            .write(
                vec![
                    StoreOp::Dequeue { queue: 7, seq: 1 }.to_kv(),
                    StoreOp::Dequeue { queue: 7, seq: 2 }.to_kv(),
                    StoreOp::DeleteMessage { id: 3 }.to_kv(),
                ],
                false,
            )
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
