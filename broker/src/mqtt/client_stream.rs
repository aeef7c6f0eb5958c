//! A client's byte stream as a session uses it: what it needs of a
//! transport ([`ClientStream`]: TCP, TLS, WebSocket), and the stream
//! counted ([`Counted`]) as RabbitMQ 3.10's plugin counts an MQTT
//! connection's socket (`recv_oct`, `recv_cnt`, `send_oct`, `send_cnt`):
//! into the connection's figures (listed, and `/metrics/detailed`'s
//! connection families) and the broker's totals, beside the AMQP
//! connections'. The MQTT bytes are counted (inside TLS and WebSocket
//! framing), as the AMQP side counts a TLS connection's.

use crate::stats::ConnectionTraffic;
use std::io;
use std::pin::Pin;
use std::sync::Arc;
use std::task::{Context, Poll};
use tokio::io::{AsyncRead, AsyncWrite, ReadBuf};

/// A client's byte stream (TCP, TLS, WebSocket), told when its CONNECT
/// has been accepted, so a transport that holds back reads until then
/// (the WebSocket's, whose messages arrive whole) can stop.
pub(super) trait ClientStream: AsyncRead + AsyncWrite + Unpin {
    /// The session has logged in.
    fn logged_in(&mut self) {}
}

impl ClientStream for tokio::net::TcpStream {}

#[cfg(feature = "tls")]
impl ClientStream for tokio_rustls::server::TlsStream<tokio::net::TcpStream> {}

/// A client stream whose reads and writes are counted.
pub(super) struct Counted<S> {
    inner: S,
    traffic: Arc<ConnectionTraffic>,
}

impl<S> Counted<S> {
    pub(super) fn new(inner: S, traffic: Arc<ConnectionTraffic>) -> Self {
        Counted { inner, traffic }
    }
}

impl<S: AsyncRead + Unpin> AsyncRead for Counted<S> {
    fn poll_read(
        self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &mut ReadBuf<'_>,
    ) -> Poll<io::Result<()>> {
        let this = self.get_mut();
        let before = buf.filled().len();
        let polled = Pin::new(&mut this.inner).poll_read(cx, buf);
        let read = buf.filled().len() - before;
        if matches!(polled, Poll::Ready(Ok(()))) && read > 0 {
            this.traffic.read(read);
        }
        polled
    }
}

impl<S: AsyncWrite + Unpin> AsyncWrite for Counted<S> {
    fn poll_write(
        self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        bytes: &[u8],
    ) -> Poll<io::Result<usize>> {
        let this = self.get_mut();
        let polled = Pin::new(&mut this.inner).poll_write(cx, bytes);
        if let Poll::Ready(Ok(written)) = polled {
            if written > 0 {
                this.traffic.wrote(written);
            }
        }
        polled
    }

    fn poll_flush(self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        Pin::new(&mut self.get_mut().inner).poll_flush(cx)
    }

    fn poll_shutdown(self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        Pin::new(&mut self.get_mut().inner).poll_shutdown(cx)
    }
}

impl<S: ClientStream> ClientStream for Counted<S> {
    fn logged_in(&mut self) {
        self.inner.logged_in();
    }
}
