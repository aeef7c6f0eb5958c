//! The `quality` scenario, the paper's messaging-quality experiment: one
//! publisher broadcasts through a fanout exchange to four queues, each
//! with its own consumer on its own connection; `count` consecutive
//! messages at `rate` per second (default 10,000 at 100 Hz), repeated
//! `repeat` times `pause` seconds apart. After each repetition the
//! consumers drain; then each consumer's lost messages (published minus
//! distinct received), gaps and out-of-order arrivals (together the
//! paper's arrival-order errors) and duplicates are counted for that
//! repetition. The target is exactly zero of each.

use crate::histogram::{Histogram, LatencySummary};
use crate::load::{
    connect, consume, prepare_publisher, publish, start_consumer, ConsumerSpec, ConsumerStats,
    ExchangeKind, PublisherCounters, PublisherSpec, Topology, DEFAULT_URL, PHASE_MEASURE,
};
use crate::report::{micros, thousands, Table};
use crate::sequence::SeqCounts;
use crate::Result;
use serde::Serialize;
use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, AtomicU8, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

/// Options of the `quality` subcommand.
#[derive(Debug, Clone, clap::Args, Serialize)]
pub struct QualityArgs {
    /// Broker URL.
    #[arg(long, default_value = DEFAULT_URL)]
    pub url: String,
    /// Queues and consumers on the fanout exchange.
    #[arg(long, default_value_t = 4)]
    pub consumers: usize,
    /// Messages per repetition.
    #[arg(long, default_value_t = 10_000)]
    pub count: u64,
    /// Messages per second (0: as fast as possible).
    #[arg(long, default_value_t = 100.0)]
    pub rate: f64,
    /// Repetitions.
    #[arg(long, default_value_t = 1)]
    pub repeat: usize,
    /// Seconds between repetitions.
    #[arg(long, default_value_t = 0.0)]
    pub pause: f64,
    /// Body size in bytes (at least 8; latency needs 16).
    #[arg(long, default_value_t = 64)]
    pub size: usize,
    /// Persistent messages on durable queues.
    #[arg(long)]
    pub persistent: bool,
    /// Publisher confirms with this many outstanding (0: none).
    #[arg(long, default_value_t = 0, value_name = "WINDOW")]
    pub confirm: usize,
    /// Manual acknowledgements (otherwise no-ack).
    #[arg(long)]
    pub ack: bool,
    /// Prefetch count of each consumer (0: none).
    #[arg(long, default_value_t = 0)]
    pub prefetch: u16,
    /// With --ack, acknowledge with `multiple` every N deliveries.
    #[arg(long, default_value_t = 1, value_name = "N")]
    pub multi_ack: u32,
    /// Seconds without a delivery after which draining gives up.
    #[arg(long, default_value_t = 10.0)]
    pub drain_timeout: f64,
    /// Write the report as JSON to this file.
    #[arg(long)]
    pub json: Option<PathBuf>,
    /// No summary table.
    #[arg(long)]
    pub quiet: bool,
}

impl Default for QualityArgs {
    fn default() -> Self {
        QualityArgs {
            url: DEFAULT_URL.to_owned(),
            consumers: 4,
            count: 10_000,
            rate: 100.0,
            repeat: 1,
            pause: 0.0,
            size: 64,
            persistent: false,
            confirm: 0,
            ack: false,
            prefetch: 0,
            multi_ack: 1,
            drain_timeout: 10.0,
            json: None,
            quiet: false,
        }
    }
}

/// One consumer's counts over one repetition (or all of them).
#[derive(Debug, Clone, Serialize)]
pub struct QualityRow {
    /// Repetition (1-based; 0 for the totals).
    pub repetition: usize,
    /// Consumer number.
    pub consumer: usize,
    /// Messages published to its queue.
    pub expected: u64,
    /// Sequence counts.
    #[serde(flatten)]
    pub counts: SeqCounts,
    /// Expected minus distinct received.
    pub lost: u64,
    /// Gaps plus out-of-order arrivals.
    pub order_errors: u64,
}

