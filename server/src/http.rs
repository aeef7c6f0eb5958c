//! Serving an axum router on a TCP listener so that no peer can lock the
//! operators out, whatever it holds open. Bounds:
//! - At most [`MAX_CONNECTIONS`] connections at once (fewer when the
//!   process's open-file limit is low: see [`capacity`]), and at most
//!   [`MAX_PER_SOURCE`] from one IP address.
//! - A new connection that would pass either bound makes room by closing
//!   the oldest *waiting* connection (one not being served: silent,
//!   still sending its request, or idle between requests) of its own
//!   address, or, for the overall bound, of the address holding the most
//!   connections. A peer's silent sockets therefore hold their slots only
//!   until somebody else needs one, and a busy address gives up its own
//!   before anyone else's. Only when every candidate is being served is
//!   the new connection closed at accept.
//! - The request head within [`HEADER_TIMEOUT`] (also between keep-alive
//!   requests), its body within [`BODY_TIMEOUT`] of the head, each
//!   connection at most [`CONNECTION_LIFETIME`] (then closed after its
//!   current request), request bodies capped by the router's own
//!   `DefaultBodyLimit`.
//! - Closing: the answer's end is sent (FIN), then what the peer still
//!   sends is read and thrown away until its own end, at most
//!   [`LINGER`] (RFC 9112's lingering close). A socket closed with
//!   bytes unread (a body the handler never asked for, a pipelined
//!   request) makes the kernel reset the connection, and a reset throws
//!   away the answer's bytes not yet sent.
//! - An answer the peer stops reading: a connection whose writes have
//!   made no progress for [`WRITE_TIMEOUT`] (the socket's buffers full,
//!   the peer not reading) is closed, and with it the rest of the answer
//!   it held (a connection being served is never closed to make room, so
//!   without this a client that asked for `/api/queues` or
//!   `/metrics/per-object` and stopped reading held its slot and the
//!   answer for ever). A slow reader that keeps reading is not closed.
//!
//! Connections closed by these bounds are counted and logged (a warning
//! at most every [`REPORT_EVERY`], the first one at once).
//!
//! Each request carries its peer's address as a [`Peer`] extension (for
//! RabbitMQ's `loopback_users`). HTTP/1.1 only, as RabbitMQ's listeners
//! are served. hyper (through hyper-util's connection builder) does the
//! protocol; axum's `Router` is the service. The loop is ours rather than
//! `axum::serve` so the bounds sit in one place.

use axum::body::Body;
use axum::Router;
use bytes::Bytes;
use hyper::body::{Frame, Incoming, SizeHint};
use hyper_util::rt::{TokioIo, TokioTimer};
use hyper_util::service::TowerToHyperService;
use std::collections::{BTreeMap, HashMap};
use std::convert::Infallible;
use std::future::Future;
use std::net::{IpAddr, SocketAddr};
use std::pin::Pin;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::task::{Context, Poll};
use std::time::{Duration, Instant};
use tokio::net::TcpListener;
use tokio::sync::{watch, Notify};

/// Connections served at once per listener, at most.
pub const MAX_CONNECTIONS: usize = 1024;
/// Connections from one IP address per listener, at most.
pub const MAX_PER_SOURCE: usize = 256;
/// Time a client has to send a request's head, and to start the next one
/// on a kept-alive connection.
pub const HEADER_TIMEOUT: Duration = Duration::from_secs(2);
/// Time a client has to send a request's body, from its head.
pub const BODY_TIMEOUT: Duration = Duration::from_secs(10);
/// Longest a connection's writes may make no progress (the peer not
/// reading its answer) before it is closed.
pub const WRITE_TIMEOUT: Duration = Duration::from_secs(5);
/// Longest a closing connection reads what its peer still sends before
/// it is closed (see the module's documentation).
pub const LINGER: Duration = Duration::from_secs(2);
/// Longest a connection is kept (keep-alive included).
pub const CONNECTION_LIFETIME: Duration = Duration::from_secs(300);
/// Longest gap between two log lines about connections closed to make
/// room (they are counted in between, not logged one by one).
const REPORT_EVERY: Duration = Duration::from_secs(10);

