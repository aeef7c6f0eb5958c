//! The disk alarm (RabbitMQ's `disk_free_limit`): below the limit a
//! publishing connection is blocked (a real client sees
//! connection.blocked), it is unblocked when space returns, and the store
//! takes writes again without a restart, even an engine that, like sled,
//! refuses all work after one I/O error until it is reopened.
//!
//! Two tests simulate the disk (an injected free-space probe and a store
//! that poisons itself like sled); the third (with the `persistence`
//! feature) fills a real, small tmpfs under sled. Mounting one needs root
//! (a CI container or sandbox has it): elsewhere that test says so and
//! returns, under CI it fails.

use lapin::options::{BasicPublishOptions, ConfirmSelectOptions, QueueDeclareOptions};
use lapin::publisher_confirm::{Confirmation, PublisherConfirm};
use lapin::types::FieldTable;
use lapin::{BasicProperties, Channel, Connection, ConnectionProperties};
use leveret_broker::store::{KvOp, KvPair, MemoryStore, Store, StoreError, WriteMode};
use leveret_broker::{Broker, BrokerHandle, FreeSpace, Limits};
use leveret_test_macros::both_runtimes;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::Arc;
use std::time::Duration;

const TIMEOUT: Duration = Duration::from_secs(10);

/// A simulated disk: while `full`, free space is 0 and writes fail; a
/// failed write poisons the store (as sled does) until `reopen` succeeds,
/// which it does only once the disk has room.
#[derive(Debug, Default)]
struct SimulatedDisk {
    inner: MemoryStore,
    full: AtomicBool,
    poisoned: AtomicBool,
}

impl SimulatedDisk {
    fn check(&self) -> Result<(), StoreError> {
        if self.full.load(Ordering::SeqCst) {
            self.poisoned.store(true, Ordering::SeqCst);
        }
        if self.poisoned.load(Ordering::SeqCst) {
            return Err(StoreError::Engine(
                "No space left on device (simulated)".into(),
            ));
        }
        Ok(())
    }
}

impl Store for SimulatedDisk {
    fn write(&self, ops: Vec<KvOp>, mode: WriteMode) -> Result<(), StoreError> {
        self.check()?;
        self.inner.write(ops, mode)
    }

    fn flush(&self) -> Result<(), StoreError> {
        self.check()?;
        self.inner.flush()
    }

    fn scan(&self) -> Result<Vec<KvPair>, StoreError> {
        self.inner.scan()
    }

    fn reopen(&self) -> Result<(), StoreError> {
        if self.full.load(Ordering::SeqCst) {
            return Err(StoreError::Engine("still full (simulated)".into()));
        }
        self.poisoned.store(false, Ordering::SeqCst);
        Ok(())
    }
}

/// The simulated disk's free space: none while full, `space` otherwise.
#[derive(Debug)]
struct SimulatedFreeSpace {
    disk: Arc<SimulatedDisk>,
    space: AtomicU64,
}

impl SimulatedFreeSpace {
    fn of(disk: &Arc<SimulatedDisk>) -> Arc<Self> {
        Arc::new(SimulatedFreeSpace {
            disk: Arc::clone(disk),
            space: AtomicU64::new(1 << 40),
        })
    }
}

impl FreeSpace for SimulatedFreeSpace {
    fn free_bytes(&self) -> std::io::Result<u64> {
        Ok(if self.disk.full.load(Ordering::SeqCst) {
            0
        } else {
            self.space.load(Ordering::SeqCst)
        })
    }
}

async fn start_on(disk: &Arc<SimulatedDisk>) -> BrokerHandle {
    Broker::builder()
        .listen("127.0.0.1:0".parse().expect("addr"))
        .store(Arc::clone(disk) as Arc<dyn Store>)
        .free_space(SimulatedFreeSpace::of(disk))
        .start()
        .await
        .expect("start")
}

async fn connect(handle: &BrokerHandle) -> Connection {
    let url = format!("amqp://guest:guest@{}/%2f", handle.local_addrs()[0]);
    Connection::connect(&url, ConnectionProperties::default())
        .await
        .expect("connect")
}

const DURABLE: QueueDeclareOptions = QueueDeclareOptions {
    passive: false,
    durable: true,
    exclusive: false,
    auto_delete: false,
    nowait: false,
};

