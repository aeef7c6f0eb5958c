//! The writer task of a connection: owns the socket's write half, drains
//! the outbox, encodes everything waiting into one buffer and writes it
//! with one syscall (batching under load, no added latency when idle), and
//! sends heartbeats when nothing else was written for an interval. A
//! write the client does not take for two heartbeat intervals while it
//! sends nothing either ends the writer (and with it the connection's
//! output): the client is gone, or has stopped, as RabbitMQ judges by its
//! heartbeats whether or not its writer is blocked.
//!
//! Bodies of [`BODY_BY_REFERENCE`] bytes and more are not copied into the
//! buffer: their frames are written straight from the message (vectored
//! writes), so a consumer that stops reading holds the message its queue
//! already counts rather than an uncounted copy of it, and a large message
//! costs no copy. The buffer itself stays within about [`BATCH_BYTES`] and
//! is given back once nothing was written for `IDLE_RELEASE`, so an idle
//! connection holds none; a batch after a release starts at the size of
//! the last one instead of growing step by step. The outbox's queue gives
//! its room back at the same moment.

use super::reader::IDLE_RELEASE;
use crate::outbox::{Framed, Outbound, Outbox};
use crate::stats::ConnectionTraffic;
use bytes::{Buf, BufMut, Bytes, BytesMut};
use leveret_protocol::{
    encode_content, encode_header, encode_method, handoff, ContentHeader, Frame, FRAME_END,
    FRAME_OVERHEAD,
};
use std::collections::VecDeque;
use std::io::IoSlice;
use std::sync::Arc;
use std::time::Duration;
use tokio::io::{AsyncWrite, AsyncWriteExt};
use tokio::time::Instant;

/// Stop adding to a batch once the buffer holds this much.
const BATCH_BYTES: usize = 128 * 1024;
/// The smallest buffer a batch starts with.
const BATCH_START: usize = 512;
/// Bodies at least this large are written from the message, not copied.
const BODY_BY_REFERENCE: usize = 16 * 1024;
/// The frame type of body frames.
const BODY_FRAME: u8 = 3;

/// A socket's write half that counts each write that moved bytes, and
/// the bytes, into a connection's traffic.
pub struct Counted<W> {
    socket: W,
    traffic: Arc<ConnectionTraffic>,
}

impl<W> Counted<W> {
    /// `socket`, counted into `traffic`.
    pub fn new(socket: W, traffic: Arc<ConnectionTraffic>) -> Self {
        Counted { socket, traffic }
    }

    fn count(&self, written: &std::task::Poll<std::io::Result<usize>>) {
        if let std::task::Poll::Ready(Ok(bytes @ 1..)) = written {
            self.traffic.wrote(*bytes);
        }
    }
}

impl<W: AsyncWrite + Unpin> AsyncWrite for Counted<W> {
    fn poll_write(
        mut self: std::pin::Pin<&mut Self>,
        cx: &mut std::task::Context<'_>,
        buf: &[u8],
    ) -> std::task::Poll<std::io::Result<usize>> {
        let written = std::pin::Pin::new(&mut self.socket).poll_write(cx, buf);
        self.count(&written);
        written
    }

