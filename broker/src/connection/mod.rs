//! One client connection: the protocol header, the connection.* handshake
//! (start, start-ok with PLAIN/AMQPLAIN, tune, open) within the handshake
//! timeout, then the reader loop that hands frames (and an in-process
//! client's whole publishes) to channels, heartbeats, memory-alarm
//! blocking, and closing in either direction. Limits on what a client may
//! open (connections per vhost, channels per connection) are enforced
//! here.
//!
//! Layout: `handshake` is the connection.* handshake, a function a step;
//! `source` is what the loop needs of its input; `reader` reads frames
//! into a buffer sized to the traffic; `direct` is the in-process value
//! link, whose loop its client may run (`direct_loop`); `writer` owns the
//! socket's write half, reached through the outbox. What a client may
//! open is counted by the crate's `admission` (connections against
//! `max_connections`, user and vhost limits), which the core holds.

mod direct;
mod direct_loop;
mod handshake;
mod reader;
mod source;
mod writer;

use crate::admission::{self, Slot};
pub use direct::{DirectLink, DirectReplies, DirectReply, DIRECT_CAPACITY};
pub use direct_loop::{DirectLoop, LoopClaim};
pub(crate) use reader::copy_below;

use crate::channel::confirms::confirms_due;
use crate::channel::{AtOnce, Channel, Leftover, WholePublish};
use crate::core::Core;
use crate::error::{AmqpError, AmqpResult};
use crate::outbox::{Outbound, Outbox};
use crate::stats::ConnectionTraffic;
use crate::vhost::Vhost;
use crate::word_hash::{WordHashMap, WordHashSet};
use bytes::Bytes;
use leveret_protocol::{
    ConnectionClose, ConnectionCloseOk, ConnectionUpdateSecretOk, Frame, Method, ReplyCode,
    ShortStr, FRAME_MIN_SIZE, PROTOCOL_HEADER,
};
use reader::{FrameReader, Incoming, IDLE_RELEASE};
use source::{FrameSource, ReadError};
use std::net::SocketAddr;
use std::sync::Arc;
use std::time::Duration;
use tokio::io::{AsyncWrite, AsyncWriteExt};
use tokio::time::Instant;

/// What the connection loop takes next from its source.
enum Input {
    Frame(Frame),
    Publish(WholePublish),
}

/// The longest a publishing connection waits for one crowded queue.
const FLOW_WAIT: Duration = Duration::from_millis(100);
/// How long a client has to answer a close.
const CLOSE_TIMEOUT: Duration = Duration::from_secs(3);

/// What the transport tells about the client.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Identity {
    /// Plain TCP, or in-process.
    None,
    /// TLS, with the common name of the verified client certificate if the
    /// client gave one: SASL EXTERNAL logs in as it (and is refused
    /// without one).
    #[cfg_attr(not(any(feature = "tls", feature = "mqtt")), allow(dead_code))]
    Tls(Option<String>),
}

/// The future that serves one connection over a byte stream until it
/// closes, to be spawned as it is (see [`Accepted`]); its connection id
/// and traffic counters are made now. `slot` is its place in the
/// connection counts, given back when it ends; `local` is the listener's
/// address it came in on (none in-process); `held` is dropped once the
/// connection has closed and let go of everything else (a listener's
/// count of open connections).
pub fn serve<R, W>(
    core: Arc<Core>,
    read: R,
    write: W,
    (peer, local): (String, Option<SocketAddr>),
    slot: Slot,
    identity: Identity,
    held: impl Send + 'static,
) -> impl std::future::Future<Output = ()> + Send + 'static
where
    R: Incoming + Sync,
    W: AsyncWrite + Unpin + Send + 'static,
{
    let traffic = Arc::new(ConnectionTraffic::new(Arc::clone(&core.stats)));
    let reader = FrameReader::new(read, core.busy_poll.clone(), Some(Arc::clone(&traffic)));
    let mut ends = Ends::new(peer, local, AMQP_0_9_1);
    ends.traffic = Some(Arc::clone(&traffic));
    let sink = SocketSink(writer::Counted::new(write, traffic));
    let connection_id = core.next_connection_id();
    serve_frames(Box::new(Accepted {
        core,
        connection_id,
        reader,
        sink,
        ends,
        slot,
        identity,
        held,
    }))
}

