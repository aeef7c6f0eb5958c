//! Durable state: what is persisted (durable exchanges, queues and bindings,
//! persistent messages in durable queues), how it is keyed, the group-commit
//! persister that batches writes from every connection into one atomic,
//! flushed batch, and recovery.
//!
//! Storage engines implement the small key-value [`Store`] trait: on disk
//! [`DiskStore`] (`disk.rs`), which keeps definitions in sled (`sled.rs`)
//! and the keys written for every message in the message log (`log/`,
//! append-only segments, one sync per group); `memory.rs` for tests and
//! transient brokers. The on-disk engines are the `persistence` feature's
//! (default): without it, durable state lives only in a [`Store`] the
//! embedder provides. Everything about keys and values lives here, once
//! (`codec.rs`, which also says which engine keeps a key).
//!
//! Keys, in one keyspace so a transaction's batch is atomic:
//! - `e` vhost 0 name → exchange definition
//! - `q` vhost 0 name → queue definition (with the queue's numeric id)
//! - `b` vhost 0 source 0 kind destination 0 key 0 args → binding
//! - `i` queue-id (8 bytes BE) seq (8 BE) → the message inline (`0` +
//!   record), or a reference to a shared record (`1` + message-id)
//! - `m` message-id (8 BE) → a message held by several durable queues
//! - `d` queue-id (8 BE) → the highest seq delivered from the queue
//! - `!clean` → the generation of the last clean shutdown (its last
//!   write; `integrity` checks it against the manifest beside the store)
//! - `!starts` → how many times the broker has started on this store
//!   (written and flushed at each start, before serving): each start's new
//!   queue positions begin above every earlier start's
//!   ([`Persistence::seq_floor`])
//! - `!seeded` → present once the default user has been considered (it is
//!   created on a store's first start only, as RabbitMQ creates `guest`)
//! - `a` kind (1 byte) then each name as a long string → a user, vhost,
//!   permission, topic permission or runtime parameter changed at run time
//!   ([`MetaRecord`])
//!
//! A message in one durable queue (the usual case) costs one key; one in
//! several is stored once and referenced, and the last queue to drop it
//! deletes it. Instead of rewriting an entry on every delivery, each queue
//! keeps a delivery mark: after a restart, entries at or below it come back
//! redelivered (they may have been delivered; the flag is a hint, and a
//! false positive only happens with priorities).
//!
//! The persister writes plain inserts and removes, uses an atomic batch
//! only for a transaction's commit (or a set of definitions), and flushes
//! once per group. Safety rests only on `flush`: everything written
//! before it is durable when it returns, and nothing is confirmed earlier.
//! Writes not yet flushed at a crash may survive in any combination, which
//! is harmless: an insert without its remove brings back a message that was
//! not confirmed gone (it is redelivered), and an entry whose shared record
//! was deleted belongs to a queue that had already acked it (recovery
//! skips it).

mod codec;
#[cfg(feature = "persistence")]
mod disk;
#[cfg(feature = "persistence")]
mod integrity;
#[cfg(feature = "persistence")]
mod log;
mod memory;
mod persister;
#[cfg(feature = "persistence")]
mod sled;
pub(crate) mod slots;

pub use self::codec::BadRecord;
#[cfg(feature = "persistence")]
pub use self::disk::DiskStore;
#[cfg(feature = "persistence")]
pub use self::integrity::{mark_clean, open_checked, OpenedStore};
#[cfg(feature = "persistence")]
pub use self::log::{Bookkeeping, Losses, LostRange, OnDamage};
pub use self::memory::MemoryStore;
pub(crate) use self::persister::AfterSync;
pub use self::persister::{Durable, Persistence, PersisterFigures, Written};
#[cfg(feature = "persistence")]
pub use self::sled::SledStore;

use bytes::Bytes;
use leveret_protocol::{FieldTable, ShortStr};

