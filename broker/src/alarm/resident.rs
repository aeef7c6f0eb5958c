//! The process's resident memory as a source of the memory alarm: read from
//! `/proc/self/statm` on a timer (Linux), compared with the resident-memory
//! watermark, fed to the [`MemoryGauge`]. This catches memory the broker
//! does not count (allocator overhead, buffers, anything an embedding
//! application holds). Where `/proc` is absent the watcher logs once and
//! stops; the counted-bytes alarm works as before. Uses only `memory`.

use crate::alarm::memory::{below_hysteresis, MemoryGauge};
use std::sync::Arc;
use std::time::Duration;
use tokio::sync::watch;

/// How often resident memory is read: one read of a ~30-byte procfs file
/// (a few microseconds) four times a second.
const POLL_PERIOD: Duration = Duration::from_millis(250);
/// The page size where `/proc/self/auxv` does not say.
const DEFAULT_PAGE_SIZE: u64 = 4096;
/// `AT_PAGESZ` in the ELF auxiliary vector.
const AT_PAGESZ: usize = 6;

/// The resident memory above which publishers are blocked, RabbitMQ's
/// `vm_memory_high_watermark`. In an embedding application it is the
/// whole process's memory, the application's included.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum ResidentMemoryWatermark {
    /// A fraction of the machine's physical memory (`MemTotal` in
    /// `/proc/meminfo`): RabbitMQ's `vm_memory_high_watermark.relative`,
    /// whose default is 0.4.
    Relative(f64),
    /// Bytes: RabbitMQ's `vm_memory_high_watermark.absolute`.
    Absolute(u64),
    /// Resident memory is not watched.
    Unwatched,
}

impl Default for ResidentMemoryWatermark {
    fn default() -> Self {
        ResidentMemoryWatermark::Relative(0.4)
    }
}

impl ResidentMemoryWatermark {
    /// The watermark in bytes, if it applies here.
    fn bytes(self) -> Option<u64> {
        match self {
            ResidentMemoryWatermark::Absolute(bytes) => Some(bytes),
            ResidentMemoryWatermark::Relative(fraction) => {
                let total = physical_memory()?;
                Some((total as f64 * fraction) as u64)
            }
            ResidentMemoryWatermark::Unwatched => None,
        }
    }
}

/// Reads this process's resident memory.
#[derive(Debug, Clone, Copy)]
struct ResidentMemory {
    page_size: u64,
}

impl ResidentMemory {
    /// A reader, if `/proc/self/statm` can be read here.
    fn open() -> Option<Self> {
        let reader = ResidentMemory {
            page_size: page_size().unwrap_or(DEFAULT_PAGE_SIZE),
        };
        reader.read().map(|_| reader)
    }

    /// Resident bytes now.
    fn read(&self) -> Option<u64> {
        let statm = std::fs::read_to_string("/proc/self/statm").ok()?;
        parse_statm_resident(&statm).map(|pages| pages * self.page_size)
    }
}

/// The second field of `/proc/self/statm`: resident pages.
fn parse_statm_resident(statm: &str) -> Option<u64> {
    statm.split_whitespace().nth(1)?.parse().ok()
}

/// The page size from the ELF auxiliary vector (pairs of native words).
fn page_size() -> Option<u64> {
    let auxv = std::fs::read("/proc/self/auxv").ok()?;
    parse_auxv_page_size(&auxv)
}

fn parse_auxv_page_size(auxv: &[u8]) -> Option<u64> {
    const WORD: usize = std::mem::size_of::<usize>();
    auxv.chunks_exact(2 * WORD).find_map(|entry| {
        let (key, value) = entry.split_at(WORD);
        let key = usize::from_ne_bytes(key.try_into().ok()?);
        let value = usize::from_ne_bytes(value.try_into().ok()?);
        (key == AT_PAGESZ).then_some(value as u64)
    })
}

/// Physical memory, `MemTotal` of `/proc/meminfo`.
fn physical_memory() -> Option<u64> {
    let meminfo = std::fs::read_to_string("/proc/meminfo").ok()?;
    parse_meminfo_total(&meminfo)
}

fn parse_meminfo_total(meminfo: &str) -> Option<u64> {
    let line = meminfo.lines().find(|l| l.starts_with("MemTotal:"))?;
    let kib: u64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kib * 1024)
}

