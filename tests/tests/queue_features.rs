//! Queue arguments: x-message-ttl, per-message expiration, x-max-length
//! (drop-head and reject-publish), dead-lettering with the x-death header,
//! x-max-priority, and the 406s for invalid arguments.
//!
//! Expiry is observed as an event (the dead-lettered message arriving at a
//! consumer), never by sleeping.

#[macro_use]
mod common;

use common::lp::AMQPValue;
use common::*;

async fn confirm_channel(conn: &lp::Connection) -> lp::Channel {
    let ch = lp::channel(conn).await;
    tmo!(ch.confirm_select(lp::ConfirmSelectOptions::default())).expect("confirm.select");
    ch
}

/// A fanout dead-letter exchange with one queue bound, and a consumer on
/// that queue.
async fn dead_letter_sink(ch: &lp::Channel) -> (String, String, lp::Consumer) {
    let dlx = lp::exchange(ch, "dlx", lp::ExchangeKind::Fanout).await;
    let dead = lp::queue(ch, "dead").await;
    lp::bind(ch, &dead, &dlx, "").await;
    let consumer = lp::consume_opts(
        ch,
        &dead,
        "",
        lp::BasicConsumeOptions {
            no_ack: true,
            ..Default::default()
        },
    )
    .await;
    (dlx, dead, consumer)
}

/// A queue dead-lettering to a [`dead_letter_sink`]: the queue's name, the
/// dead-letter exchange's, and the consumer of what it dead-letters.
async fn queue_with_dead_letter_sink(
    ch: &lp::Channel,
    prefix: &str,
) -> (String, String, lp::Consumer) {
    let (dlx, _dead, dead_consumer) = dead_letter_sink(ch).await;
    let q = lp::queue_with(
        ch,
        prefix,
        lp::table(vec![("x-dead-letter-exchange", lp::lstr(&dlx))]),
    )
    .await;
    (q, dlx, dead_consumer)
}

fn header<'a>(d: &'a lp::Delivery, key: &str) -> Option<&'a AMQPValue> {
    d.properties
        .headers()
        .as_ref()
        .and_then(|h| h.inner().get(key))
}

/// The first (most recent) x-death entry.
fn x_death(d: &lp::Delivery) -> lp::FieldTable {
    match header(d, "x-death") {
        Some(AMQPValue::FieldArray(a)) => match a.as_slice().first() {
            Some(AMQPValue::FieldTable(t)) => t.clone(),
            other => panic!("x-death entries are tables, got {other:?}"),
        },
        other => panic!("x-death should be an array, got {other:?}"),
    }
}

fn text_of(v: Option<&AMQPValue>) -> String {
    match v {
        Some(AMQPValue::LongString(s)) => String::from_utf8_lossy(s.as_bytes()).into_owned(),
        other => panic!("expected a long string, got {other:?}"),
    }
}

fn count_of(v: Option<&AMQPValue>) -> i64 {
    match v {
        Some(AMQPValue::LongLongInt(n)) => *n,
        other => panic!("expected a long-long count, got {other:?}"),
    }
}

fn routing_keys(t: &lp::FieldTable) -> Vec<String> {
    match t.inner().get("routing-keys") {
        Some(AMQPValue::FieldArray(a)) => a.as_slice().iter().map(|v| text_of(Some(v))).collect(),
        other => panic!("routing-keys should be an array, got {other:?}"),
    }
}

