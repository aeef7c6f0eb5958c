//! declare-ok, bind-ok, unbind-ok and delete-ok for durable things go out
//! only once the change is flushed. The store here keeps what has been
//! written apart from what has been flushed, and flushes slowly (a slow
//! disk widens the window a -ok sent before its flush would fall into); at
//! chosen moments the test takes only what was flushed, as a power cut
//! would leave it, starts a second broker on it and checks that every
//! change already answered -ok is there.

use lapin::options::{
    BasicGetOptions, BasicPublishOptions, ConfirmSelectOptions, ExchangeBindOptions,
    ExchangeDeclareOptions, ExchangeDeleteOptions, QueueBindOptions, QueueDeclareOptions,
    QueueDeleteOptions,
};
use lapin::types::FieldTable;
use lapin::{BasicProperties, Connection, ConnectionProperties, ExchangeKind};
use leveret_broker::store::{KvOp, KvPair, MemoryStore, Store, StoreError, WriteMode};
use leveret_test_macros::both_runtimes;
use std::collections::BTreeMap;
use std::sync::{Arc, Mutex};
use std::time::Duration;

/// How long a flush takes on this pretend disk.
const FLUSH_TIME: Duration = Duration::from_millis(20);

/// A store in memory whose writes count only once flushed.
#[derive(Debug, Default)]
struct SlowDisk {
    written: Mutex<BTreeMap<Vec<u8>, Vec<u8>>>,
    flushed: Mutex<BTreeMap<Vec<u8>, Vec<u8>>>,
}

impl SlowDisk {
    /// What a power cut now would leave: the flushed state, as a store.
    fn after_power_cut(&self) -> Arc<dyn Store> {
        let flushed = self.flushed.lock().expect("lock").clone();
        let survivor = MemoryStore::default();
        survivor
            .write(
                flushed.into_iter().map(|(k, v)| (k, Some(v))).collect(),
                WriteMode::Plain,
            )
            .expect("seed");
        Arc::new(survivor)
    }
}

impl Store for SlowDisk {
    fn write(&self, ops: Vec<KvOp>, _mode: WriteMode) -> Result<(), StoreError> {
        let mut written = self.written.lock().expect("lock");
        for (key, value) in ops {
            match value {
                Some(value) => written.insert(key, value),
                None => written.remove(&key),
            };
        }
        Ok(())
    }

    fn flush(&self) -> Result<(), StoreError> {
        // Takes what is written now; writes that come during the flush
        // wait for the next one, as with a real disk.
        let snapshot = self.written.lock().expect("lock").clone();
        std::thread::sleep(FLUSH_TIME);
        *self.flushed.lock().expect("lock") = snapshot;
        Ok(())
    }

    fn scan(&self) -> Result<Vec<KvPair>, StoreError> {
        let flushed = self.flushed.lock().expect("lock");
        Ok(flushed
            .iter()
            .map(|(k, v)| (k.clone(), v.clone()))
            .collect())
    }
}

async fn broker(store: Arc<dyn Store>) -> (leveret_broker::BrokerHandle, Connection) {
    let handle = leveret_broker::Broker::builder()
        .listen("127.0.0.1:0".parse().expect("addr"))
        .store(store)
        .start()
        .await
        .expect("start");
    let url = format!("amqp://guest:guest@{}/%2f", handle.local_addrs()[0]);
    let conn = Connection::connect(&url, ConnectionProperties::default())
        .await
        .expect("connect");
    (handle, conn)
}

const QUEUES: usize = 20;
const EXCHANGES: usize = 10;

fn queue(i: usize) -> String {
    format!("q{i}")
}

fn exchange(i: usize) -> String {
    format!("x{i}")
}

/// Each queue `i` is bound to exchange `i % EXCHANGES` with key `k{i}`.
fn key(i: usize) -> String {
    format!("k{i}")
}

/// What a broker started on the surviving store should find.
#[derive(Default)]
struct Expected {
    queues: Vec<(usize, bool)>,
    exchanges: Vec<(usize, bool)>,
    /// (exchange, routing key, queue that must receive it, or none).
    routes: Vec<(String, String, Option<usize>)>,
}

