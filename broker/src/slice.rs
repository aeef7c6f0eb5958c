//! Long work in time slices: the stall budget. No single piece of work may
//! keep a runtime thread longer than [`SLICE`]: work whose size a client
//! chooses (purging a queue of a million messages, requeueing a closed
//! channel's deliveries, deleting a connection's exclusive queues,
//! expiring a backlog, one publish fanned out to thousands of queues) runs
//! as steps that check a [`Slice`] and stop when it is spent; between
//! slices the task yields, so every other connection is served.
//!
//! Used by the queue, the vhost and the channel; uses only tokio.

use std::time::{Duration, Instant};

/// The longest a slice of work runs before it yields.
pub const SLICE: Duration = Duration::from_micros(500);

/// Steps between clock readings: a step is a few hundred nanoseconds of
/// work at most, so a slice overruns by well under a millisecond.
const STEPS_PER_CHECK: u32 = 32;

/// The time one slice of work may still use. The clock is first read at
/// the first check, not at the start: most slices (one publish to a few
/// queues) end before that, and read no clock at all.
#[derive(Debug, Default)]
pub struct Slice {
    started: Option<Instant>,
    steps: u32,
    spent: bool,
}

impl Slice {
    /// A slice starting now.
    pub fn start() -> Self {
        Slice::default()
    }

    /// Counts one step; true once the slice is spent (the caller stops
    /// and comes back in the next slice).
    pub fn step(&mut self) -> bool {
        self.steps += 1;
        if self.steps % STEPS_PER_CHECK == 0 {
            self.is_spent()
        } else {
            self.spent
        }
    }

    /// Whether the slice is spent, reading the clock now.
    pub fn is_spent(&mut self) -> bool {
        if !self.spent {
            let started = *self.started.get_or_insert_with(Instant::now);
            self.spent = started.elapsed() >= SLICE;
        }
        self.spent
    }
}

/// Whether a sliced piece of work has more to do.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Progress {
    /// Nothing is left.
    Done,
    /// The slice was spent first: call again.
    More,
}

/// Runs `step` until it is [`Progress::Done`]: the first slice now, the
/// rest in a task that yields between slices, so the caller returns at
/// once whatever the size of the work. Without a tokio runtime (unit tests
/// of the core) it all runs now.
pub fn finish_in_background<F>(mut step: F)
where
    F: FnMut(&mut Slice) -> Progress + Send + 'static,
{
    if step(&mut Slice::start()) == Progress::Done {
        return;
    }
    match tokio::runtime::Handle::try_current() {
        Ok(runtime) => {
            runtime.spawn(async move {
                loop {
                    tokio::task::yield_now().await;
                    if step(&mut Slice::start()) == Progress::Done {
                        break;
                    }
                }
            });
        }
        Err(_) => while step(&mut Slice::start()) == Progress::More {},
    }
}

/// Yields to the runtime when `slice` is spent, and starts a new one.
pub async fn yield_if_spent(slice: &mut Slice) {
    if slice.step() {
        tokio::task::yield_now().await;
        *slice = Slice::start();
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_slice_is_spent_after_its_time() {
        let mut slice = Slice::start();
        assert!(!slice.step());
        assert!(!slice.is_spent(), "the clock starts at the first reading");
        std::thread::sleep(SLICE + Duration::from_millis(1));
        // Read only every few steps.
        let spent_at = (0..STEPS_PER_CHECK).position(|_| slice.step());
        assert!(spent_at.is_some());
        assert!(slice.is_spent());
    }

    #[test]
    fn work_without_a_runtime_runs_to_the_end() {
        let left = std::sync::Arc::new(std::sync::atomic::AtomicUsize::new(10));
        let counter = std::sync::Arc::clone(&left);
        finish_in_background(move |_| {
            match counter.fetch_sub(1, std::sync::atomic::Ordering::Relaxed) {
                1 => Progress::Done,
                _ => Progress::More,
            }
        });
        assert_eq!(left.load(std::sync::atomic::Ordering::Relaxed), 0);
    }
}
