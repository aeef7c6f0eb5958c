//! Publishing: mandatory returns, missing exchanges, basic.get, large and
//! empty bodies, every property and header value type, ordering, publisher
//! confirms and transactions.

#[macro_use]
mod common;

use common::lp::AMQPValue;
use common::*;
use lapin::types::{ByteArray, DecimalValue, FieldArray};

async fn confirm_channel(conn: &lp::Connection) -> lp::Channel {
    let ch = lp::channel(conn).await;
    tmo!(ch.confirm_select(lp::ConfirmSelectOptions::default())).expect("confirm.select");
    ch
}

#[both_runtimes]
async fn mandatory_unroutable_message_comes_back_with_312_lapin() {
    let b = broker().await;
    let conn = lp::connect(&b).await;
    let ch = confirm_channel(&conn).await;
    let props = lp::BasicProperties::default().with_message_id("m-1".into());
    let confirm = tmo!(ch.basic_publish(
        "amq.direct",
        "nobody-bound-this-key",
        lp::BasicPublishOptions {
            mandatory: true,
            ..Default::default()
        },
        b"bounce",
        props
    ))
    .expect("publish");
    // basic.return arrives before the confirm (which is still an ack).
    match tmo!(confirm).expect("confirm") {
        lp::Confirmation::Ack(Some(ret)) => {
            assert_eq!(ret.reply_code, 312);
            assert_eq!(ret.reply_text.as_str(), "NO_ROUTE");
            assert_eq!(ret.exchange.as_str(), "amq.direct");
            assert_eq!(ret.routing_key.as_str(), "nobody-bound-this-key");
            assert_eq!(ret.delivery.data, b"bounce");
            assert_eq!(
                ret.delivery
                    .properties
                    .message_id()
                    .as_ref()
                    .map(|s| s.as_str()),
                Some("m-1")
            );
        }
        other => panic!("expected an ack carrying the returned message, got {other:?}"),
    }
    // The channel is still open.
    assert!(ch.status().connected());
}

#[both_runtimes]
async fn mandatory_unroutable_message_comes_back_with_312_amqprs() {
    let b = broker().await;
    let (_conn, ch, mut ev) = rs::open(&b).await;
    let missing_queue = unique("no-such-queue");
    let mut props = rs::BasicProperties::default();
    props.with_correlation_id("c-9");
    let mut args = rs::BasicPublishArguments::new("", &missing_queue);
    args.mandatory = true;
    tmo!(ch.basic_publish(props, b"back".to_vec(), args)).expect("publish");
    match tmo!(ev.recv()) {
        Some(rs::Event::Return {
            code,
            text,
            exchange,
            routing_key,
            props,
            body,
        }) => {
            assert_eq!((code, text.as_str()), (312, "NO_ROUTE"));
            assert_eq!(exchange, "");
            assert_eq!(routing_key, missing_queue);
            assert_eq!(body, b"back");
            assert_eq!(props.correlation_id().map(|s| s.as_str()), Some("c-9"));
        }
        other => panic!("expected basic.return, got {other:?}"),
    }
}

#[both_runtimes]
async fn unroutable_message_without_mandatory_is_dropped_silently() {
    let b = broker().await;
    let conn = lp::connect(&b).await;
    let ch = confirm_channel(&conn).await;
    let c = lp::publish_confirmed(
        &ch,
        "amq.topic",
        "no.binding.here",
        b"lost",
        lp::BasicProperties::default(),
    )
    .await;
    assert_eq!(c, lp::Confirmation::Ack(None));
}

#[both_runtimes]
async fn mandatory_routed_message_is_not_returned() {
    let b = broker().await;
    let conn = lp::connect(&b).await;
    let ch = confirm_channel(&conn).await;
    let q = lp::queue(&ch, "mandatory-ok").await;
    let confirm = tmo!(ch.basic_publish(
        "",
        &q,
        lp::BasicPublishOptions {
            mandatory: true,
            ..Default::default()
        },
        b"delivered",
        lp::BasicProperties::default()
    ))
    .expect("publish");
    assert_eq!(tmo!(confirm).expect("confirm"), lp::Confirmation::Ack(None));
    assert_eq!(
        lp::get(&ch, &q, true).await.expect("m").delivery.data,
        b"delivered"
    );
}

