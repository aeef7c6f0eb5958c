//! The broker's shared state, independent of sockets: vhosts, users,
//! permissions, limits, the memory gauge, the store handle, the shutdown signal that
//! connections watch, and the server properties connection.start
//! announces. The server and the embedding API build one `Core` and hand
//! an `Arc` of it to every connection and its channels. It uses the vhost
//! layer and below, never a connection.

use crate::access::auth::Users;
use crate::access::permissions::Permissions;
use crate::admission::Admission;
use crate::alarm::memory::MemoryGauge;
use crate::alarm::resident::ResidentMemoryWatermark;
use crate::busy_poll::BusyPoll;
use crate::limits::LimitTables;
pub use crate::limits::{UserLimits, VhostLimits};
use crate::parameters::Parameters;
use crate::registry::Registry;
use crate::stats::BrokerCounters;
use crate::store::Persistence;
use crate::vhost::Vhost;
use leveret_protocol::{FieldTable, FieldValue, ShortStr};
use std::collections::HashMap;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, RwLock};
use std::time::Duration;
use tokio::sync::watch;

/// Limits a broker enforces and offers in connection.tune, with RabbitMQ's
/// names and meanings. Everything a client can make the broker hold is
/// counted against one of them or capped by one.
#[derive(Debug, Clone)]
pub struct Limits {
    /// Most channels open at once on one connection, offered in
    /// connection.tune (RabbitMQ's `channel_max`, default 2047). Opening
    /// one more than the negotiated value closes the connection with 530
    /// NOT_ALLOWED, as RabbitMQ does; channel numbers themselves are not
    /// limited by it.
    pub channel_max: u16,
    /// Largest frame (connection.tune frame-max). Until the client's
    /// connection.tune-ok, frames are limited to the protocol's 4096-byte
    /// minimum.
    pub frame_max: u32,
    /// Heartbeat interval offered, seconds (0 = none).
    pub heartbeat: u16,
    /// Largest message body accepted (RabbitMQ's default: 128 MiB).
    pub max_message_size: u64,
    /// Bytes the broker holds for messages (queued, held by transactions,
    /// being received) above which publishers are blocked. A body is
    /// counted at its announced size from its first body frame, so keep
    /// this well above `max_message_size`: bodies being received that
    /// alone exceed it keep their publishers blocked until other memory
    /// is freed.
    pub memory_high_watermark: usize,
    /// The process's resident memory above which publishers are blocked
    /// too (RabbitMQ's `vm_memory_high_watermark`; read from /proc every
    /// 250 ms where there is one).
    pub resident_memory_high_watermark: ResidentMemoryWatermark,
    /// Free bytes on the data directory's disk below which publishers are
    /// blocked (RabbitMQ's `disk_free_limit`, default 50 MB). Probed every
    /// 10 s, every second near the limit, and at once after a failed
    /// store write; the alarm clears by itself when space returns.
    pub disk_free_limit: u64,
    /// Most TCP connections served at once (RabbitMQ's `connection_max`;
    /// `None`, the default, is no limit). A connection over it is closed
    /// as soon as it is accepted, before anything is read from it, and
    /// logged. In-process connections are not counted.
    pub max_connections: Option<usize>,
    /// How long a client has from connecting to connection.open-ok
    /// (RabbitMQ's `handshake_timeout`, default 10 s); a connection that
    /// has not finished the handshake by then is logged and closed.
    pub handshake_timeout: Duration,
    /// Limits of individual vhosts at start, by vhost name (RabbitMQ's
    /// vhost limits), over those stored; changed at run time through
    /// [`crate::Admin::set_vhost_limits`].
    pub vhost_limits: HashMap<String, VhostLimits>,
    /// Limits of individual users at start, by user name (RabbitMQ's user
    /// limits), over those stored; changed at run time through
    /// [`crate::Admin::set_user_limits`].
    pub user_limits: HashMap<String, UserLimits>,
}

