//! The in-process transport (`embedded` feature): the same client API over
//! the in-memory pipe of an embedded Leveret as over TCP. These tests need
//! an embedded broker, so they run against Leveret whatever
//! LEVERET_TEST_AMQP_URL says.

mod common;

use bytes::Bytes;
use common::within;
use leveret_broker::{Broker, Permission};
use leveret_client::{
    BasicConsumeOptions, BasicGetOptions, BasicProperties, BasicPublishOptions, Connection,
    ConnectionOptions, Error, FieldTable, FieldValue, QueueDeclareOptions, ReplyCode, ShortStr,
};
use std::sync::Arc;

#[tokio::test]
async fn publish_confirm_consume_over_the_pipe() {
    let broker = Arc::new(Broker::builder().start().await.expect("start"));
    let connection = within("connect", Connection::in_process(&broker))
        .await
        .expect("in-process connect");
    assert!(connection.is_open());
    let product = connection
        .server_properties()
        .get("product")
        .map(|v| format!("{v:?}"));
    assert!(
        product
            .as_ref()
            .is_some_and(|p| p.to_lowercase().contains("leveret")),
        "{product:?}"
    );
    let channel = within("channel", connection.open_channel()).await.unwrap();
    let queue = within(
        "declare",
        channel.queue_declare("", QueueDeclareOptions::default(), FieldTable::new()),
    )
    .await
    .unwrap();
    within("confirm.select", channel.confirm_select())
        .await
        .unwrap();
    let mut consumer = within(
        "consume",
        channel.basic_consume(
            &queue.name,
            "",
            BasicConsumeOptions::default(),
            FieldTable::new(),
        ),
    )
    .await
    .unwrap();
    for i in 0..100u32 {
        let confirm = channel
            .basic_publish(
                "",
                &queue.name,
                BasicPublishOptions::default(),
                BasicProperties::default(),
                Bytes::from(i.to_le_bytes().to_vec()),
            )
            .await
            .unwrap();
        if i == 99 {
            assert!(within("confirm", confirm).await.unwrap().is_ack());
        }
    }
    for i in 0..100u32 {
        let delivery = within("delivery", consumer.next()).await.expect("delivery");
        assert_eq!(&delivery.body[..], &i.to_le_bytes());
        delivery.ack().await.unwrap();
    }
    within("close", connection.close()).await.unwrap();
    Arc::into_inner(broker)
        .expect("the only handle")
        .shutdown()
        .await;
}

/// Content comes from the embedded broker whole (method, properties and
/// body in one value): a return, a get-ok and a delivery carry their
/// properties and body as over a socket, a large body in one piece.
#[tokio::test]
async fn returns_gets_and_deliveries_come_whole_over_the_value_link() {
    let broker = Arc::new(Broker::builder().start().await.expect("start"));
    let connection = within("connect", Connection::in_process(&broker))
        .await
        .expect("in-process connect");
    let channel = within("channel", connection.open_channel()).await.unwrap();
    let mut returns = channel.returns();
    let properties = BasicProperties {
        message_id: Some(ShortStr::from_static("m-1")),
        ..Default::default()
    };
    let publish = |key: ShortStr, mandatory: bool, body: Bytes| {
        channel.basic_publish(
            "",
            key,
            BasicPublishOptions { mandatory },
            properties.clone(),
            body,
        )
    };
    within(
        "publish",
        publish(
            ShortStr::from_static("nowhere"),
            true,
            Bytes::from_static(b"lost"),
        ),
    )
    .await
    .unwrap();
    let returned = within("return", returns.next()).await.expect("returned");
    assert_eq!(returned.reply_code, 312);
    assert_eq!(returned.properties, properties);
    assert_eq!(&returned.body[..], b"lost");

    let queue = within(
        "declare",
        channel.queue_declare("", QueueDeclareOptions::default(), FieldTable::new()),
    )
    .await
    .unwrap();
    let large = Bytes::from(vec![7u8; 300_000]);
    within("publish", publish(queue.name.clone(), false, large.clone()))
        .await
        .unwrap();
    within("publish", publish(queue.name.clone(), false, Bytes::new()))
        .await
        .unwrap();
    let got = within(
        "get",
        channel.basic_get(&queue.name, BasicGetOptions { no_ack: true }),
    )
    .await
    .unwrap()
    .expect("a message");
    assert_eq!(got.properties, properties);
    assert_eq!(got.body, large);
    let mut consumer = within(
        "consume",
        channel.basic_consume(
            &queue.name,
            "",
            BasicConsumeOptions {
                no_ack: true,
                ..Default::default()
            },
            FieldTable::new(),
        ),
    )
    .await
    .unwrap();
    let delivery = within("delivery", consumer.next()).await.expect("delivery");
    assert_eq!(delivery.properties, properties);
    assert!(delivery.body.is_empty());
    within("close", connection.close()).await.unwrap();
    Arc::into_inner(broker)
        .expect("the only handle")
        .shutdown()
        .await;
}

#[tokio::test]
async fn the_announced_product_is_the_builders() {
    let broker = Arc::new(
        Broker::builder()
            .product("RabbitMQ")
            .start()
            .await
            .expect("start"),
    );
    let connection = within("connect", Connection::in_process(&broker))
        .await
        .expect("in-process connect");
    let product = connection.server_properties().get("product").cloned();
    assert_eq!(product, Some(FieldValue::string("RabbitMQ")));
    connection.close().await.expect("close");
    Arc::into_inner(broker)
        .expect("the only handle")
        .shutdown()
        .await;
}

