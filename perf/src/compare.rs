//! The `compare` subcommand: one scenario set run against two brokers, A
//! then B for each scenario (never both under load at once: on a small
//! machine the idle broker must not steal the other's cores), printed as
//! one table with each figure for A and B and the ratio A/B. With
//! `--leveret-url` and `--rabbit-url`, A is Leveret and B RabbitMQ, so
//! ratios read as leveret/rabbit for throughput (higher is better) and for
//! latency and memory (lower is better); the `better` column says which
//! broker wins each row.
//!
//! The scenarios (the table; `--only` picks some by id):
//! - `idle`: idle resident memory (first, before the load makes the broker grow);
//! - `conns` (with `--memory-connections`): memory with 1,000 idle connections × 1 channel × 1 queue;
//! - `backlog` (with `--memory-backlog`): memory with 1,000,000 queued 16 B messages, no consumer;
//! - `noack`: 1 publisher → 1 queue → 1 consumer, 16 B, transient, no-ack;
//! - `ack`: the same with manual acks, prefetch 500, multiple-ack every 50;
//! - `confirm`: durable queue, persistent messages, confirms (window 256), manual acks;
//! - `confirm4p`: the same with 4 publishers;
//! - `fanout`: 1 publisher → fanout → 4 queues → 4 consumers, 64 B, no-ack, counting lost and out-of-order;
//! - `rtt16`: round trip, 16 B, one message in flight;
//! - `rtt128hz`: round trip, 128 B, at 100 Hz;
//! - `quality` (with `--quality`): the paper's 1-to-4 broadcast, 10,000 messages at 100 Hz.

use crate::histogram::BoxStats;
use crate::load::ExchangeKind;
use crate::memory;
use crate::procfs::find_broker_pid;
use crate::quality::{self, QualityArgs};
use crate::report::{mib, micros, thousands, Table};
use crate::rtt::{self, RttArgs};
use crate::svg::{box_plot, Group};
use crate::throughput::{self, ThroughputArgs};
use crate::{PerfError, Result};
use serde::Serialize;
use std::path::PathBuf;
use std::time::Duration;

/// Options of the `compare` subcommand.
#[derive(Debug, Clone, clap::Args, Serialize)]
pub struct CompareArgs {
    /// Broker URLs: give exactly two, A then B.
    #[arg(long = "url")]
    pub urls: Vec<String>,
    /// Leveret's URL (broker A).
    #[arg(long)]
    pub leveret_url: Option<String>,
    /// RabbitMQ's URL (broker B).
    #[arg(long)]
    pub rabbit_url: Option<String>,
    /// Names of A and B in the table (default: leveret and rabbitmq with
    /// --leveret-url/--rabbit-url, else A and B).
    #[arg(long = "name")]
    pub names: Vec<String>,
    /// PID of broker A (default: the process listening on its port).
    #[arg(long)]
    pub leveret_pid: Option<u32>,
    /// PID of broker B (default: the process listening on its port).
    #[arg(long)]
    pub rabbit_pid: Option<u32>,
    /// Seconds measured per throughput run.
    #[arg(long, default_value_t = 10.0)]
    pub duration: f64,
    /// Seconds of warm-up per throughput run.
    #[arg(long, default_value_t = 3.0)]
    pub warmup: f64,
    /// Pings per round-trip run.
    #[arg(long, default_value_t = 1000)]
    pub rtt_count: usize,
    /// Unmeasured pings before each round-trip run.
    #[arg(long, default_value_t = 100)]
    pub rtt_warmup: usize,
    /// Prefetch of the manual-ack scenarios.
    #[arg(long, default_value_t = 500)]
    pub prefetch: u16,
    /// Multiple-ack every N in the manual-ack scenarios.
    #[arg(long, default_value_t = 50)]
    pub multi_ack: u32,
    /// Also measure memory with this many idle connections [default when given: 1000].
    #[arg(long, num_args = 0..=1, default_missing_value = "1000", value_name = "N")]
    pub memory_connections: Option<usize>,
    /// Also measure memory with this many queued 16 B messages [default when given: 1000000].
    #[arg(long, num_args = 0..=1, default_missing_value = "1000000", value_name = "N")]
    pub memory_backlog: Option<u64>,
    /// Also run the broadcast-quality scenario with this many messages [default when given: 10000].
    #[arg(long, num_args = 0..=1, default_missing_value = "10000", value_name = "N")]
    pub quality: Option<u64>,
    /// Rate of the quality scenario, messages per second.
    #[arg(long, default_value_t = 100.0)]
    pub quality_rate: f64,
    /// Run only these scenarios (comma-separated ids: noack, ack, confirm,
    /// confirm4p, fanout, rtt16, rtt128hz, idle, conns, backlog, quality).
    #[arg(long, value_delimiter = ',')]
    pub only: Vec<String>,
    /// Seconds to let a broker settle between runs.
    #[arg(long, default_value_t = 2.0)]
    pub settle: f64,
    /// Show each run's progress lines and summary.
    #[arg(long)]
    pub verbose: bool,
    /// Write every figure and full report as JSON to this file.
    #[arg(long)]
    pub json: Option<PathBuf>,
    /// Write the round-trip box plot (SVG) to this file.
    #[arg(long)]
    pub svg: Option<PathBuf>,
}

