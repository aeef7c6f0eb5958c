//! Client-side helpers shared by the integration test files (each file
//! includes this module with `#[macro_use] mod common;`).
//!
//! Every wait goes through [`TIMEOUT`] so a hung broker fails the test
//! instead of hanging it; [`QUIET`] is the short window used only to check
//! that something does *not* arrive.
#![allow(dead_code, unused_macros, unused_imports)]

use std::future::Future;
use std::time::Duration;

use async_trait::async_trait;
use futures_lite::StreamExt;
use tokio::sync::mpsc::{unbounded_channel, UnboundedReceiver, UnboundedSender};

pub use leveret_tests::{both_runtimes, broker, unique, TestBroker};

/// How long any single expected event may take: a hang limit, generous
/// enough for a debug build on a loaded two-core machine.
pub const TIMEOUT: Duration = Duration::from_secs(30);
/// How long to wait to be fairly sure something does not arrive.
pub const QUIET: Duration = Duration::from_millis(200);

/// Awaits `$fut` for at most [`TIMEOUT`], panicking with the expression's
/// text when it takes longer.
macro_rules! tmo {
    ($fut:expr) => {
        match ::tokio::time::timeout($crate::common::TIMEOUT, $fut).await {
            Ok(v) => v,
            Err(_) => panic!(
                "timed out after {:?}: {}",
                $crate::common::TIMEOUT,
                stringify!($fut)
            ),
        }
    };
}

/// Awaits `fut` for at most [`TIMEOUT`].
pub async fn within<T>(what: &str, fut: impl Future<Output = T>) -> T {
    match tokio::time::timeout(TIMEOUT, fut).await {
        Ok(v) => v,
        Err(_) => panic!("timed out after {TIMEOUT:?} waiting for {what}"),
    }
}

/// How long the calling thread has run on a CPU (its
/// `CLOCK_THREAD_CPUTIME_ID`). Time spent waiting for a CPU does not count,
/// so a loaded machine does not inflate it: the stall tests bound the work
/// a broker thread does with it, where a wall clock would measure the
/// machine.
pub fn thread_cpu_time() -> Duration {
    let now = rustix::time::clock_gettime(rustix::time::ClockId::ThreadCPUTime);
    Duration::new(
        u64::try_from(now.tv_sec).expect("a thread's CPU time is positive"),
        u32::try_from(now.tv_nsec).expect("nanoseconds"),
    )
}

/// One MQTT packet, written by hand: `first` (type and flags), the
/// remaining length (MQTT's variable byte integer), then `body`.
pub fn mqtt_packet(first: u8, body: &[u8]) -> Vec<u8> {
    let mut out = vec![first];
    let mut left = body.len();
    loop {
        let byte = (left % 128) as u8;
        left /= 128;
        out.push(if left > 0 { byte | 0x80 } else { byte });
        if left == 0 {
            break;
        }
    }
    out.extend_from_slice(body);
    out
}

/// `text` as MQTT's length-prefixed string.
pub fn mqtt_string(text: &str) -> Vec<u8> {
    let mut out = (text.len() as u16).to_be_bytes().to_vec();
    out.extend_from_slice(text.as_bytes());
    out
}

/// Asserts a reply text starts with the reply code's name, as RabbitMQ's
/// do (`NOT_FOUND - no queue 'x' in vhost '/'`).
pub fn assert_text_prefix(text: &str, prefix: &str) {
    assert!(
        text.starts_with(prefix),
        "reply text {text:?} should start with {prefix:?}"
    );
}

// ---------------------------------------------------------------------------
// lapin

pub mod lp {
    use super::*;
    pub use lapin::message::{BasicGetMessage, BasicReturnMessage, Delivery};
    pub use lapin::options::*;
    pub use lapin::publisher_confirm::Confirmation;
    pub use lapin::types::{AMQPValue, FieldTable, ShortString};
    pub use lapin::{
        BasicProperties, Channel, Connection, ConnectionProperties, Consumer, ExchangeKind,
    };

    /// Opens a lapin connection to the default vhost.
    pub async fn connect(b: &TestBroker) -> Connection {
        within(
            "lapin connect",
            Connection::connect(b.url(), ConnectionProperties::default()),
        )
        .await
        .expect("lapin connects")
    }

    /// Opens a channel.
    pub async fn channel(conn: &Connection) -> Channel {
        within("lapin channel.open", conn.create_channel())
            .await
            .expect("channel opens")
    }

