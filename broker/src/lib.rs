//! # leveret-broker
//!
//! An embeddable AMQP 0.9.1 broker that RabbitMQ clients use unchanged.
//! Start one inside a process with [`Broker::builder`], or run the
//! `leveret` binary. The binary is a crate of its own (`server/`, package
//! `leveret`) that owns the command line, the config file and the logging
//! set-up, so an embedder compiles none of clap, serde, toml or
//! tracing-subscriber: this library is configured only through the
//! builder, and reports through `tracing` events that the embedder's own
//! subscriber (if any) receives.
//!
//! ```no_run
//! # async fn demo() -> Result<(), leveret_broker::StartError> {
//! let handle = leveret_broker::Broker::builder()
//!     .listen("127.0.0.1:0".parse().unwrap())
//!     .start()
//!     .await?;
//! println!("serving on {:?}", handle.local_addrs());
//! handle.shutdown().await;
//! # Ok(()) }
//! ```
//!
//! # Features
//!
//! All on by default; an embedder that needs less takes
//! `default-features = false` and names what it uses (43 crates on Linux
//! with none, 92 with all):
//! - `tls`: TLS listeners and SASL EXTERNAL (rustls on ring, tokio-rustls,
//!   x509-parser: 32 crates).
//! - `persistence`: `BrokerBuilder::data_dir`, durable state on disk
//!   (sled and the message log: 13 crates). Without it durable state
//!   lives in a [`store::Store`] the embedder gives, or nowhere.
//! - `mqtt`: MQTT listeners (leveret-mqtt).
//! - `regex`: permission patterns as regular expressions (4 crates);
//!   without it only `.*`, the empty pattern and literal names and
//!   prefixes (`^name$`, `^name`, `^name.*`) are taken, others refused
//!   when set.
//!
//! # Layout
//!
//! The crate is built in layers. Each uses only the layers below it and
//! the shared pieces beside them, never one above, so no circle of
//! imports runs between layers: a lower layer that needs something done
//! above returns it as a value (a queue's dead letters), or names it by a
//! type parameter or a trait of its own that the layer above fills in (an
//! unacked delivery's queue, the queues waiting for room in an outbox),
//! instead of calling up. `tests/layering.rs` holds this table against
//! every `crate::` and `super::` path in the code.
//!
//! 1. **Server**: `embed` (the builder and handle, the public entry
//!    point), `server` (TCP listeners, the accept loop, the TTL/expiry
//!    sweeper), `connection` (the reader loop, heartbeats, closing;
//!    `connection::handshake` is the handshake, a function a step;
//!    `connection::writer` owns the socket's write half),
//!    `recovery` (durable state rebuilt at start), `mqtt` (MQTT listeners
//!    and sessions: a front end that drives the core through an in-process
//!    AMQP link, as RabbitMQ's MQTT plugin did through its direct
//!    connection). May use every layer below.
//! 2. **Operators**: `admin` ([`Admin`], a cloneable handle for tools:
//!    object operations, reading state as `BrokerHandle::overview` does,
//!    users and permissions, closing connections, runtime parameters:
//!    every `impl Admin` is in its folder, and `admin::as_user`, the same
//!    operations checked against a user's permissions); and below those
//!    two, knowing no handle, `inspect` (the plain structs state is read
//!    into, with RabbitMQ's field meanings) and `access::lasting` (users,
//!    vhosts and permissions that last: restored at start, and their
//!    records; the rest of `access` is shared, below).
//!    No layer below calls them.
//! 3. **Channel**: `channel`, content assembly and one module per AMQP
//!    class (`basic`, `queue`, `exchange`, `tx`, `reply_to`), and
//!    `confirms`, publisher confirms: the channel keeps their state and
//!    watches the store for them itself, its connection only drives the
//!    futures. A whole publish from an in-process client is its input
//!    type. Uses the core and below; knows no connection and no socket.
//! 4. **Core**: `core`, the state every connection shares (vhosts, users,
//!    limits, the memory gauge, the store handle, the shutdown signal,
//!    connection.start's server properties). Uses vhosts and below.
//! 5. **Vhost and exchanges**: `vhost` (declare, delete, bind, route;
//!    `vhost::routing`, a published message's way through exchanges to
//!    the queues it reaches; `vhost::publish`, the one owner of a
//!    message's durable write, through which every publisher goes: it
//!    writes the message's shared record, offers it to its queues (each
//!    writes its index entry under its own lock) and returns what a
//!    confirm waits for; `vhost::deadletter`, routing the dead letters
//!    queue operations return: a work list with RabbitMQ's cycle rule and
//!    a budget; it routes through the vhost, whose `dead_letter` hands the
//!    letters to it, the one circle left), `exchange` (the kinds and their
//!    bindings: the `topic` trie, `headers` matching, the binding
//!    registry). Modules of one layer may use each other. Use queues and
//!    below.
//! 6. **Queue**: `queue` (the FIFO, dispatch to consumers, TTL,
//!    max-length, durable index entries; dead letters are returned to the
//!    caller; `queue::stream`, a stream's log and its readers;
//!    `queue::Origin`, what an unacked delivery keeps of its queue, to
//!    which `queue::{Consumer, ChannelLink, Unacked}` fix the consumer
//!    layer's types), and beside it `registry` (open connections and
//!    channels, for listing and for closing one from outside). Uses
//!    consumers, outboxes and the store.
//! 7. **Consumer and outbox**: `consumer` (delivery tags, unacked
//!    bookkeeping, prefetch credit, direct reply-to targets), `outbox`
//!    (what goes to a connection's writer, with backpressure, or straight
//!    to an in-process client's consumer or confirms: [`InlineDeliveries`]). They know
//!    no queue: the delivery bookkeeping is generic over what a queue
//!    keeps of a delivery, and an outbox wakes what waited for room in it
//!    through its trait `WaitsForRoom`, which a queue implements.
//!
//! Beside the layers: `store` (the [`store::Store`] trait, the key codec,
//! the group-commit persister), used from the queue layer up and using
//! nothing of the broker but `stats` (its histograms) and `word_hash`; and
//! the pieces every layer may use, which use only each other and the store:
//! `message` (a message as the broker holds it), `alarm` (the memory and
//! disk alarms: `alarm::memory` the alarm itself, `alarm::resident` the
//! process's resident memory from /proc and `alarm::disk` free disk space,
//! its sources), `admission` (connections and channels counted against
//! RabbitMQ's connection, vhost and user limits), `limits` (the vhost and
//! user limits in effect, set at run time too), `arguments` (every argument
//! RabbitMQ 3.10 knows and what Leveret does with it), `access` (access
//! control: `access::auth` users and SASL, `access::password` password
//! hashes, `access::hash_pool` the bounded threads that check slow hashes,
//! `access::login_backoff` failed logins answered later, and
//! `access::permissions`; not `access::lasting`, above), `parameters`
//! (runtime parameters as the core keeps them), `policy` (policies and
//! operator policies: matching, checking, and RabbitMQ's rules for
//! combining them with arguments), `busy_poll` (polling for input for a
//! short window after socket reads instead of sleeping, shortened under CPU
//! pressure: `busy_poll::cpu_pressure`), `tls`, `error` (reply errors),
//! `slice` (long work in time slices: the stall budget), `stats` (message
//! and churn counters with RabbitMQ's meanings, relaxed atomic adds on the
//! hot path) and `word_hash` (a cheap hasher for small integer keys).
#![forbid(unsafe_code)]
#![deny(missing_docs)]