impl Default for CompareArgs {
    fn default() -> Self {
        CompareArgs {
            urls: Vec::new(),
            leveret_url: None,
            rabbit_url: None,
            names: Vec::new(),
            leveret_pid: None,
            rabbit_pid: None,
            duration: 10.0,
            warmup: 3.0,
            rtt_count: 1000,
            rtt_warmup: 100,
            prefetch: 500,
            multi_ack: 50,
            memory_connections: None,
            memory_backlog: None,
            quality: None,
            quality_rate: 100.0,
            only: Vec::new(),
            settle: 2.0,
            verbose: false,
            json: None,
            svg: None,
        }
    }
}

/// A broker under comparison.
#[derive(Debug, Clone, Serialize)]
pub struct BrokerUnderTest {
    /// Its name in the table.
    pub name: String,
    /// Its URL.
    pub url: String,
    /// Its PID, if known (for memory and CPU).
    pub pid: Option<u32>,
}

/// How a figure is printed and which way is better.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Unit {
    /// Messages per second (higher is better).
    MsgsPerSecond,
    /// Microseconds (lower is better).
    Micros,
    /// Bytes (lower is better).
    Bytes,
    /// A count of bad events (lower is better).
    Count,
    /// Percent of a core (informational).
    Percent,
}

impl Unit {
    fn higher_is_better(self) -> bool {
        matches!(self, Unit::MsgsPerSecond)
    }

    fn format(self, v: f64) -> String {
        match self {
            Unit::MsgsPerSecond => format!("{}/s", thousands(v)),
            Unit::Micros => micros(v),
            Unit::Bytes => {
                if v.abs() >= 1024.0 * 1024.0 {
                    mib(v)
                } else {
                    format!("{} B", thousands(v))
                }
            }
            Unit::Count => thousands(v),
            Unit::Percent => format!("{v:.0}%"),
        }
    }
}

/// One row of the table.
#[derive(Debug, Clone, Serialize)]
pub struct Figure {
    /// Scenario id.
    pub scenario: String,
    /// What is measured.
    pub figure: String,
    /// Its unit.
    pub unit: Unit,
    /// A's value.
    pub a: Option<f64>,
    /// B's value.
    pub b: Option<f64>,
    /// A/B, where both are known and B is not zero.
    pub ratio: Option<f64>,
    /// Which broker did better ("A", "B", "=" or "").
    pub better: String,
}