/// Starts serving an in-process client that exchanges frame values with
/// the broker (see `direct`), on the current runtime; the client holds
/// the returned link. `peer` names the client in logs and for
/// `loopback_users` (a socket address for a protocol front end such as
/// MQTT; anything else counts as local); `protocol` is what the client
/// speaks, as RabbitMQ lists it (`AMQP 0-9-1`, `MQTT 3.1.1`, `MQTT 5.0`),
/// and its first word names the connection in the log; `identity` what
/// the front end's transport tells (an MQTT session's TLS certificate, for
/// SASL EXTERNAL); `traffic` counts the front end's byte stream, listed
/// as the connection's (an MQTT session's socket); `done` is dropped when
/// the connection has ended and cleaned up. `connection_id` is the
/// connection's ([`Core::next_connection_id`]), for a front end that
/// closes it through the registry (an MQTT takeover).
pub fn serve_direct(
    core: Arc<Core>,
    connection_id: u64,
    slot: Slot,
    (peer, identity): (String, Identity),
    (protocol, traffic): (&'static str, Option<Arc<ConnectionTraffic>>),
    done: impl Send + 'static,
) -> DirectLink {
    direct::link(move |frames, start| {
        let mut ends = Ends::new(peer, None, protocol);
        ends.traffic = traffic;
        serve_frames(Box::new(Accepted {
            core,
            connection_id,
            reader: frames,
            sink: DirectSink(start),
            ends,
            slot,
            identity,
            held: done,
        }))
    })
}

/// Where a connection's outgoing items go: a writer task on a socket, or
/// an in-process client that takes them itself.
trait Sink: Send + 'static {
    /// Whether an in-process client takes the items (it counts down what
    /// it handles, for its inline deliveries: see [`Outbox::connection`]).
    const IN_PROCESS: bool;

    /// Answers a wrong protocol header with ours, and ends.
    fn refuse(self) -> impl std::future::Future<Output = ()> + Send;

    /// Hands the outbox's receiving end over; the task it returns ends
    /// once everything before [`Outbound::Shutdown`] is out.
    fn start(
        self,
        inbox: leveret_protocol::handoff::Receiver<Outbound>,
        outbox: Arc<Outbox>,
    ) -> tokio::task::JoinHandle<()>;
}

struct SocketSink<W>(W);

impl<W: AsyncWrite + Unpin + Send + 'static> Sink for SocketSink<W> {
    const IN_PROCESS: bool = false;

    async fn refuse(mut self) {
        let _ = self.0.write_all(PROTOCOL_HEADER).await;
        let _ = self.0.shutdown().await;
    }

    fn start(
        self,
        inbox: leveret_protocol::handoff::Receiver<Outbound>,
        outbox: Arc<Outbox>,
    ) -> tokio::task::JoinHandle<()> {
        tokio::spawn(writer::run(self.0, inbox, outbox))
    }
}

struct DirectSink(tokio::sync::oneshot::Sender<direct::WriterEnd>);

impl Sink for DirectSink {
    const IN_PROCESS: bool = true;

    async fn refuse(self) {}

    fn start(
        self,
        inbox: leveret_protocol::handoff::Receiver<Outbound>,
        outbox: Arc<Outbox>,
    ) -> tokio::task::JoinHandle<()> {
        // The client drains the outbox itself; a client already gone
        // drops the end, which the connection sees as a closed writer.
        let _ = self.0.send(direct::WriterEnd { inbox, outbox });
        tokio::spawn(async {})
    }
}

/// A connection as it starts: what carries its frames each way, who it
/// is, where it stands in the connection counts, and what it holds until
/// it has closed (`held`: its listener's count of open connections, an
/// in-process client's signal that it has ended). Boxed into its future,
/// which would otherwise keep room for its arguments for its whole life
/// (issue 32's idle memory). Spawn the future as it is where possible: a
/// block around it keeps room for the block's own captures besides.
struct Accepted<S, K, H> {
    core: Arc<Core>,
    connection_id: u64,
    reader: S,
    sink: K,
    ends: Ends,
    slot: Slot,
    identity: Identity,
    held: H,
}

