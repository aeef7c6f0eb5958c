//! Exchange types and routing (direct, fanout, topic, headers, the default
//! exchange, the predefined amq.* ones), exchange declare/delete rules,
//! exchange-to-exchange bindings and alternate exchanges.

#[macro_use]
mod common;

use std::collections::BTreeSet;

use common::lp::AMQPValue;
use common::*;

/// Deletes fanout exchange `x` and declares it again under its name.
async fn delete_and_declare_fanout_again(ch: &lp::Channel, x: &str) {
    tmo!(ch.exchange_delete(x, lp::ExchangeDeleteOptions::default())).expect("delete");
    tmo!(ch.exchange_declare(
        x,
        lp::ExchangeKind::Fanout,
        lp::ExchangeDeclareOptions::default(),
        lp::FieldTable::default()
    ))
    .expect("declare again");
}

/// A lapin channel in confirm mode: every publish is confirmed before the
/// test looks at queues, so routing has certainly happened.
async fn confirm_channel(conn: &lp::Connection) -> lp::Channel {
    let ch = lp::channel(conn).await;
    tmo!(ch.confirm_select(lp::ConfirmSelectOptions::default())).expect("confirm.select");
    ch
}

/// Publishes with confirmation and asserts a plain ack.
async fn publish_acked(ch: &lp::Channel, exchange: &str, key: &str, body: &[u8]) {
    publish_acked_props(ch, exchange, key, body, lp::BasicProperties::default()).await
}

async fn publish_acked_props(
    ch: &lp::Channel,
    exchange: &str,
    key: &str,
    body: &[u8],
    props: lp::BasicProperties,
) {
    let c = lp::publish_confirmed(ch, exchange, key, body, props).await;
    assert!(
        c.is_ack(),
        "publish to {exchange:?}/{key:?} confirmed: {c:?}"
    );
}

/// Drains a queue with basic.get (no-ack) and returns the bodies in order.
async fn drain(ch: &lp::Channel, queue: &str) -> Vec<String> {
    let mut out = Vec::new();
    while let Some(m) = lp::get(ch, queue, true).await {
        out.push(String::from_utf8(m.delivery.data).expect("utf-8"));
    }
    out
}

async fn drain_rs(ch: &rs::Channel, queue: &str) -> Vec<String> {
    let mut out = Vec::new();
    while let Some((_, _, _, body)) = rs::get(ch, queue, true).await {
        out.push(String::from_utf8(body).expect("utf-8"));
    }
    out
}

fn passive() -> lp::ExchangeDeclareOptions {
    lp::ExchangeDeclareOptions {
        passive: true,
        ..Default::default()
    }
}

#[both_runtimes]
async fn direct_exchange_routes_on_the_exact_key() {
    let b = broker().await;
    let conn = lp::connect(&b).await;
    let ch = confirm_channel(&conn).await;
    let x = lp::exchange(&ch, "direct", lp::ExchangeKind::Direct).await;
    let qa = lp::queue(&ch, "qa").await;
    let qb = lp::queue(&ch, "qb").await;
    let both = lp::queue(&ch, "both").await;
    lp::bind(&ch, &qa, &x, "a").await;
    lp::bind(&ch, &qb, &x, "b").await;
    lp::bind(&ch, &both, &x, "a").await;
    lp::bind(&ch, &both, &x, "b").await;
    for key in ["a", "b", "c", "A", "a.b", ""] {
        publish_acked(&ch, &x, key, key.as_bytes()).await;
    }
    assert_eq!(drain(&ch, &qa).await, ["a"]);
    assert_eq!(drain(&ch, &qb).await, ["b"]);
    assert_eq!(drain(&ch, &both).await, ["a", "b"]);
}

#[both_runtimes]
async fn a_message_matching_two_bindings_of_one_queue_arrives_once() {
    let b = broker().await;
    let conn = lp::connect(&b).await;
    let ch = confirm_channel(&conn).await;
    let x = lp::exchange(&ch, "topic-twice", lp::ExchangeKind::Topic).await;
    let q = lp::queue(&ch, "twice").await;
    lp::bind(&ch, &q, &x, "a.*").await;
    lp::bind(&ch, &q, &x, "#").await;
    lp::bind(&ch, &q, &x, "a.b").await;
    publish_acked(&ch, &x, "a.b", b"once").await;
    assert_eq!(drain(&ch, &q).await, ["once"]);
}

