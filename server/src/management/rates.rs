//! Message rates for the management API (`*_details: {"rate": r}`), as
//! RabbitMQ's "basic" rates mode gives them: the change per second between
//! the last two samples, taken every [`SAMPLE_EVERY`] by a task on the
//! listeners' thread. Queues are sampled a chunk at a time with yields in
//! between; a queue that is gone drops out of the table at the next pass,
//! so the table holds one entry per live queue.
//!
//! The broker-wide figures are also kept for [`HISTORY`] (a ring of
//! [`HISTORY_SAMPLES`] samples, about 15 KB), which `/api/overview` gives
//! as RabbitMQ's `samples` when asked with `msg_rates_age` /
//! `lengths_age` (see [`History`]); the status page draws its charts from
//! them.

use leveret_broker::{Admin, Overview, QueueInfo};
use std::collections::{HashMap, VecDeque};
use std::sync::{Arc, Mutex, MutexGuard};
use std::time::{Duration, Instant, SystemTime};
use tokio::sync::watch;

/// How often counters are sampled (RabbitMQ's default collect_statistics_interval).
pub const SAMPLE_EVERY: Duration = Duration::from_secs(5);
/// How far back the broker-wide samples go (RabbitMQ's default retention
/// of global samples at 5 s resolution is 605 s).
pub const HISTORY: Duration = Duration::from_secs(600);
/// The broker-wide samples kept: [`HISTORY`] at [`SAMPLE_EVERY`], and the
/// one that starts it.
pub const HISTORY_SAMPLES: usize = (HISTORY.as_secs() / SAMPLE_EVERY.as_secs()) as usize + 1;
/// Queues sampled between two yields.
const CHUNK: usize = 1000;

/// A rate, per second.
pub type Rate = f64;

/// The rates of one queue.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct QueueRates {
    pub messages: Rate,
    pub messages_ready: Rate,
    pub messages_unacknowledged: Rate,
    pub publish: Rate,
    pub deliver: Rate,
    pub deliver_no_ack: Rate,
    pub get: Rate,
    pub get_no_ack: Rate,
    pub get_empty: Rate,
    pub deliver_get: Rate,
    pub redeliver: Rate,
    pub ack: Rate,
}

/// The broker-wide rates of `/api/overview`.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct OverviewRates {
    pub publish: Rate,
    pub confirm: Rate,
    pub return_unroutable: Rate,
    pub drop_unroutable: Rate,
    pub deliver: Rate,
    pub deliver_no_ack: Rate,
    pub get: Rate,
    pub get_no_ack: Rate,
    pub get_empty: Rate,
    pub deliver_get: Rate,
    pub redeliver: Rate,
    pub ack: Rate,
    pub messages: Rate,
    pub messages_ready: Rate,
    pub messages_unacknowledged: Rate,
}

const QUEUE_FIGURES: usize = 12;
/// How many broker-wide figures are sampled, in [`OverviewFigure`]'s order.
pub const OVERVIEW_FIGURES: usize = 15;

/// The broker-wide figures, in the order they are sampled (the index of
/// each in a sample).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum OverviewFigure {
    Publish,
    Confirm,
    ReturnUnroutable,
    DropUnroutable,
    Deliver,
    DeliverNoAck,
    Get,
    GetNoAck,
    GetEmpty,
    DeliverGet,
    Redeliver,
    Ack,
    Messages,
    MessagesReady,
    MessagesUnacknowledged,
}

fn queue_figures(q: &QueueInfo) -> [f64; QUEUE_FIGURES] {
    let m = &q.message_stats;
    [
        q.messages(),
        q.messages_ready,
        q.messages_unacknowledged,
        m.publish,
        m.deliver,
        m.deliver_no_ack,
        m.get,
        m.get_no_ack,
        m.get_empty,
        m.deliver_get(),
        m.redeliver,
        m.ack,
    ]
    .map(|v| v as f64)
}

fn overview_figures(o: &Overview) -> [f64; OVERVIEW_FIGURES] {
    let m = &o.message_stats;
    let q = &o.queue_totals;
    [
        m.received,
        m.confirmed,
        m.unroutable_returned,
        m.unroutable_dropped,
        m.delivered_consume_manual_ack,
        m.delivered_consume_auto_ack,
        m.delivered_get_manual_ack,
        m.delivered_get_auto_ack,
        m.get_empty,
        m.delivered(),
        m.redelivered,
        m.acknowledged,
        q.messages(),
        q.messages_ready,
        q.messages_unacknowledged,
    ]
    .map(|v| v as f64)
}

/// The last two samples of some figures.
#[derive(Debug, Clone, Copy)]
struct Window<const N: usize> {
    previous: Option<(Instant, [f64; N])>,
    latest: (Instant, [f64; N]),
}

impl<const N: usize> Window<N> {
    fn new(at: Instant, figures: [f64; N]) -> Self {
        Window {
            previous: None,
            latest: (at, figures),
        }
    }