/// Why storage failed.
#[derive(Debug, thiserror::Error)]
pub enum StoreError {
    /// The data directory could not be created.
    #[cfg(feature = "persistence")]
    #[error("cannot create {path}: {source}")]
    DataDir {
        /// The directory.
        path: std::path::PathBuf,
        /// What the file system said.
        source: std::io::Error,
    },
    /// The sled database failed.
    #[cfg(feature = "persistence")]
    #[error("sled: {0}")]
    Sled(#[from] ::sled::Error),
    /// Another storage engine failed: for [`Store`]s an embedder provides.
    #[error("storage engine: {0}")]
    Engine(Box<dyn std::error::Error + Send + Sync>),
    /// A stored record could not be decoded.
    #[error("corrupt record ({what})")]
    Corrupt {
        /// The part of the record that is wrong.
        what: &'static str,
    },
    /// A stored field table could not be decoded.
    #[error("corrupt record (field table): {0}")]
    CorruptTable(#[from] leveret_protocol::DecodeError),
    /// The storage engine panicked (a bug in it, or a damaged file it did
    /// not expect); caught at the boundary by [`guarded`].
    #[error("the storage engine panicked during {what}: {message}")]
    Panicked {
        /// The call that panicked.
        what: &'static str,
        /// The panic's message.
        message: String,
    },
    /// The store in a data directory is damaged (see `integrity`).
    #[cfg(feature = "persistence")]
    #[error(
        "the store in {path} is damaged: {problem}; the broker does not start on it. \
         Start with --recover to keep every readable record (the damaged files are \
         copied aside first)"
    )]
    Damaged {
        /// The data directory.
        path: std::path::PathBuf,
        /// What is wrong.
        problem: String,
    },
    /// A stream's segment file could not be synced.
    #[error("cannot sync a stream segment: {0}")]
    StreamSync(std::io::Error),
    /// The persister thread could not be started.
    #[error("cannot start the persister thread: {0}")]
    Persister(std::io::Error),
}

/// Runs one call into a storage engine, turning a panic inside it into
/// [`StoreError::Panicked`], so a storage bug or a damaged file becomes an
/// error the broker reports (a nack, a refused start) instead of killing
/// the persister thread, after which every later write would fail.
pub fn guarded<T>(
    what: &'static str,
    call: impl FnOnce() -> Result<T, StoreError>,
) -> Result<T, StoreError> {
    // The engine's state after a panic is its own business: a later call
    // that finds it broken panics or fails again, and is reported again.
    std::panic::catch_unwind(std::panic::AssertUnwindSafe(call)).unwrap_or_else(|panic| {
        let message = panic
            .downcast_ref::<&str>()
            .map(|s| (*s).to_owned())
            .or_else(|| panic.downcast_ref::<String>().cloned())
            .unwrap_or_else(|| "(no message)".to_owned());
        Err(StoreError::Panicked { what, message })
    })
}

/// One key-value change.
pub type KvOp = (Vec<u8>, Option<Vec<u8>>);

/// One stored key and its value.
pub type KvPair = (Vec<u8>, Vec<u8>);

/// How [`Store::write`] applies its ops.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum WriteMode {
    /// In order, one by one: a crash may leave any prefix applied.
    Plain,
    /// All or nothing (a transaction's commit).
    Atomic,
}

/// A key-value engine: ordered writes, atomic batches on request, and a
/// flush that makes everything written so far durable.
pub trait Store: Send + Sync + std::fmt::Debug + 'static {
    /// Applies `ops` in order, as `mode` says. Not yet durable.
    fn write(&self, ops: Vec<KvOp>, mode: WriteMode) -> Result<(), StoreError>;
    /// Makes every write so far durable.
    fn flush(&self) -> Result<(), StoreError>;
    /// Every key and value, in key order.
    fn scan(&self) -> Result<Vec<KvPair>, StoreError>;
    /// Starts again from what is durable, after a failed write or flush
    /// (writes not flushed may be lost): an engine that refuses all work
    /// after an I/O error reopens its files here. The default does
    /// nothing, for engines that recover by themselves.
    fn reopen(&self) -> Result<(), StoreError> {
        Ok(())
    }
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

