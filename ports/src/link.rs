//! What both kinds of port share about their link to the broker: its
//! [`LinkStatus`] (published through a `watch`), declaring the profile's
//! topology (and an out-port's recording stream) on every new connection,
//! and the message headers that carry a
//! port's identity, sequence number and send time.

use super::profile::PortProfile;
use leveret_client::Result;
use leveret_client::{
    Channel, ExchangeDeclareOptions, FieldTable, FieldValue, QueueBindOptions, QueueDeclareOptions,
    ShortStr,
};
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::{SystemTime, UNIX_EPOCH};
use tokio::sync::watch;

/// Header with the out-port's sequence number (a long-long, from 1).
pub const SEQ_HEADER: &str = "x-seq";
/// Header with the time of `put`, nanoseconds since the Unix epoch (a
/// long-long).
pub const SENT_HEADER: &str = "x-sent-ns";
/// Header naming the out-port instance (a long string), so an in-port
/// keeps one sequence per sender and a restarted sender starts afresh.
pub const PORT_HEADER: &str = "x-port";

/// The state of a port's link to the broker, in a word.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum LinkState {
    /// Not connected (connecting, or waiting to retry).
    Down,
    /// Connected, and the broker keeps up.
    Up,
    /// Connected, but the broker has stopped confirming (see
    /// [`LinkStatus::degraded`]).
    Degraded,
}

impl LinkState {
    /// `down`, `up` or `degraded`.
    pub fn as_str(self) -> &'static str {
        match self {
            LinkState::Down => "down",
            LinkState::Up => "up",
            LinkState::Degraded => "degraded",
        }
    }
}

/// The state of a port's link to the broker.
#[derive(Debug, Clone, PartialEq, Eq, Default)]
pub struct LinkStatus {
    /// Connected, topology declared (and, for an in-port, consuming).
    pub up: bool,
    /// Up, but stalled: the broker has confirmed (or, without confirms,
    /// taken) nothing of an out-port's for longer than the profile's
    /// stall timeout ([`super::PortProfile::stall_timeout`]), as when it
    /// is frozen. Cleared when it confirms again or the link drops.
    pub degraded: bool,
    /// Links established so far (1 after the first connect).
    pub connects: u64,
    /// Links lost so far.
    pub losses: u64,
    /// Why the last link ended or the last attempt failed.
    pub last_error: Option<String>,
}

impl LinkStatus {
    /// The link's state in a word.
    pub fn state(&self) -> LinkState {
        match (self.up, self.degraded) {
            (false, _) => LinkState::Down,
            (true, false) => LinkState::Up,
            (true, true) => LinkState::Degraded,
        }
    }
}

/// The sending side of a port's [`LinkStatus`].
#[derive(Debug)]
pub(crate) struct Link(watch::Sender<LinkStatus>);

impl Link {
    pub(crate) fn new() -> Self {
        Link(watch::Sender::new(LinkStatus::default()))
    }

    pub(crate) fn subscribe(&self) -> watch::Receiver<LinkStatus> {
        self.0.subscribe()
    }

    pub(crate) fn connected(&self) {
        self.0.send_modify(|s| {
            s.up = true;
            s.connects += 1;
        });
    }

    pub(crate) fn lost(&self, error: &leveret_client::Error) {
        tracing::debug!(%error, "port link lost");
        self.0.send_modify(|s| {
            if s.up {
                s.losses += 1;
            }
            s.up = false;
            s.degraded = false;
            s.last_error = Some(error.to_string());
        });
    }

    pub(crate) fn degraded(&self, degraded: bool) {
        if degraded {
            tracing::debug!("port link stalled");
        }
        self.0.send_modify(|s| s.degraded = degraded && s.up);
    }

    pub(crate) fn failed(&self, error: &leveret_client::Error) {
        tracing::debug!(%error, "port reconnection attempt failed");
        self.0
            .send_modify(|s| s.last_error = Some(error.to_string()));
    }
}

/// Nanoseconds since the Unix epoch, now.
pub(crate) fn now_ns() -> i64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map(|d| i64::try_from(d.as_nanos()).unwrap_or(i64::MAX))
        .unwrap_or(0)
}

