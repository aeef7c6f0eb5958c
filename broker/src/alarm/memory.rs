//! The broker-wide resource alarms (RabbitMQ's memory and disk alarms):
//! while either is set, publishing connections stop being read and clients
//! that asked for it get connection.blocked. Three sources set them:
//! - the bytes the broker counts (queued messages, publishes a transaction
//!   holds, message bodies being assembled) above the high watermark;
//! - the process's resident memory above its own watermark, reported by
//!   the `resident` watcher;
//! - free disk space below `disk_free_limit`, reported by the
//!   `disk` watcher.
//!
//! Publishers are unblocked only once every source has cleared; the
//! memory sources clear below 90% of their watermark (hysteresis, so the
//! alarm does not flap). This module uses nothing else of the broker; the
//! queues, transactions, content assembly and the connection reader use
//! it.

use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::sync::Arc;
use tokio::sync::{watch, Notify};

/// Counts held bytes against a limit and carries the memory and disk alarms.
#[derive(Debug)]
pub struct MemoryGauge {
    used: AtomicUsize,
    limit: usize,
    /// Set while the counted bytes are above the limit.
    counted_alarm: AtomicBool,
    /// Set while resident memory is above its watermark.
    resident_alarm: AtomicBool,
    /// Set while free disk space is below its limit.
    disk_alarm: AtomicBool,
    /// The resident-memory watermark in bytes, once it is watched.
    resident_limit: std::sync::OnceLock<u64>,
    cleared: Notify,
    /// Counts the times a source turned on; idle publishers watch it, so
    /// they are blocked (and told) at once rather than at their next read.
    raised: watch::Sender<u64>,
}

/// Which source of the alarm changed, for the log line.
#[derive(Debug, Clone, Copy)]
enum Source {
    Counted,
    Resident,
    Disk,
}

impl MemoryGauge {
    /// A gauge with a high watermark of `limit` counted bytes.
    pub fn new(limit: usize) -> Self {
        MemoryGauge {
            used: AtomicUsize::new(0),
            limit,
            counted_alarm: AtomicBool::new(false),
            resident_alarm: AtomicBool::new(false),
            disk_alarm: AtomicBool::new(false),
            resident_limit: std::sync::OnceLock::new(),
            cleared: Notify::new(),
            raised: watch::Sender::new(0),
        }
    }

    /// Records `bytes` more held.
    pub fn add(&self, bytes: usize) {
        let used = self.used.fetch_add(bytes, Ordering::Relaxed) + bytes;
        if used > self.limit && !self.counted_alarm.swap(true, Ordering::AcqRel) {
            tracing::warn!(
                used,
                limit = self.limit,
                "memory alarm set: blocking publishers"
            );
            self.raised.send_modify(|count| *count += 1);
        }
    }

    /// The bytes counted now.
    pub fn used(&self) -> usize {
        self.used.load(Ordering::Relaxed)
    }

    /// Records `bytes` released.
    pub fn sub(&self, bytes: usize) {
        let used = self
            .used
            .fetch_sub(bytes, Ordering::Relaxed)
            .saturating_sub(bytes);
        if (used as u64) < below_hysteresis(self.limit as u64) {
            self.clear(Source::Counted, used);
        }
    }

    /// Counts `bytes` until the returned reservation is dropped, whatever
    /// path drops it (done, refused, channel or connection closed).
    pub fn reserve(self: &Arc<Self>, bytes: usize) -> Reservation {
        self.add(bytes);
        Reservation {
            gauge: Arc::clone(self),
            bytes,
        }
    }

    /// Records the resident-memory watermark the watcher holds to.
    pub(crate) fn set_resident_limit(&self, bytes: u64) {
        let _ = self.resident_limit.set(bytes);
    }

    /// The resident-memory watermark in bytes; `None` where resident
    /// memory is not watched.
    pub fn resident_limit(&self) -> Option<u64> {
        self.resident_limit.get().copied()
    }

    /// Sets or clears the resident-memory source of the alarm.
    pub fn set_resident_alarm(&self, on: bool, resident: u64) {
        if on {
            if !self.resident_alarm.swap(true, Ordering::AcqRel) {
                tracing::warn!(
                    resident,
                    "memory alarm set by resident memory: blocking publishers"
                );
                self.raised.send_modify(|count| *count += 1);
            }
        } else {
            self.clear(Source::Resident, resident as usize);
        }
    }

    /// Sets or clears the disk alarm (`free` bytes left on the disk).
    pub fn set_disk_alarm(&self, on: bool, free: u64) {
        if on {
            if !self.disk_alarm.swap(true, Ordering::AcqRel) {
                tracing::warn!(free, "disk alarm set: blocking publishers");
                self.raised.send_modify(|count| *count += 1);
            }
        } else {
            self.clear(Source::Disk, free as usize);
        }
    }

    fn clear(&self, source: Source, now: usize) {
        let flag = match source {
            Source::Counted => &self.counted_alarm,
            Source::Resident => &self.resident_alarm,
            Source::Disk => &self.disk_alarm,
        };
        if !flag.swap(false, Ordering::AcqRel) {
            return;
        }
        if self.in_alarm() {
            tracing::info!(?source, now, "alarm source cleared; another remains");
            return;
        }
        tracing::info!(?source, now, "alarms cleared: unblocking publishers");
        self.cleared.notify_waiters();
    }