    /// A connection with one channel.
    pub async fn open(b: &TestBroker) -> (Connection, Channel) {
        let conn = connect(b).await;
        let ch = channel(&conn).await;
        (conn, ch)
    }

    /// The reply code and text of a protocol error (a channel or connection
    /// close from the broker).
    pub fn code(err: &lapin::Error) -> (u16, String) {
        match err {
            lapin::Error::ProtocolError(e) => (e.get_id(), e.get_message().to_string()),
            other => panic!("expected a protocol error from the broker, got {other:?}"),
        }
    }

    /// Asserts `res` failed with `code` and a reply text starting with `prefix`.
    pub fn assert_err<T: std::fmt::Debug>(res: lapin::Result<T>, want: u16, prefix: &str) {
        let err = res.expect_err("the broker should refuse this");
        let (got, text) = code(&err);
        assert_eq!(got, want, "reply code (text {text:?})");
        assert_text_prefix(&text, prefix);
    }

    /// Errors reported for a channel (a channel.close from the broker that
    /// no pending call is waiting for, such as after a bad basic.ack).
    pub fn watch_errors(ch: &Channel) -> UnboundedReceiver<lapin::Error> {
        let (tx, rx) = unbounded_channel();
        ch.on_error(move |e| {
            let _ = tx.send(e);
        });
        rx
    }

    /// Errors reported for a connection.
    pub fn watch_conn_errors(conn: &Connection) -> UnboundedReceiver<lapin::Error> {
        let (tx, rx) = unbounded_channel();
        conn.on_error(move |e| {
            let _ = tx.send(e);
        });
        rx
    }

    /// Declares a non-durable queue with a unique name (no arguments).
    pub async fn queue(ch: &Channel, prefix: &str) -> String {
        queue_with(ch, prefix, FieldTable::default()).await
    }

    /// Declares a non-durable queue with a unique name and arguments.
    pub async fn queue_with(ch: &Channel, prefix: &str, args: FieldTable) -> String {
        let name = unique(prefix);
        within(
            "queue.declare",
            ch.queue_declare(&name, QueueDeclareOptions::default(), args),
        )
        .await
        .expect("queue.declare");
        name
    }

    /// Declares an exchange with a unique name.
    pub async fn exchange(ch: &Channel, prefix: &str, kind: ExchangeKind) -> String {
        let name = unique(prefix);
        within(
            "exchange.declare",
            ch.exchange_declare(
                &name,
                kind,
                ExchangeDeclareOptions {
                    auto_delete: false,
                    ..Default::default()
                },
                FieldTable::default(),
            ),
        )
        .await
        .expect("exchange.declare");
        name
    }

    /// Binds a queue.
    pub async fn bind(ch: &Channel, queue: &str, exchange: &str, key: &str) {
        bind_args(ch, queue, exchange, key, FieldTable::default()).await
    }

    /// Binds a queue with arguments.
    pub async fn bind_args(ch: &Channel, queue: &str, exchange: &str, key: &str, a: FieldTable) {
        within(
            "queue.bind",
            ch.queue_bind(queue, exchange, key, QueueBindOptions::default(), a),
        )
        .await
        .expect("queue.bind");
    }

    /// Publishes a transient message with no properties.
    pub async fn publish(ch: &Channel, exchange: &str, key: &str, body: &[u8]) {
        publish_props(ch, exchange, key, body, BasicProperties::default()).await
    }

    /// Publishes with properties.
    pub async fn publish_props(
        ch: &Channel,
        exchange: &str,
        key: &str,
        body: &[u8],
        props: BasicProperties,
    ) {
        within(
            "basic.publish",
            ch.basic_publish(exchange, key, BasicPublishOptions::default(), body, props),
        )
        .await
        .expect("basic.publish");
    }

    /// Publishes on a channel in confirm mode and waits for the confirm.
    pub async fn publish_confirmed(
        ch: &Channel,
        exchange: &str,
        key: &str,
        body: &[u8],
        props: BasicProperties,
    ) -> Confirmation {
        let confirm = within(
            "basic.publish",
            ch.basic_publish(exchange, key, BasicPublishOptions::default(), body, props),
        )
        .await
        .expect("basic.publish");
        within("publisher confirm", confirm).await.expect("confirm")
    }

