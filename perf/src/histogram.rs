//! Latency statistics.
//!
//! [`Histogram`] is a log-linear histogram of nanosecond values (as in
//! HdrHistogram: 64 linear sub-buckets per power of two, so any value is
//! known within 1/64, about 1.6 %), cheap to record into at millions of
//! samples a second and to merge. [`Samples`] keeps every value for the
//! round trip, where the counts are small and exact quartiles are wanted
//! for the box plot.

use serde::Serialize;

/// Sub-bucket bits: values below `2^SUB_BITS` are exact.
const SUB_BITS: u32 = 7;
const SUB: u64 = 1 << SUB_BITS;
const HALF: u64 = SUB / 2;
/// Enough buckets for any `u64`.
const BUCKETS: usize = ((64 - SUB_BITS as usize) + 1) * HALF as usize + HALF as usize;

/// Bucket of a value.
fn index(v: u64) -> usize {
    if v < SUB {
        return v as usize;
    }
    let msb = 63 - v.leading_zeros();
    let shift = msb + 1 - SUB_BITS;
    let mantissa = v >> shift; // in [HALF, SUB)
    (u64::from(shift) * HALF + mantissa) as usize
}

/// Lowest and highest value of a bucket.
fn bounds(i: usize) -> (u64, u64) {
    let i = i as u64;
    if i < SUB {
        return (i, i);
    }
    let shift = i / HALF - 1;
    let mantissa = i - shift * HALF;
    let low = mantissa << shift;
    let high = low.saturating_add((1u64 << shift) - 1);
    (low, high)
}

/// A log-linear histogram of nanosecond values.
#[derive(Clone)]
pub struct Histogram {
    counts: Box<[u64]>,
    count: u64,
    sum: u128,
    min: u64,
    max: u64,
}

impl std::fmt::Debug for Histogram {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Histogram")
            .field("count", &self.count)
            .field("min", &self.min)
            .field("max", &self.max)
            .finish()
    }
}

impl Default for Histogram {
    fn default() -> Self {
        Histogram::new()
    }
}

impl Histogram {
    /// An empty histogram.
    pub fn new() -> Self {
        Histogram {
            counts: vec![0; BUCKETS].into_boxed_slice(),
            count: 0,
            sum: 0,
            min: u64::MAX,
            max: 0,
        }
    }

    /// Records one value.
    #[inline]
    pub fn record(&mut self, v: u64) {
        self.counts[index(v)] += 1;
        self.count += 1;
        self.sum += u128::from(v);
        self.min = self.min.min(v);
        self.max = self.max.max(v);
    }

    /// Number of values.
    pub fn count(&self) -> u64 {
        self.count
    }

    /// Adds another histogram's values.
    pub fn merge(&mut self, other: &Histogram) {
        if other.count == 0 {
            return;
        }
        for (a, b) in self.counts.iter_mut().zip(other.counts.iter()) {
            *a += *b;
        }
        self.count += other.count;
        self.sum += other.sum;
        self.min = self.min.min(other.min);
        self.max = self.max.max(other.max);
    }

    /// Empties the histogram.
    pub fn clear(&mut self) {
        if self.count > 0 {
            self.counts.fill(0);
        }
        self.count = 0;
        self.sum = 0;
        self.min = u64::MAX;
        self.max = 0;
    }

    /// The value at quantile `q` (0 to 1): the middle of its bucket, kept
    /// within the exact minimum and maximum.
    pub fn quantile(&self, q: f64) -> u64 {
        if self.count == 0 {
            return 0;
        }
        let rank = ((q.clamp(0.0, 1.0) * self.count as f64).ceil() as u64).max(1);
        let mut seen = 0;
        for (i, &n) in self.counts.iter().enumerate() {
            seen += n;
            if seen >= rank {
                let (low, high) = bounds(i);
                let mid = low + (high - low) / 2;
                return mid.clamp(self.min, self.max);
            }
        }
        self.max
    }

    /// Mean, nanoseconds.
    pub fn mean(&self) -> f64 {
        if self.count == 0 {
            0.0
        } else {
            self.sum as f64 / self.count as f64
        }
    }

    /// The summary in microseconds.
    pub fn summary(&self) -> LatencySummary {
        let us = |ns: u64| ns as f64 / 1000.0;
        LatencySummary {
            count: self.count,
            min_us: if self.count == 0 { 0.0 } else { us(self.min) },
            mean_us: self.mean() / 1000.0,
            p50_us: us(self.quantile(0.50)),
            p95_us: us(self.quantile(0.95)),
            p99_us: us(self.quantile(0.99)),
            max_us: us(self.max),
        }
    }
}