/// The result of a `quality` run.
#[derive(Debug, Clone, Serialize)]
pub struct QualityReport {
    /// The options it ran with.
    pub config: QualityArgs,
    /// Per repetition and consumer.
    pub rows: Vec<QualityRow>,
    /// Per consumer over every repetition.
    pub per_consumer: Vec<QualityRow>,
    /// Deliveries over all.
    pub delivered: u64,
    /// Lost over all.
    pub lost: u64,
    /// Order errors over all.
    pub order_errors: u64,
    /// Duplicates over all.
    pub duplicates: u64,
    /// Publish to delivery latency.
    pub latency: LatencySummary,
    /// Whether every repetition drained completely.
    pub drained: bool,
    /// Wall time, seconds.
    pub elapsed_s: f64,
}

/// Runs the broadcast; prints a table unless `quiet`.
pub async fn run(args: &QualityArgs) -> Result<QualityReport> {
    if args.size < 8 || args.consumers == 0 || args.count == 0 {
        return Err("--size must be at least 8, --consumers and --count at least 1".into());
    }
    let topology = Topology::new(
        "quality",
        ExchangeKind::Fanout,
        args.consumers,
        args.persistent,
    )?;
    let setup = connect(&args.url, "setup").await?;
    let setup_channel = setup.open_channel().await?;
    topology.declare(&setup_channel).await?;
    let result = run_declared(args, &topology).await;
    let cleanup = topology.delete(&setup_channel).await;
    let _ = setup.close().await;
    let report = result?;
    cleanup?;
    if !args.quiet {
        print_table(&report);
    }
    if let Some(path) = &args.json {
        crate::report::write_json(path, &report)?;
    }
    Ok(report)
}

async fn run_declared(args: &QualityArgs, topology: &Topology) -> Result<QualityReport> {
    let started = Instant::now();
    let phase = Arc::new(AtomicU8::new(PHASE_MEASURE));
    let spec = ConsumerSpec {
        manual_ack: args.ack,
        prefetch: args.prefetch,
        ack_every: args.multi_ack,
    };
    let mut connections = Vec::new();
    let mut stats = Vec::new();
    let mut tasks = Vec::new();
    for c in 0..args.consumers {
        let connection = connect(&args.url, &format!("quality consumer {c}")).await?;
        let channel = connection.open_channel().await?;
        let consumer = start_consumer(&channel, &topology.queues[c], &spec).await?;
        let s = Arc::new(ConsumerStats::default());
        tasks.push(tokio::spawn(consume(
            consumer,
            spec,
            Arc::clone(&s),
            Arc::clone(&phase),
        )));
        stats.push(s);
        connections.push(connection);
    }
    let publisher = connect(&args.url, "quality publisher").await?;
    let channel = publisher.open_channel().await?;
    let mut publisher_spec = PublisherSpec {
        id: 0,
        exchange: topology.exchange.clone(),
        routing_key: topology.routing_key(0),
        persistent: args.persistent,
        size: args.size,
        rate: args.rate,
        count: args.count,
        confirm_window: args.confirm,
        first: 0,
    };
    prepare_publisher(&channel, &publisher_spec).await?;
    let counters = PublisherCounters::default();
    let stop = AtomicBool::new(false);

    let mut rows = Vec::new();
    let mut previous: Vec<SeqCounts> = vec![SeqCounts::default(); args.consumers];
    let mut expected_total = 0u64;
    let mut drained = true;
    let result: Result<()> = async {
        for rep in 1..=args.repeat {
            if rep > 1 && args.pause > 0.0 {
                tokio::time::sleep(Duration::from_secs_f64(args.pause)).await;
            }
            let outcome = publish(&channel, &publisher_spec, &counters, &stop).await?;
            publisher_spec.first = outcome.next;
            let expected = outcome.published - outcome.nacked;
            expected_total += expected;
            drained &= drain(&stats, expected_total, args.drain_timeout).await;
            for (c, s) in stats.iter().enumerate() {
                let now = s.state().tracker.counts();
                let counts = now.since(&previous[c]);
                previous[c] = now;
                rows.push(QualityRow {
                    repetition: rep,
                    consumer: c,
                    expected,
                    counts,
                    lost: expected.saturating_sub(counts.distinct),
                    order_errors: counts.order_errors(),
                });
            }
        }
        Ok(())
    }
    .await;
    let _ = publisher.close().await;
    for connection in &connections {
        let _ = connection.close().await;
    }
    for task in tasks {
        let _ = task.await;
    }
    result?;

    let mut latency = Histogram::new();
    for s in &stats {
        latency.merge(&s.state().window);
    }
    let per_consumer: Vec<QualityRow> = (0..args.consumers)
        .map(|c| {
            let mut counts = SeqCounts::default();
            let mut expected = 0;
            let mut lost = 0;
            for row in rows.iter().filter(|r| r.consumer == c) {
                counts.add(&row.counts);
                expected += row.expected;
                lost += row.lost;
            }
            QualityRow {
                repetition: 0,
                consumer: c,
                expected,
                counts,
                lost,
                order_errors: counts.order_errors(),
            }
        })
        .collect();
    Ok(QualityReport {
        config: args.clone(),
        delivered: per_consumer.iter().map(|r| r.counts.received).sum(),
        lost: per_consumer.iter().map(|r| r.lost).sum(),
        order_errors: per_consumer.iter().map(|r| r.order_errors).sum(),
        duplicates: per_consumer.iter().map(|r| r.counts.duplicates).sum(),
        rows,
        per_consumer,
        latency: latency.summary(),
        drained,
        elapsed_s: started.elapsed().as_secs_f64(),
    })
}

