//! Message rates for the management API (`*_details: {"rate": r}`), as
//! RabbitMQ's "basic" rates mode gives them: the change per second between
//! the last two samples, taken every [`SAMPLE_EVERY`] by a task on the
//! listeners' thread. Queues are sampled a chunk at a time with yields in
//! between; a queue that is gone drops out of the table at the next pass,
//! so the table holds one entry per live queue.

use leveret_broker::{Admin, Overview, QueueInfo};
use std::collections::HashMap;
use std::sync::{Arc, Mutex, MutexGuard};
use std::time::{Duration, Instant};
use tokio::sync::watch;

/// How often counters are sampled (RabbitMQ's default collect_statistics_interval).
pub const SAMPLE_EVERY: Duration = Duration::from_secs(5);
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
const OVERVIEW_FIGURES: usize = 15;

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
    queues: HashMap<(String, String), Window<QUEUE_FIGURES>>,
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
}