    fn push(&mut self, at: Instant, figures: [f64; N]) {
        self.previous = Some(self.latest);
        self.latest = (at, figures);
    }

    fn rates(&self) -> [Rate; N] {
        let Some((then, before)) = self.previous else {
            return [0.0; N];
        };
        let (now, after) = self.latest;
        let seconds = now.duration_since(then).as_secs_f64();
        if seconds <= 0.0 {
            return [0.0; N];
        }
        std::array::from_fn(|i| (after[i] - before[i]) / seconds)
    }
}

#[derive(Debug, Default)]
struct Samples {
    overview: Option<Window<OVERVIEW_FIGURES>>,
    history: VecDeque<(u64, [f64; OVERVIEW_FIGURES])>,
    queues: HashMap<(String, String), Window<QUEUE_FIGURES>>,
}

impl Samples {
    /// Adds a broker-wide sample to the ring, dropping the oldest when full.
    fn remember(&mut self, at_ms: u64, figures: [f64; OVERVIEW_FIGURES]) {
        if self.history.len() == HISTORY_SAMPLES {
            self.history.pop_front();
        }
        self.history.push_back((at_ms, figures));
    }
}

/// One figure's past as RabbitMQ's API gives it when asked for `samples`
/// over `age` seconds every `incr` seconds: the value at each multiple of
/// `incr` from the present's back to `age` before it (the last sample
/// taken in that step; steps without one are absent), newest first, with `avg_rate` (the change per second from the
/// oldest to the newest) and `avg` (their mean).
#[derive(Debug, Clone, PartialEq)]
pub struct History {
    /// (timestamp in milliseconds since the Unix epoch, value), newest first.
    pub samples: Vec<(u64, f64)>,
    pub avg_rate: f64,
    pub avg: f64,
}

/// Picks `figure`'s samples from `ring` (oldest first) as [`History`]
/// describes, `now_ms` being the present; `incr_secs` is at least 1.
fn history_of(
    ring: &VecDeque<(u64, [f64; OVERVIEW_FIGURES])>,
    figure: OverviewFigure,
    age_secs: u64,
    incr_secs: u64,
    now_ms: u64,
) -> History {
    let step = incr_secs.saturating_mul(1000);
    let oldest = (now_ms - now_ms % step).saturating_sub(age_secs.saturating_mul(1000));
    let mut samples: Vec<(u64, f64)> = Vec::new();
    for (at, figures) in ring.iter().rev() {
        let aligned = at - at % step;
        if aligned < oldest {
            break;
        }
        if samples.last().is_none_or(|(last, _)| *last != aligned) {
            samples.push((aligned, figures[figure as usize]));
        }
    }
    let avg = if samples.is_empty() {
        0.0
    } else {
        samples.iter().map(|(_, v)| v).sum::<f64>() / samples.len() as f64
    };
    let avg_rate = match (samples.first(), samples.last()) {
        (Some((newest_at, newest)), Some((oldest_at, oldest))) if newest_at > oldest_at => {
            (newest - oldest) / ((newest_at - oldest_at) as f64 / 1000.0)
        }
        _ => 0.0,
    };
    History {
        samples,
        avg_rate,
        avg,
    }
}

fn unix_millis(at: SystemTime) -> u64 {
    at.duration_since(SystemTime::UNIX_EPOCH)
        .map_or(0, |since| since.as_millis() as u64)
}

/// The sampled rates, shared by the sampler and the request handlers.
#[derive(Debug, Default, Clone)]
pub struct Rates {
    samples: Arc<Mutex<Samples>>,
}

impl Rates {
    fn lock(&self) -> MutexGuard<'_, Samples> {
        self.samples.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// Rates of queue `name` in `vhost` (zero until sampled twice).
    pub fn queue(&self, vhost: &str, name: &str) -> QueueRates {
        let key = (vhost.to_owned(), name.to_owned());
        let r = self
            .lock()
            .queues
            .get(&key)
            .map(Window::rates)
            .unwrap_or_default();
        QueueRates {
            messages: r[0],
            messages_ready: r[1],
            messages_unacknowledged: r[2],
            publish: r[3],
            deliver: r[4],
            deliver_no_ack: r[5],
            get: r[6],
            get_no_ack: r[7],
            get_empty: r[8],
            deliver_get: r[9],
            redeliver: r[10],
            ack: r[11],
        }
    }

    /// Broker-wide rates (zero until sampled twice).
    pub fn overview(&self) -> OverviewRates {
        let r = self.lock().overview.map(|w| w.rates()).unwrap_or_default();
        OverviewRates {
            publish: r[0],
            confirm: r[1],
            return_unroutable: r[2],
            drop_unroutable: r[3],
            deliver: r[4],
            deliver_no_ack: r[5],
            get: r[6],
            get_no_ack: r[7],
            get_empty: r[8],
            deliver_get: r[9],
            redeliver: r[10],
            ack: r[11],
            messages: r[12],
            messages_ready: r[13],
            messages_unacknowledged: r[14],
        }
    }

