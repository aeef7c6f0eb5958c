//! The in-process transports: a broker with no listener serves a
//! connection over an in-memory byte pipe exactly as over TCP, and one
//! over a value link (`connect_direct`) with the same connection code:
//! publishes taken whole and deliveries handed over whole, and
//! max_message_size for what it receives.

use bytes::{Bytes, BytesMut};
use leveret_broker::{DirectReply, Limits};
use leveret_protocol::{
    decode_frame, BasicConsume, BasicProperties, BasicPublish, ChannelCloseOk, ChannelOpen,
    ConnectionOpen, ConnectionStartOk, ConnectionTuneOk, FieldTable, Frame, Method, Outgoing,
    QueueDeclare, ShortStr, PROTOCOL_HEADER,
};
use leveret_test_macros::both_runtimes;
use std::time::Duration;
use tokio::io::{AsyncReadExt, AsyncWriteExt};

#[both_runtimes]
async fn a_broker_without_listeners_greets_an_in_process_client() {
    let handle = leveret_broker::Broker::builder()
        .start()
        .await
        .expect("start");
    assert!(handle.local_addrs().is_empty());
    let mut pipe = handle.connect_in_process();
    pipe.write_all(PROTOCOL_HEADER).await.expect("header");
    let mut buf = BytesMut::new();
    let frame = tokio::time::timeout(std::time::Duration::from_secs(30), async {
        loop {
            if let Some(frame) = decode_frame(&mut buf, 0).expect("valid frame") {
                return frame;
            }
            assert!(pipe.read_buf(&mut buf).await.expect("read") > 0, "eof");
        }
    })
    .await
    .expect("connection.start in time");
    match frame {
        Frame::Method {
            channel: 0,
            method: Method::ConnectionStart(start),
        } => assert_eq!((start.version_major, start.version_minor), (0, 9)),
        other => panic!("expected connection.start, got {other:?}"),
    }
    handle.shutdown().await;
}

/// The client's side of a value link, driven item by item.
struct DirectClient {
    link: leveret_broker::DirectLink,
}

impl DirectClient {
    async fn send(&self, channel: u16, method: impl Into<Method>) {
        let item = Outgoing::Method {
            channel,
            method: method.into(),
        };
        self.link.to_broker.send(item).await.expect("broker there");
    }

    async fn publish(&self, routing_key: &'static str, properties: BasicProperties, body: Bytes) {
        self.publish_on(1, routing_key, properties, body).await;
    }

    async fn publish_on(
        &self,
        channel: u16,
        routing_key: &'static str,
        properties: BasicProperties,
        body: Bytes,
    ) {
        let item = Outgoing::Publish {
            channel,
            method: BasicPublish {
                routing_key: ShortStr::from_static(routing_key),
                ..Default::default()
            },
            properties: Box::new(properties),
            body,
        };
        self.link.to_broker.send(item).await.expect("broker there");
    }

    async fn next(&mut self) -> Option<DirectReply> {
        tokio::time::timeout(Duration::from_secs(30), self.link.from_broker.recv())
            .await
            .expect("a reply in time")
    }

    async fn method(&mut self) -> Method {
        match self.next().await {
            Some(DirectReply::Frame(Frame::Method { method, .. })) => method,
            other => panic!("expected a method, got {other:?}"),
        }
    }

    /// Declares `queue` on channel 1.
    async fn declare(&mut self, queue: &'static str) {
        let declare = QueueDeclare {
            queue: ShortStr::from_static(queue),
            ..Default::default()
        };
        self.send(1, declare).await;
        assert!(matches!(self.method().await, Method::QueueDeclareOk(_)));
    }

    /// Consumes `queue` on channel 1 without acks.
    async fn consume(&mut self, queue: &'static str) {
        let consume = BasicConsume {
            queue: ShortStr::from_static(queue),
            no_ack: true,
            ..Default::default()
        };
        self.send(1, consume).await;
        assert!(matches!(self.method().await, Method::BasicConsumeOk(_)));
    }

    /// The handshake as guest, then channel 1 open.
    async fn open(handle: &leveret_broker::BrokerHandle) -> DirectClient {
        let mut client = DirectClient {
            link: handle.connect_direct(),
        };
        assert!(matches!(client.method().await, Method::ConnectionStart(_)));
        client
            .send(
                0,
                ConnectionStartOk {
                    client_properties: FieldTable::new(),
                    mechanism: ShortStr::from_static("PLAIN"),
                    response: Bytes::from_static(b"\0guest\0guest"),
                    locale: ShortStr::from_static("en_US"),
                },
            )
            .await;
        assert!(matches!(client.method().await, Method::ConnectionTune(_)));
        client
            .send(
                0,
                ConnectionTuneOk {
                    channel_max: 16,
                    frame_max: 4096,
                    heartbeat: 0,
                },
            )
            .await;
        client
            .send(
                0,
                ConnectionOpen {
                    virtual_host: ShortStr::from_static("/"),
                    ..Default::default()
                },
            )
            .await;
        assert!(matches!(client.method().await, Method::ConnectionOpenOk(_)));
        client.send(1, ChannelOpen::default()).await;
        assert!(matches!(client.method().await, Method::ChannelOpenOk(_)));
        client
    }
}

