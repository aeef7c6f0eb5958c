//! Acknowledgements: prefetch (qos), ack / ack multiple, nack, reject,
//! recover, unknown delivery tags, and requeueing of unacked messages
//! (order and the redelivered flag).

#[macro_use]
mod common;

use common::*;

#[both_runtimes]
async fn prefetch_limits_unacked_deliveries() {
    let b = broker().await;
    let (_conn, ch) = lp::open(&b).await;
    let q = lp::queue(&ch, "prefetch").await;
    tmo!(ch.basic_qos(2, lp::BasicQosOptions::default())).expect("qos");
    for i in 0..5 {
        lp::publish(&ch, "", &q, format!("{i}").as_bytes()).await;
    }
    let mut c = lp::consume(&ch, &q, "").await;
    let d0 = lp::next(&mut c).await;
    let d1 = lp::next(&mut c).await;
    assert_eq!((lp::text(&d0), lp::text(&d1)), ("0".into(), "1".into()));
    // Two unacked: the third waits.
    lp::nothing(&mut c).await;
    lp::ack(&ch, d0.delivery_tag).await;
    let d2 = lp::next(&mut c).await;
    assert_eq!(lp::text(&d2), "2");
    lp::nothing(&mut c).await;
    // Acking both outstanding lets two more through.
    tmo!(ch.basic_ack(d2.delivery_tag, lp::BasicAckOptions { multiple: true })).expect("ack");
    let d3 = lp::next(&mut c).await;
    let d4 = lp::next(&mut c).await;
    assert_eq!((lp::text(&d3), lp::text(&d4)), ("3".into(), "4".into()));
}

#[both_runtimes]
async fn prefetch_applies_per_consumer_and_zero_means_unlimited() {
    let b = broker().await;
    let (_conn, ch, _ev) = rs::open(&b).await;
    let q = rs::queue(&ch, "prefetch-rs").await;
    for i in 0..6 {
        rs::publish(&ch, "", &q, format!("{i}").as_bytes()).await;
    }
    tmo!(ch.basic_qos(rs::BasicQosArguments::new(0, 1, false))).expect("qos 1");
    let (_, mut one) = rs::consume(&ch, &q, "one", false).await;
    let first = rs::next(&mut one).await;
    assert_eq!(first.text(), "0");
    rs::nothing(&mut one).await;
    // A consumer started after qos 0 has no limit and takes the rest.
    tmo!(ch.basic_qos(rs::BasicQosArguments::new(0, 0, false))).expect("qos 0");
    let (_, mut all) = rs::consume(&ch, &q, "all", false).await;
    for i in 1..6 {
        assert_eq!(rs::next(&mut all).await.text(), format!("{i}"));
    }
    rs::nothing(&mut one).await;
}

#[both_runtimes]
async fn ack_multiple_acks_everything_up_to_the_tag() {
    let b = broker().await;
    let (conn, _) = rs::connect(&b).await;
    let (ch, _) = rs::channel(&conn).await;
    let q = rs::queue(&ch, "ack-multiple").await;
    for i in 0..5 {
        rs::publish(&ch, "", &q, format!("{i}").as_bytes()).await;
    }
    let (_, mut rx) = rs::consume(&ch, &q, "", false).await;
    let mut tags = Vec::new();
    for _ in 0..5 {
        tags.push(rs::next(&mut rx).await.tag);
    }
    assert_eq!(tags, [1, 2, 3, 4, 5]);
    tmo!(ch.basic_ack(rs::BasicAckArguments::new(3, true))).expect("ack multiple");
    tmo!(ch.close()).expect("close");
    // Only 4 and 5 were unacked: they come back, redelivered, in order.
    let (ch, _) = rs::channel(&conn).await;
    let a = rs::get(&ch, &q, true).await.expect("first requeued");
    let c = rs::get(&ch, &q, true).await.expect("second requeued");
    assert_eq!((a.1, a.3.as_slice()), (true, &b"3"[..]));
    assert_eq!((c.1, c.3.as_slice()), (true, &b"4"[..]));
    assert!(rs::get(&ch, &q, true).await.is_none());
}