    /// Starts a consumer with manual acks.
    pub async fn consume(ch: &Channel, queue: &str, tag: &str) -> Consumer {
        consume_opts(ch, queue, tag, BasicConsumeOptions::default()).await
    }

    /// Starts a consumer with options.
    pub async fn consume_opts(
        ch: &Channel,
        queue: &str,
        tag: &str,
        opts: BasicConsumeOptions,
    ) -> Consumer {
        within(
            "basic.consume",
            ch.basic_consume(queue, tag, opts, FieldTable::default()),
        )
        .await
        .expect("basic.consume")
    }

    /// The next delivery (panics on timeout, error, or end of stream).
    pub async fn next(consumer: &mut Consumer) -> Delivery {
        within("a delivery", consumer.next())
            .await
            .expect("consumer stream ended")
            .expect("delivery error")
    }

    /// Asserts nothing is delivered within [`QUIET`].
    pub async fn nothing(consumer: &mut Consumer) {
        if let Ok(Some(d)) = tokio::time::timeout(QUIET, consumer.next()).await {
            panic!("unexpected delivery: {d:?}");
        }
    }

    /// basic.get (manual ack unless `no_ack`).
    pub async fn get(ch: &Channel, queue: &str, no_ack: bool) -> Option<BasicGetMessage> {
        within("basic.get", ch.basic_get(queue, BasicGetOptions { no_ack }))
            .await
            .expect("basic.get")
    }

    /// Acks one delivery.
    pub async fn ack(ch: &Channel, tag: u64) {
        within("basic.ack", ch.basic_ack(tag, BasicAckOptions::default()))
            .await
            .expect("basic.ack")
    }

    /// Body as text.
    pub fn text(d: &Delivery) -> String {
        String::from_utf8(d.data.clone()).expect("utf-8 body")
    }

    /// A field table from pairs.
    pub fn table(pairs: Vec<(&str, AMQPValue)>) -> FieldTable {
        let mut t = FieldTable::default();
        for (k, v) in pairs {
            t.insert(ShortString::from(k.to_owned()), v);
        }
        t
    }

    /// A long-string value.
    pub fn lstr(s: &str) -> AMQPValue {
        AMQPValue::LongString(s.into())
    }
}

// ---------------------------------------------------------------------------
// amqprs

pub mod rs {
    use super::*;
    pub use amqprs::callbacks::{ChannelCallback, ConnectionCallback};
    pub use amqprs::channel::ConsumerMessage;
    pub use amqprs::channel::{
        BasicAckArguments, BasicCancelArguments, BasicConsumeArguments, BasicGetArguments,
        BasicNackArguments, BasicPublishArguments, BasicQosArguments, BasicRejectArguments,
        Channel, ConfirmSelectArguments, ExchangeBindArguments, ExchangeDeclareArguments,
        ExchangeDeleteArguments, ExchangeType, ExchangeUnbindArguments, QueueBindArguments,
        QueueDeclareArguments, QueueDeleteArguments, QueuePurgeArguments, QueueUnbindArguments,
    };
    pub use amqprs::connection::{Connection, OpenConnectionArguments};
    pub use amqprs::consumer::AsyncConsumer;
    pub use amqprs::{
        Ack, BasicProperties, Cancel, Close, CloseChannel, Deliver, FieldName, FieldTable,
        FieldValue, Nack, Return,
    };

    /// Something the broker sent on a channel on its own initiative.
    #[derive(Debug)]
    pub enum Event {
        /// channel.close from the broker.
        Close {
            code: u16,
            text: String,
            class_id: u16,
            method_id: u16,
        },
        /// basic.cancel from the broker (consumer cancel notification).
        Cancel { tag: String },
        /// basic.ack publisher confirm.
        Ack { tag: u64, multiple: bool },
        /// basic.nack publisher confirm.
        Nack { tag: u64, multiple: bool },
        /// basic.return with its message.
        Return {
            code: u16,
            text: String,
            exchange: String,
            routing_key: String,
            props: Box<BasicProperties>,
            body: Vec<u8>,
        },
    }

    struct ChannelEvents(UnboundedSender<Event>);

