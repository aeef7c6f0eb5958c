//! RabbitMQ's permissions (issue 14 item 2), driven by lapin: a user with
//! configure `^pu\.`, write `^(pu\.|amq\.default|amq\.topic)`, read
//! `^(pu\.|amq\.topic)` and, on `amq.topic`, topic write `^{username}\.`
//! and read `^r\.`. Each operation of RabbitMQ's mapping is tried allowed
//! and refused; the expected codes and texts are RabbitMQ 3.10's, taken
//! from it with the same user (`rabbitmqctl set_permissions`,
//! `set_topic_permissions`) and pika. `conformance/` runs the same table
//! against RabbitMQ and Leveret side by side.

#[macro_use]
mod common;

use common::*;
use leveret_broker::{Broker, Permission, TopicPermission};

const USER: &str = "pu";

fn restricted() -> Permission {
    Permission {
        configure: "^pu\\.".into(),
        write: "^(pu\\.|amq\\.default|amq\\.topic)".into(),
        read: "^(pu\\.|amq\\.topic)".into(),
    }
}

async fn broker() -> TestBroker {
    let builder = Broker::builder()
        .user("guest", "guest")
        .user(USER, "pupw")
        .vhost("/")
        .vhost("other")
        .permission("guest", "/", Permission::full())
        .permission(USER, "/", restricted())
        .topic_permission(
            USER,
            "/",
            "amq.topic",
            TopicPermission {
                write: "^{username}\\.".into(),
                read: "^r\\.".into(),
            },
        );
    TestBroker::leveret(builder).await
}

async fn connect(b: &TestBroker, vhost: &str) -> lapin::Result<lp::Connection> {
    tmo!(lp::Connection::connect(
        &b.url_with(USER, "pupw", vhost),
        lp::ConnectionProperties::default()
    ))
}

/// A fresh channel of the restricted user.
async fn channel(conn: &lp::Connection) -> lp::Channel {
    tmo!(conn.create_channel()).expect("channel")
}

const REFUSED_QUEUE: &str = "ACCESS_REFUSED - access to queue";

/// Publishes and waits for the channel's fate: `None` when a later
/// round trip succeeds, else the broker's close.
async fn publish_outcome(ch: &lp::Channel, exchange: &str, key: &str) -> Option<(u16, String)> {
    let mut errors = lp::watch_errors(ch);
    let _ = tmo!(ch.basic_publish(
        exchange,
        key,
        lp::BasicPublishOptions::default(),
        b"x",
        lp::BasicProperties::default()
    ));
    match tmo!(ch.basic_qos(1, lp::BasicQosOptions::default())) {
        Ok(()) => None,
        // lapin may fail the call before it reports the broker's close:
        // the close is the outcome.
        Err(_) => Some(lp::code(&tmo!(errors.recv()).expect("the broker's close"))),
    }
}

#[both_runtimes]
async fn a_user_without_a_permission_on_a_vhost_cannot_open_it() {
    let b = broker().await;
    lp::assert_err(
        connect(&b, "other").await,
        530,
        "NOT_ALLOWED - access to vhost 'other' refused for user 'pu'",
    );
    connect(&b, "/")
        .await
        .expect("the vhost it has a permission on");
    b.stop().await;
}

