//! Single active consumer (`x-single-active-consumer`) and consumer
//! priorities (`x-priority`) as RabbitMQ 3.10 has them: one consumer of
//! such a queue gets everything, the next registered takes over when it
//! is cancelled, its channel closes or its connection is lost (what it
//! held unacked comes back to the new one first, in order); a
//! higher-priority consumer gets messages while it has prefetch room, a
//! lower one only the overflow.

#[macro_use]
mod common;

use common::*;
use leveret_tests::fault_proxy::FaultProxy;
use lp::AMQPValue;

fn single_active() -> lp::FieldTable {
    lp::table(vec![("x-single-active-consumer", AMQPValue::Boolean(true))])
}

/// A consumer on a channel of its own with manual acks and `prefetch`
/// (0: none), with `arguments`.
async fn consumer_on(
    conn: &lp::Connection,
    queue: &str,
    tag: &str,
    prefetch: u16,
    arguments: lp::FieldTable,
) -> (lp::Channel, lp::Consumer) {
    let ch = lp::channel(conn).await;
    tmo!(ch.basic_qos(prefetch, Default::default())).expect("basic.qos");
    let consumer =
        tmo!(ch.basic_consume(queue, tag, Default::default(), arguments)).expect("basic.consume");
    (ch, consumer)
}

async fn publish_numbered(ch: &lp::Channel, queue: &str, range: std::ops::RangeInclusive<u32>) {
    for i in range {
        lp::publish(ch, "", queue, i.to_string().as_bytes()).await;
    }
}

/// The bodies and redelivered flags of the next `n` deliveries.
async fn next_n(consumer: &mut lp::Consumer, n: usize) -> Vec<(String, bool)> {
    next_n_acking(consumer, n, None).await
}

/// [`next_n`], then acks them all (`multiple` up to the last one's tag:
/// lapin drops deliveries it holds on an ack of tag 0).
async fn next_n_acking(
    consumer: &mut lp::Consumer,
    n: usize,
    ack_on: Option<&lp::Channel>,
) -> Vec<(String, bool)> {
    let mut got = Vec::new();
    let mut last = 0;
    for _ in 0..n {
        let d = lp::next(consumer).await;
        got.push((lp::text(&d), d.redelivered));
        last = d.delivery_tag;
    }
    if let Some(ch) = ack_on {
        tmo!(ch.basic_ack(last, lp::BasicAckOptions { multiple: true })).expect("basic.ack");
    }
    got
}

fn numbered(range: std::ops::RangeInclusive<u32>, redelivered: bool) -> Vec<(String, bool)> {
    range.map(|i| (i.to_string(), redelivered)).collect()
}

/// Whether each consumer tag of `queue` is active, as the listings say.
fn listed_active(b: &TestBroker, queue: &str) -> Option<Vec<(String, bool, &'static str)>> {
    let admin = b.admin()?;
    let mut listed: Vec<_> = admin
        .consumers()
        .into_iter()
        .filter(|c| c.queue == queue)
        .map(|c| (c.tag, c.active, c.activity_status))
        .collect();
    listed.sort();
    Some(listed)
}

#[both_runtimes]
async fn the_first_consumer_gets_everything() {
    let b = broker().await;
    let conn = lp::connect(&b).await;
    let ch = lp::channel(&conn).await;
    let q = lp::queue_with(&ch, "sac", single_active()).await;
    let (_ch1, mut first) = consumer_on(&conn, &q, "first", 0, Default::default()).await;
    let (_ch2, mut second) = consumer_on(&conn, &q, "second", 0, Default::default()).await;
    publish_numbered(&ch, &q, 1..=10).await;
    assert_eq!(next_n(&mut first, 10).await, numbered(1..=10, false));
    lp::nothing(&mut second).await;
    if let Some(listed) = listed_active(&b, &q) {
        assert_eq!(
            listed,
            [
                ("first".into(), true, "single_active"),
                ("second".into(), false, "waiting")
            ]
        );
    }
}