#[both_runtimes]
async fn fanout_exchange_copies_to_every_bound_queue_whatever_the_key() {
    let b = broker().await;
    let (_conn, ch, _ev) = rs::open(&b).await;
    let x = rs::exchange(&ch, "fanout", rs::ExchangeType::Fanout).await;
    let mut queues = Vec::new();
    for i in 0..3 {
        let q = rs::queue(&ch, "fan").await;
        // The binding key is ignored by fanout.
        rs::bind(&ch, &q, &x, &format!("ignored-{i}")).await;
        queues.push(q);
    }
    for key in ["", "x", "anything.at.all"] {
        rs::publish(&ch, &x, key, key.as_bytes()).await;
    }
    for q in &queues {
        assert_eq!(drain_rs(&ch, q).await, ["", "x", "anything.at.all"]);
    }
}

#[both_runtimes]
async fn topic_exchange_wildcards_and_empty_words() {
    let b = broker().await;
    let conn = lp::connect(&b).await;
    let ch = confirm_channel(&conn).await;
    let x = lp::exchange(&ch, "topic", lp::ExchangeKind::Topic).await;
    let keys = ["a.b.c", "a.c", "a", "", "a..c", "a.b.b.c", "b.c", ".", "a."];
    // (pattern, keys it matches), as RabbitMQ routes them. Words are split
    // on '.', so "." is two empty words and "a." is "a" plus an empty word,
    // and "*" matches an empty word. Note: the empty key "" has no words
    // at all: "*" does not match it, while "#" and the empty pattern do.
    let table: [(&str, &[&str]); 11] = [
        ("a.*.c", &["a.b.c", "a..c"]),
        ("a.#", &["a.b.c", "a.c", "a", "a..c", "a.b.b.c", "a."]),
        ("#", &keys),
        ("*", &["a"]),
        ("#.c", &["a.b.c", "a.c", "a..c", "a.b.b.c", "b.c"]),
        ("a.#.c", &["a.b.c", "a.c", "a..c", "a.b.b.c"]),
        ("a..c", &["a..c"]),
        ("", &[""]),
        ("*.*", &["a.c", "b.c", ".", "a."]),
        ("a.*", &["a.c", "a."]),
        ("#.#", &keys),
    ];
    let mut queues = Vec::new();
    for (pattern, _) in &table {
        let q = lp::queue(&ch, "topic-q").await;
        lp::bind(&ch, &q, &x, pattern).await;
        queues.push(q);
    }
    for key in keys {
        publish_acked(&ch, &x, key, key.as_bytes()).await;
    }
    let mut wrong = Vec::new();
    for ((pattern, expected), q) in table.iter().zip(&queues) {
        let got: BTreeSet<String> = drain(&ch, q).await.into_iter().collect();
        let want: BTreeSet<String> = expected.iter().map(|s| s.to_string()).collect();
        if got != want {
            wrong.push(format!("pattern {pattern:?}: got {got:?}, want {want:?}"));
        }
    }
    assert!(
        wrong.is_empty(),
        "topic routing differs:\n{}",
        wrong.join("\n")
    );
}

