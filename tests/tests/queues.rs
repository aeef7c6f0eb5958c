//! Queue declare (server-named, passive, exclusive, auto-delete, durable,
//! counts, equivalence), bind/unbind, purge and delete.

#[macro_use]
mod common;

use common::*;

fn passive() -> lp::QueueDeclareOptions {
    lp::QueueDeclareOptions {
        passive: true,
        ..Default::default()
    }
}

fn exclusive() -> lp::QueueDeclareOptions {
    lp::QueueDeclareOptions {
        exclusive: true,
        ..Default::default()
    }
}

#[both_runtimes]
async fn server_named_queues_are_amq_gen_and_distinct() {
    let b = broker().await;
    let (_conn, ch, _ev) = rs::open(&b).await;
    let a = rs::queue_args(&ch, rs::QueueDeclareArguments::exclusive_server_named()).await;
    let c = rs::queue_args(&ch, rs::QueueDeclareArguments::exclusive_server_named()).await;
    assert!(a.starts_with("amq.gen-"), "{a}");
    assert!(c.starts_with("amq.gen-"), "{c}");
    assert_ne!(a, c);
    // Reachable through the default exchange like any queue.
    rs::publish(&ch, "", &a, b"to a").await;
    let got = rs::get(&ch, &a, true).await.expect("message");
    assert_eq!(got.3, b"to a");
    assert!(rs::get(&ch, &c, true).await.is_none());
}

#[both_runtimes]
async fn passive_declare_of_a_missing_queue_gets_404() {
    let b = broker().await;
    let (conn, _) = rs::connect(&b).await;
    let (ch, mut ev) = rs::channel(&conn).await;
    let mut args = rs::QueueDeclareArguments::new(&unique("missing-q"));
    args.passive(true);
    assert!(tmo!(ch.queue_declare(args)).is_err());
    // RabbitMQ: "NOT_FOUND - no queue '...' in vhost '/'".
    rs::assert_closed(&mut ev, 404, "NOT_FOUND").await;
}

#[both_runtimes]
async fn declare_ok_reports_ready_messages_and_consumers() {
    let b = broker().await;
    let (conn, _) = rs::connect(&b).await;
    let (ch, mut ev) = rs::channel(&conn).await;
    rs::confirm_select(&ch).await;
    let q = unique("counts");
    let (name, messages, consumers) = tmo!(ch.queue_declare(rs::QueueDeclareArguments::new(&q)))
        .expect("declare")
        .expect("declare-ok");
    assert_eq!((name.as_str(), messages, consumers), (q.as_str(), 0, 0));
    for i in 0..3 {
        rs::publish(&ch, "", &q, format!("{i}").as_bytes()).await;
    }
    rs::acked(&mut ev, 3).await;
    assert_eq!(rs::counts(&ch, &q).await, (3, 0));
    // A consumer limited to one unacked message takes one: message_count
    // counts only ready messages.
    let (c1, _) = rs::channel(&conn).await;
    tmo!(c1.basic_qos(rs::BasicQosArguments::new(0, 1, false))).expect("qos");
    let (_, mut rx1) = rs::consume(&c1, &q, "", false).await;
    let m = rs::next(&mut rx1).await;
    assert_eq!(m.text(), "0");
    assert_eq!(rs::counts(&ch, &q).await, (2, 1));
    let (c2, _) = rs::channel(&conn).await;
    tmo!(c2.basic_qos(rs::BasicQosArguments::new(0, 1, false))).expect("qos");
    let (_, mut rx2) = rs::consume(&c2, &q, "", false).await;
    assert_eq!(rs::next(&mut rx2).await.text(), "1");
    // A non-passive redeclare reports the same counts.
    let (_, messages, consumers) = tmo!(ch.queue_declare(rs::QueueDeclareArguments::new(&q)))
        .expect("declare")
        .expect("declare-ok");
    assert_eq!((messages, consumers), (1, 2));
}