/// Latency percentiles, microseconds.
#[derive(Debug, Clone, Copy, Default, Serialize, PartialEq)]
pub struct LatencySummary {
    /// Number of samples.
    pub count: u64,
    /// Smallest.
    pub min_us: f64,
    /// Mean.
    pub mean_us: f64,
    /// Median.
    pub p50_us: f64,
    /// 95th percentile.
    pub p95_us: f64,
    /// 99th percentile.
    pub p99_us: f64,
    /// Largest.
    pub max_us: f64,
}

/// Every sample of a small series, for exact quartiles.
#[derive(Debug, Clone, Default)]
pub struct Samples {
    values: Vec<u64>,
}

/// Box-plot statistics of a series, microseconds.
#[derive(Debug, Clone, Copy, Default, Serialize, PartialEq)]
pub struct BoxStats {
    /// Number of samples.
    pub count: usize,
    /// Mean.
    pub mean_us: f64,
    /// Smallest.
    pub min_us: f64,
    /// First quartile.
    pub q1_us: f64,
    /// Median.
    pub median_us: f64,
    /// Third quartile.
    pub q3_us: f64,
    /// 99th percentile.
    pub p99_us: f64,
    /// Largest.
    pub max_us: f64,
}

impl Samples {
    /// Adds a sample, nanoseconds.
    pub fn push(&mut self, ns: u64) {
        self.values.push(ns);
    }

    /// Number of samples.
    pub fn len(&self) -> usize {
        self.values.len()
    }

    /// Whether there are none.
    pub fn is_empty(&self) -> bool {
        self.values.is_empty()
    }

    /// Every sample, nanoseconds, in the order they were added.
    pub fn values(&self) -> &[u64] {
        &self.values
    }

    /// Mean, min, quartiles (linear interpolation), p99 and max.
    pub fn box_stats(&self) -> BoxStats {
        if self.values.is_empty() {
            return BoxStats::default();
        }
        let mut sorted = self.values.clone();
        sorted.sort_unstable();
        let at = |q: f64| -> f64 {
            let pos = q * (sorted.len() - 1) as f64;
            let lo = pos.floor() as usize;
            let hi = pos.ceil() as usize;
            let frac = pos - lo as f64;
            (sorted[lo] as f64 * (1.0 - frac) + sorted[hi] as f64 * frac) / 1000.0
        };
        let sum: u128 = sorted.iter().map(|&v| u128::from(v)).sum();
        BoxStats {
            count: sorted.len(),
            mean_us: sum as f64 / sorted.len() as f64 / 1000.0,
            min_us: sorted[0] as f64 / 1000.0,
            q1_us: at(0.25),
            median_us: at(0.5),
            q3_us: at(0.75),
            p99_us: at(0.99),
            max_us: sorted[sorted.len() - 1] as f64 / 1000.0,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn buckets_are_contiguous_and_bound_their_values() {
        let mut previous_high = None;
        for i in 0..BUCKETS {
            let (low, high) = bounds(i);
            assert!(low <= high);
            if let Some(p) = previous_high {
                assert_eq!(low, p + 1, "bucket {i}");
            }
            previous_high = Some(high);
            assert_eq!(index(low), i);
            assert_eq!(index(high), i);
            if high == u64::MAX {
                assert_eq!(i, BUCKETS - 1);
                break;
            }
        }
    }

    #[test]
    fn quantiles_are_within_the_precision() {
        let mut h = Histogram::new();
        for v in 1..=100_000u64 {
            h.record(v * 10);
        }
        for (q, exact) in [(0.5, 500_000.0), (0.99, 990_000.0), (0.95, 950_000.0)] {
            let got = h.quantile(q) as f64;
            assert!((got - exact).abs() / exact < 0.02, "{q}: {got}");
        }
        assert_eq!(h.quantile(1.0), 1_000_000);
        assert_eq!(h.summary().min_us, 0.01);
        let mut other = Histogram::new();
        other.record(5);
        h.merge(&other);
        assert_eq!(h.count(), 100_001);
        assert_eq!(h.quantile(0.0), 5);
        h.clear();
        assert_eq!(h.count(), 0);
        assert_eq!(h.quantile(0.5), 0);
    }

    #[test]
    fn exact_quartiles() {
        let mut s = Samples::default();
        for v in [1000, 2000, 3000, 4000, 5000] {
            s.push(v);
        }
        let b = s.box_stats();
        assert_eq!(b.count, 5);
        assert_eq!(b.min_us, 1.0);
        assert_eq!(b.q1_us, 2.0);
        assert_eq!(b.median_us, 3.0);
        assert_eq!(b.q3_us, 4.0);
        assert_eq!(b.max_us, 5.0);
        assert_eq!(b.mean_us, 3.0);
    }
}
