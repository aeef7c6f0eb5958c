//! Helpers shared by the client's integration tests (each test file has
//! `mod common;`).
//!
//! [`broker`] gives every test its broker: the one at
//! `LEVERET_TEST_AMQP_URL` if set (e.g. a local RabbitMQ), otherwise an
//! in-process Leveret on 127.0.0.1:0. [`ScriptedPeer`] is a fake broker
//! driven step by step, for what a real broker cannot be made to do on
//! demand (go silent, send `connection.blocked`). Every wait goes through
//! [`within`], so a hang fails the test instead of stalling it.
#![allow(dead_code)]

use bytes::{Bytes, BytesMut};
use leveret_broker::{Broker, BrokerHandle};
use leveret_client::protocol::{
    decode_frame, encode_method, ConnectionOpenOk, ConnectionStart, ConnectionTune, Frame, Method,
    PROTOCOL_HEADER,
};
use leveret_client::{Channel, Connection, FieldTable, QueueDeclareOptions, QueueInfo};
use std::future::IntoFuture;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::Duration;
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::{TcpListener, TcpStream};

/// Polls `future` once, with a waker that does nothing: its output if it
/// finished without waiting for anything (the broker, room, a timer). A
/// proof that an operation never waited which no scheduler can upset, as
/// a stopwatch can.
pub fn without_waiting<F: std::future::Future>(future: F) -> Option<F::Output> {
    let mut future = std::pin::pin!(future);
    let mut context = std::task::Context::from_waker(std::task::Waker::noop());
    match future.as_mut().poll(&mut context) {
        std::task::Poll::Ready(output) => Some(output),
        std::task::Poll::Pending => None,
    }
}

/// How long any single expected event may take.
pub const TIMEOUT: Duration = Duration::from_secs(10);

/// Awaits `fut` for at most [`TIMEOUT`].
pub async fn within<T>(what: &str, fut: impl IntoFuture<Output = T>) -> T {
    match tokio::time::timeout(TIMEOUT, fut).await {
        Ok(v) => v,
        Err(_) => panic!("timed out after {TIMEOUT:?} waiting for {what}"),
    }
}

/// The broker a test talks to; an in-process one stops when this drops.
pub struct TestBroker {
    /// Its `amqp://` URI.
    pub uri: String,
    handle: Option<BrokerHandle>,
}

impl TestBroker {
    /// A connection to it, within [`TIMEOUT`].
    pub async fn connect(&self) -> Connection {
        within("connect", Connection::connect(&self.uri))
            .await
            .unwrap_or_else(|e| panic!("connecting to {}: {e}", self.uri))
    }

    /// A connection and one channel.
    pub async fn channel(&self) -> (Connection, Channel) {
        let connection = self.connect().await;
        let channel = within("open channel", connection.open_channel())
            .await
            .expect("open channel");
        (connection, channel)
    }

    /// The URI with a query appended (`heartbeat=1`…).
    pub fn uri_with(&self, query: &str) -> String {
        let separator = if self.uri.contains('?') { '&' } else { '?' };
        format!("{}{separator}{query}", self.uri)
    }

    /// Whether this is an external broker (LEVERET_TEST_AMQP_URL).
    pub fn is_external(&self) -> bool {
        self.handle.is_none()
    }
}

/// The broker for one test.
pub async fn broker() -> TestBroker {
    if let Ok(uri) = std::env::var("LEVERET_TEST_AMQP_URL") {
        if !uri.is_empty() {
            return TestBroker { uri, handle: None };
        }
    }
    let handle = Broker::builder()
        .listen("127.0.0.1:0".parse().expect("address"))
        .start()
        .await
        .expect("start an in-process Leveret");
    let addr = handle.local_addrs()[0];
    TestBroker {
        uri: format!("amqp://guest:guest@{addr}/%2f"),
        handle: Some(handle),
    }
}

/// An in-process Leveret with `limits`, or `None` when the tests run
/// against an external broker (whose limits cannot be set from here).
pub async fn leveret_with(limits: leveret_broker::Limits) -> Option<TestBroker> {
    if std::env::var("LEVERET_TEST_AMQP_URL").is_ok_and(|uri| !uri.is_empty()) {
        return None;
    }
    let handle = Broker::builder()
        .listen("127.0.0.1:0".parse().expect("address"))
        .limits(limits)
        .start()
        .await
        .expect("start an in-process Leveret");
    let addr = handle.local_addrs()[0];
    Some(TestBroker {
        uri: format!("amqp://guest:guest@{addr}/%2f"),
        handle: Some(handle),
    })
}