#[tokio::test]
async fn credentials_and_vhost_are_checked_in_process() {
    let broker = Arc::new(
        Broker::builder()
            .user("robot", "secret")
            .vhost("/robots")
            .permission("robot", "/robots", Permission::full())
            .start()
            .await
            .expect("start"),
    );
    let options = ConnectionOptions {
        username: "robot".into(),
        password: "secret".into(),
        vhost: "/robots".into(),
        ..Default::default()
    };
    let connection = within(
        "connect",
        Connection::in_process_with(&broker, options.clone()),
    )
    .await
    .expect("good credentials");
    within("close", connection.close()).await.unwrap();
    let wrong = ConnectionOptions {
        password: "wrong".into(),
        ..options
    };
    let refused = within("connect", Connection::in_process_with(&broker, wrong)).await;
    assert_eq!(
        refused.expect_err("bad password").reply_code(),
        Some(ReplyCode::AccessRefused)
    );
    Arc::into_inner(broker)
        .expect("the only handle")
        .shutdown()
        .await;
}

#[tokio::test]
async fn broker_shutdown_ends_in_process_connections() {
    let broker = Arc::new(Broker::builder().start().await.expect("start"));
    let connection = within("connect", Connection::in_process(&broker))
        .await
        .unwrap();
    Arc::into_inner(broker)
        .expect("the only handle")
        .shutdown()
        .await;
    let error = within("closed", connection.closed()).await;
    assert!(
        matches!(&error, Error::ConnectionClosed(r) if r.reply_code() == Some(ReplyCode::ConnectionForced)),
        "{error:?}"
    );
}

/// The fast path: an in-process consumer's deliveries are taken on the
/// broker's dispatching thread (counted by `inline_deliveries`), in order,
/// with their properties, acknowledged like any other (the queue is empty
/// once the channel closes, nothing requeued), and the queue counts them
/// as delivered; a consumer that leaves its buffer full gets the rest
/// through the reader, still in order.
#[leveret_tests::both_runtimes]
async fn in_process_deliveries_take_the_fast_path_in_order() {
    // Read one by one; then a burst beyond the consumer's buffer (1024).
    const READ: u32 = 300;
    const BURST: u32 = 1500;
    let broker = Arc::new(Broker::builder().start().await.expect("start"));
    let publisher = within("connect", Connection::in_process(&broker))
        .await
        .expect("in-process connect");
    let consuming = within("connect", Connection::in_process(&broker))
        .await
        .expect("in-process connect");
    let out = within("channel", publisher.open_channel()).await.unwrap();
    let inbound = within("channel", consuming.open_channel()).await.unwrap();
    let queue = within(
        "declare",
        inbound.queue_declare("", QueueDeclareOptions::default(), FieldTable::new()),
    )
    .await
    .unwrap();
    let mut consumer = within(
        "consume",
        inbound.basic_consume(
            &queue.name,
            "",
            BasicConsumeOptions::default(),
            FieldTable::new(),
        ),
    )
    .await
    .unwrap();
    within("confirm.select", out.confirm_select())
        .await
        .unwrap();
    let properties = BasicProperties {
        message_id: Some(ShortStr::from_static("fast")),
        ..Default::default()
    };
    // Read as they come (the fast path), then published in a burst the
    // consumer does not read until all are confirmed (its buffer fills,
    // the rest wait in the reader and the outbox).
    for (round, range) in [0..READ, READ..READ + BURST].into_iter().enumerate() {
        let mut confirms = Vec::new();
        for i in range {
            let body = Bytes::from(i.to_le_bytes().to_vec());
            let confirm = out
                .basic_publish(
                    "",
                    &queue.name,
                    BasicPublishOptions::default(),
                    properties.clone(),
                    body,
                )
                .await
                .unwrap();
            if round == 0 {
                assert!(within("confirm", confirm).await.unwrap().is_ack());
                let delivery = within("delivery", consumer.next()).await.expect("delivery");
                assert_eq!(&delivery.body[..], &i.to_le_bytes());
                assert_eq!(
                    delivery.properties.message_id,
                    Some(ShortStr::from_static("fast"))
                );
                delivery.ack().await.unwrap();
            } else {
                confirms.push(confirm);
            }
        }
        for confirm in confirms {
            assert!(within("confirm", confirm).await.unwrap().is_ack());
        }
    }
    let fast = consuming.inline_deliveries();
    // All those read one by one (but perhaps the first, which may find the
    // reader still handling consume-ok), never more than the buffer holds.
    assert!(
        fast >= u64::from(READ) - 1 && fast <= u64::from(READ) + 1024,
        "{fast} deliveries took the fast path"
    );
    assert_eq!(
        publisher.inline_deliveries(),
        0,
        "the publisher consumes nothing"
    );
    for i in READ..READ + BURST {
        let delivery = within("delivery", consumer.next()).await.expect("delivery");
        assert_eq!(&delivery.body[..], &i.to_le_bytes());
        delivery.ack().await.unwrap();
    }
    within("close", inbound.close()).await.unwrap();
    let check = within("channel", publisher.open_channel()).await.unwrap();
    let passive = within(
        "declare passive",
        check.queue_declare(
            &queue.name,
            QueueDeclareOptions {
                passive: true,
                ..Default::default()
            },
            FieldTable::new(),
        ),
    )
    .await
    .unwrap();
    assert_eq!(passive.message_count, 0, "every delivery was acknowledged");
    within("close", publisher.close()).await.unwrap();
    within("close", consuming.close()).await.unwrap();
    Arc::into_inner(broker)
        .expect("the only handle")
        .shutdown()
        .await;
}