async fn publish(channel: &Channel, queue: &str, body: &[u8]) -> PublisherConfirm {
    channel
        .basic_publish(
            "",
            queue,
            BasicPublishOptions::default(),
            body,
            BasicProperties::default().with_delivery_mode(2),
        )
        .await
        .expect("publish")
}

/// Publishes and waits for the confirm from a task of its own, for a
/// publish that waits while the connection is blocked.
fn spawn_publish(
    channel: &Channel,
    queue: &'static str,
    body: &'static [u8],
) -> tokio::task::JoinHandle<Confirmation> {
    let channel = channel.clone();
    tokio::spawn(async move { confirmation(publish(&channel, queue, body).await).await })
}

async fn confirmation(confirm: PublisherConfirm) -> Confirmation {
    tokio::time::timeout(TIMEOUT, confirm)
        .await
        .expect("confirm in time")
        .expect("confirm")
}

/// Polls `condition` until it holds, for at most [`TIMEOUT`].
async fn until(what: &str, condition: impl Fn() -> bool) {
    let wait = async {
        while !condition() {
            tokio::time::sleep(Duration::from_millis(10)).await;
        }
    };
    tokio::time::timeout(TIMEOUT, wait)
        .await
        .unwrap_or_else(|_| panic!("timed out waiting until {what}"));
}

async fn messages_in(handle: &BrokerHandle, queue: &str) -> u32 {
    let conn = connect(handle).await;
    let channel = conn.create_channel().await.expect("channel");
    let passive = QueueDeclareOptions {
        passive: true,
        ..DURABLE
    };
    let queue = channel
        .queue_declare(queue, passive, FieldTable::default())
        .await
        .expect("the durable queue exists");
    queue.message_count()
}

#[both_runtimes]
async fn a_full_disk_blocks_publishers_until_space_returns_and_the_store_resumes() {
    let disk = Arc::new(SimulatedDisk::default());
    let handle = start_on(&disk).await;
    let conn = connect(&handle).await;
    let channel = conn.create_channel().await.expect("channel");
    channel
        .queue_declare("disk", DURABLE, FieldTable::default())
        .await
        .expect("declare");
    channel
        .confirm_select(ConfirmSelectOptions::default())
        .await
        .expect("confirms");
    let before = publish(&channel, "disk", b"before").await;
    assert!(confirmation(before).await.is_ack(), "disk fine: ack");

    // The disk fills: the write fails (nack), the failure makes the alarm
    // probe at once, and the next publish is not read: connection.blocked.
    disk.full.store(true, Ordering::SeqCst);
    let during = publish(&channel, "disk", b"during").await;
    assert!(confirmation(during).await.is_nack(), "disk full: nack");
    until("the client is told connection.blocked", || {
        conn.status().blocked()
    })
    .await;
    // lapin holds a publish while blocked: it is sent once unblocked.
    let blocked_publish = spawn_publish(&channel, "disk", b"blocked");

    // A durable declaration meanwhile is refused, never answered OK and
    // lost (the connection is not a publisher, so not blocked).
    let other = connect(&handle).await;
    let declare = other.create_channel().await.expect("channel");
    let refused = declare
        .queue_declare("lost", DURABLE, FieldTable::default())
        .await
        .expect_err("durable declare refused while the store fails");
    assert!(refused.to_string().contains("RESOURCE_ERROR"), "{refused}");

    // Space returns: the alarm clears by itself, the blocked publish is
    // read and confirmed, and later ones too: the store was reopened.
    disk.full.store(false, Ordering::SeqCst);
    until("the client is told connection.unblocked", || {
        !conn.status().blocked()
    })
    .await;
    assert!(
        blocked_publish.await.expect("publish task").is_ack(),
        "space back: the blocked publish is confirmed"
    );
    let after = publish(&channel, "disk", b"after").await;
    assert!(confirmation(after).await.is_ack(), "space back: ack");
    let declare = conn.create_channel().await.expect("channel");
    declare
        .queue_declare("kept", DURABLE, FieldTable::default())
        .await
        .expect("durable declare accepted again");
    handle.shutdown().await;

    // Everything confirmed is there after a restart; the refused queue is
    // not, the later one is.
    let handle = start_on(&disk).await;
    assert_eq!(messages_in(&handle, "disk").await, 3);
    assert_eq!(messages_in(&handle, "kept").await, 0);
    let conn = connect(&handle).await;
    let channel = conn.create_channel().await.expect("channel");
    let passive = QueueDeclareOptions {
        passive: true,
        ..DURABLE
    };
    assert!(channel
        .queue_declare("lost", passive, FieldTable::default())
        .await
        .is_err());
    handle.shutdown().await;
}

