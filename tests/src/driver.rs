//! A scripted adversarial peer for an in-process broker, shared by the
//! broker-level cargo-fuzz target (`fuzz/fuzz_targets/broker.rs`) and the
//! corpus replay test (`tests/tests/fuzz_corpus.rs`).
//!
//! A [`Script`] is a list of [`Step`]s that several connections and channels
//! send to one broker: every AMQP method a client may send, with names,
//! arguments and properties drawn from small menus chosen to meet each other
//! (queues that dead-letter into exchanges bound back to them, topic
//! patterns full of `#`, headers bindings, TTLs of zero, tiny length
//! limits), content frames that lie about their sizes, and raw garbage.
//! [`run`] plays it and then checks what a peer may never do to the broker:
//!
//! - crash it: a panic anywhere aborts the fuzzer (libFuzzer's panic hook),
//!   and in the replay test fails the test;
//! - freeze it: every connection still open answers a `channel.open`
//!   (except those that were sent raw bytes, which may have begun a frame
//!   the broker is rightly waiting to finish), and a fresh connection completes a handshake and a `queue.declare`, each
//!   within [`ANSWER_WITHIN`];
//! - exhaust it: scripts are bounded ([`MAX_STEPS`], body sizes), so memory
//!   growth shows up as libFuzzer's RSS limit.
//!
//! It uses only the broker's public embedding API and the protocol codec.

use std::collections::HashSet;
use std::sync::{Arc, Mutex};
use std::time::Duration;

use arbitrary::Arbitrary;
use bytes::{Bytes, BytesMut};
use leveret_broker::{Broker, BrokerHandle};
use leveret_protocol::*;
use tokio::io::{AsyncReadExt, AsyncWriteExt, DuplexStream, ReadHalf, WriteHalf};
use tokio::sync::Notify;

/// Steps a script plays at most (the rest are ignored).
pub const MAX_STEPS: usize = 96;
/// Connections a script uses at once.
const CONNECTIONS: usize = 3;
/// How long the broker may take to answer the liveness probes: a hang
/// limit, generous enough for a debug build on a loaded machine (the
/// corpus replays in CI beside other tests).
pub const ANSWER_WITHIN: Duration = Duration::from_secs(30);
/// How long one write may wait for the broker to read, unless the broker
/// said it blocked the connection.
const WRITE_WITHIN: Duration = Duration::from_secs(30);
/// The frame size the driver offers; the broker's is larger.
const FRAME_MAX: u32 = 4096;

/// One fuzz input: the runtime to use and what to send.
#[derive(Arbitrary, Debug, Clone)]
pub struct Script {
    /// Run on a multi-thread runtime (2 workers) instead of a current-thread one.
    pub multi_thread: bool,
    /// What the peers send, in order.
    pub steps: Vec<Step>,
}

/// One thing a peer does.
#[derive(Arbitrary, Debug, Clone)]
pub enum Step {
    /// A method (and its content) on a connection's channel (1 to 4).
    Send {
        /// Which connection.
        connection: u8,
        /// Which channel.
        channel: u8,
        /// What to send.
        op: Op,
    },
    /// Bytes written as they are.
    Raw {
        /// Which connection.
        connection: u8,
        /// The bytes (at most 512 are sent).
        bytes: Vec<u8>,
    },
    /// Lets the broker run for a millisecond (TTLs and the sweeper).
    Pause,
    /// Drops the connection without closing it, and opens a new one.
    Reconnect {
        /// Which connection.
        connection: u8,
    },
}

/// The names scripts use; few, so that operations meet each other.
#[derive(Arbitrary, Debug, Clone, Copy)]
pub enum Name {
    /// `""`: the default exchange, or a server-named queue.
    Empty,
    /// `q0`.
    Q0,
    /// `q1`.
    Q1,
    /// `e0`.
    E0,
    /// `e1`.
    E1,
    /// `amq.direct`.
    AmqDirect,
    /// `amq.topic`.
    AmqTopic,
    /// `amq.headers`.
    AmqHeaders,
    /// `amq.fanout`.
    AmqFanout,
    /// `amq.rabbitmq.reply-to`.
    ReplyTo,
    /// A name of 255 characters.
    Long,
}

