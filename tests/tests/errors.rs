//! Reply codes in one place: every failing operation on a fresh channel,
//! with the code, the reply text's prefix and the class and method ids the
//! broker names in channel.close / connection.close, as RabbitMQ 3.10
//! sends them.

#[macro_use]
mod common;

use common::*;

/// One operation that fails on a fresh channel.
#[derive(Debug, Clone, Copy)]
enum Op {
    PassiveQueueMissing,
    PassiveExchangeMissing,
    BindMissingExchange,
    BindMissingQueue,
    PurgeMissing,
    ConsumeMissing,
    GetMissing,
    PublishMissingExchange,
    AckUnknown,
    RejectUnknown,
    NackUnknown,
    DeleteQueueIfEmpty,
    DeleteExchangeIfUnused,
    DeclareAmqExchange,
    DeclareAmqQueue,
    TxCommitWithoutSelect,
    ExchangeBindMissing,
    QueueRedeclareMismatch,
    ExchangeRedeclareMismatch,
    DeleteDefaultExchange,
    BindDefaultExchange,
    ConsumeExclusivelyTaken,
    PublishInternal,
    ConfirmOnTxChannel,
    TxOnConfirmChannel,
    BadXMatch,
}

/// Names created once for every case.
struct Fixture {
    queue_with_message: String,
    bound_exchange: String,
    internal: String,
    consumed_exclusively: String,
}

async fn fixture(conn: &rs::Connection) -> (Fixture, rs::Channel) {
    let (ch, mut ev) = rs::channel(conn).await;
    rs::confirm_select(&ch).await;
    let queue_with_message = rs::queue(&ch, "err-full").await;
    rs::publish(&ch, "", &queue_with_message, b"x").await;
    rs::acked(&mut ev, 1).await;
    let bound_exchange = rs::exchange(&ch, "err-bound", rs::ExchangeType::Direct).await;
    rs::bind(&ch, &queue_with_message, &bound_exchange, "k").await;
    let internal = unique("err-internal");
    let mut args = rs::ExchangeDeclareArguments::new(&internal, "fanout");
    args.internal = true;
    tmo!(ch.exchange_declare(args)).expect("internal exchange");
    let consumed_exclusively = rs::queue(&ch, "err-excl").await;
    let mut args = rs::BasicConsumeArguments::new(&consumed_exclusively, "exclusive-owner");
    args.exclusive = true;
    tmo!(ch.basic_consume_rx(args)).expect("exclusive consumer");
    (
        Fixture {
            queue_with_message,
            bound_exchange,
            internal,
            consumed_exclusively,
        },
        ch,
    )
}

