//! Hand-written frames over a plain TCP socket, encoded with
//! `leveret_protocol`, for what no client library will send: wrong
//! protocol headers, oversize frames, stray content frames, methods on
//! unopened channels, garbage.
//!
//! Every expectation here was taken from RabbitMQ 3.10.8. Where RabbitMQ
//! ends a connection it sends `connection.close` on channel 0 and closes
//! the socket once the client answers `close-ok` (or after about 3 s when
//! the byte stream can no longer be parsed); RabbitMQ often resets the
//! socket rather than closing it cleanly, so "closed" here means EOF *or*
//! a connection reset.

#[macro_use]
mod common;

use bytes::{BufMut, Bytes, BytesMut};
use common::*;
use leveret_protocol::{
    decode_frame, encode_content, encode_method, BasicAck, BasicPublish, BasicQos, ChannelClose,
    ChannelOpen, ConnectionClose, ConnectionCloseOk, ConnectionOpen, ConnectionStart,
    ConnectionStartOk, ConnectionTune, ConnectionTuneOk, FieldTable, FieldValue, Frame, Method,
    QueueDeclare, ShortStr, PROTOCOL_HEADER,
};
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::TcpStream;

/// One raw AMQP connection.
struct Raw {
    sock: TcpStream,
    buf: BytesMut,
    frame_max: u32,
}

/// What the broker said before the connection was opened.
struct Greeting {
    start: ConnectionStart,
    tune: ConnectionTune,
}

impl Raw {
    async fn connect(b: &TestBroker) -> Raw {
        let sock = tmo!(TcpStream::connect(b.addr())).expect("tcp connect");
        Raw {
            sock,
            buf: BytesMut::new(),
            frame_max: 0,
        }
    }

    async fn send(&mut self, bytes: &[u8]) {
        tmo!(self.sock.write_all(bytes)).expect("write");
    }

    async fn send_method(&mut self, channel: u16, m: impl Into<Method>) {
        self.send(&method_bytes(channel, m)).await;
    }

    /// The next frame, or `None` when the broker closed the socket.
    async fn frame(&mut self) -> Option<Frame> {
        loop {
            if let Some(f) = decode_frame(&mut self.buf, 0).expect("the broker sends valid frames")
            {
                return Some(f);
            }
            match tmo!(self.sock.read_buf(&mut self.buf)) {
                Ok(0) | Err(_) => {
                    assert!(
                        self.buf.is_empty(),
                        "socket closed inside a frame: {:?}",
                        self.buf
                    );
                    return None;
                }
                Ok(_) => {}
            }
        }
    }

    /// The next method frame (heartbeats from the broker are skipped).
    async fn method(&mut self) -> (u16, Method) {
        loop {
            match self.frame().await {
                Some(Frame::Method { channel, method }) => return (channel, method),
                Some(Frame::Heartbeat) => continue,
                other => panic!("expected a method frame, got {other:?}"),
            }
        }
    }

    /// Everything the broker sends until it closes the socket (EOF or
    /// reset both count as closed).
    async fn read_until_closed(&mut self) -> Vec<u8> {
        let mut all = self.buf.split().to_vec();
        loop {
            let mut chunk = [0u8; 4096];
            match tmo!(self.sock.read(&mut chunk)) {
                Ok(0) => return all,
                Ok(n) => all.extend_from_slice(&chunk[..n]),
                Err(e) if e.kind() == std::io::ErrorKind::ConnectionReset => return all,
                Err(e) => panic!("read failed: {e}"),
            }
        }
    }

    /// Asserts the broker closes the socket without sending anything more.
    async fn assert_closed(&mut self) {
        let rest = self.read_until_closed().await;
        assert!(
            rest.is_empty(),
            "nothing should follow the close, got {rest:?}"
        );
    }

    /// Protocol header, then connection.start → start-ok (PLAIN with
    /// `response`), and connection.tune if the broker sends it.
    async fn login(b: &TestBroker, response: &'static [u8], caps: bool) -> (Raw, ConnectionStart) {
        let mut raw = Raw::connect(b).await;
        raw.send(PROTOCOL_HEADER).await;
        let start = match raw.method().await {
            (0, Method::ConnectionStart(s)) => s,
            other => panic!("expected connection.start, got {other:?}"),
        };
        let mut props = FieldTable::new();
        props.insert(
            ShortStr::from_static("product"),
            FieldValue::string("leveret-tests raw"),
        );
        if caps {
            let mut c = FieldTable::new();
            c.insert(
                ShortStr::from_static("authentication_failure_close"),
                FieldValue::Bool(true),
            );
            props.insert(ShortStr::from_static("capabilities"), FieldValue::Table(c));
        }
        raw.send_method(
            0,
            ConnectionStartOk {
                client_properties: props,
                mechanism: ShortStr::from_static("PLAIN"),
                response: Bytes::from_static(response),
                locale: ShortStr::from_static("en_US"),
            },
        )
        .await;
        (raw, start)
    }

    /// A whole handshake: PLAIN "\0guest\0guest", tune-ok echoing the
    /// broker's channel_max and frame_max with heartbeats off, open "/".
    async fn handshake(b: &TestBroker) -> (Raw, Greeting) {
        let (mut raw, start) = Raw::login(b, b"\0guest\0guest", true).await;
        let tune = match raw.method().await {
            (0, Method::ConnectionTune(t)) => t,
            other => panic!("expected connection.tune, got {other:?}"),
        };
        raw.frame_max = tune.frame_max;
        raw.send_method(
            0,
            ConnectionTuneOk {
                channel_max: tune.channel_max,
                frame_max: tune.frame_max,
                heartbeat: 0,
            },
        )
        .await;
        raw.send_method(
            0,
            ConnectionOpen {
                virtual_host: ShortStr::from_static("/"),
                ..Default::default()
            },
        )
        .await;
        match raw.method().await {
            (0, Method::ConnectionOpenOk(_)) => {}
            other => panic!("expected connection.open-ok, got {other:?}"),
        }
        (raw, Greeting { start, tune })
    }

