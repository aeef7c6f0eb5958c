//! The writer task: owns the socket's write half and drains the bounded
//! outbox. Everything waiting is encoded into one reused buffer and written
//! with one syscall (batching under load, no added latency when idle); a
//! heartbeat goes out whenever nothing was written for an interval.

use bytes::{Bytes, BytesMut};
use leveret_protocol::{
    encode_content, encode_method, BasicProperties, BasicPublish, ContentHeader, Frame, Method,
};
use std::time::Duration;
use tokio::io::{AsyncWrite, AsyncWriteExt};
use tokio::sync::{mpsc, oneshot};

/// How many items may wait for the writer. Senders wait for room, so a
/// slow socket slows publishers down instead of growing a buffer.
pub(crate) const OUTBOX_CAPACITY: usize = 256;

/// Stop adding to a batch once the buffer holds this much.
const BATCH_BYTES: usize = 128 * 1024;

/// One item for the writer to encode.
///
/// `Publish` is large (the properties are inline) but is also the common
/// item: boxing it would cost an allocation per message, while the
/// outbox's slots are allocated once and reused.
#[derive(Debug)]
#[allow(clippy::large_enum_variant)]
pub(crate) enum Outbound {
    /// A method without content.
    Method {
        /// Channel number.
        channel: u16,
        /// The method.
        method: Method,
    },
    /// basic.publish with its content, kept together so no other frame on
    /// the channel can come between them.
    Publish {
        /// Channel number.
        channel: u16,
        /// The method.
        method: BasicPublish,
        /// Properties, encoded by the writer.
        properties: BasicProperties,
        /// The body, split by frame_max.
        body: Bytes,
    },
    /// Write everything queued before this, then close the socket.
    Shutdown,
}

/// Runs until [`Outbound::Shutdown`], every sender dropping, or a write
/// error, which is reported through `failed`.
pub(crate) async fn run<W: AsyncWrite + Unpin>(
    mut socket: W,
    mut inbox: mpsc::Receiver<Outbound>,
    frame_max: u32,
    heartbeat: Duration,
    failed: oneshot::Sender<std::io::Error>,
) {
    let mut buf = BytesMut::with_capacity(64 * 1024);
    let mut scratch = BytesMut::with_capacity(256);
    let result: std::io::Result<()> = async {
        loop {
            let next = if heartbeat.is_zero() {
                inbox.recv().await
            } else {
                tokio::select! {
                    item = inbox.recv() => item,
                    _ = tokio::time::sleep(heartbeat) => {
                        Frame::Heartbeat.encode(&mut buf);
                        flush(&mut socket, &mut buf).await?;
                        continue;
                    }
                }
            };
            let Some(item) = next else {
                flush(&mut socket, &mut buf).await?;
                return socket.shutdown().await;
            };
            let mut stop = encode(item, frame_max, &mut buf, &mut scratch);
            while !stop && buf.len() < BATCH_BYTES {
                match inbox.try_recv() {
                    Ok(item) => stop = encode(item, frame_max, &mut buf, &mut scratch),
                    Err(_) => break,
                }
            }
            flush(&mut socket, &mut buf).await?;
            if stop {
                return socket.shutdown().await;
            }
        }
    }
    .await;
    if let Err(error) = result {
        tracing::debug!(%error, "AMQP writer stopped");
        let _ = failed.send(error);
    }
}

async fn flush<W: AsyncWrite + Unpin>(socket: &mut W, buf: &mut BytesMut) -> std::io::Result<()> {
    if buf.is_empty() {
        return Ok(());
    }
    let result = socket.write_all(buf).await;
    buf.clear();
    result
}

/// Encodes one item; true if the writer must stop after this batch.
fn encode(item: Outbound, frame_max: u32, buf: &mut BytesMut, scratch: &mut BytesMut) -> bool {
    match item {
        Outbound::Method { channel, method } => encode_method(channel, &method, buf),
        Outbound::Publish {
            channel,
            method,
            properties,
            body,
        } => {
            encode_method(channel, &Method::BasicPublish(method), buf);
            scratch.clear();
            properties.encode(scratch);
            encode_content(
                channel,
                ContentHeader::BASIC_CLASS,
                scratch,
                &body,
                frame_max,
                buf,
            );
        }
        Outbound::Shutdown => return true,
    }
    false
}
