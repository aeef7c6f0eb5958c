//! The `throughput` scenario: P publishers, C consumers and Q queues on an
//! exchange (direct: publisher `p` and consumer `c` use queue `p mod Q` /
//! `c mod Q`; fanout: every message reaches every queue), each publisher
//! and consumer on its own connection.
//!
//! A run declares the topology, starts the consumers, then the publishers;
//! after `warmup` seconds it measures for `duration` seconds (rates over
//! that window, latency of the deliveries received in it), printing a
//! progress line every second. Then the publishers stop (waiting for their
//! last confirms), the consumers drain until every queue with a consumer
//! has delivered everything published to it (or nothing arrives for
//! `drain_timeout` seconds), and lost / out-of-order messages are counted
//! over the whole run, warm-up included. The topology is deleted at the
//! end.

use crate::histogram::{Histogram, LatencySummary};
use crate::load::{
    connect, consume, prepare_publisher, publish, start_consumer, ConsumerSpec, ConsumerStats,
    ExchangeKind, PublisherCounters, PublisherOutcome, PublisherSpec, Topology, DEFAULT_URL,
    PHASE_DRAIN, PHASE_MEASURE, PHASE_WARMUP,
};
use crate::procfs::{find_broker_pid, CpuMeter, MachineMeter};
use crate::report::{micros, thousands};
use crate::sequence::{SeqCounts, SeqTracker};
use crate::{PerfError, Result};
use leveret_client::Connection;
use serde::Serialize;
use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, AtomicU8, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};
use tokio::task::JoinHandle;

/// Options of the `throughput` subcommand.
#[derive(Debug, Clone, clap::Args, Serialize)]
pub struct ThroughputArgs {
    /// Broker URL.
    #[arg(long, default_value = DEFAULT_URL)]
    pub url: String,
    /// Publishers, each on its own connection.
    #[arg(short = 'x', long, default_value_t = 1)]
    pub publishers: usize,
    /// Consumers, each on its own connection (0: publish only).
    #[arg(short = 'y', long, default_value_t = 1)]
    pub consumers: usize,
    /// Queues.
    #[arg(short = 'q', long, default_value_t = 1)]
    pub queues: usize,
    /// Body size in bytes (at least 8; latency needs 16).
    #[arg(short = 's', long, default_value_t = 16)]
    pub size: usize,
    /// Persistent messages on durable queues (otherwise transient on
    /// non-durable queues).
    #[arg(long)]
    pub persistent: bool,
    /// Publisher confirms with this many outstanding (0: no confirms).
    #[arg(long, default_value_t = 0, value_name = "WINDOW")]
    pub confirm: usize,
    /// Manual acknowledgements (otherwise no-ack).
    #[arg(long)]
    pub ack: bool,
    /// Prefetch count (basic.qos) of each consumer (0: none).
    #[arg(long, default_value_t = 0)]
    pub prefetch: u16,
    /// With --ack, acknowledge with `multiple` every N deliveries.
    #[arg(long, default_value_t = 1, value_name = "N")]
    pub multi_ack: u32,
    /// Exchange type.
    #[arg(long, value_enum, default_value_t = ExchangeKind::Direct)]
    pub exchange: ExchangeKind,
    /// Seconds to measure, after the warm-up.
    #[arg(long, default_value_t = 10.0)]
    pub duration: f64,
    /// Seconds of warm-up before measuring.
    #[arg(long, default_value_t = 2.0)]
    pub warmup: f64,
    /// Messages per second per publisher (0: as fast as possible).
    #[arg(long, default_value_t = 0.0)]
    pub rate: f64,
    /// Messages per publisher (0: until the duration is over).
    #[arg(long, default_value_t = 0)]
    pub count: u64,
    /// Seconds without a delivery after which draining gives up.
    #[arg(long, default_value_t = 10.0)]
    pub drain_timeout: f64,
    /// Seconds after which draining gives up even if deliveries still arrive.
    #[arg(long, default_value_t = 120.0)]
    pub drain_max: f64,
    /// PID of the broker, for its CPU use (default: found from the URL's port).
    #[arg(long)]
    pub broker_pid: Option<u32>,
    /// Write the report as JSON to this file.
    #[arg(long)]
    pub json: Option<PathBuf>,
    /// No progress lines or summary.
    #[arg(long)]
    pub quiet: bool,
}

