//! Messages coming from the broker: [`Delivery`] (to a consumer, or from
//! `basic.get` inside a [`GetMessage`]) with its acknowledgement methods,
//! and [`ReturnedMessage`] (a mandatory message no queue took). Bodies are
//! `Bytes` slices of the connection's read buffer.

use crate::channel::{ChannelCore, OutboxSlot};
use crate::error::Result;
use crate::options::{BasicNackOptions, BasicRejectOptions};
use bytes::Bytes;
use leveret_protocol::{BasicAck, BasicDeliver, BasicProperties, ReplyCode, ShortStr};

/// Properties and body of a message as received.
#[derive(Debug, Clone, Default)]
pub(crate) struct Content {
    pub(crate) properties: BasicProperties,
    pub(crate) body: Bytes,
}

/// A message delivered to a consumer or fetched with `basic.get`.
#[derive(Debug, Clone)]
pub struct Delivery {
    /// The channel's tag for this delivery, for ack/nack/reject.
    pub delivery_tag: u64,
    /// Whether it was delivered before (and not acknowledged).
    pub redelivered: bool,
    /// The exchange it was published to.
    pub exchange: ShortStr,
    /// The routing key it was published with.
    pub routing_key: ShortStr,
    /// The consumer it was delivered to (empty for `basic.get`).
    pub consumer_tag: ShortStr,
    /// Its properties.
    pub properties: BasicProperties,
    /// Its body.
    pub body: Bytes,
    acker: ChannelCore,
}

impl Delivery {
    pub(crate) fn new(deliver: BasicDeliver, content: Content, acker: ChannelCore) -> Self {
        Delivery {
            delivery_tag: deliver.delivery_tag,
            redelivered: deliver.redelivered,
            exchange: deliver.exchange,
            routing_key: deliver.routing_key,
            consumer_tag: deliver.consumer_tag,
            properties: content.properties,
            body: content.body,
            acker,
        }
    }

    pub(crate) fn from_get(
        delivery_tag: u64,
        redelivered: bool,
        exchange: ShortStr,
        routing_key: ShortStr,
        content: Content,
        acker: ChannelCore,
    ) -> Self {
        Delivery {
            delivery_tag,
            redelivered,
            exchange,
            routing_key,
            consumer_tag: ShortStr::default(),
            properties: content.properties,
            body: content.body,
            acker,
        }
    }

    /// Acknowledges this delivery (`basic.ack`, not multiple).
    pub async fn ack(&self) -> Result<()> {
        self.ack_in(self.acker.reserve().await?)
    }

    /// Room for this delivery's ack in the connection's outbox if there is
    /// some now (`None` if it is full), for [`Delivery::ack_in`].
    pub fn try_reserve_ack(&self) -> Result<Option<OutboxSlot<'_>>> {
        self.acker.try_reserve()
    }

    /// Acknowledges this delivery through room reserved for it, without
    /// waiting.
    pub fn ack_in(&self, slot: OutboxSlot<'_>) -> Result<()> {
        slot.send(BasicAck {
            delivery_tag: self.delivery_tag,
            multiple: false,
        })
    }

    /// Rejects this delivery (`basic.nack`; with `multiple`, every
    /// earlier unacknowledged delivery of the channel too).
    pub async fn nack(&self, options: BasicNackOptions) -> Result<()> {
        self.acker.basic_nack(self.delivery_tag, options).await
    }

    /// Rejects this delivery (`basic.reject`).
    pub async fn reject(&self, options: BasicRejectOptions) -> Result<()> {
        self.acker.basic_reject(self.delivery_tag, options).await
    }
}

/// A message fetched with `basic.get`: the delivery, and how many messages
/// the queue still holds.
#[derive(Debug, Clone)]
pub struct GetMessage {
    /// The message.
    pub delivery: Delivery,
    /// Messages left in the queue.
    pub message_count: u32,
}

impl std::ops::Deref for GetMessage {
    type Target = Delivery;
    fn deref(&self) -> &Delivery {
        &self.delivery
    }
}

/// A mandatory message that no queue took, sent back with `basic.return`.
#[derive(Debug, Clone)]
pub struct ReturnedMessage {
    /// Why it came back, as sent (312 NO_ROUTE for an unroutable message).
    pub reply_code: u16,
    /// The broker's text for it.
    pub reply_text: ShortStr,
    /// The exchange it was published to.
    pub exchange: ShortStr,
    /// The routing key it was published with.
    pub routing_key: ShortStr,
    /// Its properties.
    pub properties: BasicProperties,
    /// Its body.
    pub body: Bytes,
}

impl ReturnedMessage {
    /// The reply code, if the spec defines it.
    pub fn reply_code(&self) -> Option<ReplyCode> {
        ReplyCode::from_code(self.reply_code)
    }
}

/// Anything usable as an AMQP short string (a name, a routing key): `&str`
/// and `String` are checked and copied; a [`ShortStr`] is taken as it is,
/// so a publisher that keeps its exchange and routing key as `ShortStr`s
/// publishes without allocating for them.
pub trait IntoShortStr {
    /// The short string, or [`crate::Error::InvalidArgument`] if longer
    /// than 255 bytes.
    fn into_short_str(self) -> Result<ShortStr>;
}

impl IntoShortStr for ShortStr {
    fn into_short_str(self) -> Result<ShortStr> {
        Ok(self)
    }
}

impl IntoShortStr for &ShortStr {
    fn into_short_str(self) -> Result<ShortStr> {
        Ok(self.clone())
    }
}

impl IntoShortStr for &str {
    fn into_short_str(self) -> Result<ShortStr> {
        Ok(ShortStr::try_from(self)?)
    }
}

impl IntoShortStr for String {
    fn into_short_str(self) -> Result<ShortStr> {
        Ok(ShortStr::try_from(self)?)
    }
}

impl IntoShortStr for &String {
    fn into_short_str(self) -> Result<ShortStr> {
        Ok(ShortStr::try_from(self.as_str())?)
    }
}