#[both_runtimes]
async fn exclusive_queue_is_locked_to_its_connection() {
    let b = broker().await;
    let owner = lp::connect(&b).await;
    let och = lp::channel(&owner).await;
    let q = unique("exclusive");
    tmo!(och.queue_declare(&q, exclusive(), lp::FieldTable::default())).expect("declare");
    // Another channel of the owning connection may use it freely.
    let och2 = lp::channel(&owner).await;
    lp::publish(&och2, "", &q, b"mine").await;
    assert_eq!(
        lp::get(&och2, &q, true)
            .await
            .expect("message")
            .delivery
            .data,
        b"mine"
    );
    tmo!(och2.queue_declare(&q, exclusive(), lp::FieldTable::default())).expect("redeclare");
    // Even the owner gets 405 when the redeclare's `exclusive` differs, and so
    // does anyone redeclaring a shared queue as exclusive (RabbitMQ 3.10).
    lp::assert_err(
        tmo!(och2.queue_declare(
            &q,
            lp::QueueDeclareOptions::default(),
            lp::FieldTable::default()
        )),
        405,
        "RESOURCE_LOCKED",
    );
    let och2 = lp::channel(&owner).await;
    let och3 = lp::channel(&owner).await;
    let shared = unique("shared");
    tmo!(och3.queue_declare(
        &shared,
        lp::QueueDeclareOptions::default(),
        lp::FieldTable::default()
    ))
    .expect("declare shared");
    lp::assert_err(
        tmo!(och3.queue_declare(&shared, exclusive(), lp::FieldTable::default())),
        405,
        "RESOURCE_LOCKED",
    );

    // Any other connection gets 405 RESOURCE_LOCKED for everything:
    // "RESOURCE_LOCKED - cannot obtain exclusive access to locked queue '...' in vhost '/'. ..."
    let other = lp::connect(&b).await;
    let ch = lp::channel(&other).await;
    lp::assert_err(
        tmo!(ch.queue_declare(&q, exclusive(), lp::FieldTable::default())),
        405,
        "RESOURCE_LOCKED",
    );
    let ch = lp::channel(&other).await;
    lp::assert_err(
        tmo!(ch.queue_declare(
            &q,
            lp::QueueDeclareOptions::default(),
            lp::FieldTable::default()
        )),
        405,
        "RESOURCE_LOCKED",
    );
    let ch = lp::channel(&other).await;
    lp::assert_err(
        tmo!(ch.queue_declare(&q, passive(), lp::FieldTable::default())),
        405,
        "RESOURCE_LOCKED",
    );
    let ch = lp::channel(&other).await;
    lp::assert_err(
        tmo!(ch.basic_consume(
            &q,
            "",
            lp::BasicConsumeOptions::default(),
            lp::FieldTable::default()
        )),
        405,
        "RESOURCE_LOCKED",
    );
    let ch = lp::channel(&other).await;
    lp::assert_err(
        tmo!(ch.basic_get(&q, lp::BasicGetOptions::default())),
        405,
        "RESOURCE_LOCKED",
    );
    let ch = lp::channel(&other).await;
    lp::assert_err(
        tmo!(ch.queue_purge(&q, lp::QueuePurgeOptions::default())),
        405,
        "RESOURCE_LOCKED",
    );
    let ch = lp::channel(&other).await;
    lp::assert_err(
        tmo!(ch.queue_delete(&q, lp::QueueDeleteOptions::default())),
        405,
        "RESOURCE_LOCKED",
    );
    let ch = lp::channel(&other).await;
    lp::assert_err(
        tmo!(ch.queue_bind(
            &q,
            "amq.fanout",
            "",
            lp::QueueBindOptions::default(),
            lp::FieldTable::default()
        )),
        405,
        "RESOURCE_LOCKED",
    );
    // Publishing to it from elsewhere is allowed: the owner receives it
    // (confirmed, so it is in the queue before the owner looks).
    let ch = lp::channel(&other).await;
    tmo!(ch.confirm_select(lp::ConfirmSelectOptions::default())).expect("confirm.select");
    let c =
        lp::publish_confirmed(&ch, "", &q, b"from outside", lp::BasicProperties::default()).await;
    assert!(c.is_ack());
    let m = lp::get(&och2, &q, true)
        .await
        .expect("message from the other connection");
    assert_eq!(m.delivery.data, b"from outside");
}

#[both_runtimes]
async fn auto_delete_queue_goes_away_after_its_last_consumer_cancels() {
    let b = broker().await;
    let (_conn, ch) = lp::open(&b).await;
    let q = unique("auto-delete");
    tmo!(ch.queue_declare(
        &q,
        lp::QueueDeclareOptions {
            auto_delete: true,
            ..Default::default()
        },
        lp::FieldTable::default()
    ))
    .expect("declare");
    // Never consumed from: it stays.
    tmo!(ch.queue_declare(&q, passive(), lp::FieldTable::default())).expect("still there");
    let c1 = lp::consume(&ch, &q, "c1").await;
    let c2 = lp::consume(&ch, &q, "c2").await;
    tmo!(ch.basic_cancel(c1.tag().as_str(), lp::BasicCancelOptions::default())).expect("cancel");
    let after_one = tmo!(ch.queue_declare(&q, passive(), lp::FieldTable::default()))
        .expect("still there with one consumer");
    assert_eq!(after_one.consumer_count(), 1);
    tmo!(ch.basic_cancel(c2.tag().as_str(), lp::BasicCancelOptions::default())).expect("cancel");
    lp::assert_err(
        tmo!(ch.queue_declare(&q, passive(), lp::FieldTable::default())),
        404,
        "NOT_FOUND",
    );
}

