//! The running broker, [`BrokerHandle`]: the addresses its listeners
//! got, opening held listeners, reloading TLS files, in-process
//! connections (a byte pipe, or frames as values), the [`Admin`] view of
//! its state, and shutdown: every connection closed with 320
//! CONNECTION_FORCED, waited for, the store synced and, for a data
//! directory, a clean shutdown recorded. `start` makes it; it uses the
//! core, `connection` (for in-process clients), `admin` and the store.

use crate::admin::Admin;
use crate::core::Core;
use crate::inspect::{Overview, QueueInfo};
#[cfg(feature = "persistence")]
use crate::store::{mark_clean, StoreError, StoreOp};
#[cfg(feature = "tls")]
use crate::tls::{TlsContext, TlsError};
use std::net::SocketAddr;
#[cfg(feature = "persistence")]
use std::path::PathBuf;
use std::sync::Arc;
use std::time::Duration;
use tokio::sync::{mpsc, watch};

/// Bytes buffered each way in an in-process connection's pipe.
const IN_PROCESS_BUFFER: usize = 256 * 1024;
/// How long shutdown waits for connections to close.
const SHUTDOWN_GRACE: Duration = Duration::from_secs(5);

/// A running broker.
pub struct BrokerHandle {
    pub(super) core: Arc<Core>,
    /// Says the held listeners may accept.
    pub(super) open: watch::Sender<bool>,
    pub(super) local_addrs: Vec<SocketAddr>,
    pub(super) tls_addrs: Vec<SocketAddr>,
    /// The MQTT listeners': TCP, TLS, WebSocket.
    pub(super) mqtt_addrs: [Vec<SocketAddr>; 3],
    #[cfg(feature = "tls")]
    pub(super) tls: Option<Arc<TlsContext>>,
    pub(super) tasks: Vec<tokio::task::JoinHandle<()>>,
    pub(super) alive: Option<mpsc::Sender<()>>,
    pub(super) finished: mpsc::Receiver<()>,
    /// For a store in a data directory: what a clean shutdown records.
    #[cfg(feature = "persistence")]
    pub(super) clean_shutdown: Option<CleanShutdown>,
}

/// Where and with which generation a clean shutdown is recorded.
#[cfg(feature = "persistence")]
#[derive(Debug)]
pub(super) struct CleanShutdown {
    pub(super) dir: PathBuf,
    pub(super) generation: u64,
}

impl BrokerHandle {
    /// Lets the listeners [`BrokerBuilder::hold_listeners`] held accept
    /// clients (a no-op when they already do).
    ///
    /// [`BrokerBuilder::hold_listeners`]: super::BrokerBuilder::hold_listeners
    pub fn open_listeners(&self) {
        self.open.send_replace(true);
    }

    /// The addresses the plaintext listeners are bound to.
    pub fn local_addrs(&self) -> &[SocketAddr] {
        &self.local_addrs
    }

    /// The addresses the TLS listeners are bound to (none without the
    /// `tls` feature).
    pub fn tls_addrs(&self) -> &[SocketAddr] {
        &self.tls_addrs
    }

    /// The addresses the MQTT listeners are bound to (none without the
    /// `mqtt` feature).
    pub fn mqtt_addrs(&self) -> &[SocketAddr] {
        &self.mqtt_addrs[0]
    }

    /// The addresses the MQTT over TLS listeners are bound to.
    pub fn mqtts_addrs(&self) -> &[SocketAddr] {
        &self.mqtt_addrs[1]
    }

    /// The addresses the MQTT over WebSocket listeners are bound to.
    pub fn web_mqtt_addrs(&self) -> &[SocketAddr] {
        &self.mqtt_addrs[2]
    }

    #[cfg(feature = "tls")]
    /// Re-reads the TLS certificate, key and CA bundle: connections
    /// accepted from now on use them, open ones keep theirs. On an error
    /// the files in use before stay in use.
    pub fn reload_tls(&self) -> Result<(), TlsError> {
        match &self.tls {
            Some(tls) => tls.reload(),
            None => Err(TlsError::NoOptions),
        }
    }