/// Serves one connection, whatever carries its frames, until it closes.
async fn serve_frames<S: FrameSource, K: Sink, H: Send>(accepted: Box<Accepted<S, K, H>>) {
    // Unboxed in a block of its own, so that the box is freed now, not
    // when the connection ends.
    // `held` first: bound first, it is dropped last on an early return.
    let Accepted {
        held,
        core,
        connection_id,
        mut reader,
        sink,
        ends,
        slot,
        identity,
    } = {
        let boxed = accepted;
        *boxed
    };
    let Ends {
        peer,
        local,
        label,
        protocol,
        traffic,
    } = ends;
    let started = Instant::now();
    let _registration = core
        .registry
        .connection(connection_id, &peer, protocol, traffic);
    // RabbitMQ's lines name MQTT connections as such.
    let kind = protocol.split(' ').next().unwrap_or(protocol);
    // RabbitMQ's handshake_timeout runs from the connection's start to
    // connection.open-ok.
    let handshake_deadline = Instant::now() + core.limits.handshake_timeout;
    let header = handshake::protocol_header(&core, handshake_deadline, &peer, &mut reader, sink);
    let header = Box::pin(header).await;
    let Some(sink) = header else {
        return;
    };
    tracing::info!(
        connection = connection_id,
        %peer,
        local = local.map(tracing::field::display),
        "accepting {kind} connection #{connection_id} ({label})"
    );
    let closing =
        (core.registry.close_signal(connection_id)).unwrap_or_else(|| core.shutdown_signal());
    let (outbox, inbox) = Outbox::connection(connection_id, K::IN_PROCESS, closing);
    let mut writer = sink.start(inbox, Arc::clone(&outbox));
    let mut conn = Connection {
        core,
        outbox,
        connection_id,
        peer,
        label,
        kind,
        client_name: None,
        slot,
        identity,
        user: String::new(),
        vhost: None,
        channels: WordHashMap::default(),
        closed_this_batch: WordHashSet::default(),
        channel_max: 0,
        copy_below: copy_below(FRAME_MIN_SIZE),
        heartbeat: Duration::ZERO,
        blocked_notify: false,
        blocked: false,
    };
    let outcome = conn.run(&mut reader, handshake_deadline).await;
    conn.cleanup();
    // A client that stopped answering (missed heartbeats) may have
    // stopped reading too, with the writer blocked on its full socket:
    // the writer is stopped where it is, as RabbitMQ closes the socket,
    // and what it held is dropped. Otherwise it gets what is queued out
    // within the close timeout.
    let unresponsive = matches!(
        outcome,
        Err(Ended::MissedHeartbeats(_) | Ended::Read(ReadError::TimedOut))
    );
    conn.log_close(&outcome, started.elapsed());
    if unresponsive {
        writer.abort();
    }
    let drained = async {
        conn.outbox.send_closing(Outbound::Shutdown).await;
        let _ = (&mut writer).await;
    };
    if tokio::time::timeout(CLOSE_TIMEOUT, drained).await.is_err() {
        tracing::info!(peer = %conn.peer, "client not reading; closing its socket with output unsent");
        writer.abort();
        let _ = writer.await;
    }
    // What the connection held goes before `held` says it has ended.
    drop((conn, reader, _registration));
    drop(held);
}

/// Where a connection comes from and goes to, for its log lines.
struct Ends {
    peer: String,
    local: Option<SocketAddr>,
    /// `peer -> local` as RabbitMQ logs it (the peer alone in-process).
    label: String,
    protocol: &'static str,
    /// The socket's traffic counters (none in-process).
    traffic: Option<Arc<ConnectionTraffic>>,
}

/// The protocol of a client on an AMQP socket, as RabbitMQ lists it.
pub const AMQP_0_9_1: &str = "AMQP 0-9-1";

impl Ends {
    fn new(peer: String, local: Option<SocketAddr>, protocol: &'static str) -> Ends {
        let label = match local {
            Some(local) => format!("{peer} -> {local}"),
            None => peer.clone(),
        };
        Ends {
            peer,
            local,
            label,
            protocol,
            traffic: None,
        }
    }
}

/// A client-supplied text made safe for a log line: control characters
/// escaped (no forged lines), at most [`LOGGED_TEXT_MAX`] characters.
fn loggable(text: &[u8]) -> String {
    let text = String::from_utf8_lossy(text);
    let mut out = String::new();
    for c in text.chars().take(LOGGED_TEXT_MAX) {
        if c.is_control() {
            out.extend(c.escape_default());
        } else {
            out.push(c);
        }
    }
    out
}

/// The longest client-supplied text logged (a user or connection name,
/// or a close text, which AMQP caps at 255 bytes).
const LOGGED_TEXT_MAX: usize = 300;

struct Connection {
    core: Arc<Core>,
    outbox: Arc<Outbox>,
    connection_id: u64,
    peer: String,
    /// `peer -> local`.
    label: String,
    /// `AMQP` or `MQTT`, for the log lines.
    kind: &'static str,
    /// The client-provided name (`connection_name`), for the log lines.
    client_name: Option<String>,
    slot: Slot,
    identity: Identity,
    user: String,
    vhost: Option<Arc<Vhost>>,
    /// Looked up per frame: hashed by a multiply, not SipHash (which
    /// showed in profiles under load); see `word_hash` for why a peer's
    /// channel numbers are safe keys for it. Boxed: the map keeps room for
    /// a few entries, and a channel is large (some 650 bytes), so a
    /// connection with one channel would hold room for three more.
    channels: WordHashMap<u16, Box<Channel>>,
    /// Channels the client closed (`channel.close`, already answered and
    /// removed) in the batch of buffered frames being handled: what it
    /// sent on them behind the close in that batch is discarded, as
    /// RabbitMQ's channel does until its close handshake ends, not an
    /// error for an unopened channel. Emptied when the batch ends.
    closed_this_batch: WordHashSet<u16>,
    /// Most channels open at once (the negotiated channel_max; 0 from the
    /// client means the broker's).
    channel_max: u16,
    /// Content below this size is copied out of the read buffer.
    copy_below: usize,
    heartbeat: Duration,
    blocked_notify: bool,
    blocked: bool,
}