/// Runs `op` on `ch`; the call itself may or may not report the failure
/// (amqprs only learns of it through the channel.close callback).
async fn run(ch: &rs::Channel, op: Op, f: &Fixture) {
    let missing = unique("err-missing");
    let _ = match op {
        Op::PassiveQueueMissing => {
            let mut a = rs::QueueDeclareArguments::new(&missing);
            a.passive(true);
            tmo!(ch.queue_declare(a)).map(drop)
        }
        Op::PassiveExchangeMissing => {
            let mut a = rs::ExchangeDeclareArguments::new(&missing, "direct");
            a.passive = true;
            tmo!(ch.exchange_declare(a))
        }
        Op::BindMissingExchange => tmo!(ch.queue_bind(rs::QueueBindArguments::new(
            &f.queue_with_message,
            &missing,
            "k"
        ))),
        Op::BindMissingQueue => {
            tmo!(ch.queue_bind(rs::QueueBindArguments::new(&missing, "amq.direct", "k")))
        }
        Op::PurgeMissing => tmo!(ch.queue_purge(rs::QueuePurgeArguments::new(&missing))).map(drop),
        Op::ConsumeMissing => {
            tmo!(ch.basic_consume_rx(rs::BasicConsumeArguments::new(&missing, ""))).map(drop)
        }
        Op::GetMissing => tmo!(ch.basic_get(rs::BasicGetArguments::new(&missing))).map(drop),
        Op::PublishMissingExchange => tmo!(ch.basic_publish(
            rs::BasicProperties::default(),
            b"x".to_vec(),
            rs::BasicPublishArguments::new(&missing, "k")
        )),
        Op::AckUnknown => tmo!(ch.basic_ack(rs::BasicAckArguments::new(42, false))),
        Op::RejectUnknown => tmo!(ch.basic_reject(rs::BasicRejectArguments::new(42, false))),
        Op::NackUnknown => tmo!(ch.basic_nack(rs::BasicNackArguments::new(42, false, false))),
        Op::DeleteQueueIfEmpty => {
            let mut a = rs::QueueDeleteArguments::new(&f.queue_with_message);
            a.if_empty(true);
            tmo!(ch.queue_delete(a)).map(drop)
        }
        Op::DeleteExchangeIfUnused => {
            let mut a = rs::ExchangeDeleteArguments::new(&f.bound_exchange);
            a.if_unused = true;
            tmo!(ch.exchange_delete(a))
        }
        Op::DeclareAmqExchange => tmo!(ch.exchange_declare(rs::ExchangeDeclareArguments::new(
            &unique("amq.err"),
            "direct"
        ))),
        Op::DeclareAmqQueue => {
            tmo!(ch.queue_declare(rs::QueueDeclareArguments::new(&unique("amq.err")))).map(drop)
        }
        Op::TxCommitWithoutSelect => tmo!(ch.tx_commit()),
        Op::ExchangeBindMissing => {
            tmo!(ch.exchange_bind(rs::ExchangeBindArguments::new(&missing, "amq.direct", "k")))
        }
        Op::QueueRedeclareMismatch => {
            let mut a = rs::QueueDeclareArguments::new(&f.queue_with_message);
            a.durable(true);
            tmo!(ch.queue_declare(a)).map(drop)
        }
        Op::ExchangeRedeclareMismatch => tmo!(ch.exchange_declare(
            rs::ExchangeDeclareArguments::new(&f.bound_exchange, "topic")
        )),
        Op::DeleteDefaultExchange => tmo!(ch.exchange_delete(rs::ExchangeDeleteArguments::new(""))),
        Op::BindDefaultExchange => {
            tmo!(ch.queue_bind(rs::QueueBindArguments::new(&f.queue_with_message, "", "k")))
        }
        Op::ConsumeExclusivelyTaken => {
            tmo!(ch.basic_consume_rx(rs::BasicConsumeArguments::new(&f.consumed_exclusively, "")))
                .map(drop)
        }
        Op::PublishInternal => tmo!(ch.basic_publish(
            rs::BasicProperties::default(),
            b"x".to_vec(),
            rs::BasicPublishArguments::new(&f.internal, "")
        )),
        Op::ConfirmOnTxChannel => {
            tmo!(ch.tx_select()).expect("tx.select");
            tmo!(ch.confirm_select(rs::ConfirmSelectArguments::default()))
        }
        Op::TxOnConfirmChannel => {
            rs::confirm_select(ch).await;
            tmo!(ch.tx_select())
        }
        Op::BadXMatch => {
            let x = rs::exchange(ch, "err-headers", rs::ExchangeType::Headers).await;
            let mut a = rs::QueueBindArguments::new(&f.queue_with_message, &x, "");
            a.arguments = rs::table(vec![("x-match", rs::lstr("some"))]);
            tmo!(ch.queue_bind(a))
        }
    };
}

/// Runs every case on its own channel and reports all mismatches at once.
async fn check_channel_errors(cases: &[(Op, u16, &str, (u16, u16))]) {
    let b = broker().await;
    let (conn, _) = rs::connect(&b).await;
    let (f, _keep) = fixture(&conn).await;
    let mut wrong = Vec::new();
    for &(op, code, prefix, ids) in cases {
        let (ch, mut ev) = rs::channel(&conn).await;
        run(&ch, op, &f).await;
        let Ok((got_code, text, got_ids)) =
            tokio::time::timeout(TIMEOUT, rs::closed_ids(&mut ev)).await
        else {
            wrong.push(format!(
                "{op:?}: no channel.close, want {code} {ids:?} {prefix}"
            ));
            continue;
        };
        if got_code != code || !text.starts_with(prefix) || got_ids != ids {
            wrong.push(format!(
                "{op:?}: got {got_code} {got_ids:?} {text:?}, want {code} {ids:?} {prefix}"
            ));
        }
    }
    assert!(
        wrong.is_empty(),
        "channel errors differ:\n{}",
        wrong.join("\n")
    );
    assert!(conn.is_open(), "channel errors leave the connection open");
}

