//! The reader task: owns the transport's read half, decodes frames (bodies
//! stay `Bytes` slices of the read buffer), answers `connection.*` methods,
//! assembles content (method, header, body frames) per channel and routes
//! everything to its channel: replies to the waiting call, deliveries to
//! their consumer (its sink first, if it has one), returns, confirms. Two
//! heartbeat intervals without a byte from the broker end the connection.

use super::frames::{FrameInput, WholeContent, Writer};
use super::{reason, Shared};
use crate::channel::{ChannelShared, Reply};
use crate::error::Error;
use crate::message::{Content, Delivery, ReturnedMessage};
use bytes::{Bytes, BytesMut};
use leveret_protocol::Outgoing;
use leveret_protocol::{
    BasicCancelOk, BasicProperties, ChannelCloseOk, ChannelFlowOk, ConnectionClose,
    ConnectionCloseOk, ContentHeader, DecodeError, Frame, Method, ReplyCode, ShortStr,
};
use std::collections::HashMap;
use std::sync::Arc;
use std::time::Duration;
use tokio::sync::oneshot;

/// How long a close may wait for the broker's close-ok, and for the
/// writer to flush before it is stopped.
const CLOSE_TIMEOUT: Duration = Duration::from_secs(5);

/// A method whose content is being assembled.
struct Incoming {
    method: Method,
    properties: Option<BasicProperties>,
    size: u64,
    body: Body,
}

/// A body as it arrives: one frame stays a slice of the read buffer; only
/// a body split over several frames is copied, once, into one buffer.
enum Body {
    Empty,
    One(Bytes),
    Many(BytesMut),
}

impl Body {
    fn len(&self) -> usize {
        match self {
            Body::Empty => 0,
            Body::One(b) => b.len(),
            Body::Many(b) => b.len(),
        }
    }

    fn push(&mut self, piece: Bytes, size: u64) {
        *self = match std::mem::replace(self, Body::Empty) {
            Body::Empty => Body::One(piece),
            Body::One(first) => {
                let mut all = BytesMut::with_capacity(usize::try_from(size).unwrap_or(0));
                all.extend_from_slice(&first);
                all.extend_from_slice(&piece);
                Body::Many(all)
            }
            Body::Many(mut all) => {
                all.extend_from_slice(&piece);
                Body::Many(all)
            }
        }
    }

    fn freeze(self) -> Bytes {
        match self {
            Body::Empty => Bytes::new(),
            Body::One(b) => b,
            Body::Many(b) => b.freeze(),
        }
    }
}

/// A broken rule of the protocol, answered with connection.close.
struct Violation {
    code: ReplyCode,
    text: String,
    class_id: u16,
    method_id: u16,
}

impl Violation {
    fn new(code: ReplyCode, text: impl Into<String>) -> Self {
        Violation {
            code,
            text: text.into(),
            class_id: 0,
            method_id: 0,
        }
    }
}

/// What the reader does next.
enum Flow {
    Continue,
    End(Error),
}

/// What the reader takes next from its input.
enum Input {
    Frame(Frame),
    Content(WholeContent),
}

/// Why reading a frame failed.
enum ReadError {
    Ended(Error),
    Decode(DecodeError),
}

struct Reader<I> {
    shared: Arc<Shared>,
    input: I,
    frame_max: u32,
    heartbeat: Duration,
    incoming: HashMap<u16, Incoming>,
    /// Set when the reader itself closed the connection for a violation.
    violation: Option<Error>,
}

/// Runs the reader until the connection ends, then fails everything still
/// waiting and stops the writer.
pub(crate) async fn run<I: FrameInput>(
    shared: Arc<Shared>,
    input: I,
    heartbeat: Duration,
    writer: Option<Writer>,
) {
    let frame_max = shared.tuning.frame_max;
    let mut reader = Reader {
        shared: Arc::clone(&shared),
        input,
        frame_max,
        heartbeat,
        incoming: HashMap::new(),
        violation: None,
    };
    let (task, failed) = match writer {
        Some(Writer { task, failed }) => (Some(task), Some(failed)),
        None => (None, None),
    };
    let error = reader.run(failed).await;
    tracing::debug!(%error, "AMQP connection ended");
    shared.finish(error);
    let stop = shared.tx.send(Outgoing::Shutdown);
    if tokio::time::timeout(CLOSE_TIMEOUT, stop).await.is_err() {
        if let Some(task) = task {
            task.abort();
        }
    }
}

