//! The embedding API: [`Broker::builder`] configures a broker, `start`
//! binds its listeners and returns a [`BrokerHandle`].

use std::net::SocketAddr;

/// Entry point of the embedding API.
pub struct Broker;

impl Broker {
    /// A builder with the defaults: no listener, in-memory storage.
    pub fn builder() -> BrokerBuilder {
        BrokerBuilder::default()
    }
}

/// Options for an embedded broker.
#[derive(Debug, Default, Clone)]
pub struct BrokerBuilder {
    listen: Vec<SocketAddr>,
}

impl BrokerBuilder {
    /// Adds a TCP listener (port 0 picks a free port).
    pub fn listen(mut self, addr: SocketAddr) -> Self {
        self.listen.push(addr);
        self
    }

    /// Binds the listeners and starts serving.
    pub async fn start(self) -> Result<BrokerHandle, StartError> {
        Err(StartError::NotYetImplemented)
    }
}

/// A running broker.
pub struct BrokerHandle {
    local_addrs: Vec<SocketAddr>,
}

impl BrokerHandle {
    /// The addresses the listeners are bound to.
    pub fn local_addrs(&self) -> &[SocketAddr] {
        &self.local_addrs
    }

    /// Closes every connection with 320 CONNECTION_FORCED and stops.
    pub async fn shutdown(self) {}
}

/// Why a broker could not start.
#[derive(Debug, thiserror::Error)]
pub enum StartError {
    /// Placeholder while the core is being written.
    #[error("not yet implemented")]
    NotYetImplemented,
}
