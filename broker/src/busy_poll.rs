//! Busy polling: for a short window after a connection has read from its
//! socket, the broker keeps its thread polling for more input instead of
//! sleeping in the kernel.
//!
//! A request and its answer usually come in pairs a few tens of
//! microseconds apart (a publish and the consumer's ack, a ping and its
//! echo). If the broker's thread sleeps in between, the answer has to wake
//! it, and on a virtual machine whose idle vCPUs halt that wake costs more
//! than the work itself. Erlang's schedulers spin before they sleep for the
//! same reason (RabbitMQ's "scheduler busy waiting"); Linux offers it for
//! sockets as `SO_BUSY_POLL`.
//!
//! The spinner is one task that yields in a loop while the window is open.
//! Each yield lets the runtime poll its I/O driver without blocking, so
//! input that arrives during the window is found by polling, not by a
//! wake-up. It only works on a runtime whose polling thread is the thread
//! the spinner runs on: a current-thread runtime, as the `leveret` binary
//! uses. When no connection has read anything for a whole window the
//! spinner sleeps until the next read, so an idle broker does not spin.

use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::time::{Duration, Instant};
use tokio::sync::{watch, Notify};

/// The window the spinner starts from when input begins to arrive in
/// quick succession, as Linux's haltpoll governor grows its poll time.
const GROW_START: Duration = Duration::from_micros(50);

/// The shared state between the connections' readers and the spinner.
#[derive(Debug)]
pub struct BusyPoll {
    /// The longest the spinner polls after a read.
    max_window: Duration,
    /// The first window when reads begin to come close together.
    grow_start: Duration,
    /// Socket reads so far; the spinner watches it move.
    reads: AtomicU64,
    /// The spinner is asleep and wants `wake` on the next read.
    asleep: AtomicBool,
    /// Windows the spinner has polled through, and their total length in
    /// nanoseconds (read by `inspect`).
    windows: AtomicU64,
    spun_nanos: AtomicU64,
    wake: Notify,
}

impl BusyPoll {
    /// Polls for at most `max_window` after each read.
    pub fn new(max_window: Duration) -> Self {
        BusyPoll {
            max_window,
            grow_start: GROW_START,
            reads: AtomicU64::new(0),
            asleep: AtomicBool::new(false),
            windows: AtomicU64::new(0),
            spun_nanos: AtomicU64::new(0),
            wake: Notify::new(),
        }
    }

    /// A connection has read bytes from its socket.
    pub fn note_read(&self) {
        self.reads.fetch_add(1, Ordering::Relaxed);
        if self.asleep.load(Ordering::Relaxed) {
            self.asleep.store(false, Ordering::Relaxed);
            self.wake.notify_one();
        }
    }

    /// Spins while reads keep coming within the window and sleeps
    /// otherwise, until the broker shuts down.
    ///
    /// The window adapts to the gaps between reads; see [`next_window`].
    pub async fn run(&self, mut shutdown: watch::Receiver<bool>) {
        let mut window = Duration::ZERO;
        let mut last_read = Instant::now();
        loop {
            self.asleep.store(true, Ordering::Relaxed);
            tokio::select! {
                _ = self.wake.notified() => {}
                _ = shutdown.wait_for(|down| *down) => return,
            }
            let woke = Instant::now();
            window = next_window(window, woke - last_read, self.grow_start, self.max_window);
            last_read = woke;
            let mut seen = self.reads.load(Ordering::Relaxed);
            loop {
                let now = Instant::now();
                let reads = self.reads.load(Ordering::Relaxed);
                if reads != seen {
                    seen = reads;
                    last_read = now;
                } else if now - last_read >= window {
                    break;
                }
                // Clients that keep sending must not hold shutdown up.
                if *shutdown.borrow() {
                    return;
                }
                // Lets the runtime poll its I/O driver without blocking
                // and run whatever that made ready.
                tokio::task::yield_now().await;
                // Lets a client process woken onto this CPU run at once.
                std::thread::yield_now();
            }
            self.windows.fetch_add(1, Ordering::Relaxed);
            let spun = woke.elapsed().as_nanos() as u64;
            self.spun_nanos.fetch_add(spun, Ordering::Relaxed);
        }
    }

    /// Socket reads noted, windows polled through, and the time spent
    /// polling.
    pub fn figures(&self) -> (u64, u64, Duration) {
        (
            self.reads.load(Ordering::Relaxed),
            self.windows.load(Ordering::Relaxed),
            Duration::from_nanos(self.spun_nanos.load(Ordering::Relaxed)),
        )
    }
}

/// The spin window after a read that woke the sleeping spinner, `quiet`
/// after the read before it. This is how Linux's haltpoll governor adapts
/// its poll time: a read within `max` of the one before means a longer
/// window would have caught it, so the window doubles (from `grow_start`,
/// up to `max`); a read after a longer quiet spell halves it, down to no
/// spinning at all. Traffic whose gaps are all longer than `max` (a 1 kHz
/// sensor, say) therefore costs no spinning.
fn next_window(window: Duration, quiet: Duration, grow_start: Duration, max: Duration) -> Duration {
    if quiet <= max {
        (window * 2).clamp(grow_start.min(max), max)
    } else if window / 2 < grow_start {
        Duration::ZERO
    } else {
        window / 2
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const MAX: Duration = Duration::from_micros(200);

    fn micros(n: u64) -> Duration {
        Duration::from_micros(n)
    }

    #[test]
    fn quick_reads_grow_the_window_from_the_start_value_up_to_the_maximum() {
        let mut window = Duration::ZERO;
        let mut seen = Vec::new();
        for _ in 0..4 {
            window = next_window(window, micros(120), GROW_START, MAX);
            seen.push(window.as_micros());
        }
        assert_eq!(seen, [50, 100, 200, 200]);
    }

    #[test]
    fn slow_reads_shrink_the_window_to_nothing() {
        let mut window = MAX;
        let mut seen = Vec::new();
        for _ in 0..4 {
            window = next_window(window, Duration::from_millis(10), GROW_START, MAX);
            seen.push(window.as_micros());
        }
        assert_eq!(seen, [100, 50, 0, 0]);
    }

    #[test]
    fn a_maximum_below_the_start_value_caps_the_first_window() {
        assert_eq!(
            next_window(Duration::ZERO, micros(10), GROW_START, micros(20)),
            micros(20)
        );
    }

    #[tokio::test(flavor = "current_thread")]
    async fn a_spinning_runtime_still_serves_timers_and_other_threads_and_shuts_down() {
        // An hour-long window: once woken, the spinner only stops for
        // shutdown.
        let hour = Duration::from_secs(3600);
        let busy_poll = std::sync::Arc::new(BusyPoll {
            grow_start: hour,
            ..BusyPoll::new(hour)
        });
        let (stop, shutdown) = watch::channel(false);
        let spinner = tokio::spawn({
            let busy_poll = std::sync::Arc::clone(&busy_poll);
            async move { busy_poll.run(shutdown).await }
        });
        tokio::task::yield_now().await;
        busy_poll.note_read();
        tokio::time::sleep(Duration::from_millis(5)).await;
        let (sent, received) = tokio::sync::oneshot::channel();
        std::thread::spawn(move || sent.send(()));
        received.await.expect("a wake from another thread arrives");
        assert!(!spinner.is_finished());
        stop.send_replace(true);
        tokio::time::timeout(Duration::from_secs(5), spinner)
            .await
            .expect("the spinner stops at shutdown")
            .expect("the spinner does not panic");
    }
}