impl Name {
    fn short(self) -> ShortStr {
        let name = match self {
            Name::Empty => "",
            Name::Q0 => "q0",
            Name::Q1 => "q1",
            Name::E0 => "e0",
            Name::E1 => "e1",
            Name::AmqDirect => "amq.direct",
            Name::AmqTopic => "amq.topic",
            Name::AmqHeaders => "amq.headers",
            Name::AmqFanout => "amq.fanout",
            Name::ReplyTo => "amq.rabbitmq.reply-to",
            Name::Long => return ShortStr::try_from("x".repeat(255)).unwrap_or_default(),
        };
        ShortStr::from_static(name)
    }
}

/// Routing and binding keys.
#[derive(Arbitrary, Debug, Clone)]
pub enum Key {
    /// A name from the menu (so the default exchange reaches queues).
    Name(Name),
    /// Words from a small alphabet joined by dots (`a`, `b`, `*`, `#`, ``).
    Words(Vec<u8>),
    /// Many `#` segments.
    Hashes(u8),
}

impl Key {
    fn short(&self) -> ShortStr {
        match self {
            Key::Name(name) => name.short(),
            Key::Words(words) => {
                let words: Vec<&str> = words
                    .iter()
                    .take(120)
                    .map(|w| ["a", "b", "*", "#", ""][usize::from(*w) % 5])
                    .collect();
                ShortStr::try_from(words.join(".")).unwrap_or_default()
            }
            Key::Hashes(n) => ShortStr::try_from(vec!["#"; usize::from(*n % 64) + 1].join("."))
                .unwrap_or_default(),
        }
    }
}

/// One argument of a declare or bind, from RabbitMQ's menu.
#[derive(Arbitrary, Debug, Clone)]
pub enum Argument {
    /// `x-max-length`.
    MaxLength(i8),
    /// `x-max-length-bytes`.
    MaxLengthBytes(i16),
    /// `x-overflow`: drop-head, reject-publish, reject-publish-dlx or junk.
    Overflow(u8),
    /// `x-dead-letter-exchange`.
    DeadLetterExchange(Name),
    /// `x-dead-letter-routing-key`.
    DeadLetterRoutingKey(Key),
    /// `x-message-ttl`.
    MessageTtl(i16),
    /// `x-expires`.
    Expires(i16),
    /// `x-max-priority`.
    MaxPriority(i16),
    /// `x-priority` (consumers).
    Priority(i16),
    /// `alternate-exchange`.
    AlternateExchange(Name),
    /// `x-match`: all, any, all-with-x, any-with-x or junk.
    Match(u8),
    /// A header-style argument `h<k>` with a small value.
    Header(u8, Value),
    /// A known key with a value of the wrong type.
    WrongType(u8, Value),
}

/// Field values scripts use.
#[derive(Arbitrary, Debug, Clone)]
pub enum Value {
    /// A signed integer.
    Int(i32),
    /// A string.
    Str(u8),
    /// A boolean.
    Bool(bool),
    /// A nested table with one entry.
    Table(u8),
    /// Void.
    Void,
}

impl Value {
    fn field(&self) -> FieldValue {
        match self {
            Value::Int(n) => FieldValue::I32(*n),
            Value::Str(s) => FieldValue::string(&format!("s{}", s % 4)),
            Value::Bool(b) => FieldValue::Bool(*b),
            Value::Table(k) => FieldValue::Table(
                [(short(&format!("k{}", k % 3)), FieldValue::I8(1))]
                    .into_iter()
                    .collect(),
            ),
            Value::Void => FieldValue::Void,
        }
    }
}

fn short(s: &str) -> ShortStr {
    ShortStr::try_from(s).unwrap_or_default()
}