/// How the connection ended (other than by the client's close), for the
/// log line.
#[derive(Debug, thiserror::Error)]
enum Ended {
    /// The broker closed it with this error.
    #[error("{0}")]
    Protocol(AmqpError),
    /// Closed with CONNECTION_FORCED: by an administrator or at shutdown.
    #[error("{0}")]
    Forced(String),
    /// A login refused to a client that did not ask for a close: the
    /// socket is just closed, as RabbitMQ does.
    #[error("{0}")]
    Refused(String),
    #[error("missed heartbeats from client, timeout: {}s", .0.as_secs())]
    MissedHeartbeats(Duration),
    #[error("client unexpectedly closed TCP connection")]
    PeerClosed,
    #[error("socket: {0}")]
    Read(ReadError),
}

impl From<ReadError> for Ended {
    fn from(e: ReadError) -> Self {
        use std::io::ErrorKind::{BrokenPipe, ConnectionAborted, ConnectionReset, UnexpectedEof};
        match e {
            ReadError::Closed => Ended::PeerClosed,
            ReadError::Io(e)
                if matches!(
                    e.kind(),
                    ConnectionReset | ConnectionAborted | BrokenPipe | UnexpectedEof
                ) =>
            {
                Ended::PeerClosed
            }
            e => Ended::Read(e),
        }
    }
}