#[both_runtimes]
async fn ack_multiple_with_tag_zero_acks_all_outstanding() {
    let b = broker().await;
    let (conn, ch) = lp::open(&b).await;
    let q = lp::queue(&ch, "ack-zero").await;
    for _ in 0..3 {
        lp::publish(&ch, "", &q, b"x").await;
    }
    let mut c = lp::consume(&ch, &q, "").await;
    for _ in 0..3 {
        lp::next(&mut c).await;
    }
    tmo!(ch.basic_ack(0, lp::BasicAckOptions { multiple: true })).expect("ack 0 multiple");
    tmo!(ch.close(200, "bye")).expect("close");
    let ch = lp::channel(&conn).await;
    assert!(lp::get(&ch, &q, true).await.is_none(), "all were acked");
}

#[both_runtimes]
async fn nack_with_requeue_puts_the_message_back_first_and_redelivered() {
    let b = broker().await;
    let (_conn, ch) = lp::open(&b).await;
    let q = lp::queue(&ch, "nack").await;
    for body in ["a", "b", "c"] {
        lp::publish(&ch, "", &q, body.as_bytes()).await;
    }
    let a = lp::get(&ch, &q, false).await.expect("a");
    assert_eq!(a.delivery.data, b"a");
    assert!(!a.delivery.redelivered);
    assert_eq!(a.message_count, 2);
    tmo!(ch.basic_nack(
        a.delivery.delivery_tag,
        lp::BasicNackOptions {
            requeue: true,
            multiple: false
        }
    ))
    .expect("nack");
    let again = lp::get(&ch, &q, false).await.expect("a again");
    assert_eq!(
        again.delivery.data, b"a",
        "the requeued message comes first"
    );
    assert!(again.delivery.redelivered);
    assert_eq!(again.message_count, 2);
    lp::ack(&ch, again.delivery.delivery_tag).await;
    let next = lp::get(&ch, &q, true).await.expect("b");
    assert_eq!(next.delivery.data, b"b");
    assert!(!next.delivery.redelivered);
}

#[both_runtimes]
async fn nack_multiple_requeues_in_original_order() {
    let b = broker().await;
    let (_conn, ch, _ev) = rs::open(&b).await;
    let q = rs::queue(&ch, "nack-multiple").await;
    for i in 0..4 {
        rs::publish(&ch, "", &q, format!("{i}").as_bytes()).await;
    }
    let (tag, mut rx) = rs::consume(&ch, &q, "", false).await;
    let mut last = 0;
    for i in 0..4 {
        let m = rs::next(&mut rx).await;
        assert_eq!(m.text(), format!("{i}"));
        last = m.tag;
    }
    tmo!(ch.basic_cancel(rs::BasicCancelArguments::new(&tag))).expect("cancel");
    tmo!(ch.basic_nack(rs::BasicNackArguments::new(last, true, true))).expect("nack");
    for i in 0..4 {
        let (_, redelivered, _, body) = rs::get(&ch, &q, true).await.expect("requeued");
        assert!(redelivered);
        assert_eq!(body, format!("{i}").as_bytes());
    }
}

#[both_runtimes]
async fn nack_without_requeue_discards() {
    let b = broker().await;
    let (_conn, ch) = lp::open(&b).await;
    let q = lp::queue(&ch, "nack-drop").await;
    lp::publish(&ch, "", &q, b"gone").await;
    let m = lp::get(&ch, &q, false).await.expect("message");
    tmo!(ch.basic_nack(
        m.delivery.delivery_tag,
        lp::BasicNackOptions {
            requeue: false,
            multiple: false
        }
    ))
    .expect("nack");
    assert!(lp::get(&ch, &q, true).await.is_none());
}

