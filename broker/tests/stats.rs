//! The embedding API's figures (`BrokerHandle::overview`, `queues`, and the
//! `Admin` listings) against traffic from a real client (lapin), on both
//! runtime flavours: counters move with RabbitMQ's meanings, gauges come
//! back down, and a connection closed through `Admin` gets 320.

use lapin::options::{
    BasicAckOptions, BasicConsumeOptions, BasicGetOptions, BasicNackOptions, BasicPublishOptions,
    BasicQosOptions, ConfirmSelectOptions, QueueDeclareOptions,
};
use lapin::types::FieldTable;
use lapin::{BasicProperties, Connection, ConnectionProperties};
use leveret_broker::{Admin, Broker, BrokerHandle, Overview};
use std::future::Future;
use std::time::Duration;

const WAIT: Duration = Duration::from_secs(10);

async fn tmo<T>(what: &str, future: impl Future<Output = T>) -> T {
    tokio::time::timeout(WAIT, future)
        .await
        .unwrap_or_else(|_| panic!("timed out: {what}"))
}

async fn start() -> (BrokerHandle, String) {
    let handle = Broker::builder()
        .listen("127.0.0.1:0".parse().unwrap())
        .start()
        .await
        .expect("broker starts");
    let url = format!("amqp://guest:guest@{}/%2f", handle.local_addrs()[0]);
    (handle, url)
}

/// Polls `admin.overview()` until `done` holds (events reach the broker
/// asynchronously), or fails with the last overview.
async fn overview_until(admin: &Admin, done: impl Fn(&Overview) -> bool) -> Overview {
    let deadline = tokio::time::Instant::now() + WAIT;
    loop {
        let overview = admin.overview();
        if done(&overview) {
            return overview;
        }
        assert!(
            tokio::time::Instant::now() < deadline,
            "condition never held: {overview:#?}"
        );
        tokio::time::sleep(Duration::from_millis(5)).await;
    }
}