impl Connection {
    async fn run<R: FrameSource>(
        &mut self,
        reader: &mut R,
        handshake_deadline: Instant,
    ) -> Result<(), Ended> {
        // The handshake and a close (once a connection each) are boxed
        // futures, so that the connection's future holds no room for them
        // through the hours an idle connection may wait.
        match Box::pin(self.handshake(reader, handshake_deadline)).await {
            Ok(()) => {}
            Err(Ended::Protocol(error)) => return Box::pin(self.close_with(reader, error)).await,
            Err(e) => return Err(e),
        }
        self.log_open();
        let mut shutdown = (self.core.registry.close_signal(self.connection_id))
            .unwrap_or_else(|| self.core.shutdown_signal());
        // A close told during the handshake is news to the loop too.
        if *shutdown.borrow() {
            shutdown.mark_changed();
        }
        let mut alarms = self.core.gauge.raised();
        // One deadline for client silence, re-armed only when it fires (a
        // timer reset per read would cost a timer-wheel update per batch).
        let silence_limit = self.heartbeat * 2;
        let mut last_read = tokio::time::Instant::now();
        self.outbox.heard(last_read);
        let silence = tokio::time::sleep(silence_limit);
        tokio::pin!(silence);
        // Likewise for giving back a read buffer grown by a burst: due
        // `IDLE_RELEASE` after the last read that brought more than
        // heartbeats (a client that sends them every second or faster
        // would otherwise keep a burst's buffer for good). A frame still
        // arriving a second after its first bytes keeps the room it needs
        // (`FrameReader::release_spare`).
        let release = tokio::time::sleep(IDLE_RELEASE);
        tokio::pin!(release);
        let mut last_busy = last_read;
        // Told to close (a management close, an MQTT takeover's, the
        // broker's shutdown), a connection handles nothing it reads later.
        // A socket client's frames of a read made before are all handled,
        // as RabbitMQ handles every whole frame of its current read before
        // it sees a forced close; an in-process client's link holds all it
        // sent as one read, so it is checked before each frame there (one
        // atomic load a frame).
        let check_each_frame = self.outbox.in_process();
        loop {
            if told_to_close(&shutdown) {
                return Box::pin(self.close_with(reader, self.forced())).await;
            }
            // Every whole frame already buffered is handled straight away;
            // the select below runs once per socket read, not per frame.
            // A resource alarm stops it at the next message: a publisher is
            // not read further, even from its buffer, until it clears.
            loop {
                if check_each_frame && told_to_close(&shutdown) {
                    return Box::pin(self.close_with(reader, self.forced())).await;
                }
                let input = match reader.buffered_publish() {
                    Some(publish) => Input::Publish(publish),
                    None => match reader.buffered_frame() {
                        Ok(Some(frame)) => Input::Frame(frame),
                        Ok(None) => break,
                        Err(e) => {
                            tracing::warn!(peer = %self.peer, error = %e, "malformed frame");
                            let (class_id, method_id) = e.method_ids();
                            let error =
                                AmqpError::new(e.reply_code(), &e).during_ids(class_id, method_id);
                            return Box::pin(self.close_with(reader, error)).await;
                        }
                    },
                };
                if !matches!(input, Input::Frame(Frame::Heartbeat)) {
                    last_busy = last_read;
                }
                // One unit of tokio's cooperative budget per frame (or whole
                // publish): without it a busy publisher's reader runs on
                // and on per socket read while the consumer writers it
                // wakes wait in this worker's LIFO slot (consumers fell far
                // behind). On a client thread's run of
                // an in-process loop, the claim's budget (`direct_loop`).
                direct_loop::consume_budget().await;
                // The messaging frames are handled at once, without a future
                // of their own (see `Channel::handle_at_once`); the others'
                // future is boxed, so that the connection's future holds no
                // room for it while it waits for the client (issue 32's idle
                // memory: about half of this loop's size).
                let at_once = match input {
                    Input::Frame(frame) => {
                        let channel_id = frame.channel();
                        match self.handle_at_once(frame) {
                            AtOnce::Handled(left) => Ok(left.map(|left| (channel_id, left))),
                            AtOnce::Declined(frame) => Err(Box::pin(self.handle(frame)).await),
                        }
                    }
                    Input::Publish(publish) => self.publish_at_once(publish).map_err(Err),
                };
                let handled = match at_once {
                    Ok(None) => Ok(Flow::Continue),
                    Ok(Some((channel_id, leftover))) => self.finish(channel_id, leftover).await,
                    Err(handled) => handled,
                };
                match handled {
                    Ok(Flow::Continue) => {}
                    Ok(Flow::Closed) => {
                        // The client initiated the close, so it closes the
                        // socket once it has our close-ok: wait for that.
                        let drain = async { while reader.next().await.is_ok() {} };
                        let _ = tokio::time::timeout(CLOSE_TIMEOUT, drain).await;
                        return Ok(());
                    }
                    Err(error) => return Box::pin(self.close_with(reader, error)).await,
                }
                // Frames already read finish the message they belong to
                // (its bytes are held either way); the block starts
                // between messages, or when the buffer runs out.
                let mut channels = self.channels.values();
                if self.must_block() && !channels.any(|c| c.is_receiving_content()) {
                    break;
                }
            }
            self.closed_this_batch.clear();
            self.flush_confirms().await;
            if self.must_block() {
                match self.block(reader, &mut shutdown).await {
                    // The client was not heard while blocked: its silence
                    // counts from now (RabbitMQ pauses its heartbeat
                    // monitor likewise).
                    Unblocked::Cleared => {
                        last_read = tokio::time::Instant::now();
                        self.outbox.heard(last_read);
                        continue;
                    }
                    Unblocked::PeerGone => return Err(Ended::PeerClosed),
                    Unblocked::Closing => {
                        return Box::pin(self.close_with(reader, self.forced())).await;
                    }
                }
            }
            self.wait_for_crowded_queues().await;
            // Not blocked, so no alarm was set when checked: a publisher
            // waits for one too, to be blocked (and told) at once.
            let publisher = self.channels.values().any(|c| c.has_published());
            let event = tokio::select! {
                read = reader.fill() => Event::Read(read),
                _ = alarms.changed(), if publisher => Event::Alarm,
                _ = shutdown.wait_for(|down| *down) => Event::Shutdown,
                _ = confirms_due(self.channels.values().map(|c| &**c)) => Event::ConfirmsDue,
                _ = &mut silence, if !silence_limit.is_zero() => Event::Silent,
                _ = &mut release, if reader.holds_spare() => Event::Idle,
            };
            match event {
                Event::Read(Ok(())) => {
                    last_read = tokio::time::Instant::now();
                    self.outbox.heard(last_read);
                }
                Event::Read(Err(e)) => return Err(e.into()),
                Event::ConfirmsDue | Event::Alarm => {}
                Event::Idle if last_busy.elapsed() < IDLE_RELEASE => {
                    release.as_mut().reset(last_busy + IDLE_RELEASE);
                }
                Event::Idle => reader.release_spare(),
                Event::Silent if last_read.elapsed() < silence_limit => {
                    silence.as_mut().reset(last_read + silence_limit);
                }
                Event::Silent => {
                    return Err(Ended::MissedHeartbeats(self.heartbeat));
                }
                Event::Shutdown => {
                    return Box::pin(self.close_with(reader, self.forced())).await;
                }
            }
        }
    }

    /// The close of a connection told to close, with the reason it was
    /// given (320 CONNECTION_FORCED).
    fn forced(&self) -> AmqpError {
        let reason = self.core.registry.close_reason(self.connection_id);
        AmqpError::new(ReplyCode::ConnectionForced, reason)
    }

    /// Flow control: before reading more, give crowded queues this
    /// connection published to time to drain. Bounded, so a connection
    /// that also consumes from such a queue (and must be read to get its
    /// acks) slows down instead of stalling.
    async fn wait_for_crowded_queues(&mut self) {
        let crowded: Vec<Arc<crate::queue::Queue>> = self
            .channels
            .values_mut()
            .filter_map(|c| c.take_crowded())
            .collect();
        for queue in crowded {
            let _ = tokio::time::timeout(FLOW_WAIT, queue.uncrowded()).await;
        }
    }