    #[async_trait]
    impl ChannelCallback for ChannelEvents {
        async fn close(
            &mut self,
            _: &Channel,
            close: CloseChannel,
        ) -> std::result::Result<(), amqprs::error::Error> {
            let _ = self.0.send(Event::Close {
                code: close.reply_code(),
                text: close.reply_text().clone(),
                class_id: close.class_id(),
                method_id: close.method_id(),
            });
            Ok(())
        }
        async fn cancel(
            &mut self,
            _: &Channel,
            cancel: Cancel,
        ) -> std::result::Result<(), amqprs::error::Error> {
            let _ = self.0.send(Event::Cancel {
                tag: cancel.consumer_tag().clone(),
            });
            Ok(())
        }
        async fn flow(
            &mut self,
            _: &Channel,
            _active: bool,
        ) -> std::result::Result<bool, amqprs::error::Error> {
            Ok(true)
        }
        async fn publish_ack(&mut self, _: &Channel, ack: Ack) {
            let _ = self.0.send(Event::Ack {
                tag: ack.delivery_tag(),
                multiple: ack.mutiple(),
            });
        }
        async fn publish_nack(&mut self, _: &Channel, nack: Nack) {
            let _ = self.0.send(Event::Nack {
                tag: nack.delivery_tag(),
                multiple: nack.multiple(),
            });
        }
        async fn publish_return(
            &mut self,
            _: &Channel,
            ret: Return,
            props: BasicProperties,
            body: Vec<u8>,
        ) {
            let _ = self.0.send(Event::Return {
                code: ret.reply_code(),
                text: ret.reply_text().clone(),
                exchange: ret.exchange().clone(),
                routing_key: ret.routing_key().clone(),
                props: Box::new(props),
                body,
            });
        }
    }

    /// A connection.close from the broker.
    #[derive(Debug, Clone, PartialEq)]
    pub struct ConnClose {
        pub code: u16,
        pub text: String,
        pub class_id: u16,
        pub method_id: u16,
    }

    struct ConnectionEvents(UnboundedSender<ConnClose>);

    #[async_trait]
    impl ConnectionCallback for ConnectionEvents {
        async fn close(
            &mut self,
            _: &Connection,
            close: Close,
        ) -> std::result::Result<(), amqprs::error::Error> {
            let _ = self.0.send(ConnClose {
                code: close.reply_code(),
                text: close.reply_text().clone(),
                class_id: close.class_id(),
                method_id: close.method_id(),
            });
            Ok(())
        }
        async fn blocked(&mut self, _: &Connection, _reason: String) {}
        async fn unblocked(&mut self, _: &Connection) {}
        async fn secret_updated(&mut self, _: &Connection) {}
    }

    /// Connection arguments for the default vhost as guest.
    pub fn args(b: &TestBroker) -> OpenConnectionArguments {
        OpenConnectionArguments::new(b.host(), b.port(), "guest", "guest")
    }

    /// Opens an amqprs connection; the receiver gets every connection.close
    /// the broker sends (code, text).
    pub async fn connect(b: &TestBroker) -> (Connection, UnboundedReceiver<ConnClose>) {
        let conn = within("amqprs connect", Connection::open(&args(b)))
            .await
            .expect("amqprs connects");
        let (tx, rx) = unbounded_channel();
        conn.register_callback(ConnectionEvents(tx))
            .await
            .expect("register connection callback");
        (conn, rx)
    }

    /// Opens a channel whose broker-initiated events go to the receiver.
    pub async fn channel(conn: &Connection) -> (Channel, UnboundedReceiver<Event>) {
        let ch = within("amqprs channel.open", conn.open_channel(None))
            .await
            .expect("channel opens");
        let (tx, rx) = unbounded_channel();
        ch.register_callback(ChannelEvents(tx))
            .await
            .expect("register channel callback");
        (ch, rx)
    }

    /// A connection with one channel.
    pub async fn open(b: &TestBroker) -> (Connection, Channel, UnboundedReceiver<Event>) {
        let (conn, _) = connect(b).await;
        let (ch, ev) = channel(&conn).await;
        (conn, ch, ev)
    }

    /// Waits for the broker's channel.close and returns (code, text),
    /// skipping other events.
    pub async fn closed(ev: &mut UnboundedReceiver<Event>) -> (u16, String) {
        let (code, text, _) = closed_ids(ev).await;
        (code, text)
    }

    /// Waits for the broker's channel.close and returns (code, text,
    /// (class id, method id)), skipping other events.
    pub async fn closed_ids(ev: &mut UnboundedReceiver<Event>) -> (u16, String, (u16, u16)) {
        within("channel.close from the broker", async {
            loop {
                match ev.recv().await {
                    Some(Event::Close {
                        code,
                        text,
                        class_id,
                        method_id,
                    }) => return (code, text, (class_id, method_id)),
                    Some(_) => continue,
                    None => panic!("channel event stream ended without a channel.close"),
                }
            }
        })
        .await
    }

