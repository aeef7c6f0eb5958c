//! The connection: a transport (a TCP socket with TCP_NODELAY, optionally
//! TLS, see `transport`; or with the `embedded` feature a frame-value link
//! to a Leveret broker in this process, which nothing encodes or parses),
//! the `connection.*` handshake (PLAIN, tune negotiation, vhost open), then
//! two tasks that own the link's halves: the reader (`reader`), which
//! takes frames (`frames::FrameInput`) and routes them to channels, and the
//! writer (`writer`), which drains a bounded outbox into a
//! `frames::FrameOutput`. Everything after opening the transport is one
//! code path, generic over it, but for an in-process link's deliveries
//! taken on the broker's dispatching thread (`inline`). The
//! [`Connection`] handle and every channel share [`Shared`]: the outbox
//! sender, the channel table and the connection's state.

mod frames;
#[cfg(feature = "embedded")]
mod inline;
mod reader;
mod transport;
pub(crate) mod writer;

use crate::channel::{Channel, ChannelShared};
use crate::error::{CloseReason, Error, Result};
use crate::uri::{AuthMechanism, ConnectionOptions};
use bytes::Bytes;
use frames::{ByteInput, ByteOutput, FrameInput, FrameOutput};
use leveret_protocol::handoff;
use leveret_protocol::Outgoing;
use leveret_protocol::{
    ConnectionClose, ConnectionCloseOk, ConnectionOpen, ConnectionStartOk, ConnectionTuneOk,
    FieldTable, FieldValue, Frame, Method, ShortStr, FRAME_MIN_SIZE,
};
use std::collections::HashMap;
use std::sync::{Arc, Mutex, MutexGuard};
use std::time::Duration;
use tokio::sync::watch;
use transport::Transport;

/// How long [`Connection::close`] waits for room in the outbox.
const CLOSE_TIMEOUT: Duration = Duration::from_secs(5);

/// Largest frame accepted before tune settles frame_max.
const HANDSHAKE_FRAME_MAX: u32 = 131_072;

/// What was agreed in `connection.tune-ok`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Tuning {
    /// Highest channel number (0 would mean 65535; never 0 here).
    pub channel_max: u16,
    /// Largest frame, bytes (0 = no limit).
    pub frame_max: u32,
    /// Heartbeat interval, seconds (0 = none).
    pub heartbeat: u16,
}

/// Where the connection is in its life.
#[derive(Debug)]
pub(crate) enum ConnStatus {
    Open,
    /// connection.close sent (by the client, or by the reader after a
    /// protocol violation); waiting for close-ok.
    Closing,
    /// Done: every call fails with this error.
    Closed(Error),
}

#[derive(Debug)]
pub(crate) struct ConnState {
    pub(crate) status: ConnStatus,
    channels: HashMap<u16, Arc<ChannelShared>>,
    next_channel: u16,
}

/// State shared by the connection handle, its channels and its reader.
#[derive(Debug)]
pub(crate) struct Shared {
    /// The writer's bounded outbox.
    pub(crate) tx: handoff::Sender<Outgoing>,
    state: Mutex<ConnState>,
    /// True once a close has begun: the reader stops waiting on full
    /// consumer buffers and drops channel traffic.
    pub(crate) closing: watch::Sender<bool>,
    /// Set once, to why the connection ended.
    ended: watch::Sender<Option<Error>>,
    /// `Some(reason)` while the broker has blocked publishing.
    pub(crate) blocked: watch::Sender<Option<String>>,
    pub(crate) tuning: Tuning,
    server_properties: FieldTable,
    /// Deliveries taken on the broker's dispatching thread (in-process
    /// only; see `inline`).
    pub(crate) inline_deliveries: std::sync::atomic::AtomicU64,
    /// Publishes handled on the publishing thread (in-process only).
    pub(crate) inline_publishes: std::sync::atomic::AtomicU64,
    /// Publisher confirms an in-process connection settled on the thread
    /// where the broker settled them (see `inline`).
    pub(crate) inline_confirms: std::sync::atomic::AtomicU64,
    /// An in-process connection's loop, which a publish runs on its own
    /// thread when it is free (`leveret_broker::DirectLoop`).
    #[cfg(feature = "embedded")]
    pub(crate) here: Option<leveret_broker::DirectLoop>,
}