/// One run of one scenario against one broker.
#[derive(Debug, Clone, Serialize)]
pub struct Run {
    /// Scenario id.
    pub scenario: String,
    /// Broker name.
    pub broker: String,
    /// The full report, or the error.
    pub report: serde_json::Value,
}

/// The result of a comparison.
#[derive(Debug, Clone, Serialize)]
pub struct CompareReport {
    /// A and B.
    pub brokers: Vec<BrokerUnderTest>,
    /// The table.
    pub figures: Vec<Figure>,
    /// Every run.
    pub runs: Vec<Run>,
}

/// What one run gave: named figures, and for a round trip its box.
#[derive(Debug, Default)]
struct Outcome {
    figures: Vec<(String, Unit, f64)>,
    rtt_box: Option<BoxStats>,
    report: serde_json::Value,
}

#[derive(Debug, Clone)]
enum Scenario {
    Throughput(ThroughputArgs),
    Rtt(RttArgs),
    Quality(QualityArgs),
    Idle,
    Connections(usize),
    Backlog(u64),
}

fn brokers(args: &CompareArgs) -> Result<[BrokerUnderTest; 2]> {
    let (urls, default_names) = match (&args.leveret_url, &args.rabbit_url) {
        (Some(l), Some(r)) if args.urls.is_empty() => {
            ([l.clone(), r.clone()], ["leveret", "rabbitmq"])
        }
        (None, None) if args.urls.len() == 2 => {
            ([args.urls[0].clone(), args.urls[1].clone()], ["A", "B"])
        }
        _ => {
            return Err(
                "give two brokers: --url A --url B, or --leveret-url and --rabbit-url".into(),
            )
        }
    };
    let name = |i: usize| {
        args.names
            .get(i)
            .cloned()
            .unwrap_or_else(|| default_names[i].to_owned())
    };
    let pids = [args.leveret_pid, args.rabbit_pid];
    let [a, b] = urls;
    Ok([
        BrokerUnderTest {
            name: name(0),
            pid: pids[0].or_else(|| find_broker_pid(&a)),
            url: a,
        },
        BrokerUnderTest {
            name: name(1),
            pid: pids[1].or_else(|| find_broker_pid(&b)),
            url: b,
        },
    ])
}

