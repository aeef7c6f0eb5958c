//! MQTT over WebSocket (RabbitMQ's `web_mqtt`, MQTT 5.0 section 6): the
//! HTTP upgrade on path [`PATH`] with the subprotocol `mqtt` (or 3.1's
//! `mqttv3.1`), then a byte stream over binary messages, so the session
//! reads and writes it as it does a socket and all of its rules hold.
//!
//! Bounded: a message or frame larger than the session's packet limit is
//! refused by tungstenite before it is buffered whole, and ends the
//! connection; a text message ends it too (MQTT-6.0.0-1). Until the
//! session has logged in, the socket is read no further than
//! [`UPGRADE_BUDGET`] bytes for the upgrade, then [`BEFORE_LOGIN`]
//! ([`HeldBack`]): tungstenite buffers a message
//! whole before the session sees a byte of it, so without that a client
//! that never logs in could make the broker hold a message of the
//! packet limit (128 MiB by default) per connection. The read buffer is
//! small ([`READ_BUFFER`]), so idle connections cost little.

use bytes::Bytes;
use futures_core::Stream;
use futures_sink::Sink;
use std::io;
use std::pin::Pin;
use std::task::{ready, Context, Poll, Waker};
use tokio::io::{AsyncRead, AsyncWrite, ReadBuf};
use tokio::net::TcpStream;
use tokio_tungstenite::tungstenite::handshake::server::{ErrorResponse, Request, Response};
use tokio_tungstenite::tungstenite::http::{HeaderValue, StatusCode};
use tokio_tungstenite::tungstenite::protocol::WebSocketConfig;
use tokio_tungstenite::tungstenite::{Error, Message};
use tokio_tungstenite::WebSocketStream;

/// The path clients connect to (RabbitMQ's and most brokers').
pub(super) const PATH: &str = "/ws";
/// The subprotocols accepted, in order of preference.
const SUBPROTOCOLS: [&str; 2] = ["mqtt", "mqttv3.1"];
/// tungstenite's read buffer per connection (its default is 128 KiB).
const READ_BUFFER: usize = 8 * 1024;
/// Bytes read from a client's socket for its HTTP upgrade request:
/// tungstenite's own limit on the request (64 KiB) and room to spare.
const UPGRADE_BUDGET: usize = 64 * 1024 + 16 * 1024;
/// Bytes read from a client's socket after the upgrade and before its
/// CONNECT is accepted: a CONNECT of the unauthenticated packet limit
/// with its WebSocket framing, with room to spare.
const BEFORE_LOGIN: usize = super::session::CONNECT_MAX_PACKET as usize + 16 * 1024;

/// Completes the WebSocket handshake on `socket`: path [`PATH`], one of
/// [`SUBPROTOCOLS`] offered (and chosen in the answer); messages and
/// frames up to `max_message` bytes.
pub(super) async fn accept(
    socket: TcpStream,
    max_message: usize,
) -> Result<ByteStream<HeldBack<TcpStream>>, Error> {
    let config = WebSocketConfig::default()
        .read_buffer_size(READ_BUFFER)
        .max_message_size(Some(max_message))
        .max_frame_size(Some(max_message));
    let socket = HeldBack::new(socket, UPGRADE_BUDGET);
    let mut stream =
        tokio_tungstenite::accept_hdr_async_with_config(socket, choose_subprotocol, Some(config))
            .await?;
    stream.get_mut().budget = Some(BEFORE_LOGIN);
    Ok(ByteStream {
        stream,
        unread: Bytes::new(),
    })
}

/// The handshake's check of the request: the path, then the subprotocol.
// The signature is tungstenite's `Callback`: its error is an HTTP response.
#[allow(clippy::result_large_err)]
fn choose_subprotocol(
    request: &Request,
    mut response: Response,
) -> Result<Response, ErrorResponse> {
    let refuse = |status: StatusCode, why: &str| {
        let mut refusal = ErrorResponse::new(Some(why.to_owned()));
        *refusal.status_mut() = status;
        refusal
    };
    if request.uri().path() != PATH {
        return Err(refuse(
            StatusCode::NOT_FOUND,
            "MQTT over WebSocket is on /ws",
        ));
    }
    let offered: Vec<&str> = request
        .headers()
        .get_all("sec-websocket-protocol")
        .iter()
        .filter_map(|value| value.to_str().ok())
        .flat_map(|list| list.split(','))
        .map(str::trim)
        .collect();
    let Some(chosen) = SUBPROTOCOLS
        .iter()
        .find(|wanted| offered.iter().any(|o| o.eq_ignore_ascii_case(wanted)))
    else {
        return Err(refuse(
            StatusCode::BAD_REQUEST,
            "the WebSocket subprotocol must be mqtt",
        ));
    };
    response
        .headers_mut()
        .insert("sec-websocket-protocol", HeaderValue::from_static(chosen));
    Ok(response)
}

/// A socket read at most `budget` bytes until [`HeldBack::release`]:
/// past it, reads wait (the client's sends back up in TCP) instead of
/// failing, so a client that sends its first packets right after the
/// CONNECT, before the CONNACK, is served once it has logged in.
pub(super) struct HeldBack<S> {
    socket: S,
    /// Bytes that may still be read; `None` once released.
    budget: Option<usize>,
    /// The read that found the budget spent, woken on release.
    parked: Option<Waker>,
}

impl<S> HeldBack<S> {
    fn new(socket: S, budget: usize) -> Self {
        HeldBack {
            socket,
            budget: Some(budget),
            parked: None,
        }
    }

    /// Lifts the budget: reads go straight to the socket from now on.
    fn release(&mut self) {
        self.budget = None;
        if let Some(parked) = self.parked.take() {
            parked.wake();
        }
    }
}