    /// Asserts the broker closed the channel with `code` and a text starting
    /// with `prefix`.
    pub async fn assert_closed(ev: &mut UnboundedReceiver<Event>, code: u16, prefix: &str) {
        let (got, text) = closed(ev).await;
        assert_eq!(got, code, "channel.close reply code (text {text:?})");
        assert_text_prefix(&text, prefix);
    }

    /// Declares a queue with a unique name.
    pub async fn queue(ch: &Channel, prefix: &str) -> String {
        queue_args(ch, QueueDeclareArguments::new(&unique(prefix))).await
    }

    /// Declares a queue and returns its name.
    pub async fn queue_args(ch: &Channel, args: QueueDeclareArguments) -> String {
        let (name, _, _) = within("queue.declare", ch.queue_declare(args))
            .await
            .expect("queue.declare")
            .expect("declare-ok (no_wait is off)");
        name
    }

    /// Declares an exchange with a unique name.
    pub async fn exchange(ch: &Channel, prefix: &str, kind: ExchangeType) -> String {
        let name = unique(prefix);
        within(
            "exchange.declare",
            ch.exchange_declare(ExchangeDeclareArguments::of_type(&name, kind)),
        )
        .await
        .expect("exchange.declare");
        name
    }

    /// Binds a queue.
    pub async fn bind(ch: &Channel, queue: &str, exchange: &str, key: &str) {
        within(
            "queue.bind",
            ch.queue_bind(QueueBindArguments::new(queue, exchange, key)),
        )
        .await
        .expect("queue.bind");
    }

    /// Publishes a message with no properties.
    pub async fn publish(ch: &Channel, exchange: &str, key: &str, body: &[u8]) {
        publish_props(ch, exchange, key, body, BasicProperties::default()).await
    }

    /// Publishes a message with properties.
    pub async fn publish_props(
        ch: &Channel,
        exchange: &str,
        key: &str,
        body: &[u8],
        props: BasicProperties,
    ) {
        within(
            "basic.publish",
            ch.basic_publish(
                props,
                body.to_vec(),
                BasicPublishArguments::new(exchange, key),
            ),
        )
        .await
        .expect("basic.publish");
    }

    /// Puts the channel in confirm mode.
    pub async fn confirm_select(ch: &Channel) {
        within(
            "confirm.select",
            ch.confirm_select(ConfirmSelectArguments::default()),
        )
        .await
        .expect("confirm.select");
    }

    /// Waits until the broker has acked every publish up to sequence
    /// number `upto` (the count of publishes on the channel since
    /// confirm.select), skipping other events; panics on a nack or close.
    ///
    /// Counting queues right after a publish needs this: RabbitMQ answers a
    /// passive queue.declare before it has enqueued publishes still in
    /// flight, but confirms only once they are enqueued.
    pub async fn acked(ev: &mut UnboundedReceiver<Event>, upto: u64) {
        within("publisher confirms", async {
            loop {
                match ev.recv().await {
                    Some(Event::Ack { tag, .. }) if tag >= upto => return,
                    Some(Event::Ack { .. }) => continue,
                    Some(Event::Nack { tag, .. }) => panic!("publish {tag} was nacked"),
                    Some(Event::Close { code, text, .. }) => {
                        panic!("channel closed while waiting for confirms: {code} {text}")
                    }
                    Some(_) => continue,
                    None => panic!("channel event stream ended"),
                }
            }
        })
        .await
    }

    /// Starts a consumer (manual ack unless `no_ack`).
    pub async fn consume(
        ch: &Channel,
        queue: &str,
        tag: &str,
        no_ack: bool,
    ) -> (String, UnboundedReceiver<ConsumerMessage>) {
        let mut args = BasicConsumeArguments::new(queue, tag);
        args.manual_ack(!no_ack);
        within("basic.consume", ch.basic_consume_rx(args))
            .await
            .expect("basic.consume")
    }

    /// A delivered message, unpacked.
    #[derive(Debug)]
    pub struct Msg {
        pub tag: u64,
        pub redelivered: bool,
        pub exchange: String,
        pub routing_key: String,
        pub consumer_tag: String,
        pub props: BasicProperties,
        pub body: Vec<u8>,
    }