/// The peer of the connection a request came on (a request extension).
#[derive(Debug, Clone, Copy)]
pub struct Peer(pub SocketAddr);

/// The connections a listener may hold at once: [`MAX_CONNECTIONS`], or a
/// quarter of the process's open-file limit when that is lower (two such
/// listeners then leave half of the limit to AMQP).
pub fn capacity() -> usize {
    let limit = rustix::process::getrlimit(rustix::process::Resource::Nofile)
        .current
        .unwrap_or(u64::MAX);
    MAX_CONNECTIONS.min(usize::try_from(limit / 4).unwrap_or(usize::MAX).max(1))
}

/// What the accept loop and a connection's task share about it.
#[derive(Debug, Default)]
struct Connection {
    /// A request of it is being served (its body was read, or its
    /// handler is running, or its answer is being sent): it is not
    /// closed to make room.
    serving: AtomicBool,
    /// Told to close at once (to make room, or a body too slow).
    close: Notify,
    /// Its writes made no progress for [`WRITE_TIMEOUT`]: closed for it.
    write_stalled: AtomicBool,
}

impl Connection {
    fn close_now(&self) {
        self.close.notify_one();
    }
}

/// The connections a listener holds, by source address, oldest first.
#[derive(Debug)]
struct Table {
    capacity: usize,
    per_source: usize,
    next_id: u64,
    held: usize,
    sources: HashMap<IpAddr, BTreeMap<u64, Arc<Connection>>>,
    /// Connections closed to make room, and new ones closed at accept,
    /// since the last log line about them.
    made_room: u64,
    refused: u64,
    write_stalled: u64,
    /// When the last such line was logged (`None`: never).
    reported: Option<Instant>,
}

impl Table {
    fn new(capacity: usize, per_source: usize) -> Self {
        Table {
            capacity,
            per_source: per_source.min(capacity),
            next_id: 0,
            held: 0,
            sources: HashMap::new(),
            made_room: 0,
            refused: 0,
            write_stalled: 0,
            reported: None,
        }
    }

    /// Admits a connection from `source`, closing a waiting one if a
    /// bound needs it (see the module docs); `None` when it must be
    /// closed instead.
    fn admit(&mut self, source: IpAddr) -> Option<(u64, Arc<Connection>)> {
        let from_source = self.sources.get(&source).map_or(0, BTreeMap::len);
        let room = (from_source < self.per_source || self.close_waiting(source))
            && (self.held < self.capacity || self.close_waiting_of_busiest());
        if !room {
            self.refused += 1;
            return None;
        }
        let id = self.next_id;
        self.next_id += 1;
        let connection = Arc::new(Connection::default());
        self.sources
            .entry(source)
            .or_default()
            .insert(id, Arc::clone(&connection));
        self.held += 1;
        Some((id, connection))
    }

    /// Closes the oldest waiting connection of `source`; false if it has
    /// none.
    fn close_waiting(&mut self, source: IpAddr) -> bool {
        let Some(connections) = self.sources.get_mut(&source) else {
            return false;
        };
        let Some(id) = connections
            .iter()
            .find(|(_, c)| !c.serving.load(Ordering::Acquire))
            .map(|(id, _)| *id)
        else {
            return false;
        };
        if let Some(connection) = connections.remove(&id) {
            connection.close_now();
        }
        if connections.is_empty() {
            self.sources.remove(&source);
        }
        self.held -= 1;
        self.made_room += 1;
        true
    }

    /// Closes the oldest waiting connection of the address holding the
    /// most (the next busiest if that one's are all being served).
    fn close_waiting_of_busiest(&mut self) -> bool {
        let mut by_count: Vec<(usize, IpAddr)> = self
            .sources
            .iter()
            .map(|(source, connections)| (connections.len(), *source))
            .collect();
        by_count.sort_unstable_by(|a, b| b.cmp(a));
        by_count
            .into_iter()
            .any(|(_, source)| self.close_waiting(source))
    }

    /// Forgets a connection that ended (no-op if it was closed to make
    /// room, which forgot it then).
    fn forget(&mut self, source: IpAddr, id: u64) {
        if let Some(connections) = self.sources.get_mut(&source) {
            if connections.remove(&id).is_some() {
                self.held -= 1;
            }
            if connections.is_empty() {
                self.sources.remove(&source);
            }
        }
    }