impl<I: FrameInput> Reader<I> {
    /// Reads until the connection ends; `writer_failed` reports a writer
    /// task's failure where one drains the outbox.
    async fn run(&mut self, writer_failed: Option<oneshot::Receiver<std::io::Error>>) -> Error {
        let writer_failed = async move {
            match writer_failed {
                Some(failed) => failed.await,
                None => std::future::pending().await,
            }
        };
        tokio::pin!(writer_failed);
        let mut closing = self.shared.closing.subscribe();
        let close_deadline = async move {
            let _ = closing.wait_for(|c| *c).await;
            tokio::time::sleep(CLOSE_TIMEOUT).await;
        };
        tokio::pin!(close_deadline);
        loop {
            let input = tokio::select! {
                input = self.next_input() => input,
                failed = &mut writer_failed => match failed {
                    Ok(error) => return Error::io(error),
                    // The writer stopped without error: only after Shutdown.
                    Err(_) => return self.ending_error(Error::Closed),
                },
                _ = &mut close_deadline => {
                    tracing::debug!("no connection.close-ok from the broker; giving up");
                    return self.ending_error(Error::Closed);
                }
            };
            let result = match input {
                Ok(Input::Frame(frame)) => self.handle(frame).await,
                Ok(Input::Content(content)) => self.whole_content(content).await,
                Err(ReadError::Ended(error)) => return self.ending_error(error),
                Err(ReadError::Decode(e)) => {
                    // No frame boundary can be trusted any more: send
                    // connection.close (the writer flushes it before it
                    // stops) and end without waiting for close-ok.
                    let (class_id, method_id) = e.method_ids();
                    self.violate(Violation {
                        code: e.reply_code(),
                        text: e.to_string(),
                        class_id,
                        method_id,
                    })
                    .await;
                    return self.ending_error(Error::Protocol(e.to_string()));
                }
            };
            match result {
                Ok(Flow::Continue) => {}
                Ok(Flow::End(error)) => return self.ending_error(error),
                Err(violation) => self.violate(violation).await,
            }
        }
    }

    /// A violation's error wins over how the close then went.
    fn ending_error(&mut self, error: Error) -> Error {
        self.violation.take().unwrap_or(error)
    }

    async fn next_input(&mut self) -> Result<Input, ReadError> {
        loop {
            if let Some(content) = self.input.buffered_content() {
                return Ok(Input::Content(content));
            }
            match self.input.buffered(self.frame_max) {
                Ok(Some(frame)) => return Ok(Input::Frame(frame)),
                Ok(None) => {}
                Err(e) => return Err(ReadError::Decode(e)),
            }
            let read = self.input.receive();
            let read = if self.heartbeat.is_zero() {
                read.await
            } else {
                match tokio::time::timeout(self.heartbeat * 2, read).await {
                    Ok(read) => read,
                    Err(_) => return Err(ReadError::Ended(Error::MissedHeartbeats)),
                }
            };
            match read {
                Ok(true) => {}
                Ok(false) => {
                    return Err(ReadError::Ended(Error::io(std::io::Error::new(
                        std::io::ErrorKind::UnexpectedEof,
                        "the broker closed the connection",
                    ))))
                }
                Err(e) => return Err(ReadError::Ended(Error::io(e))),
            }
        }
    }

    /// Sends a method from the reader (close-ok and the like).
    async fn send(&self, channel: u16, method: impl Into<Method>) {
        let item = Outgoing::Method {
            channel,
            method: method.into(),
        };
        let _ = tokio::time::timeout(CLOSE_TIMEOUT, self.shared.tx.send(item)).await;
    }

    /// Closes the connection for a violation by the broker; the loop then
    /// waits for close-ok, ignoring everything else.
    async fn violate(&mut self, violation: Violation) {
        tracing::warn!(code = %violation.code, text = %violation.text, "AMQP protocol violation by the broker; closing");
        if !self.shared.mark_closing() {
            return;
        }
        self.violation = Some(Error::Protocol(violation.text.clone()));
        let mut text = format!("{} - {}", violation.code.name(), violation.text);
        text.truncate(ShortStr::MAX_LEN);
        while !text.is_char_boundary(text.len()) {
            text.pop();
        }
        self.send(
            0,
            ConnectionClose {
                reply_code: violation.code.code(),
                reply_text: ShortStr::try_from(text).unwrap_or_default(),
                class_id: violation.class_id,
                method_id: violation.method_id,
            },
        )
        .await;
    }

    async fn handle(&mut self, frame: Frame) -> Result<Flow, Violation> {
        let closing = *self.shared.closing.borrow();
        match frame {
            Frame::Heartbeat => Ok(Flow::Continue),
            Frame::Method { channel: 0, method } => self.connection_method(method).await,
            Frame::Header { channel: 0, .. } | Frame::Body { channel: 0, .. } => Err(
                Violation::new(ReplyCode::UnexpectedFrame, "content frame on channel 0"),
            ),
            // Closing: the spec says to discard everything but close/close-ok.
            _ if closing => Ok(Flow::Continue),
            Frame::Method { channel, method } => self.channel_method(channel, method).await,
            Frame::Header { channel, header } => self.header(channel, header).await,
            Frame::Body { channel, payload } => self.body(channel, payload).await,
        }
    }

