//! Power cuts, not only kill -9: a store that keeps only what was flushed
//! (plus, as a page cache might, a random prefix of what was written after
//! the last flush, the last plain batch possibly torn) loses power at a
//! random moment of a mixed workload: confirmed publishes, transactions,
//! gets with acks, durable declares and deletes. A new broker starts on
//! what survived, and every promise must hold: no confirmed message lost
//! (unless its ack was sent), no committed transaction partial or missing,
//! no uncommitted one partial, no durable queue lost after declare-ok or
//! back after delete-ok, no message twice, no failed start. Each round
//! starts on what the previous one left.
//!
//! CI runs a short version (12 rounds, a fixed seed);
//! `LEVERET_POWER_CUT_ROUNDS=500 LEVERET_POWER_CUT_SEED=N cargo test -p
//! leveret-broker --test power_cut -- --nocapture` is the longer run (it
//! prints the seed and the promises made). Every fourth round purges the
//! queues and forgets their promises, so rounds cost the same throughout.

use lapin::options::{
    BasicAckOptions, BasicGetOptions, BasicPublishOptions, ConfirmSelectOptions,
    QueueDeclareOptions, QueueDeleteOptions, QueuePurgeOptions,
};
use lapin::types::FieldTable;
use lapin::{BasicProperties, Connection, ConnectionProperties};
use leveret_broker::store::{KvOp, KvPair, Store, StoreError, WriteMode};
use leveret_broker::{Broker, BrokerHandle};
use leveret_test_macros::both_runtimes;
use std::collections::{BTreeMap, BTreeSet};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Duration;

/// The queue confirmed messages go to (never deleted).
const WORK: &str = "work";
/// The queue transactions publish to (never consumed from).
const TXQ: &str = "txq";
/// Messages per transaction.
const TX_SIZE: usize = 3;

type Map = BTreeMap<Vec<u8>, Vec<u8>>;

/// What the disk holds, what is written but not flushed, and whether the
/// power is off.
#[derive(Debug, Default)]
struct Disk {
    durable: Map,
    pending: Vec<(Vec<KvOp>, WriteMode)>,
    off: bool,
}

/// A store that loses unflushed writes when the power goes.
#[derive(Debug, Default)]
struct PowerCutStore {
    disk: Mutex<Disk>,
}

fn apply(map: &mut Map, ops: impl IntoIterator<Item = KvOp>) {
    for (key, value) in ops {
        match value {
            Some(value) => map.insert(key, value),
            None => map.remove(&key),
        };
    }
}

fn power_off() -> StoreError {
    StoreError::Engine("the power is off (simulated)".into())
}

impl PowerCutStore {
    fn holding(durable: Map) -> Self {
        PowerCutStore {
            disk: Mutex::new(Disk {
                durable,
                ..Disk::default()
            }),
        }
    }

    /// Cuts the power: what was flushed survives, and of what was written
    /// since, the first `batches` batches, then `torn` ops of the next if
    /// it is a plain one. Nothing is written afterwards.
    fn cut(&self, random: &mut Random) -> Map {
        let mut disk = self.disk.lock().expect("disk");
        disk.off = true;
        let pending = std::mem::take(&mut disk.pending);
        let batches = random.below(pending.len() + 1);
        let mut survived = std::mem::take(&mut disk.durable);
        let mut pending = pending.into_iter();
        for (ops, _) in pending.by_ref().take(batches) {
            apply(&mut survived, ops);
        }
        if let Some((ops, WriteMode::Plain)) = pending.next() {
            let torn = random.below(ops.len() + 1);
            apply(&mut survived, ops.into_iter().take(torn));
        }
        survived
    }
}

impl Store for PowerCutStore {
    fn write(&self, ops: Vec<KvOp>, mode: WriteMode) -> Result<(), StoreError> {
        let mut disk = self.disk.lock().expect("disk");
        if disk.off {
            return Err(power_off());
        }
        disk.pending.push((ops, mode));
        Ok(())
    }