/// basic.cancel of the active consumer: the next registered one becomes
/// active; what the cancelled one holds unacked stays with its channel (as
/// in RabbitMQ: that channel may still ack it), and the new one gets its
/// first message only once those are settled, so two consumers never work
/// on the queue at once: acked, and the rest follows; requeued (the channel
/// closes), and they come first, in order. A consumer cancelled holding
/// nothing hands over at once.
///
/// RabbitMQ 3.10.8 makes the next consumer active on cancel too but
/// delivers nothing to it until the queue runs for another reason (a
/// close, an ack), and a publish in between crashes its queue process
/// (`badmatch` in `rabbit_amqqueue_process:attempt_delivery`, the
/// messages lost): this test is Leveret's.
#[both_runtimes]
async fn cancel_hands_over_once_the_cancelled_consumer_holds_nothing() {
    let b = broker().await;
    if b.is_external() {
        return;
    }
    let conn = lp::connect(&b).await;
    let ch = lp::channel(&conn).await;
    let q = lp::queue_with(&ch, "sac-cancel", single_active()).await;
    let (ch1, mut first) = consumer_on(&conn, &q, "first", 3, Default::default()).await;
    let (ch2, mut second) = consumer_on(&conn, &q, "second", 3, Default::default()).await;
    let (_ch3, mut third) = consumer_on(&conn, &q, "third", 0, Default::default()).await;
    publish_numbered(&ch, &q, 1..=12).await;
    assert_eq!(next_n(&mut first, 3).await, numbered(1..=3, false));
    tmo!(ch1.basic_cancel("first", Default::default())).expect("basic.cancel");
    lp::nothing(&mut second).await;
    if let Some(listed) = listed_active(&b, &q) {
        assert_eq!(
            listed,
            [
                ("second".into(), true, "single_active"),
                ("third".into(), false, "waiting")
            ]
        );
    }
    // The cancelled consumer's channel closes: its three come back first.
    tmo!(ch1.close(200, "bye")).expect("channel.close");
    assert_eq!(
        next_n_acking(&mut second, 3, Some(&ch2)).await,
        numbered(1..=3, true)
    );
    // The second is cancelled holding three: the third waits until they
    // are acked, then gets what is left, in order.
    let mut held = Vec::new();
    for _ in 0..3 {
        held.push(lp::next(&mut second).await);
    }
    let bodies: Vec<_> = held.iter().map(|d| (lp::text(d), d.redelivered)).collect();
    assert_eq!(bodies, numbered(4..=6, false));
    tmo!(ch2.basic_cancel("second", Default::default())).expect("basic.cancel");
    lp::nothing(&mut third).await;
    let last = held.last().expect("three").delivery_tag;
    tmo!(ch2.basic_ack(last, lp::BasicAckOptions { multiple: true })).expect("ack");
    assert_eq!(next_n(&mut third, 6).await, numbered(7..=12, false));
    lp::nothing(&mut first).await;
}

/// channel.close of the active consumer: its unacked messages come back
/// first, in order, to the next registered consumer, then the rest.
#[both_runtimes]
async fn channel_close_hands_over_with_the_unacked_first() {
    let b = broker().await;
    let conn = lp::connect(&b).await;
    let ch = lp::channel(&conn).await;
    let q = lp::queue_with(&ch, "sac-close", single_active()).await;
    let (ch1, mut first) = consumer_on(&conn, &q, "first", 5, Default::default()).await;
    let (_ch2, mut second) = consumer_on(&conn, &q, "second", 0, Default::default()).await;
    publish_numbered(&ch, &q, 1..=10).await;
    assert_eq!(next_n(&mut first, 5).await, numbered(1..=5, false));
    tmo!(ch1.close(200, "bye")).expect("channel.close");
    let mut expected = numbered(1..=5, true);
    expected.extend(numbered(6..=10, false));
    assert_eq!(next_n(&mut second, 10).await, expected);
}