#[both_runtimes]
async fn headers_exchange_x_match_all_and_any() {
    let b = broker().await;
    let conn = lp::connect(&b).await;
    let ch = confirm_channel(&conn).await;
    let x = lp::exchange(&ch, "headers", lp::ExchangeKind::Headers).await;
    let all = lp::queue(&ch, "h-all").await;
    let any = lp::queue(&ch, "h-any").await;
    let default = lp::queue(&ch, "h-default").await;
    let everything = lp::queue(&ch, "h-everything").await;
    lp::bind_args(
        &ch,
        &all,
        &x,
        "ignored",
        lp::table(vec![
            ("x-match", lp::lstr("all")),
            ("format", lp::lstr("pdf")),
            ("type", lp::lstr("report")),
        ]),
    )
    .await;
    lp::bind_args(
        &ch,
        &any,
        &x,
        "",
        lp::table(vec![
            ("x-match", lp::lstr("any")),
            ("format", lp::lstr("pdf")),
            ("type", lp::lstr("log")),
        ]),
    )
    .await;
    // No x-match: "all" is the default.
    lp::bind_args(
        &ch,
        &default,
        &x,
        "",
        lp::table(vec![
            ("format", lp::lstr("pdf")),
            ("size", AMQPValue::LongInt(42)),
        ]),
    )
    .await;
    // Only x-match=all, nothing to compare: every message matches.
    lp::bind_args(
        &ch,
        &everything,
        &x,
        "",
        lp::table(vec![("x-match", lp::lstr("all"))]),
    )
    .await;
    let messages: Vec<(&str, Vec<(&str, AMQPValue)>)> = vec![
        (
            "pdf-report",
            vec![("format", lp::lstr("pdf")), ("type", lp::lstr("report"))],
        ),
        ("pdf-only", vec![("format", lp::lstr("pdf"))]),
        ("log-only", vec![("type", lp::lstr("log"))]),
        (
            "zip-report",
            vec![("format", lp::lstr("zip")), ("type", lp::lstr("report"))],
        ),
        (
            "pdf-42",
            vec![
                ("format", lp::lstr("pdf")),
                ("size", AMQPValue::LongInt(42)),
                ("extra", lp::lstr("more")),
            ],
        ),
        ("no-headers", vec![]),
    ];
    for (name, headers) in messages {
        let props = if headers.is_empty() {
            lp::BasicProperties::default()
        } else {
            lp::BasicProperties::default().with_headers(lp::table(headers))
        };
        // The routing key plays no part.
        publish_acked_props(&ch, &x, "some.key", name.as_bytes(), props).await;
    }
    assert_eq!(drain(&ch, &all).await, ["pdf-report"]);
    assert_eq!(
        drain(&ch, &any).await,
        ["pdf-report", "pdf-only", "log-only", "pdf-42"]
    );
    assert_eq!(drain(&ch, &default).await, ["pdf-42"]);
    assert_eq!(
        drain(&ch, &everything).await,
        [
            "pdf-report",
            "pdf-only",
            "log-only",
            "zip-report",
            "pdf-42",
            "no-headers"
        ]
    );
}

#[both_runtimes]
async fn default_exchange_routes_to_the_queue_named_by_the_key() {
    let b = broker().await;
    let (_conn, ch, _ev) = rs::open(&b).await;
    let q1 = rs::queue(&ch, "default-1").await;
    let q2 = rs::queue(&ch, "default-2").await;
    rs::publish(&ch, "", &q1, b"one").await;
    rs::publish(&ch, "", &q2, b"two").await;
    rs::publish(&ch, "", &unique("nobody"), b"lost").await;
    assert_eq!(drain_rs(&ch, &q1).await, ["one"]);
    assert_eq!(drain_rs(&ch, &q2).await, ["two"]);
}

#[both_runtimes]
async fn binding_to_the_default_exchange_is_refused_with_403() {
    let b = broker().await;
    let (conn, _) = rs::connect(&b).await;
    let (ch, mut ev) = rs::channel(&conn).await;
    let q = rs::queue(&ch, "default-bind").await;
    assert!(tmo!(ch.queue_bind(rs::QueueBindArguments::new(&q, "", "other"))).is_err());
    // RabbitMQ: "ACCESS_REFUSED - operation not permitted on the default exchange".
    rs::assert_closed(&mut ev, 403, "ACCESS_REFUSED").await;
    let (ch, mut ev) = rs::channel(&conn).await;
    assert!(tmo!(ch.queue_unbind(rs::QueueUnbindArguments::new(&q, "", &q))).is_err());
    rs::assert_closed(&mut ev, 403, "ACCESS_REFUSED").await;
}

#[both_runtimes]
async fn deleting_or_declaring_the_default_exchange_is_refused_with_403() {
    let b = broker().await;
    let conn = lp::connect(&b).await;
    let ch = lp::channel(&conn).await;
    let res = tmo!(ch.exchange_delete("", lp::ExchangeDeleteOptions::default()));
    lp::assert_err(res, 403, "ACCESS_REFUSED");
    // Note: even a passive declare of the default exchange is refused:
    // "ACCESS_REFUSED - operation not permitted on the default exchange".
    let ch = lp::channel(&conn).await;
    let res = tmo!(ch.exchange_declare(
        "",
        lp::ExchangeKind::Direct,
        passive(),
        lp::FieldTable::default()
    ));
    lp::assert_err(res, 403, "ACCESS_REFUSED");
    let ch = lp::channel(&conn).await;
    let res = tmo!(ch.exchange_declare(
        "",
        lp::ExchangeKind::Direct,
        lp::ExchangeDeclareOptions::default(),
        lp::FieldTable::default()
    ));
    lp::assert_err(res, 403, "ACCESS_REFUSED");
}