    /// Whether publishers must wait.
    pub fn in_alarm(&self) -> bool {
        self.counted_alarm.load(Ordering::Acquire)
            || self.resident_alarm.load(Ordering::Acquire)
            || self.disk_alarm.load(Ordering::Acquire)
    }

    /// Whether a memory source (counted bytes or resident memory) is set.
    pub fn memory_alarm(&self) -> bool {
        self.counted_alarm.load(Ordering::Acquire) || self.resident_alarm.load(Ordering::Acquire)
    }

    /// Whether the disk alarm is set.
    pub fn disk_alarm(&self) -> bool {
        self.disk_alarm.load(Ordering::Acquire)
    }

    /// Why publishers wait, as connection.blocked's reason (RabbitMQ's
    /// wording).
    pub fn alarm_reason(&self) -> &'static str {
        if self.disk_alarm.load(Ordering::Acquire) {
            "low on disk"
        } else {
            "low on memory"
        }
    }

    /// Changes each time a source of the alarm is set.
    pub fn raised(&self) -> watch::Receiver<u64> {
        self.raised.subscribe()
    }

    /// Waits until the alarm clears (returns at once if it is not set).
    pub async fn wait_clear(&self) {
        loop {
            let notified = self.cleared.notified();
            if !self.in_alarm() {
                return;
            }
            notified.await;
        }
    }
}

/// The level below which an alarm set at `limit` clears: 90% of it.
pub(crate) fn below_hysteresis(limit: u64) -> u64 {
    limit / 10 * 9
}

/// Bytes counted in a [`MemoryGauge`] for as long as this lives.
#[derive(Debug)]
pub struct Reservation {
    gauge: Arc<MemoryGauge>,
    bytes: usize,
}

impl Drop for Reservation {
    fn drop(&mut self) {
        self.gauge.sub(self.bytes);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn counted_bytes_set_and_clear_the_alarm_with_hysteresis() {
        let gauge = MemoryGauge::new(1000);
        gauge.add(1000);
        assert!(!gauge.in_alarm(), "at the limit is not above it");
        gauge.add(1);
        assert!(gauge.in_alarm());
        gauge.sub(100);
        assert!(gauge.in_alarm(), "901 is not below 90% of 1000");
        gauge.sub(2);
        assert!(!gauge.in_alarm());
    }

    #[test]
    fn a_reservation_counts_until_dropped() {
        let gauge = Arc::new(MemoryGauge::new(100));
        let held = gauge.reserve(150);
        assert_eq!(gauge.used.load(Ordering::Relaxed), 150);
        assert!(gauge.in_alarm());
        drop(held);
        assert_eq!(gauge.used.load(Ordering::Relaxed), 0);
        assert!(!gauge.in_alarm());
    }

    #[test]
    fn the_alarm_clears_only_when_every_source_has() {
        let gauge = MemoryGauge::new(100);
        gauge.set_resident_alarm(true, 1 << 30);
        gauge.add(101);
        gauge.set_resident_alarm(false, 1 << 20);
        assert!(gauge.in_alarm(), "counted bytes still above the limit");
        gauge.sub(101);
        assert!(!gauge.in_alarm());
        gauge.set_resident_alarm(true, 1 << 30);
        assert!(gauge.in_alarm(), "resident memory alone sets it");
    }

    #[test]
    fn the_disk_alarm_blocks_alone_and_both_alarms_must_clear() {
        let gauge = MemoryGauge::new(100);
        gauge.set_disk_alarm(true, 10);
        assert!(gauge.in_alarm());
        assert_eq!(gauge.alarm_reason(), "low on disk");
        gauge.add(101);
        gauge.set_disk_alarm(false, 1 << 30);
        assert!(gauge.in_alarm(), "the memory alarm remains");
        assert_eq!(gauge.alarm_reason(), "low on memory");
        gauge.set_disk_alarm(true, 10);
        gauge.sub(101);
        assert!(gauge.in_alarm(), "the disk alarm remains");
        gauge.set_disk_alarm(false, 1 << 30);
        assert!(!gauge.in_alarm());
    }

    #[tokio::test]
    async fn waiters_wake_when_the_last_source_clears() {
        let gauge = Arc::new(MemoryGauge::new(100));
        gauge.set_resident_alarm(true, 1 << 30);
        let held = gauge.reserve(200);
        let waiter = tokio::spawn({
            let gauge = Arc::clone(&gauge);
            async move { gauge.wait_clear().await }
        });
        tokio::task::yield_now().await;
        drop(held);
        tokio::task::yield_now().await;
        assert!(
            !waiter.is_finished(),
            "resident memory still sets the alarm"
        );
        gauge.set_resident_alarm(false, 0);
        tokio::time::timeout(std::time::Duration::from_secs(30), waiter)
            .await
            .expect("woken")
            .expect("no panic");
    }
}