    fn flush(&self) -> Result<(), StoreError> {
        let mut disk = self.disk.lock().expect("disk");
        if disk.off {
            return Err(power_off());
        }
        let pending = std::mem::take(&mut disk.pending);
        for (ops, _) in pending {
            apply(&mut disk.durable, ops);
        }
        Ok(())
    }

    fn scan(&self) -> Result<Vec<KvPair>, StoreError> {
        let disk = self.disk.lock().expect("disk");
        let mut view = disk.durable.clone();
        for (ops, _) in &disk.pending {
            apply(&mut view, ops.iter().cloned());
        }
        Ok(view.into_iter().collect())
    }
}

/// splitmix64: a seeded sequence, so a failing round can be replayed.
struct Random(u64);

impl Random {
    fn next(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9e37_79b9_7f4a_7c15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
        z ^ (z >> 31)
    }

    fn below(&mut self, n: usize) -> usize {
        (self.next() % n.max(1) as u64) as usize
    }
}

/// The promises the broker made, across rounds.
#[derive(Debug, Default)]
struct Promises {
    /// Confirmed messages in `WORK` whose ack was not sent (once it is,
    /// or the queue was purged, they may be there or not).
    confirmed: BTreeSet<String>,
    /// Committed transactions (their number).
    committed: BTreeSet<u64>,
    /// Transactions numbered below this were purged: a cut during the
    /// purge may bring back any part of them.
    purged_below: u64,
    /// Queues declared (declare-ok) and not deleted since.
    declared: BTreeSet<String>,
    /// Queues deleted (delete-ok).
    deleted: BTreeSet<String>,
    /// How many promises of each kind were made over the whole run.
    made: BTreeMap<&'static str, u64>,
}

impl Promises {
    fn made(&mut self, kind: &'static str) {
        *self.made.entry(kind).or_default() += 1;
    }
}

const DURABLE: QueueDeclareOptions = QueueDeclareOptions {
    passive: false,
    durable: true,
    exclusive: false,
    auto_delete: false,
    nowait: false,
};

fn persistent() -> BasicProperties {
    BasicProperties::default().with_delivery_mode(2)
}

async fn start(store: Arc<PowerCutStore>) -> BrokerHandle {
    Broker::builder()
        .listen("127.0.0.1:0".parse().expect("addr"))
        .store(store as Arc<dyn Store>)
        .start()
        .await
        .expect("the broker starts on whatever survived the cut")
}

async fn connect(handle: &BrokerHandle) -> Connection {
    let url = format!("amqp://guest:guest@{}/%2f", handle.local_addrs()[0]);
    tokio::time::timeout(
        Duration::from_secs(10),
        Connection::connect(&url, ConnectionProperties::default()),
    )
    .await
    .expect("connect in time")
    .expect("connect")
}