#[both_runtimes]
async fn predefined_amq_exchanges_exist_with_their_types() {
    let b = broker().await;
    let (_conn, ch, _ev) = rs::open(&b).await;
    for (name, kind) in [
        ("amq.direct", "direct"),
        ("amq.fanout", "fanout"),
        ("amq.topic", "topic"),
        ("amq.headers", "headers"),
        ("amq.match", "headers"),
    ] {
        let mut args = rs::ExchangeDeclareArguments::new(name, kind);
        args.passive = true;
        tmo!(ch.exchange_declare(args)).unwrap_or_else(|e| panic!("passive declare {name}: {e}"));
    }
    // They route like any exchange of their type.
    let q = rs::queue(&ch, "amq-routing").await;
    rs::bind(&ch, &q, "amq.direct", "k").await;
    rs::bind(&ch, &q, "amq.topic", "t.#").await;
    rs::bind(&ch, &q, "amq.fanout", "").await;
    rs::publish(&ch, "amq.direct", "k", b"direct").await;
    rs::publish(&ch, "amq.topic", "t.x.y", b"topic").await;
    rs::publish(&ch, "amq.fanout", "whatever", b"fanout").await;
    assert_eq!(drain_rs(&ch, &q).await, ["direct", "topic", "fanout"]);
    for x in ["amq.direct", "amq.topic", "amq.fanout"] {
        let key = match x {
            "amq.direct" => "k",
            "amq.topic" => "t.#",
            _ => "",
        };
        tmo!(ch.queue_unbind(rs::QueueUnbindArguments::new(&q, x, key))).expect("unbind");
    }
}

#[both_runtimes]
async fn declaring_an_amq_prefixed_exchange_is_refused_with_403() {
    let b = broker().await;
    let (conn, _) = rs::connect(&b).await;
    let (ch, mut ev) = rs::channel(&conn).await;
    let name = unique("amq.foo");
    assert!(tmo!(ch.exchange_declare(rs::ExchangeDeclareArguments::new(&name, "direct"))).is_err());
    // RabbitMQ: "ACCESS_REFUSED - exchange name 'amq.foo...' contains reserved prefix 'amq.*'".
    rs::assert_closed(&mut ev, 403, "ACCESS_REFUSED").await;
    // Note: re-declaring an existing amq.* exchange identically (durable
    // direct) is accepted; with another type it is the usual 406.
    let (ch, mut ev) = rs::channel(&conn).await;
    let mut args = rs::ExchangeDeclareArguments::new("amq.direct", "direct");
    args.durable = true;
    tmo!(ch.exchange_declare(args)).expect("identical redeclare of amq.direct");
    let mut args = rs::ExchangeDeclareArguments::new("amq.direct", "fanout");
    args.durable = true;
    assert!(tmo!(ch.exchange_declare(args)).is_err());
    rs::assert_closed(&mut ev, 406, "PRECONDITION_FAILED").await;
}

#[both_runtimes]
async fn unknown_exchange_type_is_a_503_connection_error() {
    let b = broker().await;
    let (conn, mut conn_ev) = rs::connect(&b).await;
    let (ch, _) = rs::channel(&conn).await;
    let name = unique("typo");
    let _ = tmo!(ch.exchange_declare(rs::ExchangeDeclareArguments::new(&name, "no-such-type")));
    // Note: the whole connection is closed: RabbitMQ says "COMMAND_INVALID
    // - unknown exchange type 'no-such-type'".
    let rs::ConnClose { code, text, .. } = tmo!(conn_ev.recv()).expect("connection.close");
    assert_eq!(code, 503, "{text}");
    assert_text_prefix(&text, "COMMAND_INVALID");
}

#[both_runtimes]
async fn passive_declare_of_a_missing_exchange_gets_404() {
    let b = broker().await;
    let (_conn, ch) = lp::open(&b).await;
    let res = tmo!(ch.exchange_declare(
        &unique("missing-x"),
        lp::ExchangeKind::Direct,
        passive(),
        lp::FieldTable::default()
    ));
    // RabbitMQ: "NOT_FOUND - no exchange '...' in vhost '/'".
    lp::assert_err(res, 404, "NOT_FOUND");
}

