//! One channel's state machine: content assembly (method → header → body),
//! method dispatch to the per-class handlers (`exchange`, `queue`,
//! `basic`, `tx`), soft errors (channel.close and discarding frames until
//! close-ok), and releasing what a closed channel held.
//!
//! Layout: `basic.rs` publishing, consuming, acks and get; `queue.rs`
//! queue.*; `exchange.rs` exchange.*; `tx.rs` transactions and publisher
//! confirms.

mod basic;
mod exchange;
mod queue;
mod reply_to;
mod tx;

pub(crate) use reply_to::ReplyTarget;

use crate::consumer::{ChannelLink, Consumer};
use crate::core::Core;
use crate::error::{AmqpError, AmqpResult};
use crate::outbox::Outbox;
use crate::queue::Queue;
use crate::registry::ChannelRegistration;
use crate::vhost::Vhost;
use bytes::{Bytes, BytesMut};
use leveret_protocol::{
    BasicProperties, BasicPublish, ChannelClose, ChannelCloseOk, ChannelFlowOk, ContentHeader,
    Frame, Method, ShortStr,
};
use std::collections::HashMap;
use std::sync::Arc;

/// A publish waiting for its content. One per channel, replaced in place,
/// so the size of its largest variant costs nothing per message.
#[derive(Debug)]
#[allow(clippy::large_enum_variant)]
enum Assembly {
    /// Expecting a method.
    Idle,
    /// basic.publish seen, expecting the content header.
    Header(BasicPublish),
    /// Header seen, expecting body frames.
    Body {
        publish: BasicPublish,
        properties: BasicProperties,
        property_bytes: Bytes,
        size: u64,
        first: Option<Bytes>,
        rest: Option<BytesMut>,
        received: u64,
    },
}

/// A fully assembled publish.
#[derive(Debug)]
pub(crate) struct Publish {
    method: BasicPublish,
    properties: BasicProperties,
    property_bytes: Bytes,
    body: Bytes,
}

impl Publish {
    /// Bytes it accounts for in the memory gauge while a transaction holds
    /// it: what the message will weigh once queued.
    fn weight(&self) -> usize {
        self.body.len() + self.property_bytes.len() + crate::message::MESSAGE_OVERHEAD
    }
}

/// A channel of a connection.
pub struct Channel {
    id: u16,
    link: Arc<ChannelLink>,
    vhost: Arc<Vhost>,
    core: Arc<Core>,
    user: String,
    assembly: Assembly,
    closing: bool,
    consumers: HashMap<ShortStr, (Arc<Consumer>, Arc<Queue>)>,
    last_queue: Option<ShortStr>,
    prefetch_count: u32,
    published: bool,
    route_buffer: Vec<Arc<Queue>>,
    tx: Option<tx::Transaction>,
    confirms: Option<tx::Confirms>,
    direct_reply: Option<reply_to::DirectReply>,
    /// A queue this channel published to that is over the flow limit.
    crowded: Option<Arc<Queue>>,
    /// Keeps the channel listed (`registry`) until it is dropped.
    registration: ChannelRegistration,
}

impl Channel {
    /// A newly opened channel.
    pub fn new(
        id: u16,
        outbox: Arc<Outbox>,
        vhost: Arc<Vhost>,
        core: Arc<Core>,
        user: String,
    ) -> Self {
        let link = Arc::new(ChannelLink::new(id, outbox));
        Channel {
            id,
            registration: core.registry.channel(link.outbox.connection_id, id, &link),
            link,
            vhost,
            core,
            user,
            assembly: Assembly::Idle,
            closing: false,
            consumers: HashMap::new(),
            last_queue: None,
            prefetch_count: 0,
            published: false,
            route_buffer: Vec::new(),
            tx: None,
            confirms: None,
            direct_reply: None,
            crowded: None,
        }
    }

    fn outbox(&self) -> &Outbox {
        &self.link.outbox
    }

    async fn reply(&self, method: impl Into<Method>) {
        self.link.outbox.method(self.id, method).await;
    }

    /// A crowded queue this channel published to since the last call: the
    /// connection waits for it to drain before reading more.
    pub fn take_crowded(&mut self) -> Option<Arc<Queue>> {
        self.crowded.take()
    }

    /// Whether this channel has published (memory alarms block it).
    pub fn has_published(&self) -> bool {
        self.published
    }

