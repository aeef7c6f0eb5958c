//! Queue, exchange and consumer arguments as RabbitMQ 3.10 takes them:
//! numbers compared by value whatever their AMQP width (pika sends 32-bit
//! integers, the management API and definitions 64-bit), each argument
//! Leveret refuses refused with 406 naming it, unknown ones kept and never
//! compared.

#[macro_use]
mod common;

use common::*;
use leveret_broker::{ArgumentScope, ArgumentSupport, QueueSettings, ARGUMENTS};
use leveret_protocol::FieldValue;
use lp::AMQPValue;

/// `n` in every integer width lapin can send.
fn widths(n: u8) -> Vec<AMQPValue> {
    vec![
        AMQPValue::ShortShortInt(n as i8),
        AMQPValue::ShortShortUInt(n),
        AMQPValue::ShortInt(n.into()),
        AMQPValue::ShortUInt(n.into()),
        AMQPValue::LongInt(n.into()),
        AMQPValue::LongUInt(n.into()),
        AMQPValue::LongLongInt(n.into()),
    ]
}

fn numeric_args(value: AMQPValue) -> lp::FieldTable {
    lp::table(vec![
        ("x-message-ttl", value.clone()),
        ("x-max-priority", value.clone()),
        ("x-expires", AMQPValue::LongUInt(60_000)),
        ("x-max-length", value),
    ])
}

async fn declare(ch: &lp::Channel, name: &str, args: lp::FieldTable) -> lapin::Result<()> {
    tmo!(ch.queue_declare(name, lp::QueueDeclareOptions::default(), args)).map(|_| ())
}

#[both_runtimes]
async fn integer_arguments_are_equal_whatever_their_width() {
    let b = broker().await;
    let conn = lp::connect(&b).await;
    for (i, first) in widths(100).into_iter().enumerate() {
        let ch = lp::channel(&conn).await;
        let name = unique(&format!("width-{i}"));
        declare(&ch, &name, numeric_args(first.clone()))
            .await
            .expect("first declaration");
        for again in widths(100) {
            declare(&ch, &name, numeric_args(again.clone()))
                .await
                .unwrap_or_else(|e| panic!("{first:?} then {again:?}: {e}"));
        }
        // A different number is a different argument, whatever its width.
        let err = declare(&ch, &name, numeric_args(AMQPValue::LongLongInt(101)))
            .await
            .expect_err("101 is not 100");
        let (code, text) = lp::code(&err);
        assert_eq!(code, 406);
        assert!(
            text.ends_with("received '101' but current is '100'"),
            "{text}"
        );
        tmo!(lp::channel(&conn)
            .await
            .queue_delete(&name, Default::default()))
        .expect("delete");
    }
}

/// amqprs sends what the application typed: a u16 from amqprs and a
/// 32-bit integer from lapin name the same TTL.
#[both_runtimes]
async fn amqprs_and_lapin_widths_are_equivalent() {
    let b = broker().await;
    let (_rs_conn, rs_ch, _ev) = rs::open(&b).await;
    let args = rs::table(vec![("x-message-ttl", rs::FieldValue::u(5000))]);
    let name = rs::queue_args(
        &rs_ch,
        rs::QueueDeclareArguments::new(&unique("amqprs-width"))
            .arguments(args)
            .finish(),
    )
    .await;
    let (_conn, ch) = lp::open(&b).await;
    declare(
        &ch,
        &name,
        lp::table(vec![("x-message-ttl", AMQPValue::LongInt(5000))]),
    )
    .await
    .expect("the same TTL in another width");
}

