//! Publishing and consuming: deliveries with properties, prefetch, get,
//! ack/nack/reject, recover, mandatory returns, consumer cancellation by
//! either side.

mod common;

use bytes::Bytes;
use common::{broker, temp_queue, unique, within, TIMEOUT};
use leveret_client::{
    BasicAckOptions, BasicConsumeOptions, BasicGetOptions, BasicNackOptions, BasicProperties,
    BasicPublishOptions, BasicQosOptions, BasicRecoverOptions, BasicRejectOptions, Channel,
    Confirmation, Consumer, ConsumerEnd, Delivery, Error, FieldTable, FieldValue,
    QueueDeclareOptions, ReplyCode, ShortStr,
};

/// Publishes on a channel in confirm mode and waits for the ack, so the
/// message is in its queue afterwards (on any broker).
async fn publish(channel: &Channel, queue: &ShortStr, body: &str) {
    let confirm = within(
        "publish",
        channel.basic_publish(
            "",
            queue,
            BasicPublishOptions::default(),
            BasicProperties::default(),
            Bytes::copy_from_slice(body.as_bytes()),
        ),
    )
    .await
    .expect("publish");
    assert_eq!(
        within("confirm", confirm).await.expect("confirm"),
        Confirmation::Ack
    );
}

async fn confirming(broker: &common::TestBroker) -> (leveret_client::Connection, Channel) {
    let (connection, channel) = broker.channel().await;
    within("confirm.select", channel.confirm_select())
        .await
        .expect("confirm.select");
    (connection, channel)
}

async fn next(consumer: &mut Consumer) -> Delivery {
    within("delivery", consumer.next())
        .await
        .expect("consumer ended")
}

async fn consume(channel: &Channel, queue: &ShortStr, options: BasicConsumeOptions) -> Consumer {
    within(
        "basic.consume",
        channel.basic_consume(queue, "", options, FieldTable::new()),
    )
    .await
    .expect("basic.consume")
}

