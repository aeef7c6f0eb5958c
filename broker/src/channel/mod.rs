//! One channel's state machine: content assembly (method → header → body),
//! method dispatch to the per-class handlers (`exchange`, `queue`,
//! `basic`, `tx`), soft errors (channel.close and discarding frames until
//! close-ok), and releasing what a closed channel held.
//!
//! Content assembly keeps nothing that points into the connection's read
//! buffer (which would pin the whole buffer for as long as the message is
//! queued): a body in one frame is copied when it is smaller than the
//! connection's `copy_below`, property lists and long exchange names and
//! routing keys likewise; a body in several frames is copied into one
//! buffer of its announced size, counted in the memory gauge from its
//! first body frame until the message is routed or dropped.
//!
//! Layout: `basic.rs` publishing, consuming, acks and get; `queue.rs`
//! queue.*; `exchange.rs` exchange.*; `tx.rs` transactions; `confirms.rs`
//! publisher confirms, watching the store itself; `reply_to.rs` direct
//! reply-to; `names.rs` generated names. A publish is routed here and
//! handed to the vhost's publish step, which stores it and offers it to its
//! queues (`vhost::publish`).

mod basic;
pub(crate) mod confirms;
mod exchange;
mod names;
mod queue;
mod reply_to;
mod tx;

use crate::access::permissions::{AccessView, Resource, Right};
use crate::alarm::memory::{MemoryGauge, Reservation};
use crate::core::Core;
use crate::error::{AmqpError, AmqpResult};
use crate::exchange::{Exchange, ExchangeKind};
use crate::outbox::Outbox;
use crate::queue::{ChannelLink, Consumer, Queue};
use crate::registry::ChannelRegistration;
use crate::vhost::{RememberedQueue, Vhost};
use basic::Unfinished;

pub(crate) use basic::{apply_settles, Settle};
use bytes::{Bytes, BytesMut};
use leveret_protocol::{
    BasicProperties, BasicPublish, ChannelClose, ChannelCloseOk, ChannelFlowOk, ContentHeader,
    Frame, Method, ShortStr,
};
#[cfg(feature = "mqtt")]
pub(crate) use names::unique_name;
use std::collections::HashMap;
use std::sync::Arc;

/// A basic.publish with its content, received as one value (from an
/// in-process client): what its three frames would carry, with the
/// properties not encoded. A channel takes it whole, with nothing to
/// assemble.
#[derive(Debug)]
pub(crate) struct WholePublish {
    pub channel: u16,
    pub method: BasicPublish,
    pub properties: Box<BasicProperties>,
    pub body: Bytes,
}

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
        properties: Box<BasicProperties>,
        property_bytes: Bytes,
        size: u64,
        /// Set from the first body frame of a body that takes several.
        partial: Option<PartialBody>,
    },
}

/// A body arriving in several frames, copied into a buffer of its
/// announced size, which the memory gauge counts until it is dropped.
#[derive(Debug)]
struct PartialBody {
    bytes: Vec<u8>,
    reservation: Reservation,
}

impl PartialBody {
    /// The buffer for a body of `size` bytes whose first frame is `first`,
    /// counted in `gauge` at its full size. A buffer that cannot be
    /// allocated is 506 RESOURCE_ERROR, never an abort.
    fn start(gauge: &Arc<MemoryGauge>, size: u64, first: &[u8]) -> AmqpResult<Self> {
        let capacity = usize::try_from(size).map_err(|_| resource_error(size))?;
        let mut bytes = Vec::new();
        bytes
            .try_reserve_exact(capacity)
            .map_err(|_| resource_error(size))?;
        bytes.extend_from_slice(first);
        Ok(PartialBody {
            bytes,
            reservation: gauge.reserve(capacity),
        })
    }
}

