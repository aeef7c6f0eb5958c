//! The broker-wide memory gauge: bytes held by queued messages, and the
//! high watermark above which publishing connections stop being read and
//! get connection.blocked (RabbitMQ's memory alarm).

use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use tokio::sync::Notify;

/// Counts queued message bytes against a limit.
#[derive(Debug)]
pub struct MemoryGauge {
    used: AtomicUsize,
    limit: usize,
    alarm: AtomicBool,
    cleared: Notify,
}

impl MemoryGauge {
    /// A gauge with a high watermark of `limit` bytes.
    pub fn new(limit: usize) -> Self {
        MemoryGauge {
            used: AtomicUsize::new(0),
            limit,
            alarm: AtomicBool::new(false),
            cleared: Notify::new(),
        }
    }

    /// Records `bytes` more held.
    pub fn add(&self, bytes: usize) {
        let used = self.used.fetch_add(bytes, Ordering::Relaxed) + bytes;
        if used > self.limit && !self.alarm.swap(true, Ordering::AcqRel) {
            tracing::warn!(
                used,
                limit = self.limit,
                "memory alarm set: blocking publishers"
            );
        }
    }

    /// Records `bytes` released.
    pub fn sub(&self, bytes: usize) {
        let used = self
            .used
            .fetch_sub(bytes, Ordering::Relaxed)
            .saturating_sub(bytes);
        // Clear with hysteresis, at 90% of the limit, so the alarm does not flap.
        if used < self.limit / 10 * 9 && self.alarm.swap(false, Ordering::AcqRel) {
            tracing::info!(used, "memory alarm cleared: unblocking publishers");
            self.cleared.notify_waiters();
        }
    }

    /// Whether publishers must wait.
    pub fn in_alarm(&self) -> bool {
        self.alarm.load(Ordering::Acquire)
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
