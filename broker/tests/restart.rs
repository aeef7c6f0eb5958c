//! An embedded broker restarted in the same process: `shutdown` releases
//! the data directory, so a new broker opens it at once and finds the
//! durable state.
#![cfg(feature = "persistence")]

use lapin::options::{
    BasicGetOptions, BasicPublishOptions, BasicRejectOptions, ConfirmSelectOptions,
    ExchangeDeclareOptions, QueueBindOptions, QueueDeclareOptions,
};
use lapin::types::{AMQPValue, FieldTable};
use lapin::{BasicProperties, Connection, ConnectionProperties, ExchangeKind};
use leveret_test_macros::both_runtimes;

async fn start(dir: &std::path::Path) -> leveret_broker::BrokerHandle {
    leveret_broker::Broker::builder()
        .listen("127.0.0.1:0".parse().expect("addr"))
        .data_dir(dir)
        .start()
        .await
        .expect("start on the data directory")
}

#[both_runtimes]
async fn shutdown_releases_the_data_directory_for_an_immediate_restart() {
    // One directory per runtime flavour: both variants run at once.
    let flavor = tokio::runtime::Handle::current().runtime_flavor();
    let dir =
        std::env::temp_dir().join(format!("leveret-restart-{}-{flavor:?}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    let durable = QueueDeclareOptions {
        durable: true,
        ..Default::default()
    };
    for round in 0..3u8 {
        let handle = start(&dir).await;
        let url = format!("amqp://guest:guest@{}/%2f", handle.local_addrs()[0]);
        let conn = Connection::connect(&url, ConnectionProperties::default())
            .await
            .expect("connect");
        let channel = conn.create_channel().await.expect("channel");
        channel
            .queue_declare("kept", durable, FieldTable::default())
            .await
            .expect("declare");
        if round > 0 {
            let got = channel
                .basic_get("kept", BasicGetOptions { no_ack: true })
                .await
                .expect("get")
                .expect("the message from the previous round");
            assert_eq!(got.delivery.data, [round - 1]);
        }
        channel
            .confirm_select(ConfirmSelectOptions::default())
            .await
            .expect("confirms");
        let confirm = channel
            .basic_publish(
                "",
                "kept",
                BasicPublishOptions::default(),
                &[round],
                BasicProperties::default().with_delivery_mode(2),
            )
            .await
            .expect("publish")
            .await
            .expect("confirm");
        assert!(confirm.is_ack());
        // No waiting: the next round opens the directory right away.
        handle.shutdown().await;
    }
    let _ = std::fs::remove_dir_all(&dir);
}

/// A persistent message dead-lettered into durable queues is on disk there
/// like a published one: after a restart it is in the dead-letter queues
/// (one target: stored inline; two: one shared record), and gone from the
/// queue it died in.
#[both_runtimes]
async fn dead_lettered_persistent_messages_survive_a_restart() {
    let flavor = tokio::runtime::Handle::current().runtime_flavor();
    let dir = std::env::temp_dir().join(format!(
        "leveret-restart-dlx-{}-{flavor:?}",
        std::process::id()
    ));
    let _ = std::fs::remove_dir_all(&dir);
    let durable = QueueDeclareOptions {
        durable: true,
        ..Default::default()
    };
    let text = |s: &str| AMQPValue::LongString(s.into());
    let sources = [
        // Through the default exchange into one durable queue.
        (
            "to-one",
            [
                ("x-dead-letter-exchange", text("")),
                ("x-dead-letter-routing-key", text("dead-one")),
            ],
        ),
        // Through a fanout into two durable queues and a transient one.
        (
            "to-many",
            [
                ("x-dead-letter-exchange", text("dlx")),
                ("x-dead-letter-routing-key", text("any")),
            ],
        ),
    ];
    let handle = start(&dir).await;
    let url = format!("amqp://guest:guest@{}/%2f", handle.local_addrs()[0]);
    let conn = Connection::connect(&url, ConnectionProperties::default())
        .await
        .expect("connect");
    let channel = conn.create_channel().await.expect("channel");
    channel
        .exchange_declare(
            "dlx",
            ExchangeKind::Fanout,
            ExchangeDeclareOptions {
                durable: true,
                ..Default::default()
            },
            FieldTable::default(),
        )
        .await
        .expect("exchange.declare");
    for (name, durable) in [
        ("dead-one", true),
        ("dead-a", true),
        ("dead-b", true),
        ("dead-transient", false),
    ] {
        let options = QueueDeclareOptions {
            durable,
            ..Default::default()
        };
        channel
            .queue_declare(name, options, FieldTable::default())
            .await
            .expect("declare");
        if name != "dead-one" {
            channel
                .queue_bind(
                    name,
                    "dlx",
                    "",
                    QueueBindOptions::default(),
                    FieldTable::default(),
                )
                .await
                .expect("bind");
        }
    }
    channel
        .confirm_select(ConfirmSelectOptions::default())
        .await
        .expect("confirms");
    for (source, arguments) in &sources {
        let mut table = FieldTable::default();
        for (key, value) in arguments {
            table.insert((*key).into(), value.clone());
        }
        channel
            .queue_declare(source, durable, table)
            .await
            .expect("declare source");
        let confirm = channel
            .basic_publish(
                "",
                source,
                BasicPublishOptions::default(),
                source.as_bytes(),
                BasicProperties::default().with_delivery_mode(2),
            )
            .await
            .expect("publish")
            .await
            .expect("confirm");
        assert!(confirm.is_ack());
        let got = channel
            .basic_get(source, BasicGetOptions::default())
            .await
            .expect("get")
            .expect("the message");
        got.reject(BasicRejectOptions { requeue: false })
            .await
            .expect("reject");
    }
    // Wait for the dead letters to land (routing follows the reject).
    for queue in ["dead-one", "dead-a", "dead-b", "dead-transient"] {
        let passive = QueueDeclareOptions {
            passive: true,
            ..Default::default()
        };
        tokio::time::timeout(std::time::Duration::from_secs(10), async {
            while channel
                .queue_declare(queue, passive, FieldTable::default())
                .await
                .expect("passive declare")
                .message_count()
                == 0
            {
                tokio::task::yield_now().await;
            }
        })
        .await
        .expect("dead letter routed");
    }
    drop(conn);
    handle.shutdown().await;

    let handle = start(&dir).await;
    let url = format!("amqp://guest:guest@{}/%2f", handle.local_addrs()[0]);
    let conn = Connection::connect(&url, ConnectionProperties::default())
        .await
        .expect("connect");
    let channel = conn.create_channel().await.expect("channel");
    for (queue, body) in [
        ("dead-one", "to-one"),
        ("dead-a", "to-many"),
        ("dead-b", "to-many"),
    ] {
        let got = channel
            .basic_get(queue, BasicGetOptions { no_ack: true })
            .await
            .expect("get")
            .unwrap_or_else(|| panic!("the dead letter in {queue} after the restart"));
        assert_eq!(got.delivery.data, body.as_bytes(), "{queue}");
        let deaths = got
            .delivery
            .properties
            .headers()
            .as_ref()
            .and_then(|h| h.inner().get("x-death").cloned());
        assert!(deaths.is_some(), "{queue}: x-death kept");
    }
    for (source, _) in &sources {
        let left = channel
            .basic_get(source, BasicGetOptions { no_ack: true })
            .await
            .expect("get");
        assert!(left.is_none(), "{source}: the dead message is gone");
    }
    handle.shutdown().await;
    let _ = std::fs::remove_dir_all(&dir);
}

/// A durable x-consistent-hash exchange and its weighted bindings come
/// back after a restart, and a routing key goes to the same queue as
/// before.
#[both_runtimes]
async fn a_consistent_hash_exchange_survives_a_restart() {
    let flavor = tokio::runtime::Handle::current().runtime_flavor();
    let dir = std::env::temp_dir().join(format!("leveret-ring-{}-{flavor:?}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    let durable_queue = QueueDeclareOptions {
        durable: true,
        ..Default::default()
    };
    let kind = ExchangeKind::Custom("x-consistent-hash".to_owned());
    let mut owners = Vec::new();
    for round in 0..2 {
        let handle = start(&dir).await;
        let url = format!("amqp://guest:guest@{}/%2f", handle.local_addrs()[0]);
        let conn = Connection::connect(&url, ConnectionProperties::default())
            .await
            .expect("connect");
        let channel = conn.create_channel().await.expect("channel");
        if round == 0 {
            let options = ExchangeDeclareOptions {
                durable: true,
                ..Default::default()
            };
            channel
                .exchange_declare("ring", kind.clone(), options, FieldTable::default())
                .await
                .expect("declare x-consistent-hash");
            for (queue, weight) in [("ring-a", "1"), ("ring-b", "3")] {
                channel
                    .queue_declare(queue, durable_queue, FieldTable::default())
                    .await
                    .expect("queue");
                channel
                    .queue_bind(
                        queue,
                        "ring",
                        weight,
                        QueueBindOptions::default(),
                        FieldTable::default(),
                    )
                    .await
                    .expect("bind with a weight");
            }
        } else {
            let passive = ExchangeDeclareOptions {
                passive: true,
                durable: true,
                ..Default::default()
            };
            channel
                .exchange_declare("ring", kind.clone(), passive, FieldTable::default())
                .await
                .expect("recovered");
        }
        channel
            .confirm_select(ConfirmSelectOptions::default())
            .await
            .expect("confirms");
        let mut owner = Vec::new();
        for key in 0..40u8 {
            let confirm = channel
                .basic_publish(
                    "ring",
                    &format!("robot-{key}"),
                    BasicPublishOptions::default(),
                    &[key],
                    BasicProperties::default(),
                )
                .await
                .expect("publish")
                .await
                .expect("confirm");
            assert!(confirm.is_ack());
        }
        for queue in ["ring-a", "ring-b"] {
            while let Some(got) = channel
                .basic_get(queue, BasicGetOptions { no_ack: true })
                .await
                .expect("get")
            {
                owner.push((got.delivery.data[0], queue));
            }
        }
        owner.sort();
        assert_eq!(owner.len(), 40, "each message to one queue");
        owners.push(owner);
        handle.shutdown().await;
    }
    assert_eq!(owners[0], owners[1], "the same keys to the same queues");
    let _ = std::fs::remove_dir_all(&dir);
}