#[both_runtimes]
async fn redeclaring_an_exchange_differently_gets_406() {
    let b = broker().await;
    let conn = lp::connect(&b).await;
    let ch = lp::channel(&conn).await;
    let x = lp::exchange(&ch, "redeclare", lp::ExchangeKind::Direct).await;
    // Same everything: fine.
    tmo!(ch.exchange_declare(
        &x,
        lp::ExchangeKind::Direct,
        lp::ExchangeDeclareOptions::default(),
        lp::FieldTable::default()
    ))
    .expect("identical redeclare");
    // A passive declare does not compare the type.
    tmo!(ch.exchange_declare(
        &x,
        lp::ExchangeKind::Fanout,
        passive(),
        lp::FieldTable::default()
    ))
    .expect("passive declare ignores the type");
    // Different type: "PRECONDITION_FAILED - inequivalent arg 'type' for exchange ...".
    let res = tmo!(ch.exchange_declare(
        &x,
        lp::ExchangeKind::Fanout,
        lp::ExchangeDeclareOptions::default(),
        lp::FieldTable::default()
    ));
    lp::assert_err(res, 406, "PRECONDITION_FAILED");
    // Different durability.
    let ch = lp::channel(&conn).await;
    let res = tmo!(ch.exchange_declare(
        &x,
        lp::ExchangeKind::Direct,
        lp::ExchangeDeclareOptions {
            durable: true,
            ..Default::default()
        },
        lp::FieldTable::default()
    ));
    lp::assert_err(res, 406, "PRECONDITION_FAILED");
    let ch = lp::channel(&conn).await;
    tmo!(ch.exchange_delete(&x, lp::ExchangeDeleteOptions::default())).expect("delete");
}

#[both_runtimes]
async fn durable_exchange_declare_and_delete() {
    let b = broker().await;
    let (_conn, ch, _ev) = rs::open(&b).await;
    let name = unique("durable-x");
    let mut args = rs::ExchangeDeclareArguments::new(&name, "topic");
    args.durable = true;
    tmo!(ch.exchange_declare(args.clone())).expect("declare durable");
    tmo!(ch.exchange_declare(args)).expect("identical redeclare");
    tmo!(ch.exchange_delete(rs::ExchangeDeleteArguments::new(&name))).expect("delete");
    let mut args = rs::ExchangeDeclareArguments::new(&name, "topic");
    args.passive = true;
    assert!(tmo!(ch.exchange_declare(args)).is_err(), "deleted");
}

#[both_runtimes]
async fn auto_delete_exchange_goes_away_with_its_last_binding() {
    let b = broker().await;
    let conn = lp::connect(&b).await;
    let ch = lp::channel(&conn).await;
    let x = unique("auto-delete-x");
    tmo!(ch.exchange_declare(
        &x,
        lp::ExchangeKind::Fanout,
        lp::ExchangeDeclareOptions {
            auto_delete: true,
            ..Default::default()
        },
        lp::FieldTable::default()
    ))
    .expect("declare");
    // No binding yet: it stays.
    tmo!(ch.exchange_declare(
        &x,
        lp::ExchangeKind::Fanout,
        passive(),
        lp::FieldTable::default()
    ))
    .expect("still there before any binding");
    let q1 = lp::queue(&ch, "ad1").await;
    let q2 = lp::queue(&ch, "ad2").await;
    lp::bind(&ch, &q1, &x, "").await;
    lp::bind(&ch, &q2, &x, "").await;
    tmo!(ch.queue_unbind(&q1, &x, "", lp::FieldTable::default())).expect("unbind 1");
    tmo!(ch.exchange_declare(
        &x,
        lp::ExchangeKind::Fanout,
        passive(),
        lp::FieldTable::default()
    ))
    .expect("still there with one binding");
    tmo!(ch.queue_unbind(&q2, &x, "", lp::FieldTable::default())).expect("unbind 2");
    let res = tmo!(ch.exchange_declare(
        &x,
        lp::ExchangeKind::Fanout,
        passive(),
        lp::FieldTable::default()
    ));
    lp::assert_err(res, 404, "NOT_FOUND");
}