/// A queue made through the management API or definitions (`Admin`, with
/// the 64-bit integers JSON gives) is declared again by an AMQP client
/// sending 32-bit ones, and the other way round.
#[both_runtimes]
async fn queues_declared_by_the_api_are_redeclared_over_amqp() {
    let b = broker().await;
    let Some(admin) = b.admin() else {
        return; // An external broker: no in-process API to declare with.
    };
    let from_api = unique("from-api");
    let mut arguments = leveret_protocol::FieldTable::new();
    for key in ["x-message-ttl", "x-expires", "x-max-priority"] {
        arguments.insert(
            key.try_into().unwrap(),
            FieldValue::I64(if key == "x-max-priority" { 5 } else { 60_000 }),
        );
    }
    let settings = QueueSettings {
        durable: false,
        auto_delete: false,
        arguments: arguments.clone(),
    };
    admin
        .declare_queue("/", &from_api, settings.clone())
        .await
        .expect("declared by the API");
    let (conn, ch) = lp::open(&b).await;
    let pika_like = lp::table(vec![
        ("x-message-ttl", AMQPValue::LongInt(60_000)),
        ("x-expires", AMQPValue::LongInt(60_000)),
        ("x-max-priority", AMQPValue::LongInt(5)),
    ]);
    declare(&ch, &from_api, pika_like.clone())
        .await
        .expect("redeclared over AMQP");
    // The other way: declared over AMQP, then through the API.
    let from_amqp = unique("from-amqp");
    declare(&ch, &from_amqp, pika_like).await.expect("declared");
    admin
        .declare_queue("/", &from_amqp, settings)
        .await
        .expect("redeclared by the API");
    // A different value is still refused, with RabbitMQ's text.
    let ch = lp::channel(&conn).await;
    let err = declare(
        &ch,
        &from_api,
        lp::table(vec![
            ("x-message-ttl", AMQPValue::LongInt(1000)),
            ("x-expires", AMQPValue::LongInt(60_000)),
            ("x-max-priority", AMQPValue::LongInt(5)),
        ]),
    )
    .await
    .expect_err("another TTL");
    let (code, text) = lp::code(&err);
    assert_eq!(code, 406);
    assert_eq!(
        text,
        format!("PRECONDITION_FAILED - inequivalent arg 'x-message-ttl' for queue '{from_api}' in vhost '/': received '1000' but current is '60000'")
    );
}

/// Every queue and consumer argument the code's list marks refused is
/// refused with 406 and a text naming it; nothing is declared.
#[both_runtimes]
async fn each_refused_argument_is_refused_naming_it() {
    let b = broker().await;
    if b.is_external() {
        return; // RabbitMQ takes some of these (x-credit): Leveret's list.
    }
    let conn = lp::connect(&b).await;
    let consumed = lp::queue(&lp::channel(&conn).await, "consumed").await;
    for argument in ARGUMENTS {
        if !matches!(argument.support, ArgumentSupport::Refused(_)) {
            continue;
        }
        let ch = lp::channel(&conn).await;
        let args = lp::table(vec![(argument.name, AMQPValue::LongInt(1))]);
        let name = unique("refused");
        let result = match argument.scope {
            ArgumentScope::Queue => declare(&ch, &name, args).await,
            ArgumentScope::Consumer => {
                tmo!(ch.basic_consume(&consumed, "c", Default::default(), args)).map(|_| ())
            }
            ArgumentScope::Exchange => tmo!(ch.exchange_declare(
                &name,
                lp::ExchangeKind::Custom("x-consistent-hash".into()),
                Default::default(),
                args
            )),
        };
        let err = result.expect_err(argument.name);
        let (code, text) = lp::code(&err);
        assert_eq!(code, 406, "{}: {text}", argument.name);
        assert!(
            text.contains(&format!("invalid arg '{}'", argument.name)),
            "{text}"
        );
        if argument.scope == ArgumentScope::Queue {
            let check = lp::channel(&conn).await;
            let passive = tmo!(check.queue_declare(
                &name,
                lp::QueueDeclareOptions {
                    passive: true,
                    ..Default::default()
                },
                Default::default()
            ));
            assert_eq!(lp::code(&passive.expect_err("not declared")).0, 404);
        }
    }
}