fn scenarios(args: &CompareArgs) -> Vec<(&'static str, String, Scenario)> {
    let base = ThroughputArgs {
        duration: args.duration,
        warmup: args.warmup,
        quiet: !args.verbose,
        ..Default::default()
    };
    let acks = ThroughputArgs {
        ack: true,
        prefetch: args.prefetch,
        multi_ack: args.multi_ack,
        ..base.clone()
    };
    let confirm = ThroughputArgs {
        persistent: true,
        confirm: 256,
        ..acks.clone()
    };
    let rtt = RttArgs {
        count: args.rtt_count,
        warmup: args.rtt_warmup,
        quiet: !args.verbose,
        ..Default::default()
    };
    let mut list = vec![
        // First, while the broker has not yet grown for the load.
        ("idle", "idle broker".to_owned(), Scenario::Idle),
        (
            "noack",
            "1 pub → 1 queue → 1 cons, 16 B, transient, no-ack".to_owned(),
            Scenario::Throughput(base.clone()),
        ),
        (
            "ack",
            format!(
                "same, manual acks (prefetch {}, multiple every {})",
                args.prefetch, args.multi_ack
            ),
            Scenario::Throughput(acks.clone()),
        ),
        (
            "confirm",
            "durable, persistent, confirms (window 256), manual acks".to_owned(),
            Scenario::Throughput(confirm.clone()),
        ),
        (
            "confirm4p",
            "same with 4 publishers".to_owned(),
            Scenario::Throughput(ThroughputArgs {
                publishers: 4,
                ..confirm
            }),
        ),
        (
            "fanout",
            "1 pub → fanout → 4 queues → 4 cons, 64 B, no-ack".to_owned(),
            Scenario::Throughput(ThroughputArgs {
                exchange: ExchangeKind::Fanout,
                queues: 4,
                consumers: 4,
                size: 64,
                ..base
            }),
        ),
        (
            "rtt16",
            "round trip, 16 B, one in flight".to_owned(),
            Scenario::Rtt(RttArgs {
                sizes: vec![16],
                rate: 0.0,
                ..rtt.clone()
            }),
        ),
        (
            "rtt128hz",
            "round trip, 128 B, 100 Hz".to_owned(),
            Scenario::Rtt(RttArgs {
                sizes: vec![128],
                rate: 100.0,
                ..rtt
            }),
        ),
    ];
    // Memory next, before the load scenarios make the brokers' heaps grow.
    let load = list.split_off(1);
    if let Some(n) = args.memory_connections {
        list.push((
            "conns",
            format!(
                "{} idle connections × 1 channel × 1 queue",
                thousands(n as f64)
            ),
            Scenario::Connections(n),
        ));
    }
    if let Some(n) = args.memory_backlog {
        list.push((
            "backlog",
            format!("{} queued 16 B messages, no consumer", thousands(n as f64)),
            Scenario::Backlog(n),
        ));
    }
    list.extend(load);
    if let Some(n) = args.quality {
        list.push((
            "quality",
            format!(
                "broadcast quality: 1 → fanout → 4, {} msgs at {} Hz",
                thousands(n as f64),
                args.quality_rate
            ),
            Scenario::Quality(QualityArgs {
                count: n,
                rate: args.quality_rate,
                quiet: !args.verbose,
                ..Default::default()
            }),
        ));
    }
    if !args.only.is_empty() {
        list.retain(|(id, _, _)| args.only.iter().any(|o| o == id));
    }
    list
}

