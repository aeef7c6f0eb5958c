//! The embedding API: [`Broker::builder`] configures a broker (listeners,
//! users, vhosts, limits), `start` binds the listeners and returns a
//! [`BrokerHandle`]; `shutdown` closes every connection with 320
//! CONNECTION_FORCED and waits for them to finish.

use crate::auth::Users;
use crate::core::{Core, Limits};
use std::net::SocketAddr;
use std::sync::Arc;
use std::time::Duration;
use tokio::net::TcpListener;
use tokio::sync::mpsc;

/// How often message TTLs and queue x-expires are checked.
const SWEEP_PERIOD: Duration = Duration::from_millis(50);
/// How long shutdown waits for connections to close.
const SHUTDOWN_GRACE: Duration = Duration::from_secs(5);

/// Entry point of the embedding API.
pub struct Broker;

impl Broker {
    /// A builder with the defaults: no listener, user guest/guest, vhost `/`.
    pub fn builder() -> BrokerBuilder {
        BrokerBuilder::default()
    }
}

/// Options for a broker.
#[derive(Debug, Clone, Default)]
pub struct BrokerBuilder {
    listen: Vec<SocketAddr>,
    users: Vec<(String, String)>,
    vhosts: Vec<String>,
    limits: Limits,
}

impl BrokerBuilder {
    /// Adds a TCP listener (port 0 picks a free port).
    pub fn listen(mut self, addr: SocketAddr) -> Self {
        self.listen.push(addr);
        self
    }

    /// Adds a user; without any, the broker has RabbitMQ's `guest`/`guest`.
    pub fn user(mut self, name: impl Into<String>, password: impl Into<String>) -> Self {
        self.users.push((name.into(), password.into()));
        self
    }

    /// Adds a vhost; without any, the broker has `/`.
    pub fn vhost(mut self, name: impl Into<String>) -> Self {
        self.vhosts.push(name.into());
        self
    }

    /// Replaces the limits.
    pub fn limits(mut self, limits: Limits) -> Self {
        self.limits = limits;
        self
    }

    /// Binds the listeners and starts serving.
    pub async fn start(self) -> Result<BrokerHandle, StartError> {
        let mut users = Users::default();
        if self.users.is_empty() {
            users.insert("guest", "guest");
        }
        for (name, password) in &self.users {
            users.insert(name.clone(), password);
        }
        let vhosts = if self.vhosts.is_empty() {
            vec!["/".to_owned()]
        } else {
            self.vhosts
        };
        let core = Core::new(&vhosts, users, self.limits);
        let (alive, finished) = mpsc::channel(1);
        let mut local_addrs = Vec::new();
        let mut tasks = Vec::new();
        for addr in self.listen {
            let listener = TcpListener::bind(addr)
                .await
                .map_err(|source| StartError::Bind { addr, source })?;
            let bound = listener
                .local_addr()
                .map_err(|source| StartError::Bind { addr, source })?;
            tracing::info!(addr = %bound, "accepting AMQP 0.9.1 connections");
            local_addrs.push(bound);
            tasks.push(tokio::spawn(crate::server::accept_loop(
                Arc::clone(&core),
                listener,
                alive.clone(),
            )));
        }
        tasks.push(tokio::spawn(crate::server::sweeper(
            Arc::clone(&core),
            SWEEP_PERIOD,
        )));
        Ok(BrokerHandle {
            core,
            local_addrs,
            tasks,
            alive: Some(alive),
            finished,
        })
    }
}

/// A running broker.
pub struct BrokerHandle {
    core: Arc<Core>,
    local_addrs: Vec<SocketAddr>,
    tasks: Vec<tokio::task::JoinHandle<()>>,
    alive: Option<mpsc::Sender<()>>,
    finished: mpsc::Receiver<()>,
}

impl BrokerHandle {
    /// The addresses the listeners are bound to.
    pub fn local_addrs(&self) -> &[SocketAddr] {
        &self.local_addrs
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
    }
}

impl Drop for BrokerHandle {
    fn drop(&mut self) {
        self.core.begin_shutdown();
    }
}

/// Why a broker could not start.
#[derive(Debug, thiserror::Error)]
pub enum StartError {
    /// A listener could not be bound.
    #[error("cannot listen on {addr}: {source}")]
    Bind {
        /// The address.
        addr: SocketAddr,
        /// The error.
        source: std::io::Error,
    },
}
