//! A published message as the broker holds it: routing information, the
//! content header's property bytes exactly as the publisher encoded them
//! (forwarded to consumers without re-encoding), and the body as `Bytes`
//! slices of the publisher's read buffer.

use bytes::Bytes;
use leveret_protocol::ShortStr;

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
}

impl Message {
    /// Bytes this message accounts for in memory limits.
    pub fn weight(&self) -> usize {
        self.body.len() + self.properties.len() + 64
    }
}