    impl Msg {
        /// The body as text.
        pub fn text(&self) -> String {
            String::from_utf8(self.body.clone()).expect("utf-8 body")
        }
    }

    /// The next delivery.
    pub async fn next(rx: &mut UnboundedReceiver<ConsumerMessage>) -> Msg {
        let m = within("a delivery", rx.recv())
            .await
            .expect("consumer channel ended");
        let d = m.deliver.expect("deliver method");
        Msg {
            tag: d.delivery_tag(),
            redelivered: d.redelivered(),
            exchange: d.exchange().clone(),
            routing_key: d.routing_key().clone(),
            consumer_tag: d.consumer_tag().clone(),
            props: m.basic_properties.expect("properties"),
            body: m.content.expect("content"),
        }
    }

    /// Asserts nothing is delivered within [`QUIET`].
    pub async fn nothing(rx: &mut UnboundedReceiver<ConsumerMessage>) {
        if let Ok(Some(m)) = tokio::time::timeout(QUIET, rx.recv()).await {
            panic!("unexpected delivery: {:?}", m.deliver);
        }
    }

    /// basic.get: (delivery tag, redelivered, message_count, body).
    pub async fn get(ch: &Channel, queue: &str, no_ack: bool) -> Option<(u64, bool, u32, Vec<u8>)> {
        let mut args = BasicGetArguments::new(queue);
        args.no_ack = no_ack;
        within("basic.get", ch.basic_get(args))
            .await
            .expect("basic.get")
            .map(|(ok, _props, body)| {
                (
                    ok.delivery_tag(),
                    ok.redelivered(),
                    ok.message_count(),
                    body,
                )
            })
    }

    /// Acks one delivery.
    pub async fn ack(ch: &Channel, tag: u64) {
        within(
            "basic.ack",
            ch.basic_ack(BasicAckArguments::new(tag, false)),
        )
        .await
        .expect("basic.ack")
    }

    /// The message and consumer counts passive declare reports.
    pub async fn counts(ch: &Channel, queue: &str) -> (u32, u32) {
        let mut args = QueueDeclareArguments::new(queue);
        args.passive(true);
        let (_, m, c) = within("passive queue.declare", ch.queue_declare(args))
            .await
            .expect("queue.declare passive")
            .expect("declare-ok");
        (m, c)
    }

    /// A long-string field value.
    pub fn lstr(s: &str) -> FieldValue {
        FieldValue::S(s.try_into().expect("long string"))
    }

    /// A field table from pairs.
    pub fn table(pairs: Vec<(&str, FieldValue)>) -> FieldTable {
        let mut t = FieldTable::new();
        for (k, v) in pairs {
            t.insert(k.try_into().expect("field name"), v);
        }
        t
    }
}

// ---------------------------------------------------------------------------
// raw frames

/// A raw AMQP connection for what a client library hides or will not do:
/// reading frames in wire order, or not reading at all (a stalled peer).
pub mod raw {
    use super::*;
    use bytes::{Bytes, BytesMut};
    use leveret_protocol::{
        decode_frame, encode_content, encode_method, BasicPublish, ChannelOpen, ConnectionOpen,
        ConnectionStartOk, ConnectionTuneOk, ContentHeader,
    };
    pub use leveret_protocol::{
        BasicProperties, FieldTable, Frame, Method, ShortStr, PROTOCOL_HEADER,
    };
    use tokio::io::{AsyncReadExt, AsyncWriteExt};
    use tokio::net::TcpStream;

    /// A short string (panics past 255 bytes).
    pub fn short(s: &str) -> ShortStr {
        ShortStr::try_from(s).expect("short string")
    }

    /// The frames of a method.
    pub fn method_frame(channel: u16, method: impl Into<Method>) -> Bytes {
        let mut buf = BytesMut::new();
        encode_method(channel, &method.into(), &mut buf);
        buf.freeze()
    }