#[both_runtimes]
async fn publishing_to_a_missing_exchange_gets_404_lapin() {
    let b = broker().await;
    let (conn, ch) = lp::open(&b).await;
    let mut errors = lp::watch_errors(&ch);
    let _ = tmo!(ch.basic_publish(
        &unique("no-such-exchange"),
        "k",
        lp::BasicPublishOptions::default(),
        b"x",
        lp::BasicProperties::default()
    ));
    let err = tmo!(errors.recv()).expect("channel closed");
    let (code, text) = lp::code(&err);
    // RabbitMQ: "NOT_FOUND - no exchange '...' in vhost '/'".
    assert_eq!(code, 404, "{text}");
    assert_text_prefix(&text, "NOT_FOUND");
    assert!(conn.status().connected());
}

#[both_runtimes]
async fn publishing_to_a_missing_exchange_gets_404_amqprs() {
    let b = broker().await;
    let (conn, ch, mut ev) = rs::open(&b).await;
    rs::publish(&ch, &unique("no-such-exchange"), "k", b"x").await;
    rs::assert_closed(&mut ev, 404, "NOT_FOUND").await;
    assert!(conn.is_open());
}

#[both_runtimes]
async fn publishing_with_immediate_is_a_540_connection_error() {
    let b = broker().await;
    let (conn, mut conn_ev) = rs::connect(&b).await;
    let (ch, _) = rs::channel(&conn).await;
    let q = rs::queue(&ch, "immediate").await;
    let mut args = rs::BasicPublishArguments::new("", &q);
    args.immediate = true;
    let _ = tmo!(ch.basic_publish(rs::BasicProperties::default(), b"now".to_vec(), args));
    // Note: RabbitMQ 3.x does not implement immediate: "NOT_IMPLEMENTED -
    // immediate=true", closing the whole connection.
    let rs::ConnClose { code, text, .. } = tmo!(conn_ev.recv()).expect("connection.close");
    assert_eq!(code, 540, "{text}");
    assert_text_prefix(&text, "NOT_IMPLEMENTED");
}

#[both_runtimes]
async fn basic_get_reports_remaining_count_and_get_empty() {
    let b = broker().await;
    let (_conn, ch, _ev) = rs::open(&b).await;
    let q = rs::queue(&ch, "get").await;
    assert!(rs::get(&ch, &q, false).await.is_none(), "get-empty");
    for i in 0..3 {
        rs::publish(&ch, "", &q, format!("{i}").as_bytes()).await;
    }
    let mut args = rs::BasicGetArguments::new(&q);
    args.no_ack = false;
    let (ok, _props, body) = tmo!(ch.basic_get(args)).expect("get").expect("get-ok");
    assert_eq!(body, b"0");
    assert_eq!(ok.delivery_tag(), 1);
    assert!(!ok.redelivered());
    assert_eq!(ok.exchange(), "");
    assert_eq!(ok.routing_key(), &q);
    assert_eq!(ok.message_count(), 2);
    rs::ack(&ch, 1).await;
    let (tag, _, count, body) = rs::get(&ch, &q, true).await.expect("second");
    assert_eq!((tag, count, body.as_slice()), (2, 1, &b"1"[..]));
    let (tag, _, count, body) = rs::get(&ch, &q, true).await.expect("third");
    assert_eq!((tag, count, body.as_slice()), (3, 0, &b"2"[..]));
    assert!(rs::get(&ch, &q, true).await.is_none(), "get-empty again");
}

#[both_runtimes]
async fn basic_get_from_a_missing_queue_gets_404() {
    let b = broker().await;
    let (_conn, ch) = lp::open(&b).await;
    let res = tmo!(ch.basic_get(&unique("no-such-queue"), lp::BasicGetOptions::default()));
    lp::assert_err(res, 404, "NOT_FOUND");
}

fn pattern(len: usize) -> Vec<u8> {
    (0..len).map(|i| (i * 31 % 251) as u8).collect()
}