#[both_runtimes]
async fn configure_covers_declare_and_delete_of_queues_and_exchanges() {
    let b = broker().await;
    let conn = connect(&b, "/").await.expect("connect");
    let ch = channel(&conn).await;
    tmo!(ch.queue_declare(
        "pu.q",
        lp::QueueDeclareOptions::default(),
        lp::FieldTable::default()
    ))
    .expect("pu.q is the user's");
    for (what, result) in [
        (
            "declare",
            tmo!(channel(&conn).await.queue_declare(
                "other",
                lp::QueueDeclareOptions::default(),
                lp::FieldTable::default()
            ))
            .map(drop),
        ),
        (
            "delete",
            tmo!(channel(&conn)
                .await
                .queue_delete("other", lp::QueueDeleteOptions::default()))
            .map(drop),
        ),
    ] {
        let err = result.expect_err(what);
        assert_eq!(
            lp::code(&err),
            (
                403,
                "ACCESS_REFUSED - access to queue 'other' in vhost '/' refused for user 'pu'"
                    .into()
            ),
            "{what}"
        );
    }
    // A server-named queue is checked under its generated name.
    lp::assert_err(
        tmo!(channel(&conn).await.queue_declare(
            "",
            lp::QueueDeclareOptions::default(),
            lp::FieldTable::default()
        )),
        403,
        "ACCESS_REFUSED - access to queue 'amq.gen-",
    );
    // Passive declares need no permission (RabbitMQ's rule): a missing
    // queue is 404, an existing exchange is fine.
    lp::assert_err(
        tmo!(channel(&conn).await.queue_declare(
            "other",
            lp::QueueDeclareOptions {
                passive: true,
                ..Default::default()
            },
            lp::FieldTable::default()
        )),
        404,
        "NOT_FOUND - no queue 'other' in vhost '/'",
    );
    tmo!(channel(&conn).await.exchange_declare(
        "amq.direct",
        lp::ExchangeKind::Direct,
        lp::ExchangeDeclareOptions {
            passive: true,
            ..Default::default()
        },
        lp::FieldTable::default()
    ))
    .expect("passive exchange.declare");
    lp::assert_err(
        tmo!(channel(&conn).await.exchange_declare(
            "other.x",
            lp::ExchangeKind::Direct,
            lp::ExchangeDeclareOptions::default(),
            lp::FieldTable::default()
        )),
        403,
        "ACCESS_REFUSED - access to exchange 'other.x' in vhost '/' refused for user 'pu'",
    );
    lp::assert_err(
        tmo!(channel(&conn)
            .await
            .exchange_delete("other.nothere", lp::ExchangeDeleteOptions::default())),
        403,
        "ACCESS_REFUSED - access to exchange 'other.nothere' in vhost '/' refused for user 'pu'",
    );
    b.stop().await;
}

#[both_runtimes]
async fn dead_letter_and_alternate_exchanges_need_write_on_them() {
    let b = broker().await;
    let conn = connect(&b, "/").await.expect("connect");
    lp::assert_err(
        tmo!(channel(&conn).await.queue_declare(
            "pu.d",
            lp::QueueDeclareOptions::default(),
            lp::table(vec![("x-dead-letter-exchange", lp::lstr("amq.fanout"))])
        )),
        403,
        "ACCESS_REFUSED - access to exchange 'amq.fanout' in vhost '/' refused for user 'pu'",
    );
    tmo!(channel(&conn).await.queue_declare(
        "pu.d",
        lp::QueueDeclareOptions::default(),
        lp::table(vec![("x-dead-letter-exchange", lp::lstr("amq.topic"))])
    ))
    .expect("a dead-letter exchange it may write to");
    lp::assert_err(
        tmo!(channel(&conn).await.exchange_declare(
            "pu.x",
            lp::ExchangeKind::Direct,
            lp::ExchangeDeclareOptions::default(),
            lp::table(vec![("alternate-exchange", lp::lstr("amq.fanout"))])
        )),
        403,
        "ACCESS_REFUSED - access to exchange 'amq.fanout' in vhost '/' refused for user 'pu'",
    );
    b.stop().await;
}

