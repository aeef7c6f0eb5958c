//! Exchanges, queues and bindings, and the reply codes of their errors.

mod common;

use bytes::Bytes;
use common::{broker, temp_queue, unique, within};
use leveret_client::{
    BasicGetOptions, Channel, Error, ExchangeBindOptions, ExchangeDeclareOptions,
    ExchangeDeleteOptions, FieldTable, QueueBindOptions, QueueDeclareOptions, QueueDeleteOptions,
    QueuePurgeOptions, ReplyCode,
};

/// Publishes and, on a channel in confirm mode, waits for the broker's
/// ack: RabbitMQ answers queue stats (passive declare) ahead of publishes
/// still on their way to the queue, so counts are only exact after it.
async fn publish(channel: &Channel, exchange: &str, key: &str, body: &'static [u8]) {
    let confirm = within(
        "publish",
        channel.basic_publish(
            exchange,
            key,
            Default::default(),
            Default::default(),
            Bytes::from_static(body),
        ),
    )
    .await
    .expect("publish");
    let confirmation = within("confirm", confirm).await.expect("confirm");
    assert_ne!(confirmation, leveret_client::Confirmation::Nack);
}

/// A connection and a channel in confirm mode.
async fn confirming(broker: &common::TestBroker) -> (leveret_client::Connection, Channel) {
    let (connection, channel) = broker.channel().await;
    within("confirm.select", channel.confirm_select())
        .await
        .expect("confirm.select");
    (connection, channel)
}

/// Message count of a queue, from a passive declare.
async fn count(channel: &Channel, queue: &str) -> u32 {
    let passive = QueueDeclareOptions {
        passive: true,
        ..Default::default()
    };
    within(
        "passive declare",
        channel.queue_declare(queue, passive, FieldTable::new()),
    )
    .await
    .expect("passive declare")
    .message_count
}