/// A name no other test (or earlier run against the same broker) uses.
pub fn unique(prefix: &str) -> String {
    static COUNTER: AtomicU64 = AtomicU64::new(0);
    let nanos = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map(|d| d.as_nanos())
        .unwrap_or(0);
    format!(
        "leveret-client-test.{prefix}.{}.{}.{}",
        std::process::id(),
        nanos % 1_000_000_000_000,
        COUNTER.fetch_add(1, Ordering::Relaxed)
    )
}

/// Declares a fresh auto-delete queue (gone when its connection is, on
/// any broker; exclusive would stop a second connection using it).
pub async fn temp_queue(channel: &Channel, prefix: &str) -> QueueInfo {
    let options = QueueDeclareOptions {
        auto_delete: false,
        exclusive: false,
        ..Default::default()
    };
    let mut arguments = FieldTable::new();
    // Expire unused queues, so a failed run leaves nothing behind.
    arguments.insert(
        leveret_client::ShortStr::from_static("x-expires"),
        leveret_client::FieldValue::I32(60_000),
    );
    within(
        "queue.declare",
        channel.queue_declare(unique(prefix).as_str(), options, arguments),
    )
    .await
    .expect("queue.declare")
}

/// A fake broker for one connection, driven step by step by the test.
pub struct ScriptedPeer {
    listener: TcpListener,
}

/// The accepted connection of a [`ScriptedPeer`].
pub struct PeerConnection {
    socket: TcpStream,
    buf: BytesMut,
}

impl ScriptedPeer {
    pub async fn bind() -> ScriptedPeer {
        let listener = TcpListener::bind("127.0.0.1:0").await.expect("bind");
        ScriptedPeer { listener }
    }

    pub fn uri(&self, query: &str) -> String {
        let addr = self.listener.local_addr().expect("local addr");
        format!("amqp://guest:guest@{addr}/?{query}")
    }

    /// Connects a client with `query` and runs the handshake, offering
    /// `heartbeat`.
    pub async fn connect(&self, query: &str, heartbeat: u16) -> (Connection, PeerConnection) {
        let uri = self.uri(query);
        let connecting = tokio::spawn(async move { Connection::connect(&uri).await });
        let server = self.accept(heartbeat).await;
        let connection = within("connect", connecting)
            .await
            .expect("join")
            .expect("connect");
        (connection, server)
    }

    /// Accepts the client and runs the handshake, offering `heartbeat`.
    pub async fn accept(&self, heartbeat: u16) -> PeerConnection {
        let (socket, _) = within("accept", self.listener.accept())
            .await
            .expect("accept");
        let mut peer = PeerConnection {
            socket,
            buf: BytesMut::new(),
        };
        let mut header = [0u8; 8];
        within("protocol header", peer.socket.read_exact(&mut header))
            .await
            .expect("protocol header");
        assert_eq!(&header, PROTOCOL_HEADER);
        peer.send(
            0,
            ConnectionStart {
                version_major: 0,
                version_minor: 9,
                server_properties: FieldTable::new(),
                mechanisms: Bytes::from_static(b"PLAIN"),
                locales: Bytes::from_static(b"en_US"),
            },
        )
        .await;
        assert!(matches!(peer.method().await, Method::ConnectionStartOk(_)));
        peer.send(
            0,
            ConnectionTune {
                channel_max: 16,
                frame_max: 4096,
                heartbeat,
            },
        )
        .await;
        assert!(matches!(peer.method().await, Method::ConnectionTuneOk(_)));
        assert!(matches!(peer.method().await, Method::ConnectionOpen(_)));
        peer.send(0, ConnectionOpenOk::default()).await;
        peer
    }
}

impl PeerConnection {
    pub async fn send(&mut self, channel: u16, method: impl Into<Method>) {
        let mut out = BytesMut::new();
        encode_method(channel, &method.into(), &mut out);
        self.socket.write_all(&out).await.expect("peer write");
    }

    pub async fn send_raw(&mut self, bytes: &[u8]) {
        self.socket.write_all(bytes).await.expect("peer write");
    }

    pub async fn send_heartbeat(&mut self) {
        let mut out = BytesMut::new();
        Frame::Heartbeat.encode(&mut out);
        self.socket.write_all(&out).await.expect("peer write");
    }

    /// The next frame from the client; `None` once it closed the socket.
    pub async fn frame(&mut self) -> Option<Frame> {
        loop {
            if let Some(frame) = decode_frame(&mut self.buf, 0).expect("client frame") {
                return Some(frame);
            }
            let n = within("client bytes", self.socket.read_buf(&mut self.buf))
                .await
                .ok()?;
            if n == 0 {
                return None;
            }
        }
    }

    /// The next method from the client, skipping heartbeats.
    pub async fn method(&mut self) -> Method {
        loop {
            match self.frame().await.expect("client closed the socket") {
                Frame::Heartbeat => continue,
                Frame::Method { method, .. } => return method,
                other => panic!("expected a method, got {other:?}"),
            }
        }
    }
}