#[both_runtimes]
async fn auto_delete_queue_goes_away_when_its_consumers_channel_closes() {
    let b = broker().await;
    let conn = lp::connect(&b).await;
    let ch = lp::channel(&conn).await;
    let q = unique("auto-delete-close");
    tmo!(ch.queue_declare(
        &q,
        lp::QueueDeclareOptions {
            auto_delete: true,
            ..Default::default()
        },
        lp::FieldTable::default()
    ))
    .expect("declare");
    let consumer_ch = lp::channel(&conn).await;
    let _c = lp::consume(&consumer_ch, &q, "").await;
    tmo!(consumer_ch.close(200, "bye")).expect("close");
    lp::assert_err(
        tmo!(ch.queue_declare(&q, passive(), lp::FieldTable::default())),
        404,
        "NOT_FOUND",
    );
}

#[both_runtimes]
async fn queue_bind_and_unbind() {
    let b = broker().await;
    let (_conn, ch) = lp::open(&b).await;
    let x = lp::exchange(&ch, "bind-x", lp::ExchangeKind::Direct).await;
    let q = lp::queue(&ch, "bind-q").await;
    lp::bind(&ch, &q, &x, "k").await;
    // Binding twice is the same binding.
    lp::bind(&ch, &q, &x, "k").await;
    lp::publish(&ch, &x, "k", b"bound").await;
    assert_eq!(
        lp::get(&ch, &q, true).await.expect("m").delivery.data,
        b"bound"
    );
    tmo!(ch.queue_unbind(&q, &x, "k", lp::FieldTable::default())).expect("unbind");
    lp::publish(&ch, &x, "k", b"unbound").await;
    assert!(lp::get(&ch, &q, true).await.is_none());
    // Note: unbinding a binding that does not exist is not an error in
    // RabbitMQ 3.10.
    tmo!(ch.queue_unbind(&q, &x, "k", lp::FieldTable::default())).expect("unbind again");
    tmo!(ch.queue_unbind(&q, &x, "never-bound", lp::FieldTable::default()))
        .expect("unbind never bound");
}

#[both_runtimes]
async fn bind_with_a_missing_exchange_or_queue_gets_404() {
    let b = broker().await;
    let (conn, _) = rs::connect(&b).await;
    let (ch, mut ev) = rs::channel(&conn).await;
    let q = rs::queue(&ch, "bind-missing").await;
    assert!(tmo!(ch.queue_bind(rs::QueueBindArguments::new(&q, &unique("no-x"), "k"))).is_err());
    // RabbitMQ: "NOT_FOUND - no exchange '...' in vhost '/'".
    rs::assert_closed(&mut ev, 404, "NOT_FOUND").await;
    let (ch, mut ev) = rs::channel(&conn).await;
    assert!(tmo!(ch.queue_bind(rs::QueueBindArguments::new(
        &unique("no-q"),
        "amq.direct",
        "k"
    )))
    .is_err());
    // RabbitMQ: "NOT_FOUND - no queue '...' in vhost '/'".
    rs::assert_closed(&mut ev, 404, "NOT_FOUND").await;
}

#[both_runtimes]
async fn purge_returns_the_number_of_ready_messages_removed() {
    let b = broker().await;
    let (_conn, ch, mut ev) = rs::open(&b).await;
    rs::confirm_select(&ch).await;
    let q = rs::queue(&ch, "purge").await;
    for i in 0..4 {
        rs::publish(&ch, "", &q, format!("{i}").as_bytes()).await;
    }
    rs::acked(&mut ev, 4).await;
    // One message is out unacknowledged: purge does not touch it.
    let (tag, _, remaining, body) = rs::get(&ch, &q, false).await.expect("message");
    assert_eq!((remaining, body.as_slice()), (3, &b"0"[..]));
    let purged = tmo!(ch.queue_purge(rs::QueuePurgeArguments::new(&q)))
        .expect("purge")
        .expect("purge-ok");
    assert_eq!(purged, 3);
    let again = tmo!(ch.queue_purge(rs::QueuePurgeArguments::new(&q)))
        .expect("purge")
        .expect("purge-ok");
    assert_eq!(again, 0);
    // Rejected with requeue, the unacked one is back.
    tmo!(ch.basic_reject(rs::BasicRejectArguments::new(tag, true))).expect("reject");
    let (_, redelivered, remaining, body) = rs::get(&ch, &q, true).await.expect("requeued");
    assert!(redelivered);
    assert_eq!((remaining, body.as_slice()), (0, &b"0"[..]));
}