/// The workload: random operations until one fails (the power is off) or
/// the broker goes. Every -ok received is recorded as a promise.
/// The workload: random steps until the first refused operation; counts
/// the steps it begins in `begun`.
async fn work(
    conn: Connection,
    round: u64,
    seed: u64,
    promises: Arc<Mutex<Promises>>,
    begun: Arc<AtomicU64>,
) -> Result<(), lapin::Error> {
    let mut random = Random(seed);
    let confirming = conn.create_channel().await?;
    confirming
        .confirm_select(ConfirmSelectOptions::default())
        .await?;
    let tx = conn.create_channel().await?;
    tx.tx_select().await?;
    let admin = conn.create_channel().await?;
    for step in 0u64.. {
        begun.fetch_add(1, Ordering::Relaxed);
        match random.below(10) {
            0..=4 => {
                let body = format!("m-{round}-{step}");
                let confirm = confirming
                    .basic_publish(
                        "",
                        WORK,
                        BasicPublishOptions::default(),
                        body.as_bytes(),
                        persistent(),
                    )
                    .await?
                    .await?;
                if !confirm.is_ack() {
                    return Ok(());
                }
                let mut p = promises.lock().expect("promises");
                p.confirmed.insert(body);
                p.made("confirm");
            }
            5 => {
                let number = round * 1_000_000 + step;
                for part in 0..TX_SIZE {
                    let body = format!("tx-{number}-{part}");
                    tx.basic_publish(
                        "",
                        TXQ,
                        BasicPublishOptions::default(),
                        body.as_bytes(),
                        persistent(),
                    )
                    .await?;
                }
                tx.tx_commit().await?;
                let mut p = promises.lock().expect("promises");
                p.committed.insert(number);
                p.made("commit");
            }
            6 | 7 => {
                let got = admin
                    .basic_get(WORK, BasicGetOptions { no_ack: false })
                    .await?;
                if let Some(message) = got {
                    let body = String::from_utf8_lossy(&message.delivery.data).into_owned();
                    promises.lock().expect("promises").confirmed.remove(&body);
                    message.delivery.ack(BasicAckOptions::default()).await?;
                }
            }
            8 => {
                let name = format!("d-{round}-{step}");
                admin
                    .queue_declare(&name, DURABLE, FieldTable::default())
                    .await?;
                let mut p = promises.lock().expect("promises");
                p.declared.insert(name);
                p.made("declare");
            }
            _ => {
                let victim = {
                    let p = promises.lock().expect("promises");
                    let declared: Vec<_> = p.declared.iter().cloned().collect();
                    if declared.is_empty() {
                        continue;
                    }
                    declared[random.below(declared.len())].clone()
                };
                admin
                    .queue_delete(&victim, QueueDeleteOptions::default())
                    .await?;
                let mut p = promises.lock().expect("promises");
                p.declared.remove(&victim);
                p.deleted.insert(victim);
                p.made("delete");
            }
        }
    }
    Ok(())
}

/// Every message in `queue`, read without acking (they return to the
/// queue when the connection closes).
async fn contents(conn: &Connection, queue: &str) -> Vec<String> {
    let channel = conn.create_channel().await.expect("channel");
    let mut out = Vec::new();
    while let Some(message) = channel
        .basic_get(queue, BasicGetOptions { no_ack: false })
        .await
        .expect("get")
    {
        out.push(String::from_utf8_lossy(&message.delivery.data).into_owned());
    }
    out
}

async fn exists(conn: &Connection, queue: &str) -> bool {
    let channel = conn.create_channel().await.expect("channel");
    let passive = QueueDeclareOptions {
        passive: true,
        ..DURABLE
    };
    channel
        .queue_declare(queue, passive, FieldTable::default())
        .await
        .is_ok()
}

/// Checks every promise against what the broker holds after a cut.
async fn check(handle: &BrokerHandle, promises: &Promises, round: u64) {
    let conn = connect(handle).await;
    let channel = conn.create_channel().await.expect("channel");
    for queue in [WORK, TXQ] {
        channel
            .queue_declare(queue, DURABLE, FieldTable::default())
            .await
            .expect("declare");
    }
    let work = contents(&conn, WORK).await;
    let unique: BTreeSet<_> = work.iter().cloned().collect();
    assert_eq!(unique.len(), work.len(), "round {round}: a message twice");
    for body in &promises.confirmed {
        assert!(
            unique.contains(body),
            "round {round}: confirmed message {body} lost"
        );
    }
    let mut parts: BTreeMap<u64, BTreeSet<usize>> = BTreeMap::new();
    for body in contents(&conn, TXQ).await {
        let mut fields = body.split('-').skip(1);
        let number: u64 = fields.next().and_then(|n| n.parse().ok()).expect("number");
        let part: usize = fields.next().and_then(|n| n.parse().ok()).expect("part");
        assert!(
            parts.entry(number).or_default().insert(part),
            "round {round}: transaction message {body} twice"
        );
    }
    for (number, got) in parts.range(promises.purged_below..) {
        assert_eq!(
            got.len(),
            TX_SIZE,
            "round {round}: transaction {number} partial: {got:?}"
        );
    }
    for number in &promises.committed {
        assert!(
            parts.contains_key(number),
            "round {round}: committed transaction {number} lost"
        );
    }
    for queue in &promises.declared {
        assert!(
            exists(&conn, queue).await,
            "round {round}: queue {queue} lost after declare-ok"
        );
    }
    for queue in &promises.deleted {
        assert!(
            !exists(&conn, queue).await,
            "round {round}: queue {queue} back after delete-ok"
        );
    }
    let _ = conn.close(200, "checked").await;
}

