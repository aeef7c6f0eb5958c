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
    let (queue, mut consumer) = consumed_queue_with_confirms(&channel, &channel).await;
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
    let (queue, mut consumer) = consumed_queue_with_confirms(&out, &inbound).await;
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

/// Publishes a numbered message; its confirm.
/// A server-named queue declared and consumed on `consuming`, with
/// `publishing` in confirm mode (the same channel or another).
async fn consumed_queue_with_confirms(
    publishing: &leveret_client::Channel,
    consuming: &leveret_client::Channel,
) -> (leveret_client::QueueInfo, leveret_client::Consumer) {
    let queue = within(
        "declare",
        consuming.queue_declare("", QueueDeclareOptions::default(), FieldTable::new()),
    )
    .await
    .unwrap();
    within("confirm.select", publishing.confirm_select())
        .await
        .unwrap();
    let consumer = within(
        "consume",
        consuming.basic_consume(
            &queue.name,
            "",
            BasicConsumeOptions::default(),
            FieldTable::new(),
        ),
    )
    .await
    .unwrap();
    (queue, consumer)
}

async fn publish_numbered(
    channel: &leveret_client::Channel,
    queue: &ShortStr,
    i: u32,
    properties: BasicProperties,
) -> leveret_client::PublishConfirm {
    within(
        "publish",
        channel.basic_publish(
            "",
            queue.clone(),
            BasicPublishOptions::default(),
            properties,
            Bytes::from(i.to_le_bytes().to_vec()),
        ),
    )
    .await
    .expect("publish")
}

/// The ready messages of a queue, from a passive declare.
async fn ready(channel: &leveret_client::Channel, queue: &ShortStr) -> u32 {
    within(
        "declare passive",
        channel.queue_declare(
            queue.clone(),
            QueueDeclareOptions {
                passive: true,
                ..Default::default()
            },
            FieldTable::new(),
        ),
    )
    .await
    .expect("passive declare")
    .message_count
}

/// The publish side of the in-process fast path: a publish whose
/// connection's loop is free and whose link holds nothing sent before is
/// handled on the publishing thread (counted by `inline_publishes`); one
/// published while something waits in the link (here: room held in it)
/// goes through the link. Mixed on one channel they keep their order and
/// their confirms' numbering, and the queue counts every one.
#[leveret_tests::both_runtimes]
async fn in_process_publishes_run_on_the_callers_thread_in_order() {
    const ROUNDS: u32 = 100;
    let broker = Arc::new(Broker::builder().start().await.expect("start"));
    let publisher = within("connect", Connection::in_process(&broker))
        .await
        .expect("in-process connect");
    let consuming = within("connect", Connection::in_process(&broker))
        .await
        .expect("in-process connect");
    let out = within("channel", publisher.open_channel()).await.unwrap();
    let inbound = within("channel", consuming.open_channel()).await.unwrap();
    let (queue, mut consumer) = consumed_queue_with_confirms(&out, &inbound).await;
    let mut next = 0u32;
    for _ in 0..ROUNDS {
        // One with the link free (the fast path when the loop is free),
        // then two while room is held in the link (through the link),
        // then one more right behind them.
        let mut confirms =
            vec![publish_numbered(&out, &queue.name, next, Default::default()).await];
        let held = out.try_reserve().unwrap().expect("room in the link");
        for i in next + 1..next + 3 {
            confirms.push(publish_numbered(&out, &queue.name, i, Default::default()).await);
        }
        drop(held);
        confirms.push(publish_numbered(&out, &queue.name, next + 3, Default::default()).await);
        for confirm in confirms {
            assert!(within("confirm", confirm).await.unwrap().is_ack());
        }
        for i in next..next + 4 {
            let delivery = within("delivery", consumer.next()).await.expect("delivery");
            assert_eq!(&delivery.body[..], &i.to_le_bytes(), "in publish order");
            delivery.ack().await.unwrap();
        }
        next += 4;
    }
    let fast = publisher.inline_publishes();
    // Never those published with room held; the first of each round
    // unless the connection's task happened to run its loop just then
    // (how often depends on the scheduler: on a loaded machine most
    // rounds can find it running, so only "some" is asserted).
    assert!(
        fast >= 1 && fast <= 2 * u64::from(ROUNDS),
        "{fast} of {next} publishes took the fast path"
    );
    assert_eq!(
        consuming.inline_publishes(),
        0,
        "the consumer publishes nothing"
    );
    within("close", inbound.close()).await.unwrap();
    assert_eq!(
        ready(&out, &queue.name).await,
        0,
        "every message acknowledged"
    );
    within("close", publisher.close()).await.unwrap();
    within("close", consuming.close()).await.unwrap();
    Arc::into_inner(broker)
        .expect("the only handle")
        .shutdown()
        .await;
}