    /// A handshake plus channel 1 opened.
    async fn open(b: &TestBroker) -> Raw {
        let (mut raw, _) = Raw::handshake(b).await;
        raw.open_channel(1).await;
        raw
    }

    async fn open_channel(&mut self, channel: u16) {
        self.send_method(channel, ChannelOpen::default()).await;
        match self.method().await {
            (c, Method::ChannelOpenOk(_)) if c == channel => {}
            other => panic!("expected channel.open-ok on {channel}, got {other:?}"),
        }
    }

    /// Closes `channel` (reply 200) and expects its close-ok.
    async fn close_channel(&mut self, channel: u16) {
        let close = ChannelClose {
            reply_code: 200,
            ..Default::default()
        };
        self.send_method(channel, close).await;
        match self.method().await {
            (c, Method::ChannelCloseOk(_)) if c == channel => {}
            other => panic!("expected channel.close-ok on {channel}, got {other:?}"),
        }
    }

    /// Expects connection.close with `code`, a text starting with `prefix`
    /// and the given class and method ids; answers close-ok and expects the
    /// socket to be closed.
    async fn expect_close(&mut self, code: u16, prefix: &str, class_method: (u16, u16)) {
        self.expect_close_frame(code, prefix, class_method).await;
        self.send_method(0, ConnectionCloseOk::default()).await;
        self.assert_closed().await;
    }

    async fn expect_close_frame(
        &mut self,
        code: u16,
        prefix: &str,
        class_method: (u16, u16),
    ) -> ConnectionClose {
        let close = match self.frame().await {
            Some(Frame::Method {
                channel: 0,
                method: Method::ConnectionClose(c),
            }) => c,
            other => panic!("expected connection.close {code}, got {other:?}"),
        };
        let text = close.reply_text.to_string_lossy().into_owned();
        assert_eq!(close.reply_code, code, "reply code (text {text:?})");
        assert_text_prefix(&text, prefix);
        assert_eq!(
            (close.class_id, close.method_id),
            class_method,
            "class and method ids in connection.close (text {text:?})"
        );
        close
    }
}

fn method_bytes(channel: u16, m: impl Into<Method>) -> Vec<u8> {
    let mut buf = BytesMut::new();
    encode_method(channel, &m.into(), &mut buf);
    buf.to_vec()
}

fn declare(name: &'static str) -> QueueDeclare {
    QueueDeclare {
        queue: ShortStr::from_static(name),
        ..Default::default()
    }
}

/// After an error on one connection, the broker still serves new ones.
async fn assert_broker_alive(b: &TestBroker) {
    let (mut raw, _) = Raw::handshake(b).await;
    raw.open_channel(1).await;
    raw.send_method(
        1,
        QueueDeclare {
            exclusive: true,
            ..Default::default()
        },
    )
    .await;
    match raw.method().await {
        (1, Method::QueueDeclareOk(ok)) => {
            assert!(ok.queue.to_string_lossy().starts_with("amq.gen-"))
        }
        other => panic!("expected queue.declare-ok, got {other:?}"),
    }
    raw.send_method(
        0,
        ConnectionClose {
            reply_code: 200,
            reply_text: ShortStr::from_static("bye"),
            ..Default::default()
        },
    )
    .await;
    loop {
        match raw.frame().await {
            Some(Frame::Method {
                channel: 0,
                method: Method::ConnectionCloseOk(_),
            }) => break,
            Some(_) => continue,
            None => panic!("socket closed before connection.close-ok"),
        }
    }
}

#[both_runtimes]
async fn wrong_protocol_headers_get_the_091_header_back_and_the_socket_closed() {
    let b = broker().await;
    // Note: RabbitMQ still speaks the legacy "AMQP 1 1 0 9" (0-9) and
    // "AMQP 1 1 8 0" (0-8) headers, answering with connection.start, so
    // those are not used as "wrong" headers here.
    let wrong: [&[u8]; 3] = [
        b"AMQP\x00\x00\x0a\x00",
        b"AMQP\x00\x00\x09\x02",
        b"GET / HTTP/1.1\r\nHost: x\r\n\r\n",
    ];
    for header in wrong {
        let mut raw = Raw::connect(&b).await;
        raw.send(header).await;
        let got = raw.read_until_closed().await;
        assert_eq!(got, b"AMQP\x00\x00\x09\x01", "answer to header {header:?}");
    }
    assert_broker_alive(&b).await;
}

#[both_runtimes]
async fn connection_start_and_tune_match_rabbitmq() {
    let b = broker().await;
    let (mut raw, greeting) = Raw::handshake(&b).await;
    let start = greeting.start;
    assert_eq!((start.version_major, start.version_minor), (0, 9));
    let mechanisms = String::from_utf8_lossy(&start.mechanisms).into_owned();
    assert!(
        mechanisms.split(' ').any(|m| m == "PLAIN"),
        "mechanisms {mechanisms:?} include PLAIN"
    );
    assert_eq!(&start.locales[..], b"en_US");
    let caps = match start.server_properties.get("capabilities") {
        Some(FieldValue::Table(t)) => t.clone(),
        other => panic!("server_properties.capabilities should be a table, got {other:?}"),
    };
    for cap in [
        "publisher_confirms",
        "exchange_exchange_bindings",
        "basic.nack",
        "consumer_cancel_notify",
        "per_consumer_qos",
        "authentication_failure_close",
    ] {
        assert_eq!(
            caps.get(cap),
            Some(&FieldValue::Bool(true)),
            "capability {cap}"
        );
    }
    // RabbitMQ's defaults: channel_max 2047, frame_max 128 KiB, heartbeat 60 s.
    assert_eq!(greeting.tune.channel_max, 2047);
    assert_eq!(greeting.tune.frame_max, 131_072);
    assert_eq!(greeting.tune.heartbeat, 60);
    // A heartbeat from the client is accepted silently.
    let mut hb = BytesMut::new();
    Frame::Heartbeat.encode(&mut hb);
    raw.send(&hb).await;
    raw.open_channel(1).await;
}

