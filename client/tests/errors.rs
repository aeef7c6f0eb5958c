//! Broker errors as the client reports them: channel-level codes with
//! their text and offending method, and a connection-level error that
//! reaches every channel.

mod common;

use bytes::Bytes;
use common::{broker, temp_queue, unique, within};
use leveret_client::{
    BasicConsumeOptions, BasicGetOptions, Channel, Connection, Error, ExchangeDeclareOptions,
    ExchangeDeleteOptions, FieldTable, QueueDeleteOptions, ReplyCode,
};

/// A fresh channel on `connection`.
async fn channel(connection: &Connection) -> Channel {
    within("open channel", connection.open_channel())
        .await
        .expect("open channel")
}

/// Asserts a channel-level close with `code` caused by class/method ids.
fn assert_channel_error(err: &Error, code: ReplyCode, ids: (u16, u16)) {
    match err {
        Error::ChannelClosed(reason) => {
            assert_eq!(reason.reply_code(), Some(code), "{reason}");
            assert!(
                reason.text.starts_with(code.name()),
                "reply text {:?} should start with {}",
                reason.text,
                code.name()
            );
            assert_eq!((reason.class_id, reason.method_id), ids, "{reason}");
        }
        other => panic!("expected a {code} channel close, got {other:?}"),
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn consume_and_get_on_a_missing_queue_are_404() {
    let broker = broker().await;
    let connection = broker.connect().await;
    let missing = unique("missing");
    let err = channel(&connection)
        .await
        .basic_consume(
            missing.as_str(),
            "",
            BasicConsumeOptions::default(),
            FieldTable::new(),
        )
        .await
        .expect_err("missing queue");
    assert_channel_error(&err, ReplyCode::NotFound, (60, 20));
    let err = channel(&connection)
        .await
        .basic_get(missing.as_str(), BasicGetOptions::default())
        .await
        .expect_err("missing queue");
    assert_channel_error(&err, ReplyCode::NotFound, (60, 70));
    connection.close().await.expect("close");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn bind_to_a_missing_exchange_is_404() {
    let broker = broker().await;
    let connection = broker.connect().await;
    let ch = channel(&connection).await;
    let queue = temp_queue(&ch, "bind404").await;
    let err = ch
        .queue_bind(
            &queue.name,
            unique("no-exchange").as_str(),
            "k",
            Default::default(),
            FieldTable::new(),
        )
        .await
        .expect_err("missing exchange");
    assert_channel_error(&err, ReplyCode::NotFound, (50, 20));
    connection.close().await.expect("close");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn exclusive_consumer_conflicts_are_403() {
    let broker = broker().await;
    let connection = broker.connect().await;
    let ch = channel(&connection).await;
    let queue = temp_queue(&ch, "exclusive-consumer").await;
    let _exclusive = ch
        .basic_consume(
            &queue.name,
            "",
            BasicConsumeOptions {
                exclusive: true,
                ..Default::default()
            },
            FieldTable::new(),
        )
        .await
        .expect("exclusive consume");
    let err = channel(&connection)
        .await
        .basic_consume(
            &queue.name,
            "",
            BasicConsumeOptions::default(),
            FieldTable::new(),
        )
        .await
        .expect_err("queue has an exclusive consumer");
    assert_channel_error(&err, ReplyCode::AccessRefused, (60, 20));
    connection.close().await.expect("close");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn declaring_an_amq_prefixed_exchange_is_403() {
    let broker = broker().await;
    let connection = broker.connect().await;
    let err = channel(&connection)
        .await
        .exchange_declare(
            unique("amq.mine").trim_start_matches("leveret-client-test."),
            "direct",
            ExchangeDeclareOptions::default(),
            FieldTable::new(),
        )
        .await
        .expect_err("reserved name");
    assert_channel_error(&err, ReplyCode::AccessRefused, (40, 10));
    connection.close().await.expect("close");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn if_unused_deletes_are_406_while_in_use() {
    let broker = broker().await;
    let connection = broker.connect().await;
    let ch = channel(&connection).await;
    let queue = temp_queue(&ch, "in-use").await;
    let _consumer = ch
        .basic_consume(
            &queue.name,
            "",
            BasicConsumeOptions::default(),
            FieldTable::new(),
        )
        .await
        .expect("consume");
    let err = channel(&connection)
        .await
        .queue_delete(
            &queue.name,
            QueueDeleteOptions {
                if_unused: true,
                ..Default::default()
            },
        )
        .await
        .expect_err("queue has a consumer");
    assert_channel_error(&err, ReplyCode::PreconditionFailed, (50, 40));

    let exchange = unique("bound");
    ch.exchange_declare(
        exchange.as_str(),
        "fanout",
        ExchangeDeclareOptions::default(),
        FieldTable::new(),
    )
    .await
    .expect("declare");
    ch.queue_bind(
        &queue.name,
        exchange.as_str(),
        "",
        Default::default(),
        FieldTable::new(),
    )
    .await
    .expect("bind");
    let err = channel(&connection)
        .await
        .exchange_delete(
            exchange.as_str(),
            ExchangeDeleteOptions {
                if_unused: true,
                ..Default::default()
            },
        )
        .await
        .expect_err("exchange has a binding");
    assert_channel_error(&err, ReplyCode::PreconditionFailed, (40, 20));
    ch.exchange_delete(exchange.as_str(), Default::default())
        .await
        .expect("delete");
    connection.close().await.expect("close");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn acking_twice_is_406() {
    let broker = broker().await;
    let connection = broker.connect().await;
    let ch = channel(&connection).await;
    let queue = temp_queue(&ch, "double-ack").await;
    ch.confirm_select().await.expect("confirm.select");
    let confirm = ch
        .basic_publish(
            "",
            &queue.name,
            Default::default(),
            Default::default(),
            Bytes::from_static(b"once"),
        )
        .await
        .expect("publish");
    assert!(within("confirm", confirm).await.expect("confirm").is_ack());
    let message = ch
        .basic_get(&queue.name, BasicGetOptions::default())
        .await
        .expect("get")
        .expect("message");
    message.ack().await.expect("ack");
    message.ack().await.expect("second ack is sent");
    let err = within("next call", ch.basic_qos(1, Default::default()))
        .await
        .expect_err("double ack");
    assert_channel_error(&err, ReplyCode::PreconditionFailed, (60, 80));
    connection.close().await.expect("close");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn reusing_a_consumer_tag_is_a_connection_error() {
    let broker = broker().await;
    let connection = broker.connect().await;
    let ch = channel(&connection).await;
    let bystander = channel(&connection).await;
    let queue = temp_queue(&ch, "tag").await;
    let _first = ch
        .basic_consume(
            &queue.name,
            "same-tag",
            BasicConsumeOptions::default(),
            FieldTable::new(),
        )
        .await
        .expect("consume");
    let err = ch
        .basic_consume(
            &queue.name,
            "same-tag",
            BasicConsumeOptions::default(),
            FieldTable::new(),
        )
        .await
        .expect_err("tag in use");
    // RabbitMQ: 530 NOT_ALLOWED, closing the connection.
    match &err {
        Error::ConnectionClosed(reason) => {
            assert_eq!(reason.reply_code(), Some(ReplyCode::NotAllowed), "{reason}");
            assert_eq!((reason.class_id, reason.method_id), (60, 20));
        }
        other => panic!("expected a connection close, got {other:?}"),
    }
    // Every channel and the connection report the same error.
    assert_eq!(
        within("closed", connection.closed()).await.close_reason(),
        err.close_reason()
    );
    let on_bystander = bystander
        .queue_declare("", Default::default(), FieldTable::new())
        .await
        .expect_err("connection closed");
    assert_eq!(on_bystander.close_reason(), err.close_reason());
    assert!(!connection.is_open());
}