    fn poll_write_vectored(
        mut self: std::pin::Pin<&mut Self>,
        cx: &mut std::task::Context<'_>,
        bufs: &[IoSlice<'_>],
    ) -> std::task::Poll<std::io::Result<usize>> {
        let written = std::pin::Pin::new(&mut self.socket).poll_write_vectored(cx, bufs);
        self.count(&written);
        written
    }

    fn is_write_vectored(&self) -> bool {
        self.socket.is_write_vectored()
    }

    fn poll_flush(
        mut self: std::pin::Pin<&mut Self>,
        cx: &mut std::task::Context<'_>,
    ) -> std::task::Poll<std::io::Result<()>> {
        std::pin::Pin::new(&mut self.socket).poll_flush(cx)
    }

    fn poll_shutdown(
        mut self: std::pin::Pin<&mut Self>,
        cx: &mut std::task::Context<'_>,
    ) -> std::task::Poll<std::io::Result<()>> {
        std::pin::Pin::new(&mut self.socket).poll_shutdown(cx)
    }
}

/// Runs until [`Outbound::Shutdown`], the outbox closing, or a write error.
pub async fn run<W: AsyncWrite + Unpin>(
    mut socket: W,
    mut inbox: handoff::Receiver<Outbound>,
    outbox: Arc<Outbox>,
) {
    let mut out = Output::default();
    let mut last_batch = BATCH_START;
    // Zero (none) until the handshake's tune-ok sets it in the outbox
    // ([`Outbox::heartbeat`]), read after every batch: from the batch
    // after the tune-ok (the open-ok, or the close) on.
    let mut interval = Duration::ZERO;
    let mut last_write = Instant::now();
    // One timer for the connection's life, re-armed only when it fires (not
    // per batch written), when a batch finds it armed for the heartbeat
    // alone (the first batch after a release), or when the interval is
    // negotiated: a heartbeat is due
    // `interval` after the last write, and a buffer is released
    // `IDLE_RELEASE` after it.
    let due = |interval: Duration, last_write: Instant, holding: bool| {
        let heartbeat = (!interval.is_zero()).then(|| last_write + interval);
        let release = holding.then(|| last_write + IDLE_RELEASE);
        heartbeat.into_iter().chain(release).min()
    };
    let timer = tokio::time::sleep(interval);
    tokio::pin!(timer);
    let mut armed = false;
    // Whether the armed timer counts a release in.
    let mut armed_holding = false;
    loop {
        if !armed {
            let holding = out.buf.capacity() > 0 || inbox.holds_room();
            if let Some(at) = due(interval, last_write, holding) {
                timer.as_mut().reset(at);
                armed = true;
                armed_holding = holding;
            }
        }
        let next = tokio::select! {
            item = inbox.recv() => item,
            _ = &mut timer, if armed => {
                armed = false;
                let now = Instant::now();
                // A heartbeat written now does not make the writer busy:
                // the release counts from the write before it (with a
                // heartbeat of `IDLE_RELEASE` or less, it would otherwise
                // never come).
                let quiet_since = last_write;
                if !interval.is_zero() && now >= last_write + interval {
                    Frame::Heartbeat.encode(&mut out.buf);
                    if out.flush_unless_unheard(&mut socket, &outbox, interval).await.is_err() {
                        return;
                    }
                    last_write = Instant::now();
                }
                if now >= quiet_since + IDLE_RELEASE {
                    out.buf = BytesMut::new();
                    inbox.release_room();
                }
                continue;
            }
        };
        let Some(item) = next else {
            let _ = out.flush(&mut socket).await;
            return;
        };
        out.buf.reserve(last_batch);
        let mut stop = out.encode(item, &outbox);
        while !stop && out.len() < BATCH_BYTES {
            match inbox.try_recv() {
                Some(item) => stop = out.encode(item, &outbox),
                None => break,
            }
        }
        last_batch = out.buf.len().clamp(BATCH_START, BATCH_BYTES);
        if out
            .flush_unless_unheard(&mut socket, &outbox, interval)
            .await
            .is_err()
        {
            return;
        }
        last_write = Instant::now();
        // The batch's buffer is to be released `IDLE_RELEASE` from now,
        // not at a heartbeat an interval away; and a heartbeat newly
        // negotiated is due an interval from now.
        armed &= armed_holding;
        let negotiated = outbox.heartbeat();
        if negotiated != interval {
            interval = negotiated;
            armed = false;
        }
        outbox.wake_blocked();
        if stop {
            let _ = socket.shutdown().await;
            return;
        }
    }
}

/// Resolves once the client has sent nothing for two heartbeat
/// `interval`s; never with heartbeats off.
async fn unheard(outbox: &Outbox, interval: Duration) {
    if interval.is_zero() {
        return std::future::pending().await;
    }
    let limit = interval * 2;
    loop {
        let quiet = outbox.unheard_for();
        if quiet >= limit {
            return;
        }
        tokio::time::sleep(limit - quiet).await;
    }
}

/// What a batch writes: bytes encoded into `buf`, preceded by `parts`
/// when the batch has bodies written by reference.
#[derive(Default)]
struct Output {
    buf: BytesMut,
    parts: Parts,
}

impl Output {
    /// Bytes in the batch.
    fn len(&self) -> usize {
        self.parts.len + self.buf.len()
    }