/// A fully assembled publish.
#[derive(Debug)]
pub(crate) struct Publish {
    method: BasicPublish,
    /// Boxed: decoded properties are ~450 bytes, and a publish moves
    /// through several async calls (each move a copy of it).
    properties: Box<BasicProperties>,
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

/// What handling a frame at once left to do, for [`Channel::finish`].
#[derive(Debug)]
pub enum Leftover {
    /// A publish that waits (see [`Channel::publish`]).
    Publish(Box<Unfinished>),
    /// An error: a channel error closes the channel, a connection error
    /// the connection.
    Failed(AmqpError),
}

/// How a frame fared in [`Channel::handle_at_once`].
#[derive(Debug)]
pub enum AtOnce {
    /// Handled, but for what it left, if anything.
    Handled(Option<Leftover>),
    /// Not a frame handled at once: given back.
    Declined(Frame),
}

impl Leftover {
    fn of(handled: AmqpResult<Option<Box<Unfinished>>>) -> Option<Leftover> {
        match handled {
            Ok(rest) => rest.map(Leftover::Publish),
            Err(error) => Some(Leftover::Failed(error)),
        }
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
    /// The exchange the last publish named: most publishers name one, and
    /// looking it up again hashes its name under the vhost's lock.
    last_exchange: Option<Arc<Exchange>>,
    /// The queue the last publish to the default exchange reached.
    last_routed_queue: Option<RememberedQueue>,
    tx: Option<tx::Transaction>,
    confirms: Option<confirms::Confirms>,
    direct_reply: Option<reply_to::DirectReply>,
    /// A queue this channel published to that is over the flow limit.
    crowded: Option<Arc<Queue>>,
    /// Keeps the channel listed (`registry`) until it is dropped.
    registration: ChannelRegistration,
    /// Content smaller than this is copied out of the read buffer.
    copy_below: usize,
    /// What the user may do in the vhost.
    access: AccessView,
}

impl Channel {
    /// A newly opened channel; content below `copy_below` bytes is copied
    /// out of the connection's read buffer.
    pub fn new(
        id: u16,
        outbox: Arc<Outbox>,
        vhost: Arc<Vhost>,
        core: Arc<Core>,
        user: String,
        copy_below: usize,
    ) -> Self {
        let link = Arc::new(ChannelLink::new(id, outbox));
        let access = AccessView::new(
            Arc::clone(&core.permissions),
            &user,
            &vhost.name.to_string_lossy(),
        );
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
            last_exchange: None,
            last_routed_queue: None,
            tx: None,
            confirms: None,
            direct_reply: None,
            crowded: None,
            copy_below,
            access,
        }
    }

    /// Checks the user's `right` on the queue `name`.
    fn allow_queue(&mut self, right: Right, name: &[u8]) -> AmqpResult<()> {
        self.access
            .check(right, Resource::Queue(&String::from_utf8_lossy(name)))
    }

    /// Checks the user's `right` on the exchange `name`.
    fn allow_exchange(&mut self, right: Right, name: &[u8]) -> AmqpResult<()> {
        self.access
            .check(right, Resource::Exchange(&String::from_utf8_lossy(name)))
    }

    /// Checks a routing key against the user's topic permission when
    /// `exchange` is a topic exchange (`Write` for publishing, `Read` for
    /// binding). Takes the exchange the caller has already looked up.
    fn allow_topic(
        &mut self,
        right: Right,
        exchange: &Exchange,
        routing_key: &ShortStr,
    ) -> AmqpResult<()> {
        let access = self.access.current()?;
        if !access.has_topic_permissions() || exchange.kind != ExchangeKind::Topic {
            return Ok(());
        }
        access.check_topic(
            right,
            &exchange.name.to_string_lossy(),
            &routing_key.to_string_lossy(),
        )
    }

    /// [`Channel::allow_topic`] for a binding change from the exchange
    /// `name`, if it exists (a missing one is the binding's 404).
    fn allow_topic_binding(&mut self, name: &ShortStr, routing_key: &ShortStr) -> AmqpResult<()> {
        match self.vhost.exchange(name) {
            Some(exchange) => self.allow_topic(Right::Read, &exchange, routing_key),
            None => Ok(()),
        }
    }

    fn outbox(&self) -> &Outbox {
        &self.link.outbox
    }

    async fn reply(&self, method: impl Into<Method>) {
        self.link.outbox.method(self.id, method).await;
    }