    async fn connection_method(&mut self, method: Method) -> Result<Flow, Violation> {
        match method {
            Method::ConnectionClose(close) => {
                self.send(0, ConnectionCloseOk {}).await;
                let reason = reason(
                    &close.reply_text,
                    close.reply_code,
                    close.class_id,
                    close.method_id,
                );
                tracing::debug!(%reason, "the broker closed the connection");
                Ok(Flow::End(Error::ConnectionClosed(reason)))
            }
            Method::ConnectionCloseOk(_) => Ok(Flow::End(Error::Closed)),
            Method::ConnectionBlocked(blocked) => {
                let reason = blocked.reason.to_string_lossy().into_owned();
                self.shared.blocked.send_replace(Some(reason));
                Ok(Flow::Continue)
            }
            Method::ConnectionUnblocked(_) => {
                self.shared.blocked.send_replace(None);
                Ok(Flow::Continue)
            }
            Method::ConnectionUpdateSecretOk(_) => Ok(Flow::Continue),
            _ if *self.shared.closing.borrow() => Ok(Flow::Continue),
            other => Err(Violation::new(
                ReplyCode::CommandInvalid,
                format!("unexpected {} on channel 0", other.name()),
            )),
        }
    }

    /// A method (other than content) on a channel that is in the middle
    /// of receiving content is a framing error.
    fn no_content_pending(&self, channel: u16, method: &Method) -> Result<(), Violation> {
        if self.incoming.contains_key(&channel) {
            return Err(Violation::new(
                ReplyCode::UnexpectedFrame,
                format!(
                    "{} on channel {channel} while content was expected",
                    method.name()
                ),
            ));
        }
        Ok(())
    }

    async fn channel_method(&mut self, channel: u16, method: Method) -> Result<Flow, Violation> {
        self.no_content_pending(channel, &method)?;
        if method.has_content() {
            // Assembled even for a channel already gone, to keep the frame
            // sequence checked; dropped when complete.
            self.incoming.insert(
                channel,
                Incoming {
                    method,
                    properties: None,
                    size: 0,
                    body: Body::Empty,
                },
            );
            return Ok(Flow::Continue);
        }
        let Some(chan) = self.shared.channel(channel) else {
            if let Method::ChannelClose(_) = method {
                self.send(channel, ChannelCloseOk {}).await;
            }
            return Ok(Flow::Continue);
        };
        match method {
            Method::ChannelClose(close) => {
                let reason = reason(
                    &close.reply_text,
                    close.reply_code,
                    close.class_id,
                    close.method_id,
                );
                tracing::debug!(channel, %reason, "the broker closed a channel");
                // In this order: once closed, no call can queue a frame
                // behind the close-ok (the broker would take it for a
                // frame on a channel that is not open, a connection
                // error); the number is free only once close-ok is queued.
                chan.finish(Error::ChannelClosed(reason));
                self.send(channel, ChannelCloseOk {}).await;
                self.shared.remove_channel(&chan);
            }
            Method::ChannelCloseOk(_) => {
                if chan.is_closing() {
                    self.shared.remove_channel(&chan);
                    chan.finish(Error::Closed);
                }
            }
            Method::BasicAck(ack) => chan.confirmed(ack.delivery_tag, ack.multiple, true),
            Method::BasicNack(nack) => chan.confirmed(nack.delivery_tag, nack.multiple, false),
            Method::BasicCancel(cancel) => {
                chan.cancelled_by_broker(&cancel.consumer_tag);
                if !cancel.no_wait {
                    let ok = BasicCancelOk {
                        consumer_tag: cancel.consumer_tag,
                    };
                    self.send(channel, ok).await;
                }
            }
            Method::ChannelFlow(flow) => {
                self.send(
                    channel,
                    ChannelFlowOk {
                        active: flow.active,
                    },
                )
                .await;
            }
            other => chan
                .complete(Reply {
                    method: other,
                    content: None,
                })
                .map_err(|text| Violation::new(ReplyCode::UnexpectedFrame, text))?,
        }
        Ok(Flow::Continue)
    }

    async fn header(&mut self, channel: u16, header: ContentHeader) -> Result<Flow, Violation> {
        let Some(incoming) = self.incoming.get_mut(&channel) else {
            return Err(Violation::new(
                ReplyCode::UnexpectedFrame,
                format!("content header on channel {channel} without a method"),
            ));
        };
        if incoming.properties.is_some() {
            return Err(Violation::new(
                ReplyCode::UnexpectedFrame,
                format!("second content header on channel {channel}"),
            ));
        }
        let properties = header
            .properties()
            .map_err(|e| Violation::new(e.reply_code(), e.to_string()))?;
        incoming.properties = Some(properties);
        incoming.size = header.body_size;
        if header.body_size == 0 {
            return self.complete(channel).await;
        }
        Ok(Flow::Continue)
    }