    /// Logs what the bounds closed since the last such line, at most
    /// once per [`REPORT_EVERY`] (what is closed in between is counted
    /// and logged with the next event after it).
    fn report(&mut self, what: &'static str) {
        if (self.made_room, self.refused, self.write_stalled) == (0, 0, 0)
            || self.reported.is_some_and(|at| at.elapsed() < REPORT_EVERY)
        {
            return;
        }
        tracing::warn!(
            listener = what,
            held = self.held,
            capacity = self.capacity,
            per_source = self.per_source,
            closed_to_make_room = self.made_room,
            closed_at_accept = self.refused,
            closed_not_reading = self.write_stalled,
            write_timeout = ?WRITE_TIMEOUT,
            "HTTP connections closed by the listener's bounds: waiting ones to make room, or peers that stopped reading their answer"
        );
        self.made_room = 0;
        self.refused = 0;
        self.write_stalled = 0;
        self.reported = Some(Instant::now());
    }
}

type Shared = Arc<Mutex<Table>>;

fn lock(table: &Shared) -> std::sync::MutexGuard<'_, Table> {
    table.lock().unwrap_or_else(|e| e.into_inner())
}

/// Serves `router` on `listener` until `stop` turns true.
pub async fn serve(
    listener: TcpListener,
    router: Router,
    what: &'static str,
    mut stop: watch::Receiver<bool>,
) {
    let table: Shared = Arc::new(Mutex::new(Table::new(capacity(), MAX_PER_SOURCE)));
    loop {
        let accepted = tokio::select! {
            accepted = listener.accept() => accepted,
            _ = stop.wait_for(|stop| *stop) => return,
        };
        let (stream, peer) = match accepted {
            Ok(pair) => pair,
            Err(e) => {
                tracing::warn!(listener = what, error = %e, "accept failed");
                tokio::time::sleep(Duration::from_millis(50)).await;
                continue;
            }
        };
        let source = peer.ip().to_canonical();
        let admitted = {
            let mut table = lock(&table);
            let admitted = table.admit(source);
            table.report(what);
            admitted
        };
        // One accept per turn of the scheduler: the connections accepted
        // before get to read their request (and so count as being served)
        // before a flood's next sockets can make room by closing them.
        tokio::task::yield_now().await;
        let Some((id, connection)) = admitted else {
            continue;
        };
        let service = Tracked {
            router: TowerToHyperService::new(router.clone()),
            connection: Arc::clone(&connection),
            peer,
        };
        let table = Arc::clone(&table);
        let stop = stop.clone();
        tokio::spawn(async move {
            run(stream, service, &connection, what, peer, stop).await;
            let mut table = lock(&table);
            table.forget(source, id);
            if connection.write_stalled.load(Ordering::Acquire) {
                table.write_stalled += 1;
                table.report(what);
            }
        });
    }
}

/// Serves one connection until it ends, its lifetime is over, the
/// listener stops, or it is told to close.
async fn run(
    stream: tokio::net::TcpStream,
    service: Tracked,
    connection: &Connection,
    what: &'static str,
    peer: SocketAddr,
    mut stop: watch::Receiver<bool>,
) {
    let served = hyper::server::conn::http1::Builder::new()
        .timer(TokioTimer::new())
        .header_read_timeout(HEADER_TIMEOUT)
        .serve_connection(
            TokioIo::new(LingeringClose::new(WriteTimeout::new(
                stream,
                WRITE_TIMEOUT,
                connection,
            ))),
            service,
        );
    tokio::pin!(served);
    let deadline = tokio::time::sleep(CONNECTION_LIFETIME);
    tokio::pin!(deadline);
    let mut closing = false;
    loop {
        tokio::select! {
            result = served.as_mut() => {
                if let Err(e) = result {
                    tracing::debug!(listener = what, %peer, error = %e, "HTTP connection ended with an error");
                }
                return;
            }
            _ = connection.close.notified() => {
                tracing::debug!(listener = what, %peer, "HTTP connection closed: room needed or body too slow");
                return;
            }
            _ = &mut deadline, if !closing => {
                closing = true;
                served.as_mut().graceful_shutdown();
            }
            _ = stop.wait_for(|stop| *stop), if !closing => {
                closing = true;
                served.as_mut().graceful_shutdown();
            }
        }
    }
}

