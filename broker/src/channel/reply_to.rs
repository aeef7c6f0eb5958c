//! RabbitMQ's direct reply-to: a channel consumes from the pseudo-queue
//! `amq.rabbitmq.reply-to` (no-ack only); its requests carrying that
//! `reply_to` get it rewritten to a unique `amq.rabbitmq.reply-to.<token>`
//! name; a reply published to that name on the default exchange goes
//! straight to the consumer, without any queue.

use super::Channel;
use crate::error::{AmqpError, AmqpResult};
use crate::message::Message;
use crate::outbox::Outbound;
use crate::queue::ReplyTarget;
use bytes::BytesMut;
use leveret_protocol::{BasicConsume, BasicConsumeOk, ShortStr};
use std::sync::Arc;

/// The pseudo-queue name clients consume from and put in `reply_to`.
pub(crate) const PSEUDO_QUEUE: &str = "amq.rabbitmq.reply-to";
/// Prefix of the per-channel names replies are published to.
const PREFIX: &str = "amq.rabbitmq.reply-to.";

/// A channel's reply consumer.
#[derive(Debug)]
pub(crate) struct DirectReply {
    /// The unique name requests carry as `reply_to`.
    name: ShortStr,
    /// The consumer tag.
    tag: ShortStr,
}

/// Whether `routing_key` names a reply consumer.
pub(crate) fn is_reply_address(exchange: &ShortStr, routing_key: &ShortStr) -> bool {
    exchange.is_empty() && routing_key.as_bytes().starts_with(PREFIX.as_bytes())
}

impl Channel {
    /// basic.consume on `amq.rabbitmq.reply-to`.
    pub(super) async fn consume_direct_reply(&mut self, consume: BasicConsume) -> AmqpResult<()> {
        if !consume.no_ack {
            return Err(AmqpError::precondition_failed(
                "reply consumer cannot acknowledge",
            ));
        }
        if self.direct_reply.is_some() {
            return Err(AmqpError::precondition_failed("reply consumer already set"));
        }
        let tag = if consume.consumer_tag.is_empty() {
            super::names::unique_name("amq.ctag-")
        } else {
            consume.consumer_tag
        };
        let name = super::names::unique_name(PREFIX);
        self.vhost.register_reply_target(
            name.clone(),
            ReplyTarget {
                link: Arc::clone(&self.link),
                consumer_tag: tag.clone(),
            },
        );
        self.direct_reply = Some(DirectReply {
            name,
            tag: tag.clone(),
        });
        if !consume.no_wait {
            self.reply(BasicConsumeOk { consumer_tag: tag }).await;
        }
        Ok(())
    }

    /// basic.cancel of the reply consumer; false if `tag` is another consumer.
    pub(super) fn cancel_direct_reply(&mut self, tag: &ShortStr) -> bool {
        match &self.direct_reply {
            Some(reply) if reply.tag == *tag => {
                self.drop_direct_reply();
                true
            }
            _ => false,
        }
    }

    /// Forgets the reply consumer (cancel, channel close).
    pub(super) fn drop_direct_reply(&mut self) {
        if let Some(reply) = self.direct_reply.take() {
            self.vhost.unregister_reply_target(&reply.name);
        }
    }

    /// Rewrites a request's `reply_to: amq.rabbitmq.reply-to` to this
    /// channel's reply name; 406 if the channel has no reply consumer.
    pub(super) fn rewrite_reply_to(&self, publish: &mut super::Publish) -> AmqpResult<()> {
        if publish
            .properties
            .reply_to
            .as_ref()
            .is_none_or(|r| *r != PSEUDO_QUEUE)
        {
            return Ok(());
        }
        let Some(reply) = &self.direct_reply else {
            return Err(AmqpError::precondition_failed(
                "fast reply consumer does not exist",
            ));
        };
        publish.properties.reply_to = Some(reply.name.clone());
        let mut encoded = BytesMut::with_capacity(publish.property_bytes.len() + 32);
        publish.properties.encode(&mut encoded);
        publish.property_bytes = encoded.freeze();
        Ok(())
    }

    /// Delivers a reply to the consumer whose name it was published to;
    /// false if that consumer is gone (the reply is then unroutable).
    ///
    /// Never waits: the responder's channel must not stall behind another
    /// connection's socket. RabbitMQ hands a reply to the requester's
    /// channel without flow control, and documents direct reply-to as
    /// at-most-once; holding replies for a requester that does not read
    /// would grow without bound, so a reply that finds the requester's
    /// outbox full is dropped (counted and logged) and still counts as
    /// routed, as in RabbitMQ, where the responder learns nothing either.
    pub(super) fn deliver_reply(&self, message: &Arc<Message>) -> bool {
        let Some(target) = self.vhost.reply_target(&message.routing_key) else {
            return false;
        };
        let link = &target.link;
        let Some(permit) = link.outbox.try_reserve() else {
            let dropped = link.count_dropped_reply();
            // Log the 1st, 2nd, 4th, 8th... drop: visible, but a flood of
            // replies to a stalled requester cannot flood the log.
            if dropped.is_power_of_two() {
                tracing::warn!(
                    channel = link.id,
                    connection = link.outbox.connection_id,
                    dropped,
                    "direct reply dropped: the requester's connection is not reading"
                );
            }
            return true;
        };
        // The tag is taken and the delivery queued under the channel's
        // delivery lock, so the client sees tags in the order they are
        // handed out.
        let mut deliveries = link.deliveries();
        permit.send(Outbound::Deliver {
            channel: link.id,
            consumer_tag: target.consumer_tag,
            delivery_tag: deliveries.next_tag(),
            redelivered: false,
            message: Arc::clone(message),
        });
        true
    }
}