#[both_runtimes]
async fn one_mebibyte_message_round_trips_lapin() {
    let b = broker().await;
    let (_conn, ch) = lp::open(&b).await;
    let q = lp::queue(&ch, "large").await;
    // Larger than frame_max (128 KiB): split across several body frames.
    let body = pattern(1024 * 1024 + 17);
    lp::publish(&ch, "", &q, &body).await;
    let mut c = lp::consume(&ch, &q, "").await;
    let d = lp::next(&mut c).await;
    assert_eq!(d.data.len(), body.len());
    assert!(d.data == body, "body differs");
}

#[both_runtimes]
async fn large_message_round_trips_amqprs() {
    let b = broker().await;
    let (_conn, ch, _ev) = rs::open(&b).await;
    let q = rs::queue(&ch, "large-rs").await;
    let body = pattern(3 * 131_072 + 5);
    rs::publish(&ch, "", &q, &body).await;
    let (_, _, _, got) = rs::get(&ch, &q, true).await.expect("message");
    assert_eq!(got.len(), body.len());
    assert!(got == body, "body differs");
}

#[both_runtimes]
async fn empty_body_round_trips() {
    let b = broker().await;
    let (_conn, ch, _ev) = rs::open(&b).await;
    let q = rs::queue(&ch, "empty").await;
    let mut props = rs::BasicProperties::default();
    props.with_content_type("application/x-empty");
    rs::publish_props(&ch, "", &q, b"", props.clone()).await;
    rs::publish_props(&ch, "", &q, b"", props).await;
    // One at a time, so the second one is left for basic.get.
    tmo!(ch.basic_qos(rs::BasicQosArguments::new(0, 1, false))).expect("qos");
    let (_, mut rx) = rs::consume(&ch, &q, "", false).await;
    let m = rs::next(&mut rx).await;
    assert!(m.body.is_empty());
    assert_eq!(
        m.props.content_type().map(|s| s.as_str()),
        Some("application/x-empty")
    );
    tmo!(ch.basic_cancel(rs::BasicCancelArguments::new(&m.consumer_tag))).expect("cancel");
    rs::ack(&ch, m.tag).await;
    // And through basic.get.
    let (_, _, _, body) = rs::get(&ch, &q, true).await.expect("second");
    assert!(body.is_empty());
}

#[both_runtimes]
async fn every_basic_property_round_trips_unchanged() {
    let b = broker().await;
    let (_conn, ch) = lp::open(&b).await;
    let q = lp::queue(&ch, "props").await;
    let headers = lp::table(vec![("h", lp::lstr("v"))]);
    let props = lp::BasicProperties::default()
        .with_content_type("text/plain".into())
        .with_content_encoding("gzip".into())
        .with_headers(headers.clone())
        .with_delivery_mode(2)
        .with_priority(7)
        .with_correlation_id("corr-1".into())
        .with_reply_to("reply-queue".into())
        .with_expiration("600000".into())
        .with_message_id("msg-1".into())
        .with_timestamp(1_700_000_000)
        .with_type("kind-a".into())
        // user-id must be the authenticated user (see the next test).
        .with_user_id("guest".into())
        .with_app_id("leveret-tests".into())
        .with_cluster_id("cluster-x".into());
    lp::publish_props(&ch, "", &q, b"with properties", props.clone()).await;
    let mut c = lp::consume(&ch, &q, "").await;
    let d = lp::next(&mut c).await;
    assert_eq!(d.properties, props);
    assert_eq!(d.data, b"with properties");
    // Unset properties stay unset.
    lp::publish(&ch, "", &q, b"bare").await;
    let d = lp::next(&mut c).await;
    assert_eq!(d.properties, lp::BasicProperties::default());
}

#[both_runtimes]
async fn user_id_must_match_the_authenticated_user() {
    let b = broker().await;
    let (_conn, ch, mut ev) = rs::open(&b).await;
    let q = rs::queue(&ch, "user-id").await;
    let mut props = rs::BasicProperties::default();
    props.with_user_id("someone-else");
    rs::publish_props(&ch, "", &q, b"impostor", props).await;
    // RabbitMQ: "PRECONDITION_FAILED - user_id property set to
    // 'someone-else' but authenticated user was 'guest'".
    rs::assert_closed(&mut ev, 406, "PRECONDITION_FAILED").await;
}

