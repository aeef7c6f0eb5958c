//! [`Admin`]: a cloneable handle on a running broker for tools beside the
//! AMQP listeners (the `leveret` binary's HTTP API, an embedder's own
//! dashboard). Reading state is `inspect`'s part of it; this module holds
//! the handle and the operations that change things, each doing what the
//! AMQP method of the same meaning does, with the same checks.

use crate::core::Core;
use std::sync::Arc;

/// A cheap, cloneable handle for inspecting and administering a running
/// broker. It stays usable after the broker shuts down, showing what was
/// left.
#[derive(Debug, Clone)]
pub struct Admin {
    pub(crate) core: Arc<Core>,
}

impl Admin {
    /// Closes connection `id` with 320 CONNECTION_FORCED and `reason` as
    /// the text; false if no such connection is open.
    pub fn close_connection(&self, id: u64, reason: &str) -> bool {
        self.core.registry.close(id, reason)
    }
}