    /// The frames of a basic.publish with its content (one body frame per
    /// `frame_max`; 0 for no limit).
    pub fn publish_frames(
        channel: u16,
        exchange: &str,
        routing_key: &str,
        properties: &BasicProperties,
        body: &[u8],
        frame_max: u32,
    ) -> Bytes {
        let mut buf = BytesMut::new();
        let publish = BasicPublish {
            exchange: short(exchange),
            routing_key: short(routing_key),
            ..Default::default()
        };
        encode_method(channel, &publish.into(), &mut buf);
        let mut property_bytes = BytesMut::new();
        properties.encode(&mut property_bytes);
        encode_content(
            channel,
            ContentHeader::BASIC_CLASS,
            &property_bytes,
            body,
            frame_max,
            &mut buf,
        );
        buf.freeze()
    }

    /// One connection: the socket and what was read but not yet decoded.
    pub struct Raw {
        /// The socket.
        pub socket: TcpStream,
        /// Bytes read and not yet decoded.
        pub buf: BytesMut,
        /// The negotiated frame_max.
        pub frame_max: u32,
    }

    impl Raw {
        /// Connects and logs in as guest/guest on vhost `/`, heartbeats off.
        pub async fn open(b: &TestBroker) -> Raw {
            Raw::open_with_heartbeat(b, 0).await
        }

        /// Connects and logs in as guest/guest on vhost `/`, asking for a
        /// heartbeat every `heartbeat` seconds (0: off).
        pub async fn open_with_heartbeat(b: &TestBroker, heartbeat: u16) -> Raw {
            let socket = within("tcp connect", TcpStream::connect(b.addr()))
                .await
                .expect("tcp connect");
            socket.set_nodelay(true).expect("nodelay");
            let mut raw = Raw {
                socket,
                buf: BytesMut::new(),
                frame_max: 0,
            };
            raw.send_bytes(PROTOCOL_HEADER).await;
            raw.expect(0, |m| matches!(m, Method::ConnectionStart(_)))
                .await;
            let start_ok = ConnectionStartOk {
                client_properties: FieldTable::new(),
                mechanism: short("PLAIN"),
                response: Bytes::from_static(b"\0guest\0guest"),
                locale: short("en_US"),
            };
            let tune = raw.call(0, start_ok, |m| matches!(m, Method::ConnectionTune(_)));
            let Method::ConnectionTune(tune) = tune.await else {
                unreachable!("call matched connection.tune")
            };
            raw.frame_max = tune.frame_max;
            let tune_ok = ConnectionTuneOk {
                channel_max: tune.channel_max,
                frame_max: tune.frame_max,
                heartbeat,
            };
            raw.send(0, tune_ok).await;
            let open = ConnectionOpen {
                virtual_host: short("/"),
                ..Default::default()
            };
            raw.call(0, open, |m| matches!(m, Method::ConnectionOpenOk(_)))
                .await;
            raw
        }

        /// Opens `channel`.
        pub async fn open_channel(&mut self, channel: u16) {
            self.call(channel, ChannelOpen::default(), |m| {
                matches!(m, Method::ChannelOpenOk(_))
            })
            .await;
        }

        /// Writes bytes as they are.
        pub async fn send_bytes(&mut self, bytes: &[u8]) {
            within("a write", self.socket.write_all(bytes))
                .await
                .expect("write");
        }

        /// Sends a method.
        pub async fn send(&mut self, channel: u16, method: impl Into<Method>) {
            self.send_bytes(&method_frame(channel, method)).await;
        }

        /// Sends a method and returns the reply `what` accepts.
        pub async fn call(
            &mut self,
            channel: u16,
            method: impl Into<Method>,
            what: impl Fn(&Method) -> bool,
        ) -> Method {
            self.send(channel, method).await;
            self.expect(channel, what).await
        }

        /// The next frame, heartbeats skipped; panics if the broker closes
        /// the socket.
        pub async fn frame(&mut self) -> Frame {
            loop {
                match decode_frame(&mut self.buf, 0).expect("the broker sends valid frames") {
                    Some(Frame::Heartbeat) => continue,
                    Some(frame) => return frame,
                    None => {}
                }
                let read = within("a frame", self.socket.read_buf(&mut self.buf))
                    .await
                    .expect("read");
                assert!(read > 0, "the broker closed the connection");
            }
        }

        /// The next frame must be a method on `channel` that `what` accepts.
        pub async fn expect(&mut self, channel: u16, what: impl Fn(&Method) -> bool) -> Method {
            match self.frame().await {
                Frame::Method { channel: c, method } if c == channel && what(&method) => method,
                other => panic!("unexpected frame on channel {channel}: {other:?}"),
            }
        }
    }
}

/// Declared after the macros above, which it uses.
pub mod stall;