/// Feeds resident memory to `gauge` until the broker shuts down. The
/// watermark is resolved to bytes and recorded in the gauge (where the
/// broker's figures read it) when this is called, before the returned
/// watcher first runs.
pub(crate) fn watch(
    gauge: Arc<MemoryGauge>,
    watermark: ResidentMemoryWatermark,
    shutdown: watch::Receiver<bool>,
) -> impl std::future::Future<Output = ()> {
    let watched = match (watermark.bytes(), ResidentMemory::open()) {
        (Some(limit), Some(reader)) => {
            gauge.set_resident_limit(limit);
            Some((limit, reader))
        }
        _ if watermark == ResidentMemoryWatermark::Unwatched => None,
        _ => {
            tracing::info!(
                ?watermark,
                "resident memory is not watched here (no /proc); the memory alarm counts queued bytes only"
            );
            None
        }
    };
    async move {
        if let Some((limit, reader)) = watched {
            poll(&gauge, limit, reader, shutdown).await;
        }
    }
}

async fn poll(
    gauge: &MemoryGauge,
    limit: u64,
    reader: ResidentMemory,
    mut shutdown: watch::Receiver<bool>,
) {
    tracing::debug!(limit, "watching resident memory");
    let mut ticker = tokio::time::interval(POLL_PERIOD);
    ticker.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    loop {
        tokio::select! {
            _ = ticker.tick() => {}
            _ = shutdown.wait_for(|down| *down) => return,
        }
        let Some(resident) = reader.read() else {
            tracing::warn!(
                "cannot read /proc/self/statm any more; resident memory no longer watched"
            );
            return;
        };
        apply(gauge, resident, limit);
    }
}

/// Sets the resident source of the alarm above `limit`, clears it below
/// 90% of it, and leaves it as it is in between.
fn apply(gauge: &MemoryGauge, resident: u64, limit: u64) {
    if resident > limit {
        gauge.set_resident_alarm(true, resident);
    } else if resident < below_hysteresis(limit) {
        gauge.set_resident_alarm(false, resident);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parses_procfs_files() {
        assert_eq!(
            parse_statm_resident("2617 1283 904 1 0 473 0\n"),
            Some(1283)
        );
        assert_eq!(parse_statm_resident(""), None);
        let meminfo = "MemTotal:       24684456 kB\nMemFree:        13407648 kB\n";
        assert_eq!(parse_meminfo_total(meminfo), Some(24_684_456 * 1024));
        let mut auxv = Vec::new();
        for (key, value) in [(33usize, 1usize), (AT_PAGESZ, 16384), (0, 0)] {
            auxv.extend_from_slice(&key.to_ne_bytes());
            auxv.extend_from_slice(&value.to_ne_bytes());
        }
        assert_eq!(parse_auxv_page_size(&auxv), Some(16384));
        assert_eq!(parse_auxv_page_size(&auxv[..8]), None);
    }

    #[test]
    fn reads_this_process_where_proc_exists() {
        let Some(reader) = ResidentMemory::open() else {
            assert!(std::fs::metadata("/proc/self/statm").is_err());
            return;
        };
        assert!(reader.page_size.is_power_of_two());
        let resident = reader.read().expect("readable once opened");
        assert!(
            resident > 1 << 20,
            "a test process has more than 1 MiB resident"
        );
    }

    #[test]
    fn the_resident_source_follows_the_watermark_with_hysteresis() {
        let gauge = MemoryGauge::new(usize::MAX);
        apply(&gauge, 1001, 1000);
        assert!(gauge.in_alarm());
        apply(&gauge, 950, 1000);
        assert!(
            gauge.in_alarm(),
            "between 90% and the watermark nothing changes"
        );
        apply(&gauge, 899, 1000);
        assert!(!gauge.in_alarm());
        apply(&gauge, 950, 1000);
        assert!(!gauge.in_alarm());
    }

    #[tokio::test]
    async fn the_watcher_sets_the_alarm_above_an_absolute_watermark() {
        if ResidentMemory::open().is_none() {
            return;
        }
        let gauge = Arc::new(MemoryGauge::new(usize::MAX));
        let (stop, shutdown) = watch::channel(false);
        let watcher = tokio::spawn(watch(
            Arc::clone(&gauge),
            ResidentMemoryWatermark::Absolute(1),
            shutdown,
        ));
        assert_eq!(gauge.resident_limit(), Some(1), "recorded before it runs");
        let set = async {
            while !gauge.in_alarm() {
                tokio::time::sleep(Duration::from_millis(10)).await;
            }
        };
        tokio::time::timeout(Duration::from_secs(30), set)
            .await
            .expect("the alarm is set at the first reading");
        stop.send_replace(true);
        watcher.await.expect("the watcher stops at shutdown");
    }
}