#[both_runtimes]
async fn purge_of_a_missing_queue_gets_404() {
    let b = broker().await;
    let (conn, _) = rs::connect(&b).await;
    let (ch, mut ev) = rs::channel(&conn).await;
    assert!(tmo!(ch.queue_purge(rs::QueuePurgeArguments::new(&unique("no-q")))).is_err());
    rs::assert_closed(&mut ev, 404, "NOT_FOUND").await;
}

#[both_runtimes]
async fn delete_returns_the_message_count() {
    let b = broker().await;
    let (_conn, ch, mut ev) = rs::open(&b).await;
    rs::confirm_select(&ch).await;
    let q = rs::queue(&ch, "delete-count").await;
    for _ in 0..5 {
        rs::publish(&ch, "", &q, b"x").await;
    }
    rs::acked(&mut ev, 5).await;
    let n = tmo!(ch.queue_delete(rs::QueueDeleteArguments::new(&q)))
        .expect("delete")
        .expect("delete-ok");
    assert_eq!(n, 5);
    let mut args = rs::QueueDeclareArguments::new(&q);
    args.passive(true);
    assert!(tmo!(ch.queue_declare(args)).is_err(), "deleted");
}

#[both_runtimes]
async fn deleting_a_missing_queue_succeeds_with_zero() {
    let b = broker().await;
    let (_conn, ch) = lp::open(&b).await;
    // Note: RabbitMQ 3.10 answers delete-ok (0 messages) for a queue that
    // does not exist, rather than 404.
    let n = tmo!(ch.queue_delete(&unique("never-was"), lp::QueueDeleteOptions::default()))
        .expect("delete-ok");
    assert_eq!(n, 0);
}

#[both_runtimes]
async fn delete_if_unused_refuses_while_a_consumer_exists() {
    let b = broker().await;
    let (conn, _) = rs::connect(&b).await;
    let (ch, mut ev) = rs::channel(&conn).await;
    let q = rs::queue(&ch, "if-unused").await;
    let (consumer_ch, _) = rs::channel(&conn).await;
    let (tag, _rx) = rs::consume(&consumer_ch, &q, "", false).await;
    let mut del = rs::QueueDeleteArguments::new(&q);
    del.if_unused(true);
    assert!(tmo!(ch.queue_delete(del.clone())).is_err());
    // RabbitMQ: "PRECONDITION_FAILED - queue '...' in vhost '/' in use".
    rs::assert_closed(&mut ev, 406, "PRECONDITION_FAILED").await;
    tmo!(consumer_ch.basic_cancel(rs::BasicCancelArguments::new(&tag))).expect("cancel");
    let (ch, _) = rs::channel(&conn).await;
    let n = tmo!(ch.queue_delete(del))
        .expect("delete")
        .expect("delete-ok");
    assert_eq!(n, 0);
}

#[both_runtimes]
async fn delete_if_empty_refuses_while_messages_are_ready() {
    let b = broker().await;
    let (conn, _) = rs::connect(&b).await;
    let (ch, mut ev) = rs::channel(&conn).await;
    let q = rs::queue(&ch, "if-empty").await;
    rs::confirm_select(&ch).await;
    rs::publish(&ch, "", &q, b"still here").await;
    rs::acked(&mut ev, 1).await;
    let mut del = rs::QueueDeleteArguments::new(&q);
    del.if_empty(true);
    assert!(tmo!(ch.queue_delete(del.clone())).is_err());
    // RabbitMQ 3.10.8's text, word for word (pika against it).
    let text = format!("PRECONDITION_FAILED - queue '{q}' in vhost '/' not empty");
    rs::assert_closed(&mut ev, 406, &text).await;
    let (ch, _) = rs::channel(&conn).await;
    assert!(rs::get(&ch, &q, true).await.is_some());
    let n = tmo!(ch.queue_delete(del))
        .expect("delete")
        .expect("delete-ok");
    assert_eq!(n, 0);
}

