//! How a thread blocked in [`crate::InPort::recv_blocking`] may wait
//! before it sleeps, when its profile asks for it
//! ([`crate::PortProfile::spin`]): a bounded adaptive spin
//! ([`AdaptiveSpin`]). Waking a thread from a condition variable costs some
//! 10 µs on a loaded machine; a value that comes within the spin (a
//! back-to-back exchange, the next value of a burst) is taken by the
//! spinning thread itself, with no wake at all.
//!
//! The spin is bounded and adapts, as an adaptive mutex does: it looks
//! for at most its budget (between [`MIN_SPIN`], or the ceiling if lower,
//! and the profile's ceiling), then yields the processor [`YIELDS`] times,
//! then the caller sleeps. A wait that ended in the spin or the yields
//! doubles the budget; one that had to sleep halves it, so a port whose
//! values come seldom (a 1 kHz loop, an idle port) spins [`MIN_SPIN`] per
//! wait and costs next to no CPU. A wait whose deadline has already passed
//! neither spins nor yields, and leaves the budget as it was.

use std::sync::atomic::{AtomicU32, Ordering};
use std::time::{Duration, Instant};

/// The least a wait spins.
pub(crate) const MIN_SPIN: Duration = Duration::from_micros(2);

/// The budget a port starts with (or its ceiling, if lower).
const FIRST_SPIN: Duration = Duration::from_micros(16);

/// How often a wait yields the processor after its spin, before sleeping.
pub(crate) const YIELDS: u32 = 2;

/// Looks between two readings of the clock.
const LOOKS_PER_CLOCK: u32 = 8;

/// A wait's spin budget, adapted to how the port's values have come.
#[derive(Debug)]
pub(crate) struct AdaptiveSpin {
    budget_ns: AtomicU32,
    floor_ns: u32,
    ceiling_ns: u32,
}

fn nanos(duration: Duration) -> u32 {
    u32::try_from(duration.as_nanos()).unwrap_or(u32::MAX)
}

impl AdaptiveSpin {
    /// A spin whose budget never passes `ceiling`; `None` if `ceiling` is
    /// zero (no spin at all).
    pub(crate) fn up_to(ceiling: Duration) -> Option<Self> {
        let ceiling_ns = nanos(ceiling);
        (ceiling_ns > 0).then(|| AdaptiveSpin {
            budget_ns: AtomicU32::new(nanos(FIRST_SPIN).min(ceiling_ns)),
            floor_ns: nanos(MIN_SPIN).min(ceiling_ns),
            ceiling_ns,
        })
    }

    /// What the next wait may spin.
    pub(crate) fn budget(&self) -> Duration {
        Duration::from_nanos(u64::from(self.budget_ns.load(Ordering::Relaxed)))
    }

    /// Calls `look` until it finds something, spinning up to the budget
    /// (and never past `deadline`), then yielding [`YIELDS`] times; `None`
    /// if it found nothing: the caller sleeps. Adapts the budget to the
    /// result. With `deadline` already passed it neither looks nor yields
    /// and leaves the budget alone: the caller's one look is all there is.
    pub(crate) fn wait<R>(
        &self,
        deadline: Instant,
        mut look: impl FnMut() -> Option<R>,
    ) -> Option<R> {
        let start = Instant::now();
        if start >= deadline {
            return None;
        }
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
    /// time (up to the ceiling).
    fn caught(&self) {
        let budget = self.budget_ns.load(Ordering::Relaxed);
        let doubled = budget.saturating_mul(2).min(self.ceiling_ns);
        self.budget_ns.store(doubled, Ordering::Relaxed);
    }

    /// The thread had to sleep: spin less next time (down to the floor).
    fn missed(&self) {
        let budget = self.budget_ns.load(Ordering::Relaxed);
        let halved = (budget / 2).max(self.floor_ns);
        self.budget_ns.store(halved, Ordering::Relaxed);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const CEILING: Duration = Duration::from_micros(64);

    fn spin() -> AdaptiveSpin {
        AdaptiveSpin::up_to(CEILING).expect("a ceiling above zero")
    }

    fn far() -> Instant {
        Instant::now() + Duration::from_secs(60)
    }

    #[test]
    fn waits_that_must_sleep_bring_the_budget_down_to_its_floor() {
        let spin = spin();
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
        let spin = spin();
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
    fn a_wait_past_its_deadline_neither_looks_nor_changes_the_budget() {
        let spin = spin();
        let before = spin.budget();
        let mut looks = 0;
        let found = spin.wait(Instant::now(), || {
            looks += 1;
            None::<()>
        });
        assert_eq!(found, None);
        assert_eq!(looks, 0, "no spin and no yields: the caller looked once");
        assert_eq!(spin.budget(), before, "the budget is left as it was");
    }

    #[test]
    fn the_budget_stays_under_a_lower_ceiling_and_a_zero_ceiling_is_no_spin() {
        assert!(AdaptiveSpin::up_to(Duration::ZERO).is_none());
        let low = AdaptiveSpin::up_to(Duration::from_micros(1)).expect("spin");
        assert_eq!(low.budget(), Duration::from_micros(1));
        assert_eq!(low.wait(far(), || None::<()>), None);
        assert_eq!(low.budget(), Duration::from_micros(1), "floor = ceiling");
        let found = low.wait(far(), || Some(()));
        assert_eq!(found, Some(()));
        assert_eq!(low.budget(), Duration::from_micros(1), "never above it");
    }
}