    /// Whether a resource alarm (memory or disk) is set and this
    /// connection publishes.
    fn must_block(&self) -> bool {
        self.core.gauge.in_alarm() && self.channels.values().any(|c| c.has_published())
    }

    /// Resource alarm: stop reading until it clears, telling the client if it
    /// asked to know. The client is not heard meanwhile (heartbeats
    /// included, as with RabbitMQ); the wait ends early when the
    /// connection is told to close (`closing`: the broker shutting down
    /// too) or the client goes away (its socket hung up, or the writer
    /// failed on it), so that what it held is released.
    async fn block<R: FrameSource>(
        &mut self,
        reader: &R,
        closing: &mut tokio::sync::watch::Receiver<bool>,
    ) -> Unblocked {
        if self.blocked_notify && !self.blocked {
            self.blocked = true;
            let reason = ShortStr::from_static(self.core.gauge.alarm_reason());
            self.outbox
                .method(0, leveret_protocol::ConnectionBlocked { reason })
                .await;
        }
        tracing::debug!(peer = %self.peer, "resource alarm: not reading from this publisher");
        // Publishes read before the block are still confirmed as they
        // reach the disk: only reading stops.
        let outcome = loop {
            tokio::select! {
                _ = self.core.gauge.wait_clear() => break Unblocked::Cleared,
                _ = closing.wait_for(|close| *close) => break Unblocked::Closing,
                _ = reader.hung_up() => break Unblocked::PeerGone,
                // The writer (or the in-process client's replies) holds
                // the outbox's receiver until it ends.
                _ = self.outbox.receiver_gone() => break Unblocked::PeerGone,
                _ = confirms_due(self.channels.values().map(|c| &**c)) => {}
            }
            self.flush_confirms().await;
        };
        if self.blocked && matches!(outcome, Unblocked::Cleared) {
            self.blocked = false;
            self.outbox
                .method(0, leveret_protocol::ConnectionUnblocked {})
                .await;
        }
        outcome
    }

    async fn flush_confirms(&mut self) {
        for channel in self.channels.values_mut() {
            channel.flush_confirms().await;
        }
    }

    async fn handle(&mut self, frame: Frame) -> AmqpResult<Flow> {
        let channel_id = frame.channel();
        match frame {
            Frame::Heartbeat => Ok(Flow::Continue),
            // Rare methods run in futures of their own on the heap, so the
            // future of every frame (created and moved per frame) stays the
            // size the common ones need.
            Frame::Method { channel: 0, method } => {
                Box::pin(self.handle_connection_method(method)).await
            }
            Frame::Header { channel: 0, .. } | Frame::Body { channel: 0, .. } => {
                Err(AmqpError::unexpected_frame("content frame on channel 0"))
            }
            Frame::Method {
                method: Method::ChannelOpen(_),
                ..
            } => {
                if self.channels.contains_key(&channel_id) {
                    return Err(AmqpError::channel_error(format_args!(
                        "second 'channel.open' seen on channel {channel_id}"
                    ))
                    .during_ids(20, 10));
                }
                // RabbitMQ's channel_max counts open channels (closing ones
                // included), whatever their numbers.
                if self.channels.len() >= usize::from(self.channel_max) {
                    tracing::warn!(peer = %self.peer, channel_max = self.channel_max, "channel limit reached");
                    return Err(AmqpError::not_allowed(format_args!(
                        "number of channels opened ({}) has reached the negotiated channel_max ({})",
                        self.channels.len(),
                        self.channel_max
                    ))
                    .during_ids(20, 10));
                }
                let Some(vhost) = self.vhost.clone() else {
                    return Err(AmqpError::command_invalid("connection not open"));
                };
                let max_channels = (self.core.limit_tables.user(&self.user))
                    .and_then(|limits| limits.max_channels);
                if let Err(admission::OverLimit(limit)) = self.slot.open_channel(max_channels) {
                    tracing::warn!(peer = %self.peer, user = %self.user, limit, "user channel limit reached");
                    return Err(AmqpError::not_allowed(format_args!(
                        "number of channels opened for user '{}' has reached the maximum allowed user limit of ({})",
                        self.user, limit
                    ))
                    .during_ids(20, 10));
                }
                let channel = Channel::new(
                    channel_id,
                    Arc::clone(&self.outbox),
                    vhost,
                    Arc::clone(&self.core),
                    self.user.clone(),
                    self.copy_below,
                );
                self.channels.insert(channel_id, Box::new(channel));
                self.closed_this_batch.remove(&channel_id);
                let open_ok = leveret_protocol::ChannelOpenOk {
                    channel_id: Bytes::new(),
                };
                Box::pin(self.outbox.method(channel_id, open_ok)).await;
                Ok(Flow::Continue)
            }
            frame => {
                let Some(channel) = self.channels.get_mut(&channel_id) else {
                    if self.closed_this_batch.contains(&channel_id) {
                        return Ok(Flow::Continue);
                    }
                    return Err(match &frame {
                        Frame::Method { method, .. } => AmqpError::channel_error(format_args!(
                            "expected 'channel.open' on channel {channel_id}"
                        ))
                        .during(method),
                        _ => AmqpError::unexpected_frame(format_args!(
                            "content frame on unopened channel {channel_id}"
                        )),
                    });
                };
                // A channel ends on the client's close (answered) or on its
                // close-ok to ours; only after the client's own close may
                // frames it sent meanwhile follow in this batch.
                let client_close = matches!(
                    &frame,
                    Frame::Method {
                        method: Method::ChannelClose(_),
                        ..
                    }
                );
                if channel.handle(frame).await? {
                    if let Some(channel) = self.channels.remove(&channel_id) {
                        channel.cleanup();
                        self.slot.close_channels(1);
                    }
                    if client_close {
                        self.closed_this_batch.insert(channel_id);
                    }
                }
                Ok(Flow::Continue)
            }
        }
    }