/// A queue both in use and not empty refuses an if-unused if-empty delete
/// as not empty, RabbitMQ's order (3.10.8, pika: "PRECONDITION_FAILED -
/// queue '...' in vhost '/' not empty").
#[both_runtimes]
async fn delete_if_unused_and_if_empty_refuses_as_not_empty_first() {
    let b = broker().await;
    let conn = lp::connect(&b).await;
    let consumer_ch = lp::channel(&conn).await;
    tmo!(consumer_ch.basic_qos(1, lp::BasicQosOptions::default())).expect("qos");
    let q = lp::queue(&consumer_ch, "in-use-and-not-empty").await;
    let mut consumer = lp::consume(&consumer_ch, &q, "holding").await;
    lp::publish(&consumer_ch, "", &q, b"held").await;
    lp::publish(&consumer_ch, "", &q, b"ready").await;
    lp::next(&mut consumer).await;
    let ch = lp::channel(&conn).await;
    let both = lp::QueueDeleteOptions {
        if_unused: true,
        if_empty: true,
        ..Default::default()
    };
    let refused = tmo!(ch.queue_delete(&q, both)).unwrap_err().to_string();
    assert!(refused.contains("PRECONDITION_FAILED"), "{refused}");
    assert!(refused.contains("not empty"), "{refused}");
}

#[both_runtimes]
async fn redeclaring_a_queue_differently_gets_406() {
    let b = broker().await;
    let conn = lp::connect(&b).await;
    let ch = lp::channel(&conn).await;
    let q = lp::queue_with(
        &ch,
        "redeclare-q",
        lp::table(vec![("x-max-length", lp::AMQPValue::LongInt(10))]),
    )
    .await;
    // Passive: arguments and flags are not compared.
    tmo!(ch.queue_declare(
        &q,
        lp::QueueDeclareOptions {
            passive: true,
            durable: true,
            ..Default::default()
        },
        lp::FieldTable::default()
    ))
    .expect("passive ignores flags");
    // Durability differs: "PRECONDITION_FAILED - inequivalent arg 'durable' for queue ...".
    lp::assert_err(
        tmo!(ch.queue_declare(
            &q,
            lp::QueueDeclareOptions {
                durable: true,
                ..Default::default()
            },
            lp::table(vec![("x-max-length", lp::AMQPValue::LongInt(10))])
        )),
        406,
        "PRECONDITION_FAILED",
    );
    // An argument differs: "inequivalent arg 'x-max-length' for queue ...".
    let ch = lp::channel(&conn).await;
    lp::assert_err(
        tmo!(ch.queue_declare(
            &q,
            lp::QueueDeclareOptions::default(),
            lp::table(vec![("x-max-length", lp::AMQPValue::LongInt(11))])
        )),
        406,
        "PRECONDITION_FAILED",
    );
    // Auto-delete differs.
    let ch = lp::channel(&conn).await;
    lp::assert_err(
        tmo!(ch.queue_declare(
            &q,
            lp::QueueDeclareOptions {
                auto_delete: true,
                ..Default::default()
            },
            lp::table(vec![("x-max-length", lp::AMQPValue::LongInt(10))])
        )),
        406,
        "PRECONDITION_FAILED",
    );
    // The same declaration is fine.
    let ch = lp::channel(&conn).await;
    tmo!(ch.queue_declare(
        &q,
        lp::QueueDeclareOptions::default(),
        lp::table(vec![("x-max-length", lp::AMQPValue::LongInt(10))])
    ))
    .expect("identical redeclare");
}

#[both_runtimes]
async fn queue_names_starting_with_amq_are_reserved() {
    let b = broker().await;
    let (conn, _) = rs::connect(&b).await;
    let (ch, mut ev) = rs::channel(&conn).await;
    assert!(tmo!(ch.queue_declare(rs::QueueDeclareArguments::new(&unique("amq.mine")))).is_err());
    // RabbitMQ: "ACCESS_REFUSED - queue name 'amq.mine...' contains reserved prefix 'amq.*'".
    rs::assert_closed(&mut ev, 403, "ACCESS_REFUSED").await;
}

#[both_runtimes]
async fn durable_queue_declare_and_delete() {
    let b = broker().await;
    let (_conn, ch, _ev) = rs::open(&b).await;
    let q = unique("durable-q");
    let (name, m, c) = tmo!(ch.queue_declare(rs::QueueDeclareArguments::durable_client_named(&q)))
        .expect("declare")
        .expect("declare-ok");
    assert_eq!((name.as_str(), m, c), (q.as_str(), 0, 0));
    let mut persistent = rs::BasicProperties::default();
    persistent.with_delivery_mode(2);
    rs::publish_props(&ch, "", &q, b"persisted", persistent).await;
    let (_, _, _, body) = rs::get(&ch, &q, true).await.expect("message");
    assert_eq!(body, b"persisted");
    let n = tmo!(ch.queue_delete(rs::QueueDeleteArguments::new(&q)))
        .expect("delete")
        .expect("delete-ok");
    assert_eq!(n, 0);
}