fn table(arguments: &[Argument]) -> FieldTable {
    let mut table = FieldTable::new();
    for argument in arguments.iter().take(8) {
        let (key, value) = match argument {
            Argument::MaxLength(n) => ("x-max-length", FieldValue::I32(i32::from(*n))),
            Argument::MaxLengthBytes(n) => ("x-max-length-bytes", FieldValue::I32(i32::from(*n))),
            Argument::Overflow(n) => (
                "x-overflow",
                FieldValue::string(
                    ["drop-head", "reject-publish", "reject-publish-dlx", "junk"]
                        [usize::from(*n) % 4],
                ),
            ),
            Argument::DeadLetterExchange(name) => (
                "x-dead-letter-exchange",
                FieldValue::LongStr(name.short().into_bytes()),
            ),
            Argument::DeadLetterRoutingKey(key) => (
                "x-dead-letter-routing-key",
                FieldValue::LongStr(key.short().into_bytes()),
            ),
            Argument::MessageTtl(n) => ("x-message-ttl", FieldValue::I32(i32::from(*n))),
            Argument::Expires(n) => ("x-expires", FieldValue::I32(i32::from(*n))),
            Argument::MaxPriority(n) => ("x-max-priority", FieldValue::I32(i32::from(*n))),
            Argument::Priority(n) => ("x-priority", FieldValue::I32(i32::from(*n))),
            Argument::AlternateExchange(name) => (
                "alternate-exchange",
                FieldValue::LongStr(name.short().into_bytes()),
            ),
            Argument::Match(n) => (
                "x-match",
                FieldValue::string(
                    ["all", "any", "all-with-x", "any-with-x", "junk"][usize::from(*n) % 5],
                ),
            ),
            Argument::Header(k, value) => {
                table.insert(short(&format!("h{}", k % 4)), value.field());
                continue;
            }
            Argument::WrongType(k, value) => (
                [
                    "x-max-length",
                    "x-message-ttl",
                    "x-expires",
                    "x-dead-letter-exchange",
                    "x-overflow",
                    "x-max-priority",
                    "alternate-exchange",
                    "x-match",
                ][usize::from(*k) % 8],
                value.field(),
            ),
        };
        table.insert(ShortStr::from_static(key), value);
    }
    table
}

/// Message properties a publish carries.
#[derive(Arbitrary, Debug, Clone)]
pub struct Props {
    /// 1 transient, 2 persistent.
    pub delivery_mode: Option<u8>,
    /// Priority.
    pub priority: Option<u8>,
    /// Per-message TTL, as RabbitMQ's decimal string (or junk when 0xFFFF).
    pub expiration: Option<u16>,
    /// Headers for headers exchanges and dead-letter history.
    pub headers: Vec<Argument>,
    /// `reply-to` (direct reply-to when it names it).
    pub reply_to: Option<Name>,
}

impl Props {
    fn encode(&self) -> Bytes {
        let properties = BasicProperties {
            delivery_mode: self.delivery_mode.map(|m| m % 3),
            priority: self.priority,
            expiration: self.expiration.map(|ms| match ms {
                0xFFFF => ShortStr::from_static("-1x"),
                ms => short(&(ms % 200).to_string()),
            }),
            headers: (!self.headers.is_empty()).then(|| table(&self.headers)),
            reply_to: self.reply_to.map(Name::short),
            ..Default::default()
        };
        let mut buf = BytesMut::new();
        properties.encode(&mut buf);
        buf.freeze()
    }
}