async fn counters_follow_traffic() {
    let (handle, url) = start().await;
    let admin = handle.admin();
    let before = handle.overview();
    assert_eq!(before.object_totals.connections, 0);
    assert_eq!(
        before.object_totals.exchanges, 6,
        "the default and amq.* ones"
    );
    assert_eq!(before.message_stats.received, 0);
    assert_eq!(before.busy_poll, None, "not asked for");

    let conn = tmo(
        "connect",
        Connection::connect(&url, ConnectionProperties::default()),
    )
    .await
    .unwrap();
    let ch = tmo("channel", conn.create_channel()).await.unwrap();
    tmo(
        "confirm.select",
        ch.confirm_select(ConfirmSelectOptions::default()),
    )
    .await
    .unwrap();
    tmo(
        "declare",
        ch.queue_declare(
            "depth",
            QueueDeclareOptions::default(),
            FieldTable::default(),
        ),
    )
    .await
    .unwrap();
    tmo(
        "redeclare",
        ch.queue_declare(
            "depth",
            QueueDeclareOptions::default(),
            FieldTable::default(),
        ),
    )
    .await
    .unwrap();
    let publish = |key: &'static str, mandatory: bool| {
        let ch = ch.clone();
        async move {
            let options = BasicPublishOptions {
                mandatory,
                ..Default::default()
            };
            ch.basic_publish("", key, options, b"hello", BasicProperties::default())
                .await
                .unwrap()
                .await
                .unwrap()
        }
    };
    for _ in 0..5 {
        tmo("publish", publish("depth", false)).await;
    }
    tmo("unroutable mandatory", publish("nowhere", true)).await;
    tmo("unroutable", publish("nowhere", false)).await;

    let queues = handle.queues();
    assert_eq!(queues.len(), 1);
    let q = &queues[0];
    assert_eq!((q.vhost.as_str(), q.name.as_str()), ("/", "depth"));
    assert_eq!((q.messages_ready, q.messages_unacknowledged), (5, 0));
    assert_eq!(q.message_bytes_ready, 25);
    assert_eq!(q.message_stats.publish, 5);

    let o = handle.overview();
    let m = o.message_stats;
    assert_eq!((m.received, m.received_confirm), (7, 7));
    assert_eq!(
        (m.routed, m.unroutable_returned, m.unroutable_dropped),
        (5, 1, 1)
    );
    assert_eq!(m.confirmed, 7, "unroutable messages are confirmed too");
    assert_eq!(o.churn.queues_declared, 2);
    assert_eq!(o.churn.queues_created, 1);
    assert_eq!(
        (o.object_totals.connections, o.object_totals.channels),
        (1, 1)
    );
    assert_eq!(o.object_totals.queues, 1);
    assert_eq!(o.publishers, 1);
    assert_eq!(o.queue_totals.messages(), 5);

    // Two to a manual-ack consumer (prefetch 2), then one requeued and
    // redelivered, one acked (which lets a third through).
    let consumer_channel = tmo("channel", conn.create_channel()).await.unwrap();
    tmo(
        "qos",
        consumer_channel.basic_qos(2, BasicQosOptions::default()),
    )
    .await
    .unwrap();
    let mut consumer = tmo(
        "consume",
        consumer_channel.basic_consume(
            "depth",
            "watcher",
            BasicConsumeOptions::default(),
            FieldTable::default(),
        ),
    )
    .await
    .unwrap();
    use futures_lite::StreamExt;
    let first = tmo("delivery", consumer.next()).await.unwrap().unwrap();
    let second = tmo("delivery", consumer.next()).await.unwrap().unwrap();
    let q = &handle.queues()[0];
    assert_eq!((q.messages_ready, q.messages_unacknowledged), (3, 2));
    assert_eq!(q.consumers, 1);
    let consumers = admin.consumers();
    assert_eq!(consumers.len(), 1);
    assert_eq!(consumers[0].tag, "watcher");
    assert!(consumers[0].ack_required);
    assert_eq!(consumers[0].prefetch_count, 2);
    let channels = admin.channels();
    assert_eq!(channels.len(), 2);
    let consuming = channels.iter().find(|c| c.consumers == 1).unwrap();
    assert_eq!(consuming.messages_unacknowledged, 2);
    assert_eq!(consuming.prefetch_count, 2);
    assert!(channels.iter().any(|c| c.confirm && c.consumers == 0));

    tmo(
        "nack",
        first.acker.nack(BasicNackOptions {
            requeue: true,
            ..Default::default()
        }),
    )
    .await
    .unwrap();
    let again = tmo("redelivery", consumer.next()).await.unwrap().unwrap();
    assert!(again.redelivered);
    tmo("ack", second.acker.ack(BasicAckOptions::default()))
        .await
        .unwrap();
    let _third = tmo("delivery", consumer.next()).await.unwrap().unwrap();
    let o = overview_until(&admin, |o| o.message_stats.acknowledged == 1).await;
    let m = o.message_stats;
    assert_eq!(m.delivered_consume_manual_ack, 4);
    assert_eq!(m.redelivered, 1);
    assert_eq!(m.delivered(), 4);
    assert_eq!(o.object_totals.consumers, 1);

    // basic.get, with and without ack, and on an empty queue.
    let getter = tmo("channel", conn.create_channel()).await.unwrap();
    let got = tmo(
        "get",
        getter.basic_get("depth", BasicGetOptions { no_ack: true }),
    )
    .await
    .unwrap();
    assert!(got.is_some());
    let got = tmo(
        "get",
        getter.basic_get("depth", BasicGetOptions { no_ack: false }),
    )
    .await
    .unwrap();
    assert!(got.is_some());
    let none = tmo(
        "get",
        getter.basic_get("depth", BasicGetOptions { no_ack: true }),
    )
    .await
    .unwrap();
    assert!(none.is_none());
    let q = &handle.queues()[0];
    assert_eq!(q.message_stats.get_no_ack, 1);
    assert_eq!(q.message_stats.get, 1);
    assert_eq!(q.message_stats.get_empty, 1);
    assert_eq!(q.message_stats.deliver_get(), 6);
    assert_eq!((q.messages_ready, q.messages_unacknowledged), (0, 3));

    // Closing the connection requeues the unacked, drops the consumer and
    // counts the closes.
    tmo("close", conn.close(200, "bye")).await.unwrap();
    let o = overview_until(&admin, |o| o.churn.connections_closed == 1).await;
    assert_eq!(o.churn.connections_opened, 1);
    assert_eq!((o.churn.channels_opened, o.churn.channels_closed), (3, 3));
    assert_eq!(o.object_totals.consumers, 0);
    assert_eq!(o.publishers, 0);
    assert_eq!(
        (o.object_totals.connections, o.object_totals.channels),
        (0, 0)
    );
    let q = &handle.queues()[0];
    assert_eq!((q.messages_ready, q.messages_unacknowledged), (3, 0));
    handle.shutdown().await;
}