#[both_runtimes]
async fn clean_connection_close_gets_close_ok() {
    let b = broker().await;
    let (mut raw, _) = Raw::handshake(&b).await;
    raw.open_channel(1).await;
    raw.send_method(
        0,
        ConnectionClose {
            reply_code: 200,
            reply_text: ShortStr::from_static("Goodbye"),
            ..Default::default()
        },
    )
    .await;
    match raw.method().await {
        (0, Method::ConnectionCloseOk(_)) => {}
        other => panic!("expected connection.close-ok, got {other:?}"),
    }
    // Note: RabbitMQ leaves closing the socket to the client after
    // close-ok; either way nothing more may arrive.
    let mut rest = [0u8; 64];
    if let Ok(Ok(n)) = tokio::time::timeout(QUIET, raw.sock.read(&mut rest)).await {
        assert_eq!(n, 0, "nothing may follow close-ok: {:?}", &rest[..n]);
    }
}

#[both_runtimes]
async fn channel_close_gets_close_ok_and_the_channel_number_can_be_reused() {
    let b = broker().await;
    let (mut raw, _) = Raw::handshake(&b).await;
    raw.open_channel(1).await;
    raw.send_method(
        1,
        ChannelClose {
            reply_code: 200,
            reply_text: ShortStr::from_static("done"),
            ..Default::default()
        },
    )
    .await;
    match raw.method().await {
        (1, Method::ChannelCloseOk(_)) => {}
        other => panic!("expected channel.close-ok, got {other:?}"),
    }
    raw.open_channel(1).await;
}

/// A client that acks while it closes its channel (lavinmqperf's consumer
/// does, at the end of a run) sends methods behind its `channel.close`.
/// RabbitMQ 3.10 discards those that arrive with the close (its channel
/// ignores them until the close handshake ends): close-ok, no error, and
/// the discarded declare has no effect.
#[both_runtimes]
async fn methods_sent_with_a_channel_close_are_discarded() {
    let b = broker().await;
    let (mut raw, _) = Raw::handshake(&b).await;
    raw.open_channel(1).await;
    let mut burst = method_bytes(
        1,
        ChannelClose {
            reply_code: 200,
            ..Default::default()
        },
    );
    burst.extend(method_bytes(
        1,
        BasicAck {
            delivery_tag: 1,
            multiple: false,
        },
    ));
    burst.extend(method_bytes(1, declare("discarded-behind-close")));
    raw.send(&burst).await;
    match raw.method().await {
        (1, Method::ChannelCloseOk(_)) => {}
        other => panic!("expected channel.close-ok, got {other:?}"),
    }
    raw.open_channel(1).await;
    raw.send_method(
        1,
        QueueDeclare {
            passive: true,
            ..declare("discarded-behind-close")
        },
    )
    .await;
    match raw.method().await {
        (1, Method::ChannelClose(close)) => assert_eq!(close.reply_code, 404),
        other => panic!("expected channel.close 404 for the discarded declare, got {other:?}"),
    }
}

/// Once close-ok is sent the channel is gone: a method that arrives after
/// it is on an unopened channel, 504 as with RabbitMQ 3.10.
#[both_runtimes]
async fn a_method_after_channel_close_ok_gets_504() {
    let b = broker().await;
    let (mut raw, _) = Raw::handshake(&b).await;
    raw.open_channel(1).await;
    raw.close_channel(1).await;
    raw.send_method(
        1,
        BasicAck {
            delivery_tag: 1,
            multiple: false,
        },
    )
    .await;
    raw.expect_close(504, "CHANNEL_ERROR", (60, 80)).await;
    assert_broker_alive(&b).await;
}

#[both_runtimes]
async fn oversize_frame_gets_501_frame_error() {
    let b = broker().await;
    let mut raw = Raw::open(&b).await;
    // Only the 7-byte frame header: the declared size alone must be
    // refused (RabbitMQ: "FRAME_ERROR - type 3, all octets = <<>>:
    // {frame_too_large,131073,131064}").
    // Note: RabbitMQ checks the header with an 8-byte allowance
    // (FRAME_SIZE_FUDGE): a declared payload of up to frame_max bytes is
    // not refused from the header, so this uses frame_max + 1.
    let mut buf = BytesMut::new();
    buf.put_u8(3);
    buf.put_u16(1);
    buf.put_u32(raw.frame_max + 1);
    raw.send(&buf).await;
    raw.expect_close(501, "FRAME_ERROR", (0, 0)).await;
    assert_broker_alive(&b).await;
}

#[both_runtimes]
async fn an_oversize_frame_sent_whole_still_gets_its_close() {
    let b = broker().await;
    let mut raw = Raw::open(&b).await;
    // The whole oversize frame in one write, more than the socket buffers
    // hold: the broker must read it to the end after refusing it, or its
    // close resets the connection, the write fails and the client never
    // reads the 501 (seen in conformance as a broken pipe half the time).
    let mut buf = BytesMut::new();
    buf.put_u8(3);
    buf.put_u16(1);
    buf.put_u32(raw.frame_max + 1);
    buf.resize(buf.len() + (16 << 20), 0);
    raw.send(&buf).await;
    raw.expect_close(501, "FRAME_ERROR", (0, 0)).await;
    assert_broker_alive(&b).await;
}