/// A method a client may send, with what it needs.
#[derive(Arbitrary, Debug, Clone)]
pub enum Op {
    /// channel.open.
    ChannelOpen,
    /// channel.close.
    ChannelClose,
    /// channel.flow.
    ChannelFlow(bool),
    /// exchange.declare.
    ExchangeDeclare {
        /// Name.
        name: Name,
        /// 0 direct, 1 fanout, 2 topic, 3 headers, else junk.
        kind: u8,
        /// Flags: passive, durable, auto-delete, internal, no-wait.
        flags: u8,
        /// Arguments.
        arguments: Vec<Argument>,
    },
    /// exchange.delete.
    ExchangeDelete {
        /// Name.
        name: Name,
        /// if-unused.
        if_unused: bool,
    },
    /// exchange.bind or exchange.unbind.
    ExchangeBind {
        /// Destination.
        destination: Name,
        /// Source.
        source: Name,
        /// Key.
        key: Key,
        /// Arguments.
        arguments: Vec<Argument>,
        /// Unbind instead.
        unbind: bool,
    },
    /// queue.declare.
    QueueDeclare {
        /// Name.
        name: Name,
        /// Flags: passive, durable, exclusive, auto-delete, no-wait.
        flags: u8,
        /// Arguments.
        arguments: Vec<Argument>,
    },
    /// queue.bind or queue.unbind.
    QueueBind {
        /// Queue.
        queue: Name,
        /// Exchange.
        exchange: Name,
        /// Key.
        key: Key,
        /// Arguments.
        arguments: Vec<Argument>,
        /// Unbind instead.
        unbind: bool,
    },
    /// queue.purge.
    QueuePurge(Name),
    /// queue.delete.
    QueueDelete {
        /// Name.
        name: Name,
        /// if-unused, if-empty.
        flags: u8,
    },
    /// basic.qos.
    Qos {
        /// prefetch-count.
        count: u8,
        /// global.
        global: bool,
    },
    /// basic.consume.
    Consume {
        /// Queue.
        queue: Name,
        /// Consumer tag `c<tag>`, or server-named for 0.
        tag: u8,
        /// Flags: no-ack, exclusive, no-local.
        flags: u8,
        /// Arguments.
        arguments: Vec<Argument>,
    },
    /// basic.cancel.
    Cancel(u8),
    /// basic.publish with its content.
    Publish {
        /// Exchange.
        exchange: Name,
        /// Routing key.
        key: Key,
        /// mandatory, immediate.
        flags: u8,
        /// Properties.
        props: Props,
        /// Body size (at most 8 KiB).
        body: u16,
    },
    /// basic.get.
    Get {
        /// Queue.
        queue: Name,
        /// no-ack.
        no_ack: bool,
    },
    /// basic.ack.
    Ack {
        /// Delivery tag.
        tag: u8,
        /// multiple.
        multiple: bool,
    },
    /// basic.nack.
    Nack {
        /// Delivery tag.
        tag: u8,
        /// multiple, requeue.
        flags: u8,
    },
    /// basic.reject.
    Reject {
        /// Delivery tag.
        tag: u8,
        /// requeue.
        requeue: bool,
    },
    /// basic.recover.
    Recover(bool),
    /// tx.select.
    TxSelect,
    /// tx.commit.
    TxCommit,
    /// tx.rollback.
    TxRollback,
    /// confirm.select.
    ConfirmSelect,
    /// A content header with no publish before it.
    StrayHeader(u32),
    /// A body frame with no header before it.
    StrayBody(u8),
    /// A publish whose header announces more body than follows.
    ShortBody {
        /// Body bytes announced.
        announced: u16,
        /// Body bytes sent.
        sent: u8,
    },
}

fn bit(flags: u8, n: u8) -> bool {
    flags & (1 << n) != 0
}

/// What the driver knows of one connection, updated by its reader task.
#[derive(Default)]
struct Seen {
    /// The broker closed the connection or the pipe ended.
    closed: bool,
    /// The broker sent connection.blocked and not yet unblocked.
    blocked: bool,
    /// Channels whose channel.open-ok arrived since the last probe.
    opened: HashSet<u16>,
    /// Replies to the driver's liveness queue.declare.
    declared: u32,
    /// Raw bytes were sent: the broker may rightly be waiting for the rest
    /// of a frame they began, so this connection is not probed.
    raw: bool,
}

struct Peer {
    writer: Arc<tokio::sync::Mutex<WriteHalf<DuplexStream>>>,
    seen: Arc<Mutex<Seen>>,
    changed: Arc<Notify>,
    reader: tokio::task::JoinHandle<()>,
}

impl Drop for Peer {
    fn drop(&mut self) {
        self.reader.abort();
    }
}

fn method_bytes(channel: u16, method: impl Into<Method>) -> BytesMut {
    let mut buf = BytesMut::new();
    encode_method(channel, &method.into(), &mut buf);
    buf
}