/// Waits until every consumer has `expected` distinct messages, or none
/// arrives for `timeout` seconds; true if complete.
async fn drain(stats: &[Arc<ConsumerStats>], expected: u64, timeout: f64) -> bool {
    let timeout = Duration::from_secs_f64(timeout.max(0.0));
    let mut last_total = u64::MAX;
    let mut last_change = Instant::now();
    loop {
        if stats
            .iter()
            .all(|s| s.state().tracker.counts().distinct >= expected)
        {
            return true;
        }
        let total: u64 = stats
            .iter()
            .map(|s| s.received.load(Ordering::Relaxed))
            .sum();
        if total != last_total {
            last_total = total;
            last_change = Instant::now();
        } else if last_change.elapsed() >= timeout {
            return false;
        }
        tokio::time::sleep(Duration::from_millis(10)).await;
    }
}

/// Prints per-repetition and total rows.
pub fn print_table(r: &QualityReport) {
    let c = &r.config;
    println!(
        "--- quality: 1 publisher -> fanout -> {} queues -> {} consumers, {} messages at {} x {}, {} B, {}, {}",
        c.consumers,
        c.consumers,
        thousands(c.count as f64),
        if c.rate > 0.0 {
            format!("{} Hz", c.rate)
        } else {
            "full speed".to_owned()
        },
        c.repeat,
        c.size,
        if c.persistent { "persistent" } else { "transient" },
        if c.ack { "manual acks" } else { "no-ack" },
    );
    let mut table = Table::new(&[
        "repetition",
        "consumer",
        "expected",
        "received",
        "lost",
        "gaps",
        "out of order",
        "duplicates",
    ]);
    let rows = r.rows.iter().chain(r.per_consumer.iter());
    for row in rows {
        table.row(vec![
            if row.repetition == 0 {
                "all".to_owned()
            } else {
                row.repetition.to_string()
            },
            row.consumer.to_string(),
            thousands(row.expected as f64),
            thousands(row.counts.received as f64),
            row.lost.to_string(),
            row.counts.gaps.to_string(),
            row.counts.out_of_order.to_string(),
            row.counts.duplicates.to_string(),
        ]);
    }
    print!("{}", table.render());
    println!(
        "total: {} deliveries, {} lost, {} arrival-order errors, {} duplicates{}; latency p50 {} p99 {} max {}",
        thousands(r.delivered as f64),
        r.lost,
        r.order_errors,
        r.duplicates,
        if r.drained { "" } else { " (a drain timed out)" },
        micros(r.latency.p50_us),
        micros(r.latency.p99_us),
        micros(r.latency.max_us),
    );
}