    async fn body(&mut self, channel: u16, payload: Bytes) -> Result<Flow, Violation> {
        let Some(incoming) = self.incoming.get_mut(&channel) else {
            return Err(Violation::new(
                ReplyCode::UnexpectedFrame,
                format!("body frame on channel {channel} without a method"),
            ));
        };
        if incoming.properties.is_none() {
            return Err(Violation::new(
                ReplyCode::UnexpectedFrame,
                format!("body frame on channel {channel} before the content header"),
            ));
        }
        let received = (incoming.body.len() + payload.len()) as u64;
        if received > incoming.size {
            return Err(Violation::new(
                ReplyCode::FrameError,
                format!(
                    "body on channel {channel} longer than the {} bytes announced",
                    incoming.size
                ),
            ));
        }
        let size = incoming.size;
        incoming.body.push(payload, size);
        if received == size {
            return self.complete(channel).await;
        }
        Ok(Flow::Continue)
    }

    /// Content received whole: handled as its method, content header and
    /// body frames would be, one after the other.
    async fn whole_content(&mut self, whole: WholeContent) -> Result<Flow, Violation> {
        if *self.shared.closing.borrow() {
            return Ok(Flow::Continue);
        }
        let WholeContent {
            channel,
            method,
            properties,
            body,
        } = whole;
        self.no_content_pending(channel, &method)?;
        let properties = BasicProperties::decode(&properties)
            .map_err(|e| Violation::new(e.reply_code(), e.to_string()))?;
        self.hand_over(channel, method, Content { properties, body })
            .await
    }

    /// Hands a complete message to its channel.
    async fn complete(&mut self, channel: u16) -> Result<Flow, Violation> {
        let Some(incoming) = self.incoming.remove(&channel) else {
            return Ok(Flow::Continue);
        };
        let content = Content {
            properties: incoming.properties.unwrap_or_default(),
            body: incoming.body.freeze(),
        };
        self.hand_over(channel, incoming.method, content).await
    }

    /// Hands a message's method and content to its channel.
    async fn hand_over(
        &mut self,
        channel: u16,
        method: Method,
        content: Content,
    ) -> Result<Flow, Violation> {
        let Some(chan) = self.shared.channel(channel) else {
            return Ok(Flow::Continue);
        };
        match method {
            Method::BasicDeliver(deliver) => self.deliver(&chan, deliver, content).await,
            Method::BasicReturn(ret) => {
                let message = ReturnedMessage {
                    reply_code: ret.reply_code,
                    reply_text: ret.reply_text,
                    exchange: ret.exchange,
                    routing_key: ret.routing_key,
                    properties: content.properties,
                    body: content.body,
                };
                chan.returned(message, &self.shared).await;
            }
            method => chan
                .complete(Reply {
                    method,
                    content: Some(content),
                })
                .map_err(|text| Violation::new(ReplyCode::UnexpectedFrame, text))?,
        }
        Ok(Flow::Continue)
    }

    async fn deliver(
        &self,
        chan: &Arc<ChannelShared>,
        deliver: leveret_protocol::BasicDeliver,
        content: Content,
    ) {
        let Some(route) = chan.consumer(&deliver.consumer_tag) else {
            tracing::debug!(tag = %deliver.consumer_tag, "delivery for a consumer that is gone; dropped");
            return;
        };
        let (tx, consumer) = (route.tx, route.shared);
        let delivery = Delivery::new(
            deliver,
            content,
            crate::channel::ChannelCore::new(Arc::clone(&self.shared), Arc::clone(chan)),
        );
        if route.sink.is_some_and(|sink| sink.take(&delivery)) {
            return;
        }
        let delivery = match tx.try_send(delivery) {
            Ok(()) => return,
            Err(tokio::sync::mpsc::error::TrySendError::Closed(_)) => return,
            Err(tokio::sync::mpsc::error::TrySendError::Full(delivery)) => delivery,
        };
        // The consumer's buffer is full: stop reading (backpressure on the
        // whole connection) until it has room, unless the consumer, its
        // channel or the connection is going away.
        let mut cancelling = consumer.cancelling.subscribe();
        let mut chan_closing = chan.closing.subscribe();
        let mut conn_closing = self.shared.closing.subscribe();
        tokio::select! {
            _ = tx.send(delivery) => {}
            _ = cancelling.wait_for(|c| *c) => {
                tracing::debug!("delivery dropped: its consumer is being cancelled");
            }
            _ = chan_closing.wait_for(|c| *c) => {}
            _ = conn_closing.wait_for(|c| *c) => {}
        }
    }
}