impl Peer {
    /// Opens an in-process connection and completes the handshake.
    async fn connect(broker: &BrokerHandle) -> Option<Peer> {
        let (mut read, mut write) = tokio::io::split(broker.connect_in_process());
        write.write_all(PROTOCOL_HEADER).await.ok()?;
        let mut buf = BytesMut::new();
        expect(&mut read, &mut buf, |m| {
            matches!(m, Method::ConnectionStart(_))
        })
        .await?;
        let start_ok = ConnectionStartOk {
            client_properties: FieldTable::new(),
            mechanism: ShortStr::from_static("PLAIN"),
            response: Bytes::from_static(b"\0guest\0guest"),
            locale: ShortStr::from_static("en_US"),
        };
        write.write_all(&method_bytes(0, start_ok)).await.ok()?;
        expect(&mut read, &mut buf, |m| {
            matches!(m, Method::ConnectionTune(_))
        })
        .await?;
        let tune_ok = ConnectionTuneOk {
            channel_max: 16,
            frame_max: FRAME_MAX,
            heartbeat: 0,
        };
        write.write_all(&method_bytes(0, tune_ok)).await.ok()?;
        let open = ConnectionOpen {
            virtual_host: ShortStr::from_static("/"),
            ..Default::default()
        };
        write.write_all(&method_bytes(0, open)).await.ok()?;
        expect(&mut read, &mut buf, |m| {
            matches!(m, Method::ConnectionOpenOk(_))
        })
        .await?;
        let writer = Arc::new(tokio::sync::Mutex::new(write));
        let seen = Arc::new(Mutex::new(Seen::default()));
        let changed = Arc::new(Notify::new());
        let reader = tokio::spawn(read_replies(
            read,
            buf,
            Arc::clone(&writer),
            Arc::clone(&seen),
            Arc::clone(&changed),
        ));
        Some(Peer {
            writer,
            seen,
            changed,
            reader,
        })
    }

    fn seen(&self) -> std::sync::MutexGuard<'_, Seen> {
        self.seen.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// Writes bytes; false when the connection is gone. Panics when the
    /// broker stops reading without having said it blocked the connection.
    async fn send(&self, bytes: &[u8]) -> bool {
        let mut writer = self.writer.lock().await;
        match tokio::time::timeout(WRITE_WITHIN, writer.write_all(bytes)).await {
            Ok(result) => result.is_ok(),
            Err(_) if self.seen().blocked || self.seen().closed => false,
            Err(_) => panic!("the broker stopped reading a connection it had not blocked"),
        }
    }

    /// Waits until `done` holds for what the reader saw, or the connection
    /// closes; panics after [`ANSWER_WITHIN`].
    async fn wait_for(&self, what: &str, done: impl Fn(&Seen) -> bool) {
        let wait = async {
            loop {
                let notified = self.changed.notified();
                {
                    let seen = self.seen();
                    if seen.closed || done(&seen) {
                        return;
                    }
                }
                notified.await;
            }
        };
        if tokio::time::timeout(ANSWER_WITHIN, wait).await.is_err() {
            panic!("the broker did not answer {what} within {ANSWER_WITHIN:?}");
        }
    }
}

/// Reads frames until one method matches; None on anything else.
async fn expect(
    read: &mut ReadHalf<DuplexStream>,
    buf: &mut BytesMut,
    wanted: impl Fn(&Method) -> bool,
) -> Option<()> {
    loop {
        match decode_frame(buf, 0) {
            Ok(Some(Frame::Method { method, .. })) => return wanted(&method).then_some(()),
            Ok(Some(_)) => return None,
            Ok(None) => {}
            Err(_) => return None,
        }
        let read_one = read.read_buf(buf);
        match tokio::time::timeout(ANSWER_WITHIN, read_one).await {
            Ok(Ok(n)) if n > 0 => {}
            Ok(_) => return None,
            Err(_) => panic!("the broker did not answer the handshake within {ANSWER_WITHIN:?}"),
        }
    }
}