#[both_runtimes]
async fn body_frame_without_header_gets_505_unexpected_frame() {
    let b = broker().await;
    let mut raw = Raw::open(&b).await;
    let mut buf = BytesMut::new();
    Frame::Body {
        channel: 1,
        payload: Bytes::from_static(b"hello"),
    }
    .encode(&mut buf);
    raw.send(&buf).await;
    // RabbitMQ: "UNEXPECTED_FRAME - expected method frame, got non method
    // frame instead".
    raw.expect_close(505, "UNEXPECTED_FRAME", (0, 0)).await;
    assert_broker_alive(&b).await;
}

#[both_runtimes]
async fn content_header_without_method_gets_505_unexpected_frame() {
    let b = broker().await;
    let mut raw = Raw::open(&b).await;
    let mut buf = BytesMut::new();
    encode_content(1, 60, b"\x00\x00", b"abc", 0, &mut buf);
    raw.send(&buf).await;
    raw.expect_close(505, "UNEXPECTED_FRAME", (0, 0)).await;
    assert_broker_alive(&b).await;
}

#[both_runtimes]
async fn method_instead_of_content_header_gets_505_with_publish_ids() {
    let b = broker().await;
    let mut raw = Raw::open(&b).await;
    let mut bytes = method_bytes(
        1,
        BasicPublish {
            routing_key: ShortStr::from_static("nowhere"),
            ..Default::default()
        },
    );
    bytes.extend(method_bytes(1, BasicQos::default()));
    raw.send(&bytes).await;
    // RabbitMQ: "UNEXPECTED_FRAME - expected content header for class 60,
    // got non content header frame instead", reported against basic.publish.
    raw.expect_close(505, "UNEXPECTED_FRAME", (60, 40)).await;
    assert_broker_alive(&b).await;
}

#[both_runtimes]
async fn method_on_unopened_channel_gets_504_channel_error() {
    let b = broker().await;
    let (mut raw, _) = Raw::handshake(&b).await;
    raw.send_method(5, declare("never-declared")).await;
    // RabbitMQ: "CHANNEL_ERROR - expected 'channel.open'", class 50 method 10.
    raw.expect_close(504, "CHANNEL_ERROR", (50, 10)).await;
    assert_broker_alive(&b).await;
}

#[both_runtimes]
async fn content_frames_on_unopened_channel_get_505() {
    let b = broker().await;
    let (mut raw, _) = Raw::handshake(&b).await;
    let mut buf = BytesMut::new();
    encode_content(3, 60, b"\x00\x00", b"abc", 0, &mut buf);
    raw.send(&buf).await;
    // Note: 505 (not 504): RabbitMQ complains about the frame type first.
    raw.expect_close(505, "UNEXPECTED_FRAME", (0, 0)).await;
    assert_broker_alive(&b).await;
}

#[both_runtimes]
async fn channel_close_on_unopened_channel_gets_504() {
    let b = broker().await;
    let (mut raw, _) = Raw::handshake(&b).await;
    raw.send_method(
        7,
        ChannelClose {
            reply_code: 200,
            ..Default::default()
        },
    )
    .await;
    raw.expect_close(504, "CHANNEL_ERROR", (20, 40)).await;
    assert_broker_alive(&b).await;
}

#[both_runtimes]
async fn second_channel_open_gets_504() {
    let b = broker().await;
    let mut raw = Raw::open(&b).await;
    raw.send_method(1, ChannelOpen::default()).await;
    // RabbitMQ: "CHANNEL_ERROR - second 'channel.open' seen".
    raw.expect_close(504, "CHANNEL_ERROR", (20, 10)).await;
    assert_broker_alive(&b).await;
}

#[both_runtimes]
async fn channel_method_on_channel_zero_gets_504() {
    let b = broker().await;
    let (mut raw, _) = Raw::handshake(&b).await;
    raw.send_method(0, declare("on-channel-zero")).await;
    // RabbitMQ: "CHANNEL_ERROR - unexpected method in connection state running".
    raw.expect_close(504, "CHANNEL_ERROR", (50, 10)).await;
    assert_broker_alive(&b).await;
}

#[both_runtimes]
async fn second_connection_open_gets_504() {
    let b = broker().await;
    let (mut raw, _) = Raw::handshake(&b).await;
    raw.send_method(
        0,
        ConnectionOpen {
            virtual_host: ShortStr::from_static("/"),
            ..Default::default()
        },
    )
    .await;
    raw.expect_close(504, "CHANNEL_ERROR", (10, 40)).await;
    assert_broker_alive(&b).await;
}

#[both_runtimes]
async fn garbage_gets_501_and_the_socket_closed() {
    let b = broker().await;
    let (mut raw, _) = Raw::handshake(&b).await;
    // 't' is read as a frame type and "s is" as a huge size: RabbitMQ says
    // "FRAME_ERROR - type 116, all octets = <<>>: {frame_too_large,1931503987,131064}"
    // and, since the rest of the stream is unparsable, closes the socket
    // about 3 s later without waiting for close-ok.
    raw.send(b"this is not an AMQP frame at all, just garbage!!")
        .await;
    raw.expect_close_frame(501, "FRAME_ERROR", (0, 0)).await;
    raw.assert_closed().await;
    assert_broker_alive(&b).await;
}

#[both_runtimes]
async fn bad_frame_end_gets_501() {
    let b = broker().await;
    let mut raw = Raw::open(&b).await;
    let mut bytes = method_bytes(1, declare("bad-frame-end"));
    *bytes.last_mut().expect("frame") = 0xCF;
    raw.send(&bytes).await;
    // RabbitMQ: "FRAME_ERROR - type 1, all octets = <<...>>: {invalid_frame_end_marker, 207}".
    raw.expect_close_frame(501, "FRAME_ERROR", (0, 0)).await;
    raw.assert_closed().await;
    assert_broker_alive(&b).await;
}