impl Default for ThroughputArgs {
    fn default() -> Self {
        ThroughputArgs {
            url: DEFAULT_URL.to_owned(),
            publishers: 1,
            consumers: 1,
            queues: 1,
            size: 16,
            persistent: false,
            confirm: 0,
            ack: false,
            prefetch: 0,
            multi_ack: 1,
            exchange: ExchangeKind::Direct,
            duration: 10.0,
            warmup: 2.0,
            rate: 0.0,
            count: 0,
            drain_timeout: 10.0,
            drain_max: 120.0,
            broker_pid: None,
            json: None,
            quiet: false,
        }
    }
}

/// One progress line.
#[derive(Debug, Clone, Serialize)]
pub struct Progress {
    /// Seconds since the publishers started.
    pub t_s: f64,
    /// `warmup`, `measure` or `drain`.
    pub phase: &'static str,
    /// Publishes per second over the interval.
    pub publish_rate: f64,
    /// Deliveries per second over the interval.
    pub consume_rate: f64,
    /// Median latency of the interval's deliveries, µs.
    pub p50_us: f64,
    /// 99th percentile, µs.
    pub p99_us: f64,
    /// Messages published but not yet delivered (where a consumer waits).
    pub backlog: i64,
}

/// One consumer's counts.
#[derive(Debug, Clone, Serialize)]
pub struct ConsumerReport {
    /// Consumer number.
    pub id: usize,
    /// Its queue.
    pub queue: String,
    /// Sequence counts.
    #[serde(flatten)]
    pub counts: SeqCounts,
    /// Lost (only for a queue's sole consumer; see the queue otherwise).
    pub lost: Option<u64>,
}

/// One queue's counts.
#[derive(Debug, Clone, Serialize)]
pub struct QueueReport {
    /// Queue name.
    pub name: String,
    /// Messages published to it (minus nacked).
    pub expected: u64,
    /// Distinct messages its consumers received.
    pub distinct: u64,
    /// Expected minus distinct (`None` without a consumer).
    pub lost: Option<u64>,
}

/// Totals over every consumer.
#[derive(Debug, Clone, Copy, Default, Serialize)]
pub struct Totals {
    /// Deliveries.
    pub received: u64,
    /// Lost messages, summed over queues with consumers.
    pub lost: u64,
    /// Gaps in sequence (meaningful for sole consumers only).
    pub gaps: u64,
    /// Arrivals behind a later message.
    pub out_of_order: u64,
    /// Messages delivered twice.
    pub duplicates: u64,
}

/// The result of a throughput run.
#[derive(Debug, Clone, Serialize)]
pub struct ThroughputReport {
    /// The options it ran with.
    pub config: ThroughputArgs,
    /// Length of the measurement window, seconds.
    pub window_s: f64,
    /// Publishes per second over the window.
    pub publish_rate: f64,
    /// Deliveries per second over the window (all consumers).
    pub consume_rate: f64,
    /// Latency of the deliveries received in the window.
    pub latency: LatencySummary,
    /// Publish-to-confirm latency in the window (with confirms).
    pub confirm_latency: Option<LatencySummary>,
    /// Messages published over the whole run.
    pub published: u64,
    /// Of which confirmed.
    pub acked: u64,
    /// Of which refused.
    pub nacked: u64,
    /// Of which never confirmed.
    pub unconfirmed: u64,
    /// Messages published to queues with a consumer but not yet delivered
    /// when the window closed: growth here means the publishers outran
    /// the consumers (the broker did not hold them back).
    pub backlog_at_end: i64,
    /// Whether every queue with a consumer delivered everything (otherwise
    /// `lost` also counts messages still queued when draining gave up).
    pub drained: bool,
    /// Totals.
    pub totals: Totals,
    /// Per queue.
    pub queues: Vec<QueueReport>,
    /// Per consumer.
    pub consumers: Vec<ConsumerReport>,
    /// CPU use of this load generator over the window, % of one core.
    pub generator_cpu_percent: Option<f64>,
    /// The broker's PID, if found.
    pub broker_pid: Option<u32>,
    /// Its CPU use over the window, % of one core.
    pub broker_cpu_percent: Option<f64>,
    /// CPU use of every other process on the machine over the window, %
    /// of one core: a sign of how noisy the measurement was.
    pub other_cpu_percent: Option<f64>,
    /// The progress lines.
    pub progress: Vec<Progress>,
    /// Errors of publishers, if any.
    pub errors: Vec<String>,
}

