//! The broker as the `leveret` binary runs it: every connection on one
//! current-thread runtime that busy-polls after socket reads, driven by
//! lapin. Confirms of persistent messages come back from the storage
//! thread (a wake from outside the runtime), round trips keep the spinner
//! busy, and shutdown still completes.

#[macro_use]
mod common;

use common::*;
use leveret_broker::Broker;
use std::time::Duration;

const MESSAGES: u32 = 500;
const ROUND_TRIPS: u32 = 200;

#[both_runtimes]
async fn a_busy_polling_broker_confirms_delivers_in_order_echoes_and_shuts_down() {
    let dir = std::env::temp_dir().join(unique("leveret-busy-poll"));
    let b = TestBroker::leveret(
        Broker::builder()
            .data_dir(&dir)
            .busy_poll(Duration::from_micros(200)),
    )
    .await;

    let (_connection, channel) = lp::open(&b).await;
    let durable = lp::QueueDeclareOptions {
        durable: true,
        ..Default::default()
    };
    let queue = unique("busy-poll");
    tmo!(channel.queue_declare(&queue, durable, lp::FieldTable::default())).expect("declare");
    tmo!(channel.confirm_select(lp::ConfirmSelectOptions::default())).expect("confirm.select");
    for seq in 0..MESSAGES {
        let persistent = lp::BasicProperties::default().with_delivery_mode(2);
        let confirmation =
            lp::publish_confirmed(&channel, "", &queue, seq.to_string().as_bytes(), persistent)
                .await;
        assert!(confirmation.is_ack(), "message {seq} confirmed");
    }
    let mut consumer = lp::consume(&channel, &queue, "in-order").await;
    for seq in 0..MESSAGES {
        let delivery = lp::next(&mut consumer).await;
        assert_eq!(delivery.data, seq.to_string().as_bytes());
        lp::ack(&channel, delivery.delivery_tag).await;
    }

    // Ping-pong through two queues and a second connection, one in flight.
    let echo_connection = lp::connect(&b).await;
    let echo = lp::channel(&echo_connection).await;
    let ping_queue = lp::queue(&channel, "busy-poll-ping").await;
    let pong_queue = lp::queue(&channel, "busy-poll-pong").await;
    let no_ack = lp::BasicConsumeOptions {
        no_ack: true,
        ..Default::default()
    };
    let mut pings = lp::consume_opts(&echo, &ping_queue, "echo", no_ack).await;
    let mut pongs = lp::consume_opts(&channel, &pong_queue, "pongs", no_ack).await;
    for seq in 0..ROUND_TRIPS {
        let body = seq.to_string();
        lp::publish(&channel, "", &ping_queue, body.as_bytes()).await;
        let ping = lp::next(&mut pings).await;
        lp::publish(&echo, "", &pong_queue, &ping.data).await;
        let pong = lp::next(&mut pongs).await;
        assert_eq!(pong.data, body.as_bytes());
    }

    within("shutdown", b.stop()).await;
    let _ = std::fs::remove_dir_all(&dir);
}
