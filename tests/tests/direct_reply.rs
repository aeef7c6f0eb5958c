//! RabbitMQ's direct reply-to (`amq.rabbitmq.reply-to`): RPC replies that
//! go straight to the requester's no-ack consumer, without a reply queue.

#[macro_use]
mod common;

use common::*;
use futures_lite::StreamExt;

#[both_runtimes]
async fn an_rpc_reply_reaches_the_requester_without_a_queue() {
    let b = broker().await;
    let conn = lp::connect(&b).await;
    let client = lp::channel(&conn).await;
    let requests = lp::queue(&client, "rpc-requests").await;
    let mut replies = tmo!(client.basic_consume(
        "amq.rabbitmq.reply-to",
        "",
        lp::BasicConsumeOptions {
            no_ack: true,
            ..Default::default()
        },
        lp::FieldTable::default()
    ))
    .expect("consume from the reply pseudo-queue");
    let props = lp::BasicProperties::default()
        .with_reply_to("amq.rabbitmq.reply-to".into())
        .with_correlation_id("c-1".into());
    tmo!(client.basic_publish(
        "",
        &requests,
        lp::BasicPublishOptions::default(),
        b"ping",
        props
    ))
    .expect("request");

    // The server side sees a unique reply address, and answers to it.
    let server = lp::channel(&conn).await;
    let request = tmo!(server.basic_get(&requests, lp::BasicGetOptions { no_ack: true }))
        .expect("get")
        .expect("the request");
    let reply_to = request
        .delivery
        .properties
        .reply_to()
        .clone()
        .expect("reply_to")
        .to_string();
    assert!(
        reply_to.starts_with("amq.rabbitmq.reply-to."),
        "reply_to rewritten: {reply_to}"
    );
    let answer = lp::BasicProperties::default().with_correlation_id("c-1".into());
    tmo!(server.basic_publish(
        "",
        &reply_to,
        lp::BasicPublishOptions::default(),
        b"pong",
        answer
    ))
    .expect("reply");

    let reply = tmo!(replies.next()).expect("a reply").expect("delivery");
    assert_eq!(reply.data, b"pong");
    assert_eq!(
        reply
            .properties
            .correlation_id()
            .as_ref()
            .map(|c| c.as_str()),
        Some("c-1")
    );
}

#[both_runtimes]
async fn reply_to_without_a_reply_consumer_or_with_acks_is_406() {
    let b = broker().await;
    let conn = lp::connect(&b).await;
    let ch = lp::channel(&conn).await;
    let q = lp::queue(&ch, "rpc-no-consumer").await;
    // The channel close answers a publish (no reply of its own), so it is
    // watched for rather than raced against the next method.
    let mut errors = lp::watch_errors(&ch);
    let props = lp::BasicProperties::default().with_reply_to("amq.rabbitmq.reply-to".into());
    let _ = tmo!(ch.basic_publish("", &q, lp::BasicPublishOptions::default(), b"x", props));
    // "PRECONDITION_FAILED - fast reply consumer does not exist"
    let err = tmo!(errors.recv()).expect("channel closed");
    lp::assert_err::<()>(Err(err), 406, "PRECONDITION_FAILED");

    let ch = lp::channel(&conn).await;
    // "PRECONDITION_FAILED - reply consumer cannot acknowledge"
    let res = tmo!(ch.basic_consume(
        "amq.rabbitmq.reply-to",
        "",
        lp::BasicConsumeOptions::default(),
        lp::FieldTable::default()
    ));
    lp::assert_err(res, 406, "PRECONDITION_FAILED");
}

/// A requester that stops reading its socket must not stall the responder:
/// replies are handed over without waiting (RabbitMQ's direct reply-to has no
/// flow control and is at-most-once), so replies that find the requester's
/// connection full are dropped, and the responder's connection goes on
/// serving everyone else.
#[both_runtimes]
async fn a_requester_that_stops_reading_does_not_stall_its_responder() {
    // Far more than the requester's connection can hold: its outbox, the
    // socket buffers of a peer that never reads, and then some.
    const REPLIES: usize = 1000;
    const REPLY_BYTES: usize = 32 * 1024;
    let b = broker().await;
    let responder_conn = lp::connect(&b).await;
    let responder = lp::channel(&responder_conn).await;
    let requests = lp::queue(&responder, "rpc-stalled").await;
    let no_ack = lp::BasicConsumeOptions {
        no_ack: true,
        ..Default::default()
    };
    let mut incoming = lp::consume_opts(&responder, &requests, "server", no_ack).await;

    // The stalled requester: raw frames, and after its request it never
    // reads again.
    let mut stalled = raw::Raw::open(&b).await;
    stalled.open_channel(1).await;
    let consume = leveret_protocol::BasicConsume {
        queue: raw::short("amq.rabbitmq.reply-to"),
        no_ack: true,
        ..Default::default()
    };
    stalled
        .call(1, consume, |m| matches!(m, raw::Method::BasicConsumeOk(_)))
        .await;
    let asks_for_replies = raw::BasicProperties {
        reply_to: Some(raw::short("amq.rabbitmq.reply-to")),
        ..Default::default()
    };
    let request = raw::publish_frames(1, "", &requests, &asks_for_replies, b"flood me", 0);
    stalled.send_bytes(&request).await;

    let request = lp::next(&mut incoming).await;
    let reply_to = request.properties.reply_to().clone().expect("reply_to");
    let flood = vec![0u8; REPLY_BYTES];
    for _ in 0..REPLIES {
        lp::publish(&responder, "", reply_to.as_str(), &flood).await;
    }
    // The responder's connection still answers at once...
    let passive = lp::QueueDeclareOptions {
        passive: true,
        ..Default::default()
    };
    tmo!(responder.queue_declare(&requests, passive, lp::FieldTable::default()))
        .expect("the responder's channel is served");

    // ...and still serves another requester.
    let requester_conn = lp::connect(&b).await;
    let requester = lp::channel(&requester_conn).await;
    let mut replies = lp::consume_opts(&requester, "amq.rabbitmq.reply-to", "", no_ack).await;
    let props = lp::BasicProperties::default().with_reply_to("amq.rabbitmq.reply-to".into());
    lp::publish_props(&requester, "", &requests, b"ping", props).await;
    let request = lp::next(&mut incoming).await;
    assert_eq!(request.data, b"ping");
    let reply_to = request.properties.reply_to().clone().expect("reply_to");
    lp::publish(&responder, "", reply_to.as_str(), b"pong").await;
    assert_eq!(lp::next(&mut replies).await.data, b"pong");
    drop(stalled);
}