#[both_runtimes]
async fn not_found_errors_name_the_method() {
    check_channel_errors(&[
        (Op::PassiveQueueMissing, 404, "NOT_FOUND", (50, 10)),
        (Op::PassiveExchangeMissing, 404, "NOT_FOUND", (40, 10)),
        (Op::BindMissingExchange, 404, "NOT_FOUND", (50, 20)),
        (Op::BindMissingQueue, 404, "NOT_FOUND", (50, 20)),
        (Op::PurgeMissing, 404, "NOT_FOUND", (50, 30)),
        (Op::ConsumeMissing, 404, "NOT_FOUND", (60, 20)),
        (Op::GetMissing, 404, "NOT_FOUND", (60, 70)),
        (Op::PublishMissingExchange, 404, "NOT_FOUND", (60, 40)),
        (Op::ExchangeBindMissing, 404, "NOT_FOUND", (40, 30)),
    ])
    .await;
}

#[both_runtimes]
async fn precondition_failed_errors_name_the_method() {
    check_channel_errors(&[
        (Op::AckUnknown, 406, "PRECONDITION_FAILED", (60, 80)),
        (Op::RejectUnknown, 406, "PRECONDITION_FAILED", (60, 90)),
        (Op::NackUnknown, 406, "PRECONDITION_FAILED", (60, 120)),
        (Op::DeleteQueueIfEmpty, 406, "PRECONDITION_FAILED", (50, 40)),
        (
            Op::DeleteExchangeIfUnused,
            406,
            "PRECONDITION_FAILED",
            (40, 20),
        ),
        (
            Op::TxCommitWithoutSelect,
            406,
            "PRECONDITION_FAILED",
            (90, 20),
        ),
        (
            Op::QueueRedeclareMismatch,
            406,
            "PRECONDITION_FAILED",
            (50, 10),
        ),
        (
            Op::ExchangeRedeclareMismatch,
            406,
            "PRECONDITION_FAILED",
            (40, 10),
        ),
        (Op::ConfirmOnTxChannel, 406, "PRECONDITION_FAILED", (85, 10)),
        (Op::TxOnConfirmChannel, 406, "PRECONDITION_FAILED", (90, 10)),
        (Op::BadXMatch, 406, "PRECONDITION_FAILED", (50, 20)),
    ])
    .await;
}

#[both_runtimes]
async fn access_refused_errors_name_the_method() {
    check_channel_errors(&[
        (Op::DeclareAmqExchange, 403, "ACCESS_REFUSED", (40, 10)),
        (Op::DeclareAmqQueue, 403, "ACCESS_REFUSED", (50, 10)),
        (Op::DeleteDefaultExchange, 403, "ACCESS_REFUSED", (40, 20)),
        (Op::BindDefaultExchange, 403, "ACCESS_REFUSED", (50, 20)),
        (Op::ConsumeExclusivelyTaken, 403, "ACCESS_REFUSED", (60, 20)),
        (Op::PublishInternal, 403, "ACCESS_REFUSED", (60, 40)),
    ])
    .await;
}

#[both_runtimes]
async fn resource_locked_names_the_method() {
    let b = broker().await;
    let (owner, _) = rs::connect(&b).await;
    let (och, _) = rs::channel(&owner).await;
    let q = rs::queue_args(
        &och,
        rs::QueueDeclareArguments::new(&unique("locked"))
            .exclusive(true)
            .finish(),
    )
    .await;
    let (other, _) = rs::connect(&b).await;
    let (ch, mut ev) = rs::channel(&other).await;
    let _ = tmo!(ch.basic_get(rs::BasicGetArguments::new(&q)));
    let (code, text, ids) = rs::closed_ids(&mut ev).await;
    assert_eq!((code, ids), (405, (60, 70)), "{text}");
    assert_text_prefix(&text, "RESOURCE_LOCKED");
}