#[both_runtimes]
async fn message_ttl_expires_messages_to_the_dead_letter_exchange() {
    let b = broker().await;
    let conn = lp::connect(&b).await;
    let ch = confirm_channel(&conn).await;
    let (dlx, dead, mut dead_consumer) = dead_letter_sink(&ch).await;
    let q = lp::queue_with(
        &ch,
        "ttl",
        lp::table(vec![
            ("x-message-ttl", AMQPValue::LongInt(50)),
            ("x-dead-letter-exchange", lp::lstr(&dlx)),
        ]),
    )
    .await;
    let props = lp::BasicProperties::default().with_message_id("ttl-1".into());
    let c = lp::publish_confirmed(&ch, "", &q, b"short-lived", props).await;
    assert!(c.is_ack());
    let d = lp::next(&mut dead_consumer).await;
    assert_eq!(d.data, b"short-lived");
    assert_eq!(d.exchange.as_str(), dlx);
    // Dead-lettering keeps the original routing key.
    assert_eq!(d.routing_key.as_str(), q);
    assert_eq!(
        d.properties.message_id().as_ref().map(|s| s.as_str()),
        Some("ttl-1")
    );
    let death = x_death(&d);
    assert_eq!(text_of(death.inner().get("reason")), "expired");
    assert_eq!(text_of(death.inner().get("queue")), q);
    assert_eq!(text_of(death.inner().get("exchange")), "");
    assert_eq!(count_of(death.inner().get("count")), 1);
    assert_eq!(routing_keys(&death), [q.as_str()]);
    assert!(matches!(
        death.inner().get("time"),
        Some(AMQPValue::Timestamp(_))
    ));
    assert_eq!(text_of(header(&d, "x-first-death-reason")), "expired");
    assert_eq!(text_of(header(&d, "x-first-death-queue")), q);
    assert_eq!(text_of(header(&d, "x-first-death-exchange")), "");
    // Nothing is left in the original queue.
    assert!(lp::get(&ch, &q, true).await.is_none());
    let _ = dead;
}

#[both_runtimes]
async fn per_message_expiration_dead_letters_with_original_expiration() {
    let b = broker().await;
    let conn = lp::connect(&b).await;
    let ch = confirm_channel(&conn).await;
    let (q, _dlx, mut dead_consumer) = queue_with_dead_letter_sink(&ch, "expiration").await;
    let props = lp::BasicProperties::default().with_expiration("20".into());
    assert!(lp::publish_confirmed(&ch, "", &q, b"expiring", props)
        .await
        .is_ack());
    assert!(
        lp::publish_confirmed(&ch, "", &q, b"lasting", lp::BasicProperties::default())
            .await
            .is_ack()
    );
    let d = lp::next(&mut dead_consumer).await;
    assert_eq!(d.data, b"expiring");
    // The expiration property is removed and kept in x-death instead.
    assert_eq!(d.properties.expiration(), &None);
    let death = x_death(&d);
    assert_eq!(text_of(death.inner().get("reason")), "expired");
    assert_eq!(text_of(death.inner().get("original-expiration")), "20");
    // The message without expiration is still there.
    let kept = lp::get(&ch, &q, true).await.expect("lasting message");
    assert_eq!(kept.delivery.data, b"lasting");
}

#[both_runtimes]
async fn expiry_resumes_after_a_queue_had_nothing_left_to_expire() {
    // Between the two messages the queue holds nothing that can expire (a
    // quiet spell); the second must still be dead-lettered without anyone
    // touching the queue.
    let b = broker().await;
    let conn = lp::connect(&b).await;
    let ch = confirm_channel(&conn).await;
    let (q, _dlx, mut dead_consumer) = queue_with_dead_letter_sink(&ch, "expiry-resumes").await;
    for body in [&b"first"[..], b"second"] {
        let props = lp::BasicProperties::default().with_expiration("20".into());
        assert!(lp::publish_confirmed(&ch, "", &q, body, props)
            .await
            .is_ack());
        let d = lp::next(&mut dead_consumer).await;
        assert_eq!(d.data, body);
        tokio::time::sleep(std::time::Duration::from_millis(200)).await;
    }
}

#[both_runtimes]
async fn an_unused_queue_is_deleted_after_x_expires() {
    let b = broker().await;
    let conn = lp::connect(&b).await;
    let ch = lp::channel(&conn).await;
    let q = lp::queue_with(
        &ch,
        "x-expires",
        lp::table(vec![("x-expires", AMQPValue::LongInt(100))]),
    )
    .await;
    // Observed by polling: a passive declare answers 404 once it is gone
    // (and closes its channel, so each try gets a fresh one). A declare may
    // count as a use, so the tries are further apart than x-expires.
    let passive = lp::QueueDeclareOptions {
        passive: true,
        ..Default::default()
    };
    within("x-expires deletion", async {
        loop {
            let probe = lp::channel(&conn).await;
            match probe
                .queue_declare(&q, passive, lp::FieldTable::default())
                .await
            {
                Ok(_) => {
                    let _ = probe.close(200, "still there").await;
                    tokio::time::sleep(std::time::Duration::from_millis(400)).await;
                }
                Err(err) => {
                    lp::assert_err::<()>(Err(err), 404, "NOT_FOUND");
                    return;
                }
            }
        }
    })
    .await;
}