#[both_runtimes]
async fn unknown_frame_type_gets_501() {
    let b = broker().await;
    let mut raw = Raw::open(&b).await;
    raw.send(&[9, 0, 1, 0, 0, 0, 0, 0xCE]).await;
    // RabbitMQ: "FRAME_ERROR - type 9, all octets = <<>>: unknown_frame".
    raw.expect_close(501, "FRAME_ERROR", (0, 0)).await;
    assert_broker_alive(&b).await;
}

#[both_runtimes]
async fn heartbeat_on_a_channel_gets_505() {
    let b = broker().await;
    let mut raw = Raw::open(&b).await;
    raw.send(&[8, 0, 1, 0, 0, 0, 0, 0xCE]).await;
    // Note: 505 UNEXPECTED_FRAME, not 501: RabbitMQ says
    // "UNEXPECTED_FRAME - type 8, all octets = <<>>".
    raw.expect_close(505, "UNEXPECTED_FRAME", (0, 0)).await;
    assert_broker_alive(&b).await;
}

#[both_runtimes]
async fn truncated_method_arguments_get_501_with_method_ids() {
    let b = broker().await;
    let mut raw = Raw::open(&b).await;
    // queue.declare whose payload stops after one byte of arguments.
    raw.send(&[1, 0, 1, 0, 0, 0, 5, 0, 50, 0, 10, 0, 0xCE])
        .await;
    // Note: RabbitMQ answers 501 FRAME_ERROR ("FRAME_ERROR - cannot decode
    // <<0>>"), not 502 SYNTAX_ERROR, and names queue.declare.
    raw.expect_close(501, "FRAME_ERROR", (50, 10)).await;
    assert_broker_alive(&b).await;
}

#[both_runtimes]
async fn trailing_bytes_after_method_arguments_get_501() {
    let b = broker().await;
    let mut raw = Raw::open(&b).await;
    let mut bytes = method_bytes(1, declare("trailing"));
    let end = bytes.len() - 1;
    bytes.splice(end..end, [0u8, 0u8]);
    let size = u32::from_be_bytes([bytes[3], bytes[4], bytes[5], bytes[6]]) + 2;
    bytes[3..7].copy_from_slice(&size.to_be_bytes());
    raw.send(&bytes).await;
    raw.expect_close(501, "FRAME_ERROR", (50, 10)).await;
    assert_broker_alive(&b).await;
}

#[both_runtimes]
async fn unknown_method_ends_the_connection() {
    let b = broker().await;
    let mut raw = Raw::open(&b).await;
    // basic method id 99 does not exist.
    raw.send(&[1, 0, 1, 0, 0, 0, 4, 0, 60, 0, 99, 0xCE]).await;
    // Note: RabbitMQ 3.10 sends no connection.close here at all: it drops
    // the socket at once. A broker that says why first (a hard error,
    // >= 500) is accepted too.
    let rest = raw.read_until_closed().await;
    if !rest.is_empty() {
        let mut buf = BytesMut::from(&rest[..]);
        match decode_frame(&mut buf, 0) {
            Ok(Some(Frame::Method {
                channel: 0,
                method: Method::ConnectionClose(c),
            })) => assert!(c.reply_code >= 500, "hard error expected: {c:?}"),
            other => panic!("only a connection.close may come back, got {other:?}"),
        }
    }
    assert_broker_alive(&b).await;
}

#[both_runtimes]
async fn bad_password_gets_403_when_the_client_asks_for_it() {
    let b = broker().await;
    let (mut raw, _) = Raw::login(&b, b"\0guest\0wrong-password", true).await;
    // RabbitMQ: "ACCESS_REFUSED - Login was refused using authentication
    // mechanism PLAIN. For details see the broker logfile."
    raw.expect_close(403, "ACCESS_REFUSED", (0, 0)).await;
    assert_broker_alive(&b).await;
}

#[both_runtimes]
async fn bad_password_without_the_capability_just_closes_the_socket() {
    let b = broker().await;
    let (mut raw, _) = Raw::login(&b, b"\0guest\0wrong-password", false).await;
    // Note: without the client capability authentication_failure_close,
    // RabbitMQ sends no connection.close: the socket is closed (after ~3 s).
    // That is the capability's point: a client that did not ask for it may
    // not expect a connection.close before connection.open-ok.
    raw.assert_closed().await;
    assert_broker_alive(&b).await;
}

#[both_runtimes]
async fn unknown_vhost_gets_530_not_allowed() {
    let b = broker().await;
    let (mut raw, _) = Raw::login(&b, b"\0guest\0guest", true).await;
    let tune = match raw.method().await {
        (0, Method::ConnectionTune(t)) => t,
        other => panic!("expected connection.tune, got {other:?}"),
    };
    raw.send_method(
        0,
        ConnectionTuneOk {
            channel_max: tune.channel_max,
            frame_max: tune.frame_max,
            heartbeat: 0,
        },
    )
    .await;
    raw.send_method(
        0,
        ConnectionOpen {
            virtual_host: ShortStr::from_static("no-such-vhost"),
            ..Default::default()
        },
    )
    .await;
    // RabbitMQ: "NOT_ALLOWED - vhost no-such-vhost not found" (530, not
    // 402 INVALID_PATH), against connection.open.
    raw.expect_close(530, "NOT_ALLOWED", (10, 40)).await;
    assert_broker_alive(&b).await;
}