/// Drains what the broker sends, answering closes as a client must.
async fn read_replies(
    mut read: ReadHalf<DuplexStream>,
    mut buf: BytesMut,
    writer: Arc<tokio::sync::Mutex<WriteHalf<DuplexStream>>>,
    seen: Arc<Mutex<Seen>>,
    changed: Arc<Notify>,
) {
    let lock = || seen.lock().unwrap_or_else(|e| e.into_inner());
    loop {
        loop {
            let frame = match decode_frame(&mut buf, 0) {
                Ok(Some(frame)) => frame,
                Ok(None) => break,
                Err(e) => panic!("the broker sent a frame its own codec rejects: {e:?}"),
            };
            let Frame::Method { channel, method } = frame else {
                continue;
            };
            let reply = match method {
                Method::ChannelClose(_) => Some(method_bytes(channel, ChannelCloseOk {})),
                Method::ConnectionClose(_) => {
                    let close_ok = method_bytes(0, ConnectionCloseOk {});
                    let _ = writer.lock().await.write_all(&close_ok).await;
                    lock().closed = true;
                    changed.notify_waiters();
                    return;
                }
                Method::ConnectionBlocked(_) => {
                    lock().blocked = true;
                    None
                }
                Method::ConnectionUnblocked(_) => {
                    lock().blocked = false;
                    None
                }
                Method::ChannelOpenOk(_) => {
                    lock().opened.insert(channel);
                    None
                }
                Method::QueueDeclareOk(_) if channel == PROBE_CHANNEL => {
                    lock().declared += 1;
                    None
                }
                _ => None,
            };
            if let Some(reply) = reply {
                // A write that cannot finish means the broker stopped
                // reading; the probes report that.
                let _ = tokio::time::timeout(WRITE_WITHIN, async {
                    writer.lock().await.write_all(&reply).await
                })
                .await;
            }
            changed.notify_waiters();
        }
        match read.read_buf(&mut buf).await {
            Ok(n) if n > 0 => {}
            _ => {
                lock().closed = true;
                changed.notify_waiters();
                return;
            }
        }
    }
}

/// The channel the liveness probes use (the scripts use 1 to 4).
const PROBE_CHANNEL: u16 = 15;

