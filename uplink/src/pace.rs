//! Link discipline: a token bucket that paces a shovel to a rate (bytes or
//! messages per second). Taking more than is in the bucket borrows against
//! the future and waits until the debt is paid, so a message larger than
//! the burst still goes, and the average holds. Uses nothing else.

use std::time::Duration;
use tokio::time::Instant;

/// A rate and what has been used of it.
#[derive(Debug)]
pub struct Pace {
    per_second: f64,
    burst: f64,
    tokens: f64,
    last: Instant,
}

impl Pace {
    /// At most `per_second` on average, bursts of a tenth of a second.
    pub fn new(per_second: u64) -> Pace {
        let per_second = per_second as f64;
        let burst = per_second / 10.0;
        Pace {
            per_second,
            burst,
            tokens: burst,
            last: Instant::now(),
        }
    }

    /// Takes `amount`, first waiting as long as the rate requires.
    pub async fn take(&mut self, amount: u64) {
        let now = Instant::now();
        let earned = now.duration_since(self.last).as_secs_f64() * self.per_second;
        self.tokens = (self.tokens + earned).min(self.burst);
        self.last = now;
        self.tokens -= amount as f64;
        if self.tokens < 0.0 {
            let wait = Duration::from_secs_f64(-self.tokens / self.per_second);
            tokio::time::sleep(wait).await;
            self.tokens = 0.0;
            self.last = Instant::now();
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[tokio::test(start_paused = true)]
    async fn keeps_the_average_with_bursts_and_large_items() {
        let start = Instant::now();
        let mut pace = Pace::new(1000);
        for _ in 0..100 {
            pace.take(50).await;
        }
        // 5,000 units at 1,000/s, less the first burst of 100.
        let elapsed = start.elapsed().as_secs_f64();
        assert!((4.8..=5.0).contains(&elapsed), "{elapsed}");
        let start = Instant::now();
        pace.take(3000).await;
        assert!(
            start.elapsed() >= Duration::from_secs(3),
            "larger than the burst still waits its share"
        );
    }
}