#[both_runtimes]
async fn quorum_queues_are_refused_and_classic_is_no_type() {
    let b = broker().await;
    let conn = lp::connect(&b).await;
    // Streams have their own tests (streams.rs).
    for kind in ["quorum"] {
        let ch = lp::channel(&conn).await;
        let name = unique(kind);
        let err = declare(
            &ch,
            &name,
            lp::table(vec![("x-queue-type", lp::lstr(kind))]),
        )
        .await
        .expect_err(kind);
        let (code, text) = lp::code(&err);
        if b.is_external() {
            continue; // RabbitMQ has them.
        }
        assert_eq!(code, 406);
        assert_eq!(
            text,
            format!("PRECONDITION_FAILED - invalid arg 'x-queue-type' for queue '{name}' in vhost '/': queue type '{kind}' is not available: this broker has classic queues and streams")
        );
    }
    let ch = lp::channel(&conn).await;
    let name = unique("classic");
    declare(
        &ch,
        &name,
        lp::table(vec![("x-queue-type", lp::lstr("classic"))]),
    )
    .await
    .expect("classic is what this broker has");
    declare(&ch, &name, lp::FieldTable::default())
        .await
        .expect("no type is classic");
    let err = declare(
        &ch,
        &unique("nonsense"),
        lp::table(vec![("x-queue-type", lp::lstr("nonsense"))]),
    )
    .await
    .expect_err("unknown type");
    assert!(lp::code(&err)
        .1
        .ends_with("\"unsupported queue type 'nonsense'\""));
}

/// RabbitMQ 3.10 keeps arguments it does not know and never compares
/// them; so does Leveret.
#[both_runtimes]
async fn unknown_arguments_are_kept_and_not_compared() {
    let b = broker().await;
    let (_conn, ch) = lp::open(&b).await;
    let name = unique("unknown-arg");
    declare(&ch, &name, lp::table(vec![("x-app-owner", lp::lstr("a"))]))
        .await
        .expect("unknown argument taken");
    declare(&ch, &name, lp::table(vec![("x-app-owner", lp::lstr("b"))]))
        .await
        .expect("and not compared");
    if let Some(admin) = b.admin() {
        let listed = admin
            .queue_refs()
            .into_iter()
            .find(|q| q.name() == name)
            .expect("listed")
            .info();
        assert_eq!(
            listed.arguments.get("x-app-owner"),
            Some(&FieldValue::string("a"))
        );
    }
}

/// `x-priority` must be an integer (RabbitMQ 3.10.8's text); exchanges
/// compare only `alternate-exchange`.
#[both_runtimes]
async fn consumer_and_exchange_arguments_are_checked_as_rabbitmq_does() {
    let b = broker().await;
    let conn = lp::connect(&b).await;
    let ch = lp::channel(&conn).await;
    let q = lp::queue(&ch, "prio-type").await;
    let err = tmo!(ch.basic_consume(
        &q,
        "c",
        Default::default(),
        lp::table(vec![("x-priority", lp::lstr("high"))])
    ))
    .expect_err("a string priority");
    let (code, text) = lp::code(&err);
    assert_eq!(code, 406);
    assert_eq!(
        text,
        format!("PRECONDITION_FAILED - invalid arg 'x-priority' for queue '{q}' in vhost '/': \"expected integer, got longstr\"")
    );
    let ch = lp::channel(&conn).await;
    let x = unique("ae");
    let ae = |name: &str| {
        lp::table(vec![
            ("alternate-exchange", lp::lstr(name)),
            ("x-other", lp::lstr(name)),
        ])
    };
    let direct = || lp::ExchangeKind::Direct;
    tmo!(ch.exchange_declare(&x, direct(), Default::default(), ae("a"))).expect("declared");
    let mut same_ae = ae("a");
    same_ae.insert("x-other".into(), lp::lstr("b"));
    tmo!(ch.exchange_declare(&x, direct(), Default::default(), same_ae))
        .expect("x-other is not compared");
    let err = tmo!(ch.exchange_declare(&x, direct(), Default::default(), ae("b")))
        .expect_err("another AE");
    assert_eq!(
        lp::code(&err).1,
        format!("PRECONDITION_FAILED - inequivalent arg 'alternate-exchange' for exchange '{x}' in vhost '/': received 'b' but current is 'a'")
    );
}