fn every_header_type() -> lp::FieldTable {
    let mut nested = lp::FieldTable::default();
    nested.insert("inner".into(), AMQPValue::LongString("deep".into()));
    nested.insert("n".into(), AMQPValue::LongInt(-5));
    let array = FieldArray::from(vec![
        AMQPValue::LongInt(1),
        AMQPValue::LongString("two".into()),
        AMQPValue::Boolean(false),
        AMQPValue::FieldArray(FieldArray::from(vec![AMQPValue::Double(3.5)])),
    ]);
    lp::table(vec![
        ("bool-true", AMQPValue::Boolean(true)),
        ("bool-false", AMQPValue::Boolean(false)),
        ("i8", AMQPValue::ShortShortInt(-8)),
        ("u8", AMQPValue::ShortShortUInt(200)),
        ("i16", AMQPValue::ShortInt(-1600)),
        ("u16", AMQPValue::ShortUInt(60_000)),
        ("i32", AMQPValue::LongInt(-320_000)),
        ("u32", AMQPValue::LongUInt(4_000_000_000)),
        ("i64", AMQPValue::LongLongInt(-6_400_000_000_000)),
        ("f32", AMQPValue::Float(1.5)),
        ("f64", AMQPValue::Double(-2.25e100)),
        (
            "decimal",
            AMQPValue::DecimalValue(DecimalValue {
                scale: 2,
                value: 12345,
            }),
        ),
        ("string", AMQPValue::LongString("héllo wörld".into())),
        ("empty-string", AMQPValue::LongString("".into())),
        (
            "bytes",
            AMQPValue::ByteArray(ByteArray::from(vec![0u8, 1, 2, 255])),
        ),
        ("array", AMQPValue::FieldArray(array)),
        ("empty-array", AMQPValue::FieldArray(FieldArray::default())),
        ("timestamp", AMQPValue::Timestamp(1_234_567_890)),
        ("table", AMQPValue::FieldTable(nested)),
        (
            "empty-table",
            AMQPValue::FieldTable(lp::FieldTable::default()),
        ),
        ("void", AMQPValue::Void),
    ])
}

#[both_runtimes]
async fn headers_of_every_value_type_round_trip_lapin() {
    let b = broker().await;
    let (_conn, ch) = lp::open(&b).await;
    let q = lp::queue(&ch, "header-types").await;
    let headers = every_header_type();
    let props = lp::BasicProperties::default().with_headers(headers.clone());
    lp::publish_props(&ch, "", &q, b"typed", props).await;
    let got = lp::get(&ch, &q, true).await.expect("message");
    let got_headers = got
        .delivery
        .properties
        .headers()
        .clone()
        .expect("headers present");
    for (k, v) in headers.inner() {
        assert_eq!(got_headers.inner().get(k), Some(v), "header {k:?}");
    }
    assert_eq!(got_headers, headers);
}

#[both_runtimes]
async fn headers_of_every_value_type_round_trip_amqprs() {
    let b = broker().await;
    let (_conn, ch, _ev) = rs::open(&b).await;
    let q = rs::queue(&ch, "header-types-rs").await;
    let mut nested = rs::FieldTable::new();
    nested.insert("k".try_into().unwrap(), rs::lstr("v"));
    let headers = rs::table(vec![
        ("t", rs::FieldValue::t(true)),
        ("b", rs::FieldValue::b(-3)),
        ("B", rs::FieldValue::B(250)),
        ("s", rs::FieldValue::s(-300)),
        ("u", rs::FieldValue::u(65_000)),
        ("I", rs::FieldValue::I(-70_000)),
        ("i", rs::FieldValue::i(3_000_000_000)),
        ("l", rs::FieldValue::l(i64::MIN)),
        ("f", rs::FieldValue::f(0.25)),
        ("d", rs::FieldValue::d(1e-300)),
        ("S", rs::lstr("text")),
        ("T", rs::FieldValue::T(42)),
        ("F", rs::FieldValue::F(nested)),
        ("V", rs::FieldValue::V),
    ]);
    let mut props = rs::BasicProperties::default();
    props.with_headers(headers.clone());
    rs::publish_props(&ch, "", &q, b"typed", props).await;
    let (_, mut rx) = rs::consume(&ch, &q, "", true).await;
    let m = rs::next(&mut rx).await;
    assert_eq!(m.props.headers(), Some(&headers));
}