/// Empties the queues and forgets what was checked, so each round costs
/// the same whatever came before: what was in the queues is no longer
/// promised, and deletions are not checked again.
async fn settle(handle: &BrokerHandle, promises: &mut Promises, round: u64) {
    let conn = connect(handle).await;
    let channel = conn.create_channel().await.expect("channel");
    for queue in [WORK, TXQ] {
        channel
            .queue_purge(queue, QueuePurgeOptions::default())
            .await
            .expect("purge");
    }
    let _ = conn.close(200, "settled").await;
    promises.confirmed.clear();
    promises.committed.clear();
    promises.purged_below = round * 1_000_000;
    promises.deleted.clear();
}

fn rounds() -> u64 {
    std::env::var("LEVERET_POWER_CUT_ROUNDS")
        .ok()
        .and_then(|n| n.parse().ok())
        .unwrap_or(12)
}

#[both_runtimes]
async fn every_promise_survives_a_power_cut_at_a_random_moment() {
    let seed = std::env::var("LEVERET_POWER_CUT_SEED")
        .ok()
        .and_then(|n| n.parse().ok())
        .unwrap_or(0x01e7_e2e7);
    eprintln!("power cut seed {seed}");
    let mut random = Random(seed);
    let promises = Arc::new(Mutex::new(Promises::default()));
    let mut survived = Map::new();
    for round in 0..rounds() {
        let store = Arc::new(PowerCutStore::holding(survived));
        let handle = start(Arc::clone(&store)).await;
        let mut expected = std::mem::take(&mut *promises.lock().expect("promises"));
        check(&handle, &expected, round).await;
        if round % 4 == 3 {
            settle(&handle, &mut expected, round).await;
        }
        *promises.lock().expect("promises") = expected;
        let conn = connect(&handle).await;
        let begun = Arc::new(AtomicU64::new(0));
        let worker = tokio::spawn(work(
            conn,
            round,
            random.next(),
            Arc::clone(&promises),
            Arc::clone(&begun),
        ));
        // The power goes once the workload has begun a random number of
        // steps (counted, so that a loaded machine, which slows the
        // workload, does not shrink it), at a random moment in that step.
        let steps = 1 + random.below(32) as u64;
        tokio::time::timeout(Duration::from_secs(30), async {
            while begun.load(Ordering::Relaxed) < steps && !worker.is_finished() {
                tokio::time::sleep(Duration::from_millis(1)).await;
            }
        })
        .await
        .expect("the workload makes progress");
        tokio::time::sleep(Duration::from_micros(random.below(5_000) as u64)).await;
        survived = store.cut(&mut random);
        // The worker stops at its first refused operation.
        let _ = tokio::time::timeout(Duration::from_secs(10), worker)
            .await
            .expect("the workload stops once the power is off");
        handle.shutdown().await;
    }
    let store = Arc::new(PowerCutStore::holding(survived));
    let handle = start(store).await;
    let p = std::mem::take(&mut *promises.lock().expect("promises"));
    check(&handle, &p, rounds()).await;
    assert_eq!(
        p.made.len(),
        4,
        "the workload made promises of every kind: {:?}",
        p.made
    );
    eprintln!("promises made over {} rounds: {:?}", rounds(), p.made);
    handle.shutdown().await;
}