    /// Handles a frame for this channel. `Ok(true)` means the channel is
    /// finished and must be removed; `Err` is a connection-level error.
    pub async fn handle(&mut self, frame: Frame) -> AmqpResult<bool> {
        if self.closing {
            // After channel.close, only close and close-ok count.
            return match frame {
                Frame::Method {
                    method: Method::ChannelCloseOk(_),
                    ..
                } => Ok(true),
                Frame::Method {
                    method: Method::ChannelClose(_),
                    ..
                } => {
                    self.reply(ChannelCloseOk {}).await;
                    Ok(false)
                }
                _ => Ok(false),
            };
        }
        let result = match frame {
            Frame::Method { method, .. } => self.handle_method(method).await,
            Frame::Header { header, .. } => self.handle_header(header).await,
            Frame::Body { payload, .. } => self.handle_body(payload).await,
            Frame::Heartbeat => Ok(false),
        };
        match result {
            Err(error) if !error.is_connection_error() => {
                tracing::debug!(channel = self.id, %error, "closing channel");
                self.close_with(error).await;
                Ok(false)
            }
            other => other,
        }
    }

    async fn close_with(&mut self, error: AmqpError) {
        self.release();
        self.closing = true;
        self.reply(ChannelClose {
            reply_code: error.code.code(),
            reply_text: error.reply_text(),
            class_id: error.class_id,
            method_id: error.method_id,
        })
        .await;
    }

    async fn handle_method(&mut self, method: Method) -> AmqpResult<bool> {
        if !matches!(self.assembly, Assembly::Idle) {
            return Err(AmqpError::unexpected_frame(format_args!(
                "expected content header for class 60, got non content header frame instead ({})",
                method.name()
            ))
            .during_ids(60, 40));
        }
        let ids = (method.class_id(), method.method_id());
        let result = self.dispatch(method).await;
        result.map_err(|e| e.during_ids(ids.0, ids.1))
    }

    async fn dispatch(&mut self, method: Method) -> AmqpResult<bool> {
        match method {
            Method::ChannelClose(_) => {
                self.release();
                self.reply(ChannelCloseOk {}).await;
                return Ok(true);
            }
            Method::ChannelCloseOk(_) => return Ok(false),
            Method::ChannelFlow(flow) => {
                if !flow.active {
                    return Err(AmqpError::not_implemented("active=false"));
                }
                self.reply(ChannelFlowOk { active: true }).await;
            }
            Method::ChannelOpen(_) => {
                return Err(AmqpError::channel_error(format_args!(
                    "second 'channel.open' seen on channel {}",
                    self.id
                )))
            }
            Method::AccessRequest(_) => {
                self.reply(leveret_protocol::AccessRequestOk { ticket: 1 })
                    .await;
            }
            Method::ExchangeDeclare(m) => self.exchange_declare(m).await?,
            Method::ExchangeDelete(m) => self.exchange_delete(m).await?,
            Method::ExchangeBind(m) => {
                self.exchange_bind(
                    m.destination,
                    m.source,
                    m.routing_key,
                    m.arguments,
                    m.no_wait,
                    true,
                )
                .await?
            }
            Method::ExchangeUnbind(m) => {
                self.exchange_bind(
                    m.destination,
                    m.source,
                    m.routing_key,
                    m.arguments,
                    m.no_wait,
                    false,
                )
                .await?
            }
            Method::QueueDeclare(m) => self.queue_declare(m).await?,
            Method::QueueBind(m) => self.queue_bind(m).await?,
            Method::QueueUnbind(m) => self.queue_unbind(m).await?,
            Method::QueuePurge(m) => self.queue_purge(m).await?,
            Method::QueueDelete(m) => self.queue_delete(m).await?,
            Method::BasicQos(m) => self.basic_qos(m).await?,
            Method::BasicConsume(m) => self.basic_consume(m).await?,
            Method::BasicCancel(m) => self.basic_cancel(m).await?,
            Method::BasicPublish(m) => self.basic_publish(m)?,
            Method::BasicGet(m) => self.basic_get(m).await?,
            Method::BasicAck(m) => {
                self.settle(m.delivery_tag, m.multiple, basic::Settle::Ack)
                    .await?
            }
            Method::BasicReject(m) => {
                self.settle(
                    m.delivery_tag,
                    false,
                    basic::Settle::Reject { requeue: m.requeue },
                )
                .await?
            }
            Method::BasicNack(m) => {
                self.settle(
                    m.delivery_tag,
                    m.multiple,
                    basic::Settle::Reject { requeue: m.requeue },
                )
                .await?
            }
            Method::BasicRecover(m) => self.basic_recover(m.requeue, true).await?,
            Method::BasicRecoverAsync(m) => self.basic_recover(m.requeue, false).await?,
            Method::TxSelect(_) => self.tx_select().await?,
            Method::TxCommit(_) => self.tx_commit().await?,
            Method::TxRollback(_) => self.tx_rollback().await?,
            Method::ConfirmSelect(m) => self.confirm_select(m.no_wait).await?,
            other => {
                return Err(AmqpError::command_invalid(format_args!(
                    "method {} is not valid from a client on a channel",
                    other.name()
                )))
            }
        }
        Ok(false)
    }