impl<S: AsyncRead + Unpin> AsyncRead for HeldBack<S> {
    fn poll_read(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &mut ReadBuf<'_>,
    ) -> Poll<io::Result<()>> {
        let Some(budget) = self.budget else {
            return Pin::new(&mut self.socket).poll_read(cx, buf);
        };
        if budget == 0 {
            self.parked = Some(cx.waker().clone());
            return Poll::Pending;
        }
        // Before login only: a small copy keeps the read within the budget
        // without unsafe code.
        let mut chunk = [0u8; 4096];
        let wanted = budget.min(buf.remaining()).min(chunk.len());
        let mut limited = ReadBuf::new(&mut chunk[..wanted]);
        ready!(Pin::new(&mut self.socket).poll_read(cx, &mut limited))?;
        let read = limited.filled();
        buf.put_slice(read);
        self.budget = Some(budget - read.len());
        Poll::Ready(Ok(()))
    }
}

impl<S: AsyncWrite + Unpin> AsyncWrite for HeldBack<S> {
    fn poll_write(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &[u8],
    ) -> Poll<io::Result<usize>> {
        Pin::new(&mut self.socket).poll_write(cx, buf)
    }

    fn poll_flush(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        Pin::new(&mut self.socket).poll_flush(cx)
    }

    fn poll_shutdown(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        Pin::new(&mut self.socket).poll_shutdown(cx)
    }
}

impl super::client_stream::ClientStream for ByteStream<HeldBack<TcpStream>> {
    fn logged_in(&mut self) {
        self.stream.get_mut().release();
    }
}

/// A WebSocket as a byte stream: reads take the bytes of binary messages
/// in order, whatever their boundaries; each write is one binary message
/// (sent on flush).
pub(super) struct ByteStream<S> {
    stream: WebSocketStream<S>,
    /// What is left of the last message read.
    unread: Bytes,
}

fn io_error(error: Error) -> io::Error {
    match error {
        Error::Io(e) => e,
        other => io::Error::new(io::ErrorKind::InvalidData, other),
    }
}

impl<S: AsyncRead + AsyncWrite + Unpin> AsyncRead for ByteStream<S> {
    fn poll_read(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &mut ReadBuf<'_>,
    ) -> Poll<io::Result<()>> {
        while self.unread.is_empty() {
            match ready!(Pin::new(&mut self.stream).poll_next(cx)) {
                Some(Ok(Message::Binary(bytes))) => self.unread = bytes,
                // Pings are answered by tungstenite itself.
                Some(Ok(Message::Ping(_) | Message::Pong(_) | Message::Frame(_))) => {}
                Some(Ok(Message::Text(_))) => {
                    return Poll::Ready(Err(io::Error::new(
                        io::ErrorKind::InvalidData,
                        "a text WebSocket message (MQTT travels in binary ones)",
                    )))
                }
                Some(Ok(Message::Close(_))) | None => return Poll::Ready(Ok(())),
                Some(Err(e)) => return Poll::Ready(Err(io_error(e))),
            }
        }
        let n = self.unread.len().min(buf.remaining());
        let taken = self.unread.split_to(n);
        buf.put_slice(&taken);
        Poll::Ready(Ok(()))
    }
}

impl<S: AsyncRead + AsyncWrite + Unpin> AsyncWrite for ByteStream<S> {
    fn poll_write(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &[u8],
    ) -> Poll<io::Result<usize>> {
        let stream = Pin::new(&mut self.stream);
        ready!(stream.poll_ready(cx)).map_err(io_error)?;
        let message = Message::Binary(Bytes::copy_from_slice(buf));
        Pin::new(&mut self.stream)
            .start_send(message)
            .map_err(io_error)?;
        Poll::Ready(Ok(buf.len()))
    }

    fn poll_flush(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        Pin::new(&mut self.stream).poll_flush(cx).map_err(io_error)
    }

    fn poll_shutdown(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        match ready!(Pin::new(&mut self.stream).poll_close(cx)) {
            Ok(()) | Err(Error::ConnectionClosed | Error::AlreadyClosed) => Poll::Ready(Ok(())),
            Err(e) => Poll::Ready(Err(io_error(e))),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use tokio::io::{AsyncReadExt, AsyncWriteExt};

    /// True if a read of `held` would wait now: data already sitting in
    /// the pipe would otherwise be returned at once.
    async fn read_waits(held: &mut HeldBack<tokio::io::DuplexStream>) -> bool {
        let mut byte = [0u8; 1];
        tokio::select! {
            biased;
            _ = held.read(&mut byte) => false,
            _ = tokio::task::yield_now() => true,
        }
    }

    #[tokio::test]
    async fn a_held_back_socket_reads_its_budget_then_waits_until_released() {
        let (mut client, server) = tokio::io::duplex(1024);
        client.write_all(&[7u8; 25]).await.unwrap();
        let mut held = HeldBack::new(server, 10);
        let mut read = Vec::new();
        while read.len() < 10 {
            let mut chunk = [0u8; 64];
            let n = held.read(&mut chunk).await.unwrap();
            read.extend_from_slice(&chunk[..n]);
        }
        assert_eq!(read.len(), 10, "never past the budget");
        assert!(read_waits(&mut held).await, "15 bytes wait in the pipe");
        held.release();
        let mut rest = [0u8; 64];
        let n = held.read(&mut rest).await.unwrap();
        assert_eq!(n, 15, "the rest once released");
        // Writes were never held back.
        held.write_all(b"connack").await.unwrap();
        let mut answer = [0u8; 7];
        client.read_exact(&mut answer).await.unwrap();
        assert_eq!(&answer, b"connack");
    }
}
