//! Consumers: round-robin dispatch, consumer tags, exclusive consumers,
//! cancel (by the client and, when the queue goes away, by the broker).

#[macro_use]
mod common;

use common::*;
use futures_lite::StreamExt;

#[both_runtimes]
async fn two_consumers_get_messages_in_exact_alternation() {
    let b = broker().await;
    let conn = lp::connect(&b).await;
    let ch = lp::channel(&conn).await;
    let q = lp::queue(&ch, "round-robin").await;
    let ch1 = lp::channel(&conn).await;
    let ch2 = lp::channel(&conn).await;
    let mut c1 = lp::consume_opts(
        &ch1,
        &q,
        "first",
        lp::BasicConsumeOptions {
            no_ack: true,
            ..Default::default()
        },
    )
    .await;
    let mut c2 = lp::consume_opts(
        &ch2,
        &q,
        "second",
        lp::BasicConsumeOptions {
            no_ack: true,
            ..Default::default()
        },
    )
    .await;
    for i in 0..10 {
        lp::publish(&ch, "", &q, format!("{i}").as_bytes()).await;
    }
    let mut got1 = Vec::new();
    let mut got2 = Vec::new();
    for _ in 0..5 {
        got1.push(lp::text(&lp::next(&mut c1).await));
        got2.push(lp::text(&lp::next(&mut c2).await));
    }
    // The consumer that registered first gets the first message.
    assert_eq!(got1, ["0", "2", "4", "6", "8"]);
    assert_eq!(got2, ["1", "3", "5", "7", "9"]);
    lp::nothing(&mut c1).await;
    lp::nothing(&mut c2).await;
}

#[both_runtimes]
async fn three_consumers_on_one_channel_share_round_robin() {
    let b = broker().await;
    let (_conn, ch, _ev) = rs::open(&b).await;
    let q = rs::queue(&ch, "rr3").await;
    let (_, mut a) = rs::consume(&ch, &q, "a", true).await;
    let (_, mut bb) = rs::consume(&ch, &q, "b", true).await;
    let (_, mut c) = rs::consume(&ch, &q, "c", true).await;
    for i in 0..9 {
        rs::publish(&ch, "", &q, format!("{i}").as_bytes()).await;
    }
    let mut got = [Vec::new(), Vec::new(), Vec::new()];
    for _ in 0..3 {
        for (slot, rx) in [&mut a, &mut bb, &mut c].into_iter().enumerate() {
            let m = rs::next(rx).await;
            assert_eq!(m.consumer_tag, ["a", "b", "c"][slot]);
            assert!(!m.redelivered);
            got[slot].push(m.text());
        }
    }
    assert_eq!(got[0], ["0", "3", "6"]);
    assert_eq!(got[1], ["1", "4", "7"]);
    assert_eq!(got[2], ["2", "5", "8"]);
}

#[both_runtimes]
async fn consumer_gets_the_backlog_in_order_then_new_messages() {
    let b = broker().await;
    let (_conn, ch, _ev) = rs::open(&b).await;
    let q = rs::queue(&ch, "backlog").await;
    for i in 0..20 {
        rs::publish(&ch, "", &q, format!("{i}").as_bytes()).await;
    }
    let (tag, mut rx) = rs::consume(&ch, &q, "", false).await;
    // Server-generated consumer tags look like "amq.ctag-...".
    assert!(tag.starts_with("amq.ctag-"), "{tag}");
    for i in 0..20 {
        let m = rs::next(&mut rx).await;
        assert_eq!(m.text(), format!("{i}"));
        assert_eq!(m.consumer_tag, tag);
        assert_eq!(m.exchange, "");
        assert_eq!(m.routing_key, q);
        // Delivery tags count up from 1 on each channel.
        assert_eq!(m.tag, i + 1);
        rs::ack(&ch, m.tag).await;
    }
    rs::publish(&ch, "", &q, b"late").await;
    assert_eq!(rs::next(&mut rx).await.text(), "late");
}

#[both_runtimes]
async fn consumer_tag_chosen_by_the_client_is_kept() {
    let b = broker().await;
    let (_conn, ch) = lp::open(&b).await;
    let q = lp::queue(&ch, "tagged").await;
    let tag = unique("my-tag");
    let mut c = lp::consume(&ch, &q, &tag).await;
    assert_eq!(c.tag().as_str(), tag);
    lp::publish(&ch, "", &q, b"x").await;
    let d = lp::next(&mut c).await;
    assert_eq!(d.delivery_tag, 1);
    assert!(!d.redelivered);
}