    /// A messaging frame on an open channel, handled at once; what is
    /// left is for [`Connection::finish`]. Any other frame is given back.
    fn handle_at_once(&mut self, frame: Frame) -> AtOnce {
        let channel = match frame.channel() {
            0 => None,
            id => self.channels.get_mut(&id),
        };
        match channel {
            Some(channel) => channel.handle_at_once(frame),
            None => AtOnce::Declined(frame),
        }
    }

    /// A publish received whole: its channel takes it as it would its
    /// three frames, at once.
    fn publish_at_once(&mut self, publish: WholePublish) -> AmqpResult<Option<(u16, Leftover)>> {
        let channel_id = publish.channel;
        let Some(channel) = self.channels.get_mut(&channel_id) else {
            if self.closed_this_batch.contains(&channel_id) {
                return Ok(None);
            }
            return Err(AmqpError::channel_error(format_args!(
                "expected 'channel.open' on channel {channel_id}"
            ))
            .during_ids(60, 40));
        };
        Ok(channel
            .publish_at_once(publish)
            .map(|leftover| (channel_id, leftover)))
    }

    /// Does what a channel left of a frame it handled at once.
    async fn finish(&mut self, channel_id: u16, leftover: Leftover) -> AmqpResult<Flow> {
        if let Some(channel) = self.channels.get_mut(&channel_id) {
            channel.finish(leftover).await?;
        }
        Ok(Flow::Continue)
    }

    async fn handle_connection_method(&mut self, method: Method) -> AmqpResult<Flow> {
        match method {
            Method::ConnectionClose(close) => {
                tracing::debug!(code = close.reply_code, text = %close.reply_text, "client closed the connection");
                self.cleanup();
                self.answer_close().await;
                Ok(Flow::Closed)
            }
            Method::ConnectionCloseOk(_) => Ok(Flow::Closed),
            Method::ConnectionUpdateSecret(_) => {
                self.outbox.method(0, ConnectionUpdateSecretOk {}).await;
                Ok(Flow::Continue)
            }
            Method::ConnectionBlocked(_) | Method::ConnectionUnblocked(_) => Ok(Flow::Continue),
            other => Err(AmqpError::channel_error(format_args!(
                "unexpected method {} on channel 0",
                other.name()
            ))
            .during(&other)),
        }
    }

    /// Sends connection.close for `error`, waits briefly for close-ok
    /// (discarding anything else, as the spec says; raw bytes once the
    /// stream cannot be parsed), then ends.
    async fn close_with<R: FrameSource>(
        &mut self,
        reader: &mut R,
        error: AmqpError,
    ) -> Result<(), Ended> {
        self.cleanup();
        let close = ConnectionClose {
            reply_code: error.code.code(),
            reply_text: error.reply_text(),
            class_id: error.class_id,
            method_id: error.method_id,
        };
        // Bounded: a client that stops reading leaves no room for it.
        let close = self.outbox.send_closing(Outbound::method(0, close.into()));
        let _ = tokio::time::timeout(CLOSE_TIMEOUT, close).await;
        let wait = async {
            loop {
                match reader.next().await {
                    Ok(Frame::Method {
                        method: Method::ConnectionCloseOk(_),
                        ..
                    }) => return,
                    // Both ends closing at once: the client's close is
                    // answered too (as RabbitMQ answers one it receives
                    // while closing).
                    Ok(Frame::Method {
                        method: Method::ConnectionClose(_),
                        ..
                    }) => return self.answer_close().await,
                    Ok(_) => continue,
                    Err(ReadError::Decode(_)) => return reader.discard_input().await,
                    Err(_) => return,
                }
            }
        };
        let _ = tokio::time::timeout(CLOSE_TIMEOUT, wait).await;
        if error.code == ReplyCode::ConnectionForced {
            return Err(Ended::Forced(error.text));
        }
        Err(Ended::Protocol(error))
    }

