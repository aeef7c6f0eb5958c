//! A connection's frames in and out, whatever carries them:
//! [`FrameInput`] and [`FrameOutput`], implemented over a byte stream
//! (frames decoded from and encoded into buffers here, a writer task
//! draining the outbox) and, with the `embedded` feature, over the link of
//! an in-process Leveret (`BrokerHandle::connect_direct`), where frames
//! and [`Outgoing`] items cross as values and a delivery's content comes
//! whole ([`WholeContent`]): no frame is encoded or parsed, and the
//! outbox's receiving end is the broker's connection itself. The
//! handshake and the reader are written once against these two traits.
//!
//! Uses the codec and the byte writer task.

use super::writer::{self, OUTBOX_CAPACITY};
use bytes::{Bytes, BytesMut};
use leveret_protocol::handoff;
use leveret_protocol::{
    decode_frame, encode_content, encode_method, ContentHeader, DecodeError, Frame, Method,
    Outgoing, PROTOCOL_HEADER,
};
use std::future::Future;
use std::time::Duration;
use tokio::io::{AsyncRead, AsyncReadExt, AsyncWrite, AsyncWriteExt};
use tokio::sync::oneshot;
use tokio::task::JoinHandle;

/// A content-carrying method (deliver, get-ok, return) received whole,
/// with its message's content: what its method, content header and body
/// frames would carry.
pub(crate) struct WholeContent {
    pub(crate) channel: u16,
    pub(crate) method: Method,
    /// The encoded property flags and list.
    pub(crate) properties: Bytes,
    pub(crate) body: Bytes,
}

/// Where a connection's incoming frames come from.
pub(crate) trait FrameInput: Send + Sync + 'static {
    /// The next input if it is content received whole (only an in-process
    /// link has it, and never on channel 0); taken off the input.
    fn buffered_content(&mut self) -> Option<WholeContent> {
        None
    }

    /// A whole frame already received, if any (taken off the input).
    fn buffered(&mut self, frame_max: u32) -> Result<Option<Frame>, DecodeError>;

    /// Waits for more input; false once the broker has ended the stream.
    fn receive(&mut self) -> impl Future<Output = std::io::Result<bool>> + Send;

    /// After a decoding error: whether the broker answered in another
    /// protocol (its own protocol header instead of a frame).
    fn other_protocol(&self) -> bool;

    /// The connection is open: an in-process link takes its deliveries
    /// inline from now on (see `inline`).
    fn attach(&mut self, _shared: &std::sync::Arc<super::Shared>) {}
}

/// Where a connection's outgoing items go: during the handshake, methods
/// one batch at a time; after it, the outbox every channel sends into.
pub(crate) trait FrameOutput: Send + 'static {
    /// Opens the stream (the protocol header, for bytes).
    fn begin(&mut self) -> impl Future<Output = std::io::Result<()>> + Send;

    /// Adds a handshake method to the batch.
    fn queue(&mut self, method: Method);

    /// Sends the batch.
    fn flush(&mut self) -> impl Future<Output = std::io::Result<()>> + Send;

    /// Whether the link needs heartbeats to find a dead peer (a socket
    /// does; an in-process link ends when either side drops it).
    fn needs_heartbeats(&self) -> bool;

    /// The outbox after the handshake: the sender channels use and, on a
    /// socket, the writer task draining it.
    fn into_outbox(self, frame_max: u32, heartbeat: Duration) -> Outbox;
}

/// A connection's outbox after the handshake.
pub(crate) struct Outbox {
    /// What every channel sends into (bounded: senders wait for room).
    pub tx: handoff::Sender<Outgoing>,
    /// The writer task, where one drains the outbox.
    pub writer: Option<Writer>,
    /// An in-process connection's loop (see `Shared::here`).
    #[cfg(feature = "embedded")]
    pub here: Option<leveret_broker::DirectLoop>,
}

/// A running writer task.
pub(crate) struct Writer {
    /// The task, aborted if it cannot be stopped in time.
    pub task: JoinHandle<()>,
    /// Why it failed, if it did.
    pub failed: oneshot::Receiver<std::io::Error>,
}

/// Frames decoded from a byte stream's read half.
pub(crate) struct ByteInput<R> {
    socket: R,
    buf: BytesMut,
}

impl<R> ByteInput<R> {
    pub(crate) fn new(socket: R) -> Self {
        ByteInput {
            socket,
            buf: BytesMut::with_capacity(16 * 1024),
        }
    }
}

impl<R: AsyncRead + Unpin + Send + Sync + 'static> FrameInput for ByteInput<R> {
    fn buffered(&mut self, frame_max: u32) -> Result<Option<Frame>, DecodeError> {
        decode_frame(&mut self.buf, frame_max)
    }

    async fn receive(&mut self) -> std::io::Result<bool> {
        if self.buf.capacity() - self.buf.len() < 4096 {
            self.buf.reserve(64 * 1024);
        }
        Ok(self.socket.read_buf(&mut self.buf).await? > 0)
    }

    fn other_protocol(&self) -> bool {
        self.buf.starts_with(b"AMQP")
    }
}

/// Frames encoded into a byte stream's write half, a batch per write.
pub(crate) struct ByteOutput<W> {
    socket: W,
    buf: BytesMut,
    scratch: BytesMut,
}

impl<W> ByteOutput<W> {
    pub(crate) fn new(socket: W) -> Self {
        ByteOutput {
            socket,
            buf: BytesMut::with_capacity(64 * 1024),
            scratch: BytesMut::with_capacity(256),
        }
    }
}

