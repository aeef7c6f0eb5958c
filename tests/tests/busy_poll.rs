//! The broker as the `leveret` binary runs it: every connection on one
//! current-thread runtime that busy-polls after socket reads, driven by
//! lapin. Confirms of persistent messages come back from the storage
//! thread (a wake from outside the runtime), round trips keep the spinner
//! busy, and shutdown still completes.

use futures_lite::StreamExt;
use lapin::message::Delivery;
use lapin::options::{
    BasicAckOptions, BasicConsumeOptions, BasicPublishOptions, ConfirmSelectOptions,
    QueueDeclareOptions,
};
use lapin::types::FieldTable;
use lapin::{BasicProperties, Channel, Connection, ConnectionProperties, Consumer};
use leveret_broker::Broker;
use std::time::Duration;

const MESSAGES: u32 = 500;
const ROUND_TRIPS: u32 = 200;

/// The consumer's next delivery, within the time limit.
async fn next_delivery(consumer: &mut Consumer, what: &str) -> Delivery {
    within(what, consumer.next())
        .await
        .unwrap_or_else(|| panic!("the {what} consumer ended"))
        .expect("no consumer error")
}

/// A transient publish to the default exchange, without confirms.
async fn publish(channel: &Channel, queue: &str, body: &[u8]) {
    channel
        .basic_publish(
            "",
            queue,
            BasicPublishOptions::default(),
            body,
            BasicProperties::default(),
        )
        .await
        .expect("publish");
}

/// `future`'s output, or a panic naming `what` after ten seconds.
async fn within<T>(what: &str, future: impl std::future::Future<Output = T>) -> T {
    tokio::time::timeout(Duration::from_secs(10), future)
        .await
        .unwrap_or_else(|_| panic!("{what} timed out"))
}

#[tokio::test(flavor = "current_thread")]
async fn a_busy_polling_broker_confirms_delivers_in_order_echoes_and_shuts_down() {
    let dir = std::env::temp_dir().join(format!("leveret-busy-poll-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    let broker = Broker::builder()
        .listen("127.0.0.1:0".parse().expect("static address"))
        .data_dir(&dir)
        .busy_poll(Duration::from_micros(200))
        .start()
        .await
        .expect("start");
    let addr = broker.local_addrs()[0];
    let url = format!("amqp://guest:guest@{addr}/%2f");

    let connection = Connection::connect(&url, ConnectionProperties::default())
        .await
        .expect("connect");
    let channel = connection.create_channel().await.expect("channel");
    let durable = QueueDeclareOptions {
        durable: true,
        ..Default::default()
    };
    channel
        .queue_declare("busy-poll", durable, FieldTable::default())
        .await
        .expect("declare");
    channel
        .confirm_select(ConfirmSelectOptions::default())
        .await
        .expect("confirm.select");
    for seq in 0..MESSAGES {
        let confirm = channel
            .basic_publish(
                "",
                "busy-poll",
                BasicPublishOptions::default(),
                seq.to_string().as_bytes(),
                BasicProperties::default().with_delivery_mode(2),
            )
            .await
            .expect("publish");
        let confirmation = within("confirm", confirm).await.expect("confirmation");
        assert!(confirmation.is_ack(), "message {seq} confirmed");
    }

    let mut consumer = channel
        .basic_consume(
            "busy-poll",
            "in-order",
            BasicConsumeOptions::default(),
            FieldTable::default(),
        )
        .await
        .expect("consume");
    for seq in 0..MESSAGES {
        let delivery = next_delivery(&mut consumer, "delivery").await;
        assert_eq!(delivery.data, seq.to_string().as_bytes());
        delivery.ack(BasicAckOptions::default()).await.expect("ack");
    }

    // Ping-pong through two queues and a second connection, one in flight.
    let echo_connection = Connection::connect(&url, ConnectionProperties::default())
        .await
        .expect("connect the echo");
    let echo = echo_connection
        .create_channel()
        .await
        .expect("echo channel");
    for queue in ["busy-poll-ping", "busy-poll-pong"] {
        channel
            .queue_declare(queue, QueueDeclareOptions::default(), FieldTable::default())
            .await
            .expect("declare ping-pong queue");
    }
    let mut pings = echo
        .basic_consume(
            "busy-poll-ping",
            "echo",
            BasicConsumeOptions {
                no_ack: true,
                ..Default::default()
            },
            FieldTable::default(),
        )
        .await
        .expect("consume pings");
    let mut pongs = channel
        .basic_consume(
            "busy-poll-pong",
            "pongs",
            BasicConsumeOptions {
                no_ack: true,
                ..Default::default()
            },
            FieldTable::default(),
        )
        .await
        .expect("consume pongs");
    for seq in 0..ROUND_TRIPS {
        let body = seq.to_string();
        publish(&channel, "busy-poll-ping", body.as_bytes()).await;
        let ping = next_delivery(&mut pings, "ping").await;
        publish(&echo, "busy-poll-pong", &ping.data).await;
        let pong = next_delivery(&mut pongs, "pong").await;
        assert_eq!(pong.data, body.as_bytes());
    }

    within("shutdown", broker.shutdown()).await;
    let _ = std::fs::remove_dir_all(&dir);
}
