//! Deleting a vhost (issue 31): its connections are closed with RabbitMQ's
//! 320 CONNECTION_FORCED "vhost 'NAME' is deleted", connection.open to it
//! is then refused as to any unknown vhost, and its queues, messages,
//! exchanges, bindings, permissions, topic permissions and runtime
//! parameters are gone, after a restart too; other vhosts are untouched.
//! The adversarial case deletes a vhost while its publishers publish as
//! fast as they can.

#[macro_use]
mod common;

use common::*;
use leveret_broker::store::MemoryStore;
use leveret_broker::{
    Admin, Broker, BrokerHandle, ExchangeSettings, Permission, QueueSettings, TopicPermission,
};
use std::sync::Arc;

const DOOMED: &str = "doomed";

async fn start(store: &Arc<MemoryStore>) -> BrokerHandle {
    Broker::builder()
        .listen("127.0.0.1:0".parse().expect("addr"))
        .store(store.clone())
        .start()
        .await
        .expect("broker starts")
}

fn url(handle: &BrokerHandle, vhost: &str) -> String {
    format!("amqp://guest:guest@{}/{vhost}", handle.local_addrs()[0])
}

async fn connect(url: &str) -> lapin::Result<lp::Connection> {
    tmo!(lp::Connection::connect(
        url,
        lp::ConnectionProperties::default()
    ))
}

/// The vhost, with guest allowed in and something of every kind in it.
async fn populate(admin: &Admin) {
    assert_eq!(admin.add_vhost(DOOMED).await, Ok(true));
    admin
        .set_permission("guest", DOOMED, Permission::full())
        .await
        .expect("permission");
    admin
        .set_topic_permission(
            "guest",
            DOOMED,
            "amq.topic",
            TopicPermission {
                write: ".*".into(),
                read: ".*".into(),
            },
        )
        .await
        .expect("topic permission");
    admin
        .set_parameter("shovel", DOOMED, "up", "{}".into())
        .await
        .expect("parameter");
    let durable = QueueSettings {
        durable: true,
        ..Default::default()
    };
    admin
        .declare_queue(DOOMED, "kept", durable)
        .await
        .expect("queue");
    admin
        .declare_exchange(
            DOOMED,
            "x",
            ExchangeSettings {
                kind: "topic".into(),
                durable: true,
                ..Default::default()
            },
        )
        .await
        .expect("exchange");
}

fn left_in(admin: &Admin, vhost: &str) -> (usize, usize, usize, usize, usize) {
    (
        admin.queues().iter().filter(|q| q.vhost == vhost).count(),
        admin
            .exchanges()
            .iter()
            .filter(|e| e.vhost == vhost)
            .count(),
        admin.bindings().iter().filter(|b| b.vhost == vhost).count(),
        admin.permissions().iter().filter(|p| p.1 == vhost).count()
            + admin
                .topic_permissions()
                .iter()
                .filter(|p| p.1 == vhost)
                .count(),
        admin
            .parameters("shovel")
            .iter()
            .filter(|p| p.0 == vhost)
            .count(),
    )
}

#[both_runtimes]
async fn deleting_a_vhost_closes_its_connections_and_forgets_everything_in_it() {
    let store = Arc::new(MemoryStore::default());
    let broker = start(&store).await;
    let admin = broker.admin();
    populate(&admin).await;

    let inside = connect(&url(&broker, DOOMED)).await.expect("connects");
    let mut closed = lp::watch_conn_errors(&inside);
    let channel = lp::channel(&inside).await;
    tmo!(channel.confirm_select(lp::ConfirmSelectOptions::default())).expect("confirms");
    tmo!(channel.queue_bind(
        "kept",
        "x",
        "a.#",
        lp::QueueBindOptions::default(),
        lp::FieldTable::default()
    ))
    .expect("bind");
    let persistent = lp::BasicProperties::default().with_delivery_mode(2);
    for _ in 0..10 {
        tmo!(tmo!(channel.basic_publish(
            "x",
            "a.b",
            lp::BasicPublishOptions::default(),
            b"m",
            persistent.clone()
        ))
        .expect("publish"))
        .expect("confirmed");
    }
    // Beside it, the default vhost with a message of its own.
    let outside = connect(&url(&broker, "%2f")).await.expect("connects");
    let other = lp::channel(&outside).await;
    let bystander = lp::queue(&other, "bystander").await;
    lp::publish(&other, "", &bystander, b"still here").await;
    assert_eq!(
        left_in(&admin, DOOMED),
        (1, 7, 2, 2, 1),
        "populated (the default binding listed too)"
    );

    assert_eq!(admin.delete_vhost(DOOMED).await, Ok(true));
    let error = tmo!(closed.recv()).expect("the connection is closed");
    let (code, text) = lp::code(&error);
    assert_eq!(
        (code, text.as_str()),
        (320, "CONNECTION_FORCED - vhost 'doomed' is deleted")
    );
    lp::assert_err(
        connect(&url(&broker, DOOMED)).await,
        530,
        "NOT_ALLOWED - vhost doomed not found",
    );
    assert!(!admin.vhosts().contains(&DOOMED.to_owned()));
    assert_eq!(left_in(&admin, DOOMED), (0, 0, 0, 0, 0));
    assert_eq!(admin.delete_vhost(DOOMED).await, Ok(false), "gone already");
    let got = lp::get(&other, &bystander, true).await.expect("message");
    assert_eq!(
        &got.delivery.data[..],
        b"still here",
        "other vhosts untouched"
    );
    drop(outside);
    broker.shutdown().await;

    // Nothing of it comes back at the next start, and a vhost of the same
    // name is a new, empty one that guest may not open.
    let broker = start(&store).await;
    let admin = broker.admin();
    assert!(!admin.vhosts().contains(&DOOMED.to_owned()));
    assert_eq!(left_in(&admin, DOOMED), (0, 0, 0, 0, 0));
    assert_eq!(admin.add_vhost(DOOMED).await, Ok(true));
    assert_eq!(
        left_in(&admin, DOOMED),
        (0, 6, 0, 0, 0),
        "the predefined exchanges only"
    );
    lp::assert_err(
        connect(&url(&broker, DOOMED)).await,
        530,
        "NOT_ALLOWED - access to vhost 'doomed' refused for user 'guest'",
    );
    broker.shutdown().await;
}

