//! [`LatencyStats`]: an in-port's latencies from put to the application
//! taking the value: count, min, max, mean, the latest, and percentiles
//! from a fixed-size log-linear histogram (constant memory and O(1) per sample, whatever
//! the number of samples).

use std::time::Duration;

/// Sub-buckets per power of two: a percentile is reported within 1/8 of
/// its value (12.5 %).
const SUB_BUCKET_BITS: u32 = 3;
const SUB_BUCKETS: usize = 1 << SUB_BUCKET_BITS;
/// The largest power of two tracked, in nanoseconds (2^36 ns, about 69 s);
/// longer latencies count in the last bucket.
const MAX_EXPONENT: u32 = 36;
const BUCKETS: usize = (MAX_EXPONENT - SUB_BUCKET_BITS + 2) as usize * SUB_BUCKETS;

/// Latencies from `x-sent-ns` to the application taking the value.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct LatencyStats {
    /// Samples measured.
    pub count: u64,
    /// Smallest.
    pub min: Duration,
    /// Largest.
    pub max: Duration,
    /// Sum of all, for the mean.
    pub total: Duration,
    /// The latest.
    pub last: Duration,
    histogram: Histogram,
}

impl Default for LatencyStats {
    fn default() -> Self {
        LatencyStats {
            count: 0,
            min: Duration::ZERO,
            max: Duration::ZERO,
            total: Duration::ZERO,
            last: Duration::ZERO,
            histogram: Histogram([0; BUCKETS]),
        }
    }
}

/// Counts per bucket: values below `SUB_BUCKETS` ns exactly, then each
/// power of two split into `SUB_BUCKETS` equal parts.
#[derive(Clone, Copy, PartialEq, Eq)]
struct Histogram([u64; BUCKETS]);

impl std::fmt::Debug for Histogram {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("Histogram")
    }
}

/// The bucket of `nanos`.
fn bucket(nanos: u64) -> usize {
    let nanos = nanos.min((1 << (MAX_EXPONENT + 1)) - 1);
    if nanos < SUB_BUCKETS as u64 {
        return nanos as usize;
    }
    let exponent = 63 - nanos.leading_zeros();
    let shift = exponent - SUB_BUCKET_BITS;
    let mantissa = (nanos >> shift) as usize & (SUB_BUCKETS - 1);
    (shift as usize + 1) * SUB_BUCKETS + mantissa
}

/// The largest value of bucket `index`, in nanoseconds.
fn bucket_top(index: usize) -> u64 {
    if index < SUB_BUCKETS {
        return index as u64;
    }
    let shift = (index / SUB_BUCKETS - 1) as u32;
    let mantissa = (index % SUB_BUCKETS) as u64;
    ((SUB_BUCKETS as u64 + mantissa + 1) << shift) - 1
}

impl LatencyStats {
    /// The mean (zero before the first sample).
    pub fn mean(&self) -> Duration {
        match u32::try_from(self.count) {
            Ok(0) => Duration::ZERO,
            Ok(n) => self.total / n,
            Err(_) => Duration::from_secs_f64(self.total.as_secs_f64() / self.count as f64),
        }
    }

    /// The latency at or below which a fraction `q` (0.0 to 1.0) of the
    /// samples fall, within 12.5 % (never above `max`; `percentile(0.0)`
    /// is `min`); zero before the first sample. `percentile(0.5)` is the median, `percentile(0.99)`
    /// the p99.
    pub fn percentile(&self, q: f64) -> Duration {
        if self.count == 0 {
            return Duration::ZERO;
        }
        let q = if q.is_nan() { 0.0 } else { q.clamp(0.0, 1.0) };
        if q == 0.0 {
            return self.min;
        }
        let rank = ((q * self.count as f64).ceil() as u64).clamp(1, self.count);
        let mut seen = 0;
        for (index, &count) in self.histogram.0.iter().enumerate() {
            seen += count;
            if seen >= rank {
                return Duration::from_nanos(bucket_top(index)).clamp(self.min, self.max);
            }
        }
        self.max
    }

    pub(crate) fn record(&mut self, latency: Duration) {
        if self.count == 0 || latency < self.min {
            self.min = latency;
        }
        self.max = self.max.max(latency);
        self.total = self.total.saturating_add(latency);
        self.last = latency;
        self.count += 1;
        let nanos = u64::try_from(latency.as_nanos()).unwrap_or(u64::MAX);
        self.histogram.0[bucket(nanos)] += 1;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn latency_mean() {
        let mut stats = LatencyStats::default();
        assert_eq!(stats.mean(), Duration::ZERO);
        assert_eq!(stats.percentile(0.5), Duration::ZERO);
        stats.record(Duration::from_millis(2));
        stats.record(Duration::from_millis(4));
        assert_eq!(stats.mean(), Duration::from_millis(3));
        assert_eq!(stats.min, Duration::from_millis(2));
        assert_eq!(stats.max, Duration::from_millis(4));
    }

    #[test]
    fn buckets_cover_every_value_in_order() {
        let mut previous_top = None;
        for index in 0..BUCKETS {
            let top = bucket_top(index);
            assert_eq!(bucket(top), index, "top of {index}");
            if let Some(previous) = previous_top {
                assert_eq!(bucket(previous + 1), index, "start of {index}");
            }
            previous_top = Some(top);
        }
        assert_eq!(bucket(u64::MAX), BUCKETS - 1);
    }

    #[test]
    fn percentiles_within_an_eighth() {
        let mut stats = LatencyStats::default();
        // 1..=1000 us: p50 500 us, p99 990 us, p100 1000 us.
        for micros in 1..=1000 {
            stats.record(Duration::from_micros(micros));
        }
        for (q, exact) in [(0.5, 500), (0.9, 900), (0.99, 990), (1.0, 1000)] {
            let got = stats.percentile(q).as_nanos() as f64;
            let exact = (exact * 1000) as f64;
            assert!(
                got >= exact && got <= exact * 1.125,
                "p{q}: {got} ns for {exact} ns"
            );
        }
        assert_eq!(stats.percentile(0.0), stats.min);
        assert_eq!(stats.percentile(1.0), stats.max);
        // A long tail shows in the p99, not in the median.
        let mut tail = LatencyStats::default();
        for _ in 0..98 {
            tail.record(Duration::from_micros(10));
        }
        tail.record(Duration::from_secs(3));
        tail.record(Duration::from_secs(3));
        assert!(tail.percentile(0.5) <= Duration::from_micros(12));
        assert!(tail.percentile(0.99) >= Duration::from_secs(3));
    }
}