/// On the fast path the broker's rules hold as through the link: a queue
/// at its max-length with `reject-publish` nacks the publish, and a
/// message past its expiration is never delivered.
#[leveret_tests::both_runtimes]
async fn in_process_fast_path_keeps_max_length_and_expiration() {
    let broker = Arc::new(Broker::builder().start().await.expect("start"));
    let publisher = within("connect", Connection::in_process(&broker))
        .await
        .expect("in-process connect");
    let out = within("channel", publisher.open_channel()).await.unwrap();
    within("confirm.select", out.confirm_select())
        .await
        .unwrap();
    let mut arguments = FieldTable::new();
    arguments.insert(ShortStr::from_static("x-max-length"), FieldValue::I32(2));
    arguments.insert(
        ShortStr::from_static("x-overflow"),
        FieldValue::string("reject-publish"),
    );
    let full = within(
        "declare",
        out.queue_declare("", QueueDeclareOptions::default(), arguments),
    )
    .await
    .unwrap();
    let mut outcomes = Vec::new();
    for i in 0..4 {
        let confirm = publish_numbered(&out, &full.name, i, Default::default()).await;
        outcomes.push(within("confirm", confirm).await.unwrap().is_ack());
    }
    assert_eq!(
        outcomes,
        [true, true, false, false],
        "acked while room, then nacked"
    );
    assert_eq!(ready(&out, &full.name).await, 2);

    let expiring = within(
        "declare",
        out.queue_declare("", QueueDeclareOptions::default(), FieldTable::new()),
    )
    .await
    .unwrap();
    let short_lived = BasicProperties {
        expiration: Some(ShortStr::from_static("1")),
        ..Default::default()
    };
    let confirm = publish_numbered(&out, &expiring.name, 0, short_lived).await;
    assert!(within("confirm", confirm).await.unwrap().is_ack());
    tokio::time::sleep(std::time::Duration::from_millis(20)).await;
    let got = within(
        "get",
        out.basic_get(&expiring.name, BasicGetOptions { no_ack: true }),
    )
    .await
    .unwrap();
    assert!(got.is_none(), "an expired message is never delivered");
    assert_eq!(ready(&out, &expiring.name).await, 0);
    // Both runtimes' publishes here were free to take the fast path; on
    // the current-thread runtime nothing else can hold the loop.
    assert!(publisher.inline_publishes() >= 1);
    within("close", publisher.close()).await.unwrap();
    Arc::into_inner(broker)
        .expect("the only handle")
        .shutdown()
        .await;
}

/// Once the broker's runtime is gone, a publish never runs the connection's
/// loop on the publishing thread (there is no loop left to run): it fails
/// or goes nowhere, without a panic.
#[test]
fn a_publish_after_the_runtime_is_gone_runs_no_loop() {
    let runtime = tokio::runtime::Runtime::new().expect("runtime");
    let (broker, connection, channel) = runtime.block_on(async {
        let broker = Arc::new(Broker::builder().start().await.expect("start"));
        let connection = within("connect", Connection::in_process(&broker))
            .await
            .expect("in-process connect");
        let channel = within("channel", connection.open_channel()).await.unwrap();
        (broker, connection, channel)
    });
    drop(runtime);
    if let Ok(Some(slot)) = channel.try_reserve() {
        let _ = slot.basic_publish(
            "",
            "nowhere",
            BasicPublishOptions::default(),
            BasicProperties::default(),
            Bytes::from_static(b"late"),
        );
    }
    assert_eq!(connection.inline_publishes(), 0);
    drop((channel, connection, broker));
}

/// A publish handled on the publishing thread has its confirm when
/// `basic_publish` returns: the broker settles it there and the client
/// takes it inline (counted by `inline_confirms`), acks and nacks alike,
/// with no reader task in between. A publish whose `basic.return` comes
/// first (mandatory, unroutable) has its confirm through the reader,
/// after the return, as ever. On the current-thread runtime no task runs
/// between the publish and the look, so the confirm is there at once; on
/// the multi-thread one, the answers are the same.
#[leveret_tests::both_runtimes]
async fn in_process_confirms_come_with_a_fast_path_publish() {
    use leveret_client::Confirmation::{Ack, Nack};
    use std::future::IntoFuture;
    let broker = Arc::new(Broker::builder().start().await.expect("start"));
    let publisher = within("connect", Connection::in_process(&broker))
        .await
        .expect("in-process connect");
    let out = within("channel", publisher.open_channel()).await.unwrap();
    within("confirm.select", out.confirm_select())
        .await
        .unwrap();
    let mut arguments = FieldTable::new();
    arguments.insert(ShortStr::from_static("x-max-length"), FieldValue::I32(2));
    arguments.insert(
        ShortStr::from_static("x-overflow"),
        FieldValue::string("reject-publish"),
    );
    let full = within(
        "declare",
        out.queue_declare("", QueueDeclareOptions::default(), arguments),
    )
    .await
    .unwrap();
    let at_once = tokio::runtime::Handle::current().runtime_flavor()
        == tokio::runtime::RuntimeFlavor::CurrentThread;
    let mut answers = Vec::new();
    for i in 0..4 {
        let mut confirm = publish_numbered(&out, &full.name, i, Default::default())
            .await
            .into_future();
        let answer = if at_once {
            confirm
                .try_answer()
                .expect("confirmed when the publish returned")
        } else {
            within("confirm", confirm).await
        };
        answers.push(answer.unwrap());
    }
    assert_eq!(answers, [Ack, Ack, Nack, Nack]);
    if at_once {
        assert_eq!(publisher.inline_confirms(), 4);
    }

    let mut returns = out.returns();
    let confirm = within(
        "publish",
        out.basic_publish(
            "",
            "no-such-queue",
            BasicPublishOptions { mandatory: true },
            BasicProperties::default(),
            Bytes::from_static(b"unroutable"),
        ),
    )
    .await
    .expect("publish");
    let mut confirm = confirm.into_future();
    if at_once {
        assert!(
            confirm.try_answer().is_none(),
            "behind its return, through the reader"
        );
    }
    assert!(within("confirm", confirm).await.unwrap().is_ack());
    let returned = returns
        .try_next()
        .expect("the return came before its confirm");
    assert_eq!(returned.reply_code, ReplyCode::NoRoute.code());
    within("close", publisher.close()).await.unwrap();
    Arc::into_inner(broker)
        .expect("the only handle")
        .shutdown()
        .await;
}