    /// Writes the batch.
    async fn flush<W: AsyncWrite + Unpin>(&mut self, socket: &mut W) -> std::io::Result<()> {
        let result = if self.parts.is_empty() {
            socket.write_all(&self.buf).await
        } else {
            self.parts.push(self.buf.split().freeze());
            socket.write_all_buf(&mut self.parts).await
        };
        self.buf.clear();
        self.parts.clear();
        result
    }

    /// Writes the batch, unless the client stops taking it and has sent
    /// nothing for two heartbeat `interval`s (an error then).
    async fn flush_unless_unheard<W: AsyncWrite + Unpin>(
        &mut self,
        socket: &mut W,
        outbox: &Outbox,
        interval: Duration,
    ) -> std::io::Result<()> {
        tokio::select! {
            // The write first: when the socket takes it at once, the
            // watch is never polled and costs no timer.
            biased;
            written = self.flush(socket) => written,
            () = unheard(outbox, interval) => {
                tracing::info!(
                    connection = outbox.connection_id,
                    "missed heartbeats from a client that is not reading; closing"
                );
                Err(std::io::ErrorKind::TimedOut.into())
            }
        }
    }

    /// Encodes one item; true if the writer must stop after this batch.
    fn encode(&mut self, item: Outbound, outbox: &Outbox) -> bool {
        let (channel, method, message) = match item.framed() {
            Framed::Method { channel, method } => {
                encode_method(channel, &method, &mut self.buf);
                return false;
            }
            Framed::Shutdown => return true,
            Framed::Content {
                channel,
                method,
                message,
            } => (channel, method, message),
        };
        encode_method(channel, &method, &mut self.buf);
        if message.body.len() < BODY_BY_REFERENCE {
            encode_content(
                channel,
                ContentHeader::BASIC_CLASS,
                &message.properties,
                &message.body,
                outbox.frame_max(),
                &mut self.buf,
            );
        } else {
            self.body_by_reference(
                channel,
                &message.properties,
                &message.body,
                outbox.frame_max(),
            );
        }
        false
    }

    /// The content header, then body frames whose payloads are slices of
    /// `body` between envelopes encoded into the buffer.
    fn body_by_reference(
        &mut self,
        channel: u16,
        properties: &Bytes,
        body: &Bytes,
        frame_max: u32,
    ) {
        let header = ContentHeader {
            class_id: ContentHeader::BASIC_CLASS,
            body_size: body.len() as u64,
            property_bytes: properties.clone(),
        };
        encode_header(channel, &header, &mut self.buf);
        let chunk = (frame_max as usize).saturating_sub(FRAME_OVERHEAD).max(1);
        let mut start = 0;
        while start < body.len() {
            let end = (start + chunk).min(body.len());
            self.buf.put_u8(BODY_FRAME);
            self.buf.put_u16(channel);
            self.buf.put_u32((end - start) as u32);
            self.parts.push(self.buf.split().freeze());
            self.parts.push(body.slice(start..end));
            self.buf.put_u8(FRAME_END);
            start = end;
        }
    }
}

/// Byte strings written one after the other, with vectored writes where
/// the socket has them.
#[derive(Default)]
struct Parts {
    queue: VecDeque<Bytes>,
    len: usize,
}

impl Parts {
    fn push(&mut self, part: Bytes) {
        if !part.is_empty() {
            self.len += part.len();
            self.queue.push_back(part);
        }
    }

