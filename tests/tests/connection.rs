//! Connections and channels through both clients: open, close, many
//! channels, what a channel error and a connection error each take down,
//! bad credentials, unknown vhosts.

#[macro_use]
mod common;

use common::*;

#[both_runtimes]
async fn lapin_opens_and_closes_a_connection() {
    let b = broker().await;
    let (conn, ch) = lp::open(&b).await;
    assert!(conn.status().connected());
    assert!(ch.status().connected());
    tmo!(ch.close(200, "bye")).expect("channel.close");
    assert!(!ch.status().connected());
    tmo!(conn.close(200, "bye")).expect("connection.close");
    assert!(!conn.status().connected());
}

#[both_runtimes]
async fn amqprs_opens_and_closes_a_connection() {
    let b = broker().await;
    let (conn, _) = rs::connect(&b).await;
    assert!(conn.is_open());
    // RabbitMQ's tune: channel_max 2047, frame_max 128 KiB; amqprs keeps
    // the server's values.
    assert_eq!(conn.channel_max(), 2047);
    assert_eq!(conn.frame_max(), 131_072);
    let caps = conn.server_properties().capabilities();
    assert!(caps.publisher_confirms());
    assert!(caps.consumer_cancel_notify());
    assert!(caps.exchange_exchange_bindings());
    assert!(caps.basic_nack());
    assert!(caps.per_consumer_qos());
    assert!(caps.authentication_failure_close());
    let (ch, _) = rs::channel(&conn).await;
    assert!(ch.is_open());
    tmo!(ch.close()).expect("channel.close");
    tmo!(conn.close()).expect("connection.close");
}

#[both_runtimes]
async fn lapin_many_channels_on_one_connection() {
    let b = broker().await;
    let conn = lp::connect(&b).await;
    let mut channels = Vec::new();
    for _ in 0..64 {
        channels.push(lp::channel(&conn).await);
    }
    let mut ids: Vec<u16> = channels.iter().map(|c| c.id()).collect();
    ids.sort_unstable();
    ids.dedup();
    assert_eq!(ids.len(), 64, "every channel has its own number");
    // Each channel works independently: declare, publish, get back.
    for (i, ch) in channels.iter().enumerate() {
        let q = lp::queue(ch, "many-ch").await;
        lp::publish(ch, "", &q, format!("m{i}").as_bytes()).await;
        let got = lp::get(ch, &q, true).await.expect("a message");
        assert_eq!(got.delivery.data, format!("m{i}").as_bytes());
        tmo!(ch.queue_delete(&q, lp::QueueDeleteOptions::default())).expect("delete");
    }
    for ch in &channels {
        tmo!(ch.close(200, "done")).expect("channel.close");
    }
    tmo!(conn.close(200, "done")).expect("connection.close");
}

#[both_runtimes]
async fn amqprs_channels_with_chosen_numbers_can_be_reopened() {
    let b = broker().await;
    let (conn, _) = rs::connect(&b).await;
    for round in 0..2 {
        let mut chans = Vec::new();
        for id in [1u16, 2, 7, 100, 2047] {
            let ch = tmo!(conn.open_channel(Some(id)))
                .unwrap_or_else(|e| panic!("open channel {id} (round {round}): {e}"));
            assert_eq!(ch.channel_id(), id);
            chans.push(ch);
        }
        for ch in chans {
            let q = rs::queue(&ch, "chosen").await;
            rs::publish(&ch, "", &q, b"x").await;
            assert!(rs::get(&ch, &q, true).await.is_some());
            tmo!(ch.queue_delete(rs::QueueDeleteArguments::new(&q))).expect("delete");
            tmo!(ch.close()).expect("channel.close");
        }
    }
    tmo!(conn.close()).expect("connection.close");
}

#[both_runtimes]
async fn closing_one_channel_leaves_the_others_working() {
    let b = broker().await;
    let conn = lp::connect(&b).await;
    let a = lp::channel(&conn).await;
    let c = lp::channel(&conn).await;
    tmo!(a.close(200, "done")).expect("channel.close");
    // The closed channel refuses further use (client side)...
    assert!(tmo!(a.queue_declare(
        "",
        lp::QueueDeclareOptions::default(),
        lp::FieldTable::default()
    ))
    .is_err());
    // ...the other one and the connection carry on.
    let q = lp::queue(&c, "survivor").await;
    lp::publish(&c, "", &q, b"still here").await;
    assert_eq!(
        lp::get(&c, &q, true).await.expect("message").delivery.data,
        b"still here"
    );
    assert!(conn.status().connected());
}

#[both_runtimes]
async fn a_channel_error_closes_only_that_channel() {
    let b = broker().await;
    let (conn, _) = rs::connect(&b).await;
    let (bad, mut bad_ev) = rs::channel(&conn).await;
    let (good, _) = rs::channel(&conn).await;
    let mut args = rs::QueueDeclareArguments::new(&unique("missing"));
    args.passive(true);
    assert!(tmo!(bad.queue_declare(args)).is_err());
    rs::assert_closed(&mut bad_ev, 404, "NOT_FOUND").await;
    // The other channel and the connection are unaffected.
    let q = rs::queue(&good, "after-soft-error").await;
    rs::publish(&good, "", &q, b"ok").await;
    let got = rs::get(&good, &q, true).await.expect("message");
    assert_eq!(got.3, b"ok");
    assert!(conn.is_open());
    // A new channel can be opened on the same connection.
    let (again, _) = rs::channel(&conn).await;
    assert_eq!(rs::counts(&again, &q).await, (0, 0));
}

