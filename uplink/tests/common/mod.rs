//! Helpers shared by the uplink's integration test files (each includes
//! this module with `mod common;`): scratch directories, channels to a
//! broker over TCP or in process, durable declarations, confirmed
//! publishes of numbered messages, and waits on a shovel's status within
//! [`WAIT`], a hang limit.
#![allow(dead_code)]

use leveret_broker::BrokerHandle;
use leveret_client::{
    BasicProperties, BasicPublishOptions, Channel, Connection, FieldTable, QueueDeclareOptions,
};
use leveret_uplink::{Shovel, ShovelStatus};
use std::path::PathBuf;
use std::sync::Arc;
use std::time::Duration;

/// How long a shovel or a link may take to get where a test waits for it:
/// a hang limit for a debug build on a loaded machine.
pub const WAIT: Duration = Duration::from_secs(30);

/// An empty directory of this test's own (by process and thread), named
/// after `name`.
pub fn scratch(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!(
        "leveret-uplink-{name}-{}-{:?}",
        std::process::id(),
        std::thread::current().id()
    ));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

/// A connection to `uri` and a channel on it.
pub async fn channel_to(uri: &str) -> (Connection, Channel) {
    let connection = Connection::connect(uri).await.expect("connect");
    let channel = connection.open_channel().await.expect("channel");
    (connection, channel)
}

/// An in-process connection to `robot` and a channel on it.
pub async fn local_channel(robot: &Arc<BrokerHandle>) -> (Connection, Channel) {
    let connection = Connection::in_process(robot).await.expect("in process");
    let channel = connection.open_channel().await.expect("channel");
    (connection, channel)
}

/// Declares durable `queue` with `arguments`.
pub async fn declare(channel: &Channel, queue: &str, arguments: FieldTable) {
    let durable = QueueDeclareOptions {
        durable: true,
        ..Default::default()
    };
    channel
        .queue_declare(queue, durable, arguments)
        .await
        .expect("declare");
}

/// Publishes `from..to` (the number as the body) as persistent messages
/// to `exchange` with routing key `key`, each confirmed.
pub async fn publish_confirmed(channel: &Channel, exchange: &str, key: &str, from: u32, to: u32) {
    for n in from..to {
        let properties = BasicProperties {
            delivery_mode: Some(2),
            ..Default::default()
        };
        let confirm = channel
            .basic_publish(
                exchange,
                key,
                BasicPublishOptions::default(),
                properties,
                n.to_string().into_bytes().into(),
            )
            .await
            .expect("publish");
        assert!(confirm.await.expect("confirm").is_ack());
    }
}

/// Waits within [`WAIT`] until `shovel`'s status is `done`.
pub async fn wait_status(shovel: &Shovel, what: &str, done: impl Fn(&ShovelStatus) -> bool) {
    let mut watch = shovel.watch();
    tokio::time::timeout(WAIT, watch.wait_for(|s| done(s)))
        .await
        .unwrap_or_else(|_| panic!("waited for {what}: {:?}", shovel.status()))
        .expect("shovel alive");
}
