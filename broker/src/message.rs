//! A published message as the broker holds it: routing information, the
//! content header's property bytes exactly as the publisher encoded them
//! (forwarded to consumers without re-encoding), and the body as `Bytes`
//! slices of the publisher's read buffer.

use bytes::Bytes;
use leveret_protocol::ShortStr;
use std::sync::atomic::{AtomicUsize, Ordering};

/// The stored copy of a persistent message: its id, and how many durable
/// queues still hold it (the last one deletes it from disk).
#[derive(Debug)]
pub struct StoredBody {
    /// Message id in the store.
    pub id: u64,
    refs: AtomicUsize,
}

impl StoredBody {
    /// A body held by `refs` durable queues.
    pub fn new(id: u64, refs: usize) -> Self {
        StoredBody {
            id,
            refs: AtomicUsize::new(refs),
        }
    }

    /// One queue let go; true if it was the last.
    pub fn release(&self) -> bool {
        self.refs.fetch_sub(1, Ordering::AcqRel) == 1
    }
}

/// One message; shared by `Arc` between every queue it was routed to.
#[derive(Debug)]
pub struct Message {
    /// Exchange it was published to.
    pub exchange: ShortStr,
    /// Routing key it was published with.
    pub routing_key: ShortStr,
    /// Encoded property flags and list.
    pub properties: Bytes,
    /// The body.
    pub body: Bytes,
    /// delivery-mode 2.
    pub persistent: bool,
    /// The priority property (0 if absent).
    pub priority: u8,
    /// Per-message TTL from the `expiration` property, in milliseconds.
    pub ttl_ms: Option<u64>,
    /// Set when the message is persistent and routed to durable queues.
    pub stored: Option<StoredBody>,
}

impl Message {
    /// Bytes this message accounts for in memory limits.
    pub fn weight(&self) -> usize {
        self.body.len() + self.properties.len() + 64
    }
}