#[both_runtimes]
async fn messages_keep_their_order() {
    let b = broker().await;
    let (_conn, ch) = lp::open(&b).await;
    let q = lp::queue(&ch, "order").await;
    for i in 0..1000 {
        lp::publish(&ch, "", &q, format!("{i}").as_bytes()).await;
    }
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
    for i in 0..1000u64 {
        let d = lp::next(&mut c).await;
        assert_eq!(lp::text(&d), format!("{i}"));
        assert_eq!(d.delivery_tag, i + 1);
    }
}

#[both_runtimes]
async fn publisher_confirms_ack_every_publish_lapin() {
    let b = broker().await;
    let conn = lp::connect(&b).await;
    let ch = confirm_channel(&conn).await;
    let q = lp::queue(&ch, "confirms").await;
    let mut pending = Vec::new();
    for i in 0..200 {
        pending.push(
            tmo!(ch.basic_publish(
                "",
                &q,
                lp::BasicPublishOptions::default(),
                format!("{i}").as_bytes(),
                lp::BasicProperties::default()
            ))
            .expect("publish"),
        );
    }
    for p in pending {
        assert_eq!(tmo!(p).expect("confirm"), lp::Confirmation::Ack(None));
    }
    // Unroutable publishes are confirmed too.
    let c = lp::publish_confirmed(
        &ch,
        "amq.direct",
        "nowhere",
        b"x",
        lp::BasicProperties::default(),
    )
    .await;
    assert!(c.is_ack());
    let info = tmo!(ch.queue_declare(
        &q,
        lp::QueueDeclareOptions {
            passive: true,
            ..Default::default()
        },
        lp::FieldTable::default()
    ))
    .expect("passive");
    assert_eq!(info.message_count(), 200);
}

#[both_runtimes]
async fn publisher_confirms_cover_every_sequence_number_amqprs() {
    let b = broker().await;
    let (_conn, ch, mut ev) = rs::open(&b).await;
    rs::confirm_select(&ch).await;
    let q = rs::queue(&ch, "confirms-rs").await;
    let n = 50u64;
    for i in 0..n {
        rs::publish(&ch, "", &q, format!("{i}").as_bytes()).await;
    }
    // Acks may be single or multiple, but together they must cover 1..=n
    // exactly once, in increasing order.
    let mut covered = 0u64;
    while covered < n {
        match tmo!(ev.recv()) {
            Some(rs::Event::Ack { tag, multiple }) => {
                assert!(tag > covered, "ack {tag} after {covered}");
                if !multiple {
                    assert_eq!(tag, covered + 1, "single ack skips a sequence number");
                }
                covered = tag;
            }
            other => panic!("expected basic.ack, got {other:?}"),
        }
    }
    assert_eq!(covered, n);
    assert_eq!(rs::counts(&ch, &q).await, (n as u32, 0));
}

#[both_runtimes]
async fn confirm_and_tx_modes_exclude_each_other() {
    let b = broker().await;
    let (conn, _) = rs::connect(&b).await;
    let (ch, mut ev) = rs::channel(&conn).await;
    tmo!(ch.tx_select()).expect("tx.select");
    assert!(tmo!(ch.confirm_select(rs::ConfirmSelectArguments::default())).is_err());
    // RabbitMQ: "PRECONDITION_FAILED - cannot switch from tx to confirm mode".
    rs::assert_closed(&mut ev, 406, "PRECONDITION_FAILED").await;
    let (ch, mut ev) = rs::channel(&conn).await;
    rs::confirm_select(&ch).await;
    assert!(tmo!(ch.tx_select()).is_err());
    // RabbitMQ: "PRECONDITION_FAILED - cannot switch from confirm to tx mode".
    rs::assert_closed(&mut ev, 406, "PRECONDITION_FAILED").await;
}