#[both_runtimes]
async fn reject_with_and_without_requeue() {
    let b = broker().await;
    let (_conn, ch, _ev) = rs::open(&b).await;
    let q = rs::queue(&ch, "reject").await;
    rs::publish(&ch, "", &q, b"keep").await;
    rs::publish(&ch, "", &q, b"drop").await;
    let (keep_tag, _, _, body) = rs::get(&ch, &q, false).await.expect("keep");
    assert_eq!(body, b"keep");
    let (drop_tag, _, _, body) = rs::get(&ch, &q, false).await.expect("drop");
    assert_eq!(body, b"drop");
    tmo!(ch.basic_reject(rs::BasicRejectArguments::new(drop_tag, false))).expect("reject");
    tmo!(ch.basic_reject(rs::BasicRejectArguments::new(keep_tag, true))).expect("reject");
    let (_, redelivered, count, body) = rs::get(&ch, &q, true).await.expect("kept");
    assert_eq!(
        (redelivered, count, body.as_slice()),
        (true, 0, &b"keep"[..])
    );
    assert!(
        rs::get(&ch, &q, true).await.is_none(),
        "the dropped one is gone"
    );
}

#[both_runtimes]
async fn recover_with_requeue_redelivers_unacked_messages() {
    let b = broker().await;
    let (_conn, ch) = lp::open(&b).await;
    let q = lp::queue(&ch, "recover").await;
    for body in ["x", "y"] {
        lp::publish(&ch, "", &q, body.as_bytes()).await;
    }
    let mut c = lp::consume(&ch, &q, "").await;
    let x = lp::next(&mut c).await;
    let y = lp::next(&mut c).await;
    assert!(!x.redelivered && !y.redelivered);
    lp::ack(&ch, x.delivery_tag).await;
    tmo!(ch.basic_recover(lp::BasicRecoverOptions { requeue: true })).expect("recover");
    let again = lp::next(&mut c).await;
    assert_eq!(lp::text(&again), "y");
    assert!(again.redelivered);
    // Redelivery gets a fresh delivery tag.
    assert!(again.delivery_tag > y.delivery_tag);
    lp::ack(&ch, again.delivery_tag).await;
    lp::nothing(&mut c).await;
}

#[both_runtimes]
async fn acking_an_unknown_delivery_tag_gets_406() {
    let b = broker().await;
    let (conn, ch) = lp::open(&b).await;
    let mut errors = lp::watch_errors(&ch);
    tmo!(ch.basic_ack(99, lp::BasicAckOptions::default())).expect("ack sent");
    let err = tmo!(errors.recv()).expect("channel closed");
    let (code, text) = lp::code(&err);
    // RabbitMQ: "PRECONDITION_FAILED - unknown delivery tag 99".
    assert_eq!(code, 406, "{text}");
    assert_text_prefix(&text, "PRECONDITION_FAILED");
    assert!(conn.status().connected(), "only the channel is closed");
}

#[both_runtimes]
async fn acking_twice_gets_406() {
    let b = broker().await;
    let (conn, _) = rs::connect(&b).await;
    let (ch, mut ev) = rs::channel(&conn).await;
    let q = rs::queue(&ch, "double-ack").await;
    rs::publish(&ch, "", &q, b"once").await;
    let (tag, _, _, _) = rs::get(&ch, &q, false).await.expect("message");
    rs::ack(&ch, tag).await;
    rs::ack(&ch, tag).await;
    rs::assert_closed(&mut ev, 406, "PRECONDITION_FAILED").await;
    assert!(conn.is_open());
}

#[both_runtimes]
async fn nack_and_reject_of_unknown_tags_get_406() {
    let b = broker().await;
    let (conn, _) = rs::connect(&b).await;
    let (ch, mut ev) = rs::channel(&conn).await;
    tmo!(ch.basic_nack(rs::BasicNackArguments::new(7, false, true))).expect("nack sent");
    rs::assert_closed(&mut ev, 406, "PRECONDITION_FAILED").await;
    let (ch, mut ev) = rs::channel(&conn).await;
    tmo!(ch.basic_reject(rs::BasicRejectArguments::new(7, true))).expect("reject sent");
    rs::assert_closed(&mut ev, 406, "PRECONDITION_FAILED").await;
}