#[both_runtimes]
async fn content_split_across_many_body_frames_is_reassembled() {
    let b = broker().await;
    let mut raw = Raw::open(&b).await;
    raw.send_method(
        1,
        QueueDeclare {
            exclusive: true,
            ..Default::default()
        },
    )
    .await;
    let queue = match raw.method().await {
        (1, Method::QueueDeclareOk(ok)) => ok.queue,
        other => panic!("expected queue.declare-ok, got {other:?}"),
    };
    let body: Vec<u8> = (0..10_000u32).map(|i| (i % 251) as u8).collect();
    let mut buf = BytesMut::new();
    encode_method(
        1,
        &BasicPublish {
            routing_key: queue.clone(),
            ..Default::default()
        }
        .into(),
        &mut buf,
    );
    // Deliberately small body frames (1000 bytes), well under frame_max.
    encode_content(1, 60, b"\x00\x00", &body, 1008, &mut buf);
    raw.send(&buf).await;
    raw.send_method(
        1,
        leveret_protocol::BasicGet {
            queue,
            no_ack: true,
            ..Default::default()
        },
    )
    .await;
    match raw.method().await {
        (1, Method::BasicGetOk(ok)) => assert_eq!(ok.message_count, 0),
        other => panic!("expected basic.get-ok, got {other:?}"),
    }
    let size = match raw.frame().await {
        Some(Frame::Header { channel: 1, header }) => header.body_size,
        other => panic!("expected a content header, got {other:?}"),
    };
    assert_eq!(size, body.len() as u64);
    let mut got = Vec::new();
    while got.len() < body.len() {
        match raw.frame().await {
            Some(Frame::Body {
                channel: 1,
                payload,
            }) => got.extend_from_slice(&payload),
            other => panic!("expected a body frame, got {other:?}"),
        }
    }
    assert_eq!(got, body);
    // Closing the channel by hand still works afterwards.
    raw.close_channel(1).await;
}

#[both_runtimes]
async fn channel_error_then_close_ok_frees_the_channel_number() {
    let b = broker().await;
    let mut raw = Raw::open(&b).await;
    raw.send_method(
        1,
        QueueDeclare {
            queue: ShortStr::try_from(unique("missing").as_str()).expect("short"),
            passive: true,
            ..Default::default()
        },
    )
    .await;
    match raw.method().await {
        (1, Method::ChannelClose(c)) => {
            assert_eq!(c.reply_code, 404);
            assert_text_prefix(&c.reply_text.to_string_lossy(), "NOT_FOUND");
            assert_eq!((c.class_id, c.method_id), (50, 10));
        }
        other => panic!("expected channel.close 404, got {other:?}"),
    }
    // Until the client's close-ok, anything else on the channel is
    // discarded (no second error).
    raw.send_method(
        1,
        QueueDeclare {
            queue: ShortStr::try_from(unique("ignored-while-closing").as_str()).expect("short"),
            passive: true,
            ..Default::default()
        },
    )
    .await;
    raw.send_method(1, leveret_protocol::ChannelCloseOk::default())
        .await;
    raw.open_channel(1).await;
    raw.send_method(
        1,
        QueueDeclare {
            exclusive: true,
            ..Default::default()
        },
    )
    .await;
    match raw.method().await {
        (1, Method::QueueDeclareOk(ok)) => assert_eq!(ok.message_count, 0),
        other => panic!("expected queue.declare-ok, got {other:?}"),
    }
}

/// Logs in and answers tune with the given values, then sends
/// connection.open "/".
async fn tuned(b: &TestBroker, channel_max: u16, frame_max: u32, heartbeat: u16) -> Raw {
    let (mut raw, _) = Raw::login(b, b"\0guest\0guest", true).await;
    match raw.method().await {
        (0, Method::ConnectionTune(_)) => {}
        other => panic!("expected connection.tune, got {other:?}"),
    }
    raw.frame_max = frame_max;
    raw.send_method(
        0,
        ConnectionTuneOk {
            channel_max,
            frame_max,
            heartbeat,
        },
    )
    .await;
    raw.send_method(
        0,
        ConnectionOpen {
            virtual_host: ShortStr::from_static("/"),
            ..Default::default()
        },
    )
    .await;
    raw
}

async fn refused_tune(b: &TestBroker, channel_max: u16, frame_max: u32) {
    let mut raw = tuned(b, channel_max, frame_max, 0).await;
    let rest = raw.read_until_closed().await;
    if !rest.is_empty() {
        let mut buf = BytesMut::from(&rest[..]);
        match decode_frame(&mut buf, 0) {
            Ok(Some(Frame::Method {
                channel: 0,
                method: Method::ConnectionClose(c),
            })) => assert!(c.reply_code >= 500, "{c:?}"),
            other => {
                panic!("tune-ok channel_max {channel_max} frame_max {frame_max}: got {other:?}")
            }
        }
    }
}

#[both_runtimes]
async fn tune_ok_outside_the_servers_limits_is_refused() {
    let b = broker().await;
    // frame_max below the 4096 minimum, above the server's 131072, 0
    // ("unlimited") when the server has a limit, and channel_max above the
    // server's 2047. Note: RabbitMQ sends no connection.close before
    // connection.open-ok: it just closes the socket (after ~3 s). A
    // connection.close with a hard error is accepted too; open-ok is not.
    tokio::join!(
        refused_tune(&b, 2047, 1000),
        refused_tune(&b, 2047, 200_000),
        refused_tune(&b, 2047, 0),
        refused_tune(&b, 3000, 131_072),
    );
    assert_broker_alive(&b).await;
}