#[both_runtimes]
async fn reusing_a_consumer_tag_on_a_channel_is_a_530_connection_error() {
    let b = broker().await;
    let (conn, mut conn_ev) = rs::connect(&b).await;
    let (ch, _) = rs::channel(&conn).await;
    let q = rs::queue(&ch, "dup-tag").await;
    let _first = rs::consume(&ch, &q, "same-tag", false).await;
    let res = tmo!(ch.basic_consume_rx(rs::BasicConsumeArguments::new(&q, "same-tag")));
    assert!(res.is_err());
    // Note: a connection error, not a channel error: "NOT_ALLOWED - attempt
    // to reuse consumer tag 'same-tag'".
    let rs::ConnClose { code, text, .. } = tmo!(conn_ev.recv()).expect("connection.close");
    assert_eq!(code, 530, "{text}");
    assert_text_prefix(&text, "NOT_ALLOWED");
}

#[both_runtimes]
async fn consuming_from_a_missing_queue_gets_404() {
    let b = broker().await;
    let (_conn, ch) = lp::open(&b).await;
    let res = tmo!(ch.basic_consume(
        &unique("no-such-queue"),
        "",
        lp::BasicConsumeOptions::default(),
        lp::FieldTable::default()
    ));
    lp::assert_err(res, 404, "NOT_FOUND");
}

#[both_runtimes]
async fn exclusive_consumer_shuts_out_other_consumers_with_403() {
    let b = broker().await;
    let (conn, _) = rs::connect(&b).await;
    let (ch, _) = rs::channel(&conn).await;
    let q = rs::queue(&ch, "exclusive-consumer").await;
    let mut args = rs::BasicConsumeArguments::new(&q, "only-me");
    args.exclusive = true;
    let (_, mut rx) = tmo!(ch.basic_consume_rx(args)).expect("exclusive consume");
    let (other, mut ev) = rs::channel(&conn).await;
    assert!(tmo!(other.basic_consume_rx(rs::BasicConsumeArguments::new(&q, "me-too"))).is_err());
    // RabbitMQ: "ACCESS_REFUSED - queue '...' in vhost '/' in exclusive use".
    rs::assert_closed(&mut ev, 403, "ACCESS_REFUSED").await;
    // The exclusive consumer carries on.
    rs::publish(&ch, "", &q, b"all mine").await;
    assert_eq!(rs::next(&mut rx).await.text(), "all mine");
}

#[both_runtimes]
async fn exclusive_consume_is_refused_while_another_consumer_exists() {
    let b = broker().await;
    let (conn, _) = rs::connect(&b).await;
    let (ch, _) = rs::channel(&conn).await;
    let q = rs::queue(&ch, "not-alone").await;
    let _plain = rs::consume(&ch, &q, "plain", false).await;
    let (other, mut ev) = rs::channel(&conn).await;
    let mut args = rs::BasicConsumeArguments::new(&q, "wants-all");
    args.exclusive = true;
    assert!(tmo!(other.basic_consume_rx(args)).is_err());
    rs::assert_closed(&mut ev, 403, "ACCESS_REFUSED").await;
}

#[both_runtimes]
async fn basic_cancel_stops_deliveries_and_leaves_messages_queued() {
    let b = broker().await;
    let (_conn, ch, mut ev) = rs::open(&b).await;
    rs::confirm_select(&ch).await;
    let q = rs::queue(&ch, "cancelled").await;
    let (tag, mut rx) = rs::consume(&ch, &q, "to-cancel", true).await;
    rs::publish(&ch, "", &q, b"before").await;
    assert_eq!(rs::next(&mut rx).await.text(), "before");
    let cancelled = tmo!(ch.basic_cancel(rs::BasicCancelArguments::new(&tag))).expect("cancel");
    assert_eq!(cancelled, tag);
    rs::publish(&ch, "", &q, b"after").await;
    rs::acked(&mut ev, 2).await;
    rs::nothing(&mut rx).await;
    assert_eq!(rs::counts(&ch, &q).await, (1, 0));
}