#[both_runtimes]
async fn delivery_tags_belong_to_their_channel() {
    let b = broker().await;
    let (conn, _) = rs::connect(&b).await;
    let (ch1, _) = rs::channel(&conn).await;
    let (ch2, mut ev2) = rs::channel(&conn).await;
    let q = rs::queue(&ch1, "tag-scope").await;
    rs::publish(&ch1, "", &q, b"m").await;
    let (tag, _, _, _) = rs::get(&ch1, &q, false).await.expect("message");
    assert_eq!(tag, 1);
    // Tag 1 means nothing on channel 2.
    rs::ack(&ch2, tag).await;
    rs::assert_closed(&mut ev2, 406, "PRECONDITION_FAILED").await;
    rs::ack(&ch1, tag).await;
    assert!(rs::get(&ch1, &q, true).await.is_none());
}

#[both_runtimes]
async fn acking_a_no_ack_delivery_gets_406() {
    let b = broker().await;
    let (_conn, ch) = lp::open(&b).await;
    let q = lp::queue(&ch, "no-ack-then-ack").await;
    lp::publish(&ch, "", &q, b"auto").await;
    let m = lp::get(&ch, &q, true).await.expect("message");
    let mut errors = lp::watch_errors(&ch);
    tmo!(ch.basic_ack(m.delivery.delivery_tag, lp::BasicAckOptions::default())).expect("sent");
    let err = tmo!(errors.recv()).expect("channel closed");
    assert_eq!(lp::code(&err).0, 406);
}

#[both_runtimes]
async fn unacked_messages_are_requeued_in_order_when_the_channel_closes() {
    let b = broker().await;
    let conn = lp::connect(&b).await;
    let ch = lp::channel(&conn).await;
    let q = lp::queue(&ch, "requeue-on-close").await;
    for i in 0..10 {
        lp::publish(&ch, "", &q, format!("{i}").as_bytes()).await;
    }
    let consumer_ch = lp::channel(&conn).await;
    let mut c = lp::consume(&consumer_ch, &q, "").await;
    for i in 0..10 {
        let d = lp::next(&mut c).await;
        assert_eq!(lp::text(&d), format!("{i}"));
        // Ack the even ones only.
        if i % 2 == 0 {
            lp::ack(&consumer_ch, d.delivery_tag).await;
        }
    }
    tmo!(consumer_ch.close(200, "bye")).expect("close");
    let ch2 = lp::channel(&conn).await;
    let mut c2 = lp::consume(&ch2, &q, "").await;
    for i in [1, 3, 5, 7, 9] {
        let d = lp::next(&mut c2).await;
        assert_eq!(lp::text(&d), format!("{i}"));
        assert!(d.redelivered, "message {i} is marked redelivered");
        lp::ack(&ch2, d.delivery_tag).await;
    }
    lp::nothing(&mut c2).await;
}

#[both_runtimes]
async fn unacked_messages_go_back_ahead_of_newer_ones_when_the_connection_closes() {
    let b = broker().await;
    let (conn, ch, _ev) = rs::open(&b).await;
    let q = rs::queue(&ch, "requeue-on-conn-close").await;
    for i in 0..3 {
        rs::publish(&ch, "", &q, format!("old{i}").as_bytes()).await;
    }
    let (consumer_conn, _) = rs::connect(&b).await;
    let (cch, _) = rs::channel(&consumer_conn).await;
    // Room for exactly the three old messages, so "new" stays queued.
    tmo!(cch.basic_qos(rs::BasicQosArguments::new(0, 3, false))).expect("qos");
    let (_, mut rx) = rs::consume(&cch, &q, "", false).await;
    for i in 0..3 {
        assert_eq!(rs::next(&mut rx).await.text(), format!("old{i}"));
    }
    rs::publish(&ch, "", &q, b"new").await;
    tmo!(consumer_conn.close()).expect("close");
    let (_, mut rx) = rs::consume(&ch, &q, "", true).await;
    for body in ["old0", "old1", "old2", "new"] {
        let m = rs::next(&mut rx).await;
        assert_eq!(m.text(), body);
        assert_eq!(m.redelivered, body != "new", "redelivered flag of {body}");
    }
    drop(conn);
}
