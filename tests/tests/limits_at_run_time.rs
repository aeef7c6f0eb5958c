//! Vhost and user limits set at run time (issue 31), through
//! [`leveret_broker::Admin`] as the API and leveretctl set them: they
//! apply from the next connection.open, channel.open or queue.declare
//! with RabbitMQ's codes and texts, count what was already open, hold
//! under concurrent attempts (never one admitted over the limit), and last
//! across a restart until cleared; deleting a user takes their limits.

#[macro_use]
mod common;

use common::*;
use leveret_broker::store::MemoryStore;
use leveret_broker::{Admin, Broker, BrokerHandle, Permission, UserLimits, VhostLimits};
use std::sync::Arc;

async fn start(store: &Arc<MemoryStore>) -> BrokerHandle {
    Broker::builder()
        .listen("127.0.0.1:0".parse().expect("addr"))
        .store(store.clone())
        .start()
        .await
        .expect("broker starts")
}

fn url(handle: &BrokerHandle, user: &str, vhost: &str) -> String {
    format!("amqp://{user}:pw@{}/{vhost}", handle.local_addrs()[0])
}

async fn connect(url: &str) -> lapin::Result<lp::Connection> {
    tmo!(lp::Connection::connect(
        url,
        lp::ConnectionProperties::default()
    ))
}

async fn user(admin: &Admin, name: &str, vhost: &str) {
    admin
        .put_user(
            name,
            leveret_broker::User {
                password_hash: leveret_broker::PasswordHash::new("pw"),
                tags: vec![],
            },
        )
        .await
        .expect("user");
    admin
        .set_permission(name, vhost, Permission::full())
        .await
        .expect("permission");
}

/// Connections attempted at once against a vhost limit of [`ADMITTED`].
const ATTEMPTS: usize = 100;
const ADMITTED: usize = 10;

#[both_runtimes]
async fn concurrent_connections_never_pass_a_vhost_limit_set_at_run_time() {
    let store = Arc::new(MemoryStore::default());
    let broker = start(&store).await;
    let admin = broker.admin();
    admin.add_vhost("capped").await.expect("vhost");
    user(&admin, "racer", "capped").await;
    let limits = VhostLimits::default()
        .with("max-connections", ADMITTED as i64)
        .expect("known");
    admin
        .set_vhost_limits("capped", limits)
        .await
        .expect("limits");
    let target = url(&broker, "racer", "capped");
    let attempts: Vec<_> = (0..ATTEMPTS)
        .map(|_| {
            let target = target.clone();
            tokio::spawn(async move { connect(&target).await })
        })
        .collect();
    let (mut open, mut refused) = (Vec::new(), 0);
    for attempt in attempts {
        match tmo!(attempt).expect("task") {
            Ok(connection) => open.push(connection),
            Err(e) => {
                let (code, text) = lp::code(&e);
                assert_eq!(code, 530, "{text}");
                assert_eq!(
                    text,
                    "NOT_ALLOWED - access to vhost 'capped' refused for user 'racer': connection limit (10) is reached"
                );
                refused += 1;
            }
        }
    }
    assert_eq!((open.len(), refused), (ADMITTED, ATTEMPTS - ADMITTED));
    // Cleared: the next one is admitted.
    admin.clear_vhost_limits("capped").await.expect("cleared");
    open.push(connect(&target).await.expect("no limit any more"));
    drop(open);
    broker.shutdown().await;
}