    /// Waits until every store write submitted so far (among them the
    /// definition change this channel just made) is flushed, so a -ok for
    /// something durable goes out only once it is on disk. It rides the
    /// persister's group commit: one flush covers every waiter.
    async fn definitions_on_disk(&self) -> AmqpResult<()> {
        match &self.core.persistence {
            Some(persistence) if !persistence.sync().await => Err(AmqpError::resource_error(
                "could not write the definition to disk",
            )),
            _ => Ok(()),
        }
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

    /// Whether a message's header or body frames are still to come.
    pub fn is_receiving_content(&self) -> bool {
        !matches!(self.assembly, Assembly::Idle)
    }

    /// Handles a frame [`Channel::handle_at_once`] gave back: a method
    /// other than the messaging ones, or any frame while the channel
    /// closes. `Ok(true)` means the channel is finished and must be
    /// removed; `Err` is a connection-level error.
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
                    Box::pin(self.reply(ChannelCloseOk {})).await;
                    Ok(false)
                }
                _ => Ok(false),
            };
        }
        let Frame::Method { method, .. } = frame else {
            // Content frames are handled at once; a heartbeat is not a
            // channel's.
            return Ok(false);
        };
        match self.handle_method(method).await {
            Err(error) => self.fail(error).await.map(|()| false),
            done => done,
        }
    }

    /// Handles at once the frames that never wait: content frames,
    /// basic.publish and basic.ack, the messaging path, so that theirs
    /// take no future (see [`Channel::publish`]). What is left, if
    /// anything, is for [`Channel::finish`]; any other frame, and every
    /// frame while the channel closes, is given back.
    pub fn handle_at_once(&mut self, frame: Frame) -> AtOnce {
        if self.closing {
            return AtOnce::Declined(frame);
        }
        let handled = match frame {
            Frame::Header { header, .. } => self.handle_header(header),
            Frame::Body { payload, .. } => self.handle_body(payload),
            Frame::Method {
                method: Method::BasicPublish(publish),
                ..
            } => self.publish_method(publish).map(|()| None),
            Frame::Method {
                method: Method::BasicAck(ack),
                ..
            } => self
                .expect_no_content("basic.ack")
                .and_then(|()| self.settle(ack.delivery_tag, ack.multiple, basic::Settle::Ack))
                .map_err(|e| e.during_ids(60, 80))
                .map(|()| None),
            frame => return AtOnce::Declined(frame),
        };
        AtOnce::Handled(Leftover::of(handled))
    }

    /// Handles a publish received whole, as its method, content header
    /// and body frame would be handled one after the other (a closing
    /// channel drops it); only the properties are encoded here, for the
    /// message, instead of decoded from a header. What is left, if
    /// anything, is for [`Channel::finish`].
    pub(crate) fn publish_at_once(&mut self, whole: WholePublish) -> Option<Leftover> {
        if self.closing {
            return None;
        }
        Leftover::of(self.publish_whole(whole))
    }

    /// Does what handling at once left. `Err` is a connection-level error.
    pub async fn finish(&mut self, leftover: Leftover) -> AmqpResult<()> {
        match leftover {
            Leftover::Publish(rest) => {
                Box::pin(self.finish_publish(rest)).await;
                Ok(())
            }
            Leftover::Failed(error) => self.fail(error).await,
        }
    }

    /// A channel error closes the channel; a connection error is returned,
    /// for the connection to close.
    async fn fail(&mut self, error: AmqpError) -> AmqpResult<()> {
        if error.is_connection_error() {
            return Err(error);
        }
        tracing::debug!(channel = self.id, %error, "closing channel");
        // On the heap, as the rare methods: see handle_method.
        Box::pin(self.close_with(error)).await;
        Ok(())
    }

    fn publish_whole(&mut self, whole: WholePublish) -> AmqpResult<Option<Box<Unfinished>>> {
        let WholePublish {
            method,
            properties,
            body,
            ..
        } = whole;
        self.publish_method(method)?;
        let Assembly::Header(publish) = std::mem::replace(&mut self.assembly, Assembly::Idle)
        else {
            return Ok(None);
        };
        let mut encoded = BytesMut::new();
        properties.encode(&mut encoded);
        let property_bytes = self.kept(encoded.freeze());
        let size = body.len() as u64;
        let unfinished = self.content_header(publish, properties, property_bytes, size)?;
        if size > 0 {
            return self.handle_body(body);
        }
        Ok(unfinished)
    }

    /// basic.publish: its content follows.
    fn publish_method(&mut self, method: BasicPublish) -> AmqpResult<()> {
        self.expect_no_content("basic.publish")
            .and_then(|()| self.basic_publish(method))
            .map_err(|e| e.during_ids(60, 40))
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

    /// A method frame may come only between messages.
    fn expect_no_content(&self, method_name: &str) -> AmqpResult<()> {
        if matches!(self.assembly, Assembly::Idle) {
            return Ok(());
        }
        Err(AmqpError::unexpected_frame(format_args!(
            "expected content header for class 60, got non content header frame instead ({method_name})"
        ))
        .during_ids(60, 40))
    }

    async fn handle_method(&mut self, method: Method) -> AmqpResult<bool> {
        self.expect_no_content(method.name())?;
        let ids = (method.class_id(), method.method_id());
        // In a future of its own on the heap, so the future of every frame
        // (created and moved per frame) stays small.
        let result = Box::pin(self.dispatch(method)).await;
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
            Method::ExchangeBind(m) => self.exchange_bind(m).await?,
            Method::ExchangeUnbind(m) => self.exchange_unbind(m).await?,
            Method::QueueDeclare(m) => self.queue_declare(m).await?,
            Method::QueueBind(m) => self.queue_bind(m).await?,
            Method::QueueUnbind(m) => self.queue_unbind(m).await?,
            Method::QueuePurge(m) => self.queue_purge(m).await?,
            Method::QueueDelete(m) => self.queue_delete(m).await?,
            Method::BasicQos(m) => self.basic_qos(m).await?,
            Method::BasicConsume(m) => self.basic_consume(m).await?,
            Method::BasicCancel(m) => self.basic_cancel(m).await?,
            Method::BasicGet(m) => self.basic_get(m).await?,
            Method::BasicReject(m) => self.settle(
                m.delivery_tag,
                false,
                basic::Settle::Reject { requeue: m.requeue },
            )?,
            Method::BasicNack(m) => self.settle(
                m.delivery_tag,
                m.multiple,
                basic::Settle::Reject { requeue: m.requeue },
            )?,
            Method::BasicRecover(m) => {
                self.basic_recover(m.requeue, basic::Recover::Answered)
                    .await?
            }
            Method::BasicRecoverAsync(m) => {
                self.basic_recover(m.requeue, basic::Recover::Unanswered)
                    .await?
            }
            Method::TxSelect(_) => self.tx_select().await?,
            Method::TxCommit(_) => self.tx_commit().await?,
            Method::TxRollback(_) => self.tx_rollback().await?,
            Method::ConfirmSelect(m) => self.confirm_select(m.no_wait).await?,
            // basic.publish and basic.ack are handled before dispatch.
            other => {
                return Err(AmqpError::command_invalid(format_args!(
                    "method {} is not valid from a client on a channel",
                    other.name()
                )))
            }
        }
        Ok(false)
    }

    fn handle_header(&mut self, header: ContentHeader) -> AmqpResult<Option<Box<Unfinished>>> {
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
        let property_bytes = self.kept(header.property_bytes);
        let properties = BasicProperties::decode(&property_bytes)
            .map(Box::new)
            .map_err(|e| AmqpError::new(e.reply_code(), &e).during_ids(60, 40))?;
        self.content_header(publish, properties, property_bytes, header.body_size)
    }

    /// A publish's content header, its properties decoded: checks its
    /// size, then publishes a message without body or waits for the body.
    fn content_header(
        &mut self,
        publish: BasicPublish,
        properties: Box<BasicProperties>,
        property_bytes: Bytes,
        body_size: u64,
    ) -> AmqpResult<Option<Box<Unfinished>>> {
        let max = self.core.limits.max_message_size;
        if body_size > max {
            return Err(AmqpError::precondition_failed(format_args!(
                "message size {} is larger than configured max size {}",
                body_size, max
            ))
            .during_ids(60, 40));
        }
        let publish = BasicPublish {
            exchange: kept_short(publish.exchange),
            routing_key: kept_short(publish.routing_key),
            ..publish
        };
        if body_size == 0 {
            return self.publish(Publish {
                method: publish,
                properties,
                property_bytes,
                body: Bytes::new(),
            });
        }
        self.assembly = Assembly::Body {
            publish,
            properties,
            property_bytes,
            size: body_size,
            partial: None,
        };
        Ok(None)
    }

    fn handle_body(&mut self, payload: Bytes) -> AmqpResult<Option<Box<Unfinished>>> {
        let Assembly::Body { size, partial, .. } = &mut self.assembly else {
            return Err(AmqpError::unexpected_frame(format_args!(
                "expected method frame, got content body frame on channel {}",
                self.id
            )));
        };
        let size = *size;
        let before = partial.as_ref().map_or(0, |p| p.bytes.len());
        let received = before as u64 + payload.len() as u64;
        if received > size {
            return Err(AmqpError::unexpected_frame(format_args!(
                "content body of {} bytes exceeds the {} declared in its header",
                received, size
            ))
            .during_ids(60, 40));
        }
        if received < size {
            match partial {
                Some(partial) => partial.bytes.extend_from_slice(&payload),
                None => *partial = Some(PartialBody::start(&self.core.gauge, size, &payload)?),
            }
            return Ok(None);
        }
        let Assembly::Body {
            publish,
            properties,
            property_bytes,
            partial,
            ..
        } = std::mem::replace(&mut self.assembly, Assembly::Idle)
        else {
            return Ok(None);
        };
        // The reservation lasts until the message is routed (or refused).
        let (body, _reservation) = match partial {
            Some(PartialBody {
                mut bytes,
                reservation,
            }) => {
                bytes.extend_from_slice(&payload);
                (Bytes::from(bytes), Some(reservation))
            }
            None => (self.kept(payload), None),
        };
        self.publish(Publish {
            method: publish,
            properties,
            property_bytes,
            body,
        })
    }

    /// `bytes` as the message will keep them: copied out of the read
    /// buffer when small (see the module docs).
    fn kept(&self, bytes: Bytes) -> Bytes {
        // A message without properties: two flag bytes, shared by all.
        const NO_PROPERTIES: &[u8] = &[0, 0];
        if bytes.as_ref() == NO_PROPERTIES {
            Bytes::from_static(NO_PROPERTIES)
        } else if bytes.len() < self.copy_below {
            Bytes::copy_from_slice(&bytes)
        } else {
            bytes
        }
    }

    /// Releases what the channel holds: cancels its consumers and requeues
    /// its unacked messages in their original order. Uncommitted
    /// transactional work and unsent confirms are dropped.
    pub fn cleanup(mut self) {
        self.release();
    }

    fn release(&mut self) {
        // A body being received is dropped with its reservation.
        self.assembly = Assembly::Idle;
        self.drop_direct_reply();
        let mut kept = Vec::new();
        for (_, (consumer, queue)) in self.consumers.drain() {
            if queue.remove_consumer(&consumer) {
                self.vhost.delete_queue(&queue).notify();
            } else {
                kept.push(queue);
            }
        }
        self.abandon_tx();
        self.drop_confirms();
        let unacked = self.link.deliveries().take_all();
        self.vhost.dead_letter(basic::requeue_all(unacked));
        // Only now may a single active consumer's successor take over: the
        // messages requeued above go to it first, in their order.
        for queue in kept {
            self.vhost.dead_letter(queue.dispatch());
        }
    }
}

/// The longest short string `leveret_protocol` keeps inline (owned);
/// longer ones are decoded as slices of the frame.
const INLINE_SHORT_STR: usize = 23;

/// A short string that owns its bytes.
fn kept_short(s: ShortStr) -> ShortStr {
    if s.len() <= INLINE_SHORT_STR {
        return s;
    }
    ShortStr::try_from(Bytes::copy_from_slice(s.as_bytes())).unwrap_or(s)
}

fn resource_error(size: u64) -> AmqpError {
    AmqpError::new(
        leveret_protocol::ReplyCode::ResourceError,
        format_args!("cannot allocate {size} bytes for a message body"),
    )
    .during_ids(60, 40)
}