    /// Opens an in-process connection: the returned stream is the client's
    /// end of an in-memory pipe whose other end the broker serves exactly
    /// like a TCP socket (same protocol, no network, no TCP stack). Works
    /// with or without listeners.
    pub fn connect_in_process(&self) -> tokio::io::DuplexStream {
        let (client, server) = tokio::io::duplex(IN_PROCESS_BUFFER);
        let (read, write) = tokio::io::split(server);
        let core = Arc::clone(&self.core);
        let slot = core.connections.admit_local();
        let alive = self.alive.clone();
        let identity = crate::connection::Identity::None;
        let ends = ("in-process".to_owned(), None);
        let connection = crate::connection::serve(core, read, write, ends, slot, identity, alive);
        tokio::spawn(connection);
        client
    }

    /// Opens an in-process connection that exchanges AMQP frames as values
    /// (the fast path `leveret-client` takes with its `embedded` feature):
    /// no bytes are encoded or parsed and no writer task runs, while the
    /// handshake, permissions, routing, queues, acks, limits and
    /// statistics are those of every other connection. For a client with a
    /// codec of its own, [`BrokerHandle::connect_in_process`] is the byte
    /// pipe. Works with or without listeners.
    pub fn connect_direct(&self) -> crate::connection::DirectLink {
        let core = Arc::clone(&self.core);
        let slot = core.connections.admit_local();
        let peer = "in-process".to_owned();
        let connection_id = core.next_connection_id();
        crate::connection::serve_direct(
            core,
            connection_id,
            slot,
            (peer, crate::connection::Identity::None),
            (crate::connection::AMQP_0_9_1, None),
            self.alive.clone(),
        )
    }

    /// A cloneable view of this broker's state, for readers that outlive
    /// a borrow of the handle (the `leveret` binary's HTTP listeners).
    pub fn admin(&self) -> Admin {
        Admin {
            core: Arc::clone(&self.core),
        }
    }

    /// Broker-wide figures with RabbitMQ's meanings: object and message
    /// totals, message counters, churn. Reads every queue once.
    pub fn overview(&self) -> Overview {
        self.admin().overview()
    }

    /// Every queue's depth, consumers and counters, sorted by vhost and
    /// name: a robot application reads queue depth here without HTTP.
    pub fn queues(&self) -> Vec<QueueInfo> {
        self.admin().queues()
    }

    /// Closes every connection with 320 CONNECTION_FORCED and stops.
    pub async fn shutdown(mut self) {
        self.core.begin_shutdown();
        for task in self.tasks.drain(..) {
            let _ = task.await;
        }
        self.alive = None;
        // Resolves once every connection task has dropped its sender.
        let _ = tokio::time::timeout(SHUTDOWN_GRACE, self.finished.recv()).await;
        if let Some(persistence) = &self.core.persistence {
            if !persistence.sync().await {
                tracing::error!("the last writes to storage failed at shutdown");
            }
            #[cfg(not(feature = "persistence"))]
            persistence.close(Vec::new()).await;
            // The marker is the store's last write; the manifest says
            // `clean` only once it is on disk.
            #[cfg(feature = "persistence")]
            {
                let marker = self
                    .clean_shutdown
                    .as_ref()
                    .map(|clean| StoreOp::CleanShutdown {
                        generation: clean.generation,
                    });
                let marked = persistence.close(marker.into_iter().collect()).await;
                if let Some(clean) = &self.clean_shutdown {
                    let recorded = if marked {
                        mark_clean(&clean.dir, clean.generation)
                    } else {
                        Err(StoreError::Engine("the marker could not be written".into()))
                    };
                    if let Err(e) = recorded {
                        tracing::error!(error = %e, "could not record a clean shutdown");
                    }
                }
            }
        }
    }
}

impl Drop for BrokerHandle {
    fn drop(&mut self) {
        self.core.begin_shutdown();
    }
}