/// Publishers on this many connections publish into the vhost until it is
/// deleted.
const PUBLISHERS: usize = 4;
/// Queues each publish reaches (through a fanout).
const FANOUT_QUEUES: usize = 200;

#[both_runtimes]
async fn deleting_a_vhost_under_heavy_publishing_closes_every_publisher() {
    let store = Arc::new(MemoryStore::default());
    let broker = start(&store).await;
    let admin = broker.admin();
    populate(&admin).await;
    admin
        .declare_exchange(
            DOOMED,
            "fan",
            ExchangeSettings {
                kind: "fanout".into(),
                durable: true,
                ..Default::default()
            },
        )
        .await
        .expect("fanout");
    for i in 0..FANOUT_QUEUES {
        let queue = format!("q{i}");
        admin
            .declare_queue(
                DOOMED,
                &queue,
                QueueSettings {
                    durable: i % 2 == 0,
                    ..Default::default()
                },
            )
            .await
            .expect("queue");
        admin
            .bind(
                DOOMED,
                leveret_broker::BindingSpec {
                    source: "fan".into(),
                    destination: queue,
                    destination_kind: leveret_broker::DestinationKind::Queue,
                    routing_key: String::new(),
                    arguments: Default::default(),
                },
            )
            .await
            .expect("bind");
    }
    let mut publishers = Vec::new();
    let (started_tx, mut started) = tokio::sync::mpsc::unbounded_channel();
    for _ in 0..PUBLISHERS {
        let connection = connect(&url(&broker, DOOMED)).await.expect("connects");
        let started_tx = started_tx.clone();
        publishers.push(tokio::spawn(async move {
            let channel = connection.create_channel().await.expect("channel");
            let persistent = lp::BasicProperties::default().with_delivery_mode(2);
            let mut sent = 0u64;
            loop {
                // Publishes until the connection is closed under it.
                let published = channel
                    .basic_publish(
                        "fan",
                        "",
                        lp::BasicPublishOptions::default(),
                        b"payload",
                        persistent.clone(),
                    )
                    .await;
                if published.is_err() || !connection.status().connected() {
                    return sent;
                }
                sent += 1;
                if sent == 100 {
                    let _ = started_tx.send(());
                }
                if sent % 64 == 0 {
                    tokio::task::yield_now().await;
                }
            }
        }));
    }
    for _ in 0..PUBLISHERS {
        tmo!(started.recv()).expect("publishing");
    }
    assert_eq!(admin.delete_vhost(DOOMED).await, Ok(true));
    for publisher in publishers {
        let sent = tmo!(publisher).expect("publisher task");
        assert!(sent >= 100, "each published before the deletion");
    }
    assert_eq!(left_in(&admin, DOOMED), (0, 0, 0, 0, 0));
    // The deletion tells the connections to close and does not wait for
    // them: a client sees its connection closed before the broker's side
    // has finished (flushed, been unlisted), so the listing empties soon
    // after, not at once.
    within("the doomed vhost's connections unlisted", async {
        while admin.connections().iter().any(|c| c.vhost == DOOMED) {
            tokio::time::sleep(std::time::Duration::from_millis(5)).await;
        }
    })
    .await;
    // The broker still serves.
    let outside = connect(&url(&broker, "%2f")).await.expect("connects");
    let channel = lp::channel(&outside).await;
    let queue = lp::queue(&channel, "after").await;
    lp::publish(&channel, "", &queue, b"served").await;
    assert!(lp::get(&channel, &queue, true).await.is_some());
    drop(outside);
    broker.shutdown().await;
    let broker = start(&store).await;
    let admin = broker.admin();
    assert!(!admin.vhosts().contains(&DOOMED.to_owned()));
    assert_eq!(left_in(&admin, DOOMED), (0, 0, 0, 0, 0));
    broker.shutdown().await;
}