#[both_runtimes]
async fn internal_exchange_refuses_publishes_but_routes_from_other_exchanges() {
    let b = broker().await;
    let conn = lp::connect(&b).await;
    let ch = confirm_channel(&conn).await;
    let internal = unique("internal-x");
    tmo!(ch.exchange_declare(
        &internal,
        lp::ExchangeKind::Fanout,
        lp::ExchangeDeclareOptions {
            internal: true,
            ..Default::default()
        },
        lp::FieldTable::default()
    ))
    .expect("declare internal");
    let front = lp::exchange(&ch, "front", lp::ExchangeKind::Direct).await;
    let q = lp::queue(&ch, "behind-internal").await;
    lp::bind(&ch, &q, &internal, "").await;
    tmo!(ch.exchange_bind(
        &internal,
        &front,
        "k",
        lp::ExchangeBindOptions::default(),
        lp::FieldTable::default()
    ))
    .expect("exchange.bind");
    publish_acked(&ch, &front, "k", b"via front").await;
    assert_eq!(drain(&ch, &q).await, ["via front"]);
    // Publishing straight to it closes the channel:
    // "ACCESS_REFUSED - cannot publish to internal exchange '...' in vhost '/'".
    let mut errors = lp::watch_errors(&ch);
    let res = tmo!(ch.basic_publish(
        &internal,
        "",
        lp::BasicPublishOptions::default(),
        b"direct",
        lp::BasicProperties::default()
    ));
    if let Ok(confirm) = res {
        let _ = tmo!(confirm);
    }
    let err = tmo!(errors.recv()).expect("channel error");
    let (code, text) = lp::code(&err);
    assert_eq!(code, 403, "{text}");
    assert_text_prefix(&text, "ACCESS_REFUSED");
    let ch = lp::channel(&conn).await;
    assert!(drain(&ch, &q).await.is_empty());
}

#[both_runtimes]
async fn exchange_delete_if_unused_refuses_while_bound() {
    let b = broker().await;
    let (conn, _) = rs::connect(&b).await;
    let (ch, mut ev) = rs::channel(&conn).await;
    let x = rs::exchange(&ch, "if-unused", rs::ExchangeType::Direct).await;
    let q = rs::queue(&ch, "if-unused-q").await;
    rs::bind(&ch, &q, &x, "k").await;
    let mut del = rs::ExchangeDeleteArguments::new(&x);
    del.if_unused = true;
    assert!(tmo!(ch.exchange_delete(del.clone())).is_err());
    // RabbitMQ: "PRECONDITION_FAILED - exchange '...' in vhost '/' in use".
    rs::assert_closed(&mut ev, 406, "PRECONDITION_FAILED").await;
    let (ch, _) = rs::channel(&conn).await;
    tmo!(ch.queue_unbind(rs::QueueUnbindArguments::new(&q, &x, "k"))).expect("unbind");
    tmo!(ch.exchange_delete(del)).expect("unused now");
}

#[both_runtimes]
async fn deleting_a_missing_exchange_succeeds() {
    let b = broker().await;
    let (_conn, ch) = lp::open(&b).await;
    // Note: RabbitMQ (3.x) treats exchange.delete of a missing exchange as
    // success, not 404.
    tmo!(ch.exchange_delete(&unique("never-was"), lp::ExchangeDeleteOptions::default()))
        .expect("delete-ok");
    tmo!(ch.exchange_delete(
        &unique("never-was"),
        lp::ExchangeDeleteOptions {
            if_unused: true,
            ..Default::default()
        }
    ))
    .expect("delete-ok with if-unused");
}

#[both_runtimes]
async fn deleting_an_exchange_removes_its_bindings() {
    let b = broker().await;
    let conn = lp::connect(&b).await;
    let ch = confirm_channel(&conn).await;
    let x = lp::exchange(&ch, "deleted", lp::ExchangeKind::Fanout).await;
    let q = lp::queue(&ch, "orphan").await;
    lp::bind(&ch, &q, &x, "").await;
    // Re-created with the same name, it has no bindings left.
    delete_and_declare_fanout_again(&ch, &x).await;
    publish_acked(&ch, &x, "", b"nobody").await;
    assert!(drain(&ch, &q).await.is_empty());
}

