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
//! # Layout
//! - `embed`: the builder and handle, the public entry point.
//! - `server`: TCP listeners, the accept loop, the TTL/expiry sweeper.
//! - `busy_poll`: polling for input for a short, adaptive window after socket reads instead of sleeping.
//! - `connection`: handshake, the reader loop, heartbeats, closing; `connection::writer` owns the socket's write half.
//! - `channel`: content assembly and one module per AMQP class (`basic`, `queue`, `exchange`, `tx`).
//! - `core`: state shared by all connections (vhosts, users, limits, memory gauge, shutdown).
//! - `vhost`: exchanges and queues of a vhost, declare/delete/bind, routing.
//! - `exchange`: exchange kinds and bindings (`topic` trie, `headers` match).
//! - `queue`: FIFO, consumers, round-robin dispatch, TTL, max-length, dead-lettering (`deadletter`).
//! - `consumer`: consumers, delivery tags, unacked bookkeeping, prefetch credit.
//! - `outbox`: what the core sends to a connection's writer, with backpressure.
//! - `message`, `memory`, `auth`, `error`: messages, the memory alarm, users and SASL, reply errors.
//! - `stats`: message and churn counters with RabbitMQ's meanings (relaxed atomic adds on the hot path).
//! - `registry`: open connections and channels, for listing and for closing one from outside.
//! - `admin`: [`Admin`], a cloneable handle for tools: closing connections, and (`inspect`) reading
//!   all of the above into plain structs with RabbitMQ's field meanings (`BrokerHandle::overview`).
#![forbid(unsafe_code)]

mod admin;
mod auth;
mod busy_poll;
mod channel;
mod connection;
mod consumer;
mod core;
mod deadletter;
mod embed;
mod error;
mod exchange;
mod inspect;
mod memory;
mod message;
mod outbox;
mod queue;
mod recovery;
mod registry;
mod server;
mod stats;
pub mod store;
mod vhost;

pub use crate::admin::{Admin, BindingSpec, ExchangeSettings, GetMode, GotMessage, QueueSettings};
pub use crate::auth::PasswordHash;
pub use crate::core::Limits;
pub use embed::{Broker, BrokerBuilder, BrokerHandle, StartError};
pub use error::AmqpError;
pub use inspect::{
    BindingInfo, BusyPollFigures, ChannelInfo, ChurnTotals, ConnectionInfo, ConsumerInfo,
    DestinationKind, ExchangeInfo, GlobalMessageStats, ObjectTotals, Overview, QueueInfo,
    QueueMessageStats, QueueRef, QueueTotals,
};
