//! The broker's shared state, independent of sockets: vhosts, users,
//! limits, the memory gauge, the store handle, the shutdown signal that
//! connections watch, and the server properties connection.start
//! announces. The server and the embedding API build one `Core` and hand
//! an `Arc` of it to every connection and its channels. It uses the vhost
//! layer and below, never a connection.

use crate::auth::Users;
use crate::busy_poll::BusyPoll;
use crate::memory::MemoryGauge;
use crate::store::Persistence;
use crate::vhost::Vhost;
use leveret_protocol::{FieldTable, FieldValue, ShortStr};
use std::collections::HashMap;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, RwLock};
use tokio::sync::watch;

/// Limits a broker enforces and offers in connection.tune.
#[derive(Debug, Clone)]
pub struct Limits {
    /// Highest channel number (connection.tune channel-max).
    pub channel_max: u16,
    /// Largest frame (connection.tune frame-max).
    pub frame_max: u32,
    /// Heartbeat interval offered, seconds (0 = none).
    pub heartbeat: u16,
    /// Largest message body accepted (RabbitMQ's default: 128 MiB).
    pub max_message_size: u64,
    /// Queued-message bytes above which publishers are blocked.
    pub memory_high_watermark: usize,
}

impl Default for Limits {
    fn default() -> Self {
        Limits {
            channel_max: 2047,
            frame_max: 131_072,
            heartbeat: 60,
            max_message_size: 128 * 1024 * 1024,
            memory_high_watermark: 1 << 30,
        }
    }
}

/// What a [`Core`] is built from.
#[derive(Debug)]
pub struct CoreOptions {
    /// The vhosts to create (names that are not valid short strings are
    /// skipped).
    pub vhosts: Vec<String>,
    /// Accepted users.
    pub users: Users,
    /// Limits.
    pub limits: Limits,
    /// Durable storage, if the broker has any.
    pub persistence: Option<Arc<Persistence>>,
    /// The product name announced in connection.start.
    pub product: String,
    /// The busy-poll window's shared state, if the broker busy-polls.
    pub busy_poll: Option<Arc<BusyPoll>>,
}

/// State shared by every connection of one broker.
#[derive(Debug)]
pub struct Core {
    vhosts: RwLock<HashMap<ShortStr, Arc<Vhost>>>,
    /// Accepted users.
    pub users: Users,
    /// Limits.
    pub limits: Limits,
    /// Memory held by queued messages.
    pub gauge: Arc<MemoryGauge>,
    /// Durable storage, if the broker has any.
    pub persistence: Option<Arc<Persistence>>,
    /// connection.start's server-properties, built once.
    pub server_properties: FieldTable,
    /// The busy-poll window's shared state, if the broker busy-polls.
    pub busy_poll: Option<Arc<BusyPoll>>,
    next_connection: AtomicU64,
    shutdown: watch::Sender<bool>,
}

impl Core {
    /// A core as `options` say.
    pub fn new(options: CoreOptions) -> Arc<Self> {
        let CoreOptions {
            vhosts,
            users,
            limits,
            persistence,
            product,
            busy_poll,
        } = options;
        let gauge = Arc::new(MemoryGauge::new(limits.memory_high_watermark));
        let vhosts = vhosts
            .iter()
            .filter_map(|name| ShortStr::try_from(name.as_str()).ok())
            .map(|name| {
                let vhost = Vhost::new(name.clone(), Arc::clone(&gauge), persistence.clone());
                (name, vhost)
            })
            .collect();
        Arc::new(Core {
            vhosts: RwLock::new(vhosts),
            users,
            limits,
            gauge,
            persistence,
            server_properties: server_properties(&product),
            busy_poll,
            next_connection: AtomicU64::new(1),
            shutdown: watch::channel(false).0,
        })
    }

    /// The vhost with this name.
    pub fn vhost(&self, name: &ShortStr) -> Option<Arc<Vhost>> {
        self.vhosts
            .read()
            .unwrap_or_else(|e| e.into_inner())
            .get(name)
            .cloned()
    }

    /// The vhost with this name, created if missing (stored definitions
    /// name the vhosts they belong to).
    pub fn vhost_or_create(&self, name: &ShortStr) -> Arc<Vhost> {
        let mut vhosts = self.vhosts.write().unwrap_or_else(|e| e.into_inner());
        let vhost = vhosts.entry(name.clone()).or_insert_with(|| {
            Vhost::new(
                name.clone(),
                Arc::clone(&self.gauge),
                self.persistence.clone(),
            )
        });
        Arc::clone(vhost)
    }

    /// Every vhost.
    pub fn vhosts(&self) -> Vec<Arc<Vhost>> {
        self.vhosts
            .read()
            .unwrap_or_else(|e| e.into_inner())
            .values()
            .cloned()
            .collect()
    }

    /// A fresh connection id.
    pub fn next_connection_id(&self) -> u64 {
        self.next_connection.fetch_add(1, Ordering::Relaxed)
    }

    /// Tells every connection to close with 320 CONNECTION_FORCED.
    pub fn begin_shutdown(&self) {
        self.shutdown.send_replace(true);
    }

    /// A receiver that turns true when the broker shuts down.
    pub fn shutdown_signal(&self) -> watch::Receiver<bool> {
        self.shutdown.subscribe()
    }
}

/// What connection.start announces: `product` (the builder's, "Leveret"
/// by default), version, platform and RabbitMQ's capability flags.
fn server_properties(product: &str) -> FieldTable {
    let text = |s: &str| FieldValue::string(s);
    let capabilities: FieldTable = [
        "publisher_confirms",
        "exchange_exchange_bindings",
        "basic.nack",
        "consumer_cancel_notify",
        "connection.blocked",
        "authentication_failure_close",
        "per_consumer_qos",
    ]
    .into_iter()
    .map(|c| {
        (
            ShortStr::try_from(c).unwrap_or_default(),
            FieldValue::Bool(true),
        )
    })
    .collect();
    [
        (ShortStr::from_static("product"), text(product)),
        (
            ShortStr::from_static("version"),
            text(env!("CARGO_PKG_VERSION")),
        ),
        (ShortStr::from_static("platform"), text("Rust")),
        (
            ShortStr::from_static("information"),
            text("An embeddable AMQP 0.9.1 broker"),
        ),
        (
            ShortStr::from_static("capabilities"),
            FieldValue::Table(capabilities),
        ),
    ]
    .into_iter()
    .collect()
}