/// CPU meters of the generator, the broker and the machine.
type Meters = (Option<CpuMeter>, Option<CpuMeter>, Option<MachineMeter>);

/// Counters at one instant.
#[derive(Debug, Clone, Copy)]
struct Snapshot {
    at: Instant,
    published: u64,
    consumed: u64,
}

/// What the reporter reads while the run goes on.
struct Running {
    publishers: Vec<Arc<PublisherCounters>>,
    consumers: Vec<Arc<ConsumerStats>>,
    /// For each publisher, how many queues with a consumer it reaches.
    reach: Vec<u64>,
}

impl Running {
    fn snapshot(&self) -> Snapshot {
        Snapshot {
            at: Instant::now(),
            published: self
                .publishers
                .iter()
                .map(|p| p.published.load(Ordering::Relaxed))
                .sum(),
            consumed: self
                .consumers
                .iter()
                .map(|c| c.received.load(Ordering::Relaxed))
                .sum(),
        }
    }

    fn expected_deliveries(&self) -> u64 {
        self.publishers
            .iter()
            .zip(&self.reach)
            .map(|(p, r)| p.published.load(Ordering::Relaxed) * r)
            .sum()
    }

    fn interval_latency(&self, scratch: &mut Histogram) {
        scratch.clear();
        for c in &self.consumers {
            let mut state = c.state();
            scratch.merge(&state.interval);
            state.interval.clear();
        }
    }

    fn confirm_latency(&self) -> Histogram {
        let mut all = Histogram::new();
        for p in &self.publishers {
            all.merge(&p.confirm_latency());
        }
        all
    }

    fn window_latency(&self) -> Histogram {
        let mut all = Histogram::new();
        for c in &self.consumers {
            all.merge(&c.state().window);
        }
        all
    }
}

fn validate(args: &ThroughputArgs) -> Result<()> {
    if args.size < 8 {
        return Err("--size must be at least 8 bytes (the sequence number)".into());
    }
    if args.publishers == 0 || args.queues == 0 {
        return Err("--publishers and --queues must be at least 1".into());
    }
    if args.publishers > usize::from(u16::MAX) {
        return Err("too many publishers".into());
    }
    if args.ack && args.prefetch > 0 && args.multi_ack > u32::from(args.prefetch) {
        return Err("--multi-ack must not exceed --prefetch (the consumer would stall)".into());
    }
    if args.duration.is_nan() || args.duration <= 0.0 || args.warmup < 0.0 {
        return Err("--duration must be positive and --warmup not negative".into());
    }
    Ok(())
}

/// Runs the scenario; prints progress and a summary unless `quiet`.
pub async fn run(args: &ThroughputArgs) -> Result<ThroughputReport> {
    validate(args)?;
    let topology = Topology::new("tp", args.exchange, args.queues, args.persistent)?;
    let setup = connect(&args.url, "setup").await?;
    let setup_channel = setup.open_channel().await?;
    topology.declare(&setup_channel).await?;
    let result = run_declared(args, &topology).await;
    let cleanup = topology.delete(&setup_channel).await;
    let _ = setup.close().await;
    let report = result?;
    cleanup?;
    if !args.quiet {
        print_summary(&report);
    }
    if let Some(path) = &args.json {
        crate::report::write_json(path, &report)?;
    }
    Ok(report)
}