#[both_runtimes]
async fn the_client_frame_max_is_honoured_both_ways() {
    let b = broker().await;
    let mut raw = tuned(&b, 2047, 4096, 0).await;
    match raw.method().await {
        (0, Method::ConnectionOpenOk(_)) => {}
        other => panic!("expected connection.open-ok, got {other:?}"),
    }
    raw.open_channel(1).await;
    raw.send_method(
        1,
        QueueDeclare {
            exclusive: true,
            ..Default::default()
        },
    )
    .await;
    let queue = match raw.method().await {
        (1, Method::QueueDeclareOk(ok)) => ok.queue,
        other => panic!("expected queue.declare-ok, got {other:?}"),
    };
    let body: Vec<u8> = (0..10_000u32).map(|i| (i % 253) as u8).collect();
    let mut buf = BytesMut::new();
    encode_method(
        1,
        &BasicPublish {
            routing_key: queue.clone(),
            ..Default::default()
        }
        .into(),
        &mut buf,
    );
    encode_content(1, 60, b"\x00\x00", &body, 4096, &mut buf);
    raw.send(&buf).await;
    raw.send_method(
        1,
        leveret_protocol::BasicGet {
            queue,
            no_ack: true,
            ..Default::default()
        },
    )
    .await;
    match raw.method().await {
        (1, Method::BasicGetOk(_)) => {}
        other => panic!("expected basic.get-ok, got {other:?}"),
    }
    match raw.frame().await {
        Some(Frame::Header { header, .. }) => assert_eq!(header.body_size, 10_000),
        other => panic!("expected a content header, got {other:?}"),
    }
    // The broker splits the body to fit 4096-byte frames (4088-byte payloads).
    let mut got = Vec::new();
    let mut frames = 0;
    while got.len() < body.len() {
        match raw.frame().await {
            Some(Frame::Body { payload, .. }) => {
                assert!(payload.len() <= 4096 - 8, "body frame of {}", payload.len());
                frames += 1;
                got.extend_from_slice(&payload);
            }
            other => panic!("expected a body frame, got {other:?}"),
        }
    }
    assert_eq!(got, body);
    assert!(frames >= 3);
    // And a client frame over the negotiated 4096 is a frame error.
    let mut buf = BytesMut::new();
    buf.put_u8(3);
    buf.put_u16(1);
    buf.put_u32(5000);
    raw.send(&buf).await;
    raw.expect_close(501, "FRAME_ERROR", (0, 0)).await;
    assert_broker_alive(&b).await;
}

#[both_runtimes]
async fn heartbeats_are_sent_and_a_silent_client_is_dropped() {
    let b = broker().await;
    let mut raw = tuned(&b, 2047, 131_072, 1).await;
    match raw.method().await {
        (0, Method::ConnectionOpenOk(_)) => {}
        other => panic!("expected connection.open-ok, got {other:?}"),
    }
    // RabbitMQ sends a heartbeat every half interval (500 ms here) and,
    // when the client sends nothing, closes the socket after about 3 s,
    // without a connection.close.
    let mut heartbeats = 0;
    loop {
        match raw.frame().await {
            Some(Frame::Heartbeat) => heartbeats += 1,
            None => break,
            Some(Frame::Method {
                channel: 0,
                method: Method::ConnectionClose(c),
            }) => {
                // Accepted too: saying why before closing.
                assert!(c.reply_code >= 500, "{c:?}");
            }
            Some(other) => panic!("unexpected frame {other:?}"),
        }
    }
    assert!(heartbeats >= 1, "at least one heartbeat before the close");
    assert_broker_alive(&b).await;
}

#[both_runtimes]
async fn client_heartbeats_keep_a_quiet_connection_alive() {
    let b = broker().await;
    let mut raw = tuned(&b, 2047, 131_072, 1).await;
    match raw.method().await {
        (0, Method::ConnectionOpenOk(_)) => {}
        other => panic!("expected connection.open-ok, got {other:?}"),
    }
    let mut hb = BytesMut::new();
    Frame::Heartbeat.encode(&mut hb);
    // Beat every 250 ms for 4 s: longer than the ~3 s after which a silent
    // client is dropped (the cadence is the protocol, not a wait).
    let mut tick = tokio::time::interval(std::time::Duration::from_millis(250));
    for _ in 0..16 {
        tick.tick().await;
        raw.send(&hb).await;
    }
    raw.open_channel(1).await;
}

/// Messages, of [`STALL_BODY`] bytes each, in the queue a stalled consumer
/// consumes: more than the socket buffers and its connection's outbox
/// (512 items) hold.
const STALL_MESSAGES: usize = 1000;
const STALL_BODY: usize = 64 * 1024;

/// The id of the one connection open on `b`.
fn only_connection(b: &TestBroker) -> u64 {
    let listed = b.admin().expect("in-process broker").connections();
    assert_eq!(listed.len(), 1, "one connection open");
    listed[0].id
}

/// Waits until `b` has no connection open (each ends within a few close
/// timeouts once it is done; the hang limit is far above that).
async fn no_connection_left(b: &TestBroker) {
    let admin = b.admin().expect("in-process broker");
    tmo!(async {
        while !admin.connections().is_empty() {
            tokio::time::sleep(std::time::Duration::from_millis(50)).await;
        }
    });
}

