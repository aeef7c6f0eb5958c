//! The `compare` subcommand: one scenario set run against two or more
//! brokers, one after the other for each scenario (never two under load at
//! once: on a small machine an idle broker must not steal the other's
//! cores), printed as one table with each figure for every broker and the
//! first broker's ratio to each other one. With `--leveret-url` and
//! `--rabbit-url`, the first is Leveret and the second RabbitMQ; with
//! `--url` (given two or more times, named with `--name`), any brokers,
//! LavinMQ or a `leveret-perf sink` among them. Ratios read as first/other
//! for throughput (higher is better) and for latency and memory (lower is
//! better); the `best` column names the broker that wins each row.
//!
//! Other people's load generators run beside ours: `--external
//! ID='COMMAND'` runs COMMAND through `sh -c` against each broker (`{url}`
//! in it is replaced by the broker's URL, and `{queue}`, if there, by a
//! queue name of the run's own, which is deleted after it so that no
//! backlog carries over into the next run), and reads the last line of its
//! output that is a JSON object with `avg_pub_rate` and `avg_consume_rate`
//! (`lavinmqperf throughput -j`, `leveret-perf-go -j`). For these and for
//! our throughput scenarios the broker's CPU time per consumed message is
//! reported beside the rates.
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
//! - `quality` (with `--quality`): the paper's 1-to-4 broadcast, 10,000 messages at 100 Hz;
//! - each `--external` command, under its ID.

use crate::histogram::BoxStats;
use crate::load::ExchangeKind;
use crate::memory;
use crate::procfs::{cpu_seconds, find_broker_pid};
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
    /// Broker URLs: give two or more; the first is compared with each other.
    #[arg(long = "url")]
    pub urls: Vec<String>,
    /// Leveret's URL (broker A).
    #[arg(long)]
    pub leveret_url: Option<String>,
    /// RabbitMQ's URL (broker B).
    #[arg(long)]
    pub rabbit_url: Option<String>,
    /// Names of the brokers in the table, in order (default: leveret and
    /// rabbitmq with --leveret-url/--rabbit-url, else A, B, C...).
    #[arg(long = "name")]
    pub names: Vec<String>,
    /// PIDs of the brokers, in order (default: the process listening on
    /// each one's port).
    #[arg(long = "pid")]
    pub pids: Vec<u32>,
    /// An external load generator's command, as ID=COMMAND; `{url}` in it
    /// becomes each broker's URL, `{queue}` a queue name of the run's own
    /// (deleted after the run). Its last output line that is a JSON object
    /// with avg_pub_rate and avg_consume_rate gives the rates.
    #[arg(long = "external", value_name = "ID=COMMAND")]
    pub externals: Vec<String>,
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
            pids: Vec::new(),
            externals: Vec::new(),
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
    /// Nanoseconds (lower is better).
    Nanos,
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
            Unit::Nanos => format!("{} ns", thousands(v)),
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
    /// Each broker's value, in the brokers' order.
    pub values: Vec<Option<f64>>,
    /// The first broker's value over each other broker's (in order, from
    /// the second), where both are known and the other is not zero.
    pub ratios: Vec<Option<f64>>,
    /// The broker that did best ("=" for a tie, empty when it does not
    /// apply).
    pub best: String,
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
    /// The brokers, the first compared with each other.
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
    /// Another load generator's command line, `{url}` to be replaced.
    External(String),
}

fn brokers(args: &CompareArgs) -> Result<Vec<BrokerUnderTest>> {
    let (urls, default_names): (Vec<String>, Vec<String>) =
        match (&args.leveret_url, &args.rabbit_url) {
            (Some(l), Some(r)) if args.urls.is_empty() => (
                vec![l.clone(), r.clone()],
                vec!["leveret".into(), "rabbitmq".into()],
            ),
            (None, None) if args.urls.len() >= 2 => {
                let names = (0..args.urls.len())
                    .map(|i| char::from(b'A' + (i % 26) as u8).to_string())
                    .collect();
                (args.urls.clone(), names)
            }
            _ => {
                return Err("give two brokers or more: --url A --url B [--url C...], \
                            or --leveret-url and --rabbit-url"
                    .into())
            }
        };
    Ok(urls
        .into_iter()
        .enumerate()
        .map(|(i, url)| BrokerUnderTest {
            name: args
                .names
                .get(i)
                .cloned()
                .unwrap_or_else(|| default_names[i].clone()),
            pid: args.pids.get(i).copied().or_else(|| find_broker_pid(&url)),
            url,
        })
        .collect())
}