impl Shared {
    pub(crate) fn lock(&self) -> MutexGuard<'_, ConnState> {
        self.state.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// The error calls fail with once the connection is not open.
    pub(crate) fn error(&self) -> Error {
        match &self.lock().status {
            ConnStatus::Closed(error) => error.clone(),
            ConnStatus::Closing => Error::Closed,
            ConnStatus::Open => Error::io(std::io::Error::new(
                std::io::ErrorKind::BrokenPipe,
                "the connection's writer has stopped",
            )),
        }
    }

    /// Waits for room in the outbox.
    pub(crate) async fn reserve(&self) -> Result<handoff::Permit<'_, Outgoing>> {
        self.tx.reserve().await.map_err(|_| self.error())
    }

    /// Sends an item from a `Drop`: without waiting if there is room,
    /// otherwise from a task, if there is a runtime.
    pub(crate) fn send_from_drop(self: &Arc<Self>, item: Outgoing) {
        match self.tx.try_send(item) {
            Ok(()) | Err(handoff::TrySendError::Closed(_)) => {}
            Err(handoff::TrySendError::Full(item)) => {
                if let Ok(runtime) = tokio::runtime::Handle::try_current() {
                    let tx = self.tx.clone();
                    runtime.spawn(async move {
                        let _ = tx.send(item).await;
                    });
                }
            }
        }
    }

    pub(crate) fn channel(&self, id: u16) -> Option<Arc<ChannelShared>> {
        self.lock().channels.get(&id).cloned()
    }

    /// Forgets a channel, if `id` still names this one.
    pub(crate) fn remove_channel(&self, channel: &Arc<ChannelShared>) {
        let mut state = self.lock();
        if let Some(current) = state.channels.get(&channel.id) {
            if Arc::ptr_eq(current, channel) {
                state.channels.remove(&channel.id);
            }
        }
    }

    /// Picks a free channel number and registers a channel under it.
    fn allocate_channel(&self) -> Result<Arc<ChannelShared>> {
        let mut state = self.lock();
        match &state.status {
            ConnStatus::Open => {}
            ConnStatus::Closing => return Err(Error::Closed),
            ConnStatus::Closed(error) => return Err(error.clone()),
        }
        let max = self.tuning.channel_max;
        let start = state.next_channel.clamp(1, max);
        let mut id = start;
        loop {
            if !state.channels.contains_key(&id) {
                break;
            }
            id = if id >= max { 1 } else { id + 1 };
            if id == start {
                return Err(Error::ChannelsExhausted(max));
            }
        }
        state.next_channel = if id >= max { 1 } else { id + 1 };
        let channel = Arc::new(ChannelShared::new(id));
        state.channels.insert(id, Arc::clone(&channel));
        Ok(channel)
    }

    /// Starts closing the connection with `close` unless it is already
    /// closing; `send` puts the method in the outbox (under the lock, so
    /// nothing a channel sends afterwards can overtake it).
    pub(crate) fn begin_close(&self, send: impl FnOnce(Outgoing)) -> bool {
        let mut state = self.lock();
        if !matches!(state.status, ConnStatus::Open) {
            return false;
        }
        state.status = ConnStatus::Closing;
        send(Outgoing::Method {
            channel: 0,
            method: ConnectionClose {
                reply_code: 200,
                reply_text: ShortStr::from_static("Goodbye"),
                class_id: 0,
                method_id: 0,
            }
            .into(),
        });
        drop(state);
        self.closing.send_replace(true);
        true
    }

    /// Marks the connection ended, failing every channel with `error`.
    pub(crate) fn finish(&self, error: Error) {
        let channels: Vec<_> = {
            let mut state = self.lock();
            if let ConnStatus::Closed(_) = state.status {
                return;
            }
            state.status = ConnStatus::Closed(error.clone());
            state.channels.drain().map(|(_, c)| c).collect()
        };
        self.closing.send_replace(true);
        for channel in channels {
            channel.finish(error.clone());
        }
        self.ended.send_replace(Some(error));
    }

    /// Marks the connection closing without sending connection.close (a
    /// protocol violation of the broker's, or an outbox that does not
    /// drain); true if it was open.
    pub(crate) fn mark_closing(&self) -> bool {
        let mut state = self.lock();
        if !matches!(state.status, ConnStatus::Open) {
            return false;
        }
        state.status = ConnStatus::Closing;
        drop(state);
        self.closing.send_replace(true);
        true
    }
}