#[both_runtimes]
async fn the_disk_free_limit_blocks_publishers_and_clears_without_a_write() {
    let disk = Arc::new(SimulatedDisk::default());
    let free_space = SimulatedFreeSpace::of(&disk);
    let limits = Limits {
        disk_free_limit: 1 << 41,
        ..Limits::default()
    };
    // 1 TiB free is below a 2 TiB limit: the alarm is on from the start,
    // before anything fails.
    let handle = Broker::builder()
        .listen("127.0.0.1:0".parse().expect("addr"))
        .store(Arc::clone(&disk) as Arc<dyn Store>)
        .free_space(Arc::clone(&free_space) as Arc<dyn FreeSpace>)
        .limits(limits)
        .start()
        .await
        .expect("start");
    let conn = connect(&handle).await;
    let channel = conn.create_channel().await.expect("channel");
    channel
        .queue_declare("q", DURABLE, FieldTable::default())
        .await
        .expect("declare: not a publisher yet, not blocked");
    channel
        .confirm_select(ConfirmSelectOptions::default())
        .await
        .expect("confirms");
    let first = publish(&channel, "q", b"one").await;
    until("the client is told connection.blocked", || {
        conn.status().blocked()
    })
    .await;
    let second = spawn_publish(&channel, "q", b"two");
    tokio::time::sleep(Duration::from_millis(300)).await;
    assert!(!second.is_finished(), "a blocked publisher is held");

    // 4 TiB free: the next probe (within a second, this near the limit)
    // clears the alarm with no write having failed; both are confirmed.
    free_space.space.store(1 << 42, Ordering::SeqCst);
    until("the client is told connection.unblocked", || {
        !conn.status().blocked()
    })
    .await;
    assert!(confirmation(first).await.is_ack());
    assert!(second.await.expect("publish task").is_ack());
    assert_eq!(messages_in(&handle, "q").await, 2);
    handle.shutdown().await;
}

/// A small tmpfs, unmounted when dropped.
#[cfg(feature = "persistence")]
struct SmallDisk {
    dir: std::path::PathBuf,
}

#[cfg(feature = "persistence")]
impl SmallDisk {
    /// Mounts a `size`-byte tmpfs, or says why not: mounting needs root
    /// (a CI container or sandbox has it). Under CI the test fails instead
    /// of skipping.
    fn mount(size: u64) -> Option<SmallDisk> {
        let dir = std::env::temp_dir().join(format!(
            "leveret-small-disk-{}-{:?}",
            std::process::id(),
            std::thread::current().id()
        ));
        std::fs::create_dir_all(&dir).expect("mount point");
        let mounted = std::process::Command::new("mount")
            .args(["-t", "tmpfs", "-o", &format!("size={size}"), "tmpfs"])
            .arg(&dir)
            .output();
        match mounted {
            Ok(out) if out.status.success() => Some(SmallDisk { dir }),
            other => {
                let _ = std::fs::remove_dir(&dir);
                let in_ci = std::env::var_os("CI")
                    .is_some_and(|v| !v.is_empty() && v != "0" && v != "false");
                assert!(!in_ci, "cannot mount a tmpfs under CI: {other:?}");
                eprintln!("skipped: cannot mount a tmpfs here (needs root): {other:?}");
                None
            }
        }
    }

    /// Writes a file until the disk is full, leaving `leave` bytes free
    /// (0: until a write fails).
    fn fill(&self, leave: u64) -> std::path::PathBuf {
        use std::io::Write;
        let path = self.dir.join("filler");
        let mut file = std::fs::File::create(&path).expect("filler");
        let chunk = vec![0xa5u8; 4096];
        loop {
            let free = fs2::available_space(&self.dir).expect("statvfs");
            if free <= leave || file.write_all(&chunk).is_err() {
                break;
            }
        }
        let _ = file.sync_all();
        path
    }
}