    async fn handle_header(&mut self, header: ContentHeader) -> AmqpResult<bool> {
        let Assembly::Header(publish) = std::mem::replace(&mut self.assembly, Assembly::Idle)
        else {
            return Err(AmqpError::unexpected_frame(format_args!(
                "expected method frame, got content header frame on channel {}",
                self.id
            )));
        };
        if header.class_id != ContentHeader::BASIC_CLASS {
            return Err(AmqpError::frame_error(format_args!(
                "content header for class {} on a basic.publish",
                header.class_id
            ))
            .during_ids(60, 40));
        }
        let properties = header
            .properties()
            .map_err(|e| AmqpError::new(e.reply_code(), &e).during_ids(60, 40))?;
        let max = self.core.limits.max_message_size;
        if header.body_size > max {
            return Err(AmqpError::precondition_failed(format_args!(
                "message size {} is larger than configured max size {}",
                header.body_size, max
            ))
            .during_ids(60, 40));
        }
        if header.body_size == 0 {
            self.publish(Publish {
                method: publish,
                properties,
                property_bytes: header.property_bytes,
                body: Bytes::new(),
            })
            .await?;
        } else {
            self.assembly = Assembly::Body {
                publish,
                properties,
                property_bytes: header.property_bytes,
                size: header.body_size,
                first: None,
                rest: None,
                received: 0,
            };
        }
        Ok(false)
    }

    async fn handle_body(&mut self, payload: Bytes) -> AmqpResult<bool> {
        let Assembly::Body {
            size,
            first,
            rest,
            received,
            ..
        } = &mut self.assembly
        else {
            return Err(AmqpError::unexpected_frame(format_args!(
                "expected method frame, got content body frame on channel {}",
                self.id
            )));
        };
        *received += payload.len() as u64;
        if *received > *size {
            return Err(AmqpError::unexpected_frame(format_args!(
                "content body of {} bytes exceeds the {} declared in its header",
                received, size
            ))
            .during_ids(60, 40));
        }
        // A body in one frame stays a slice of the read buffer; bodies in
        // several frames are joined once.
        match (first.as_ref(), rest.as_mut()) {
            (None, _) => *first = Some(payload),
            (Some(head), None) => {
                let mut joined = BytesMut::with_capacity(*size as usize);
                joined.extend_from_slice(head);
                joined.extend_from_slice(&payload);
                *rest = Some(joined);
            }
            (Some(_), Some(joined)) => joined.extend_from_slice(&payload),
        }
        if received < size {
            return Ok(false);
        }
        let Assembly::Body {
            publish,
            properties,
            property_bytes,
            first,
            rest,
            ..
        } = std::mem::replace(&mut self.assembly, Assembly::Idle)
        else {
            return Ok(false);
        };
        let body = match rest {
            Some(joined) => joined.freeze(),
            None => first.unwrap_or_default(),
        };
        self.publish(Publish {
            method: publish,
            properties,
            property_bytes,
            body,
        })
        .await?;
        Ok(false)
    }

    /// Releases what the channel holds: cancels its consumers and requeues
    /// its unacked messages in their original order. Uncommitted
    /// transactional work is dropped.
    pub fn cleanup(mut self) {
        self.release();
    }

    fn release(&mut self) {
        self.drop_direct_reply();
        for (_, (consumer, queue)) in self.consumers.drain() {
            if queue.remove_consumer(&consumer) {
                self.vhost.delete_queue(&queue).notify();
            }
        }
        self.abandon_tx();
        let unacked = self.link.deliveries().take_all();
        basic::requeue_all(unacked);
    }
}