/// What the handle holds; closing the connection when the last handle (of
/// the connection or any of its channels) is dropped.
#[derive(Debug)]
pub(crate) struct ConnectionInner {
    pub(crate) shared: Arc<Shared>,
}

impl Drop for ConnectionInner {
    fn drop(&mut self) {
        let shared = Arc::clone(&self.shared);
        self.shared
            .begin_close(|close| shared.send_from_drop(close));
    }
}

/// An open AMQP connection. Cloning gives another handle on the same
/// connection; it is closed with [`Connection::close`], or when every
/// handle and every channel has been dropped.
#[derive(Debug, Clone)]
pub struct Connection {
    inner: Arc<ConnectionInner>,
}

impl Connection {
    /// Connects with an `amqp://` URI (see [`ConnectionOptions::from_uri`]).
    pub async fn connect(uri: &str) -> Result<Connection> {
        Connection::connect_with(ConnectionOptions::from_uri(uri)?).await
    }

    /// Connects with explicit options.
    pub async fn connect_with(options: ConnectionOptions) -> Result<Connection> {
        let connect = async {
            let stream = transport::tcp(&options).await?;
            match &options.tls {
                #[cfg(feature = "tls")]
                Some(settings) => {
                    let stream = transport::tls(stream, &options.host, settings).await?;
                    establish(stream, &options).await
                }
                #[cfg(not(feature = "tls"))]
                Some(_) => Err(Error::Tls("built without the `tls` feature".into())),
                None => establish(stream, &options).await,
            }
        };
        match tokio::time::timeout(options.connection_timeout, connect).await {
            Ok(result) => result,
            Err(_) => Err(Error::ConnectTimeout),
        }
    }

    /// Connects to a broker embedded in this process (user `guest`,
    /// password `guest`, vhost `/`): the same protocol, handshake and API
    /// as over TCP, with frames handed over as values (no network, nothing
    /// encoded or parsed, no heartbeats).
    #[cfg(feature = "embedded")]
    pub async fn in_process(broker: &Arc<leveret_broker::BrokerHandle>) -> Result<Connection> {
        Connection::in_process_with(broker, ConnectionOptions::default()).await
    }

    /// [`Connection::in_process`] with explicit options (`host` and `port`
    /// are not used; credentials, vhost, tuning and timeout are).
    #[cfg(feature = "embedded")]
    pub async fn in_process_with(
        broker: &Arc<leveret_broker::BrokerHandle>,
        options: ConnectionOptions,
    ) -> Result<Connection> {
        let link = broker.connect_direct();
        let input = frames::DirectInput::new(link.from_broker);
        let output = frames::DirectOutput::new(link.to_broker, link.here);
        let establish = establish_frames(input, output, &options);
        match tokio::time::timeout(options.connection_timeout, establish).await {
            Ok(result) => result,
            Err(_) => Err(Error::ConnectTimeout),
        }
    }

    /// Opens a new channel.
    pub async fn open_channel(&self) -> Result<Channel> {
        let channel = self.inner.shared.allocate_channel()?;
        Channel::open(Arc::clone(&self.inner), channel).await
    }