#[both_runtimes]
async fn exchange_to_exchange_bind_and_unbind() {
    let b = broker().await;
    let (conn, _) = rs::connect(&b).await;
    let (ch, _) = rs::channel(&conn).await;
    let source = rs::exchange(&ch, "e2e-src", rs::ExchangeType::Topic).await;
    let dest = rs::exchange(&ch, "e2e-dst", rs::ExchangeType::Fanout).await;
    let q = rs::queue(&ch, "e2e-q").await;
    let direct_q = rs::queue(&ch, "e2e-direct").await;
    rs::bind(&ch, &q, &dest, "").await;
    rs::bind(&ch, &direct_q, &source, "logs.#").await;
    tmo!(ch.exchange_bind(rs::ExchangeBindArguments::new(&dest, &source, "logs.*")))
        .expect("exchange.bind");
    rs::publish(&ch, &source, "logs.error", b"1").await;
    rs::publish(&ch, &source, "logs.a.b", b"2").await;
    rs::publish(&ch, &source, "other", b"3").await;
    assert_eq!(drain_rs(&ch, &q).await, ["1"]);
    assert_eq!(drain_rs(&ch, &direct_q).await, ["1", "2"]);
    tmo!(ch.exchange_unbind(rs::ExchangeUnbindArguments::new(&dest, &source, "logs.*")))
        .expect("exchange.unbind");
    rs::publish(&ch, &source, "logs.error", b"4").await;
    assert!(drain_rs(&ch, &q).await.is_empty());
    assert_eq!(drain_rs(&ch, &direct_q).await, ["4"]);
}

#[both_runtimes]
async fn exchange_to_exchange_cycles_deliver_once() {
    let b = broker().await;
    let conn = lp::connect(&b).await;
    let ch = confirm_channel(&conn).await;
    let a = lp::exchange(&ch, "cycle-a", lp::ExchangeKind::Fanout).await;
    let c = lp::exchange(&ch, "cycle-c", lp::ExchangeKind::Fanout).await;
    let q = lp::queue(&ch, "cycle-q").await;
    for (dst, src) in [(&a, &c), (&c, &a)] {
        tmo!(ch.exchange_bind(
            dst,
            src,
            "",
            lp::ExchangeBindOptions::default(),
            lp::FieldTable::default()
        ))
        .expect("exchange.bind");
    }
    lp::bind(&ch, &q, &a, "").await;
    lp::bind(&ch, &q, &c, "").await;
    publish_acked(&ch, &a, "", b"loop").await;
    assert_eq!(drain(&ch, &q).await, ["loop"]);
}

#[both_runtimes]
async fn exchange_bind_with_a_missing_side_gets_404() {
    let b = broker().await;
    let (conn, _) = rs::connect(&b).await;
    let (ch, mut ev) = rs::channel(&conn).await;
    let x = rs::exchange(&ch, "e2e-present", rs::ExchangeType::Direct).await;
    let missing = unique("e2e-missing");
    assert!(tmo!(ch.exchange_bind(rs::ExchangeBindArguments::new(&x, &missing, "k"))).is_err());
    // RabbitMQ: "NOT_FOUND - no exchange '...' in vhost '/'".
    rs::assert_closed(&mut ev, 404, "NOT_FOUND").await;
    let (ch, mut ev) = rs::channel(&conn).await;
    assert!(tmo!(ch.exchange_bind(rs::ExchangeBindArguments::new(&missing, &x, "k"))).is_err());
    rs::assert_closed(&mut ev, 404, "NOT_FOUND").await;
}

#[both_runtimes]
async fn alternate_exchange_takes_unroutable_messages() {
    let b = broker().await;
    let conn = lp::connect(&b).await;
    let ch = confirm_channel(&conn).await;
    let ae = lp::exchange(&ch, "ae", lp::ExchangeKind::Fanout).await;
    let unrouted = lp::queue(&ch, "unrouted").await;
    lp::bind(&ch, &unrouted, &ae, "").await;
    let main = unique("with-ae");
    tmo!(ch.exchange_declare(
        &main,
        lp::ExchangeKind::Direct,
        lp::ExchangeDeclareOptions::default(),
        lp::table(vec![("alternate-exchange", lp::lstr(&ae))])
    ))
    .expect("declare with alternate-exchange");
    let routed = lp::queue(&ch, "routed").await;
    lp::bind(&ch, &routed, &main, "good").await;
    publish_acked(&ch, &main, "good", b"routed").await;
    // Mandatory and unroutable by the main exchange, but the alternate
    // exchange routes it: no basic.return, the confirm is a plain ack.
    let confirm = tmo!(ch.basic_publish(
        &main,
        "bad",
        lp::BasicPublishOptions {
            mandatory: true,
            ..Default::default()
        },
        b"to-ae",
        lp::BasicProperties::default()
    ))
    .expect("publish");
    let c = tmo!(confirm).expect("confirm");
    assert_eq!(c, lp::Confirmation::Ack(None), "no return");
    assert_eq!(drain(&ch, &routed).await, ["routed"]);
    assert_eq!(drain(&ch, &unrouted).await, ["to-ae"]);
}

