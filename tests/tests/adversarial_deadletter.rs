//! Dead-letter topologies a client can build to make the broker loop:
//! queues that dead-letter to themselves (by max-length 0 or a TTL of 0)
//! and cycles through several queues and exchanges. RabbitMQ 3.10 drops a
//! message that would be dead-lettered back to a queue it already died in
//! when no client rejection is part of that cycle; a cycle with a
//! `rejected` death in it continues, and each round adds to the x-death
//! counts. After every probe a second connection must still be served.
//!
//! Copies that arrive are observed at "witness" queues bound beside the
//! cycling ones; absence is checked over [`QUIET`], never by sleeping.

#[macro_use]
mod common;

use common::lp::AMQPValue;
use common::*;

/// A channel in confirm mode.
async fn confirm_channel(conn: &lp::Connection) -> lp::Channel {
    let ch = lp::channel(conn).await;
    tmo!(ch.confirm_select(lp::ConfirmSelectOptions::default())).expect("confirm.select");
    ch
}

/// A no-ack consumer of `queue`.
async fn watch(ch: &lp::Channel, queue: &str) -> lp::Consumer {
    lp::consume_opts(
        ch,
        queue,
        "",
        lp::BasicConsumeOptions {
            no_ack: true,
            ..Default::default()
        },
    )
    .await
}

/// The x-death entries of a delivery as (queue, reason, count), newest
/// first.
fn deaths(d: &lp::Delivery) -> Vec<(String, String, i64)> {
    let headers = d.properties.headers().as_ref().expect("headers");
    let Some(AMQPValue::FieldArray(entries)) = headers.inner().get("x-death") else {
        panic!("x-death should be an array in {headers:?}");
    };
    entries
        .as_slice()
        .iter()
        .map(|entry| {
            let AMQPValue::FieldTable(t) = entry else {
                panic!("x-death entries are tables, got {entry:?}");
            };
            let text = |key: &str| match t.inner().get(key) {
                Some(AMQPValue::LongString(s)) => {
                    String::from_utf8_lossy(s.as_bytes()).into_owned()
                }
                other => panic!("x-death {key} should be a long string, got {other:?}"),
            };
            let count = match t.inner().get("count") {
                Some(AMQPValue::LongLongInt(n)) => *n,
                other => panic!("x-death count should be a long-long, got {other:?}"),
            };
            (text("queue"), text("reason"), count)
        })
        .collect()
}

fn death(queue: &str, reason: &str, count: i64) -> (String, String, i64) {
    (queue.to_owned(), reason.to_owned(), count)
}

/// Ready messages in `queue`, from a passive declare.
async fn ready(ch: &lp::Channel, queue: &str) -> u32 {
    tmo!(ch.queue_declare(
        queue,
        lp::QueueDeclareOptions {
            passive: true,
            ..Default::default()
        },
        lp::FieldTable::default(),
    ))
    .expect("passive queue.declare")
    .message_count()
}

/// A fresh connection is still served: declare, publish, get, close.
async fn second_connection_is_served(b: &TestBroker) {
    let (conn, ch) = lp::open(b).await;
    let q = lp::queue(&ch, "still-served").await;
    let ch = confirm_channel(&conn).await;
    let confirm = lp::publish_confirmed(&ch, "", &q, b"ping", lp::BasicProperties::default()).await;
    assert_eq!(confirm, lp::Confirmation::Ack(None));
    let got = lp::get(&ch, &q, true).await.expect("the message is there");
    assert_eq!(got.delivery.data, b"ping");
    tmo!(conn.close(200, "bye")).expect("connection.close");
}