    /// Closes the connection (reply code 200) and waits for the broker's
    /// `connection.close-ok`. Calls still waiting fail with [`Error::Closed`].
    /// If the broker had already closed it, that error is returned.
    pub async fn close(&self) -> Result<()> {
        let shared = &self.inner.shared;
        match tokio::time::timeout(CLOSE_TIMEOUT, shared.reserve()).await {
            Ok(Ok(permit)) => {
                shared.begin_close(|close| permit.send(close));
            }
            Ok(Err(_)) => {}
            // The outbox does not drain (a broker that stopped reading):
            // give up on a clean close; the reader ends the connection
            // once its close deadline passes.
            Err(_) => {
                shared.mark_closing();
            }
        }
        match self.closed().await {
            Error::Closed => Ok(()),
            error => Err(error),
        }
    }

    /// Resolves once the connection has ended, with why: [`Error::Closed`]
    /// after [`Connection::close`], or the broker's close, a socket error,
    /// missed heartbeats.
    pub async fn closed(&self) -> Error {
        let mut ended = self.inner.shared.ended.subscribe();
        let result = match ended.wait_for(Option::is_some).await {
            Ok(error) => error.clone().unwrap_or(Error::Closed),
            Err(_) => Error::Closed,
        };
        result
    }

    /// Whether the connection is open (not closing or closed).
    pub fn is_open(&self) -> bool {
        matches!(self.inner.shared.lock().status, ConnStatus::Open)
    }

    /// The broker's `connection.blocked` state: `Some(reason)` from
    /// `connection.blocked` until `connection.unblocked`. Publishing while
    /// blocked is accepted but the broker stops reading the socket.
    pub fn blocked(&self) -> watch::Receiver<Option<String>> {
        self.inner.shared.blocked.subscribe()
    }

    /// The negotiated limits.
    pub fn tuning(&self) -> Tuning {
        self.inner.shared.tuning
    }

    /// The broker's `connection.start` properties (product, version,
    /// capabilities…).
    pub fn server_properties(&self) -> &FieldTable {
        &self.inner.shared.server_properties
    }

    /// How many deliveries an in-process connection's consumers took on
    /// the thread that dispatched them, with no task in between (the
    /// in-process fast path; the others came through the connection's
    /// reader). Always 0 over TCP.
    pub fn inline_deliveries(&self) -> u64 {
        self.inner
            .shared
            .inline_deliveries
            .load(std::sync::atomic::Ordering::Relaxed)
    }

    /// How many of an in-process connection's publishes the broker's
    /// connection took on the publishing thread, with no task in between
    /// (the in-process fast path; the others went through the link to the
    /// connection's task). Always 0 over TCP.
    pub fn inline_publishes(&self) -> u64 {
        self.inner
            .shared
            .inline_publishes
            .load(std::sync::atomic::Ordering::Relaxed)
    }

    /// How many publisher confirms (`basic.ack`/`basic.nack` messages) an
    /// in-process connection settled on the thread where the broker
    /// settled them, with no task in between: for a publish the broker
    /// handled on the publishing thread, before `basic_publish` returned
    /// (the others came through the connection's reader). Always 0 over
    /// TCP.
    pub fn inline_confirms(&self) -> u64 {
        self.inner
            .shared
            .inline_confirms
            .load(std::sync::atomic::Ordering::Relaxed)
    }
}

/// Takes the smaller of two limits, where 0 means "no preference".
fn negotiate<T: Copy + Ord + Default>(client: T, server: T) -> T {
    let zero = T::default();
    if client == zero {
        server
    } else if server == zero {
        client
    } else {
        client.min(server)
    }
}

