//! Whether threads are waiting for a CPU, read from Linux's pressure stall
//! information (`/proc/pressure/cpu`), so that busy polling can give the
//! CPU back when something else wants it.
//!
//! The kernel counts, in microseconds, the time during which at least one
//! runnable thread waited for a CPU (the "some" line). Its growth over an
//! interval, divided by the interval, is the share of that interval during
//! which the machine had more runnable threads than CPUs: a share near zero
//! means a spinning thread takes nothing from anyone. Owns one open file;
//! uses only std.

use std::fs::File;
use std::os::unix::fs::FileExt;
use std::time::{Duration, Instant};

/// The kernel's pressure file for CPUs (Linux 4.20 and later, with PSI on).
const PRESSURE_FILE: &str = "/proc/pressure/cpu";

/// Reads the CPU pressure counter and turns its growth into shares.
#[derive(Debug)]
pub struct CpuPressure {
    file: File,
    /// When the counter was last read, and what it said (microseconds).
    baseline: Option<(Instant, u64)>,
}

impl CpuPressure {
    /// The pressure file opened, or `None` where the kernel has none.
    pub fn open() -> Option<Self> {
        let file = File::open(PRESSURE_FILE).ok()?;
        let pressure = CpuPressure {
            file,
            baseline: None,
        };
        // A kernel built without PSI may still have the file but fail reads.
        pressure.stalled_total()?;
        Some(pressure)
    }

    /// Forgets the previous reading: the next share counts from `now`.
    pub fn rebase(&mut self, now: Instant) {
        self.baseline = self.stalled_total().map(|total| (now, total));
    }

    /// The share (0 to 1) of the time since the previous reading during
    /// which some thread waited for a CPU; `None` on the first reading or
    /// when the file cannot be read.
    pub fn share_since_last(&mut self, now: Instant) -> Option<f64> {
        let total = self.stalled_total()?;
        let previous = self.baseline.replace((now, total));
        let (then, before) = previous?;
        Some(stall_share(
            now.saturating_duration_since(then),
            total.saturating_sub(before),
        ))
    }

    /// The "some" line's total: microseconds during which at least one
    /// thread waited for a CPU since boot.
    fn stalled_total(&self) -> Option<u64> {
        let mut text = [0u8; 256];
        // One read at offset 0 makes the kernel write the file afresh.
        let len = self.file.read_at(&mut text, 0).ok()?;
        some_total(&text[..len])
    }
}

/// The share of `interval` that `stalled_micros` of waiting make, capped
/// at 1 (the counter and the clock are read at slightly different moments).
fn stall_share(interval: Duration, stalled_micros: u64) -> f64 {
    let interval_micros = interval.as_micros();
    if interval_micros == 0 {
        return 0.0;
    }
    (stalled_micros as f64 / interval_micros as f64).min(1.0)
}

/// The `total=` figure of the file's `some` line.
fn some_total(text: &[u8]) -> Option<u64> {
    let text = std::str::from_utf8(text).ok()?;
    let line = text.lines().find(|line| line.starts_with("some "))?;
    let total = line
        .split_ascii_whitespace()
        .find_map(|field| field.strip_prefix("total="))?;
    total.parse().ok()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_some_lines_total_is_read_and_the_full_line_ignored() {
        let text = b"some avg10=0.09 avg60=2.38 avg300=2.53 total=8673697509\n\
                     full avg10=0.00 avg60=0.00 avg300=0.00 total=12\n";
        assert_eq!(some_total(text), Some(8_673_697_509));
        assert_eq!(some_total(b"full avg10=0.00 total=12\n"), None);
        assert_eq!(some_total(b"some avg10=0.00 total=x\n"), None);
        assert_eq!(some_total(b""), None);
    }

    #[test]
    fn the_share_is_stalled_time_over_the_interval_capped_at_one() {
        let ten_ms = Duration::from_millis(10);
        assert_eq!(stall_share(ten_ms, 0), 0.0);
        assert_eq!(stall_share(ten_ms, 2_500), 0.25);
        assert_eq!(stall_share(ten_ms, 20_000), 1.0);
        assert_eq!(stall_share(Duration::ZERO, 5), 0.0);
    }

    #[test]
    fn where_the_kernel_reports_pressure_a_share_follows_a_first_reading() {
        let Some(mut pressure) = CpuPressure::open() else {
            // A kernel without PSI: busy polling then never yields, and
            // there is nothing to read here.
            return;
        };
        let start = Instant::now();
        assert_eq!(pressure.share_since_last(start), None);
        std::thread::sleep(Duration::from_millis(5));
        let share = pressure
            .share_since_last(Instant::now())
            .expect("a second reading gives a share");
        assert!((0.0..=1.0).contains(&share), "{share}");
    }
}