#[both_runtimes]
async fn a_connection_error_closes_every_channel() {
    let b = broker().await;
    let conn = lp::connect(&b).await;
    let mut conn_errors = lp::watch_conn_errors(&conn);
    let other = lp::channel(&conn).await;
    let ch = lp::channel(&conn).await;
    // An unknown exchange type is a connection-level error in RabbitMQ
    // (503 COMMAND_INVALID), not a channel-level one.
    let res = tmo!(ch.exchange_declare(
        &unique("weird"),
        lp::ExchangeKind::Custom("no-such-type".into()),
        lp::ExchangeDeclareOptions::default(),
        lp::FieldTable::default(),
    ));
    lp::assert_err(res, 503, "COMMAND_INVALID");
    let err = tmo!(conn_errors.recv()).expect("connection error reported");
    let (code, text) = lp::code(&err);
    assert_eq!(code, 503);
    assert_text_prefix(&text, "COMMAND_INVALID");
    assert!(!conn.status().connected());
    assert!(tmo!(other.queue_declare(
        "",
        lp::QueueDeclareOptions::default(),
        lp::FieldTable::default()
    ))
    .is_err());
}

#[both_runtimes]
async fn lapin_bad_password_gets_403_access_refused() {
    let b = broker().await;
    let url = b.url_with("guest", "not-the-password", "%2f");
    let res = tmo!(lp::Connection::connect(
        &url,
        lp::ConnectionProperties::default()
    ));
    // lapin announces authentication_failure_close, so RabbitMQ says why:
    // "ACCESS_REFUSED - Login was refused using authentication mechanism PLAIN. ..."
    lp::assert_err(res, 403, "ACCESS_REFUSED");
}

#[both_runtimes]
async fn lapin_unknown_user_gets_403_access_refused() {
    let b = broker().await;
    let url = b.url_with(&unique("nobody"), "guest", "%2f");
    let res = tmo!(lp::Connection::connect(
        &url,
        lp::ConnectionProperties::default()
    ));
    lp::assert_err(res, 403, "ACCESS_REFUSED");
}

#[both_runtimes]
async fn amqprs_bad_password_is_refused() {
    let b = broker().await;
    let args = rs::OpenConnectionArguments::new(b.host(), b.port(), "guest", "wrong");
    // amqprs does not announce authentication_failure_close, so RabbitMQ
    // closes the socket without a connection.close: all the client sees is
    // that the connection could not be opened.
    let res = tmo!(rs::Connection::open(&args));
    assert!(res.is_err(), "login with a bad password must fail");
    // The broker still accepts good credentials afterwards.
    let (conn, _) = rs::connect(&b).await;
    tmo!(conn.close()).expect("close");
}

#[both_runtimes]
async fn lapin_unknown_vhost_gets_530_not_allowed() {
    let b = broker().await;
    let url = b.url_with("guest", "guest", &unique("no-such-vhost"));
    let res = tmo!(lp::Connection::connect(
        &url,
        lp::ConnectionProperties::default()
    ));
    // Note: RabbitMQ answers 530 NOT_ALLOWED ("NOT_ALLOWED - vhost ... not
    // found"), not 402 INVALID_PATH.
    lp::assert_err(res, 530, "NOT_ALLOWED");
}

#[both_runtimes]
async fn amqprs_unknown_vhost_is_refused_with_530() {
    let b = broker().await;
    let vhost = unique("no-such-vhost");
    let mut args = rs::args(&b);
    args.virtual_host(&vhost);
    let err = match tmo!(rs::Connection::open(&args)) {
        Ok(_) => panic!("opening an unknown vhost must fail"),
        Err(e) => e.to_string(),
    };
    assert!(
        err.contains("530") && err.contains("NOT_ALLOWED"),
        "error should carry 530 NOT_ALLOWED: {err}"
    );
}

#[both_runtimes]
async fn closing_a_connection_drops_its_exclusive_queues() {
    let b = broker().await;
    let (owner, och) = lp::open(&b).await;
    let q = unique("exclusive-dropped");
    tmo!(och.queue_declare(
        &q,
        lp::QueueDeclareOptions {
            exclusive: true,
            ..Default::default()
        },
        lp::FieldTable::default()
    ))
    .expect("declare");
    tmo!(owner.close(200, "bye")).expect("close");
    let (_conn, ch) = lp::open(&b).await;
    let res = tmo!(ch.queue_declare(
        &q,
        lp::QueueDeclareOptions {
            passive: true,
            ..Default::default()
        },
        lp::FieldTable::default()
    ));
    lp::assert_err(res, 404, "NOT_FOUND");
}

#[both_runtimes]
async fn many_connections_at_once() {
    let b = broker().await;
    let mut tasks = Vec::new();
    for i in 0..10 {
        let url = b.url().to_owned();
        tasks.push(tokio::spawn(async move {
            let conn = lapin::Connection::connect(&url, lapin::ConnectionProperties::default())
                .await
                .expect("connect");
            let ch = conn.create_channel().await.expect("channel");
            let q = ch
                .queue_declare(
                    "",
                    lapin::options::QueueDeclareOptions {
                        exclusive: true,
                        ..Default::default()
                    },
                    lapin::types::FieldTable::default(),
                )
                .await
                .expect("declare");
            let body = format!("conn {i}");
            ch.basic_publish(
                "",
                q.name().as_str(),
                lapin::options::BasicPublishOptions::default(),
                body.as_bytes(),
                lapin::BasicProperties::default(),
            )
            .await
            .expect("publish");
            let got = ch
                .basic_get(
                    q.name().as_str(),
                    lapin::options::BasicGetOptions { no_ack: true },
                )
                .await
                .expect("get")
                .expect("message");
            assert_eq!(got.delivery.data, body.as_bytes());
            conn.close(200, "bye").await.expect("close");
        }));
    }
    for t in tasks {
        tmo!(t).expect("task");
    }
}
