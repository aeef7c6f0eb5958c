//! RabbitMQ's user limits (issue 14): `max-connections` counts a user's
//! connections in every vhost, `max-channels` their channels across all
//! their connections; over either, 530 NOT_ALLOWED with RabbitMQ's text
//! (taken from RabbitMQ 3.10 with `rabbitmqctl set_user_limits` and pika),
//! and places come back when channels and connections close. Users without
//! limits are not limited.

#[macro_use]
mod common;

use common::*;
use leveret_broker::{Broker, Permission, UserLimits};

fn url(handle: &leveret_broker::BrokerHandle, user: &str, password: &str) -> String {
    format!("amqp://{user}:{password}@{}/%2f", handle.local_addrs()[0])
}

async fn connect(url: &str) -> lapin::Result<lp::Connection> {
    tmo!(lp::Connection::connect(
        url,
        lp::ConnectionProperties::default()
    ))
}

#[both_runtimes]
async fn a_users_connections_and_channels_are_limited_across_connections() {
    let handle = Broker::builder()
        .listen("127.0.0.1:0".parse().expect("addr"))
        .user("lim", "pw")
        .user("free", "pw")
        .permission("lim", "/", Permission::full())
        .permission("free", "/", Permission::full())
        .user_limits(
            "lim",
            UserLimits {
                max_connections: Some(2),
                max_channels: Some(3),
            },
        )
        .start()
        .await
        .expect("broker starts");
    let lim = url(&handle, "lim", "pw");
    let first = connect(&lim).await.expect("first connection");
    let second = connect(&lim).await.expect("second connection");
    lp::assert_err(
        connect(&lim).await,
        530,
        "NOT_ALLOWED - connection refused for user 'lim': user connection limit (2) is reached",
    );

    let a = tmo!(first.create_channel()).expect("channel 1");
    let _b = tmo!(first.create_channel()).expect("channel 2");
    let _c = tmo!(second.create_channel()).expect("channel 3, on the other connection");
    tmo!(a.close(200, "done")).expect("close channel 1");
    let _d = tmo!(second.create_channel()).expect("a closed channel gave its place back");
    lp::assert_err(
        tmo!(second.create_channel()),
        530,
        "NOT_ALLOWED - number of channels opened for user 'lim' has reached the maximum allowed user limit of (3)",
    );
    // The channel limit closed `second`: its connection and channels are
    // given back once the broker has finished closing it (after the
    // client's close-ok, which lapin sends as it reports the error).
    let deadline = tokio::time::Instant::now() + std::time::Duration::from_secs(10);
    let third = loop {
        match connect(&lim).await {
            Ok(third) => break third,
            Err(e) => {
                assert!(
                    tokio::time::Instant::now() < deadline,
                    "a connection closed: {e:?}"
                );
                tokio::time::sleep(std::time::Duration::from_millis(10)).await;
            }
        }
    };
    let _e = tmo!(third.create_channel()).expect("its channels went with it");

    let free = url(&handle, "free", "pw");
    let mut unlimited = Vec::new();
    for _ in 0..4 {
        let conn = connect(&free).await.expect("no connection limit");
        for _ in 0..4 {
            tmo!(conn.create_channel()).expect("no channel limit");
        }
        unlimited.push(conn);
    }
    handle.shutdown().await;
}
