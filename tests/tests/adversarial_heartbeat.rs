//! A consumer that stops reading (issue 29, finding 4): its socket fills,
//! the broker's writer for it blocks, and the client sends nothing more,
//! heartbeats included. The broker must close it after two missed
//! heartbeats, as RabbitMQ does whether or not its writer is blocked, and
//! give back what it held: the deliveries waiting for the writer and the
//! connection's exclusive queue. Tried twice: with the connection's
//! reader idle, and with the reader itself waiting to answer a last
//! request (a `channel.open`) for which the full outbox has no room.

#[macro_use]
mod common;

use common::raw::{short, Method, Raw};
use common::*;
use leveret_broker::{Admin, Overview};
use leveret_protocol::{BasicConsume, ChannelOpen, QueueDeclare};
use std::time::Duration;

/// The heartbeat the stalled consumer asks for, seconds.
const HEARTBEAT: u16 = 1;
/// A hang limit for the close (RabbitMQ closes after two heartbeats).
const CLOSE_HANG: Duration = Duration::from_secs(15);

/// Polls the overview until `done` holds, within `hang`.
async fn overview_until(
    admin: &Admin,
    hang: Duration,
    done: impl Fn(&Overview) -> bool,
) -> Overview {
    let deadline = tokio::time::Instant::now() + hang;
    loop {
        let overview = admin.overview();
        if done(&overview) || tokio::time::Instant::now() >= deadline {
            return overview;
        }
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
}

#[both_runtimes]
async fn a_consumer_that_stops_reading_is_closed_after_missed_heartbeats_and_freed() {
    // 400 × 64 KiB = 25 MiB, far beyond the sockets' buffers; fewer
    // deliveries than the outbox holds, so the reader stays free.
    stalled_consumer_is_closed(400, 64 * 1024, false).await;
}

#[both_runtimes]
async fn a_stalled_consumer_waiting_for_room_for_a_reply_is_closed_too() {
    // 3,000 × 8 KiB: the outbox (512 items) fills behind the blocked
    // writer, and the reply to the last request finds no room.
    stalled_consumer_is_closed(3000, 8 * 1024, true).await;
}

/// A consumer of `messages` no-ack deliveries of `body` bytes that stops
/// reading (after one last `channel.open` if `last_request`) must be closed and
/// freed.
async fn stalled_consumer_is_closed(messages: usize, body: usize, last_request: bool) {
    let b = TestBroker::leveret(leveret_broker::Broker::builder()).await;
    let admin = b.admin().expect("in-process broker");
    let mut stalled = Raw::open_with_heartbeat(&b, HEARTBEAT).await;
    stalled.open_channel(1).await;
    let queue = unique("stalled-consumer");
    let declare = QueueDeclare {
        queue: short(&queue),
        exclusive: true,
        ..Default::default()
    };
    stalled
        .call(1, declare, |m| matches!(m, Method::QueueDeclareOk(_)))
        .await;

    let (publisher, channel) = lp::open(&b).await;
    let payload = vec![7u8; body];
    for _ in 0..messages {
        lp::publish(&channel, "", &queue, &payload).await;
    }
    let queued = overview_until(&admin, CLOSE_HANG, |o| {
        o.queue_totals.messages_ready == messages as u64
    })
    .await;
    assert_eq!(queued.queue_totals.messages_ready, messages as u64);
    assert!(
        queued.memory_used >= messages * body,
        "{}",
        queued.memory_used
    );
    assert_eq!(queued.object_totals.connections, 2);

    // It consumes without acks, then neither reads nor writes again: the
    // broker's writer fills the socket and blocks on it.
    let consume = BasicConsume {
        queue: short(&queue),
        no_ack: true,
        ..Default::default()
    };
    stalled
        .call(1, consume, |m| matches!(m, Method::BasicConsumeOk(_)))
        .await;
    if last_request {
        tokio::time::sleep(Duration::from_millis(500)).await;
        stalled.send(2, ChannelOpen::default()).await;
    }
    let stalled_at = tokio::time::Instant::now();
    let closed = overview_until(&admin, CLOSE_HANG, |o| o.object_totals.connections == 1).await;
    eprintln!(
        "stalled consumer: {} connections left after {:?}",
        closed.object_totals.connections,
        stalled_at.elapsed()
    );
    assert_eq!(
        closed.object_totals.connections, 1,
        "the stalled consumer is closed within {CLOSE_HANG:?}"
    );
    // Its exclusive queue went with it, and every byte it counted.
    let freed = overview_until(&admin, CLOSE_HANG, |o| {
        o.memory_used == 0 && o.queue_totals.messages() == 0
    })
    .await;
    assert_eq!(freed.memory_used, 0, "{freed:?}");
    assert_eq!(freed.queue_totals.messages(), 0);
    assert!(admin.queues().iter().all(|q| q.name != queue));
    // The publisher is served as before.
    lp::publish(&channel, "", "nowhere", b"still here").await;
    let _ = publisher.close(200, "bye").await;
    drop(stalled);
    b.stop().await;
}