/// RabbitMQ's x-consistent-hash plugin: binding keys are weights, each
/// message goes to exactly one bound queue, the same routing key always
/// to the same one; a key that is not a weight is refused with 406.
#[both_runtimes]
async fn consistent_hash_exchange_routes_each_key_to_one_queue() {
    let b = broker().await;
    let (conn, _) = rs::connect(&b).await;
    let (ch, _ev) = rs::channel(&conn).await;
    let x = unique("hash");
    tmo!(ch.exchange_declare(rs::ExchangeDeclareArguments::new(&x, "x-consistent-hash")))
        .expect("x-consistent-hash is a known type");
    let mut queues = Vec::new();
    for weight in ["1", "1", "2"] {
        let q = rs::queue(&ch, "ring").await;
        rs::bind(&ch, &q, &x, weight).await;
        queues.push(q);
    }
    for round in 0..2 {
        for i in 0..200 {
            rs::publish(
                &ch,
                &x,
                &format!("robot-{i}"),
                format!("{round}:{i}").as_bytes(),
            )
            .await;
        }
    }
    let mut owner = std::collections::BTreeMap::new();
    let mut total = 0;
    for (index, q) in queues.iter().enumerate() {
        let bodies = drain_rs(&ch, q).await;
        assert!(bodies.len() > 20, "queue {index} got {}", bodies.len());
        for body in bodies {
            let (_, key) = body.split_once(':').unwrap();
            let previous = owner.insert(key.to_owned(), index);
            assert!(
                previous.is_none() || previous == Some(index),
                "key {key} went to two queues"
            );
            total += 1;
        }
    }
    assert_eq!(total, 400, "each message to exactly one queue");
    assert_eq!(owner.len(), 200);

    let (ch, mut ev) = rs::channel(&conn).await;
    let q = rs::queue(&ch, "ring").await;
    assert!(tmo!(ch.queue_bind(rs::QueueBindArguments::new(&q, &x, "heavy"))).is_err());
    rs::assert_closed(&mut ev, 406, "PRECONDITION_FAILED").await;
}

/// A channel publishing to one exchange keeps reaching whatever that name
/// means now: after the exchange is deleted and declared again with other
/// bindings its messages follow the new bindings, and once it is gone
/// for good a publish is refused with 404 (the channel must not keep
/// routing through the exchange it used before).
#[both_runtimes]
async fn publishing_follows_an_exchange_deleted_and_declared_again() {
    let b = broker().await;
    let conn = lp::connect(&b).await;
    let admin = lp::channel(&conn).await;
    let publisher = confirm_channel(&conn).await;
    let x = lp::exchange(&admin, "redeclared", lp::ExchangeKind::Fanout).await;
    let before = lp::queue(&admin, "redeclared-before").await;
    let after = lp::queue(&admin, "redeclared-after").await;
    lp::bind(&admin, &before, &x, "").await;
    publish_acked(&publisher, &x, "", b"one").await;
    delete_and_declare_fanout_again(&admin, &x).await;
    lp::bind(&admin, &after, &x, "").await;
    publish_acked(&publisher, &x, "", b"two").await;
    assert_eq!(drain(&admin, &before).await, ["one"]);
    assert_eq!(drain(&admin, &after).await, ["two"]);
    tmo!(admin.exchange_delete(&x, lp::ExchangeDeleteOptions::default())).expect("delete");
    let refused = tmo!(publisher.basic_publish(
        &x,
        "",
        lp::BasicPublishOptions::default(),
        b"three",
        lp::BasicProperties::default()
    ));
    let confirmed = match refused {
        Ok(confirm) => tmo!(confirm).map(|_| ()),
        Err(e) => Err(e),
    };
    lp::assert_err(confirmed, 404, "NOT_FOUND");
}