fn client_properties(options: &ConnectionOptions) -> FieldTable {
    let text = |s: &str| FieldValue::string(s);
    let capabilities: FieldTable = [
        "publisher_confirms",
        "consumer_cancel_notify",
        "connection.blocked",
        "basic.nack",
        "exchange_exchange_bindings",
        "authentication_failure_close",
        "per_consumer_qos",
    ]
    .into_iter()
    .filter_map(|name| Some((ShortStr::try_from(name).ok()?, FieldValue::Bool(true))))
    .collect();
    let mut properties: FieldTable = [
        (ShortStr::from_static("product"), text("leveret-client")),
        (
            ShortStr::from_static("version"),
            text(env!("CARGO_PKG_VERSION")),
        ),
        (ShortStr::from_static("platform"), text("Rust")),
        (
            ShortStr::from_static("information"),
            text("A thin AMQP 0.9.1 client (Leveret)"),
        ),
        (
            ShortStr::from_static("capabilities"),
            FieldValue::Table(capabilities),
        ),
    ]
    .into_iter()
    .collect();
    if let Some(name) = &options.connection_name {
        properties.insert(ShortStr::from_static("connection_name"), text(name));
    }
    properties
}

/// The handshake's view of the connection: whole frames in, methods out.
struct Handshake<I, O> {
    input: I,
    output: O,
}

impl<I: FrameInput, O: FrameOutput> Handshake<I, O> {
    async fn next_method(&mut self) -> Result<Method> {
        loop {
            match self.input.buffered(HANDSHAKE_FRAME_MAX) {
                Ok(Some(Frame::Method { channel: 0, method })) => return Ok(method),
                Ok(Some(Frame::Heartbeat)) => continue,
                Ok(Some(other)) => {
                    return Err(Error::Protocol(format!(
                        "expected a connection method during the handshake, got {other:?}"
                    )))
                }
                Ok(None) => {}
                Err(e) => {
                    if self.input.other_protocol() {
                        return Err(Error::Protocol(
                            "the broker does not speak AMQP 0.9.1".to_owned(),
                        ));
                    }
                    return Err(Error::Protocol(e.to_string()));
                }
            }
            if !self.input.receive().await? {
                return Err(Error::io(std::io::Error::new(
                    std::io::ErrorKind::UnexpectedEof,
                    "the broker closed the connection during the handshake",
                )));
            }
        }
    }

    fn queue(&mut self, method: impl Into<Method>) {
        self.output.queue(method.into());
    }

    async fn flush(&mut self) -> Result<()> {
        Ok(self.output.flush().await?)
    }

    /// Answers a `connection.close` received during the handshake.
    async fn closed_by_broker(&mut self, close: ConnectionClose) -> Error {
        self.queue(ConnectionCloseOk {});
        let _ = self.flush().await;
        Error::ConnectionClosed(reason(
            &close.reply_text,
            close.reply_code,
            close.class_id,
            close.method_id,
        ))
    }
}

fn unexpected(method: &Method, expected: &str) -> Error {
    Error::Protocol(format!(
        "expected {expected} during the handshake, got {}",
        method.name()
    ))
}

pub(crate) fn reason(text: &ShortStr, code: u16, class_id: u16, method_id: u16) -> CloseReason {
    CloseReason {
        code,
        text: text.to_string_lossy().into_owned(),
        class_id,
        method_id,
    }
}

/// Runs the handshake over an open byte stream, then starts the reader and
/// writer on its halves.
async fn establish<S: Transport>(stream: S, options: &ConnectionOptions) -> Result<Connection> {
    let (read, write) = stream.into_halves();
    establish_frames(ByteInput::new(read), ByteOutput::new(write), options).await
}