impl Default for Limits {
    fn default() -> Self {
        Limits {
            channel_max: 2047,
            frame_max: 131_072,
            heartbeat: 60,
            max_message_size: 128 * 1024 * 1024,
            memory_high_watermark: 1 << 30,
            resident_memory_high_watermark: ResidentMemoryWatermark::default(),
            disk_free_limit: 50_000_000,
            max_connections: None,
            handshake_timeout: Duration::from_secs(10),
            vhost_limits: HashMap::new(),
            user_limits: HashMap::new(),
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
    /// What each user may do in each vhost.
    pub permissions: Permissions,
    /// Runtime parameters.
    pub parameters: Parameters,
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
    /// What each user may do in each vhost.
    pub permissions: Arc<Permissions>,
    /// Runtime parameters (`parameters`).
    pub parameters: Parameters,
    /// Limits.
    pub limits: Limits,
    /// The vhost and user limits in effect (`limits`).
    pub limit_tables: LimitTables,
    /// The memory alarm and the bytes it counts.
    pub gauge: Arc<MemoryGauge>,
    /// Durable storage, if the broker has any.
    pub persistence: Option<Arc<Persistence>>,
    /// connection.start's server-properties, built once.
    pub server_properties: FieldTable,
    /// The busy-poll window's shared state, if the broker busy-polls.
    pub busy_poll: Option<Arc<BusyPoll>>,
    /// Message and churn counters (`stats`).
    pub stats: Arc<BrokerCounters>,
    /// Open connections and channels (`registry`).
    pub registry: Arc<Registry>,
    /// The product name announced to clients.
    pub product: String,
    /// When the broker started.
    pub started: std::time::Instant,
    /// Connections counted against `max_connections` and vhost limits.
    pub connections: Arc<Admission>,
    /// Taken by each run-time change to users, vhosts and permissions
    /// from its check through its write to disk to its taking effect
    /// (`access`), so the store and memory see them in one order.
    pub access_changes: tokio::sync::Mutex<()>,
    next_connection: AtomicU64,
    shutdown: watch::Sender<bool>,
}

impl Core {
    /// A core as `options` say.
    pub fn new(options: CoreOptions) -> Arc<Self> {
        let CoreOptions {
            vhosts,
            users,
            permissions,
            parameters,
            limits,
            persistence,
            product,
            busy_poll,
        } = options;
        let gauge = Arc::new(MemoryGauge::new(limits.memory_high_watermark));
        let stats = Arc::new(BrokerCounters::default());
        let connections = Admission::new(limits.max_connections);
        let vhosts = vhosts
            .iter()
            .filter_map(|name| ShortStr::try_from(name.as_str()).ok())
            .map(|name| {
                let vhost = Vhost::new(
                    name.clone(),
                    Arc::clone(&gauge),
                    persistence.clone(),
                    Arc::clone(&stats),
                );
                (name, vhost)
            })
            .collect();
        let limit_tables =
            LimitTables::at_start(&parameters, &limits.vhost_limits, &limits.user_limits);
        Arc::new(Core {
            vhosts: RwLock::new(vhosts),
            users,
            permissions: Arc::new(permissions),
            parameters,
            limits,
            limit_tables,
            gauge,
            persistence,
            server_properties: server_properties(&product),
            busy_poll,
            registry: Arc::new(Registry::new(Arc::clone(&stats))),
            stats,
            product: product.to_owned(),
            started: std::time::Instant::now(),
            connections,
            access_changes: tokio::sync::Mutex::new(()),
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
                Arc::clone(&self.stats),
            )
        });
        Arc::clone(vhost)
    }

    /// Takes the vhost with this name away, marked deleted (so nothing
    /// can be declared in it any more), for [`crate::admin::Admin`] to
    /// empty; `None` if there is none.
    pub fn remove_vhost(&self, name: &ShortStr) -> Option<Arc<Vhost>> {
        let mut vhosts = self.vhosts.write().unwrap_or_else(|e| e.into_inner());
        let vhost = vhosts.remove(name)?;
        vhost.mark_deleted();
        Some(vhost)
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
        self.registry.close_all();
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