#[both_runtimes]
async fn tx_commit_publishes_and_rollback_discards() {
    let b = broker().await;
    let (conn, _) = rs::connect(&b).await;
    let (ch, _) = rs::channel(&conn).await;
    let q = rs::queue(&ch, "tx").await;
    let (tx, _) = rs::channel(&conn).await;
    tmo!(tx.tx_select()).expect("tx.select");
    rs::publish(&tx, "", &q, b"rolled-back-1").await;
    rs::publish(&tx, "", &q, b"rolled-back-2").await;
    tmo!(tx.tx_rollback()).expect("tx.rollback");
    rs::publish(&tx, "", &q, b"committed-1").await;
    rs::publish(&tx, "", &q, b"committed-2").await;
    // Nothing is visible before the commit.
    assert!(rs::get(&ch, &q, true).await.is_none());
    tmo!(tx.tx_commit()).expect("tx.commit");
    let (_, _, _, first) = rs::get(&ch, &q, true).await.expect("first");
    let (_, _, _, second) = rs::get(&ch, &q, true).await.expect("second");
    assert_eq!(
        (first.as_slice(), second.as_slice()),
        (&b"committed-1"[..], &b"committed-2"[..])
    );
    assert!(
        rs::get(&ch, &q, true).await.is_none(),
        "rolled-back publishes never arrive"
    );
    // The channel stays transactional after commit: the next publish
    // waits for the next commit.
    rs::publish(&tx, "", &q, b"next").await;
    assert!(rs::get(&ch, &q, true).await.is_none());
    tmo!(tx.tx_commit()).expect("tx.commit");
    assert!(rs::get(&ch, &q, true).await.is_some());
}

#[both_runtimes]
async fn tx_rolled_back_publishes_never_arrive_at_a_consumer() {
    let b = broker().await;
    let conn = lp::connect(&b).await;
    let ch = lp::channel(&conn).await;
    let q = lp::queue(&ch, "tx-consumer").await;
    let mut c = lp::consume(&ch, &q, "").await;
    let tx = lp::channel(&conn).await;
    tmo!(tx.tx_select()).expect("tx.select");
    for i in 0..5 {
        lp::publish(&tx, "", &q, format!("nope{i}").as_bytes()).await;
    }
    tmo!(tx.tx_rollback()).expect("rollback");
    lp::publish(&tx, "", &q, b"yes").await;
    tmo!(tx.tx_commit()).expect("commit");
    let d = lp::next(&mut c).await;
    assert_eq!(lp::text(&d), "yes");
    lp::nothing(&mut c).await;
}

#[both_runtimes]
async fn tx_acks_take_effect_on_commit_only() {
    let b = broker().await;
    let conn = lp::connect(&b).await;
    let ch = lp::channel(&conn).await;
    let q = lp::queue(&ch, "tx-acks").await;
    lp::publish(&ch, "", &q, b"a").await;
    lp::publish(&ch, "", &q, b"b").await;
    let tx = lp::channel(&conn).await;
    tmo!(tx.tx_select()).expect("tx.select");
    let a = lp::get(&tx, &q, false).await.expect("a");
    let b2 = lp::get(&tx, &q, false).await.expect("b");
    lp::ack(&tx, a.delivery.delivery_tag).await;
    lp::ack(&tx, b2.delivery.delivery_tag).await;
    tmo!(tx.tx_rollback()).expect("rollback");
    // The rolled-back acks are forgotten, so the messages are still
    // unacked; ack "a" for real.
    lp::ack(&tx, a.delivery.delivery_tag).await;
    tmo!(tx.tx_commit()).expect("commit");
    tmo!(tx.close(200, "bye")).expect("close");
    // Closing the channel requeues only "b".
    let got = lp::get(&ch, &q, true).await.expect("b requeued");
    assert_eq!(got.delivery.data, b"b");
    assert!(got.delivery.redelivered);
    assert!(lp::get(&ch, &q, true).await.is_none());
}

#[both_runtimes]
async fn tx_commit_without_select_gets_406() {
    let b = broker().await;
    let (conn, _) = rs::connect(&b).await;
    let (ch, mut ev) = rs::channel(&conn).await;
    assert!(tmo!(ch.tx_commit()).is_err());
    // RabbitMQ: "PRECONDITION_FAILED - channel is not transactional".
    rs::assert_closed(&mut ev, 406, "PRECONDITION_FAILED").await;
    let (ch, mut ev) = rs::channel(&conn).await;
    assert!(tmo!(ch.tx_rollback()).is_err());
    rs::assert_closed(&mut ev, 406, "PRECONDITION_FAILED").await;
}
