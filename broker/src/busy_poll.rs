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
    /// Socket reads so far; the spinner watches it move.
    reads: AtomicU64,
    /// The spinner is asleep and wants `wake` on the next read.
    asleep: AtomicBool,
    wake: Notify,
}

impl BusyPoll {
    /// Polls for at most `max_window` after each read.
    pub fn new(max_window: Duration) -> Self {
        BusyPoll {
            max_window,
            reads: AtomicU64::new(0),
            asleep: AtomicBool::new(false),
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
            window = next_window(window, woke - last_read, self.max_window);
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
                // Lets the runtime poll its I/O driver without blocking
                // and run whatever that made ready.
                tokio::task::yield_now().await;
                // Lets a client process woken onto this CPU run at once.
                std::thread::yield_now();
            }
        }
    }
}

/// The spin window after a read that woke the sleeping spinner, `quiet`
/// after the read before it. This is how Linux's haltpoll governor adapts
/// its poll time: a read within `max` of the one before means a longer
/// window would have caught it, so the window doubles (from `GROW_START`,
/// up to `max`); a read after a longer quiet spell halves it, down to no
/// spinning at all. Traffic whose gaps are all longer than `max` (a 1 kHz
/// sensor, say) therefore costs no spinning.
fn next_window(window: Duration, quiet: Duration, max: Duration) -> Duration {
    if quiet <= max {
        (window * 2).clamp(GROW_START.min(max), max)
    } else if window / 2 < GROW_START {
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
            window = next_window(window, micros(120), MAX);
            seen.push(window.as_micros());
        }
        assert_eq!(seen, [50, 100, 200, 200]);
    }

    #[test]
    fn slow_reads_shrink_the_window_to_nothing() {
        let mut window = MAX;
        let mut seen = Vec::new();
        for _ in 0..4 {
            window = next_window(window, Duration::from_millis(10), MAX);
            seen.push(window.as_micros());
        }
        assert_eq!(seen, [100, 50, 0, 0]);
    }

    #[test]
    fn a_maximum_below_the_start_value_caps_the_first_window() {
        assert_eq!(
            next_window(Duration::ZERO, micros(10), micros(20)),
            micros(20)
        );
    }

    #[tokio::test(flavor = "current_thread")]
    async fn the_spinner_keeps_the_runtime_serving_and_stops_at_shutdown() {
        let busy_poll = std::sync::Arc::new(BusyPoll::new(MAX));
        let (stop, shutdown) = watch::channel(false);
        let spinner = tokio::spawn({
            let busy_poll = std::sync::Arc::clone(&busy_poll);
            async move { busy_poll.run(shutdown).await }
        });
        // Reads every 20 µs from another thread keep it spinning; timers
        // and wakes from other threads are still served on the one thread.
        let reader = std::thread::spawn({
            let busy_poll = std::sync::Arc::clone(&busy_poll);
            move || {
                let until = Instant::now() + Duration::from_millis(30);
                while Instant::now() < until {
                    busy_poll.note_read();
                    std::thread::sleep(Duration::from_micros(20));
                }
            }
        });
        tokio::time::sleep(Duration::from_millis(5)).await;
        let (sent, received) = tokio::sync::oneshot::channel();
        std::thread::spawn(move || sent.send(()));
        received.await.expect("a wake from another thread arrives");
        reader.join().expect("the reader thread finishes");
        stop.send_replace(true);
        tokio::time::timeout(Duration::from_secs(5), spinner)
            .await
            .expect("the spinner stops at shutdown")
            .expect("the spinner does not panic");
    }
}