    fn is_empty(&self) -> bool {
        self.queue.is_empty()
    }

    fn clear(&mut self) {
        self.queue.clear();
        self.len = 0;
    }
}

impl Buf for Parts {
    fn remaining(&self) -> usize {
        self.len
    }

    fn chunk(&self) -> &[u8] {
        self.queue.front().map_or(&[], |part| part)
    }

    fn advance(&mut self, mut n: usize) {
        self.len -= n.min(self.len);
        while n > 0 {
            let Some(front) = self.queue.front_mut() else {
                return;
            };
            if n < front.len() {
                front.advance(n);
                return;
            }
            n -= front.len();
            self.queue.pop_front();
        }
    }

    fn chunks_vectored<'a>(&'a self, dst: &mut [IoSlice<'a>]) -> usize {
        let mut filled = 0;
        for (slot, part) in dst.iter_mut().zip(&self.queue) {
            *slot = IoSlice::new(part);
            filled += 1;
        }
        filled
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::message::Message;
    use leveret_protocol::{decode_frame, ShortStr};
    use tokio::io::AsyncReadExt;

    fn delivery(body: Bytes) -> Outbound {
        Outbound::Deliver {
            channel: 1,
            consumer_tag: ShortStr::from_static("ctag"),
            delivery_tag: 7,
            redelivered: false,
            message: Arc::new(Message {
                exchange: ShortStr::from_static(""),
                routing_key: ShortStr::from_static("q"),
                properties: Bytes::from_static(&[0, 0]),
                body,
                persistent: false,
                priority: 0,
                ttl_ms: None,
                stored: None,
            }),
        }
    }

    /// What a client reads: the deliver, the header, the body reassembled.
    async fn written(items: Vec<Outbound>, frame_max: u32) -> (usize, Vec<u8>) {
        let (outbox, _inbox) = Outbox::new(1);
        outbox.set_frame_max(frame_max);
        let mut out = Output::default();
        for item in items {
            out.encode(item, &outbox);
        }
        let (mut client, mut server) = tokio::io::duplex(1 << 20);
        let reading = tokio::spawn(async move {
            let mut all = BytesMut::new();
            while client.read_buf(&mut all).await.expect("read") > 0 {}
            all
        });
        out.flush(&mut server).await.expect("write");
        assert!(out.parts.is_empty() && out.buf.is_empty());
        drop(server);
        let mut all = reading.await.expect("reader");
        let (mut frames, mut body) = (0, Vec::new());
        while let Some(frame) = decode_frame(&mut all, frame_max).expect("valid frames") {
            frames += 1;
            if let Frame::Body { payload, .. } = frame {
                assert!(payload.len() + FRAME_OVERHEAD <= frame_max as usize);
                body.extend_from_slice(&payload);
            }
        }
        assert!(all.is_empty());
        (frames, body)
    }

    #[tokio::test]
    async fn large_bodies_are_written_by_reference_in_whole_frames() {
        let body: Bytes = (0..300_000u32).map(|i| i as u8).collect();
        let (frames, received) = written(vec![delivery(body.clone())], 131_072).await;
        assert_eq!(received, body.as_ref());
        assert_eq!(frames, 2 + body.len().div_ceil(131_072 - 8));
    }

    #[tokio::test]
    async fn small_and_large_bodies_keep_their_order_in_a_batch() {
        let small = Bytes::from_static(b"small");
        let large: Bytes = (0..40_000u32).map(|i| (i % 251) as u8).collect();
        let items = vec![
            delivery(small.clone()),
            delivery(large.clone()),
            delivery(small.clone()),
        ];
        let (frames, received) = written(items, 4096).await;
        let expected: Vec<u8> = [&small[..], &large[..], &small[..]].concat();
        assert_eq!(received, expected);
        assert_eq!(frames, 3 + 3 + 1 + large.len().div_ceil(4096 - 8) + 1);
    }
}