    /// Answers the client's connection.close with close-ok: the
    /// connection's own close, so it goes out even once the connection
    /// is told to close, bounded as our close is (a client that stops
    /// reading leaves no room for it).
    async fn answer_close(&self) {
        let close_ok = self
            .outbox
            .send_closing(Outbound::method(0, ConnectionCloseOk {}.into()));
        let _ = tokio::time::timeout(CLOSE_TIMEOUT, close_ok).await;
    }

    /// `peer -> local`, and ` - NAME` when the client named the
    /// connection, as RabbitMQ shows them.
    fn described(&self) -> String {
        match &self.client_name {
            Some(name) => format!("{} - {name}", self.label),
            None => self.label.clone(),
        }
    }

    fn vhost_name(&self) -> Option<String> {
        (self.vhost.as_ref()).map(|vhost| vhost.name.to_string_lossy().into_owned())
    }

    /// RabbitMQ's line for a connection whose handshake is done.
    fn log_open(&self) {
        let vhost = self.vhost_name().unwrap_or_default();
        tracing::info!(
            connection = self.connection_id,
            peer = %self.peer,
            user = %self.user,
            %vhost,
            client_name = self.client_name.as_deref(),
            "connection #{} ({}): user '{}' authenticated and granted access to vhost '{vhost}'",
            self.connection_id,
            self.described(),
            self.user,
        );
    }

    /// RabbitMQ's closing line (with the client-provided name, how long
    /// the connection lived and why it ended): info when the client or
    /// an administrator closed it, a warning otherwise.
    fn log_close(&self, outcome: &Result<(), Ended>, lived: Duration) {
        // A close text can quote what the client sent (its mechanism's name).
        let reason = match outcome {
            Ok(()) => "closed by the client".to_owned(),
            Err(ended) => loggable(ended.to_string().as_bytes()),
        };
        let vhost = self.vhost_name();
        let user = (!self.user.is_empty()).then_some(self.user.as_str());
        let quoted =
            |name: Option<&str>| name.map_or("none".to_owned(), |name| format!("'{name}'"));
        let text = format!(
            "closing {} connection #{} ({}, vhost: {}, user: {}, duration: {:.3}s): {reason}",
            self.kind,
            self.connection_id,
            self.described(),
            quoted(vhost.as_deref()),
            quoted(user),
            lived.as_secs_f64(),
        );
        macro_rules! log_close_at {
            ($level:ident) => {
                tracing::$level!(
                    connection = self.connection_id,
                    peer = %self.peer,
                    user,
                    vhost = vhost.as_deref(),
                    client_name = self.client_name.as_deref(),
                    duration_secs = lived.as_secs_f64(),
                    %reason,
                    "{text}"
                )
            };
        }
        match outcome {
            Ok(()) | Err(Ended::Forced(_)) => log_close_at!(info),
            Err(_) => log_close_at!(warn),
        }
    }

    /// Releases everything the connection holds: channels (requeueing
    /// their unacked messages) and exclusive queues.
    fn cleanup(&mut self) {
        let open = self.channels.len();
        for (_, channel) in self.channels.drain() {
            channel.cleanup();
        }
        self.slot.close_channels(open);
        if let Some(vhost) = &self.vhost {
            vhost.drop_exclusive(self.connection_id);
        }
        #[cfg(feature = "mqtt")]
        self.core.registry.cleaned_up(self.connection_id);
    }
}

/// Whether the connection was told to close since the loop last waited.
fn told_to_close(signal: &tokio::sync::watch::Receiver<bool>) -> bool {
    signal.has_changed().is_ok_and(|changed| changed) && *signal.borrow()
}

/// How a memory-alarm wait ended.
enum Unblocked {
    Cleared,
    /// Told to close, or the broker is shutting down.
    Closing,
    PeerGone,
}

/// What woke the reader loop.
enum Event {
    Read(Result<(), ReadError>),
    /// A channel has publisher confirms to send.
    ConfirmsDue,
    /// A resource alarm was set: block now if this connection publishes.
    Alarm,
    /// The read buffer is larger than needed: release it if idle.
    Idle,
    Silent,
    Shutdown,
}

/// Whether the reader goes on.
enum Flow {
    Continue,
    Closed,
}

#[cfg(test)]
mod tests {
    use super::*;

    /// What a client sends cannot start a log line of its own or make
    /// one unbounded.
    #[test]
    fn client_text_is_escaped_and_capped_for_the_log() {
        assert_eq!(
            loggable(b"evil\nINFO forged\r\x1b[31m"),
            "evil\\nINFO forged\\r\\u{1b}[31m"
        );
        assert_eq!(loggable("caf\u{e9}".as_bytes()), "caf\u{e9}");
        assert_eq!(loggable(b"\xff"), "\u{fffd}");
        assert_eq!(loggable(&[b'a'; 1000]).len(), LOGGED_TEXT_MAX);
    }
}