async fn run_one(scenario: &Scenario, broker: &BrokerUnderTest, settle: f64) -> Result<Outcome> {
    let mut out = Outcome::default();
    let need_pid = || {
        broker.pid.ok_or_else(|| {
            PerfError(format!(
                "no PID for {}: give --leveret-pid/--rabbit-pid",
                broker.name
            ))
        })
    };
    match scenario {
        Scenario::Throughput(t) => {
            let args = ThroughputArgs {
                url: broker.url.clone(),
                broker_pid: broker.pid,
                ..t.clone()
            };
            let r = throughput::run(&args).await?;
            let f = &mut out.figures;
            f.push(("publish rate".into(), Unit::MsgsPerSecond, r.publish_rate));
            f.push(("consume rate".into(), Unit::MsgsPerSecond, r.consume_rate));
            f.push(("latency p50".into(), Unit::Micros, r.latency.p50_us));
            f.push(("latency p99".into(), Unit::Micros, r.latency.p99_us));
            f.push((
                "backlog at end of window".into(),
                Unit::Count,
                r.backlog_at_end.max(0) as f64,
            ));
            if r.drained {
                f.push(("lost".into(), Unit::Count, r.totals.lost as f64));
            } else {
                f.push((
                    "undelivered when draining gave up".into(),
                    Unit::Count,
                    r.totals.lost as f64,
                ));
            }
            f.push((
                "out of order + gaps".into(),
                Unit::Count,
                (r.totals.out_of_order + r.totals.gaps) as f64,
            ));
            if let Some(cpu) = r.broker_cpu_percent {
                f.push(("broker CPU".into(), Unit::Percent, cpu));
            }
            if let Some(cpu) = r.generator_cpu_percent {
                f.push(("leveret-perf CPU".into(), Unit::Percent, cpu));
            }
            if let Some(cpu) = r.other_cpu_percent {
                f.push(("other processes CPU".into(), Unit::Percent, cpu));
            }
            out.report = serde_json::to_value(&r)?;
        }
        Scenario::Rtt(rt) => {
            let args = RttArgs {
                url: broker.url.clone(),
                ..rt.clone()
            };
            let r = rtt::run(&args).await?;
            if let Some(s) = r.sizes.first() {
                let f = &mut out.figures;
                f.push(("mean".into(), Unit::Micros, s.stats.mean_us));
                f.push(("median".into(), Unit::Micros, s.stats.median_us));
                f.push(("p99".into(), Unit::Micros, s.stats.p99_us));
                f.push(("max".into(), Unit::Micros, s.stats.max_us));
                f.push(("lost".into(), Unit::Count, s.lost as f64));
                out.rtt_box = Some(s.stats);
            }
            out.report = serde_json::to_value(&r)?;
        }
        Scenario::Quality(q) => {
            let args = QualityArgs {
                url: broker.url.clone(),
                ..q.clone()
            };
            let r = quality::run(&args).await?;
            let f = &mut out.figures;
            f.push(("delivered".into(), Unit::Count, r.delivered as f64));
            f.push(("lost".into(), Unit::Count, r.lost as f64));
            f.push(("order errors".into(), Unit::Count, r.order_errors as f64));
            f.push(("duplicates".into(), Unit::Count, r.duplicates as f64));
            f.push(("latency p50".into(), Unit::Micros, r.latency.p50_us));
            f.push(("latency p99".into(), Unit::Micros, r.latency.p99_us));
            out.report = serde_json::to_value(&r)?;
        }
        Scenario::Idle => {
            let pid = need_pid()?;
            let rss = memory::idle(pid, settle).await?;
            out.figures
                .push(("resident memory".into(), Unit::Bytes, rss as f64));
            out.report = serde_json::json!({ "pid": pid, "idle_bytes": rss });
        }
        Scenario::Connections(n) => {
            let pid = need_pid()?;
            let idle = memory::idle(pid, settle).await?;
            let c = memory::with_connections(&broker.url, pid, *n, settle, idle).await?;
            let f = &mut out.figures;
            f.push(("resident memory".into(), Unit::Bytes, c.rss_bytes as f64));
            f.push(("per connection".into(), Unit::Bytes, c.per_connection_bytes));
            out.report = serde_json::to_value(c)?;
        }
        Scenario::Backlog(n) => {
            let pid = need_pid()?;
            let idle = memory::idle(pid, settle).await?;
            let b = memory::with_backlog(&broker.url, pid, *n, 16, settle, idle).await?;
            let f = &mut out.figures;
            f.push(("resident memory".into(), Unit::Bytes, b.rss_bytes as f64));
            f.push(("per message".into(), Unit::Bytes, b.per_message_bytes));
            f.push(("queued".into(), Unit::Count, b.messages as f64));
            out.report = serde_json::to_value(b)?;
        }
    }
    Ok(out)
}

fn better(unit: Unit, a: f64, b: f64) -> String {
    if unit == Unit::Percent {
        return String::new();
    }
    if a == b {
        return "=".into();
    }
    let a_wins = if unit.higher_is_better() {
        a > b
    } else {
        a < b
    };
    if a_wins { "A" } else { "B" }.into()
}

