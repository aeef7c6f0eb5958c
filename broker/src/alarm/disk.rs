//! Free disk space as a source of the broker's alarms (RabbitMQ's disk
//! alarm): the data directory's free space is probed on a timer, and at
//! once after a failed store write; below `disk_free_limit` the
//! [`MemoryGauge`]'s disk alarm is set (publishers blocked), at or above it
//! cleared. The probe is a [`FreeSpace`], so tests and embedders can
//! report any figure. Uses only `memory`.

use crate::alarm::memory::MemoryGauge;
use std::path::PathBuf;
use std::sync::Arc;
use std::time::Duration;
use tokio::sync::watch;

/// How often free space is probed while it is within [`NEAR_FACTOR`]
/// times the limit (one statvfs call: microseconds).
const NEAR_PERIOD: Duration = Duration::from_secs(1);
/// How often it is probed while there is plenty (RabbitMQ's longest
/// interval is about 10 s).
const FAR_PERIOD: Duration = Duration::from_secs(10);
/// Free space under this many times the limit counts as near it.
const NEAR_FACTOR: u64 = 4;

/// Tells how many bytes are free for the broker's data.
pub trait FreeSpace: Send + Sync + std::fmt::Debug + 'static {
    /// Bytes available to this process on the disk holding the data.
    fn free_bytes(&self) -> std::io::Result<u64>;
}

/// The free space of the file system holding a directory (statvfs).
#[derive(Debug, Clone)]
pub struct DirFreeSpace {
    dir: PathBuf,
}

impl DirFreeSpace {
    /// Probes the file system holding `dir`.
    pub fn new(dir: impl Into<PathBuf>) -> Self {
        DirFreeSpace { dir: dir.into() }
    }
}

impl FreeSpace for DirFreeSpace {
    fn free_bytes(&self) -> std::io::Result<u64> {
        fs2::available_space(&self.dir)
    }
}

/// Feeds free space to `gauge` until the broker shuts down: on a timer
/// (every second near the limit, every ten seconds otherwise) and each
/// time `write_failures` changes.
pub(crate) async fn watch(
    gauge: Arc<MemoryGauge>,
    probe: Arc<dyn FreeSpace>,
    limit: u64,
    mut write_failures: Option<watch::Receiver<u64>>,
    mut shutdown: watch::Receiver<bool>,
) {
    tracing::debug!(limit, ?probe, "watching free disk space");
    let mut warned = false;
    loop {
        let period = match probe.free_bytes() {
            Ok(free) => {
                warned = false;
                apply(&gauge, free, limit);
                if free / NEAR_FACTOR < limit {
                    NEAR_PERIOD
                } else {
                    FAR_PERIOD
                }
            }
            Err(e) => {
                // The alarm stays as it was: an unreadable figure is no
                // evidence either way.
                if !warned {
                    tracing::warn!(error = %e, ?probe, "cannot read free disk space");
                    warned = true;
                }
                NEAR_PERIOD
            }
        };
        let failed = async {
            match &mut write_failures {
                Some(failures) => {
                    if failures.changed().await.is_err() {
                        std::future::pending::<()>().await;
                    }
                }
                None => std::future::pending::<()>().await,
            }
        };
        tokio::select! {
            _ = tokio::time::sleep(period) => {}
            _ = failed => tracing::debug!("a store write failed; probing free disk space"),
            _ = shutdown.wait_for(|down| *down) => return,
        }
    }
}

/// Sets the disk alarm below `limit` free bytes, clears it at or above.
fn apply(gauge: &MemoryGauge, free: u64, limit: u64) {
    gauge.set_disk_alarm(free < limit, free);
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::sync::atomic::{AtomicU64, Ordering};

    /// Free space set by the test.
    #[derive(Debug, Default)]
    struct Simulated(AtomicU64);

    impl FreeSpace for Simulated {
        fn free_bytes(&self) -> std::io::Result<u64> {
            Ok(self.0.load(Ordering::SeqCst))
        }
    }

    #[test]
    fn the_data_directory_has_some_free_space() {
        let free = DirFreeSpace::new(std::env::temp_dir())
            .free_bytes()
            .unwrap();
        assert!(free > 0);
    }

    #[tokio::test]
    async fn a_write_failure_probes_at_once_and_the_alarm_clears_when_space_returns() {
        let gauge = Arc::new(MemoryGauge::new(usize::MAX));
        let probe = Arc::new(Simulated(AtomicU64::new(1 << 40)));
        let (failures_tx, failures) = watch::channel(0);
        let (stop, shutdown) = watch::channel(false);
        let watcher = tokio::spawn(watch(
            Arc::clone(&gauge),
            Arc::clone(&probe) as Arc<dyn FreeSpace>,
            1000,
            Some(failures),
            shutdown,
        ));
        let until = |want: bool| {
            let gauge = Arc::clone(&gauge);
            let failures_tx = failures_tx.clone();
            async move {
                let wait = async {
                    while gauge.in_alarm() != want {
                        // Each failure report makes the watcher probe now,
                        // whatever its period.
                        failures_tx.send_modify(|n| *n += 1);
                        tokio::time::sleep(Duration::from_millis(5)).await;
                    }
                };
                tokio::time::timeout(Duration::from_secs(30), wait)
                    .await
                    .expect("the watcher follows the free space");
            }
        };
        until(false).await;
        probe.0.store(999, Ordering::SeqCst);
        until(true).await;
        assert_eq!(gauge.alarm_reason(), "low on disk");
        probe.0.store(1000, Ordering::SeqCst);
        until(false).await;
        stop.send_replace(true);
        watcher.await.expect("the watcher stops at shutdown");
    }
}
