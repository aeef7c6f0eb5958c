//! The operators' listeners (Prometheus metrics, the management API) on a
//! thread of their own with its own current-thread tokio runtime: nothing
//! they do runs on the broker's thread, so a scrape or a listing of many
//! queues never delays AMQP traffic. They reach the broker only through
//! its [`Admin`] handle, whose reads take each broker lock for a few
//! instructions at a time. The sockets are bound before the thread starts,
//! so a busy port stops the binary at start with a clear error.

use crate::metrics::MetricsContext;
use leveret_broker::Admin;
use std::net::SocketAddr;
use std::path::PathBuf;
use tokio::sync::watch;

/// Where the listeners go.
#[derive(Debug, Clone)]
pub struct OpsSettings {
    /// The Prometheus endpoint.
    pub metrics_listen: SocketAddr,
    /// Where the broker keeps its data (disk space is measured there).
    pub data_dir: PathBuf,
}

/// The running listeners.
#[derive(Debug)]
pub struct Ops {
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

fn bind(addr: SocketAddr) -> Result<std::net::TcpListener, OpsError> {
    let bound = std::net::TcpListener::bind(addr)
        .and_then(|listener| listener.set_nonblocking(true).map(|()| listener));
    bound.map_err(|source| OpsError::Bind { addr, source })
}

impl Ops {
    /// Binds the listeners and serves them on their own thread.
    pub fn start(admin: Admin, settings: OpsSettings) -> Result<Ops, OpsError> {
        let metrics = bind(settings.metrics_listen)?;
        let metrics_addr = metrics.local_addr().map_err(|source| OpsError::Bind {
            addr: settings.metrics_listen,
            source,
        })?;
        let runtime = tokio::runtime::Builder::new_current_thread()
            .enable_all()
            .build()
            .map_err(OpsError::Thread)?;
        let context = MetricsContext {
            admin,
            node: crate::process::node_name(),
            data_dir: settings.data_dir,
        };
        let (stop, stopped) = watch::channel(false);
        let thread = std::thread::Builder::new()
            .name("leveret-ops".into())
            .spawn(move || {
                runtime.block_on(async move {
                    let metrics = match tokio::net::TcpListener::from_std(metrics) {
                        Ok(listener) => listener,
                        Err(e) => {
                            tracing::error!(error = %e, "cannot serve the metrics listener");
                            return;
                        }
                    };
                    tracing::info!(addr = %metrics_addr, "serving Prometheus metrics");
                    crate::http::serve(
                        metrics,
                        crate::metrics::router(context),
                        "metrics",
                        stopped,
                    )
                    .await;
                });
            })
            .map_err(OpsError::Thread)?;
        Ok(Ops { stop, thread })
    }

    /// Stops the listeners and waits for their thread.
    pub fn stop(self) {
        self.stop.send_replace(true);
        if self.thread.join().is_err() {
            tracing::error!("the listeners' thread panicked");
        }
    }
}