#[both_runtimes]
async fn cancelling_an_unknown_consumer_tag_is_not_an_error() {
    let b = broker().await;
    let (_conn, ch, _ev) = rs::open(&b).await;
    // Note: RabbitMQ answers cancel-ok for a tag it does not know.
    let tag = tmo!(ch.basic_cancel(rs::BasicCancelArguments::new("no-such-consumer")))
        .expect("cancel-ok");
    assert_eq!(tag, "no-such-consumer");
    // The channel is still usable.
    let q = rs::queue(&ch, "after-cancel").await;
    assert_eq!(rs::counts(&ch, &q).await, (0, 0));
}

#[both_runtimes]
async fn deleting_the_queue_cancels_its_consumers_lapin() {
    let b = broker().await;
    let conn = lp::connect(&b).await;
    let ch = lp::channel(&conn).await;
    let q = lp::queue(&ch, "deleted-under-consumer").await;
    let consumer_ch = lp::channel(&conn).await;
    let mut c = lp::consume(&consumer_ch, &q, "doomed").await;
    lp::publish(&ch, "", &q, b"one").await;
    let d = lp::next(&mut c).await;
    lp::ack(&consumer_ch, d.delivery_tag).await;
    tmo!(ch.queue_delete(&q, lp::QueueDeleteOptions::default())).expect("delete");
    // The broker sends basic.cancel (consumer_cancel_notify): lapin ends
    // the consumer's stream.
    let end = tmo!(c.next());
    assert!(end.is_none(), "stream should end, got {end:?}");
    assert!(!c.state().is_active());
    // The consumer's channel stays open.
    assert!(consumer_ch.status().connected());
    lp::queue(&consumer_ch, "still-usable").await;
}

#[both_runtimes]
async fn deleting_the_queue_cancels_its_consumers_amqprs() {
    let b = broker().await;
    let (conn, _) = rs::connect(&b).await;
    let (ch, _) = rs::channel(&conn).await;
    let q = rs::queue(&ch, "deleted-under-amqprs").await;
    let (consumer_ch, mut ev) = rs::channel(&conn).await;
    let (tag, _rx) = rs::consume(&consumer_ch, &q, "", false).await;
    tmo!(ch.queue_delete(rs::QueueDeleteArguments::new(&q))).expect("delete");
    match tmo!(ev.recv()) {
        Some(rs::Event::Cancel { tag: got }) => assert_eq!(got, tag),
        other => panic!("expected basic.cancel from the broker, got {other:?}"),
    }
    assert!(consumer_ch.is_open());
}

#[both_runtimes]
async fn no_ack_consumer_empties_the_queue() {
    let b = broker().await;
    let (_conn, ch) = lp::open(&b).await;
    let q = lp::queue(&ch, "no-ack").await;
    let mut c = lp::consume_opts(
        &ch,
        &q,
        "",
        lp::BasicConsumeOptions {
            no_ack: true,
            ..Default::default()
        },
    )
    .await;
    for i in 0..5 {
        lp::publish(&ch, "", &q, format!("{i}").as_bytes()).await;
    }
    for i in 0..5 {
        let d = lp::next(&mut c).await;
        assert_eq!(lp::text(&d), format!("{i}"));
    }
    tmo!(ch.basic_cancel(c.tag().as_str(), lp::BasicCancelOptions::default())).expect("cancel");
    let info = tmo!(ch.queue_declare(
        &q,
        lp::QueueDeclareOptions {
            passive: true,
            ..Default::default()
        },
        lp::FieldTable::default()
    ))
    .expect("passive");
    assert_eq!((info.message_count(), info.consumer_count()), (0, 0));
}

#[both_runtimes]
async fn consumers_on_two_queues_on_one_channel_are_kept_apart() {
    let b = broker().await;
    let (_conn, ch, _ev) = rs::open(&b).await;
    let q1 = rs::queue(&ch, "apart-1").await;
    let q2 = rs::queue(&ch, "apart-2").await;
    let (t1, mut rx1) = rs::consume(&ch, &q1, "", true).await;
    let (t2, mut rx2) = rs::consume(&ch, &q2, "", true).await;
    assert_ne!(t1, t2);
    rs::publish(&ch, "", &q2, b"for 2").await;
    rs::publish(&ch, "", &q1, b"for 1").await;
    let m1 = rs::next(&mut rx1).await;
    let m2 = rs::next(&mut rx2).await;
    assert_eq!((m1.text(), m1.consumer_tag), ("for 1".to_owned(), t1));
    assert_eq!((m2.text(), m2.consumer_tag), ("for 2".to_owned(), t2));
}