/// Users, vhosts, permissions and runtime parameters added or changed
/// while the broker runs (the management API, `leveretctl`, a definitions
/// import), kept so they last like those in RabbitMQ's metadata store.
/// Plain text: the store knows nothing of hashes, patterns or parameter
/// values; `access` and `parameters` turn them back into what they mean.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum MetaRecord {
    /// A user.
    User {
        /// Name.
        name: String,
        /// The password hash as RabbitMQ writes it in definitions.
        password_hash: String,
        /// Its `hashing_algorithm`.
        hashing_algorithm: String,
        /// Tags (`administrator`, `monitoring`…).
        tags: Vec<String>,
    },
    /// A vhost.
    Vhost {
        /// Name.
        name: String,
    },
    /// A user's permission on a vhost.
    Permission {
        /// User.
        user: String,
        /// Vhost.
        vhost: String,
        /// Configure pattern.
        configure: String,
        /// Write pattern.
        write: String,
        /// Read pattern.
        read: String,
    },
    /// A user's topic permission on an exchange of a vhost.
    TopicPermission {
        /// User.
        user: String,
        /// Vhost.
        vhost: String,
        /// Exchange.
        exchange: String,
        /// Write pattern (routing keys).
        write: String,
        /// Read pattern (binding keys).
        read: String,
    },
    /// A runtime parameter (RabbitMQ's `set_parameter`: a shovel's, for
    /// one).
    Parameter {
        /// Component (`shovel`).
        component: String,
        /// Vhost.
        vhost: String,
        /// Name.
        name: String,
        /// Its value, as JSON text.
        value: String,
    },
    /// An MQTT retained message (the `mqtt` front end's, per vhost and
    /// topic).
    Retained {
        /// Vhost.
        vhost: String,
        /// The MQTT topic name.
        topic: String,
        /// Its QoS level (0, 1 or 2).
        qos: u8,
        /// Its MQTT 5.0 properties mapped to AMQP basic properties
        /// (encoded; empty for none).
        properties: Bytes,
        /// Its payload.
        payload: Bytes,
    },
    /// A QoS 2 publish a persistent MQTT session routed and PUBREC'd, not
    /// yet released by the client's PUBREL (the `mqtt` front end's).
    Unreleased {
        /// Vhost.
        vhost: String,
        /// The MQTT client identifier.
        client_id: String,
        /// The publish's packet identifier (not 0).
        packet_id: u16,
        /// The session's Session Expiry Interval in seconds (`u32::MAX`:
        /// never), so the record expires with the session, after a restart
        /// too; `None` in a record written before it was kept.
        session_expiry: Option<u32>,
    },
    /// A shared subscription a persistent MQTT session holds (the `mqtt`
    /// front end's).
    SharedSubscription {
        /// Vhost.
        vhost: String,
        /// The MQTT client identifier.
        client_id: String,
        /// The filter, `$share/GROUP/FILTER`.
        filter: String,
        /// The QoS granted (0, 1 or 2).
        qos: u8,
        /// Its Retain As Published option.
        retain_as_published: bool,
        /// Its Subscription Identifier (0: none).
        subscription_id: u32,
        /// The session's expiry interval, seconds (`u32::MAX`: never).
        session_expiry: u32,
    },
}

