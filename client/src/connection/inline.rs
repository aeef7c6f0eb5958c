//! The in-process fast path's delivery side: an in-process connection's
//! deliveries taken on the broker's dispatching thread
//! ([`leveret_broker::InlineDeliveries`]) and handed to their consumer (its
//! sink first, if it has one, then its buffer) as the reader would, and its
//! publisher confirms settled on the thread where the broker settles them,
//! with no outbox item and no reader task in between. The broker offers a
//! delivery or a confirm only once every item it sent before has been
//! handled by the reader, so the order is the reader's; whatever this
//! declines (a consumer or channel not known, a full buffer, a closing
//! connection) goes through the reader.

use super::Shared;
use crate::channel::ChannelCore;
use crate::message::{Content, Delivery};
use leveret_broker::{InlineDeliveries, InlineDelivery};
use leveret_protocol::{BasicDeliver, BasicProperties};
use std::sync::atomic::Ordering;
use std::sync::{Arc, Weak};

/// A connection's consumers, as the broker's dispatch reaches them. Holds
/// the connection weakly: the broker's outbox must not keep it alive.
pub(crate) struct InlineConsumers {
    shared: Weak<Shared>,
}

impl InlineConsumers {
    pub(crate) fn new(shared: &Arc<Shared>) -> Arc<Self> {
        Arc::new(InlineConsumers {
            shared: Arc::downgrade(shared),
        })
    }
}

impl InlineDeliveries for InlineConsumers {
    fn deliver(&self, offered: InlineDelivery<'_>) -> bool {
        let Some(shared) = self.shared.upgrade() else {
            return false;
        };
        // The reader drops a closing connection's deliveries: let it.
        if *shared.closing.borrow() {
            return false;
        }
        let Some(chan) = shared.channel(offered.channel) else {
            return false;
        };
        let Some(route) = chan.consumer(offered.consumer_tag) else {
            return false;
        };
        // Application code may run in a sink: only on the reader, unless
        // the sink vouches for itself (it could call into the broker and
        // wait on the very queue whose lock this thread holds).
        if route.sink.as_ref().is_some_and(|sink| !sink.runs_inline()) {
            return false;
        }
        // Room in the consumer's buffer first, so that a value its sink
        // leaves is never left here with nowhere to go.
        let Ok(room) = route.tx.try_reserve() else {
            return false;
        };
        // Checked when published; the reader reports it if it ever fails.
        let Ok(properties) = BasicProperties::decode(offered.properties) else {
            return false;
        };
        let delivery = Delivery::new(
            BasicDeliver {
                consumer_tag: offered.consumer_tag.clone(),
                delivery_tag: offered.delivery_tag,
                redelivered: offered.redelivered,
                exchange: offered.exchange.clone(),
                routing_key: offered.routing_key.clone(),
            },
            Content {
                properties,
                body: offered.body.clone(),
            },
            ChannelCore::new(Arc::clone(&shared), chan),
        );
        if !route.sink.is_some_and(|sink| sink.take(&delivery)) {
            room.send(delivery);
        }
        shared.inline_deliveries.fetch_add(1, Ordering::Relaxed);
        true
    }

    /// Settles the publishes a confirm covers, as the reader would: the
    /// publisher's confirm futures are ready when the broker's settling
    /// returns (on the publishing thread, for a publish it handled there).
    fn confirm(&self, channel: u16, tag: u64, multiple: bool, ack: bool) -> bool {
        let Some(shared) = self.shared.upgrade() else {
            return false;
        };
        if *shared.closing.borrow() {
            return false;
        }
        let Some(chan) = shared.channel(channel) else {
            return false;
        };
        chan.confirmed(tag, multiple, ack);
        shared.inline_confirms.fetch_add(1, Ordering::Relaxed);
        true
    }
}
