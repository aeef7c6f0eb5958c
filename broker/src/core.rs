//! The broker's shared state, independent of sockets: vhosts, users,
//! limits, the memory gauge, and the shutdown signal that connections
//! watch. The server and the embedding API build one `Core` and hand an
//! `Arc` of it to every connection.

use crate::auth::Users;
use crate::busy_poll::BusyPoll;
use crate::memory::MemoryGauge;
use crate::registry::Registry;
use crate::stats::BrokerCounters;
use crate::store::Persistence;
use crate::vhost::Vhost;
use leveret_protocol::{FieldTable, ShortStr};
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
    /// Message and churn counters (`stats`).
    pub stats: Arc<BrokerCounters>,
    /// Open connections and channels (`registry`).
    pub registry: Arc<Registry>,
    /// The product name announced to clients.
    pub product: String,
    /// When the broker started.
    pub started: std::time::Instant,
    next_connection: AtomicU64,
    shutdown: watch::Sender<bool>,
}

impl Core {
    /// A core with the given vhosts, users, limits, storage and the
    /// `product` name it announces to clients.
    pub fn new(
        vhost_names: &[String],
        users: Users,
        limits: Limits,
        persistence: Option<Arc<Persistence>>,
        product: &str,
        busy_poll: Option<Arc<BusyPoll>>,
    ) -> Arc<Self> {
        let gauge = Arc::new(MemoryGauge::new(limits.memory_high_watermark));
        let stats = Arc::new(BrokerCounters::default());
        let vhosts = vhost_names
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
        Arc::new(Core {
            vhosts: RwLock::new(vhosts),
            users,
            limits,
            gauge,
            persistence,
            server_properties: crate::connection::server_properties(product),
            busy_poll,
            registry: Arc::new(Registry::new(Arc::clone(&stats))),
            stats,
            product: product.to_owned(),
            started: std::time::Instant::now(),
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