/// The active consumer's connection is lost (its TCP connection cut, no
/// close handshake): the same hand-over.
#[both_runtimes]
async fn connection_loss_hands_over_with_the_unacked_first() {
    let b = broker().await;
    let upstream = b.addr().parse().expect("broker address");
    let proxy = FaultProxy::start(upstream).await;
    let doomed = within(
        "lapin connect through the proxy",
        lapin::Connection::connect(
            &format!("amqp://guest:guest@{}/%2f", proxy.addr),
            lp::ConnectionProperties::default(),
        ),
    )
    .await
    .expect("connects through the proxy");
    let conn = lp::connect(&b).await;
    let ch = lp::channel(&conn).await;
    let q = lp::queue_with(&ch, "sac-loss", single_active()).await;
    let (_ch1, mut first) = consumer_on(&doomed, &q, "first", 4, Default::default()).await;
    let (_ch2, mut second) = consumer_on(&conn, &q, "second", 0, Default::default()).await;
    publish_numbered(&ch, &q, 1..=8).await;
    assert_eq!(next_n(&mut first, 4).await, numbered(1..=4, false));
    assert_eq!(proxy.cut(), 1);
    let mut expected = numbered(1..=4, true);
    expected.extend(numbered(5..=8, false));
    assert_eq!(next_n(&mut second, 8).await, expected);
}

/// A higher-priority consumer gets messages while it has prefetch room;
/// the lower one gets only what it cannot take, and equal ones share.
#[both_runtimes]
async fn higher_priority_consumers_are_served_while_they_have_room() {
    let b = broker().await;
    let conn = lp::connect(&b).await;
    let ch = lp::channel(&conn).await;
    let q = lp::queue(&ch, "prio").await;
    let priority = |p: i32| lp::table(vec![("x-priority", AMQPValue::LongInt(p))]);
    let (_low_ch, mut low) = consumer_on(&conn, &q, "low", 10, priority(1)).await;
    let (high_ch, mut high) = consumer_on(&conn, &q, "high", 3, priority(10)).await;
    publish_numbered(&ch, &q, 1..=5).await;
    assert_eq!(next_n(&mut high, 3).await, numbered(1..=3, false));
    assert_eq!(next_n(&mut low, 2).await, numbered(4..=5, false));
    // Room again for the high one: the next message is its.
    tmo!(high_ch.basic_ack(3, lp::BasicAckOptions { multiple: true })).expect("ack all");
    publish_numbered(&ch, &q, 6..=8).await;
    assert_eq!(next_n(&mut high, 3).await, numbered(6..=8, false));
    lp::nothing(&mut low).await;
}

/// Equal priorities take turns; a consumer with no priority is 0.
#[both_runtimes]
async fn equal_priorities_take_turns_above_the_default() {
    let b = broker().await;
    let conn = lp::connect(&b).await;
    let ch = lp::channel(&conn).await;
    let q = lp::queue(&ch, "prio-rr").await;
    let priority = |p: i16| lp::table(vec![("x-priority", AMQPValue::ShortInt(p))]);
    let (_c0, mut plain) = consumer_on(&conn, &q, "plain", 0, Default::default()).await;
    let (_c1, mut a) = consumer_on(&conn, &q, "a", 0, priority(5)).await;
    let (_c2, mut bb) = consumer_on(&conn, &q, "b", 0, priority(5)).await;
    publish_numbered(&ch, &q, 1..=6).await;
    assert_eq!(
        next_n(&mut a, 3).await,
        [
            ("1".into(), false),
            ("3".into(), false),
            ("5".into(), false)
        ]
    );
    assert_eq!(
        next_n(&mut bb, 3).await,
        [
            ("2".into(), false),
            ("4".into(), false),
            ("6".into(), false)
        ]
    );
    lp::nothing(&mut plain).await;
}