fn encode_op(channel: u16, op: &Op) -> BytesMut {
    let mut buf = BytesMut::new();
    let method: Method = match op {
        Op::ChannelOpen => ChannelOpen::default().into(),
        Op::ChannelClose => ChannelClose {
            reply_code: 200,
            reply_text: ShortStr::from_static("bye"),
            ..Default::default()
        }
        .into(),
        Op::ChannelFlow(active) => ChannelFlow { active: *active }.into(),
        Op::ExchangeDeclare {
            name,
            kind,
            flags,
            arguments,
        } => ExchangeDeclare {
            exchange: name.short(),
            kind: ShortStr::from_static(
                ["direct", "fanout", "topic", "headers", "x-junk"][usize::from(*kind) % 5],
            ),
            passive: bit(*flags, 0),
            durable: bit(*flags, 1),
            auto_delete: bit(*flags, 2),
            internal: bit(*flags, 3),
            no_wait: bit(*flags, 4),
            arguments: table(arguments),
            ..Default::default()
        }
        .into(),
        Op::ExchangeDelete { name, if_unused } => ExchangeDelete {
            exchange: name.short(),
            if_unused: *if_unused,
            ..Default::default()
        }
        .into(),
        Op::ExchangeBind {
            destination,
            source,
            key,
            arguments,
            unbind,
        } => {
            if *unbind {
                ExchangeUnbind {
                    destination: destination.short(),
                    source: source.short(),
                    routing_key: key.short(),
                    arguments: table(arguments),
                    ..Default::default()
                }
                .into()
            } else {
                ExchangeBind {
                    destination: destination.short(),
                    source: source.short(),
                    routing_key: key.short(),
                    arguments: table(arguments),
                    ..Default::default()
                }
                .into()
            }
        }
        Op::QueueDeclare {
            name,
            flags,
            arguments,
        } => QueueDeclare {
            queue: name.short(),
            passive: bit(*flags, 0),
            durable: bit(*flags, 1),
            exclusive: bit(*flags, 2),
            auto_delete: bit(*flags, 3),
            no_wait: bit(*flags, 4),
            arguments: table(arguments),
            ..Default::default()
        }
        .into(),
        Op::QueueBind {
            queue,
            exchange,
            key,
            arguments,
            unbind,
        } => {
            if *unbind {
                QueueUnbind {
                    queue: queue.short(),
                    exchange: exchange.short(),
                    routing_key: key.short(),
                    arguments: table(arguments),
                    ..Default::default()
                }
                .into()
            } else {
                QueueBind {
                    queue: queue.short(),
                    exchange: exchange.short(),
                    routing_key: key.short(),
                    arguments: table(arguments),
                    ..Default::default()
                }
                .into()
            }
        }
        Op::QueuePurge(name) => QueuePurge {
            queue: name.short(),
            ..Default::default()
        }
        .into(),
        Op::QueueDelete { name, flags } => QueueDelete {
            queue: name.short(),
            if_unused: bit(*flags, 0),
            if_empty: bit(*flags, 1),
            ..Default::default()
        }
        .into(),
        Op::Qos { count, global } => BasicQos {
            prefetch_count: u16::from(*count % 8),
            global: *global,
            ..Default::default()
        }
        .into(),
        Op::Consume {
            queue,
            tag,
            flags,
            arguments,
        } => BasicConsume {
            queue: queue.short(),
            consumer_tag: match tag % 4 {
                0 => ShortStr::default(),
                n => short(&format!("c{n}")),
            },
            no_ack: bit(*flags, 0),
            exclusive: bit(*flags, 1),
            no_local: bit(*flags, 2),
            arguments: table(arguments),
            ..Default::default()
        }
        .into(),
        Op::Cancel(tag) => BasicCancel {
            consumer_tag: short(&format!("c{}", tag % 4)),
            no_wait: false,
        }
        .into(),
        Op::Publish {
            exchange,
            key,
            flags,
            props,
            body,
        } => {
            let publish = BasicPublish {
                exchange: exchange.short(),
                routing_key: key.short(),
                mandatory: bit(*flags, 0),
                immediate: bit(*flags, 1),
                ..Default::default()
            };
            encode_method(channel, &publish.into(), &mut buf);
            let body = vec![0x5a; usize::from(*body % 8192)];
            encode_content(
                channel,
                ContentHeader::BASIC_CLASS,
                &props.encode(),
                &body,
                FRAME_MAX,
                &mut buf,
            );
            return buf;
        }
        Op::Get { queue, no_ack } => BasicGet {
            queue: queue.short(),
            no_ack: *no_ack,
            ..Default::default()
        }
        .into(),
        Op::Ack { tag, multiple } => BasicAck {
            delivery_tag: u64::from(*tag % 16),
            multiple: *multiple,
        }
        .into(),
        Op::Nack { tag, flags } => BasicNack {
            delivery_tag: u64::from(*tag % 16),
            multiple: bit(*flags, 0),
            requeue: bit(*flags, 1),
        }
        .into(),
        Op::Reject { tag, requeue } => BasicReject {
            delivery_tag: u64::from(*tag % 16),
            requeue: *requeue,
        }
        .into(),
        Op::Recover(requeue) => BasicRecover { requeue: *requeue }.into(),
        Op::TxSelect => TxSelect {}.into(),
        Op::TxCommit => TxCommit {}.into(),
        Op::TxRollback => TxRollback {}.into(),
        Op::ConfirmSelect => ConfirmSelect { no_wait: false }.into(),
        Op::StrayHeader(size) => {
            let header = ContentHeader {
                class_id: ContentHeader::BASIC_CLASS,
                body_size: u64::from(*size),
                property_bytes: Bytes::from_static(&[0, 0]),
            };
            encode_header(channel, &header, &mut buf);
            return buf;
        }
        Op::StrayBody(len) => {
            Frame::Body {
                channel,
                payload: Bytes::from(vec![1; usize::from(*len)]),
            }
            .encode(&mut buf);
            return buf;
        }
        Op::ShortBody { announced, sent } => {
            let publish = BasicPublish {
                routing_key: ShortStr::from_static("q0"),
                ..Default::default()
            };
            encode_method(channel, &publish.into(), &mut buf);
            let header = ContentHeader {
                class_id: ContentHeader::BASIC_CLASS,
                body_size: u64::from(*announced),
                property_bytes: Bytes::from_static(&[0, 0]),
            };
            encode_header(channel, &header, &mut buf);
            Frame::Body {
                channel,
                payload: Bytes::from(vec![2; usize::from(*sent)]),
            }
            .encode(&mut buf);
            return buf;
        }
    };
    encode_method(channel, &method, &mut buf);
    buf
}