/// Runs the handshake, then starts the reader and the writer.
async fn establish_frames<I: FrameInput, O: FrameOutput>(
    input: I,
    output: O,
    options: &ConnectionOptions,
) -> Result<Connection> {
    let mut hs = Handshake { input, output };
    hs.output.begin().await?;
    let start = match hs.next_method().await? {
        Method::ConnectionStart(start) => start,
        other => return Err(unexpected(&other, "connection.start")),
    };
    let mechanism = match options.auth_mechanism {
        AuthMechanism::Plain => "PLAIN",
        AuthMechanism::External => "EXTERNAL",
    };
    if !start
        .mechanisms
        .split(|b| *b == b' ')
        .any(|m| m == mechanism.as_bytes())
    {
        return Err(Error::Protocol(format!(
            "the broker does not offer {mechanism} authentication (mechanisms: {})",
            String::from_utf8_lossy(&start.mechanisms)
        )));
    }
    // EXTERNAL's response is empty: the identity is the transport's.
    let mut response = Vec::new();
    if options.auth_mechanism == AuthMechanism::Plain {
        response.push(0);
        response.extend_from_slice(options.username.as_bytes());
        response.push(0);
        response.extend_from_slice(options.password.as_bytes());
    }
    hs.queue(ConnectionStartOk {
        client_properties: client_properties(options),
        mechanism: ShortStr::from_static(mechanism),
        response: Bytes::from(response),
        locale: ShortStr::from_static("en_US"),
    });
    hs.flush().await?;
    let tune = match hs.next_method().await? {
        Method::ConnectionTune(tune) => tune,
        Method::ConnectionClose(close) => return Err(hs.closed_by_broker(close).await),
        other => return Err(unexpected(&other, "connection.tune")),
    };
    let channel_max = match negotiate(options.channel_max, tune.channel_max) {
        0 => u16::MAX,
        n => n,
    };
    let frame_max = match negotiate(options.frame_max, tune.frame_max) {
        0 => 0,
        n => n.max(FRAME_MIN_SIZE),
    };
    // An in-process link ends when either side drops it: no heartbeats.
    let heartbeat = match hs.output.needs_heartbeats() {
        true => negotiate(options.heartbeat, tune.heartbeat),
        false => 0,
    };
    hs.queue(ConnectionTuneOk {
        channel_max,
        frame_max,
        heartbeat,
    });
    hs.queue(ConnectionOpen {
        virtual_host: ShortStr::try_from(options.vhost.as_str())?,
        capabilities: ShortStr::default(),
        insist: false,
    });
    hs.flush().await?;
    let server_properties = start.server_properties;
    match hs.next_method().await? {
        Method::ConnectionOpenOk(_) => {}
        Method::ConnectionClose(close) => return Err(hs.closed_by_broker(close).await),
        other => return Err(unexpected(&other, "connection.open-ok")),
    }

    let tuning = Tuning {
        channel_max,
        frame_max,
        heartbeat,
    };
    let Handshake { mut input, output } = hs;
    let interval = Duration::from_secs(heartbeat.into());
    let outbox = output.into_outbox(frame_max, interval);
    let shared = Arc::new(Shared {
        tx: outbox.tx,
        state: Mutex::new(ConnState {
            status: ConnStatus::Open,
            channels: HashMap::new(),
            next_channel: 1,
        }),
        closing: watch::Sender::new(false),
        ended: watch::Sender::new(None),
        blocked: watch::Sender::new(None),
        tuning,
        server_properties,
        inline_deliveries: std::sync::atomic::AtomicU64::new(0),
        inline_publishes: std::sync::atomic::AtomicU64::new(0),
        inline_confirms: std::sync::atomic::AtomicU64::new(0),
        #[cfg(feature = "embedded")]
        here: outbox.here,
    });
    input.attach(&shared);
    tokio::spawn(reader::run(
        Arc::clone(&shared),
        input,
        interval,
        outbox.writer,
    ));
    Ok(Connection {
        inner: Arc::new(ConnectionInner { shared }),
    })
}

#[cfg(test)]
mod tests {
    use super::negotiate;

    #[test]
    fn negotiation_takes_the_smaller_non_zero() {
        assert_eq!(negotiate(60u16, 30), 30);
        assert_eq!(negotiate(10u16, 30), 10);
        assert_eq!(negotiate(0u16, 30), 30);
        assert_eq!(negotiate(10u16, 0), 10);
        assert_eq!(negotiate(0u32, 0), 0);
    }
}