#[both_runtimes]
async fn max_length_zero_dead_lettering_to_itself_drops_the_message() {
    let b = broker().await;
    let (conn, ch) = lp::open(&b).await;
    // The default exchange routes the dead letter by its routing key (the
    // queue's own name) straight back to the queue.
    let q = lp::queue_with(
        &ch,
        "self-maxlen",
        lp::table(vec![
            ("x-max-length", AMQPValue::LongInt(0)),
            ("x-dead-letter-exchange", lp::lstr("")),
        ]),
    )
    .await;
    let pub_ch = confirm_channel(&conn).await;
    let confirm =
        lp::publish_confirmed(&pub_ch, "", &q, b"loop", lp::BasicProperties::default()).await;
    assert_eq!(confirm, lp::Confirmation::Ack(None));
    assert_eq!(ready(&ch, &q).await, 0, "the cycling message is dropped");
    second_connection_is_served(&b).await;
    b.stop().await;
}

/// A queue dead-lettering into a fanout exchange bound to itself and to a
/// witness queue: each dead-lettering shows up once at the witness.
async fn self_cycle_with_witness(
    ch: &lp::Channel,
    prefix: &str,
    arguments: Vec<(&str, AMQPValue)>,
) -> (String, lp::Consumer) {
    let dlx = lp::exchange(ch, "dlx", lp::ExchangeKind::Fanout).await;
    let mut arguments = arguments;
    arguments.push(("x-dead-letter-exchange", lp::lstr(&dlx)));
    let q = lp::queue_with(ch, prefix, lp::table(arguments)).await;
    let witness = lp::queue(ch, "witness").await;
    lp::bind(ch, &q, &dlx, "").await;
    lp::bind(ch, &witness, &dlx, "").await;
    (q, watch(ch, &witness).await)
}

#[both_runtimes]
async fn ttl_zero_dead_lettering_to_itself_drops_the_message() {
    let b = broker().await;
    let (conn, ch) = lp::open(&b).await;
    let (q, mut witness) = self_cycle_with_witness(
        &ch,
        "self-ttl",
        vec![("x-message-ttl", AMQPValue::LongInt(0))],
    )
    .await;
    let pub_ch = confirm_channel(&conn).await;
    lp::publish_confirmed(&pub_ch, "", &q, b"loop", lp::BasicProperties::default()).await;
    // It expires once: the witness sees that death, and the copy routed
    // back to the queue it died in is dropped instead of expiring again.
    let d = lp::next(&mut witness).await;
    assert_eq!(deaths(&d), vec![death(&q, "expired", 1)]);
    lp::nothing(&mut witness).await;
    assert_eq!(ready(&ch, &q).await, 0);
    second_connection_is_served(&b).await;
    b.stop().await;
}

#[both_runtimes]
async fn max_length_zero_cycle_with_a_witness_dead_letters_once() {
    let b = broker().await;
    let (conn, ch) = lp::open(&b).await;
    let (q, mut witness) = self_cycle_with_witness(
        &ch,
        "self-maxlen",
        vec![("x-max-length", AMQPValue::LongInt(0))],
    )
    .await;
    let pub_ch = confirm_channel(&conn).await;
    lp::publish_confirmed(&pub_ch, "", &q, b"loop", lp::BasicProperties::default()).await;
    let d = lp::next(&mut witness).await;
    assert_eq!(deaths(&d), vec![death(&q, "maxlen", 1)]);
    lp::nothing(&mut witness).await;
    assert_eq!(ready(&ch, &q).await, 0);
    second_connection_is_served(&b).await;
    b.stop().await;
}