/// A connection's socket whose writes fail with `TimedOut` once they have
/// made no progress for `limit` (one that makes progress starts the
/// count again), marking the connection `write_stalled`.
struct WriteTimeout<'c> {
    inner: tokio::net::TcpStream,
    limit: Duration,
    /// Since when the writes have been waiting, if they are.
    stalled: Option<Pin<Box<tokio::time::Sleep>>>,
    connection: &'c Connection,
}

impl<'c> WriteTimeout<'c> {
    fn new(inner: tokio::net::TcpStream, limit: Duration, connection: &'c Connection) -> Self {
        WriteTimeout {
            inner,
            limit,
            stalled: None,
            connection,
        }
    }

    /// `attempt`'s result if it is ready (progress: the count starts
    /// again), else `TimedOut` once the writes have waited `limit`.
    fn bounded<T>(
        &mut self,
        cx: &mut Context<'_>,
        attempt: Poll<std::io::Result<T>>,
    ) -> Poll<std::io::Result<T>> {
        if attempt.is_ready() {
            self.stalled = None;
            return attempt;
        }
        let limit = self.limit;
        let stalled = self
            .stalled
            .get_or_insert_with(|| Box::pin(tokio::time::sleep(limit)));
        if stalled.as_mut().poll(cx).is_pending() {
            return Poll::Pending;
        }
        self.connection.write_stalled.store(true, Ordering::Release);
        Poll::Ready(Err(std::io::Error::new(
            std::io::ErrorKind::TimedOut,
            "the peer has not read its answer for the write timeout",
        )))
    }
}

impl tokio::io::AsyncRead for WriteTimeout<'_> {
    fn poll_read(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &mut tokio::io::ReadBuf<'_>,
    ) -> Poll<std::io::Result<()>> {
        Pin::new(&mut self.inner).poll_read(cx, buf)
    }
}