async fn close_all(connections: &[Connection]) {
    let closes = connections.iter().map(|c| {
        let c = c.clone();
        tokio::spawn(async move {
            let _ = c.close().await;
        })
    });
    let handles: Vec<_> = closes.collect();
    for h in handles {
        let _ = h.await;
    }
}

async fn run_declared(args: &ThroughputArgs, topology: &Topology) -> Result<ThroughputReport> {
    let phase = Arc::new(AtomicU8::new(PHASE_WARMUP));
    let consumer_spec = ConsumerSpec {
        manual_ack: args.ack,
        prefetch: args.prefetch,
        ack_every: args.multi_ack,
    };

    // Consumers first, so nothing published is missed.
    let mut consumer_connections = Vec::new();
    let mut consumer_tasks = Vec::new();
    let mut consumer_stats = Vec::new();
    let mut consumer_queue = Vec::new();
    for c in 0..args.consumers {
        let connection = connect(&args.url, &format!("consumer {c}")).await?;
        let channel = connection.open_channel().await?;
        let q = topology.queue_of_consumer(c);
        let consumer = start_consumer(&channel, &topology.queues[q], &consumer_spec).await?;
        let stats = Arc::new(ConsumerStats::default());
        consumer_tasks.push(tokio::spawn(consume(
            consumer,
            consumer_spec,
            Arc::clone(&stats),
            Arc::clone(&phase),
        )));
        consumer_stats.push(stats);
        consumer_queue.push(q);
        consumer_connections.push(connection);
    }
    let consumed_queues: Vec<bool> = (0..topology.queues.len())
        .map(|q| consumer_queue.contains(&q))
        .collect();

    // Then the publishers, each on its own connection.
    let stop = Arc::new(AtomicBool::new(false));
    let mut publisher_connections = Vec::new();
    let mut publisher_counters = Vec::new();
    let mut prepared = Vec::new();
    for p in 0..args.publishers {
        let connection = connect(&args.url, &format!("publisher {p}")).await?;
        let channel = connection.open_channel().await?;
        let spec = PublisherSpec {
            id: p as u16,
            exchange: topology.exchange.clone(),
            routing_key: topology.routing_key(p),
            persistent: args.persistent,
            size: args.size,
            rate: args.rate,
            count: args.count,
            confirm_window: args.confirm,
            first: 0,
        };
        prepare_publisher(&channel, &spec).await?;
        publisher_counters.push(Arc::new(PublisherCounters::default()));
        prepared.push((channel, spec));
        publisher_connections.push(connection);
    }
    let running = Running {
        publishers: publisher_counters.clone(),
        consumers: consumer_stats.clone(),
        reach: (0..args.publishers)
            .map(|p| {
                (0..topology.queues.len())
                    .filter(|&q| consumed_queues[q] && topology.reaches(p, q))
                    .count() as u64
            })
            .collect(),
    };
    let publisher_tasks: Vec<JoinHandle<Result<PublisherOutcome>>> = prepared
        .into_iter()
        .zip(&publisher_counters)
        .map(|((channel, spec), counters)| {
            let counters = Arc::clone(counters);
            let stop = Arc::clone(&stop);
            tokio::spawn(async move { publish(&channel, &spec, &counters, &stop).await })
        })
        .collect();

    // Warm-up, window, progress lines.
    let started = Instant::now();
    let warmup = Duration::from_secs_f64(args.warmup);
    let end = warmup + Duration::from_secs_f64(args.duration);
    let mut window_start = None;
    let mut window_end = None;
    let mut meters = None;
    let broker_pid = args.broker_pid.or_else(|| find_broker_pid(&args.url));
    let mut progress = Vec::new();
    let mut last = running.snapshot();
    let mut next_tick = started + Duration::from_secs(1);
    let mut scratch = Histogram::new();
    let start_window = |meters: &mut Option<Meters>| {
        phase.store(PHASE_MEASURE, Ordering::Relaxed);
        for publisher in &running.publishers {
            publisher.confirm_latency().clear();
        }
        *meters = Some((
            CpuMeter::start(std::process::id()),
            broker_pid.and_then(CpuMeter::start),
            MachineMeter::start(),
        ));
        running.snapshot()
    };
    if warmup.is_zero() {
        window_start = Some(start_window(&mut meters));
    }
    let mut cpu = (None, None, None);
    loop {
        let publishers_done = publisher_tasks.iter().all(JoinHandle::is_finished);
        if publishers_done {
            if window_start.is_none() {
                window_start = Some(start_window(&mut meters));
            }
            break;
        }
        let boundary = started + if window_start.is_none() { warmup } else { end };
        let wake = next_tick
            .min(boundary)
            .min(Instant::now() + Duration::from_millis(100));
        tokio::time::sleep_until(wake.into()).await;
        let now = Instant::now();
        let measuring = window_start.is_some();
        if now >= boundary {
            if window_start.is_none() {
                window_start = Some(start_window(&mut meters));
            } else {
                break;
            }
        }
        if now >= next_tick {
            next_tick += Duration::from_secs(1);
            let snap = running.snapshot();
            running.interval_latency(&mut scratch);
            let dt = snap.at.duration_since(last.at).as_secs_f64();
            let line = Progress {
                t_s: snap.at.duration_since(started).as_secs_f64(),
                phase: if measuring { "measure" } else { "warmup" },
                publish_rate: (snap.published - last.published) as f64 / dt,
                consume_rate: (snap.consumed - last.consumed) as f64 / dt,
                p50_us: scratch.quantile(0.5) as f64 / 1000.0,
                p99_us: scratch.quantile(0.99) as f64 / 1000.0,
                backlog: running.expected_deliveries() as i64 - snap.consumed as i64,
            };
            if !args.quiet {
                print_progress(&line);
            }
            progress.push(line);
            last = snap;
        }
    }
    let mut backlog_at_end = 0;
    let mut confirm_window = Histogram::new();
    if window_end.is_none() {
        confirm_window = running.confirm_latency();
        let snap = running.snapshot();
        backlog_at_end = running.expected_deliveries() as i64 - snap.consumed as i64;
        window_end = Some(snap);
        if let Some((generator, broker, machine)) = &meters {
            let generator = generator.and_then(|m| m.percent());
            let broker = broker.and_then(|m| m.percent());
            let others = machine
                .and_then(|m| m.percent())
                .map(|all| (all - generator.unwrap_or(0.0) - broker.unwrap_or(0.0)).max(0.0));
            cpu = (generator, broker, others);
        }
    }
    phase.store(PHASE_DRAIN, Ordering::Relaxed);
    stop.store(true, Ordering::Relaxed);

    // Publishers finish (last confirms), then consumers drain.
    let mut errors = Vec::new();
    let mut outcomes = Vec::new();
    for task in publisher_tasks {
        let abort = task.abort_handle();
        match tokio::time::timeout(Duration::from_secs(40), task).await {
            Ok(Ok(Ok(outcome))) => outcomes.push(outcome),
            Ok(Ok(Err(e))) => errors.push(format!("publisher: {e}")),
            Ok(Err(e)) => errors.push(format!("publisher task: {e}")),
            Err(_) => {
                abort.abort();
                errors.push("publisher did not stop within 40 s".to_owned());
            }
        }
    }
    let published: Vec<u64> = publisher_counters
        .iter()
        .map(|c| c.published.load(Ordering::Relaxed))
        .collect();
    let nacked: Vec<u64> = publisher_counters
        .iter()
        .map(|c| c.nacked.load(Ordering::Relaxed))
        .collect();
    let expected: Vec<u64> = (0..topology.queues.len())
        .map(|q| {
            (0..args.publishers)
                .filter(|&p| topology.reaches(p, q))
                .map(|p| published[p] - nacked[p])
                .sum()
        })
        .collect();
    let queue_received = |q: usize| -> u64 {
        consumer_stats
            .iter()
            .zip(&consumer_queue)
            .filter(|(_, &cq)| cq == q)
            .map(|(s, _)| s.received.load(Ordering::Relaxed))
            .sum()
    };
    let drain_timeout = Duration::from_secs_f64(args.drain_timeout.max(0.0));
    let drain_deadline = Instant::now() + Duration::from_secs_f64(args.drain_max.max(0.0));
    let mut drained = false;
    let mut last_total = u64::MAX;
    let mut last_change = Instant::now();
    loop {
        if (0..topology.queues.len())
            .filter(|&q| consumed_queues[q])
            .all(|q| queue_received(q) >= expected[q])
        {
            drained = true;
            break;
        }
        let total = running.snapshot().consumed;
        if total != last_total {
            last_total = total;
            last_change = Instant::now();
        } else if last_change.elapsed() >= drain_timeout {
            break;
        }
        if Instant::now() >= drain_deadline {
            break;
        }
        tokio::time::sleep(Duration::from_millis(10)).await;
    }

    close_all(&consumer_connections).await;
    for task in consumer_tasks {
        let _ = task.await;
    }
    let trackers: Vec<SeqTracker> = consumer_stats
        .iter()
        .map(|s| s.state().tracker.clone())
        .collect();
    close_all(&publisher_connections).await;

    let window_start = window_start.ok_or_else(|| PerfError::from("no window"))?;
    let window_end = window_end.ok_or_else(|| PerfError::from("no window"))?;
    let window_s = window_end
        .at
        .duration_since(window_start.at)
        .as_secs_f64()
        .max(1e-9);
    let latency = running.window_latency().summary();

    let mut queues = Vec::new();
    let mut totals = Totals::default();
    let mut consumers = Vec::new();
    for (q, name) in topology.queues.iter().enumerate() {
        let members: Vec<usize> = (0..args.consumers)
            .filter(|&c| consumer_queue[c] == q)
            .collect();
        let mut counts = SeqCounts::default();
        for &c in &members {
            counts.add(&trackers[c].counts());
        }
        let lost = (!members.is_empty()).then(|| expected[q].saturating_sub(counts.distinct));
        totals.lost += lost.unwrap_or(0);
        queues.push(QueueReport {
            name: name.to_string(),
            expected: expected[q],
            distinct: counts.distinct,
            lost,
        });
    }
    for (c, tracker) in trackers.iter().enumerate() {
        let counts = tracker.counts();
        let q = consumer_queue[c];
        let sole = consumer_queue.iter().filter(|&&cq| cq == q).count() == 1;
        totals.received += counts.received;
        totals.gaps += counts.gaps;
        totals.out_of_order += counts.out_of_order;
        totals.duplicates += counts.duplicates;
        consumers.push(ConsumerReport {
            id: c,
            queue: topology.queues[q].to_string(),
            counts,
            lost: if sole { queues[q].lost } else { None },
        });
    }
    let sum = |f: fn(&PublisherOutcome) -> u64| outcomes.iter().map(f).sum::<u64>();
    Ok(ThroughputReport {
        config: args.clone(),
        window_s,
        publish_rate: (window_end.published - window_start.published) as f64 / window_s,
        consume_rate: (window_end.consumed - window_start.consumed) as f64 / window_s,
        latency,
        confirm_latency: (args.confirm > 0).then(|| confirm_window.summary()),
        published: published.iter().sum(),
        acked: sum(|o| o.acked),
        nacked: sum(|o| o.nacked),
        unconfirmed: sum(|o| o.unconfirmed),
        backlog_at_end,
        drained,
        totals,
        queues,
        consumers,
        generator_cpu_percent: cpu.0,
        broker_pid,
        broker_cpu_percent: cpu.1,
        other_cpu_percent: cpu.2,
        progress,
        errors,
    })
}

