//! Connections: handshake and tuning, close in both directions, refused
//! logins and vhosts, heartbeats, connection.blocked, channels.

mod common;

use common::{broker, unique, within, ScriptedPeer};
use leveret_client::protocol::{
    ChannelOpenOk, ConnectionBlocked, ConnectionClose, ConnectionCloseOk, ConnectionUnblocked,
    Frame, Method,
};
use leveret_client::{
    Connection, Error, FieldTable, FieldValue, QueueDeclareOptions, ReplyCode, ShortStr,
};
use std::time::Duration;

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn connect_negotiates_and_closes() {
    let broker = broker().await;
    let connection = broker.connect().await;
    assert!(connection.is_open());
    let tuning = connection.tuning();
    assert!(tuning.frame_max >= 4096 && tuning.frame_max <= 131_072);
    assert!(tuning.channel_max >= 1 && tuning.channel_max <= 2047);
    assert!(tuning.heartbeat <= 60);
    assert!(matches!(
        connection.server_properties().get("capabilities"),
        Some(FieldValue::Table(_))
    ));
    within("close", connection.close()).await.expect("close");
    assert!(!connection.is_open());
    assert!(matches!(connection.closed().await, Error::Closed));
    assert!(matches!(
        connection.open_channel().await,
        Err(Error::Closed)
    ));
    // A second close is harmless.
    within("close again", connection.close())
        .await
        .expect("close again");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn client_limits_win_when_smaller() {
    let broker = broker().await;
    let uri = broker.uri_with("heartbeat=7&frame_max=8192&channel_max=5");
    let connection = within("connect", Connection::connect(&uri))
        .await
        .expect("connect");
    let tuning = connection.tuning();
    assert_eq!(tuning.heartbeat, 7);
    assert_eq!(tuning.frame_max, 8192);
    assert_eq!(tuning.channel_max, 5);
    // A body much larger than frame_max goes out and comes back in pieces.
    let channel = connection.open_channel().await.expect("channel");
    let queue = common::temp_queue(&channel, "frames").await;
    let body: Vec<u8> = (0..50_000u32).map(|i| (i % 251) as u8).collect();
    let _unconfirmed = channel
        .basic_publish(
            "",
            &queue.name,
            Default::default(),
            Default::default(),
            body.clone().into(),
        )
        .await
        .expect("publish");
    let got = within("get", async {
        loop {
            if let Some(m) = channel
                .basic_get(&queue.name, Default::default())
                .await
                .expect("get")
            {
                return m;
            }
            tokio::task::yield_now().await;
        }
    })
    .await;
    assert_eq!(&got.body[..], &body[..]);
    connection.close().await.expect("close");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn channel_numbers_are_limited_by_channel_max() {
    let broker = broker().await;
    let connection = Connection::connect(&broker.uri_with("channel_max=3"))
        .await
        .expect("connect");
    let a = connection.open_channel().await.expect("1");
    let b = connection.open_channel().await.expect("2");
    let c = connection.open_channel().await.expect("3");
    let mut ids = [a.id(), b.id(), c.id()];
    ids.sort();
    assert_eq!(ids, [1, 2, 3]);
    assert!(matches!(
        connection.open_channel().await,
        Err(Error::ChannelsExhausted(3))
    ));
    within("close b", b.close()).await.expect("close b");
    let d = connection.open_channel().await.expect("reuse");
    assert_eq!(d.id(), ids[1]);
    connection.close().await.expect("close");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn channels_are_independent() {
    let broker = broker().await;
    let connection = broker.connect().await;
    let good = connection.open_channel().await.expect("channel");
    let bad = connection.open_channel().await.expect("channel");
    assert_ne!(good.id(), bad.id());
    let missing = unique("missing");
    let passive = QueueDeclareOptions {
        passive: true,
        ..Default::default()
    };
    let err = within(
        "passive declare",
        bad.queue_declare(missing.as_str(), passive, FieldTable::new()),
    )
    .await
    .expect_err("missing queue");
    assert_eq!(err.reply_code(), Some(ReplyCode::NotFound));
    assert!(!bad.is_open());
    // The other channel and the connection are fine.
    let queue = common::temp_queue(&good, "independent").await;
    assert!(good.is_open());
    assert!(connection.is_open());
    good.queue_delete(&queue.name, Default::default())
        .await
        .expect("delete");
    connection.close().await.expect("close");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn channel_close_then_calls_fail() {
    let broker = broker().await;
    let (connection, channel) = broker.channel().await;
    within("close", channel.close()).await.expect("close");
    assert!(!channel.is_open());
    assert!(matches!(channel.closed().await, Error::Closed));
    let err = channel
        .queue_declare("", Default::default(), FieldTable::new())
        .await
        .expect_err("closed channel");
    assert!(matches!(err, Error::Closed), "{err:?}");
    // Closing again is fine.
    channel.close().await.expect("close again");
    connection.close().await.expect("close");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn wrong_password_is_refused_with_403() {
    let broker = broker().await;
    let mut options = leveret_client::ConnectionOptions::from_uri(&broker.uri).expect("uri");
    options.password = "definitely-not-the-password".to_owned();
    let err = within("connect", Connection::connect_with(options))
        .await
        .expect_err("bad password");
    assert_eq!(err.reply_code(), Some(ReplyCode::AccessRefused), "{err:?}");
    assert!(matches!(err, Error::ConnectionClosed(_)));
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn unknown_vhost_is_refused() {
    let broker = broker().await;
    let mut options = leveret_client::ConnectionOptions::from_uri(&broker.uri).expect("uri");
    options.vhost = unique("no-such-vhost");
    let err = within("connect", Connection::connect_with(options))
        .await
        .expect_err("unknown vhost");
    // RabbitMQ and Leveret both answer connection.open with 530 NOT_ALLOWED.
    assert_eq!(err.reply_code(), Some(ReplyCode::NotAllowed), "{err:?}");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn connection_refused_is_an_io_error() {
    let listener = std::net::TcpListener::bind("127.0.0.1:0").expect("bind");
    let addr = listener.local_addr().expect("addr");
    drop(listener);
    let err = Connection::connect(&format!("amqp://{addr}"))
        .await
        .expect_err("nothing listens");
    assert!(matches!(err, Error::Io(_)), "{err:?}");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn connection_timeout_applies() {
    // A peer that accepts but never answers the protocol header.
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0")
        .await
        .expect("bind");
    let addr = listener.local_addr().expect("addr");
    let hold = tokio::spawn(async move { listener.accept().await });
    let uri = format!("amqp://{addr}?connection_timeout=200");
    let err = within("connect", Connection::connect(&uri))
        .await
        .expect_err("silent peer");
    assert!(matches!(err, Error::ConnectTimeout), "{err:?}");
    hold.abort();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn heartbeats_keep_an_idle_connection_alive() {
    let broker = broker().await;
    let connection = Connection::connect(&broker.uri_with("heartbeat=1"))
        .await
        .expect("connect");
    assert_eq!(connection.tuning().heartbeat, 1);
    let channel = connection.open_channel().await.expect("channel");
    // The idle time is what this test is about: three intervals without
    // traffic, longer than either side's two-interval timeout.
    tokio::time::sleep(Duration::from_millis(3_200)).await;
    assert!(connection.is_open());
    let queue = common::temp_queue(&channel, "heartbeat").await;
    channel
        .queue_delete(&queue.name, Default::default())
        .await
        .expect("still usable");
    connection.close().await.expect("close");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn client_sends_heartbeats_and_detects_a_silent_broker() {
    let peer = ScriptedPeer::bind().await;
    let (connection, mut server) = peer.connect("heartbeat=1", 1).await;
    assert_eq!(connection.tuning().heartbeat, 1);
    // The idle client sends heartbeats by itself.
    let frame = within("client heartbeat", server.frame()).await;
    assert_eq!(frame, Some(Frame::Heartbeat));
    // The broker now stays silent: two intervals later the client gives up.
    let error = within("missed heartbeats", connection.closed()).await;
    assert!(matches!(error, Error::MissedHeartbeats), "{error:?}");
    assert!(!connection.is_open());
    assert!(matches!(
        connection.open_channel().await,
        Err(Error::MissedHeartbeats)
    ));
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn blocked_and_unblocked_are_exposed() {
    let peer = ScriptedPeer::bind().await;
    let (connection, mut server) = peer.connect("heartbeat=0", 0).await;
    let mut blocked = connection.blocked();
    assert_eq!(*blocked.borrow_and_update(), None);
    server
        .send(
            0,
            ConnectionBlocked {
                reason: ShortStr::from_static("low on memory"),
            },
        )
        .await;
    within("blocked", blocked.changed()).await.expect("blocked");
    assert_eq!(
        blocked.borrow_and_update().as_deref(),
        Some("low on memory")
    );
    server.send(0, ConnectionUnblocked {}).await;
    within("unblocked", blocked.changed())
        .await
        .expect("unblocked");
    assert_eq!(*blocked.borrow_and_update(), None);
    drop(server);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn broker_initiated_close_fails_everything_with_its_reason() {
    let peer = ScriptedPeer::bind().await;
    let (connection, mut server) = peer.connect("heartbeat=0", 0).await;
    let opening = tokio::spawn({
        let connection = connection.clone();
        async move { connection.open_channel().await }
    });
    assert!(matches!(server.method().await, Method::ChannelOpen(_)));
    server.send(1, ChannelOpenOk::default()).await;
    let channel = within("channel", opening)
        .await
        .expect("join")
        .expect("open");
    let declaring = tokio::spawn({
        let channel = channel.clone();
        async move {
            channel
                .queue_declare("q", Default::default(), FieldTable::new())
                .await
        }
    });
    assert!(matches!(server.method().await, Method::QueueDeclare(_)));
    server
        .send(
            0,
            ConnectionClose {
                reply_code: 320,
                reply_text: ShortStr::from_static("CONNECTION_FORCED - going down"),
                class_id: 0,
                method_id: 0,
            },
        )
        .await;
    // The client answers close-ok.
    assert!(matches!(
        server.method().await,
        Method::ConnectionCloseOk(_)
    ));
    let err = within("declare fails", declaring)
        .await
        .expect("join")
        .expect_err("connection closed");
    assert_eq!(err.reply_code(), Some(ReplyCode::ConnectionForced));
    assert!(matches!(&err, Error::ConnectionClosed(r) if r.text.contains("going down")));
    let closed = within("closed", connection.closed()).await;
    assert_eq!(closed.reply_code(), Some(ReplyCode::ConnectionForced));
    assert_eq!(
        channel.closed().await.reply_code(),
        Some(ReplyCode::ConnectionForced)
    );
    assert!(server.frame().await.is_none(), "client closes the socket");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn client_close_sends_close_and_waits_for_close_ok() {
    let peer = ScriptedPeer::bind().await;
    let (connection, mut server) = peer.connect("heartbeat=0", 0).await;
    let closing = tokio::spawn({
        let connection = connection.clone();
        async move { connection.close().await }
    });
    match server.method().await {
        Method::ConnectionClose(close) => assert_eq!(close.reply_code, 200),
        other => panic!("expected connection.close, got {other:?}"),
    }
    assert!(!closing.is_finished());
    server.send(0, ConnectionCloseOk {}).await;
    within("close", closing)
        .await
        .expect("join")
        .expect("close");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn leveret_shutdown_is_connection_forced() {
    let broker = broker().await;
    if broker.is_external() {
        // Only the in-process broker can be shut down from here.
        return;
    }
    let connection = broker.connect().await;
    drop(broker);
    let error = within("closed", connection.closed()).await;
    assert_eq!(
        error.reply_code(),
        Some(ReplyCode::ConnectionForced),
        "{error:?}"
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn dropping_the_last_handles_closes_channel_then_connection() {
    let peer = ScriptedPeer::bind().await;
    let (connection, mut server) = peer.connect("heartbeat=0", 0).await;
    let opening = tokio::spawn({
        let connection = connection.clone();
        async move { connection.open_channel().await }
    });
    assert!(matches!(server.method().await, Method::ChannelOpen(_)));
    server.send(1, ChannelOpenOk::default()).await;
    let channel = within("channel", opening)
        .await
        .expect("join")
        .expect("open");
    // The channel keeps the connection open after its handle is gone.
    drop(connection);
    drop(channel);
    match server.frame().await {
        Some(Frame::Method {
            channel: 1,
            method: Method::ChannelClose(close),
        }) => assert_eq!(close.reply_code, 200),
        other => panic!("expected channel.close, got {other:?}"),
    }
    match server.frame().await {
        Some(Frame::Method {
            channel: 0,
            method: Method::ConnectionClose(close),
        }) => assert_eq!(close.reply_code, 200),
        other => panic!("expected connection.close, got {other:?}"),
    }
    server.send(0, ConnectionCloseOk {}).await;
    assert!(server.frame().await.is_none(), "client closes the socket");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn malformed_frame_closes_with_frame_error() {
    let peer = ScriptedPeer::bind().await;
    let (connection, mut server) = peer.connect("heartbeat=0", 0).await;
    // A body frame whose frame-end octet is wrong.
    server.send_raw(b"\x03\x00\x01\x00\x00\x00\x01a\xcf").await;
    match server.method().await {
        Method::ConnectionClose(close) => {
            assert_eq!(close.reply_code, ReplyCode::FrameError.code());
        }
        other => panic!("expected connection.close, got {other:?}"),
    }
    let error = within("closed", connection.closed()).await;
    assert!(matches!(error, Error::Protocol(_)), "{error:?}");
    assert!(server.frame().await.is_none(), "client closes the socket");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn unexpected_reply_closes_with_unexpected_frame() {
    let peer = ScriptedPeer::bind().await;
    let (connection, mut server) = peer.connect("heartbeat=0", 0).await;
    let opening = tokio::spawn({
        let connection = connection.clone();
        async move { connection.open_channel().await }
    });
    assert!(matches!(server.method().await, Method::ChannelOpen(_)));
    // Answer channel.open with the wrong reply.
    server
        .send(1, leveret_client::protocol::QueueDeclareOk::default())
        .await;
    match server.method().await {
        Method::ConnectionClose(close) => {
            assert_eq!(close.reply_code, ReplyCode::UnexpectedFrame.code());
        }
        other => panic!("expected connection.close, got {other:?}"),
    }
    // While closing, the client waits for close-ok.
    server.send(0, ConnectionCloseOk {}).await;
    let err = within("open fails", opening)
        .await
        .expect("join")
        .expect_err("protocol error");
    assert!(matches!(err, Error::Protocol(_)), "{err:?}");
    assert!(matches!(connection.closed().await, Error::Protocol(_)));
}

/// Needs a broker with a tiny memory watermark: the in-process Leveret
/// (`None` when the tests run against an external broker).
async fn leveret_with_64k_watermark() -> Option<common::TestBroker> {
    common::leveret_with(leveret_broker::Limits {
        memory_high_watermark: 64 * 1024,
        ..Default::default()
    })
    .await
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn leveret_memory_alarm_blocks_and_unblocks_publishers() {
    let Some(broker) = leveret_with_64k_watermark().await else {
        return;
    };
    let (publisher, channel) = broker.channel().await;
    let queue = common::temp_queue(&channel, "alarm").await;
    let mut blocked = publisher.blocked();
    assert_eq!(*blocked.borrow_and_update(), None);
    // 200 KiB queued crosses the 64 KiB watermark.
    for _ in 0..10 {
        let _ = channel
            .basic_publish(
                "",
                &queue.name,
                Default::default(),
                Default::default(),
                bytes::Bytes::from(vec![1u8; 20 * 1024]),
            )
            .await
            .expect("publish");
    }
    within("connection.blocked", blocked.wait_for(Option::is_some))
        .await
        .expect("blocked");
    // Another connection drains the queue; the alarm clears.
    let (other, drain) = broker.channel().await;
    within("purge", async {
        let mut purged = 0;
        while purged < 10 {
            purged += drain
                .queue_purge(&queue.name, Default::default())
                .await
                .expect("purge");
        }
    })
    .await;
    within("connection.unblocked", blocked.wait_for(Option::is_none))
        .await
        .expect("unblocked");
    // Publishing works again.
    channel.confirm_select().await.expect("confirm.select");
    let confirm = channel
        .basic_publish(
            "",
            &queue.name,
            Default::default(),
            Default::default(),
            bytes::Bytes::from_static(b"after"),
        )
        .await
        .expect("publish");
    assert!(within("confirm", confirm).await.expect("confirm").is_ack());
    other.close().await.expect("close");
    publisher.close().await.expect("close");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn leveret_transaction_is_capped_at_a_quarter_of_the_memory_watermark() {
    // One transaction may hold a quarter of the watermark: 16 KiB.
    let Some(broker) = leveret_with_64k_watermark().await else {
        return;
    };
    let (connection, channel) = broker.channel().await;
    let queue = common::temp_queue(&channel, "tx-cap").await;
    let body = bytes::Bytes::from(vec![7u8; 4 * 1024]);
    let publish = |channel: &leveret_client::Channel| {
        let channel = channel.clone();
        let queue = queue.name.clone();
        let body = body.clone();
        async move {
            channel
                .basic_publish("", &queue, Default::default(), Default::default(), body)
                .await
                .map(drop)
        }
    };
    let tx = connection.open_channel().await.expect("channel");
    tx.tx_select().await.expect("tx.select");
    for _ in 0..3 {
        publish(&tx).await.expect("publish");
    }
    tx.tx_commit().await.expect("a 12 KiB transaction commits");
    // A transaction that never commits: the fourth 4 KiB publish (with the
    // per-message overhead) passes 16 KiB.
    for _ in 0..4 {
        publish(&tx).await.expect("publish");
    }
    let err = tx.tx_commit().await.expect_err("the channel was closed");
    match &err {
        leveret_client::Error::ChannelClosed(reason) => {
            assert_eq!(
                reason.reply_code(),
                Some(leveret_client::ReplyCode::PreconditionFailed),
                "{reason}"
            );
            assert!(reason.text.contains("transaction too large"), "{reason}");
            assert_eq!((reason.class_id, reason.method_id), (60, 40), "{reason}");
        }
        other => panic!("expected a 406 channel close, got {other:?}"),
    }
    // Only the committed messages were queued; the connection still serves.
    let declared = channel
        .queue_declare(
            &queue.name,
            leveret_client::QueueDeclareOptions {
                passive: true,
                ..Default::default()
            },
            Default::default(),
        )
        .await
        .expect("passive declare");
    assert_eq!(declared.message_count, 3);
    connection.close().await.expect("close");
}
