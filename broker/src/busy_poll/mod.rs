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
//!
//! Spinning is only cheap while CPUs are spare. When other threads wait
//! for a CPU (the client itself, on a small robot computer, or any other
//! busy process), every microsecond spent spinning is taken from them, and
//! a client that waits for a CPU answers later than a broker that sleeps
//! would. So the spinner reads the kernel's CPU pressure (see
//! [`cpu_pressure`]) every [`PRESSURE_SAMPLE`] while it spins, and
//! when threads waited for more than [`PRESSURE_LIMIT`] of that time it
//! stops and does not spin again for a back-off that doubles while the
//! pressure persists. Where the kernel reports no pressure it spins as
//! configured.

mod cpu_pressure;

use cpu_pressure::CpuPressure;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::time::{Duration, Instant};
use tokio::sync::{watch, Notify};

/// The window the spinner starts from when input begins to arrive in
/// quick succession, as Linux's haltpoll governor grows its poll time.
const GROW_START: Duration = Duration::from_micros(50);

/// How often a spinning spinner reads the CPU pressure.
const PRESSURE_SAMPLE: Duration = Duration::from_millis(10);

/// The share of time with threads waiting for a CPU above which spinning
/// stops.
const PRESSURE_LIMIT: f64 = 0.10;

/// The first pause in spinning after pressure was seen, and the longest
/// the doubling may reach.
const BACKOFF_START: Duration = Duration::from_millis(50);
const BACKOFF_MAX: Duration = Duration::from_secs(5);

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
    /// nanoseconds (read by `admin::inspect`).
    windows: AtomicU64,
    spun_nanos: AtomicU64,
    /// Times spinning stopped because threads were waiting for a CPU.
    yielded: AtomicU64,
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
            yielded: AtomicU64::new(0),
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
        let mut pressure = CpuPressure::open();
        if pressure.is_none() {
            tracing::debug!("no CPU pressure figures here: busy polling will not yield to them");
        }
        let mut backoff = Backoff::default();
        let mut sampled_at = last_read;
        loop {
            self.asleep.store(true, Ordering::Relaxed);
            tokio::select! {
                _ = self.wake.notified() => {}
                _ = shutdown.wait_for(|down| *down) => return,
            }
            let woke = Instant::now();
            window = next_window(window, woke - last_read, self.grow_start, self.max_window);
            last_read = woke;
            if !backoff.may_spin(woke) {
                continue;
            }
            if backoff.resuming(woke) {
                // The pause itself must not count as time spun without
                // pressure.
                if let Some(pressure) = &mut pressure {
                    pressure.rebase(woke);
                }
                sampled_at = woke;
            }
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
                if now - sampled_at >= PRESSURE_SAMPLE {
                    sampled_at = now;
                    let share = pressure.as_mut().and_then(|p| p.share_since_last(now));
                    if backoff.note(share, now) {
                        self.yielded.fetch_add(1, Ordering::Relaxed);
                        break;
                    }
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

    /// Socket reads noted, windows polled through, the time spent
    /// polling, and the times polling stopped for CPU pressure.
    pub fn figures(&self) -> (u64, u64, Duration, u64) {
        (
            self.reads.load(Ordering::Relaxed),
            self.windows.load(Ordering::Relaxed),
            Duration::from_nanos(self.spun_nanos.load(Ordering::Relaxed)),
            self.yielded.load(Ordering::Relaxed),
        )
    }
}

/// When spinning may resume after CPU pressure stopped it.
#[derive(Debug, Default)]
struct Backoff {
    /// The pause the next sign of pressure gets (zero: [`BACKOFF_START`]).
    next_pause: Duration,
    /// Spinning is paused until then.
    paused_until: Option<Instant>,
}

impl Backoff {
    /// Whether the spinner may spin at `now`.
    fn may_spin(&self, now: Instant) -> bool {
        self.paused_until.is_none_or(|until| now >= until)
    }

    /// Whether a pause has just ended (and is forgotten).
    fn resuming(&mut self, now: Instant) -> bool {
        match self.paused_until {
            Some(until) if now >= until => {
                self.paused_until = None;
                true
            }
            _ => false,
        }
    }

    /// Takes one pressure reading (`None`: nothing known) taken while
    /// spinning; whether spinning must stop. Pressure pauses spinning for
    /// a pause that doubles each time it is seen again; a reading without
    /// pressure starts the doubling over.
    fn note(&mut self, share: Option<f64>, now: Instant) -> bool {
        match share {
            Some(share) if share > PRESSURE_LIMIT => {
                let pause = self.next_pause.max(BACKOFF_START);
                self.paused_until = Some(now + pause);
                self.next_pause = (pause * 2).min(BACKOFF_MAX);
                true
            }
            Some(_) => {
                self.next_pause = Duration::ZERO;
                false
            }
            None => false,
        }
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

    #[test]
    fn pressure_pauses_spinning_for_a_doubling_pause_that_calm_resets() {
        let start = Instant::now();
        let mut backoff = Backoff::default();
        assert!(backoff.may_spin(start));
        assert!(!backoff.note(None, start), "nothing known: keep spinning");
        assert!(!backoff.note(Some(PRESSURE_LIMIT), start));
        let mut pauses = Vec::new();
        let mut now = start;
        for _ in 0..9 {
            assert!(backoff.note(Some(0.5), now));
            let until = backoff.paused_until.expect("paused");
            pauses.push((until - now).as_millis());
            assert!(!backoff.may_spin(until - Duration::from_micros(1)));
            assert!(backoff.may_spin(until));
            assert!(backoff.resuming(until));
            assert!(!backoff.resuming(until), "a pause ends once");
            now = until;
        }
        assert_eq!(pauses, [50, 100, 200, 400, 800, 1600, 3200, 5000, 5000]);
        assert!(!backoff.note(Some(0.0), now));
        assert!(backoff.note(Some(1.0), now));
        assert_eq!(backoff.paused_until, Some(now + BACKOFF_START));
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
        tokio::time::timeout(Duration::from_secs(30), spinner)
            .await
            .expect("the spinner stops at shutdown")
            .expect("the spinner does not panic");
    }
}