#[cfg(feature = "persistence")]
impl Drop for SmallDisk {
    fn drop(&mut self) {
        let _ = std::process::Command::new("umount")
            .arg("-l")
            .arg(&self.dir)
            .status();
        let _ = std::fs::remove_dir(&self.dir);
    }
}

#[cfg(feature = "persistence")]
async fn start_in(dir: &std::path::Path, disk_free_limit: u64) -> BrokerHandle {
    Broker::builder()
        .listen("127.0.0.1:0".parse().expect("addr"))
        .data_dir(dir)
        .limits(Limits {
            disk_free_limit,
            ..Limits::default()
        })
        .start()
        .await
        .expect("start")
}

/// The store (the message log and sled) on a real, full tmpfs: with the alarm off (limit 0) writes fail
/// with ENOSPC and are nacked, a durable declare is refused; once space is
/// freed the store is reopened and takes writes again, and after a restart
/// every confirmed message is there. Then with a limit above the free
/// space the alarm blocks before the disk fills, and freeing space
/// unblocks.
#[cfg(feature = "persistence")]
#[both_runtimes]
async fn the_store_on_a_full_tmpfs_nacks_then_resumes_and_the_alarm_blocks_before_it_fills() {
    let Some(disk) = SmallDisk::mount(24 << 20) else {
        return;
    };
    let data = disk.dir.join("data");
    let handle = start_in(&data, 0).await;
    let conn = connect(&handle).await;
    let channel = conn.create_channel().await.expect("channel");
    channel
        .queue_declare("disk", DURABLE, FieldTable::default())
        .await
        .expect("declare");
    channel
        .confirm_select(ConfirmSelectOptions::default())
        .await
        .expect("confirms");
    let body = vec![7u8; 16 << 10];
    let mut acked = 0;
    assert!(confirmation(publish(&channel, "disk", &body).await)
        .await
        .is_ack());
    acked += 1;

    let filler = disk.fill(0);
    let mut nacked = false;
    for _ in 0..2000 {
        if confirmation(publish(&channel, "disk", &body).await)
            .await
            .is_ack()
        {
            acked += 1;
        } else {
            nacked = true;
            break;
        }
    }
    assert!(nacked, "a full disk nacks persistent publishes");
    // 506 is a connection error: declare on a connection of its own.
    let other = connect(&handle).await;
    let refused = other
        .create_channel()
        .await
        .expect("channel")
        .queue_declare("lost", DURABLE, FieldTable::default())
        .await
        .expect_err("durable declare refused on a full disk");
    assert!(refused.to_string().contains("RESOURCE_ERROR"), "{refused}");

    std::fs::remove_file(&filler).expect("free the space");
    assert!(
        confirmation(publish(&channel, "disk", &body).await)
            .await
            .is_ack(),
        "space back: the store was reopened and takes writes"
    );
    acked += 1;
    handle.shutdown().await;

    // Everything confirmed survives a restart; the refused queue does not
    // exist. Now the alarm: 2 MB limit, 1 MB left.
    let handle = start_in(&data, 2 << 20).await;
    assert_eq!(messages_in(&handle, "disk").await, acked);
    let filler = disk.fill(1 << 20);
    let conn = connect(&handle).await;
    let channel = conn.create_channel().await.expect("channel");
    channel
        .confirm_select(ConfirmSelectOptions::default())
        .await
        .expect("confirms");
    let first = publish(&channel, "disk", b"first").await;
    until("the client is told connection.blocked", || {
        conn.status().blocked()
    })
    .await;
    std::fs::remove_file(&filler).expect("free the space");
    until("the client is told connection.unblocked", || {
        !conn.status().blocked()
    })
    .await;
    assert!(confirmation(first).await.is_ack());
    let passive = QueueDeclareOptions {
        passive: true,
        ..DURABLE
    };
    assert!(conn
        .create_channel()
        .await
        .expect("channel")
        .queue_declare("lost", passive, FieldTable::default())
        .await
        .is_err());
    handle.shutdown().await;
}