/// Runs `op` on a fresh connection and expects a connection.close.
async fn connection_error(
    setup: impl for<'a> FnOnce(
        &'a rs::Channel,
    ) -> std::pin::Pin<Box<dyn std::future::Future<Output = ()> + 'a>>,
    code: u16,
    prefix: &str,
    ids: (u16, u16),
) {
    let b = broker().await;
    let (conn, mut conn_ev) = rs::connect(&b).await;
    let (ch, _) = rs::channel(&conn).await;
    setup(&ch).await;
    let close = tmo!(conn_ev.recv()).expect("connection.close");
    assert_eq!(close.code, code, "{close:?}");
    assert_text_prefix(&close.text, prefix);
    assert_eq!((close.class_id, close.method_id), ids, "{close:?}");
}

#[both_runtimes]
async fn unknown_exchange_type_is_503_on_exchange_declare() {
    connection_error(
        |ch| {
            Box::pin(async move {
                let _ = tmo!(ch
                    .exchange_declare(rs::ExchangeDeclareArguments::new(&unique("x"), "nonsense")));
            })
        },
        503,
        "COMMAND_INVALID",
        (40, 10),
    )
    .await;
}

#[both_runtimes]
async fn reused_consumer_tag_is_530_on_basic_consume() {
    connection_error(
        |ch| {
            Box::pin(async move {
                let q = rs::queue(ch, "reuse").await;
                let _first = rs::consume(ch, &q, "dup", false).await;
                let _ = tmo!(ch.basic_consume_rx(rs::BasicConsumeArguments::new(&q, "dup")));
            })
        },
        530,
        "NOT_ALLOWED",
        (60, 20),
    )
    .await;
}

#[both_runtimes]
async fn immediate_publish_is_540_on_basic_publish() {
    connection_error(
        |ch| {
            Box::pin(async move {
                let mut args = rs::BasicPublishArguments::new("amq.direct", "k");
                args.immediate = true;
                let _ = tmo!(ch.basic_publish(rs::BasicProperties::default(), vec![], args));
            })
        },
        540,
        "NOT_IMPLEMENTED",
        (60, 40),
    )
    .await;
}

#[both_runtimes]
async fn prefetch_size_is_540_on_basic_qos() {
    connection_error(
        |ch| {
            Box::pin(async move {
                let _ = tmo!(ch.basic_qos(rs::BasicQosArguments::new(1024, 10, false)));
            })
        },
        540,
        "NOT_IMPLEMENTED",
        (60, 10),
    )
    .await;
}

#[both_runtimes]
async fn channel_flow_off_is_540() {
    connection_error(
        |ch| {
            Box::pin(async move {
                let _ = tmo!(ch.flow(false));
            })
        },
        540,
        "NOT_IMPLEMENTED",
        (20, 20),
    )
    .await;
}

#[both_runtimes]
async fn unbinding_with_a_missing_queue_or_exchange_is_not_an_error() {
    let b = broker().await;
    let (_conn, ch, mut ev) = rs::open(&b).await;
    let q = rs::queue(&ch, "unbind-present").await;
    let missing = unique("unbind-missing");
    // Note: RabbitMQ 3.10 answers unbind-ok for all of these, where a bind
    // would get 404.
    tmo!(ch.queue_unbind(rs::QueueUnbindArguments::new(&missing, "amq.direct", "k")))
        .expect("queue.unbind of a missing queue");
    tmo!(ch.queue_unbind(rs::QueueUnbindArguments::new(&q, &missing, "k")))
        .expect("queue.unbind from a missing exchange");
    tmo!(ch.exchange_unbind(rs::ExchangeUnbindArguments::new(
        &missing,
        "amq.direct",
        "k"
    )))
    .expect("exchange.unbind of a missing destination");
    tmo!(ch.exchange_unbind(rs::ExchangeUnbindArguments::new(
        "amq.direct",
        &missing,
        "k"
    )))
    .expect("exchange.unbind from a missing source");
    assert!(ch.is_open());
    assert!(ev.try_recv().is_err(), "no channel.close");
    assert_eq!(rs::counts(&ch, &q).await, (0, 0));
}