    /// `figure`'s broker-wide samples of the last `age_secs` seconds, one
    /// every `incr_secs` (at least 1) seconds.
    pub fn history(&self, figure: OverviewFigure, age_secs: u64, incr_secs: u64) -> History {
        let now = unix_millis(SystemTime::now());
        history_of(&self.lock().history, figure, age_secs, incr_secs, now)
    }

    /// Takes one sample of everything.
    pub async fn sample(&self, admin: &Admin) {
        let refs = admin.queue_refs();
        let mut seen = Vec::with_capacity(refs.len());
        for chunk in refs.chunks(CHUNK) {
            let now = Instant::now();
            let infos: Vec<QueueInfo> = chunk.iter().map(|q| q.info()).collect();
            {
                let mut samples = self.lock();
                for info in infos {
                    let figures = queue_figures(&info);
                    let key = (info.vhost, info.name);
                    match samples.queues.get_mut(&key) {
                        Some(window) => window.push(now, figures),
                        None => {
                            samples
                                .queues
                                .insert(key.clone(), Window::new(now, figures));
                        }
                    }
                    seen.push(key);
                }
            }
            tokio::task::yield_now().await;
        }
        let overview = admin.overview();
        let now = Instant::now();
        let figures = overview_figures(&overview);
        let mut samples = self.lock();
        samples.remember(unix_millis(SystemTime::now()), figures);
        match &mut samples.overview {
            Some(window) => window.push(now, figures),
            None => samples.overview = Some(Window::new(now, figures)),
        }
        let seen: std::collections::HashSet<(String, String)> = seen.into_iter().collect();
        samples.queues.retain(|key, _| seen.contains(key));
    }

    /// Samples every [`SAMPLE_EVERY`] until `stop` turns true.
    pub async fn run(self, admin: Admin, mut stop: watch::Receiver<bool>) {
        let mut ticker = tokio::time::interval(SAMPLE_EVERY);
        ticker.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
        loop {
            tokio::select! {
                _ = ticker.tick() => self.sample(&admin).await,
                _ = stop.wait_for(|stop| *stop) => return,
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_rate_is_the_change_per_second_between_the_last_two_samples() {
        let start = Instant::now();
        let mut window = Window::new(start, [10.0, 5.0]);
        assert_eq!(window.rates(), [0.0, 0.0]);
        window.push(start + Duration::from_secs(2), [30.0, 1.0]);
        assert_eq!(window.rates(), [10.0, -2.0]);
        window.push(start + Duration::from_secs(4), [30.0, 1.0]);
        assert_eq!(window.rates(), [0.0, 0.0]);
    }

    fn figures(publish: f64, messages: f64) -> [f64; OVERVIEW_FIGURES] {
        let mut figures = [0.0; OVERVIEW_FIGURES];
        figures[OverviewFigure::Publish as usize] = publish;
        figures[OverviewFigure::Messages as usize] = messages;
        figures
    }

    #[test]
    fn the_history_ring_keeps_ten_minutes_and_drops_the_oldest() {
        let mut samples = Samples::default();
        for i in 0..(HISTORY_SAMPLES as u64 * 3) {
            samples.remember(i * 5000, figures(i as f64, 0.0));
        }
        assert_eq!(samples.history.len(), HISTORY_SAMPLES);
        let oldest = samples.history.front().expect("samples").0;
        assert_eq!(oldest, (HISTORY_SAMPLES as u64 * 2) * 5000);
    }

    #[test]
    fn history_is_newest_first_aligned_to_the_step_within_the_age() {
        let mut samples = Samples::default();
        // Samples a little after each 5 s mark: 1000.2 s, 1005.2 s, ...
        for i in 0..10u64 {
            samples.remember(1_000_200 + i * 5000, figures(10.0 * i as f64, i as f64));
        }
        let now = 1_045_300;
        let h = history_of(&samples.history, OverviewFigure::Publish, 20, 5, now);
        let at: Vec<u64> = h.samples.iter().map(|(at, _)| *at).collect();
        assert_eq!(at, [1_045_000, 1_040_000, 1_035_000, 1_030_000, 1_025_000]);
        let values: Vec<f64> = h.samples.iter().map(|(_, v)| *v).collect();
        assert_eq!(values, [90.0, 80.0, 70.0, 60.0, 50.0]);
        assert_eq!(h.avg_rate, 2.0, "40 more in 20 s");
        assert_eq!(h.avg, 70.0);
        // Every 10 s: the last sample of each 10 s step.
        let h = history_of(&samples.history, OverviewFigure::Messages, 20, 10, now);
        assert_eq!(
            h.samples,
            [(1_040_000, 9.0), (1_030_000, 7.0), (1_020_000, 5.0)]
        );
    }

    #[test]
    fn history_before_any_sample_is_empty() {
        let h = history_of(&VecDeque::new(), OverviewFigure::Publish, 600, 5, 1_000_000);
        assert_eq!(
            h,
            History {
                samples: vec![],
                avg_rate: 0.0,
                avg: 0.0
            }
        );
    }
}