/// A name for one out-port instance, unique in practice across processes
/// and restarts.
pub(crate) fn port_id() -> String {
    static COUNTER: AtomicU64 = AtomicU64::new(0);
    format!(
        "{:x}.{:x}.{}",
        std::process::id(),
        now_ns(),
        COUNTER.fetch_add(1, Ordering::Relaxed)
    )
}

/// Declares the profile's exchange, unless it is the default exchange or
/// a predeclared `amq.` one.
pub(crate) async fn declare_exchange(channel: &Channel, profile: &PortProfile) -> Result<()> {
    if profile.exchange.is_empty() || profile.exchange.starts_with("amq.") {
        return Ok(());
    }
    let options = ExchangeDeclareOptions {
        durable: profile.durable,
        ..Default::default()
    };
    channel
        .exchange_declare(
            profile.exchange.as_str(),
            profile.exchange_kind.as_str(),
            options,
            FieldTable::new(),
        )
        .await
}

/// Declares the queue `name` (the profile's, or an in-port's own) and,
/// with `bind`, binds it to the profile's exchange. A port's own queue (`own`) is not
/// exclusive, so it outlives the port's reconnections, and expires once
/// unused for the profile's `queue_expires` (unless the profile's queue
/// arguments say otherwise).
pub(crate) async fn declare_queue(
    channel: &Channel,
    profile: &PortProfile,
    name: &str,
    own: bool,
    bind: bool,
) -> Result<ShortStr> {
    let options = QueueDeclareOptions {
        durable: profile.durable && !own,
        ..Default::default()
    };
    let mut arguments = profile.queue_arguments.clone();
    if own && arguments.get("x-expires").is_none() {
        let expires = i64::try_from(profile.queue_expires.as_millis().max(1)).unwrap_or(i64::MAX);
        arguments.insert(ShortStr::from_static("x-expires"), FieldValue::I64(expires));
    }
    let queue = channel.queue_declare(name, options, arguments).await?;
    if bind && !profile.exchange.is_empty() {
        channel
            .queue_bind(
                &queue.name,
                profile.exchange.as_str(),
                profile.binding_key.as_str(),
                QueueBindOptions::default(),
                FieldTable::new(),
            )
            .await?;
    }
    Ok(queue.name)
}

/// Declares the profile's recording stream, if it has one, and binds it
/// to the profile's exchange with its routing key (a fanout exchange
/// ignores the key): one more queue the port's messages are routed to.
pub(crate) async fn declare_recording(channel: &Channel, profile: &PortProfile) -> Result<()> {
    match &profile.record {
        Some(recording) => {
            recording
                .declare(channel, &profile.exchange, &profile.routing_key)
                .await
        }
        None => Ok(()),
    }
}

/// The headers of one published message.
pub(crate) fn headers(port: &str, seq: u64, sent_ns: i64) -> FieldTable {
    let mut headers = FieldTable::new();
    headers.insert(
        ShortStr::from_static(SEQ_HEADER),
        FieldValue::I64(i64::try_from(seq).unwrap_or(i64::MAX)),
    );
    headers.insert(ShortStr::from_static(SENT_HEADER), FieldValue::I64(sent_ns));
    headers.insert(ShortStr::from_static(PORT_HEADER), FieldValue::string(port));
    headers
}

/// What an in-port reads back from a message's headers.
#[derive(Debug, Clone, Default)]
pub(crate) struct Stamp {
    pub(crate) port: Option<String>,
    pub(crate) seq: Option<u64>,
    pub(crate) sent_ns: Option<i64>,
}

impl Stamp {
    pub(crate) fn read(headers: Option<&FieldTable>) -> Self {
        let Some(headers) = headers else {
            return Stamp::default();
        };
        Stamp {
            port: headers
                .get(PORT_HEADER)
                .and_then(FieldValue::as_bytes)
                .map(|b| String::from_utf8_lossy(b).into_owned()),
            seq: headers
                .get(SEQ_HEADER)
                .and_then(FieldValue::as_i64)
                .and_then(|s| u64::try_from(s).ok()),
            sent_ns: headers.get(SENT_HEADER).and_then(FieldValue::as_i64),
        }
    }
}