fn print_progress(p: &Progress) {
    println!(
        "{:6.1}s {:<7}  publish {:>11}/s  consume {:>11}/s  latency p50 {:>9} p99 {:>9}  backlog {:>10}",
        p.t_s,
        p.phase,
        thousands(p.publish_rate),
        thousands(p.consume_rate),
        micros(p.p50_us),
        micros(p.p99_us),
        thousands(p.backlog as f64),
    );
}

/// One line describing a configuration.
pub fn describe(c: &ThroughputArgs) -> String {
    format!(
        "{} pub -> {} -> {} queue(s) -> {} cons, {} B, {}, {}, {}",
        c.publishers,
        match c.exchange {
            ExchangeKind::Direct => "direct",
            ExchangeKind::Fanout => "fanout",
        },
        c.queues,
        c.consumers,
        c.size,
        if c.persistent {
            "persistent/durable"
        } else {
            "transient"
        },
        if c.confirm > 0 {
            format!("confirms window {}", c.confirm)
        } else {
            "no confirms".to_owned()
        },
        if c.ack {
            format!(
                "manual acks (prefetch {}, multiple every {})",
                c.prefetch, c.multi_ack
            )
        } else {
            "no-ack".to_owned()
        },
    )
}

/// Prints the summary of a run.
pub fn print_summary(r: &ThroughputReport) {
    println!("--- throughput: {}", describe(&r.config));
    println!(
        "window {:.1} s: publish {} msgs/s, consume {} deliveries/s",
        r.window_s,
        thousands(r.publish_rate),
        thousands(r.consume_rate)
    );
    if r.backlog_at_end > 0 {
        println!(
            "backlog when the window closed: {} messages published but not yet delivered",
            thousands(r.backlog_at_end as f64)
        );
    }
    print_latency("latency", &r.latency);
    if let Some(confirms) = &r.confirm_latency {
        print_latency("confirm latency", confirms);
    }
    let t = &r.totals;
    println!(
        "published {} (acked {}, nacked {}, unconfirmed {}), delivered {}, lost {}, gaps {}, out of order {}, duplicates {}{}",
        thousands(r.published as f64),
        thousands(r.acked as f64),
        thousands(r.nacked as f64),
        thousands(r.unconfirmed as f64),
        thousands(t.received as f64),
        t.lost,
        t.gaps,
        t.out_of_order,
        t.duplicates,
        if r.drained {
            ""
        } else {
            " (draining gave up: `lost` includes messages still queued)"
        }
    );
    let pct = |v: Option<f64>| v.map_or("-".to_owned(), |v| format!("{v:.0}%"));
    println!(
        "cpu over the window (100% = one core): leveret-perf {}, broker{} {}, other processes {}",
        pct(r.generator_cpu_percent),
        r.broker_pid
            .map_or(String::new(), |p| format!(" (pid {p})")),
        pct(r.broker_cpu_percent),
        pct(r.other_cpu_percent)
    );
    for c in &r.consumers {
        println!(
            "  consumer {} ({}): received {}, lost {}, gaps {}, out of order {}, duplicates {}",
            c.id,
            c.queue,
            thousands(c.counts.received as f64),
            c.lost.map_or("(see queue)".to_owned(), |l| l.to_string()),
            c.counts.gaps,
            c.counts.out_of_order,
            c.counts.duplicates
        );
    }
    for e in &r.errors {
        println!("  error: {e}");
    }
}

/// One line of a latency summary.
fn print_latency(label: &str, l: &LatencySummary) {
    println!(
        "{label} ({} samples): min {}  p50 {}  p95 {}  p99 {}  max {}",
        thousands(l.count as f64),
        micros(l.min_us),
        micros(l.p50_us),
        micros(l.p95_us),
        micros(l.p99_us),
        micros(l.max_us)
    );
}