mod access;
mod admin;
mod admission;
mod alarm;
mod arguments;
#[cfg(feature = "bench-internals")]
#[doc(hidden)]
pub mod bench;
mod busy_poll;
mod channel;
mod connection;
mod consumer;
mod core;
mod embed;
mod error;
#[cfg(feature = "bench-internals")]
#[doc(hidden)]
pub mod exchange;
#[cfg(not(feature = "bench-internals"))]
mod exchange;
mod inspect;
mod limits;
mod message;
#[cfg(feature = "mqtt")]
mod mqtt;
mod outbox;
mod parameters;
mod policy;
mod queue;
mod recovery;
mod registry;
mod server;
mod slice;
mod stats;
pub mod store;
#[cfg(any(test, feature = "bench-internals"))]
#[cfg_attr(not(test), allow(dead_code))] // the benches use a part of it
mod testkit;
#[cfg(feature = "tls")]
mod tls;
mod vhost;
mod word_hash;

pub use crate::access::auth::User;
pub use crate::access::hash_pool::{HashPoolStats, HASH_THREADS};
pub use crate::access::lasting::AccessError;
pub use crate::access::password::{PasswordHash, LEVERET_ARGON2ID, RABBIT_SHA256, RABBIT_SHA512};
pub use crate::access::permissions::{
    check_pattern, PatternError, Permission, TopicPermission, PATTERN_SIZE_LIMIT,
};
pub use crate::admin::as_user::AsUser;
pub use crate::admin::{Admin, BindingSpec, ExchangeSettings, GetMode, GotMessage, QueueSettings};
pub use crate::alarm::disk::{DirFreeSpace, FreeSpace};
pub use crate::alarm::resident::ResidentMemoryWatermark;
pub use crate::arguments::POSITION_HEADER;
pub use crate::arguments::{
    classic_queue_arguments, Argument, Scope as ArgumentScope, Support as ArgumentSupport,
    ARGUMENTS,
};
pub use crate::connection::{
    DirectLink, DirectLoop, DirectReplies, DirectReply, LoopClaim, DIRECT_CAPACITY,
};
pub use crate::core::{Limits, UserLimits, VhostLimits};
pub use crate::limits::UnknownLimit;
pub use crate::outbox::{InlineDeliveries, InlineDelivery};
pub use crate::policy::{
    Applied as AppliedPolicies, ApplyTo, KeySupport as PolicyKeySupport, Policy, PolicyError,
    PolicyKey, PolicyKind, PolicySpec, PolicyValue, POLICY_KEYS,
};
pub use crate::queue::process_nonce;
pub use crate::queue::{start_at as stream_start_at, StartAt as StreamStartAt};
pub use crate::stats::HistogramFigures;
#[cfg(feature = "tls")]
pub use crate::tls::{certificate_expiry, PeerVerification, TlsError, TlsOptions};
pub use embed::{Broker, BrokerBuilder, BrokerHandle, StartError};
pub use error::AmqpError;
pub use inspect::{
    AuthAttemptFigures, BindingInfo, BusyPollFigures, ChannelInfo, ChurnTotals, ConnectionInfo,
    ConsumerInfo, DeadLetteredFigures, DestinationKind, ExchangeInfo, GlobalMessageStats,
    ObjectTotals, Overview, QueueInfo, QueueMessageStats, QueueRef, QueueTotals,
    SocketTrafficFigures, StreamFigures,
};
#[cfg(feature = "mqtt")]
pub use mqtt::RetainedLimits;
#[cfg(feature = "mqtt")]
pub use parameters::{check_global_parameter, CERTIFICATE_MAPPING, PORT_MAPPING};