#[both_runtimes]
async fn zero_ttl_drops_messages_nobody_can_take_at_once() {
    let b = broker().await;
    let (_conn, ch, mut ev) = rs::open(&b).await;
    rs::confirm_select(&ch).await;
    let mut args = rs::QueueDeclareArguments::new(&unique("ttl-zero"));
    args.arguments(rs::table(vec![("x-message-ttl", rs::FieldValue::I(0))]));
    let q = rs::queue_args(&ch, args).await;
    rs::publish(&ch, "", &q, b"too late").await;
    rs::acked(&mut ev, 1).await;
    assert!(rs::get(&ch, &q, true).await.is_none());
    assert_eq!(rs::counts(&ch, &q).await, (0, 0));
    // With a consumer waiting, the message is delivered.
    let (_, mut rx) = rs::consume(&ch, &q, "", true).await;
    rs::publish(&ch, "", &q, b"just in time").await;
    assert_eq!(rs::next(&mut rx).await.text(), "just in time");
}

#[both_runtimes]
async fn max_length_drops_from_the_head() {
    let b = broker().await;
    let conn = lp::connect(&b).await;
    let ch = confirm_channel(&conn).await;
    let (dlx, _dead, mut dead_consumer) = dead_letter_sink(&ch).await;
    let q = lp::queue_with(
        &ch,
        "max-length",
        lp::table(vec![
            ("x-max-length", AMQPValue::LongInt(3)),
            ("x-dead-letter-exchange", lp::lstr(&dlx)),
        ]),
    )
    .await;
    for i in 1..=5 {
        let c = lp::publish_confirmed(
            &ch,
            "",
            &q,
            format!("{i}").as_bytes(),
            lp::BasicProperties::default(),
        )
        .await;
        // Drop-head still confirms every publish with an ack.
        assert!(c.is_ack());
    }
    let info = tmo!(ch.queue_declare(
        &q,
        lp::QueueDeclareOptions {
            passive: true,
            ..Default::default()
        },
        lp::FieldTable::default()
    ))
    .expect("passive");
    assert_eq!(info.message_count(), 3);
    for want in ["3", "4", "5"] {
        let m = lp::get(&ch, &q, true).await.expect("message");
        assert_eq!(m.delivery.data, want.as_bytes());
    }
    // The two oldest were dead-lettered, in order, as "maxlen".
    for want in ["1", "2"] {
        let d = lp::next(&mut dead_consumer).await;
        assert_eq!(lp::text(&d), want);
        assert_eq!(text_of(x_death(&d).inner().get("reason")), "maxlen");
    }
}

#[both_runtimes]
async fn max_length_with_reject_publish_nacks_the_overflow() {
    let b = broker().await;
    let conn = lp::connect(&b).await;
    let ch = confirm_channel(&conn).await;
    let q = lp::queue_with(
        &ch,
        "reject-publish",
        lp::table(vec![
            ("x-max-length", AMQPValue::LongInt(2)),
            ("x-overflow", lp::lstr("reject-publish")),
        ]),
    )
    .await;
    let mut results = Vec::new();
    for i in 1..=4 {
        let c = lp::publish_confirmed(
            &ch,
            "",
            &q,
            format!("{i}").as_bytes(),
            lp::BasicProperties::default(),
        )
        .await;
        results.push(c.is_ack());
    }
    assert_eq!(results, [true, true, false, false]);
    for want in ["1", "2"] {
        let m = lp::get(&ch, &q, true).await.expect("message");
        assert_eq!(m.delivery.data, want.as_bytes());
    }
    assert!(lp::get(&ch, &q, true).await.is_none());
}