impl tokio::io::AsyncWrite for WriteTimeout<'_> {
    fn poll_write(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &[u8],
    ) -> Poll<std::io::Result<usize>> {
        let attempt = Pin::new(&mut self.inner).poll_write(cx, buf);
        self.bounded(cx, attempt)
    }

    fn poll_write_vectored(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        bufs: &[std::io::IoSlice<'_>],
    ) -> Poll<std::io::Result<usize>> {
        let attempt = Pin::new(&mut self.inner).poll_write_vectored(cx, bufs);
        self.bounded(cx, attempt)
    }

    fn is_write_vectored(&self) -> bool {
        self.inner.is_write_vectored()
    }

    fn poll_flush(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<std::io::Result<()>> {
        let attempt = Pin::new(&mut self.inner).poll_flush(cx);
        self.bounded(cx, attempt)
    }

    fn poll_shutdown(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<std::io::Result<()>> {
        let attempt = Pin::new(&mut self.inner).poll_shutdown(cx);
        self.bounded(cx, attempt)
    }
}

/// A connection's socket whose shutdown, once its own end is sent, reads
/// and throws away what the peer still sends, until the peer's end or
/// [`LINGER`], so the socket is never closed with bytes unread (the
/// kernel would answer them with a reset, which discards the answer's
/// bytes still in the send buffer).
struct LingeringClose<S> {
    inner: S,
    /// Set once the socket's own end is sent: when the lingering stops.
    lingering: Option<Pin<Box<tokio::time::Sleep>>>,
}

impl<S> LingeringClose<S> {
    fn new(inner: S) -> Self {
        LingeringClose {
            inner,
            lingering: None,
        }
    }
}

impl<S: tokio::io::AsyncRead + Unpin> tokio::io::AsyncRead for LingeringClose<S> {
    fn poll_read(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &mut tokio::io::ReadBuf<'_>,
    ) -> Poll<std::io::Result<()>> {
        Pin::new(&mut self.inner).poll_read(cx, buf)
    }
}

impl<S: tokio::io::AsyncRead + tokio::io::AsyncWrite + Unpin> tokio::io::AsyncWrite
    for LingeringClose<S>
{
    fn poll_write(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &[u8],
    ) -> Poll<std::io::Result<usize>> {
        Pin::new(&mut self.inner).poll_write(cx, buf)
    }

    fn poll_write_vectored(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        bufs: &[std::io::IoSlice<'_>],
    ) -> Poll<std::io::Result<usize>> {
        Pin::new(&mut self.inner).poll_write_vectored(cx, bufs)
    }

    fn is_write_vectored(&self) -> bool {
        self.inner.is_write_vectored()
    }

    fn poll_flush(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<std::io::Result<()>> {
        Pin::new(&mut self.inner).poll_flush(cx)
    }

    fn poll_shutdown(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<std::io::Result<()>> {
        /// Reads a turn takes before it lets others run (a peer that
        /// keeps sending is read in slices, at most until [`LINGER`]).
        const READS_A_TURN: usize = 16;
        let this = &mut *self;
        if this.lingering.is_none() {
            match Pin::new(&mut this.inner).poll_shutdown(cx) {
                Poll::Ready(Ok(())) => {}
                other => return other,
            }
        }
        let lingering = this
            .lingering
            .get_or_insert_with(|| Box::pin(tokio::time::sleep(LINGER)));
        let mut scratch = [0u8; 4096];
        let mut drained = false;
        for _ in 0..READS_A_TURN {
            let mut buf = tokio::io::ReadBuf::new(&mut scratch);
            match Pin::new(&mut this.inner).poll_read(cx, &mut buf) {
                // The peer's end, or a socket that can no longer be read:
                // nothing is left to throw away.
                Poll::Ready(Ok(())) if buf.filled().is_empty() => return Poll::Ready(Ok(())),
                Poll::Ready(Err(_)) => return Poll::Ready(Ok(())),
                Poll::Ready(Ok(())) => {}
                Poll::Pending => {
                    drained = true;
                    break;
                }
            }
        }
        if lingering.as_mut().poll(cx).is_ready() {
            return Poll::Ready(Ok(()));
        }
        if !drained {
            // More may be waiting: read on after letting others run (the
            // socket wakes this task only when it has read all there was).
            cx.waker().wake_by_ref();
        }
        Poll::Pending
    }
}

/// The router as one connection's hyper service: marks the connection
/// as being served from the moment a request is wholly received until
/// its answer is sent, bounds the time its body may take, and tags each
/// request with the [`Peer`].
#[derive(Clone)]
struct Tracked {
    router: TowerToHyperService<Router>,
    connection: Arc<Connection>,
    peer: SocketAddr,
}

impl hyper::service::Service<hyper::Request<Incoming>> for Tracked {
    type Response = axum::response::Response;
    type Error = Infallible;
    type Future = Pin<Box<dyn Future<Output = Result<Self::Response, Infallible>> + Send>>;

    fn call(&self, request: hyper::Request<Incoming>) -> Self::Future {
        let (mut parts, body) = request.into_parts();
        parts.extensions.insert(Peer(self.peer));
        if hyper::body::Body::is_end_stream(&body) {
            self.connection.serving.store(true, Ordering::Release);
        }
        let body = TimedBody {
            inner: body,
            deadline: Box::pin(tokio::time::sleep(BODY_TIMEOUT)),
            connection: Arc::clone(&self.connection),
        };
        let answered = self
            .router
            .call(hyper::Request::from_parts(parts, Body::new(body)));
        let connection = Arc::clone(&self.connection);
        Box::pin(async move {
            let (parts, body) = answered.await?.into_parts();
            connection.serving.store(true, Ordering::Release);
            let answer = Answer {
                inner: body,
                connection,
            };
            Ok(axum::response::Response::from_parts(
                parts,
                Body::new(answer),
            ))
        })
    }
}

/// A request body that must arrive within [`BODY_TIMEOUT`]: past it the
/// connection is closed. Its end marks the connection as being served.
struct TimedBody {
    inner: Incoming,
    deadline: Pin<Box<tokio::time::Sleep>>,
    connection: Arc<Connection>,
}

impl hyper::body::Body for TimedBody {
    type Data = Bytes;
    type Error = hyper::Error;

    fn poll_frame(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
    ) -> Poll<Option<Result<Frame<Bytes>, hyper::Error>>> {
        let this = &mut *self;
        match Pin::new(&mut this.inner).poll_frame(cx) {
            Poll::Pending => {
                if this.deadline.as_mut().poll(cx).is_ready() {
                    this.connection.close_now();
                }
                Poll::Pending
            }
            Poll::Ready(frame) => {
                if frame.is_none() || this.inner.is_end_stream() {
                    this.connection.serving.store(true, Ordering::Release);
                }
                Poll::Ready(frame)
            }
        }
    }

    fn is_end_stream(&self) -> bool {
        self.inner.is_end_stream()
    }

    fn size_hint(&self) -> SizeHint {
        self.inner.size_hint()
    }
}

/// A response body; when it is sent (or dropped), the connection waits
/// for its next request again.
struct Answer {
    inner: Body,
    connection: Arc<Connection>,
}

impl Drop for Answer {
    fn drop(&mut self) {
        self.connection.serving.store(false, Ordering::Release);
    }
}

impl hyper::body::Body for Answer {
    type Data = Bytes;
    type Error = axum::Error;

    fn poll_frame(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
    ) -> Poll<Option<Result<Frame<Bytes>, axum::Error>>> {
        Pin::new(&mut self.inner).poll_frame(cx)
    }

    fn is_end_stream(&self) -> bool {
        self.inner.is_end_stream()
    }

    fn size_hint(&self) -> SizeHint {
        self.inner.size_hint()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn ip(last: u8) -> IpAddr {
        IpAddr::from([10, 0, 0, last])
    }

    fn closed(connection: &Connection) -> bool {
        use std::future::Future;
        let notified = connection.close.notified();
        tokio::pin!(notified);
        let waker = std::task::Waker::noop();
        notified
            .as_mut()
            .poll(&mut Context::from_waker(waker))
            .is_ready()
    }

    #[test]
    fn a_full_address_gives_up_its_own_oldest_waiting_connection() {
        let mut table = Table::new(100, 3);
        let other = table.admit(ip(2)).expect("room").1;
        let first = table.admit(ip(1)).expect("room").1;
        let second = table.admit(ip(1)).expect("room").1;
        let third = table.admit(ip(1)).expect("room").1;
        first.serving.store(true, Ordering::Release);
        // The fourth from 10.0.0.1: its oldest waiting one goes (the first
        // is being served), never another address's.
        let fourth = table.admit(ip(1)).expect("room").1;
        assert!(closed(&second));
        assert!(!closed(&first) && !closed(&third) && !closed(&fourth) && !closed(&other));
        assert_eq!(table.held, 4);
        // All of 10.0.0.1's being served: the next one is refused.
        for c in [&third, &fourth] {
            c.serving.store(true, Ordering::Release);
        }
        assert!(table.admit(ip(1)).is_none());
        assert_eq!((table.held, table.made_room, table.refused), (4, 1, 1));
    }

    #[test]
    fn a_full_listener_makes_room_at_the_busiest_address() {
        let mut table = Table::new(4, 4);
        let quiet = table.admit(ip(1)).expect("room").1;
        let busy: Vec<_> = (0..3).map(|_| table.admit(ip(2)).expect("room")).collect();
        // Full: a newcomer takes the busiest address's oldest waiting slot.
        let newcomer = table.admit(ip(3)).expect("room").1;
        assert!(closed(&busy[0].1));
        assert!(!closed(&quiet) && !closed(&newcomer));
        // The busiest's all being served: the next busiest gives way.
        for (_, c) in &busy[1..] {
            c.serving.store(true, Ordering::Release);
        }
        table.admit(ip(4)).expect("room");
        assert!(closed(&quiet) || closed(&newcomer));
        assert_eq!(table.held, 4);
        // A connection closed to make room is forgotten once, not twice.
        table.forget(ip(2), busy[0].0);
        assert_eq!(table.held, 4);
        table.forget(ip(2), busy[1].0);
        assert_eq!(table.held, 3);
    }

    #[test]
    fn the_capacity_leaves_room_under_the_open_file_limit() {
        let capacity = capacity();
        assert!((1..=MAX_CONNECTIONS).contains(&capacity));
    }
}