/// `ID=COMMAND` split in two.
fn external(spec: &str) -> Result<(String, String)> {
    let id_char = |c: char| c.is_ascii_alphanumeric() || c == '-' || c == '_';
    match spec.split_once('=') {
        Some((id, command))
            if !id.is_empty() && id.chars().all(id_char) && command.contains("{url}") =>
        {
            Ok((id.to_owned(), command.to_owned()))
        }
        _ => Err(format!(
            "--external wants ID=COMMAND (ID of letters, digits, - and _) with {{url}} in \
             the command, got '{spec}'"
        )
        .into()),
    }
}

fn scenarios(args: &CompareArgs) -> Result<Vec<(String, String, Scenario)>> {
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
    let mut list: Vec<(String, String, Scenario)> = list
        .into_iter()
        .map(|(id, description, scenario)| (id.to_owned(), description, scenario))
        .collect();
    for spec in &args.externals {
        let (id, command) = external(spec)?;
        list.push((
            id,
            format!("external: {command}"),
            Scenario::External(command),
        ));
    }
    if !args.only.is_empty() {
        list.retain(|(id, _, _)| args.only.iter().any(|o| o == id));
    }
    Ok(list)
}

async fn run_one(scenario: &Scenario, broker: &BrokerUnderTest, settle: f64) -> Result<Outcome> {
    let mut out = Outcome::default();
    let need_pid = || {
        broker.pid.ok_or_else(|| {
            PerfError(format!(
                "no PID for {}: give --pid for each broker, in order",
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
            if let Some(confirms) = &r.confirm_latency {
                f.push(("confirm latency p50".into(), Unit::Micros, confirms.p50_us));
                f.push(("confirm latency p99".into(), Unit::Micros, confirms.p99_us));
            }
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
                if r.consume_rate > 0.0 {
                    let per_message = cpu / 100.0 * 1e9 / r.consume_rate;
                    f.push(("broker CPU per message".into(), Unit::Nanos, per_message));
                }
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
        Scenario::External(template) => {
            let queue = format!(
                "perf-{}-{}",
                std::process::id(),
                EXTERNAL_RUNS.fetch_add(1, std::sync::atomic::Ordering::Relaxed)
            );
            let command = template
                .replace("{url}", &broker.url)
                .replace("{queue}", &queue);
            let cpu_before = broker.pid.and_then(cpu_seconds);
            let started = std::time::Instant::now();
            let run = {
                let command = command.clone();
                tokio::task::spawn_blocking(move || {
                    std::process::Command::new("sh")
                        .arg("-c")
                        .arg(command)
                        .stdin(std::process::Stdio::null())
                        .stderr(std::process::Stdio::inherit())
                        .output()
                })
            };
            let output = run
                .await
                .map_err(|e| format!("'{command}' did not finish: {e}"))?
                .map_err(|e| format!("cannot run '{command}': {e}"))?;
            let elapsed = started.elapsed().as_secs_f64();
            if template.contains("{queue}") {
                delete_queue(&broker.url, &queue).await;
            }
            let stdout = String::from_utf8_lossy(&output.stdout);
            if !output.status.success() {
                return Err(format!("'{command}' failed ({}): {stdout}", output.status).into());
            }
            let rates = generator_rates(&stdout)
                .ok_or_else(|| format!("no JSON rates in the output of '{command}': {stdout}"))?;
            let f = &mut out.figures;
            f.push(("publish rate".into(), Unit::MsgsPerSecond, rates.publish));
            f.push(("consume rate".into(), Unit::MsgsPerSecond, rates.consume));
            if let Some((p50_ms, p99_ms)) = rates.latency_ms {
                f.push(("latency p50".into(), Unit::Micros, p50_ms * 1000.0));
                f.push(("latency p99".into(), Unit::Micros, p99_ms * 1000.0));
            }
            let cpu = cpu_before.zip(broker.pid.and_then(cpu_seconds));
            if let Some((before, after)) = cpu {
                let used = after - before;
                f.push(("broker CPU".into(), Unit::Percent, used / elapsed * 100.0));
                let consumed = rates.consume * rates.elapsed;
                if consumed > 0.0 {
                    f.push((
                        "broker CPU per message".into(),
                        Unit::Nanos,
                        used * 1e9 / consumed,
                    ));
                }
            }
            out.report = serde_json::json!({
                "command": command,
                "output": stdout,
                "elapsed_seconds": elapsed,
            });
        }
    }
    Ok(out)
}

/// External runs so far, for their queues' names.
static EXTERNAL_RUNS: std::sync::atomic::AtomicU64 = std::sync::atomic::AtomicU64::new(0);

/// Deletes an external run's queue, with whatever it still holds; a
/// failure is reported, not fatal (the figures stand).
async fn delete_queue(url: &str, queue: &str) {
    let deleted = async {
        let connection = leveret_client::Connection::connect(url).await?;
        let channel = connection.open_channel().await?;
        let deleted = channel
            .queue_delete(queue, leveret_client::QueueDeleteOptions::default())
            .await;
        let _ = connection.close().await;
        deleted
    };
    match tokio::time::timeout(Duration::from_secs(60), deleted).await {
        Ok(Ok(_)) => {}
        Ok(Err(error)) => eprintln!("    could not delete queue {queue}: {error}"),
        Err(_) => eprintln!("    deleting queue {queue} took over a minute"),
    }
}

/// An external generator's rates, from its JSON line.
#[derive(Debug, Clone, Copy, PartialEq)]
struct GeneratorRates {
    publish: f64,
    consume: f64,
    /// The generator's own measuring time, seconds.
    elapsed: f64,
    /// Latency median and p99, milliseconds, when it measured them
    /// (lavinmqperf's `-l`: `latency_median_ms`, `latency_p99_ms`).
    latency_ms: Option<(f64, f64)>,
}

/// The last line of `output` that is a JSON object with `avg_pub_rate` and
/// `avg_consume_rate` (lavinmqperf's `-j` line).
fn generator_rates(output: &str) -> Option<GeneratorRates> {
    output.lines().rev().find_map(|line| {
        let value: serde_json::Value = serde_json::from_str(line.trim()).ok()?;
        Some(GeneratorRates {
            publish: value.get("avg_pub_rate")?.as_f64()?,
            consume: value.get("avg_consume_rate")?.as_f64()?,
            elapsed: value
                .get("elapsed_seconds")
                .and_then(serde_json::Value::as_f64)
                .unwrap_or(0.0),
            latency_ms: value
                .get("latency_median_ms")
                .and_then(serde_json::Value::as_f64)
                .zip(
                    value
                        .get("latency_p99_ms")
                        .and_then(serde_json::Value::as_f64),
                ),
        })
    })
}

/// The name of the broker with the best value ("=" when the best is
/// shared; empty for informational units or fewer than two values).
fn best(unit: Unit, values: &[Option<f64>], brokers: &[BrokerUnderTest]) -> String {
    if unit == Unit::Percent {
        return String::new();
    }
    let known: Vec<(usize, f64)> = values
        .iter()
        .enumerate()
        .filter_map(|(i, v)| v.map(|v| (i, v)))
        .collect();
    if known.len() < 2 {
        return String::new();
    }
    let wins = |a: f64, b: f64| {
        if unit.higher_is_better() {
            a > b
        } else {
            a < b
        }
    };
    let (top, top_value) =
        known.iter().copied().fold(
            known[0],
            |best, next| if wins(next.1, best.1) { next } else { best },
        );
    if known.iter().filter(|(_, v)| *v == top_value).count() > 1 {
        return "=".into();
    }
    brokers[top].name.clone()
}

/// Runs every scenario against each broker in turn; prints the table.
pub async fn run(args: &CompareArgs) -> Result<CompareReport> {
    let brokers = brokers(args)?;
    let list = scenarios(args)?;
    if list.is_empty() {
        return Err("no scenario selected".into());
    }
    let described: Vec<String> = brokers
        .iter()
        .map(|b| {
            let pid = b.pid.map_or("?".into(), |p| p.to_string());
            format!("{} ({}, pid {pid})", b.name, b.url)
        })
        .collect();
    println!("comparing {}", described.join(" with "));
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
                scenario: id.clone(),
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
            let values: Vec<Option<f64>> = outcomes.iter().map(value).collect();
            let ratios = values[1..]
                .iter()
                .map(|other| match (values[0], *other) {
                    (Some(a), Some(b)) if b != 0.0 => Some(a / b),
                    _ => None,
                })
                .collect();
            figures.push(Figure {
                scenario: id.clone(),
                figure: name,
                unit,
                best: best(unit, &values, &brokers),
                values,
                ratios,
            });
        }
        let rtt_boxes: Vec<(String, BoxStats)> = brokers
            .iter()
            .zip(&outcomes)
            .filter_map(|(b, o)| Some((b.name.clone(), o.rtt_box?)))
            .collect();
        if rtt_boxes.len() == brokers.len() {
            boxes.push(Group {
                label: description.clone(),
                boxes: rtt_boxes,
            });
        }
    }
    let report = CompareReport {
        brokers: brokers.clone(),
        figures,
        runs,
    };
    print_table(&report, &list);
    if let Some(path) = &args.json {
        crate::report::write_json(path, &report)?;
    }
    if let Some(path) = &args.svg {
        let names: Vec<String> = brokers.iter().map(|b| b.name.clone()).collect();
        let svg = box_plot(
            &format!("Round trip: {}", names.join(" vs ")),
            &boxes,
            &names,
        );
        std::fs::write(path, svg).map_err(|e| format!("cannot write {}: {e}", path.display()))?;
    }
    Ok(report)
}

fn print_table(report: &CompareReport, list: &[(String, String, Scenario)]) {
    let names: Vec<&str> = report.brokers.iter().map(|b| b.name.as_str()).collect();
    let ratio_headers: Vec<String> = names[1..]
        .iter()
        .map(|other| format!("{}/{other}", names[0]))
        .collect();
    let mut headers: Vec<&str> = vec!["scenario", "figure"];
    headers.extend(names.iter().copied());
    headers.extend(ratio_headers.iter().map(String::as_str));
    headers.push("best");
    let mut table = Table::new(&headers);
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
        let show = |v: &Option<f64>| v.map_or("-".to_owned(), |v| f.unit.format(v));
        let mut row = vec![label, f.figure.clone()];
        row.extend(f.values.iter().map(show));
        row.extend(
            f.ratios
                .iter()
                .map(|r| r.map_or("-".to_owned(), |r| format!("{r:.2}"))),
        );
        row.push(f.best.clone());
        table.row(row);
    }
    println!();
    print!("{}", table.render());
}

#[cfg(test)]
mod tests {
    use super::*;

    fn broker(name: &str) -> BrokerUnderTest {
        BrokerUnderTest {
            name: name.to_owned(),
            url: String::new(),
            pid: None,
        }
    }

    #[test]
    fn a_generators_rates_come_from_its_last_json_line() {
        let output = "Publish rate: 1 msgs/s Consume rate: 1 msgs/s\n\
                      {\"elapsed_seconds\":10.0,\"avg_pub_rate\":5,\"avg_consume_rate\":4}\n\
                      {\"elapsed_seconds\":10.0,\"avg_pub_rate\":132570,\"avg_consume_rate\":132556}\n\
                      trailing words\n";
        assert_eq!(
            generator_rates(output),
            Some(GeneratorRates {
                publish: 132_570.0,
                consume: 132_556.0,
                elapsed: 10.0,
                latency_ms: None,
            })
        );
        let latency = "{\"elapsed_seconds\":2.0,\"avg_pub_rate\":799,\"avg_consume_rate\":795,\
                       \"latency_median_ms\":0.206,\"latency_p99_ms\":0.34}";
        assert_eq!(
            generator_rates(latency).and_then(|rates| rates.latency_ms),
            Some((0.206, 0.34))
        );
        assert_eq!(generator_rates("no json here\n{\"other\":1}\n"), None);
    }

    #[test]
    fn an_external_needs_an_id_and_a_url_placeholder() {
        assert_eq!(
            external("lavinmqperf=lavinmqperf throughput --uri={url} -z 10").unwrap(),
            (
                "lavinmqperf".to_owned(),
                "lavinmqperf throughput --uri={url} -z 10".to_owned()
            )
        );
        assert!(external("lavinmqperf throughput --uri={url}").is_err());
        assert!(external("x=no placeholder").is_err());
        assert!(external("=cmd {url}").is_err());
    }

    #[test]
    fn the_best_broker_depends_on_the_unit() {
        let brokers = [broker("leveret"), broker("lavinmq"), broker("rabbitmq")];
        let values = [Some(3.0), Some(5.0), None];
        assert_eq!(best(Unit::MsgsPerSecond, &values, &brokers), "lavinmq");
        assert_eq!(best(Unit::Micros, &values, &brokers), "leveret");
        assert_eq!(best(Unit::Percent, &values, &brokers), "");
        assert_eq!(best(Unit::Count, &[Some(0.0), Some(0.0)], &brokers), "=");
        assert_eq!(best(Unit::Count, &[Some(0.0), None], &brokers), "");
    }
}