#[both_runtimes]
async fn rejected_messages_are_dead_lettered_with_a_routing_key_override() {
    let b = broker().await;
    let conn = lp::connect(&b).await;
    let ch = lp::channel(&conn).await;
    let dlx = lp::exchange(&ch, "dlx-direct", lp::ExchangeKind::Direct).await;
    let dead = lp::queue(&ch, "dead-direct").await;
    lp::bind(&ch, &dead, &dlx, "rk-override").await;
    let q = lp::queue_with(
        &ch,
        "rejecting",
        lp::table(vec![
            ("x-dead-letter-exchange", lp::lstr(&dlx)),
            ("x-dead-letter-routing-key", lp::lstr("rk-override")),
        ]),
    )
    .await;
    let x = lp::exchange(&ch, "src", lp::ExchangeKind::Direct).await;
    lp::bind(&ch, &q, &x, "original-key").await;
    lp::publish(&ch, &x, "original-key", b"unwanted").await;
    lp::publish(&ch, &x, "original-key", b"nacked").await;
    let mut c = lp::consume(&ch, &q, "").await;
    let d1 = lp::next(&mut c).await;
    tmo!(ch.basic_reject(d1.delivery_tag, lp::BasicRejectOptions { requeue: false }))
        .expect("reject");
    let d2 = lp::next(&mut c).await;
    tmo!(ch.basic_nack(
        d2.delivery_tag,
        lp::BasicNackOptions {
            requeue: false,
            multiple: false
        }
    ))
    .expect("nack");
    let dch = lp::channel(&conn).await;
    let mut dc = lp::consume(&dch, &dead, "").await;
    for want in ["unwanted", "nacked"] {
        let d = lp::next(&mut dc).await;
        assert_eq!(lp::text(&d), want);
        assert_eq!(d.exchange.as_str(), dlx);
        assert_eq!(d.routing_key.as_str(), "rk-override");
        let death = x_death(&d);
        assert_eq!(text_of(death.inner().get("reason")), "rejected");
        assert_eq!(text_of(death.inner().get("queue")), q);
        assert_eq!(text_of(death.inner().get("exchange")), x);
        assert_eq!(routing_keys(&death), ["original-key"]);
        assert_eq!(count_of(death.inner().get("count")), 1);
        lp::ack(&dch, d.delivery_tag).await;
    }
}

#[both_runtimes]
async fn requeued_rejects_are_not_dead_lettered() {
    let b = broker().await;
    let conn = lp::connect(&b).await;
    let ch = lp::channel(&conn).await;
    let (dlx, _dead, mut dead_consumer) = dead_letter_sink(&ch).await;
    let q = lp::queue_with(
        &ch,
        "requeue-not-dead",
        lp::table(vec![("x-dead-letter-exchange", lp::lstr(&dlx))]),
    )
    .await;
    lp::publish(&ch, "", &q, b"back").await;
    let m = lp::get(&ch, &q, false).await.expect("message");
    tmo!(ch.basic_reject(
        m.delivery.delivery_tag,
        lp::BasicRejectOptions { requeue: true }
    ))
    .expect("reject");
    let again = lp::get(&ch, &q, true).await.expect("requeued");
    assert!(again.delivery.redelivered);
    assert_eq!(header(&again.delivery, "x-death"), None);
    lp::nothing(&mut dead_consumer).await;
}

#[both_runtimes]
async fn dead_lettering_twice_through_the_same_queue_counts_up() {
    let b = broker().await;
    let conn = lp::connect(&b).await;
    let ch = lp::channel(&conn).await;
    // q (dead-letters to the default exchange, routing key = q2) and q2
    // (dead-letters back to q); reject twice in q.
    let q = unique("cycle-a");
    let q2 = unique("cycle-b");
    tmo!(ch.queue_declare(
        &q,
        lp::QueueDeclareOptions::default(),
        lp::table(vec![
            ("x-dead-letter-exchange", lp::lstr("")),
            ("x-dead-letter-routing-key", lp::lstr(&q2)),
        ])
    ))
    .expect("declare q");
    tmo!(ch.queue_declare(
        &q2,
        lp::QueueDeclareOptions::default(),
        lp::table(vec![
            ("x-dead-letter-exchange", lp::lstr("")),
            ("x-dead-letter-routing-key", lp::lstr(&q)),
        ])
    ))
    .expect("declare q2");
    lp::publish(&ch, "", &q, b"bouncing").await;
    let mut cq = lp::consume(&ch, &q, "").await;
    let ch2 = lp::channel(&conn).await;
    let mut cq2 = lp::consume(&ch2, &q2, "").await;
    let d = lp::next(&mut cq).await;
    tmo!(ch.basic_reject(d.delivery_tag, lp::BasicRejectOptions { requeue: false }))
        .expect("reject 1");
    let d = lp::next(&mut cq2).await;
    tmo!(ch2.basic_reject(d.delivery_tag, lp::BasicRejectOptions { requeue: false }))
        .expect("reject 2");
    let d = lp::next(&mut cq).await;
    tmo!(ch.basic_reject(d.delivery_tag, lp::BasicRejectOptions { requeue: false }))
        .expect("reject 3");
    let d = lp::next(&mut cq2).await;
    // Two entries: one per (queue, reason), most recent first, with counts.
    let deaths = match header(&d, "x-death") {
        Some(AMQPValue::FieldArray(a)) => a.as_slice().to_vec(),
        other => panic!("x-death: {other:?}"),
    };
    assert_eq!(deaths.len(), 2, "{deaths:?}");
    let entry = |v: &AMQPValue| match v {
        AMQPValue::FieldTable(t) => (
            text_of(t.inner().get("queue")),
            count_of(t.inner().get("count")),
        ),
        other => panic!("x-death entry: {other:?}"),
    };
    assert_eq!(entry(&deaths[0]), (q.clone(), 2));
    assert_eq!(entry(&deaths[1]), (q2.clone(), 1));
    assert_eq!(text_of(header(&d, "x-first-death-queue")), q);
    tmo!(ch2.basic_ack(d.delivery_tag, lp::BasicAckOptions::default())).expect("ack");
    for name in [&q, &q2] {
        tmo!(ch.queue_delete(name, lp::QueueDeleteOptions::default())).expect("delete");
    }
}

