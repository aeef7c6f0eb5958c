//! A published message as the broker holds it: routing information, the
//! content header's property bytes exactly as the publisher encoded them
//! (forwarded to consumers without re-encoding), and the body as `Bytes`
//! slices of the publisher's read buffer.

use crate::store::{MessageRecord, Persistence, StoreOp};
use bytes::Bytes;
use leveret_protocol::ShortStr;
use std::sync::atomic::{AtomicUsize, Ordering};

/// How a persistent message routed to durable queues is kept on disk.
#[derive(Debug)]
pub enum Stored {
    /// Inside the index entry of its one durable queue (the common case:
    /// one key per message).
    Inline,
    /// As a record of its own, `id`, shared by `refs` durable queues; the
    /// last queue to let go deletes it.
    Shared {
        /// Record id in the store.
        id: u64,
        /// Durable queues still holding it.
        refs: AtomicUsize,
    },
}

impl Stored {
    /// How a persistent message routed to `durable_queues` durable queues
    /// is kept: not at all, inline, or as a record of its own.
    pub fn for_queues(persistence: &Persistence, durable_queues: usize) -> Option<Self> {
        match durable_queues {
            0 => None,
            1 => Some(Stored::Inline),
            refs => Some(Stored::shared(persistence.next_message_id(), refs)),
        }
    }

    /// A record shared by `refs` durable queues.
    pub fn shared(id: u64, refs: usize) -> Self {
        Stored::Shared {
            id,
            refs: AtomicUsize::new(refs),
        }
    }

    /// One queue let go; the shared record's id if it was the last.
    pub fn release(&self) -> Option<u64> {
        match self {
            Stored::Inline => None,
            Stored::Shared { id, refs } => {
                (refs.fetch_sub(1, Ordering::AcqRel) == 1).then_some(*id)
            }
        }
    }
}

/// Memory a queued message costs beyond its body and properties, as
/// measured with a million small messages queued: the `Arc`'d `Message`,
/// the queue slot, and its share of the read buffer it was sliced from.
pub(crate) const MESSAGE_OVERHEAD: usize = 300;

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
    pub stored: Option<Stored>,
}

impl Message {
    /// This message kept on disk as `stored` says (cheap: `Bytes` handles).
    pub fn stored_as(&self, stored: Option<Stored>) -> Message {
        Message {
            exchange: self.exchange.clone(),
            routing_key: self.routing_key.clone(),
            properties: self.properties.clone(),
            body: self.body.clone(),
            persistent: self.persistent,
            priority: self.priority,
            ttl_ms: self.ttl_ms,
            stored,
        }
    }

    /// The op storing this message's own record, when it is shared by
    /// several durable queues (a message in one durable queue lives inside
    /// that queue's index entry instead).
    pub fn record_op(&self) -> Option<StoreOp> {
        match self.stored.as_ref()? {
            Stored::Inline => None,
            Stored::Shared { id, .. } => Some(StoreOp::PutMessage {
                id: *id,
                record: self.to_record(),
            }),
        }
    }

    /// The message as the store keeps it (cheap: `Bytes` handles).
    pub fn to_record(&self) -> MessageRecord {
        MessageRecord {
            exchange: self.exchange.clone(),
            routing_key: self.routing_key.clone(),
            properties: self.properties.clone(),
            body: self.body.clone(),
        }
    }

    /// Bytes this message accounts for in memory limits.
    pub fn weight(&self) -> usize {
        self.body.len() + self.properties.len() + MESSAGE_OVERHEAD
    }
}