impl<W: AsyncWrite + Unpin + Send + 'static> ByteOutput<W> {
    /// Adds an item to the batch; true if the writer must stop after it.
    pub(crate) fn push(&mut self, item: Outgoing, frame_max: u32) -> bool {
        match item {
            Outgoing::Method { channel, method } => encode_method(channel, &method, &mut self.buf),
            Outgoing::Publish {
                channel,
                method,
                properties,
                body,
            } => {
                encode_method(channel, &Method::BasicPublish(method), &mut self.buf);
                self.scratch.clear();
                properties.encode(&mut self.scratch);
                encode_content(
                    channel,
                    ContentHeader::BASIC_CLASS,
                    &self.scratch,
                    &body,
                    frame_max,
                    &mut self.buf,
                );
            }
            Outgoing::Shutdown => return true,
        }
        false
    }

    /// Adds a heartbeat to the batch.
    pub(crate) fn heartbeat(&mut self) {
        Frame::Heartbeat.encode(&mut self.buf);
    }

    /// Bytes in the batch (the writer caps a batch).
    pub(crate) fn batched(&self) -> usize {
        self.buf.len()
    }

    /// Writes the batch.
    pub(crate) async fn write(&mut self) -> std::io::Result<()> {
        if self.buf.is_empty() {
            return Ok(());
        }
        let result = self.socket.write_all(&self.buf).await;
        self.buf.clear();
        result
    }

    /// Ends the stream after the last write.
    pub(crate) async fn shutdown(&mut self) -> std::io::Result<()> {
        self.socket.shutdown().await
    }
}

impl<W: AsyncWrite + Unpin + Send + 'static> FrameOutput for ByteOutput<W> {
    async fn begin(&mut self) -> std::io::Result<()> {
        self.socket.write_all(PROTOCOL_HEADER).await
    }

    fn queue(&mut self, method: Method) {
        encode_method(0, &method, &mut self.buf);
    }

    async fn flush(&mut self) -> std::io::Result<()> {
        self.write().await
    }

    fn needs_heartbeats(&self) -> bool {
        true
    }

    fn into_outbox(self, frame_max: u32, heartbeat: Duration) -> Outbox {
        let (tx, rx) = handoff::channel(OUTBOX_CAPACITY);
        let (failed_tx, failed) = oneshot::channel();
        let task = tokio::spawn(writer::run(self, rx, frame_max, heartbeat, failed_tx));
        Outbox {
            tx,
            writer: Some(Writer { task, failed }),
            #[cfg(feature = "embedded")]
            here: None,
        }
    }
}

#[cfg(feature = "embedded")]
pub(crate) use direct::{DirectInput, DirectOutput};

#[cfg(feature = "embedded")]
mod direct {
    use super::{FrameInput, FrameOutput, Outbox, Outgoing, WholeContent};
    use leveret_broker::{DirectLoop, DirectReplies, DirectReply};
    use leveret_protocol::handoff;
    use leveret_protocol::{DecodeError, Frame, Method};
    use std::time::Duration;

    /// The broker's frames as values, its contents whole.
    pub(crate) struct DirectInput {
        replies: DirectReplies,
        received: Option<DirectReply>,
    }

    impl DirectInput {
        pub(crate) fn new(replies: DirectReplies) -> Self {
            DirectInput {
                replies,
                received: None,
            }
        }
    }

    impl FrameInput for DirectInput {
        fn buffered_content(&mut self) -> Option<WholeContent> {
            match self.received.take()? {
                DirectReply::Content {
                    channel,
                    method,
                    properties,
                    body,
                } => Some(WholeContent {
                    channel,
                    method,
                    properties,
                    body,
                }),
                frame => {
                    self.received = Some(frame);
                    None
                }
            }
        }

        fn buffered(&mut self, _frame_max: u32) -> Result<Option<Frame>, DecodeError> {
            Ok(match self.received.take() {
                Some(DirectReply::Frame(frame)) => Some(frame),
                Some(content) => {
                    self.received = Some(content);
                    None
                }
                None => None,
            })
        }

        async fn receive(&mut self) -> std::io::Result<bool> {
            self.received = self.replies.recv().await;
            Ok(self.received.is_some())
        }

        fn other_protocol(&self) -> bool {
            false
        }

        fn attach(&mut self, shared: &std::sync::Arc<super::super::Shared>) {
            self.replies
                .deliver_inline(super::super::inline::InlineConsumers::new(shared));
        }
    }

    /// Items handed to the broker as they are: the handshake's methods,
    /// then every channel's, through the same bounded sender.
    pub(crate) struct DirectOutput {
        to_broker: handoff::Sender<Outgoing>,
        here: DirectLoop,
        batch: Vec<Method>,
    }

    impl DirectOutput {
        pub(crate) fn new(to_broker: handoff::Sender<Outgoing>, here: DirectLoop) -> Self {
            DirectOutput {
                to_broker,
                here,
                batch: Vec::new(),
            }
        }
    }

    impl FrameOutput for DirectOutput {
        async fn begin(&mut self) -> std::io::Result<()> {
            Ok(())
        }

        fn queue(&mut self, method: Method) {
            self.batch.push(method);
        }

        async fn flush(&mut self) -> std::io::Result<()> {
            for method in std::mem::take(&mut self.batch) {
                let item = Outgoing::Method { channel: 0, method };
                if self.to_broker.send(item).await.is_err() {
                    return Err(gone());
                }
            }
            Ok(())
        }

        fn needs_heartbeats(&self) -> bool {
            false
        }

        fn into_outbox(self, _frame_max: u32, _heartbeat: Duration) -> Outbox {
            Outbox {
                tx: self.to_broker,
                writer: None,
                here: Some(self.here),
            }
        }
    }

    fn gone() -> std::io::Error {
        std::io::Error::new(
            std::io::ErrorKind::BrokenPipe,
            "the embedded broker ended the connection",
        )
    }
}