async fn ready(channel: &Channel, queue: &ShortStr) -> u32 {
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

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn publish_and_consume_with_properties() {
    let broker = broker().await;
    let (connection, channel) = broker.channel().await;
    let queue = temp_queue(&channel, "props").await;
    let mut consumer = consume(&channel, &queue.name, BasicConsumeOptions::default()).await;
    assert!(!consumer.tag().is_empty());
    let mut headers = FieldTable::new();
    headers.insert(ShortStr::from_static("robot"), FieldValue::string("r2"));
    headers.insert(ShortStr::from_static("n"), FieldValue::I32(-7));
    let properties = BasicProperties {
        content_type: Some(ShortStr::from_static("application/octet-stream")),
        headers: Some(headers),
        delivery_mode: Some(2),
        priority: Some(3),
        correlation_id: Some(ShortStr::from_static("corr")),
        reply_to: Some(ShortStr::from_static("replies")),
        message_id: Some(ShortStr::from_static("id-1")),
        timestamp: Some(1_700_000_000),
        kind: Some(ShortStr::from_static("pose")),
        app_id: Some(ShortStr::from_static("tests")),
        ..Default::default()
    };
    let _ = channel
        .basic_publish(
            "",
            &queue.name,
            BasicPublishOptions::default(),
            properties.clone(),
            Bytes::from_static(b"hello"),
        )
        .await
        .expect("publish");
    // An empty body and a body over several frames.
    let _ = channel
        .basic_publish(
            "",
            &queue.name,
            BasicPublishOptions::default(),
            BasicProperties::default(),
            Bytes::new(),
        )
        .await
        .expect("publish");
    let big: Bytes = (0..300_000u32).map(|i| (i % 253) as u8).collect();
    let _ = channel
        .basic_publish(
            "",
            &queue.name,
            BasicPublishOptions::default(),
            BasicProperties::default(),
            big.clone(),
        )
        .await
        .expect("publish");

    let first = next(&mut consumer).await;
    assert_eq!(&first.body[..], b"hello");
    assert_eq!(first.exchange, "");
    assert_eq!(first.routing_key, queue.name);
    assert_eq!(&first.consumer_tag, consumer.tag());
    assert!(!first.redelivered);
    assert_eq!(first.properties, properties);
    let second = next(&mut consumer).await;
    assert!(second.body.is_empty());
    assert!(second.delivery_tag > first.delivery_tag);
    let third = next(&mut consumer).await;
    assert_eq!(third.body, big);
    third.ack().await.expect("ack");
    channel
        .basic_ack(second.delivery_tag, BasicAckOptions { multiple: true })
        .await
        .expect("ack");
    channel
        .queue_delete(&queue.name, Default::default())
        .await
        .expect("delete");
    connection.close().await.expect("close");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn consumer_is_a_futures_stream() {
    let broker = broker().await;
    let (connection, channel) = confirming(&broker).await;
    let queue = temp_queue(&channel, "stream").await;
    let mut consumer = consume(
        &channel,
        &queue.name,
        BasicConsumeOptions {
            no_ack: true,
            ..Default::default()
        },
    )
    .await;
    for i in 0..3 {
        publish(&channel, &queue.name, &format!("m{i}")).await;
    }
    let mut bodies = Vec::new();
    while bodies.len() < 3 {
        let delivery = within(
            "poll_next",
            std::future::poll_fn(|cx| {
                futures_core::Stream::poll_next(std::pin::Pin::new(&mut consumer), cx)
            }),
        )
        .await
        .expect("stream item");
        bodies.push(delivery.body);
    }
    assert_eq!(bodies, ["m0", "m1", "m2"]);
    connection.close().await.expect("close");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn prefetch_limits_unacked_deliveries() {
    let broker = broker().await;
    let (connection, channel) = confirming(&broker).await;
    let queue = temp_queue(&channel, "qos").await;
    for i in 0..5 {
        publish(&channel, &queue.name, &format!("{i}")).await;
    }
    let consumer_channel = connection.open_channel().await.expect("channel");
    consumer_channel
        .basic_qos(2, BasicQosOptions::default())
        .await
        .expect("qos");
    let mut consumer = consume(&consumer_channel, &queue.name, Default::default()).await;
    let a = next(&mut consumer).await;
    let b = next(&mut consumer).await;
    assert_eq!((&a.body[..], &b.body[..]), (&b"0"[..], &b"1"[..]));
    // With two unacked, the broker holds the other three back.
    assert_eq!(ready(&channel, &queue.name).await, 3);
    a.ack().await.expect("ack");
    let c = next(&mut consumer).await;
    assert_eq!(&c.body[..], b"2");
    assert_eq!(ready(&channel, &queue.name).await, 2);
    consumer_channel
        .basic_ack(c.delivery_tag, BasicAckOptions { multiple: true })
        .await
        .expect("ack multiple");
    let d = next(&mut consumer).await;
    let e = next(&mut consumer).await;
    assert_eq!((&d.body[..], &e.body[..]), (&b"3"[..], &b"4"[..]));
    e.ack().await.expect("ack");
    d.ack().await.expect("ack");
    connection.close().await.expect("close");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn basic_get_empty_and_full() {
    let broker = broker().await;
    let (connection, channel) = confirming(&broker).await;
    let queue = temp_queue(&channel, "get").await;
    assert!(channel
        .basic_get(&queue.name, BasicGetOptions::default())
        .await
        .expect("get")
        .is_none());
    publish(&channel, &queue.name, "one").await;
    publish(&channel, &queue.name, "two").await;
    let first = channel
        .basic_get(&queue.name, BasicGetOptions::default())
        .await
        .expect("get")
        .expect("a message");
    assert_eq!(&first.body[..], b"one");
    assert_eq!(first.message_count, 1);
    assert_eq!(first.routing_key, queue.name);
    assert!(!first.redelivered);
    // Rejected with requeue, it comes back redelivered.
    first
        .reject(BasicRejectOptions { requeue: true })
        .await
        .expect("reject");
    let again = channel
        .basic_get(&queue.name, BasicGetOptions::default())
        .await
        .expect("get")
        .expect("a message");
    assert_eq!(&again.body[..], b"one");
    assert!(again.redelivered);
    again.ack().await.expect("ack");
    let second = channel
        .basic_get(&queue.name, BasicGetOptions { no_ack: true })
        .await
        .expect("get")
        .expect("a message");
    assert_eq!(&second.body[..], b"two");
    assert_eq!(second.message_count, 0);
    assert!(channel
        .basic_get(&queue.name, BasicGetOptions::default())
        .await
        .expect("get")
        .is_none());
    connection.close().await.expect("close");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn nack_multiple_requeues_and_reject_drops() {
    let broker = broker().await;
    let (connection, channel) = confirming(&broker).await;
    let queue = temp_queue(&channel, "nack").await;
    for body in ["a", "b", "c"] {
        publish(&channel, &queue.name, body).await;
    }
    let mut tags = Vec::new();
    for _ in 0..3 {
        let m = channel
            .basic_get(&queue.name, BasicGetOptions::default())
            .await
            .expect("get")
            .expect("a message");
        tags.push(m.delivery_tag);
    }
    // Nack the first two (multiple) with requeue; reject the third without.
    channel
        .basic_nack(
            tags[1],
            BasicNackOptions {
                multiple: true,
                requeue: true,
            },
        )
        .await
        .expect("nack");
    channel
        .basic_reject(tags[2], BasicRejectOptions { requeue: false })
        .await
        .expect("reject");
    let mut back = Vec::new();
    while let Some(m) = channel
        .basic_get(&queue.name, BasicGetOptions::default())
        .await
        .expect("get")
    {
        assert!(m.redelivered);
        back.push(m.body.clone());
        // Nack without requeue drops it.
        m.nack(BasicNackOptions::default()).await.expect("nack");
    }
    back.sort();
    assert_eq!(back, ["a", "b"]);
    assert_eq!(ready(&channel, &queue.name).await, 0);
    connection.close().await.expect("close");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn ack_of_an_unknown_delivery_tag_is_406() {
    let broker = broker().await;
    let (connection, channel) = broker.channel().await;
    channel
        .basic_ack(999, BasicAckOptions::default())
        .await
        .expect("ack is asynchronous");
    // The broker's channel.close shows up on the next call, and in closed().
    let err = within(
        "next call",
        channel.queue_declare("", Default::default(), FieldTable::new()),
    )
    .await
    .expect_err("channel closed by the broker");
    assert_eq!(
        err.reply_code(),
        Some(ReplyCode::PreconditionFailed),
        "{err:?}"
    );
    let reason = err.close_reason().expect("reason").clone();
    assert!(
        reason.text.starts_with("PRECONDITION_FAILED"),
        "{}",
        reason.text
    );
    assert_eq!((reason.class_id, reason.method_id), (60, 80));
    assert_eq!(channel.closed().await.close_reason(), Some(&reason));
    let err = channel
        .basic_ack(1, BasicAckOptions::default())
        .await
        .expect_err("closed");
    assert_eq!(err.close_reason(), Some(&reason));
    // The connection is unaffected.
    let other = connection.open_channel().await.expect("channel");
    assert!(other.is_open());
    connection.close().await.expect("close");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn recover_redelivers_unacked() {
    let broker = broker().await;
    let (connection, channel) = confirming(&broker).await;
    let queue = temp_queue(&channel, "recover").await;
    publish(&channel, &queue.name, "again").await;
    let consumer_channel = connection.open_channel().await.expect("channel");
    let mut consumer = consume(&consumer_channel, &queue.name, Default::default()).await;
    let first = next(&mut consumer).await;
    assert!(!first.redelivered);
    within(
        "recover",
        consumer_channel.basic_recover(BasicRecoverOptions { requeue: true }),
    )
    .await
    .expect("recover");
    let second = next(&mut consumer).await;
    assert_eq!(&second.body[..], b"again");
    assert!(second.redelivered);
    second.ack().await.expect("ack");
    assert_eq!(ready(&channel, &queue.name).await, 0);
    connection.close().await.expect("close");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn mandatory_unroutable_message_is_returned() {
    let broker = broker().await;
    let (connection, channel) = broker.channel().await;
    let mut returns = channel.returns();
    let key = unique("nowhere");
    let properties = BasicProperties {
        message_id: Some(ShortStr::from_static("lost-1")),
        ..Default::default()
    };
    let _ = channel
        .basic_publish(
            "amq.direct",
            key.as_str(),
            BasicPublishOptions { mandatory: true },
            properties.clone(),
            Bytes::from_static(b"unroutable"),
        )
        .await
        .expect("publish");
    // Not mandatory: silently dropped, nothing comes back for it.
    let _ = channel
        .basic_publish(
            "amq.direct",
            key.as_str(),
            BasicPublishOptions { mandatory: false },
            BasicProperties::default(),
            Bytes::from_static(b"dropped"),
        )
        .await
        .expect("publish");
    let returned = within("return", returns.next())
        .await
        .expect("returned message");
    assert_eq!(returned.reply_code(), Some(ReplyCode::NoRoute));
    assert_eq!(returned.reply_code, 312);
    assert!(returned
        .reply_text
        .as_str()
        .unwrap()
        .starts_with("NO_ROUTE"));
    assert_eq!(returned.exchange, "amq.direct");
    assert_eq!(returned.routing_key, key.as_str());
    assert_eq!(returned.properties, properties);
    assert_eq!(&returned.body[..], b"unroutable");
    // A routable mandatory message is not returned; a queue.declare round
    // trip shows the channel is still fine and orders after the publish.
    let queue = temp_queue(&channel, "routable").await;
    let _ = channel
        .basic_publish(
            "",
            &queue.name,
            BasicPublishOptions { mandatory: true },
            BasicProperties::default(),
            Bytes::from_static(b"routed"),
        )
        .await
        .expect("publish");
    let _ = channel
        .basic_publish(
            "",
            key.as_str(),
            BasicPublishOptions { mandatory: true },
            BasicProperties::default(),
            Bytes::from_static(b"second"),
        )
        .await
        .expect("publish");
    let returned = within("return", returns.next())
        .await
        .expect("returned message");
    assert_eq!(&returned.body[..], b"second");
    channel.close().await.expect("close channel");
    assert!(
        within("returns end", returns.next()).await.is_none(),
        "the stream ends with the channel"
    );
    connection.close().await.expect("close");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn client_cancel_ends_the_stream() {
    let broker = broker().await;
    let (connection, channel) = confirming(&broker).await;
    let queue = temp_queue(&channel, "cancel").await;
    let mut consumer = within(
        "basic.consume",
        channel.basic_consume(
            &queue.name,
            "my-tag",
            BasicConsumeOptions {
                no_ack: true,
                ..Default::default()
            },
            FieldTable::new(),
        ),
    )
    .await
    .expect("consume");
    assert_eq!(consumer.tag(), "my-tag");
    publish(&channel, &queue.name, "before").await;
    assert_eq!(&next(&mut consumer).await.body[..], b"before");
    within("cancel", consumer.cancel()).await.expect("cancel");
    assert!(within("end", consumer.next()).await.is_none());
    assert!(matches!(
        consumer.end_reason(),
        Some(ConsumerEnd::Cancelled)
    ));
    // Messages now stay in the queue.
    publish(&channel, &queue.name, "after").await;
    assert_eq!(ready(&channel, &queue.name).await, 1);
    connection.close().await.expect("close");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn queue_deletion_cancels_consumers_with_a_notification() {
    let broker = broker().await;
    let (connection, channel) = broker.channel().await;
    let queue = temp_queue(&channel, "deleted").await;
    let consumer_channel = connection.open_channel().await.expect("channel");
    let mut consumer = consume(&consumer_channel, &queue.name, Default::default()).await;
    channel
        .queue_delete(&queue.name, Default::default())
        .await
        .expect("delete");
    assert!(within("stream end", consumer.next()).await.is_none());
    assert!(
        matches!(consumer.end_reason(), Some(ConsumerEnd::CancelledByBroker)),
        "{:?}",
        consumer.end_reason()
    );
    // The channel itself stays open.
    assert!(consumer_channel.is_open());
    consumer_channel
        .queue_declare(
            "",
            QueueDeclareOptions {
                exclusive: true,
                ..Default::default()
            },
            FieldTable::new(),
        )
        .await
        .expect("channel still usable");
    connection.close().await.expect("close");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn channel_close_ends_consumers_with_its_reason() {
    let broker = broker().await;
    let (connection, channel) = broker.channel().await;
    let queue = temp_queue(&channel, "closing").await;
    let mut consumer = consume(&channel, &queue.name, Default::default()).await;
    // Provoke a channel error: 406 on an unknown delivery tag.
    channel
        .basic_ack(12345, BasicAckOptions::default())
        .await
        .expect("ack");
    assert!(within("stream end", consumer.next()).await.is_none());
    match consumer.end_reason() {
        Some(ConsumerEnd::ChannelClosed(error)) => {
            assert_eq!(error.reply_code(), Some(ReplyCode::PreconditionFailed))
        }
        other => panic!("unexpected end {other:?}"),
    }
    connection.close().await.expect("close");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn dropping_a_consumer_cancels_it() {
    let broker = broker().await;
    let (connection, channel) = confirming(&broker).await;
    let queue = temp_queue(&channel, "dropped").await;
    let consumer = consume(&channel, &queue.name, Default::default()).await;
    let counted = |n: u32| {
        let channel = channel.clone();
        let queue = queue.name.clone();
        async move {
            let passive = QueueDeclareOptions {
                passive: true,
                ..Default::default()
            };
            loop {
                let info = channel
                    .queue_declare(&queue, passive, FieldTable::new())
                    .await
                    .expect("declare");
                if info.consumer_count == n {
                    return;
                }
                tokio::task::yield_now().await;
            }
        }
    };
    within("one consumer", counted(1)).await;
    drop(consumer);
    within("no consumer", counted(0)).await;
    publish(&channel, &queue.name, "kept").await;
    assert_eq!(ready(&channel, &queue.name).await, 1);
    connection.close().await.expect("close");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn many_channels_consume_concurrently() {
    let broker = broker().await;
    let connection = broker.connect().await;
    let setup = connection.open_channel().await.expect("channel");
    let mut tasks = Vec::new();
    for worker in 0..4 {
        let queue = temp_queue(&setup, &format!("worker{worker}")).await.name;
        let connection = connection.clone();
        tasks.push(tokio::spawn(async move {
            let channel = connection.open_channel().await.expect("channel");
            channel.confirm_select().await.expect("confirm");
            let mut consumer = channel
                .basic_consume(
                    &queue,
                    "",
                    BasicConsumeOptions::default(),
                    FieldTable::new(),
                )
                .await
                .expect("consume");
            for i in 0..50 {
                let _ = channel
                    .basic_publish(
                        "",
                        &queue,
                        BasicPublishOptions::default(),
                        BasicProperties::default(),
                        Bytes::from(format!("{worker}:{i}")),
                    )
                    .await
                    .expect("publish");
            }
            assert!(channel.wait_for_confirms().await.expect("confirms"));
            for i in 0..50 {
                let d = consumer.next().await.expect("delivery");
                assert_eq!(d.body, format!("{worker}:{i}"));
                d.ack().await.expect("ack");
            }
            channel.close().await.expect("close");
        }));
    }
    for task in tasks {
        tokio::time::timeout(TIMEOUT, task)
            .await
            .expect("worker in time")
            .expect("worker");
    }
    connection.close().await.expect("close");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn consumer_buffer_is_bounded_and_backpressure_resumes() {
    let broker = broker().await;
    // Publisher and consumer on separate connections: a full consumer
    // buffer pauses reading its whole connection.
    let (publisher, channel) = confirming(&broker).await;
    let queue = temp_queue(&channel, "backpressure").await;
    let (consumer_connection, consumer_channel) = broker.channel().await;
    // A prefetch of 3 sizes the consumer's buffer to 3; delivered no-ack
    // (no prefetch applies), 40 messages fill it and pause the reader
    // until the consumer catches up.
    consumer_channel
        .basic_qos(3, BasicQosOptions::default())
        .await
        .expect("qos");
    let mut consumer = consume(
        &consumer_channel,
        &queue.name,
        BasicConsumeOptions {
            no_ack: true,
            ..Default::default()
        },
    )
    .await;
    for i in 0..40 {
        publish(&channel, &queue.name, &i.to_string()).await;
    }
    for i in 0..40 {
        assert_eq!(next(&mut consumer).await.body, i.to_string());
    }
    // Replies on the paused connection flow again.
    assert!(consumer_channel.is_open());
    within("close", consumer_connection.close())
        .await
        .expect("close");
    publisher.close().await.expect("close");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn operations_on_a_closed_connection_fail() {
    let broker = broker().await;
    let (connection, channel) = broker.channel().await;
    connection.close().await.expect("close");
    let err = channel
        .basic_publish(
            "",
            "q",
            BasicPublishOptions::default(),
            BasicProperties::default(),
            Bytes::new(),
        )
        .await
        .expect_err("closed");
    assert!(matches!(err, Error::Closed), "{err:?}");
    assert!(!channel.is_open());
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn cancel_and_close_do_not_hang_on_a_full_consumer_buffer() {
    let broker = broker().await;
    let (publisher, channel) = confirming(&broker).await;
    let queue = temp_queue(&channel, "undrained").await;
    let (consumer_connection, consumer_channel) = broker.channel().await;
    consumer_channel
        .basic_qos(1, BasicQosOptions::default())
        .await
        .expect("qos");
    let no_ack = BasicConsumeOptions {
        no_ack: true,
        ..Default::default()
    };
    let mut consumer = consume(&consumer_channel, &queue.name, no_ack).await;
    for i in 0..20 {
        publish(&channel, &queue.name, &i.to_string()).await;
    }
    // The first delivery is buffered; the reader is now (or soon) waiting
    // for room for the second. Cancelling must still get its cancel-ok.
    within("cancel", consumer.cancel()).await.expect("cancel");
    let mut drained = 0;
    while within("drain", consumer.next()).await.is_some() {
        drained += 1;
    }
    assert!(drained >= 1);
    assert!(matches!(
        consumer.end_reason(),
        Some(ConsumerEnd::Cancelled)
    ));
    // Same for closing the connection under a second undrained consumer.
    let second = connection_consumer(&consumer_connection, &queue.name, no_ack).await;
    within("close", consumer_connection.close())
        .await
        .expect("close");
    drop(second);
    publisher.close().await.expect("close");
}

async fn connection_consumer(
    connection: &leveret_client::Connection,
    queue: &ShortStr,
    options: BasicConsumeOptions,
) -> Consumer {
    let channel = connection.open_channel().await.expect("channel");
    channel
        .basic_qos(1, BasicQosOptions::default())
        .await
        .expect("qos");
    let consumer = consume(&channel, queue, options).await;
    // Wait until it holds a delivery, so its buffer is full.
    let passive = QueueDeclareOptions {
        passive: true,
        ..Default::default()
    };
    let _ = channel
        .queue_declare(queue, passive, FieldTable::new())
        .await;
    consumer
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn bodies_around_frame_max_boundaries() {
    let broker = broker().await;
    // frame_max 4096: a body frame carries at most 4088 bytes.
    let connection = leveret_client::Connection::connect(&broker.uri_with("frame_max=4096"))
        .await
        .expect("connect");
    assert_eq!(connection.tuning().frame_max, 4096);
    let channel = connection.open_channel().await.expect("channel");
    channel.confirm_select().await.expect("confirm.select");
    let queue = temp_queue(&channel, "boundaries").await;
    let mut consumer = consume(
        &channel,
        &queue.name,
        BasicConsumeOptions {
            no_ack: true,
            ..Default::default()
        },
    )
    .await;
    let sizes = [0usize, 1, 4087, 4088, 4089, 8176, 8177, 100_000];
    for (n, size) in sizes.iter().enumerate() {
        let body: Bytes = (0..*size).map(|i| (i * 7 + n) as u8).collect();
        let _ = channel
            .basic_publish(
                "",
                &queue.name,
                BasicPublishOptions::default(),
                BasicProperties::default(),
                body,
            )
            .await
            .expect("publish");
    }
    assert!(within("confirms", channel.wait_for_confirms())
        .await
        .expect("confirms"));
    for (n, size) in sizes.iter().enumerate() {
        let delivery = next(&mut consumer).await;
        let expected: Bytes = (0..*size).map(|i| (i * 7 + n) as u8).collect();
        assert_eq!(delivery.body.len(), *size);
        assert_eq!(delivery.body, expected, "body of {size} bytes");
    }
    connection.close().await.expect("close");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn ten_thousand_messages_arrive_in_order() {
    let broker = broker().await;
    let (publisher, channel) = confirming(&broker).await;
    let queue = temp_queue(&channel, "bulk").await;
    let (consumer_connection, consumer_channel) = broker.channel().await;
    consumer_channel
        .basic_qos(200, BasicQosOptions::default())
        .await
        .expect("qos");
    let mut consumer = consume(&consumer_channel, &queue.name, Default::default()).await;
    const N: usize = 10_000;
    let payload = Bytes::from(vec![0x5a; 1000]);
    let publishing = tokio::spawn({
        let channel = channel.clone();
        let queue = queue.name.clone();
        async move {
            for i in 0..N {
                let properties = BasicProperties {
                    message_id: Some(ShortStr::try_from(i.to_string()).expect("id")),
                    ..Default::default()
                };
                let _ = channel
                    .basic_publish(
                        "",
                        &queue,
                        BasicPublishOptions::default(),
                        properties,
                        payload.clone(),
                    )
                    .await
                    .expect("publish");
            }
            channel.wait_for_confirms().await.expect("confirms")
        }
    });
    let consuming = async {
        for i in 0..N {
            let delivery = consumer.next().await.expect("delivery");
            assert_eq!(
                delivery
                    .properties
                    .message_id
                    .as_ref()
                    .and_then(|m| m.as_str()),
                Some(i.to_string().as_str())
            );
            assert_eq!(delivery.body.len(), 1000);
            if i % 50 == 49 {
                consumer_channel
                    .basic_ack(delivery.delivery_tag, BasicAckOptions { multiple: true })
                    .await
                    .expect("ack");
            }
        }
    };
    tokio::time::timeout(std::time::Duration::from_secs(60), consuming)
        .await
        .expect("all delivered in time");
    assert!(within("publisher", publishing).await.expect("join"));
    consumer_connection.close().await.expect("close");
    publisher.close().await.expect("close");
}