async fn check(survivor: Arc<dyn Store>, expected: &Expected, moment: &str) {
    let (handle, conn) = broker(survivor).await;
    let passive_queue = QueueDeclareOptions {
        passive: true,
        ..Default::default()
    };
    for &(i, present) in &expected.queues {
        let channel = conn.create_channel().await.expect("channel");
        let found = channel
            .queue_declare(&queue(i), passive_queue, FieldTable::default())
            .await
            .is_ok();
        assert_eq!(found, present, "{moment}: queue {} on disk", queue(i));
    }
    let passive_exchange = ExchangeDeclareOptions {
        passive: true,
        ..Default::default()
    };
    for &(i, present) in &expected.exchanges {
        let channel = conn.create_channel().await.expect("channel");
        let found = channel
            .exchange_declare(
                &exchange(i),
                ExchangeKind::Direct,
                passive_exchange,
                FieldTable::default(),
            )
            .await
            .is_ok();
        assert_eq!(found, present, "{moment}: exchange {} on disk", exchange(i));
    }
    let channel = conn.create_channel().await.expect("channel");
    channel
        .confirm_select(ConfirmSelectOptions::default())
        .await
        .expect("confirms");
    for (source, routing_key, target) in &expected.routes {
        // The confirm comes after routing, so a get afterwards sees it.
        channel
            .basic_publish(
                source,
                routing_key,
                BasicPublishOptions::default(),
                routing_key.as_bytes(),
                BasicProperties::default(),
            )
            .await
            .expect("publish")
            .await
            .expect("confirm");
        if let Some(i) = target {
            let got = channel
                .basic_get(&queue(*i), BasicGetOptions { no_ack: true })
                .await
                .expect("get");
            assert!(
                got.is_some_and(|m| m.delivery.data == routing_key.as_bytes()),
                "{moment}: binding {source} -[{routing_key}]-> {} on disk",
                queue(*i)
            );
        }
    }
    for i in 0..QUEUES {
        if expected.queues.contains(&(i, true)) {
            let got = channel
                .basic_get(&queue(i), BasicGetOptions { no_ack: true })
                .await
                .expect("get");
            assert!(got.is_none(), "{moment}: an unbind or delete is on disk");
        }
    }
    handle.shutdown().await;
}

/// Runs the changes in phases of one kind each (so a later kind's wait
/// cannot cover an earlier one's) and checks the flushed state after each.
#[both_runtimes]
async fn every_durable_definition_answered_ok_is_on_disk() {
    let disk = Arc::new(SlowDisk::default());
    let (handle, conn) = broker(Arc::clone(&disk) as Arc<dyn Store>).await;
    let channel = conn.create_channel().await.expect("channel");
    let durable_exchange = ExchangeDeclareOptions {
        durable: true,
        ..Default::default()
    };
    let durable_queue = QueueDeclareOptions {
        durable: true,
        ..Default::default()
    };
    let mut expected = Expected::default();

    for i in 0..EXCHANGES {
        channel
            .exchange_declare(
                &exchange(i),
                ExchangeKind::Direct,
                durable_exchange,
                FieldTable::default(),
            )
            .await
            .expect("exchange.declare");
        expected.exchanges.push((i, true));
    }
    check(disk.after_power_cut(), &expected, "after exchange.declare").await;

    for i in 0..QUEUES {
        channel
            .queue_declare(&queue(i), durable_queue, FieldTable::default())
            .await
            .expect("queue.declare");
        expected.queues.push((i, true));
    }
    check(disk.after_power_cut(), &expected, "after queue.declare").await;

    for i in 0..QUEUES {
        channel
            .queue_bind(
                &queue(i),
                &exchange(i % EXCHANGES),
                &key(i),
                QueueBindOptions::default(),
                FieldTable::default(),
            )
            .await
            .expect("queue.bind");
        expected
            .routes
            .push((exchange(i % EXCHANGES), key(i), Some(i)));
    }
    check(disk.after_power_cut(), &expected, "after queue.bind").await;

    // x1 -> x0 with key k10: x0 routes k10 on to q10.
    channel
        .exchange_bind(
            &exchange(0),
            &exchange(1),
            &key(10),
            ExchangeBindOptions::default(),
            FieldTable::default(),
        )
        .await
        .expect("exchange.bind");
    expected.routes.push((exchange(1), key(10), Some(10)));
    check(disk.after_power_cut(), &expected, "after exchange.bind").await;

    channel
        .exchange_unbind(
            &exchange(0),
            &exchange(1),
            &key(10),
            Default::default(),
            FieldTable::default(),
        )
        .await
        .expect("exchange.unbind");
    expected
        .routes
        .retain(|(source, _, _)| *source != exchange(1));
    // Nothing may arrive in q10 now (checked by the empty gets).
    expected.routes.push((exchange(1), key(10), None));
    check(disk.after_power_cut(), &expected, "after exchange.unbind").await;

    channel
        .exchange_delete(&exchange(EXCHANGES - 1), ExchangeDeleteOptions::default())
        .await
        .expect("exchange.delete");
    expected.exchanges = (0..EXCHANGES).map(|i| (i, i < EXCHANGES - 1)).collect();
    expected
        .routes
        .retain(|(source, _, _)| *source != exchange(EXCHANGES - 1));
    check(disk.after_power_cut(), &expected, "after exchange.delete").await;

    channel
        .queue_unbind(&queue(0), &exchange(0), &key(0), FieldTable::default())
        .await
        .expect("queue.unbind");
    expected.routes.retain(|(_, _, target)| *target != Some(0));
    // Nothing may arrive in q0 now (checked by the empty gets).
    expected.routes.push((exchange(0), key(0), None));
    check(disk.after_power_cut(), &expected, "after queue.unbind").await;

    for i in QUEUES - 5..QUEUES {
        channel
            .queue_delete(&queue(i), QueueDeleteOptions::default())
            .await
            .expect("queue.delete");
    }
    expected.queues = (0..QUEUES).map(|i| (i, i < QUEUES - 5)).collect();
    expected
        .routes
        .retain(|(_, _, target)| target.is_none_or(|i| i < QUEUES - 5));
    check(disk.after_power_cut(), &expected, "after queue.delete").await;
    handle.shutdown().await;
}
