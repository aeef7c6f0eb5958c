//! The writer task of a connection: owns the socket's write half, drains
//! the outbox, encodes everything waiting into one buffer and writes it
//! with one syscall (batching under load, no added latency when idle), and
//! sends heartbeats when nothing else was written for an interval. The
//! buffer is given back once nothing was written for `IDLE_RELEASE` (and
//! at once after a batch that grew it past twice the batch size, for a
//! large message), so an idle connection holds none; a batch after a
//! release starts at the size of the last one instead of growing step by
//! step.

use super::reader::IDLE_RELEASE;
use crate::outbox::{Outbound, Outbox};
use bytes::BytesMut;
use leveret_protocol::{
    encode_content, encode_method, BasicDeliver, BasicGetOk, BasicReturn, ContentHeader, Frame,
    Method,
};
use std::sync::Arc;
use std::time::Duration;
use tokio::io::{AsyncWrite, AsyncWriteExt};
use tokio::sync::mpsc;
use tokio::time::Instant;

/// Stop adding to a batch once the buffer holds this much.
const BATCH_BYTES: usize = 128 * 1024;
/// The smallest buffer a batch starts with.
const BATCH_START: usize = 512;

/// Runs until [`Outbound::Shutdown`], the outbox closing, or a write error.
pub async fn run<W: AsyncWrite + Unpin>(
    mut socket: W,
    mut inbox: mpsc::Receiver<Outbound>,
    outbox: Arc<Outbox>,
    mut heartbeat: tokio::sync::watch::Receiver<Duration>,
) {
    let mut buf = BytesMut::new();
    let mut last_batch = BATCH_START;
    let mut interval = *heartbeat.borrow();
    let mut last_write = Instant::now();
    // One timer for the connection's life, re-armed only when it fires (not
    // per batch written): a heartbeat is due `interval` after the last
    // write, and a buffer is released `IDLE_RELEASE` after it.
    let due = |interval: Duration, last_write: Instant, holding: bool| {
        let heartbeat = (!interval.is_zero()).then(|| last_write + interval);
        let release = holding.then(|| last_write + IDLE_RELEASE);
        heartbeat.into_iter().chain(release).min()
    };
    let timer = tokio::time::sleep(interval);
    tokio::pin!(timer);
    let mut armed = false;
    loop {
        if !armed {
            if let Some(at) = due(interval, last_write, buf.capacity() > 0) {
                timer.as_mut().reset(at);
                armed = true;
            }
        }
        let next = tokio::select! {
            item = inbox.recv() => item,
            changed = heartbeat.changed() => {
                if changed.is_err() { return; }
                interval = *heartbeat.borrow();
                armed = false;
                continue;
            }
            _ = &mut timer, if armed => {
                armed = false;
                let now = Instant::now();
                if !interval.is_zero() && now >= last_write + interval {
                    Frame::Heartbeat.encode(&mut buf);
                    if flush(&mut socket, &mut buf).await.is_err() { return; }
                    last_write = Instant::now();
                }
                if now >= last_write + IDLE_RELEASE {
                    buf = BytesMut::new();
                }
                continue;
            }
        };
        let Some(item) = next else {
            let _ = flush(&mut socket, &mut buf).await;
            return;
        };
        buf.reserve(last_batch);
        let mut stop = encode(item, &outbox, &mut buf);
        while !stop && buf.len() < BATCH_BYTES {
            match inbox.try_recv() {
                Ok(item) => stop = encode(item, &outbox, &mut buf),
                Err(_) => break,
            }
        }
        last_batch = buf.len().clamp(BATCH_START, BATCH_BYTES);
        if flush(&mut socket, &mut buf).await.is_err() {
            return;
        }
        if buf.capacity() > 2 * BATCH_BYTES {
            buf = BytesMut::new();
        }
        last_write = Instant::now();
        outbox.wake_blocked();
        if stop {
            let _ = socket.shutdown().await;
            return;
        }
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
fn encode(item: Outbound, outbox: &Outbox, buf: &mut BytesMut) -> bool {
    let (channel, method, message) = match item {
        Outbound::Method { channel, method } => {
            encode_method(channel, &method, buf);
            return false;
        }
        Outbound::Shutdown => return true,
        Outbound::Deliver {
            channel,
            consumer_tag,
            delivery_tag,
            redelivered,
            message,
        } => {
            let method = Method::BasicDeliver(BasicDeliver {
                consumer_tag,
                delivery_tag,
                redelivered,
                exchange: message.exchange.clone(),
                routing_key: message.routing_key.clone(),
            });
            (channel, method, message)
        }
        Outbound::GetOk {
            channel,
            delivery_tag,
            redelivered,
            message_count,
            message,
        } => {
            let method = Method::BasicGetOk(BasicGetOk {
                delivery_tag,
                redelivered,
                exchange: message.exchange.clone(),
                routing_key: message.routing_key.clone(),
                message_count,
            });
            (channel, method, message)
        }
        Outbound::Return {
            channel,
            reply_code,
            reply_text,
            message,
        } => {
            let method = Method::BasicReturn(BasicReturn {
                reply_code,
                reply_text,
                exchange: message.exchange.clone(),
                routing_key: message.routing_key.clone(),
            });
            (channel, method, message)
        }
    };
    // The publisher's property bytes go out as they came in.
    encode_method(channel, &method, buf);
    encode_content(
        channel,
        ContentHeader::BASIC_CLASS,
        &message.properties,
        &message.body,
        outbox.frame_max(),
        buf,
    );
    false
}