#[both_runtimes]
async fn concurrent_connections_never_pass_a_user_limit_set_at_run_time() {
    let store = Arc::new(MemoryStore::default());
    let broker = start(&store).await;
    let admin = broker.admin();
    user(&admin, "swarm", "/").await;
    let limits = UserLimits::default()
        .with("max-connections", ADMITTED as i64)
        .expect("known");
    admin
        .set_user_limits("swarm", limits)
        .await
        .expect("limits");
    let target = url(&broker, "swarm", "%2f");
    let attempts: Vec<_> = (0..ATTEMPTS)
        .map(|_| {
            let target = target.clone();
            tokio::spawn(async move { connect(&target).await })
        })
        .collect();
    let (mut open, mut refused) = (Vec::new(), 0);
    for attempt in attempts {
        match tmo!(attempt).expect("task") {
            Ok(connection) => open.push(connection),
            Err(e) => {
                assert_eq!(
                    lp::code(&e),
                    (
                        530,
                        "NOT_ALLOWED - connection refused for user 'swarm': user connection limit (10) is reached".to_owned()
                    )
                );
                refused += 1;
            }
        }
    }
    assert_eq!((open.len(), refused), (ADMITTED, ATTEMPTS - ADMITTED));
    drop(open);
    broker.shutdown().await;
}

#[both_runtimes]
async fn concurrent_declares_never_pass_max_queues() {
    let store = Arc::new(MemoryStore::default());
    let broker = start(&store).await;
    let admin = broker.admin();
    admin.add_vhost("few").await.expect("vhost");
    user(&admin, "decl", "few").await;
    let limits = VhostLimits::default()
        .with("max-queues", 10)
        .expect("known");
    admin.set_vhost_limits("few", limits).await.expect("limits");
    let connection = connect(&url(&broker, "decl", "few"))
        .await
        .expect("connects");
    let mut declares = Vec::new();
    for i in 0..40 {
        let channel = lp::channel(&connection).await;
        declares.push(tokio::spawn(async move {
            channel
                .queue_declare(
                    &format!("q{i}"),
                    lp::QueueDeclareOptions::default(),
                    lp::FieldTable::default(),
                )
                .await
        }));
    }
    let mut created = 0;
    for declare in declares {
        match tmo!(declare).expect("task") {
            Ok(_) => created += 1,
            Err(e) => {
                let (code, text) = lp::code(&e);
                assert_eq!(code, 406, "{text}");
                assert!(
                    text.ends_with("queue limit in vhost 'few' (10) is reached"),
                    "{text}"
                );
            }
        }
    }
    assert_eq!(created, 10);
    assert_eq!(
        admin.queues().iter().filter(|q| q.vhost == "few").count(),
        10
    );
    broker.shutdown().await;
}

#[both_runtimes]
async fn user_limits_set_at_run_time_count_what_is_open_and_last() {
    let store = Arc::new(MemoryStore::default());
    let broker = start(&store).await;
    let admin = broker.admin();
    user(&admin, "robot", "/").await;
    let target = url(&broker, "robot", "%2f");
    let connection = connect(&target).await.expect("connects");
    let _channels = [
        lp::channel(&connection).await,
        lp::channel(&connection).await,
    ];
    let limits = UserLimits::default()
        .with("max-channels", 2)
        .and_then(|l| l.with("max-connections", 2))
        .expect("known");
    admin.set_user_limits("robot", limits).await.expect("set");
    let second = connect(&target).await.expect("a second connection");
    lp::assert_err(
        connect(&target).await,
        530,
        "NOT_ALLOWED - connection refused for user 'robot': user connection limit (2) is reached",
    );
    lp::assert_err(
        tmo!(second.create_channel()),
        530,
        "NOT_ALLOWED - number of channels opened for user 'robot' has reached the maximum allowed user limit of (2)",
    );
    drop(connection);
    broker.shutdown().await;

    // Still set after a restart; cleared by deleting the user.
    let broker = start(&store).await;
    let admin = broker.admin();
    assert_eq!(admin.user_limits("robot"), Some(limits));
    assert_eq!(
        admin.all_vhost_limits().len(),
        0,
        "no vhost limits were set"
    );
    assert_eq!(admin.delete_user("robot").await, Ok(true));
    assert_eq!(admin.user_limits("robot"), None);
    broker.shutdown().await;
    let broker = start(&store).await;
    let admin = broker.admin();
    user(&admin, "robot", "/").await;
    assert_eq!(admin.user_limits("robot"), None, "gone with the user");
    broker.shutdown().await;
}
