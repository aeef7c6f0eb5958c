//! The operators' listeners (Prometheus metrics, the management API) on a
//! thread of their own with its own current-thread tokio runtime: nothing
//! they do runs on the broker's thread, so a scrape or a listing of many
//! queues never delays AMQP traffic. They reach the broker only through
//! its [`Admin`] handle, whose reads take each broker lock for a few
//! instructions at a time. The sockets are bound before the thread starts,
//! so a busy port stops the binary at start with a clear error.

use crate::management::Rates;
use crate::metrics::MetricsContext;
use crate::uplink::Links;
use leveret_broker::Admin;
use std::net::SocketAddr;
use std::path::PathBuf;
use tokio::sync::watch;

/// Where the listeners go.
#[derive(Debug, Clone)]
pub struct OpsSettings {
    /// The Prometheus endpoint.
    pub metrics_listen: SocketAddr,
    /// The management API.
    pub http_listen: SocketAddr,
    /// Where the broker keeps its data (disk space is measured there).
    pub data_dir: PathBuf,
    /// The TLS listeners' certificate files, for the health check.
    pub tls: Option<leveret_broker::TlsOptions>,
    /// The effective configuration, for `/api/environment`.
    pub environment: serde_json::Value,
}

/// The running listeners.
#[derive(Debug)]
pub struct Ops {
    /// Every listener of the process by RabbitMQ's protocol name, as
    /// `/api/overview` lists them (the management API's is `http`, the
    /// Prometheus endpoint's `http/prometheus`).
    pub listeners: Vec<(&'static str, SocketAddr)>,
    stop: watch::Sender<bool>,
    thread: std::thread::JoinHandle<()>,
}

/// Why the listeners could not start.
#[derive(Debug, thiserror::Error)]
pub enum OpsError {
    /// A port could not be bound.
    #[error("cannot listen on {addr}: {source}")]
    Bind {
        /// The address.
        addr: SocketAddr,
        /// The error.
        source: std::io::Error,
    },
    /// The thread or its runtime could not start.
    #[error("cannot start the listeners' thread: {0}")]
    Thread(std::io::Error),
}

/// Connections the kernel queues for accept per listener: more than the
/// sockets a flood holds (`crate::http`), so an operator's connection is
/// queued rather than dropped while the flood is being shed. std binds
/// with 128; Linux takes a second `listen` as the new length (capped by
/// `net.core.somaxconn`).
const BACKLOG: i32 = 4096;

fn bind(addr: SocketAddr) -> Result<std::net::TcpListener, OpsError> {
    let bound = std::net::TcpListener::bind(addr).and_then(|listener| {
        rustix::net::listen(&listener, BACKLOG)?;
        listener.set_nonblocking(true).map(|()| listener)
    });
    bound.map_err(|source| OpsError::Bind { addr, source })
}

fn bound_addr(listener: &std::net::TcpListener, asked: SocketAddr) -> Result<SocketAddr, OpsError> {
    listener.local_addr().map_err(|source| OpsError::Bind {
        addr: asked,
        source,
    })
}

impl Ops {
    /// Binds the listeners and serves them on their own thread;
    /// `amqp_listeners` and `other_listeners` (by RabbitMQ's protocol
    /// name) are reported in `/api/overview` and the health checks.
    pub fn start(
        admin: Admin,
        links: Links,
        amqp_listeners: &[SocketAddr],
        other_listeners: Vec<(&'static str, SocketAddr)>,
        settings: OpsSettings,
    ) -> Result<Ops, OpsError> {
        let metrics = bind(settings.metrics_listen)?;
        let metrics_addr = bound_addr(&metrics, settings.metrics_listen)?;
        let http = bind(settings.http_listen)?;
        let http_addr = bound_addr(&http, settings.http_listen)?;
        let runtime = tokio::runtime::Builder::new_current_thread()
            .enable_all()
            .build()
            .map_err(OpsError::Thread)?;
        let node = crate::process::node_name();
        let listeners: Vec<(&'static str, SocketAddr)> =
            (amqp_listeners.iter().map(|addr| ("amqp", *addr)))
                .chain(other_listeners)
                .chain([("http", http_addr), ("http/prometheus", metrics_addr)])
                .collect();
        let rates = Rates::default();
        let metrics_context = MetricsContext {
            admin: admin.clone(),
            node: node.clone(),
            data_dir: settings.data_dir.clone(),
            shovels: links.shovels.clone(),
        };
        let management = crate::management::Context {
            admin: admin.clone(),
            links,
            node,
            data_dir: settings.data_dir,
            listeners: listeners.clone(),
            tls: settings.tls,
            environment: settings.environment,
            rates: rates.clone(),
        };
        let (stop, stopped) = watch::channel(false);
        let thread = std::thread::Builder::new()
            .name("leveret-ops".into())
            .spawn(move || {
                runtime.block_on(async move {
                    let (metrics, http) = match (
                        tokio::net::TcpListener::from_std(metrics),
                        tokio::net::TcpListener::from_std(http),
                    ) {
                        (Ok(metrics), Ok(http)) => (metrics, http),
                        (Err(e), _) | (_, Err(e)) => {
                            tracing::error!(error = %e, "cannot serve the operators' listeners");
                            return;
                        }
                    };
                    tracing::info!(addr = %metrics_addr, "serving Prometheus metrics");
                    tracing::info!(addr = %http_addr, "serving the management API");
                    tokio::join!(
                        crate::http::serve(
                            metrics,
                            crate::metrics::router(metrics_context),
                            "metrics",
                            stopped.clone()
                        ),
                        crate::http::serve(
                            http,
                            crate::management::router(management),
                            "management",
                            stopped.clone()
                        ),
                        rates.run(admin, stopped),
                    );
                });
            })
            .map_err(OpsError::Thread)?;
        Ok(Ops {
            listeners,
            stop,
            thread,
        })
    }

    /// Stops the listeners and waits for their thread.
    pub fn stop(self) {
        self.stop.send_replace(true);
        if self.thread.join().is_err() {
            tracing::error!("the listeners' thread panicked");
        }
    }
}