/// Declares `queue` and publishes [`STALL_MESSAGES`] into it, on a
/// connection of its own (closed after); then a consumer on channel 1 of
/// a new connection (no prefetch limit, acks on) that reads nothing more:
/// the broker's writes to it stall, its outbox fills, and the queue keeps
/// the rest. Returns that consumer once the queue has stopped
/// dispatching to it.
async fn stalled_consumer(b: &TestBroker, queue: &'static str) -> Raw {
    let mut publisher = Raw::open(b).await;
    publisher.send_method(1, declare(queue)).await;
    match publisher.method().await {
        (1, Method::QueueDeclareOk(_)) => {}
        other => panic!("expected queue.declare-ok, got {other:?}"),
    }
    let body = vec![7u8; STALL_BODY];
    for _ in 0..STALL_MESSAGES {
        let mut buf = BytesMut::new();
        let publish = BasicPublish {
            routing_key: ShortStr::from_static(queue),
            ..Default::default()
        };
        encode_method(1, &publish.into(), &mut buf);
        encode_content(1, 60, b"\x00\x00", &body, publisher.frame_max, &mut buf);
        publisher.send(&buf).await;
    }
    let admin = b.admin().expect("in-process broker");
    let ready = || {
        admin
            .queue("/", queue)
            .expect("declared")
            .info()
            .messages_ready
    };
    tmo!(async {
        while ready() < STALL_MESSAGES as u64 {
            tokio::time::sleep(std::time::Duration::from_millis(20)).await;
        }
    });
    publisher.send_method(0, ConnectionClose::default()).await;
    match publisher.method().await {
        (0, Method::ConnectionCloseOk(_)) => {}
        other => panic!("expected connection.close-ok, got {other:?}"),
    }
    drop(publisher);
    no_connection_left(b).await;
    let mut consumer = Raw::open(b).await;
    let consume = leveret_protocol::BasicConsume {
        queue: ShortStr::from_static(queue),
        consumer_tag: ShortStr::from_static("stalled"),
        ..Default::default()
    };
    consumer.send_method(1, consume).await;
    match consumer.method().await {
        (1, Method::BasicConsumeOk(_)) => {}
        other => panic!("expected basic.consume-ok, got {other:?}"),
    }
    // Dispatch stops for good once the outbox is full: the count of
    // messages ready no longer moves, and some are left.
    let mut last = u64::MAX;
    tmo!(async {
        loop {
            tokio::time::sleep(std::time::Duration::from_millis(300)).await;
            let now = ready();
            if now == last {
                break;
            }
            last = now;
        }
    });
    assert!(
        last > 0,
        "the consumer's outbox is full before the queue is empty"
    );
    consumer
}

/// A client that sends connection.close while its outbox is full and
/// then reads nothing is let go: the broker's close-ok waits for room
/// only as long as its own close would (it waited for ever, holding the
/// connection, its socket and the deliveries in its outbox).
#[both_runtimes]
async fn a_client_that_closes_and_reads_nothing_more_is_let_go() {
    let b = broker().await;
    let mut consumer = stalled_consumer(&b, "risk3-fix.close-and-stall").await;
    let close = ConnectionClose {
        reply_code: 200,
        reply_text: ShortStr::from_static("bye"),
        ..Default::default()
    };
    consumer.send_method(0, close).await;
    no_connection_left(&b).await;
    let admin = b.admin().expect("in-process broker");
    let queue = admin.queue("/", "risk3-fix.close-and-stall").expect("kept");
    assert_eq!(
        queue.info().messages_ready,
        STALL_MESSAGES as u64,
        "its deliveries are requeued"
    );
    drop(consumer);
}

/// A client's connection.close that crosses the broker's (a management
/// close) is answered with close-ok, as RabbitMQ answers a close it
/// receives while closing.
#[both_runtimes]
async fn a_connection_close_that_crosses_the_brokers_gets_close_ok() {
    let b = broker().await;
    let (mut raw, _) = Raw::handshake(&b).await;
    let admin = b.admin().expect("in-process broker");
    assert!(admin.close_connection(only_connection(&b), "Closed via management plugin"));
    raw.expect_close_frame(
        320,
        "CONNECTION_FORCED - Closed via management plugin",
        (0, 0),
    )
    .await;
    let close = ConnectionClose {
        reply_code: 200,
        reply_text: ShortStr::from_static("bye"),
        ..Default::default()
    };
    raw.send_method(0, close).await;
    match raw.frame().await {
        Some(Frame::Method {
            channel: 0,
            method: Method::ConnectionCloseOk(_),
        }) => {}
        other => panic!("expected connection.close-ok, got {other:?}"),
    }
    raw.assert_closed().await;
}

/// Frames a socket client sent in one write, read before a management
/// close, are all handled, as RabbitMQ handles every whole frame of its
/// current read before it sees a forced close: here a publish read with
/// a queue.declare whose declare-ok waits for room in the consumer's full
/// outbox when the close comes (the declare-ok is dropped; the publish is
/// still routed).
#[both_runtimes]
async fn frames_read_before_a_forced_close_are_handled() {
    let b = broker().await;
    let routed = "risk3-fix.routed-after-close";
    let mut declarer = Raw::open(&b).await;
    declarer.send_method(1, declare(routed)).await;
    match declarer.method().await {
        (1, Method::QueueDeclareOk(_)) => {}
        other => panic!("expected queue.declare-ok, got {other:?}"),
    }
    declarer.send_method(0, ConnectionClose::default()).await;
    match declarer.method().await {
        (0, Method::ConnectionCloseOk(_)) => {}
        other => panic!("expected connection.close-ok, got {other:?}"),
    }
    drop(declarer);
    no_connection_left(&b).await;
    let mut consumer = stalled_consumer(&b, "risk3-fix.read-then-closed").await;
    let marker = "risk3-fix.declared-before-close";
    let mut batch = method_bytes(1, declare(marker));
    let publish = BasicPublish {
        routing_key: ShortStr::from_static(routed),
        ..Default::default()
    };
    let mut content = BytesMut::new();
    encode_method(1, &publish.into(), &mut content);
    encode_content(
        1,
        60,
        b"\x00\x00",
        b"read before the close",
        4096,
        &mut content,
    );
    batch.extend_from_slice(&content);
    consumer.send(&batch).await;
    // The declare is handled (its queue exists) and its declare-ok waits
    // for room: the publish is read, not yet handled.
    let admin = b.admin().expect("in-process broker");
    tmo!(async {
        while admin.queue("/", marker).is_none() {
            tokio::time::sleep(std::time::Duration::from_millis(20)).await;
        }
    });
    assert!(admin.close_connection(only_connection(&b), "Closed via management plugin"));
    no_connection_left(&b).await;
    let routed = admin.queue("/", routed).expect("declared").info();
    assert_eq!(
        routed.messages_ready, 1,
        "the publish read before the close"
    );
    drop(consumer);
}
