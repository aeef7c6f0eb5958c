//! How a thread blocked in [`crate::InPort::recv_blocking`] waits before it
//! sleeps: a bounded adaptive spin ([`AdaptiveSpin`]). Waking a thread
//! from a condition variable costs some 10 µs on a loaded machine; a value
//! that comes a few microseconds after the receiver started waiting (a
//! back-to-back exchange, the next value of a burst) is taken by the
//! spinning thread itself, with no wake at all.
//!
//! The spin is bounded and adapts, as an adaptive mutex does: it looks
//! for at most its budget (between [`MIN_SPIN`] and [`MAX_SPIN`]), then
//! yields the processor [`YIELDS`] times, then the caller sleeps. A wait
//! that ended in the spin or the yields doubles the budget; one that had
//! to sleep halves it, so a port whose values come seldom (a 1 kHz loop,
//! an idle port) spins [`MIN_SPIN`] per wait and costs next to no CPU.

use std::sync::atomic::{AtomicU32, Ordering};
use std::time::{Duration, Instant};

/// The least a wait spins.
pub(crate) const MIN_SPIN: Duration = Duration::from_micros(2);

/// The most a wait spins.
pub(crate) const MAX_SPIN: Duration = Duration::from_micros(64);

/// The budget a port starts with.
const FIRST_SPIN: Duration = Duration::from_micros(16);

/// How often a wait yields the processor after its spin, before sleeping.
pub(crate) const YIELDS: u32 = 2;

/// Looks between two readings of the clock.
const LOOKS_PER_CLOCK: u32 = 8;

/// A wait's spin budget, adapted to how the port's values have come.
#[derive(Debug)]
pub(crate) struct AdaptiveSpin {
    budget_ns: AtomicU32,
}

impl Default for AdaptiveSpin {
    fn default() -> Self {
        AdaptiveSpin {
            budget_ns: AtomicU32::new(nanos(FIRST_SPIN)),
        }
    }
}

fn nanos(duration: Duration) -> u32 {
    u32::try_from(duration.as_nanos()).unwrap_or(u32::MAX)
}

impl AdaptiveSpin {
    /// What the next wait may spin.
    pub(crate) fn budget(&self) -> Duration {
        Duration::from_nanos(u64::from(self.budget_ns.load(Ordering::Relaxed)))
    }

    /// Calls `look` until it finds something, spinning up to the budget
    /// (and never past `deadline`), then yielding [`YIELDS`] times; `None`
    /// if it found nothing: the caller sleeps. Adapts the budget to the
    /// result.
    pub(crate) fn wait<R>(
        &self,
        deadline: Instant,
        mut look: impl FnMut() -> Option<R>,
    ) -> Option<R> {
        let start = Instant::now();
        let spin_until = (start + self.budget()).min(deadline);
        let mut now = start;
        while now < spin_until {
            for _ in 0..LOOKS_PER_CLOCK {
                if let Some(found) = look() {
                    self.caught();
                    return Some(found);
                }
                std::hint::spin_loop();
            }
            now = Instant::now();
        }
        for _ in 0..YIELDS {
            std::thread::yield_now();
            if let Some(found) = look() {
                self.caught();
                return Some(found);
            }
        }
        self.missed();
        None
    }

    /// A value came while the thread spun or yielded: spin longer next
    /// time (up to [`MAX_SPIN`]).
    fn caught(&self) {
        let budget = self.budget_ns.load(Ordering::Relaxed);
        let doubled = budget.saturating_mul(2).min(nanos(MAX_SPIN));
        self.budget_ns.store(doubled, Ordering::Relaxed);
    }

    /// The thread had to sleep: spin less next time (down to
    /// [`MIN_SPIN`]).
    fn missed(&self) {
        let budget = self.budget_ns.load(Ordering::Relaxed);
        let halved = (budget / 2).max(nanos(MIN_SPIN));
        self.budget_ns.store(halved, Ordering::Relaxed);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn far() -> Instant {
        Instant::now() + Duration::from_secs(60)
    }

    #[test]
    fn waits_that_must_sleep_bring_the_budget_down_to_its_floor() {
        let spin = AdaptiveSpin::default();
        let mut budgets = Vec::new();
        for _ in 0..8 {
            assert_eq!(spin.wait(far(), || None::<()>), None);
            budgets.push(spin.budget());
        }
        assert_eq!(
            budgets[..4],
            [8, 4, 2, 2].map(Duration::from_micros),
            "halved on each sleep, never below the floor"
        );
        assert_eq!(*budgets.last().unwrap(), MIN_SPIN);
    }

    #[test]
    fn caught_values_raise_the_budget_to_its_ceiling() {
        let spin = AdaptiveSpin::default();
        let mut budgets = Vec::new();
        for _ in 0..4 {
            let mut looks = 0;
            let found = spin.wait(far(), || {
                looks += 1;
                (looks == 3).then_some(looks)
            });
            assert_eq!(found, Some(3), "found on the third look, no sleep");
            budgets.push(spin.budget());
        }
        assert_eq!(budgets, [32, 64, 64, 64].map(Duration::from_micros));
    }

    #[test]
    fn a_wait_looks_in_its_yields_too_and_stops_at_the_deadline() {
        let spin = AdaptiveSpin::default();
        // A deadline already past: no spin, but each yield still looks.
        let mut looks = 0;
        let found = spin.wait(Instant::now(), || {
            looks += 1;
            None::<()>
        });
        assert_eq!(found, None);
        assert_eq!(looks, YIELDS, "one look per yield, none spinning");
    }
}
