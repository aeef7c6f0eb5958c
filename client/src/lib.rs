//! # leveret-client
//!
//! A thin async AMQP 0.9.1 client on `leveret-protocol` and tokio, for
//! Leveret or any AMQP 0.9.1 broker (RabbitMQ's extensions included:
//! publisher confirms, consumer cancel notification, `connection.blocked`,
//! `basic.nack`, exchange-to-exchange bindings).
//!
//! ```no_run
//! use bytes::Bytes;
//! use leveret_client::{
//!     BasicConsumeOptions, BasicProperties, BasicPublishOptions, Connection, FieldTable,
//!     QueueDeclareOptions,
//! };
//!
//! # async fn demo() -> leveret_client::Result<()> {
//! let connection = Connection::connect("amqp://guest:guest@localhost:5672/%2f").await?;
//! let channel = connection.open_channel().await?;
//! let queue = channel
//!     .queue_declare("tasks", QueueDeclareOptions::default(), FieldTable::new())
//!     .await?;
//! channel.confirm_select().await?;
//! let confirm = channel
//!     .basic_publish("", "tasks", BasicPublishOptions::default(), BasicProperties::default(), Bytes::from_static(b"hi"))
//!     .await?;
//! assert!(confirm.await?.is_ack());
//! let mut consumer = channel
//!     .basic_consume(&queue.name, "", BasicConsumeOptions::default(), FieldTable::new())
//!     .await?;
//! while let Some(delivery) = consumer.next().await {
//!     delivery.ack().await?;
//! }
//! connection.close().await
//! # }
//! ```
//!
//! # Transports
//! [`Connection::connect`] opens TCP. With the `embedded` feature,
//! `Connection::in_process` connects to a Leveret broker running in the
//! same process (`leveret_broker::BrokerHandle`): frames cross as values
//! (`BrokerHandle::connect_direct`), so neither side encodes or parses
//! them, and the broker serves the link with the same connection code as
//! a socket; on this side too everything after opening the link
//! (handshake, reader, writer, channels) is the same code. One shortcut:
//! the broker hands an in-process connection's deliveries to their
//! consumer, and its publisher confirms to the channel, on the thread that
//! dispatches or settles them, whenever the reader has nothing before them
//! ([`Connection::inline_deliveries`] and [`Connection::inline_confirms`]
//! count them).
//!
//! # Features
//! `tls` (default): `amqps://` with rustls and the system's CA
//! certificates. `embedded`: `Connection::in_process`; it takes
//! `leveret-broker` without its default features (TLS, persistence, MQTT,
//! regex), which the application enables on its own `leveret-broker`
//! dependency if it wants them. A TCP-only client without TLS is 30
//! crates, with it 46.
//!
//! # Design
//! Each connection has two tasks that own the transport. The reader decodes
//! frames (bodies stay slices of its read buffer) and routes them per
//! channel: replies to the waiting call, deliveries to their consumer's
//! bounded buffer, returns, confirms. The writer drains a bounded outbox,
//! encoding everything waiting into one reused buffer per write. Callers
//! wait for room in the outbox, so nothing grows without bound.
//!
//! # Layout
//! - [`uri`]: [`ConnectionOptions`] and `amqp://` URI parsing.
//! - `connection`: [`Connection`], its transports (TCP, in-process), the
//!   handshake, the reader and writer tasks.
//! - `channel`: [`Channel`], [`OutboxSlot`] and the per-channel state the
//!   reader drives.
//! - `consumer`: [`Consumer`] and [`Returns`] streams, [`DeliverySink`].
//! - `confirm`: publisher confirms ([`PublishConfirm`], [`Confirmation`]).
//! - `message`: [`Delivery`], [`GetMessage`], [`ReturnedMessage`], [`IntoShortStr`].
//! - `options`: the `…Options` structs of the channel methods.
//! - `error`: [`Error`] and [`CloseReason`].
//! - `dedupe`: [`Dedupe`], dropping the duplicates at-least-once
//!   forwarding (the uplink's shovels) can produce.
//!
//! Typed robot data ports (OpenRTM-aist style out-ports and in-ports) are
//! the `leveret-ports` crate, built on this crate's public API.
#![deny(missing_docs)]
#![forbid(unsafe_code)]

mod channel;
mod confirm;
mod connection;
mod consumer;
mod dedupe;
mod error;
mod message;
mod options;
pub mod uri;

pub use channel::{Channel, OutboxSlot, QueueInfo};
pub use confirm::{ConfirmFuture, Confirmation, PublishConfirm};
pub use connection::{Connection, Tuning};
pub use consumer::{
    Consumer, ConsumerEnd, DeliverySink, Returns, DEFAULT_CONSUMER_BUFFER, RETURNS_BUFFER,
};
pub use dedupe::{identity, Dedupe};
pub use error::{CloseReason, Error, Result};
pub use message::{Delivery, GetMessage, IntoShortStr, ReturnedMessage};
pub use options::*;
pub use uri::ConnectionOptions;

pub use leveret_protocol as protocol;

pub use leveret_protocol::{BasicProperties, FieldTable, FieldValue, ReplyCode, ShortStr};
