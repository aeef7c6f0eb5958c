//! A failing disk (full, read-only…): persistent publishes to durable
//! queues are nacked and transactions refused with 506 while the store
//! fails, and so are durable declarations; transient traffic goes on;
//! confirms are acks again once the store works.

use lapin::options::{BasicPublishOptions, ConfirmSelectOptions, QueueDeclareOptions};
use lapin::types::FieldTable;
use lapin::{BasicProperties, Channel, Connection, ConnectionProperties};
use leveret_broker::store::{KvOp, KvPair, MemoryStore, Store, StoreError, WriteMode};
use leveret_test_macros::both_runtimes;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::Duration;

/// A memory store whose writes fail while `failing` is set.
#[derive(Debug, Default)]
struct FlakyStore {
    inner: MemoryStore,
    failing: AtomicBool,
}

impl Store for FlakyStore {
    fn write(&self, ops: Vec<KvOp>, mode: WriteMode) -> Result<(), StoreError> {
        if self.failing.load(Ordering::SeqCst) {
            return Err(StoreError::Engine(
                "No space left on device (simulated)".into(),
            ));
        }
        self.inner.write(ops, mode)
    }

    fn flush(&self) -> Result<(), StoreError> {
        self.inner.flush()
    }

    fn scan(&self) -> Result<Vec<KvPair>, StoreError> {
        self.inner.scan()
    }
}

async fn confirmed(channel: &Channel, body: &[u8], delivery_mode: u8) -> bool {
    let confirm = channel
        .basic_publish(
            "",
            "disk",
            BasicPublishOptions::default(),
            body,
            BasicProperties::default().with_delivery_mode(delivery_mode),
        )
        .await
        .expect("publish");
    tokio::time::timeout(Duration::from_secs(10), confirm)
        .await
        .expect("confirm in time")
        .expect("confirm")
        .is_ack()
}

#[both_runtimes]
async fn a_failing_store_nacks_persistent_publishes_and_recovers() {
    let store = Arc::new(FlakyStore::default());
    let handle = leveret_broker::Broker::builder()
        .listen("127.0.0.1:0".parse().expect("addr"))
        .store(Arc::clone(&store) as Arc<dyn Store>)
        .start()
        .await
        .expect("start");
    let url = format!("amqp://guest:guest@{}/%2f", handle.local_addrs()[0]);
    let conn = Connection::connect(&url, ConnectionProperties::default())
        .await
        .expect("connect");
    let channel = conn.create_channel().await.expect("channel");
    let durable = QueueDeclareOptions {
        durable: true,
        ..Default::default()
    };
    channel
        .queue_declare("disk", durable, FieldTable::default())
        .await
        .expect("declare");
    channel
        .confirm_select(ConfirmSelectOptions::default())
        .await
        .expect("confirms");
    assert!(confirmed(&channel, b"before", 2).await, "disk fine: ack");

    store.failing.store(true, Ordering::SeqCst);
    assert!(
        !confirmed(&channel, b"during", 2).await,
        "disk failing: nack"
    );
    assert!(
        confirmed(&channel, b"transient", 1).await,
        "transient messages never touch the disk"
    );
    let tx_channel = conn.create_channel().await.expect("channel");
    tx_channel.tx_select().await.expect("tx.select");
    tx_channel
        .basic_publish(
            "",
            "disk",
            BasicPublishOptions::default(),
            b"in tx",
            BasicProperties::default().with_delivery_mode(2),
        )
        .await
        .expect("publish in tx");
    let err = tx_channel.tx_commit().await.expect_err("commit refused");
    assert!(
        err.to_string().contains("RESOURCE_ERROR"),
        "506 RESOURCE_ERROR: {err}"
    );

    // A durable declaration the disk did not take is refused (506 closes
    // the connection, as for the commit above), never answered declare-ok
    // and lost; a transient one goes on.
    let conn = Connection::connect(&url, ConnectionProperties::default())
        .await
        .expect("reconnect");
    let transient_channel = conn.create_channel().await.expect("channel");
    transient_channel
        .queue_declare(
            "in-memory",
            QueueDeclareOptions::default(),
            FieldTable::default(),
        )
        .await
        .expect("a transient declare never touches the disk");
    let declare_channel = conn.create_channel().await.expect("channel");
    let err = declare_channel
        .queue_declare("lost", durable, FieldTable::default())
        .await
        .expect_err("durable declare refused");
    assert!(
        err.to_string().contains("RESOURCE_ERROR"),
        "506 RESOURCE_ERROR: {err}"
    );

    store.failing.store(false, Ordering::SeqCst);
    let conn = Connection::connect(&url, ConnectionProperties::default())
        .await
        .expect("reconnect");
    let channel = conn.create_channel().await.expect("channel");
    channel
        .confirm_select(ConfirmSelectOptions::default())
        .await
        .expect("confirms");
    assert!(confirmed(&channel, b"after", 2).await, "disk back: ack");
    handle.shutdown().await;
}