#[tokio::test(flavor = "current_thread")]
async fn counters_follow_traffic_current_thread() {
    counters_follow_traffic().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn counters_follow_traffic_multi_thread() {
    counters_follow_traffic().await;
}

#[tokio::test]
async fn a_connection_closed_through_admin_gets_320_with_the_reason() {
    let (handle, url) = start().await;
    let admin = handle.admin();
    let conn = tmo(
        "connect",
        Connection::connect(&url, ConnectionProperties::default()),
    )
    .await
    .unwrap();
    let listed = admin.connections();
    assert_eq!(listed.len(), 1);
    assert_eq!(listed[0].user, "guest");
    assert_eq!(listed[0].vhost, "/");
    assert!(listed[0].client_properties.get("product").is_some());
    assert_eq!(admin.connection(listed[0].id), Some(listed[0].clone()));
    assert!(!admin.close_connection(listed[0].id + 100, "nobody"));
    assert!(admin.close_connection(listed[0].id, "Closed via management plugin"));
    let deadline = tokio::time::Instant::now() + WAIT;
    while conn.status().connected() {
        assert!(tokio::time::Instant::now() < deadline, "still connected");
        tokio::time::sleep(Duration::from_millis(5)).await;
    }
    overview_until(&admin, |o| o.churn.connections_closed == 1).await;
    assert!(admin.connections().is_empty());
    // The broker itself keeps serving.
    let again = tmo(
        "reconnect",
        Connection::connect(&url, ConnectionProperties::default()),
    )
    .await
    .unwrap();
    assert!(again.status().connected());
    handle.shutdown().await;
}

#[tokio::test]
async fn deleting_queues_counts_and_drops_their_consumers() {
    let (handle, url) = start().await;
    let admin = handle.admin();
    let conn = tmo(
        "connect",
        Connection::connect(&url, ConnectionProperties::default()),
    )
    .await
    .unwrap();
    let ch = tmo("channel", conn.create_channel()).await.unwrap();
    let exclusive = QueueDeclareOptions {
        exclusive: true,
        ..Default::default()
    };
    tmo(
        "declare",
        ch.queue_declare("mine", exclusive, FieldTable::default()),
    )
    .await
    .unwrap();
    tmo(
        "consume",
        ch.basic_consume(
            "mine",
            "",
            BasicConsumeOptions::default(),
            FieldTable::default(),
        ),
    )
    .await
    .unwrap();
    assert_eq!(handle.overview().object_totals.consumers, 1);
    assert!(handle.queues()[0].exclusive_owner.is_some());
    drop(ch);
    tmo("close", conn.close(200, "bye")).await.unwrap();
    let o = overview_until(&admin, |o| o.churn.queues_deleted == 1).await;
    assert_eq!(o.object_totals.consumers, 0);
    assert_eq!(o.object_totals.queues, 0);
    handle.shutdown().await;
}