async fn wait_for_connections(handle: &leveret_broker::BrokerHandle, count: u64) {
    let deadline = tokio::time::Instant::now() + Duration::from_secs(30);
    while handle.overview().object_totals.connections != count {
        assert!(
            tokio::time::Instant::now() < deadline,
            "{} connections, expected {count}",
            handle.overview().object_totals.connections
        );
        tokio::time::sleep(Duration::from_millis(10)).await;
    }
}

#[both_runtimes]
async fn a_value_link_routes_queues_and_delivers_like_a_socket() {
    let handle = leveret_broker::Broker::builder()
        .start()
        .await
        .expect("start");
    let mut client = DirectClient::open(&handle).await;
    client.declare("direct-q").await;
    let properties = BasicProperties {
        message_id: Some(ShortStr::from_static("m-1")),
        ..Default::default()
    };
    let body = Bytes::from(vec![7u8; 10_000]);
    client
        .publish("direct-q", properties.clone(), body.clone())
        .await;
    client.consume("direct-q").await;
    // The delivery comes whole, its body in one piece whatever frame_max:
    // nothing is parsed, so there is nothing for frame_max to protect.
    match client.next().await {
        Some(DirectReply::Content {
            channel: 1,
            method: Method::BasicDeliver(_),
            properties: got,
            body: received,
        }) => {
            assert_eq!(
                BasicProperties::decode(&got).expect("properties"),
                properties
            );
            assert_eq!(received, body);
        }
        other => panic!("expected the delivery, whole, got {other:?}"),
    }
    assert_eq!(handle.overview().object_totals.connections, 1);
    // Dropping the link is the client going away.
    drop(client);
    wait_for_connections(&handle, 0).await;
    handle.shutdown().await;
}

/// `try_recv` takes what is ready without waiting: nothing before a
/// delivery is there, then each waiting delivery in order, then nothing.
#[both_runtimes]
async fn try_recv_takes_ready_replies_without_waiting() {
    use std::task::Poll;
    let handle = leveret_broker::Broker::builder()
        .start()
        .await
        .expect("start");
    let mut client = DirectClient::open(&handle).await;
    client.declare("ready-q").await;
    client.consume("ready-q").await;
    assert!(
        client.link.from_broker.try_recv().is_pending(),
        "nothing yet"
    );
    for n in 0..3u8 {
        client
            .publish("ready-q", BasicProperties::default(), Bytes::from(vec![n]))
            .await;
    }
    // The first waits for the broker; the two after it may still be on
    // their way, so they are taken without waiting once they are there.
    let mut bodies = Vec::new();
    match client.next().await {
        Some(DirectReply::Content { body, .. }) => bodies.push(body),
        other => panic!("expected a delivery, got {other:?}"),
    }
    let deadline = tokio::time::Instant::now() + Duration::from_secs(30);
    while bodies.len() < 3 {
        match client.link.from_broker.try_recv() {
            Poll::Ready(Some(DirectReply::Content { body, .. })) => bodies.push(body),
            Poll::Ready(other) => panic!("expected a delivery, got {other:?}"),
            Poll::Pending => {
                assert!(tokio::time::Instant::now() < deadline, "{bodies:?}");
                tokio::task::yield_now().await;
            }
        }
    }
    assert_eq!(bodies, [vec![0u8], vec![1], vec![2]]);
    assert!(
        client.link.from_broker.try_recv().is_pending(),
        "nothing more"
    );
    handle.shutdown().await;
}

#[both_runtimes]
async fn a_value_link_is_held_to_max_message_size() {
    let handle = leveret_broker::Broker::builder()
        .limits(Limits {
            max_message_size: 1000,
            ..Limits::default()
        })
        .start()
        .await
        .expect("start");
    let mut client = DirectClient::open(&handle).await;
    let body = Bytes::from(vec![0u8; 100_000]);
    client
        .publish("nowhere", BasicProperties::default(), body)
        .await;
    match client.method().await {
        Method::ChannelClose(close) => assert_eq!(close.reply_code, 406, "{close:?}"),
        other => panic!("expected channel.close, got {other:?}"),
    }
    // The connection goes on: the channel opens again.
    client.send(1, ChannelCloseOk {}).await;
    client.send(1, ChannelOpen::default()).await;
    assert!(matches!(client.method().await, Method::ChannelOpenOk(_)));
    // A client that sends its end is gone, and cleaned up.
    client
        .link
        .to_broker
        .send(Outgoing::Shutdown)
        .await
        .expect("sent");
    wait_for_connections(&handle, 0).await;
    handle.shutdown().await;
}

/// A publish on a channel that is not open is the connection error a
/// socket's would be, though it reaches the connection whole.
#[both_runtimes]
async fn a_whole_publish_on_an_unopened_channel_closes_the_connection() {
    let handle = leveret_broker::Broker::builder()
        .start()
        .await
        .expect("start");
    let mut client = DirectClient::open(&handle).await;
    client
        .publish_on(
            2,
            "nowhere",
            BasicProperties::default(),
            Bytes::from_static(b"x"),
        )
        .await;
    match client.method().await {
        Method::ConnectionClose(close) => {
            assert_eq!(
                (close.reply_code, close.class_id, close.method_id),
                (504, 60, 40),
                "{close:?}"
            );
        }
        other => panic!("expected connection.close, got {other:?}"),
    }
    handle.shutdown().await;
}