/// The body of the next message in `queue`, if any.
async fn get_body(channel: &Channel, queue: &str) -> Option<Bytes> {
    within(
        "get",
        channel.basic_get(queue, BasicGetOptions { no_ack: true }),
    )
    .await
    .expect("get")
    .map(|m| m.delivery.body.clone())
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn queue_declare_returns_name_and_counts() {
    let broker = broker().await;
    let (connection, channel) = confirming(&broker).await;
    // A server-named queue.
    let named = within(
        "declare",
        channel.queue_declare(
            "",
            QueueDeclareOptions {
                exclusive: true,
                ..Default::default()
            },
            FieldTable::new(),
        ),
    )
    .await
    .expect("declare");
    assert!(!named.name.is_empty());
    assert_eq!((named.message_count, named.consumer_count), (0, 0));
    // Counts reflect messages and consumers.
    let queue = temp_queue(&channel, "counts").await;
    for _ in 0..3 {
        publish(&channel, "", queue.name.as_str().unwrap(), b"x").await;
    }
    let other = connection.open_channel().await.expect("channel");
    let _consumer = other
        .basic_consume(
            &queue.name,
            "",
            leveret_client::BasicConsumeOptions::default(),
            FieldTable::new(),
        )
        .await
        .expect("consume");
    let info = channel
        .queue_declare(
            &queue.name,
            QueueDeclareOptions {
                passive: true,
                ..Default::default()
            },
            FieldTable::new(),
        )
        .await
        .expect("passive");
    assert_eq!(info.name, queue.name);
    assert_eq!(info.consumer_count, 1);
    channel
        .queue_delete(&queue.name, Default::default())
        .await
        .expect("delete");
    connection.close().await.expect("close");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn passive_declare_of_a_missing_queue_is_404_and_closes_the_channel() {
    let broker = broker().await;
    let (connection, channel) = broker.channel().await;
    let missing = unique("missing");
    let passive = QueueDeclareOptions {
        passive: true,
        ..Default::default()
    };
    let err = within(
        "passive declare",
        channel.queue_declare(missing.as_str(), passive, FieldTable::new()),
    )
    .await
    .expect_err("missing queue");
    let reason = match &err {
        Error::ChannelClosed(reason) => reason.clone(),
        other => panic!("expected a channel close, got {other:?}"),
    };
    assert_eq!(reason.code, 404);
    assert_eq!(reason.reply_code(), Some(ReplyCode::NotFound));
    assert!(reason.text.starts_with("NOT_FOUND"), "{}", reason.text);
    assert_eq!((reason.class_id, reason.method_id), (50, 10));
    // Later calls fail with the same error.
    let later = channel
        .exchange_declare(
            "amq.direct",
            "direct",
            ExchangeDeclareOptions {
                passive: true,
                ..Default::default()
            },
            FieldTable::new(),
        )
        .await
        .expect_err("channel is closed");
    assert_eq!(later.close_reason(), Some(&reason));
    assert_eq!(channel.closed().await.close_reason(), Some(&reason));
    let err = channel.close().await.expect_err("already closed by broker");
    assert_eq!(err.reply_code(), Some(ReplyCode::NotFound));
    connection.close().await.expect("close");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn passive_exchange_declare_of_a_missing_exchange_is_404() {
    let broker = broker().await;
    let (connection, channel) = broker.channel().await;
    let err = channel
        .exchange_declare(
            unique("missing-x").as_str(),
            "direct",
            ExchangeDeclareOptions {
                passive: true,
                ..Default::default()
            },
            FieldTable::new(),
        )
        .await
        .expect_err("missing exchange");
    assert_eq!(err.reply_code(), Some(ReplyCode::NotFound));
    connection.close().await.expect("close");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn redeclare_with_other_flags_is_406() {
    let broker = broker().await;
    let (connection, channel) = broker.channel().await;
    let exchange = unique("x");
    channel
        .exchange_declare(
            exchange.as_str(),
            "direct",
            ExchangeDeclareOptions {
                auto_delete: true,
                ..Default::default()
            },
            FieldTable::new(),
        )
        .await
        .expect("declare");
    let err = channel
        .exchange_declare(
            exchange.as_str(),
            "fanout",
            ExchangeDeclareOptions {
                auto_delete: true,
                ..Default::default()
            },
            FieldTable::new(),
        )
        .await
        .expect_err("type mismatch");
    assert_eq!(err.reply_code(), Some(ReplyCode::PreconditionFailed));
    let channel = connection.open_channel().await.expect("channel");
    channel
        .exchange_delete(exchange.as_str(), Default::default())
        .await
        .expect("delete");
    connection.close().await.expect("close");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn exchange_declare_bind_route_unbind_delete() {
    let broker = broker().await;
    let (connection, channel) = confirming(&broker).await;
    let exchange = unique("direct");
    channel
        .exchange_declare(
            exchange.as_str(),
            "direct",
            ExchangeDeclareOptions::default(),
            FieldTable::new(),
        )
        .await
        .expect("declare");
    // Declaring again with the same flags is fine, passive too.
    channel
        .exchange_declare(
            exchange.as_str(),
            "direct",
            ExchangeDeclareOptions::default(),
            FieldTable::new(),
        )
        .await
        .expect("redeclare");
    let queue = temp_queue(&channel, "bound").await;
    let q = queue.name.as_str().unwrap().to_owned();
    channel
        .queue_bind(
            q.as_str(),
            exchange.as_str(),
            "key",
            QueueBindOptions::default(),
            FieldTable::new(),
        )
        .await
        .expect("bind");
    publish(&channel, &exchange, "key", b"routed").await;
    publish(&channel, &exchange, "other", b"dropped").await;
    assert_eq!(
        get_body(&channel, &q).await.as_deref(),
        Some(&b"routed"[..])
    );
    assert_eq!(get_body(&channel, &q).await, None);
    channel
        .queue_unbind(q.as_str(), exchange.as_str(), "key", FieldTable::new())
        .await
        .expect("unbind");
    publish(&channel, &exchange, "key", b"after unbind").await;
    assert_eq!(get_body(&channel, &q).await, None);
    channel
        .exchange_delete(exchange.as_str(), ExchangeDeleteOptions::default())
        .await
        .expect("delete");
    let err = channel
        .exchange_declare(
            exchange.as_str(),
            "direct",
            ExchangeDeclareOptions {
                passive: true,
                ..Default::default()
            },
            FieldTable::new(),
        )
        .await
        .expect_err("deleted");
    assert_eq!(err.reply_code(), Some(ReplyCode::NotFound));
    let channel = connection.open_channel().await.expect("channel");
    channel
        .queue_delete(q.as_str(), Default::default())
        .await
        .expect("delete queue");
    connection.close().await.expect("close");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn exchange_to_exchange_bindings() {
    let broker = broker().await;
    let (connection, channel) = confirming(&broker).await;
    let source = unique("source");
    let destination = unique("destination");
    for name in [&source, &destination] {
        channel
            .exchange_declare(
                name.as_str(),
                "fanout",
                ExchangeDeclareOptions::default(),
                FieldTable::new(),
            )
            .await
            .expect("declare");
    }
    let queue = temp_queue(&channel, "e2e").await;
    let q = queue.name.as_str().unwrap().to_owned();
    channel
        .queue_bind(
            q.as_str(),
            destination.as_str(),
            "",
            Default::default(),
            FieldTable::new(),
        )
        .await
        .expect("bind queue");
    channel
        .exchange_bind(
            destination.as_str(),
            source.as_str(),
            "",
            ExchangeBindOptions::default(),
            FieldTable::new(),
        )
        .await
        .expect("exchange.bind");
    publish(&channel, &source, "", b"through").await;
    assert_eq!(
        get_body(&channel, &q).await.as_deref(),
        Some(&b"through"[..])
    );
    channel
        .exchange_unbind(
            destination.as_str(),
            source.as_str(),
            "",
            ExchangeBindOptions::default(),
            FieldTable::new(),
        )
        .await
        .expect("exchange.unbind");
    publish(&channel, &source, "", b"not any more").await;
    assert_eq!(get_body(&channel, &q).await, None);
    for name in [&source, &destination] {
        channel
            .exchange_delete(name.as_str(), Default::default())
            .await
            .expect("delete");
    }
    channel
        .queue_delete(q.as_str(), Default::default())
        .await
        .expect("delete queue");
    connection.close().await.expect("close");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn purge_and_delete_report_counts() {
    let broker = broker().await;
    let (connection, channel) = confirming(&broker).await;
    let queue = temp_queue(&channel, "purge").await;
    let q = queue.name.as_str().unwrap().to_owned();
    for _ in 0..4 {
        publish(&channel, "", &q, b"m").await;
    }
    assert_eq!(count(&channel, &q).await, 4);
    let purged = channel
        .queue_purge(q.as_str(), QueuePurgeOptions::default())
        .await
        .expect("purge");
    assert_eq!(purged, 4);
    for _ in 0..2 {
        publish(&channel, "", &q, b"m").await;
    }
    assert_eq!(count(&channel, &q).await, 2);
    // if_empty refuses a queue with messages.
    let err = channel
        .queue_delete(
            q.as_str(),
            QueueDeleteOptions {
                if_empty: true,
                ..Default::default()
            },
        )
        .await
        .expect_err("not empty");
    assert_eq!(err.reply_code(), Some(ReplyCode::PreconditionFailed));
    let channel = connection.open_channel().await.expect("channel");
    let deleted = channel
        .queue_delete(q.as_str(), QueueDeleteOptions::default())
        .await
        .expect("delete");
    assert_eq!(deleted, 2);
    let err = channel
        .queue_declare(
            q.as_str(),
            QueueDeclareOptions {
                passive: true,
                ..Default::default()
            },
            FieldTable::new(),
        )
        .await
        .expect_err("deleted");
    assert_eq!(err.reply_code(), Some(ReplyCode::NotFound));
    connection.close().await.expect("close");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn no_wait_methods_send_without_waiting() {
    let broker = broker().await;
    let (connection, channel) = confirming(&broker).await;
    let exchange = unique("nowait-x");
    let queue = unique("nowait-q");
    channel
        .exchange_declare(
            exchange.as_str(),
            "topic",
            ExchangeDeclareOptions {
                no_wait: true,
                ..Default::default()
            },
            FieldTable::new(),
        )
        .await
        .expect("declare exchange");
    let info = channel
        .queue_declare(
            queue.as_str(),
            QueueDeclareOptions {
                no_wait: true,
                ..Default::default()
            },
            FieldTable::new(),
        )
        .await
        .expect("declare queue");
    assert_eq!(info.name, queue.as_str());
    channel
        .queue_bind(
            queue.as_str(),
            exchange.as_str(),
            "a.*",
            QueueBindOptions { no_wait: true },
            FieldTable::new(),
        )
        .await
        .expect("bind");
    publish(&channel, &exchange, "a.b", b"topic").await;
    // A synchronous call after them orders after them.
    assert_eq!(count(&channel, &queue).await, 1);
    channel
        .queue_delete(
            queue.as_str(),
            QueueDeleteOptions {
                no_wait: true,
                ..Default::default()
            },
        )
        .await
        .expect("delete queue");
    channel
        .exchange_delete(
            exchange.as_str(),
            ExchangeDeleteOptions {
                no_wait: true,
                ..Default::default()
            },
        )
        .await
        .expect("delete exchange");
    let err = channel
        .queue_declare(
            queue.as_str(),
            QueueDeclareOptions {
                passive: true,
                ..Default::default()
            },
            FieldTable::new(),
        )
        .await
        .expect_err("deleted");
    assert_eq!(err.reply_code(), Some(ReplyCode::NotFound));
    // no_wait without a name cannot work.
    let channel = connection.open_channel().await.expect("channel");
    let err = channel
        .queue_declare(
            "",
            QueueDeclareOptions {
                no_wait: true,
                ..Default::default()
            },
            FieldTable::new(),
        )
        .await
        .expect_err("no name");
    assert!(matches!(err, Error::InvalidArgument(_)));
    connection.close().await.expect("close");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn exclusive_queue_is_locked_to_its_connection() {
    let broker = broker().await;
    let (connection, channel) = broker.channel().await;
    let queue = unique("exclusive");
    channel
        .queue_declare(
            queue.as_str(),
            QueueDeclareOptions {
                exclusive: true,
                ..Default::default()
            },
            FieldTable::new(),
        )
        .await
        .expect("declare");
    let (other, other_channel) = broker.channel().await;
    let err = other_channel
        .queue_declare(
            queue.as_str(),
            QueueDeclareOptions {
                passive: true,
                ..Default::default()
            },
            FieldTable::new(),
        )
        .await
        .expect_err("locked");
    assert_eq!(err.reply_code(), Some(ReplyCode::ResourceLocked));
    other.close().await.expect("close");
    connection.close().await.expect("close");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn names_longer_than_255_bytes_are_refused_locally() {
    let broker = broker().await;
    let (connection, channel) = broker.channel().await;
    let long = "q".repeat(256);
    let err = channel
        .queue_declare(long.as_str(), Default::default(), FieldTable::new())
        .await
        .expect_err("too long");
    assert!(matches!(err, Error::InvalidArgument(_)));
    assert!(channel.is_open());
    connection.close().await.expect("close");
}