/// Plays `script` against a fresh in-process broker on the runtime the
/// script asks for, then checks the broker still answers.
///
/// # Panics
///
/// When the broker panicked, stopped reading a connection it had not
/// blocked, or did not answer a liveness probe in time.
pub fn run(script: &Script) {
    let runtime = if script.multi_thread {
        tokio::runtime::Builder::new_multi_thread()
            .worker_threads(2)
            .enable_all()
            .build()
    } else {
        tokio::runtime::Builder::new_current_thread()
            .enable_all()
            .build()
    }
    .expect("a tokio runtime");
    runtime.block_on(play(script));
}

async fn play(script: &Script) {
    let broker = Broker::builder().start().await.expect("the broker starts");
    let mut peers: Vec<Option<Peer>> = Vec::with_capacity(CONNECTIONS);
    for _ in 0..CONNECTIONS {
        peers.push(Peer::connect(&broker).await);
    }
    for step in script.steps.iter().take(MAX_STEPS) {
        match step {
            Step::Send {
                connection,
                channel,
                op,
            } => {
                let slot = usize::from(*connection) % CONNECTIONS;
                let channel = u16::from(*channel % 4) + 1;
                if let Some(peer) = &peers[slot] {
                    if !peer.send(&encode_op(channel, op)).await {
                        peers[slot] = None;
                    }
                }
            }
            Step::Raw { connection, bytes } => {
                let slot = usize::from(*connection) % CONNECTIONS;
                if let Some(peer) = &peers[slot] {
                    peer.seen().raw = true;
                    if !peer.send(&bytes[..bytes.len().min(512)]).await {
                        peers[slot] = None;
                    }
                }
            }
            Step::Pause => tokio::time::sleep(Duration::from_millis(1)).await,
            Step::Reconnect { connection } => {
                let slot = usize::from(*connection) % CONNECTIONS;
                peers[slot] = None;
                peers[slot] = Peer::connect(&broker).await;
            }
        }
        tokio::task::yield_now().await;
    }
    // Every connection the broker kept open still answers.
    for peer in peers.iter().flatten() {
        {
            let seen = peer.seen();
            if seen.closed || seen.blocked || seen.raw {
                continue;
            }
        }
        if !peer
            .send(&method_bytes(PROBE_CHANNEL, ChannelOpen::default()))
            .await
        {
            continue;
        }
        peer.wait_for("channel.open", |seen| seen.opened.contains(&PROBE_CHANNEL))
            .await;
    }
    // A newcomer is served.
    let newcomer = Peer::connect(&broker)
        .await
        .expect("a new connection completes its handshake after the script");
    assert!(
        newcomer
            .send(&method_bytes(PROBE_CHANNEL, ChannelOpen::default()))
            .await
    );
    let declare = QueueDeclare {
        exclusive: true,
        ..Default::default()
    };
    assert!(newcomer.send(&method_bytes(PROBE_CHANNEL, declare)).await);
    newcomer
        .wait_for("queue.declare", |seen| seen.declared > 0)
        .await;
    assert!(
        !newcomer.seen().closed,
        "the broker closed a newcomer's connection after the script"
    );
    drop(peers);
    drop(newcomer);
    broker.shutdown().await;
}