/// Runs every scenario against A then B; prints the table.
pub async fn run(args: &CompareArgs) -> Result<CompareReport> {
    let brokers = brokers(args)?;
    let list = scenarios(args);
    if list.is_empty() {
        return Err("no scenario selected".into());
    }
    println!(
        "comparing A = {} ({}, pid {}) with B = {} ({}, pid {})",
        brokers[0].name,
        brokers[0].url,
        brokers[0].pid.map_or("?".into(), |p| p.to_string()),
        brokers[1].name,
        brokers[1].url,
        brokers[1].pid.map_or("?".into(), |p| p.to_string()),
    );
    let mut figures = Vec::new();
    let mut runs = Vec::new();
    let mut boxes: Vec<Group> = Vec::new();
    for (id, description, scenario) in &list {
        let mut outcomes = Vec::new();
        for broker in &brokers {
            println!("[{id}] {description} — {} ...", broker.name);
            let outcome = run_one(scenario, broker, args.settle).await;
            let outcome = match outcome {
                Ok(o) => {
                    let line: Vec<String> = o
                        .figures
                        .iter()
                        .map(|(n, u, v)| format!("{n} {}", u.format(*v)))
                        .collect();
                    println!("    {}", line.join(", "));
                    o
                }
                Err(e) => {
                    println!("    error: {e}");
                    Outcome {
                        report: serde_json::json!({ "error": e.to_string() }),
                        ..Default::default()
                    }
                }
            };
            runs.push(Run {
                scenario: (*id).to_owned(),
                broker: broker.name.clone(),
                report: outcome.report.clone(),
            });
            outcomes.push(outcome);
            tokio::time::sleep(Duration::from_secs_f64(args.settle)).await;
        }
        // Rows in the order the figures came, from whichever run had them.
        let mut names: Vec<(String, Unit)> = Vec::new();
        for o in &outcomes {
            for (n, u, _) in &o.figures {
                if !names.iter().any(|(m, _)| m == n) {
                    names.push((n.clone(), *u));
                }
            }
        }
        for (name, unit) in names {
            let value = |o: &Outcome| {
                o.figures
                    .iter()
                    .find(|(n, _, _)| *n == name)
                    .map(|(_, _, v)| *v)
            };
            let (a, b) = (value(&outcomes[0]), value(&outcomes[1]));
            let ratio = match (a, b) {
                (Some(a), Some(b)) if b != 0.0 => Some(a / b),
                _ => None,
            };
            let better = match (a, b) {
                (Some(a), Some(b)) => better(unit, a, b),
                _ => String::new(),
            };
            figures.push(Figure {
                scenario: (*id).to_owned(),
                figure: name,
                unit,
                a,
                b,
                ratio,
                better,
            });
        }
        if let (Some(a), Some(b)) = (&outcomes[0].rtt_box, &outcomes[1].rtt_box) {
            boxes.push(Group {
                label: description.clone(),
                boxes: vec![(brokers[0].name.clone(), *a), (brokers[1].name.clone(), *b)],
            });
        }
    }
    let report = CompareReport {
        brokers: brokers.to_vec(),
        figures,
        runs,
    };
    print_table(&report, &list);
    if let Some(path) = &args.json {
        crate::report::write_json(path, &report)?;
    }
    if let Some(path) = &args.svg {
        let names = [brokers[0].name.clone(), brokers[1].name.clone()];
        let svg = box_plot(
            &format!("Round trip: {} vs {}", names[0], names[1]),
            &boxes,
            &names,
        );
        std::fs::write(path, svg).map_err(|e| format!("cannot write {}: {e}", path.display()))?;
    }
    Ok(report)
}

fn print_table(report: &CompareReport, list: &[(&'static str, String, Scenario)]) {
    let a = &report.brokers[0].name;
    let b = &report.brokers[1].name;
    let ratio_header = format!("{a}/{b}");
    let mut table = Table::new(&["scenario", "figure", a, b, &ratio_header, "better"]);
    let mut last = "";
    for f in &report.figures {
        let label = if f.scenario != last {
            list.iter()
                .find(|(id, _, _)| *id == f.scenario)
                .map_or(f.scenario.clone(), |(id, d, _)| format!("{id}: {d}"))
        } else {
            String::new()
        };
        last = &f.scenario;
        let show = |v: Option<f64>| v.map_or("-".to_owned(), |v| f.unit.format(v));
        table.row(vec![
            label,
            f.figure.clone(),
            show(f.a),
            show(f.b),
            f.ratio.map_or("-".to_owned(), |r| format!("{r:.2}")),
            match f.better.as_str() {
                "A" => a.clone(),
                "B" => b.clone(),
                other => other.to_owned(),
            },
        ]);
    }
    println!();
    print!("{}", table.render());
}