#[both_runtimes]
async fn max_priority_delivers_higher_priorities_first() {
    let b = broker().await;
    let (_conn, ch, mut ev) = rs::open(&b).await;
    rs::confirm_select(&ch).await;
    let mut args = rs::QueueDeclareArguments::new(&unique("priority"));
    args.arguments(rs::table(vec![("x-max-priority", rs::FieldValue::I(10))]));
    let q = rs::queue_args(&ch, args).await;
    let published: [(&str, Option<u8>); 7] = [
        ("p1", Some(1)),
        ("p5a", Some(5)),
        ("none", None),
        ("p9", Some(9)),
        ("p5b", Some(5)),
        ("p0", Some(0)),
        // Above x-max-priority: treated as the maximum.
        ("p200", Some(200)),
    ];
    for (body, priority) in published {
        let mut props = rs::BasicProperties::default();
        if let Some(p) = priority {
            props.with_priority(p);
        }
        rs::publish_props(&ch, "", &q, body.as_bytes(), props).await;
    }
    rs::acked(&mut ev, published.len() as u64).await;
    let (_, mut rx) = rs::consume(&ch, &q, "", true).await;
    let mut got = Vec::new();
    for _ in 0..published.len() {
        got.push(rs::next(&mut rx).await.text());
    }
    // Highest first; equal priorities (and "no priority" = 0) keep
    // publish order.
    assert_eq!(got, ["p200", "p9", "p5a", "p5b", "p1", "none", "p0"]);
}

#[both_runtimes]
async fn invalid_queue_arguments_get_406() {
    let b = broker().await;
    let conn = lp::connect(&b).await;
    let cases: Vec<(&str, AMQPValue)> = vec![
        // "PRECONDITION_FAILED - invalid arg 'x-max-length' for queue '...'
        // in vhost '/': {unacceptable_type,longstr}"
        ("x-max-length", lp::lstr("ten")),
        ("x-max-length", AMQPValue::LongInt(-1)),
        ("x-message-ttl", AMQPValue::LongInt(-5)),
        ("x-message-ttl", lp::lstr("soon")),
        ("x-max-priority", AMQPValue::LongInt(256)),
        ("x-overflow", lp::lstr("explode")),
        ("x-dead-letter-exchange", AMQPValue::LongInt(1)),
    ];
    for (key, value) in cases {
        let ch = lp::channel(&conn).await;
        let res = tmo!(ch.queue_declare(
            &unique("bad-args"),
            lp::QueueDeclareOptions::default(),
            lp::table(vec![(key, value.clone())])
        ));
        let err = res.expect_err(&format!("{key} = {value:?} must be refused"));
        let (code, text) = lp::code(&err);
        assert_eq!(code, 406, "{key} = {value:?}: {text}");
        assert_text_prefix(&text, "PRECONDITION_FAILED");
    }
    // A dead-letter routing key needs a dead-letter exchange.
    let ch = lp::channel(&conn).await;
    let res = tmo!(ch.queue_declare(
        &unique("bad-args"),
        lp::QueueDeclareOptions::default(),
        lp::table(vec![("x-dead-letter-routing-key", lp::lstr("k"))])
    ));
    lp::assert_err(res, 406, "PRECONDITION_FAILED");
}