#[both_runtimes]
async fn cycle_through_two_queues_and_two_exchanges_is_broken() {
    let b = broker().await;
    let (conn, ch) = lp::open(&b).await;
    // first --(maxlen 0)--> to_second --> second --(ttl 0)--> to_first --> first
    // with a witness on each exchange.
    let to_second = lp::exchange(&ch, "to-second", lp::ExchangeKind::Fanout).await;
    let to_first = lp::exchange(&ch, "to-first", lp::ExchangeKind::Fanout).await;
    let first = lp::queue_with(
        &ch,
        "first",
        lp::table(vec![
            ("x-max-length", AMQPValue::LongInt(0)),
            ("x-dead-letter-exchange", lp::lstr(&to_second)),
        ]),
    )
    .await;
    let second = lp::queue_with(
        &ch,
        "second",
        lp::table(vec![
            ("x-message-ttl", AMQPValue::LongInt(0)),
            ("x-dead-letter-exchange", lp::lstr(&to_first)),
        ]),
    )
    .await;
    let witness_second = lp::queue(&ch, "witness-second").await;
    let witness_first = lp::queue(&ch, "witness-first").await;
    lp::bind(&ch, &second, &to_second, "").await;
    lp::bind(&ch, &witness_second, &to_second, "").await;
    lp::bind(&ch, &first, &to_first, "").await;
    lp::bind(&ch, &witness_first, &to_first, "").await;
    let mut at_second = watch(&ch, &witness_second).await;
    let mut at_first = watch(&ch, &witness_first).await;

    let pub_ch = confirm_channel(&conn).await;
    lp::publish_confirmed(
        &pub_ch,
        "",
        &first,
        b"round",
        lp::BasicProperties::default(),
    )
    .await;
    let d = lp::next(&mut at_second).await;
    assert_eq!(deaths(&d), vec![death(&first, "maxlen", 1)]);
    let d = lp::next(&mut at_first).await;
    assert_eq!(
        deaths(&d),
        vec![death(&second, "expired", 1), death(&first, "maxlen", 1)]
    );
    // The copy for `first` closed a cycle of automatic deaths: dropped.
    lp::nothing(&mut at_second).await;
    lp::nothing(&mut at_first).await;
    assert_eq!(ready(&ch, &first).await, 0);
    assert_eq!(ready(&ch, &second).await, 0);
    second_connection_is_served(&b).await;
    b.stop().await;
}

#[both_runtimes]
async fn cycle_with_a_reject_in_it_continues_and_counts_deaths() {
    let b = broker().await;
    let (conn, ch) = lp::open(&b).await;
    // work --(rejected)--> to_retry --> retry --(ttl 0)--> to_work --> work
    let to_retry = lp::exchange(&ch, "to-retry", lp::ExchangeKind::Fanout).await;
    let to_work = lp::exchange(&ch, "to-work", lp::ExchangeKind::Fanout).await;
    let work = lp::queue_with(
        &ch,
        "work",
        lp::table(vec![("x-dead-letter-exchange", lp::lstr(&to_retry))]),
    )
    .await;
    let retry = lp::queue_with(
        &ch,
        "retry",
        lp::table(vec![
            ("x-message-ttl", AMQPValue::LongInt(0)),
            ("x-dead-letter-exchange", lp::lstr(&to_work)),
        ]),
    )
    .await;
    lp::bind(&ch, &retry, &to_retry, "").await;
    lp::bind(&ch, &work, &to_work, "").await;
    let consume_ch = lp::channel(&conn).await;
    let mut worker = lp::consume(&consume_ch, &work, "worker").await;

    let pub_ch = confirm_channel(&conn).await;
    lp::publish_confirmed(&pub_ch, "", &work, b"job", lp::BasicProperties::default()).await;
    let mut delivery = lp::next(&mut worker).await;
    assert!(
        delivery.properties.headers().is_none(),
        "the first delivery has no x-death"
    );
    for round in 1..=3 {
        tmo!(consume_ch.basic_reject(
            delivery.delivery_tag,
            lp::BasicRejectOptions { requeue: false }
        ))
        .expect("basic.reject");
        delivery = lp::next(&mut worker).await;
        // The rejection is part of the cycle, so it is not broken; each
        // round moves the (queue, reason) entry it repeats to the front and
        // counts it again.
        assert_eq!(
            deaths(&delivery),
            vec![
                death(&retry, "expired", round),
                death(&work, "rejected", round)
            ],
            "x-death after round {round}"
        );
    }
    lp::ack(&consume_ch, delivery.delivery_tag).await;
    lp::nothing(&mut worker).await;
    second_connection_is_served(&b).await;
    b.stop().await;
}