/// What identifies an [`MetaRecord`] (for deleting one).
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum MetaKey {
    /// A user by name.
    User(String),
    /// A vhost by name.
    Vhost(String),
    /// A (user, vhost) permission.
    Permission {
        /// User.
        user: String,
        /// Vhost.
        vhost: String,
    },
    /// A (user, vhost, exchange) topic permission.
    TopicPermission {
        /// User.
        user: String,
        /// Vhost.
        vhost: String,
        /// Exchange.
        exchange: String,
    },
    /// A (component, vhost, name) runtime parameter.
    Parameter {
        /// Component.
        component: String,
        /// Vhost.
        vhost: String,
        /// Name.
        name: String,
    },
    /// A (vhost, topic) MQTT retained message.
    Retained {
        /// Vhost.
        vhost: String,
        /// Topic.
        topic: String,
    },
    /// A (vhost, client identifier, packet identifier) unreleased MQTT
    /// QoS 2 publish.
    Unreleased {
        /// Vhost.
        vhost: String,
        /// The MQTT client identifier.
        client_id: String,
        /// The packet identifier.
        packet_id: u16,
    },
    /// A (vhost, client identifier, filter) shared subscription of a
    /// persistent MQTT session.
    SharedSubscription {
        /// Vhost.
        vhost: String,
        /// The MQTT client identifier.
        client_id: String,
        /// The filter, `$share/GROUP/FILTER`.
        filter: String,
    },
}

impl MetaRecord {
    /// What identifies it.
    pub fn key(&self) -> MetaKey {
        match self {
            MetaRecord::User { name, .. } => MetaKey::User(name.clone()),
            MetaRecord::Vhost { name } => MetaKey::Vhost(name.clone()),
            MetaRecord::Permission { user, vhost, .. } => MetaKey::Permission {
                user: user.clone(),
                vhost: vhost.clone(),
            },
            MetaRecord::TopicPermission {
                user,
                vhost,
                exchange,
                ..
            } => MetaKey::TopicPermission {
                user: user.clone(),
                vhost: vhost.clone(),
                exchange: exchange.clone(),
            },
            MetaRecord::Parameter {
                component,
                vhost,
                name,
                ..
            } => MetaKey::Parameter {
                component: component.clone(),
                vhost: vhost.clone(),
                name: name.clone(),
            },
            MetaRecord::Retained { vhost, topic, .. } => MetaKey::Retained {
                vhost: vhost.clone(),
                topic: topic.clone(),
            },
            MetaRecord::Unreleased {
                vhost,
                client_id,
                packet_id,
                ..
            } => MetaKey::Unreleased {
                vhost: vhost.clone(),
                client_id: client_id.clone(),
                packet_id: *packet_id,
            },
            MetaRecord::SharedSubscription {
                vhost,
                client_id,
                filter,
                ..
            } => MetaKey::SharedSubscription {
                vhost: vhost.clone(),
                client_id: client_id.clone(),
                filter: filter.clone(),
            },
        }
    }
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
    /// Add or replace a user, vhost, permission or parameter.
    PutMeta(MetaRecord),
    /// Remove one.
    DeleteMeta(MetaKey),
    /// The default user has been considered (written once, at a store's
    /// first start).
    Seeded,
    /// The broker has started this many times on the store.
    Starts {
        /// The count, this start included.
        count: u64,
    },
    /// The last write of a clean shutdown: the store's generation, which
    /// the manifest beside it must match at the next start.
    CleanShutdown {
        /// The generation (one more each clean shutdown).
        generation: u64,
    },
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
    /// The generation of the last clean shutdown's marker, if any.
    pub clean_generation: Option<u64>,
    /// Users, vhosts, permissions and parameters changed at run time.
    pub meta: Vec<MetaRecord>,
    /// Whether the default user has been considered already.
    pub seeded: bool,
    /// How many times the broker has started on the store before.
    pub starts: u64,
}

impl Recovered {
    /// The highest message id in use.
    pub fn max_message_id(&self) -> u64 {
        self.messages.keys().copied().max().unwrap_or(0)
    }

    /// The highest queue id in use.
    pub fn max_queue_id(&self) -> u64 {
        self.queues.iter().map(|q| q.id).max().unwrap_or(0)
    }
}