#[both_runtimes]
async fn write_and_read_cover_publish_bind_consume_get_and_purge() {
    let b = broker().await;
    let conn = connect(&b, "/").await.expect("connect");
    let guest = lp::connect(&b).await;
    let admin = lp::channel(&guest).await;
    tmo!(admin.queue_declare(
        "other",
        lp::QueueDeclareOptions::default(),
        lp::FieldTable::default()
    ))
    .expect("guest declares other");
    tmo!(channel(&conn).await.queue_declare(
        "pu.q",
        lp::QueueDeclareOptions::default(),
        lp::FieldTable::default()
    ))
    .expect("pu.q");

    // The default exchange is checked as amq.default.
    assert_eq!(
        publish_outcome(&channel(&conn).await, "", "pu.q").await,
        None
    );
    assert_eq!(
        publish_outcome(&channel(&conn).await, "amq.direct", "pu.q").await,
        Some((
            403,
            "ACCESS_REFUSED - access to exchange 'amq.direct' in vhost '/' refused for user 'pu'"
                .into()
        ))
    );
    // A missing exchange it may write to is 404, as in RabbitMQ.
    assert_eq!(
        publish_outcome(&channel(&conn).await, "pu.nothere", "k").await,
        Some((
            404,
            "NOT_FOUND - no exchange 'pu.nothere' in vhost '/'".into()
        ))
    );
    // Topic permissions: the routing key against ^{username}\.
    assert_eq!(
        publish_outcome(&channel(&conn).await, "amq.topic", "pu.y").await,
        None
    );
    assert_eq!(
        publish_outcome(&channel(&conn).await, "amq.topic", "x.y").await,
        Some((
            403,
            "ACCESS_REFUSED - access to topic 'x.y' in exchange 'amq.topic' in vhost '/' refused for user 'pu'"
                .into()
        ))
    );

    // Bindings: write on the queue, read on the exchange, topic read on the key.
    let bind = |exchange: &'static str, key: &'static str| {
        let conn = &conn;
        async move {
            tmo!(channel(conn).await.queue_bind(
                "pu.q",
                exchange,
                key,
                lp::QueueBindOptions::default(),
                lp::FieldTable::default()
            ))
        }
    };
    bind("amq.topic", "r.y").await.expect("bind with r.");
    lp::assert_err(
        bind("amq.topic", "x.y").await,
        403,
        "ACCESS_REFUSED - access to topic 'x.y' in exchange 'amq.topic' in vhost '/' refused for user 'pu'",
    );
    lp::assert_err(
        bind("amq.direct", "k").await,
        403,
        "ACCESS_REFUSED - access to exchange 'amq.direct' in vhost '/' refused for user 'pu'",
    );
    lp::assert_err(
        tmo!(channel(&conn).await.queue_unbind(
            "pu.q",
            "amq.topic",
            "x.y",
            lp::FieldTable::default()
        )),
        403,
        "ACCESS_REFUSED - access to topic 'x.y'",
    );

    // Read: consume, get, purge.
    lp::assert_err(
        tmo!(channel(&conn).await.basic_consume(
            "other",
            "",
            lp::BasicConsumeOptions::default(),
            lp::FieldTable::default()
        )),
        403,
        "ACCESS_REFUSED - access to queue 'other' in vhost '/' refused for user 'pu'",
    );
    lp::assert_err(
        tmo!(channel(&conn)
            .await
            .basic_get("other", lp::BasicGetOptions::default())),
        403,
        REFUSED_QUEUE,
    );
    lp::assert_err(
        tmo!(channel(&conn)
            .await
            .queue_purge("zzz", lp::QueuePurgeOptions::default())),
        403,
        "ACCESS_REFUSED - access to queue 'zzz' in vhost '/' refused for user 'pu'",
    );
    let mine = channel(&conn).await;
    assert!(
        tmo!(mine.basic_get("pu.q", lp::BasicGetOptions { no_ack: true }))
            .expect("get from its own queue")
            .is_some()
    );
    tmo!(mine.queue_purge("pu.q", lp::QueuePurgeOptions::default())).expect("purge its own");
    b.stop().await;
}

#[both_runtimes]
async fn a_change_applies_to_open_channels_from_their_next_operation() {
    let b = broker().await;
    let admin = b.admin().expect("in-process broker");
    let conn = connect(&b, "/").await.expect("connect");
    let ch = channel(&conn).await;
    lp::assert_err(
        tmo!(ch.queue_declare(
            "wider",
            lp::QueueDeclareOptions::default(),
            lp::FieldTable::default()
        )),
        403,
        REFUSED_QUEUE,
    );
    admin
        .set_permission(USER, "/", Permission::full())
        .await
        .expect("valid patterns");
    let ch = channel(&conn).await;
    tmo!(ch.queue_declare(
        "wider",
        lp::QueueDeclareOptions::default(),
        lp::FieldTable::default()
    ))
    .expect("granted while connected");
    admin.clear_permission(USER, "/").await.expect("cleared");
    lp::assert_err(
        tmo!(ch.queue_declare(
            "wider",
            lp::QueueDeclareOptions::default(),
            lp::FieldTable::default()
        )),
        403,
        "ACCESS_REFUSED - access to vhost '/' refused for user 'pu'",
    );
    lp::assert_err(
        connect(&b, "/").await,
        530,
        "NOT_ALLOWED - access to vhost '/' refused for user 'pu'",
    );
    assert!(admin
        .set_permission(
            USER,
            "/",
            Permission {
                configure: "(?=lookahead)".into(),
                ..Permission::full()
            }
        )
        .await
        .is_err());
    b.stop().await;
}
