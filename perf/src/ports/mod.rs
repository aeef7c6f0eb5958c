//! The `ports` scenario: round-trip latency of a pair of robot data ports,
//! measured the way the AMQP RT-Middleware paper does (section VI-A). The
//! measuring task puts a payload on an out-port; an echo task takes it
//! from an in-port and puts it on a second out-port; the measuring task
//! takes it back from a second in-port. One message is in flight at a
//! time.
//!
//! For each payload size (default 8, 16, 32, 64 and 128 bytes) and each
//! transport (Leveret in-process, Leveret over loopback TCP, both a broker
//! this process starts; RabbitMQ over loopback TCP) it runs two modes:
//! paced at 100 Hz (1,000 round trips, as in the paper) and unthrottled
//! (5,000 round trips after a warm-up, the next put as soon as the echo is
//! back). Ports are transient and unconfirmed (the control-loop case);
//! extra rows at 64 bytes show the ports with publisher confirms and a raw
//! `leveret-client` publish/consume round trip over the same topology
//! (four connections, manual acks), which is what the ports cost on top
//! of the client and broker. RabbitMQ's rows are skipped with a message
//! when it cannot be reached.
//!
//! Every pair stays open for the whole run, and the transports take turns
//! size by size, so load from elsewhere on the machine spreads over all of
//! them alike. The measuring loop and the echoes are tasks on the
//! runtime's workers (`--threads`), which the in-process broker shares.
//!
//! Diagnostics: `--spin-pace` paces the 100 Hz mode by busy-waiting
//! instead of sleeping (with `--threads 1`, the CPU never idles between
//! round trips); `--evict-kib N` writes N KiB before each round trip,
//! untimed, to run it with cold caches but no idle time; `--dump DIR`
//! writes each row's samples (ns, in the order taken) to a file in DIR.
//!
//! Layout: this module owns the options, the plan, the timing loop and the
//! report; `pair` owns the ports or raw-client loops and their echo tasks;
//! `stall` is the `ports-stall` scenario (a control loop's `try_put`
//! through a frozen broker).

mod pair;
pub mod replay;
pub mod stall;

use crate::histogram::{BoxStats, Samples};
use crate::load::DEFAULT_URL;
use crate::procfs::MachineLoad;
use crate::report::{micros, Table};
use crate::{PerfError, Result};
use bytes::Bytes;
use leveret_broker::{Broker, BrokerHandle};
use leveret_ports::{Connector, PortProfile};
use pair::{Endpoint, Pair};
use serde::Serialize;
use std::fmt::Write as _;
use std::path::PathBuf;
use std::sync::Arc;
use std::time::{Duration, Instant};
use tokio::time::MissedTickBehavior;

/// The paper's rate: one put every 10 ms.
const PACE: Duration = Duration::from_millis(10);
/// Connecting to RabbitMQ, and skipping it when it is not there.
const CONNECT_TIMEOUT: Duration = Duration::from_secs(3);
/// Payload size of the extra rows (confirmed ports, raw client).
const EXTRA_SIZE: usize = 64;
/// After a failed round trip, how long to wait for a late echo before
/// draining it, so that it does not pass for the next one's.
const LATE_ECHO_WAIT: Duration = Duration::from_millis(100);
/// The in-process targets of issue 17, back to back: median and p99.
const IN_PROCESS_UNTHROTTLED_TARGET_US: (f64, f64) = (3.0, 15.0);
/// And at 100 Hz (with the in-ports' busy polling, `--busy-poll-us`): p99.
const IN_PROCESS_PACED_P99_TARGET_US: f64 = 60.0;
/// The loopback target: Leveret's p99 at most this share of RabbitMQ's.
const LOOPBACK_P99_RATIO_TARGET: f64 = 0.5;

/// What carries the messages between the two processes' ports.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum, Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum Transport {
    /// A Leveret broker in this process, over its in-process value link.
    InProcess,
    /// The same broker over loopback TCP.
    LeveretTcp,
    /// RabbitMQ at `--rabbit-url`.
    #[value(name = "rabbitmq")]
    #[serde(rename = "rabbitmq")]
    RabbitMq,
}

impl Transport {
    fn label(self) -> &'static str {
        match self {
            Transport::InProcess => "Leveret in-process",
            Transport::LeveretTcp => "Leveret loopback TCP",
            Transport::RabbitMq => "RabbitMQ loopback TCP",
        }
    }

    fn key(self) -> &'static str {
        match self {
            Transport::InProcess => "in-process",
            Transport::LeveretTcp => "leveret-tcp",
            Transport::RabbitMq => "rabbitmq",
        }
    }
}

/// When the next round trip starts.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum, Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum Mode {
    /// One put every 10 ms (the paper's 100 Hz).
    Paced,
    /// The next put as soon as the echo is back.
    Unthrottled,
}

impl Mode {
    fn label(self) -> &'static str {
        match self {
            Mode::Paced => "100 Hz",
            Mode::Unthrottled => "unthrottled",
        }
    }
}

/// What carries the round trip.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum Carrier {
    /// Out-ports and in-ports without publisher confirms.
    Ports,
    /// Out-ports with publisher confirms, and in-ports.
    ConfirmedPorts,
    /// `basic.publish` and a consumer on plain channels, same topology.
    RawClient,
}

impl Carrier {
    const ALL: [Carrier; 3] = [Carrier::Ports, Carrier::ConfirmedPorts, Carrier::RawClient];

    fn label(self) -> &'static str {
        match self {
            Carrier::Ports => "ports",
            Carrier::ConfirmedPorts => "ports + confirms",
            Carrier::RawClient => "raw client",
        }
    }

    fn key(self) -> &'static str {
        match self {
            Carrier::Ports => "ports",
            Carrier::ConfirmedPorts => "ports-confirms",
            Carrier::RawClient => "raw-client",
        }
    }
}

/// Options of the `ports` subcommand.
#[derive(Debug, Clone, clap::Args, Serialize)]
pub struct PortsArgs {
    /// RabbitMQ's URL, for its rows (skipped when it cannot be reached).
    #[arg(long, default_value = DEFAULT_URL)]
    pub rabbit_url: String,
    /// Transports to measure.
    #[arg(
        long,
        value_enum,
        value_delimiter = ',',
        default_value = "in-process,leveret-tcp,rabbitmq"
    )]
    pub transports: Vec<Transport>,
    /// Modes to run.
    #[arg(
        long,
        value_enum,
        value_delimiter = ',',
        default_value = "paced,unthrottled"
    )]
    pub modes: Vec<Mode>,
    /// Payload sizes in bytes.
    #[arg(long, value_delimiter = ',', default_value = "8,16,32,64,128")]
    pub sizes: Vec<usize>,
    /// Measured round trips per 100 Hz row.
    #[arg(long, default_value_t = 1000)]
    pub paced_count: usize,
    /// Unmeasured round trips before each 100 Hz row.
    #[arg(long, default_value_t = 20)]
    pub paced_warmup: usize,
    /// Measured round trips per unthrottled row.
    #[arg(long, default_value_t = 5000)]
    pub unthrottled_count: usize,
    /// Unmeasured round trips before each unthrottled row.
    #[arg(long, default_value_t = 1000)]
    pub unthrottled_warmup: usize,
    /// No confirmed-ports and raw-client rows.
    #[arg(long)]
    pub no_extras: bool,
    /// The extra rows at 100 Hz too (by default they are unthrottled only:
    /// a 100 Hz row takes ten seconds).
    #[arg(long)]
    pub paced_extras: bool,
    /// Pace the 100 Hz mode by busy-waiting instead of sleeping.
    #[arg(long)]
    pub spin_pace: bool,
    /// The in-ports' busy-poll window, µs (0: none): `recv` looks for a
    /// value without sleeping this long before it waits.
    #[arg(long, default_value_t = 0)]
    pub busy_poll_us: u64,
    /// KiB written before each round trip, untimed (cold caches, no idle time).
    #[arg(long, default_value_t = 0)]
    pub evict_kib: usize,
    /// Write each row's samples (ns, in the order taken) to a file in this directory.
    #[arg(long)]
    pub dump: Option<PathBuf>,
    /// Write the report as JSON to this file.
    #[arg(long)]
    pub json: Option<PathBuf>,
    /// No header, table or targets.
    #[arg(long)]
    pub quiet: bool,
}

impl Default for PortsArgs {
    fn default() -> Self {
        PortsArgs {
            rabbit_url: DEFAULT_URL.to_owned(),
            transports: vec![
                Transport::InProcess,
                Transport::LeveretTcp,
                Transport::RabbitMq,
            ],
            modes: vec![Mode::Paced, Mode::Unthrottled],
            sizes: vec![8, 16, 32, 64, 128],
            paced_count: 1000,
            paced_warmup: 20,
            unthrottled_count: 5000,
            unthrottled_warmup: 1000,
            no_extras: false,
            paced_extras: false,
            spin_pace: false,
            busy_poll_us: 0,
            evict_kib: 0,
            dump: None,
            json: None,
            quiet: false,
        }
    }
}

impl PortsArgs {
    /// Warm-up and measured round trips of a row in `mode`.
    fn counts(&self, mode: Mode) -> (usize, usize) {
        match mode {
            Mode::Paced => (self.paced_warmup, self.paced_count),
            Mode::Unthrottled => (self.unthrottled_warmup, self.unthrottled_count),
        }
    }

    /// The rows of one mode: carrier and size.
    fn plan(&self, mode: Mode) -> Vec<(Carrier, usize)> {
        let mut plan: Vec<_> = self.sizes.iter().map(|&s| (Carrier::Ports, s)).collect();
        if !self.no_extras && (mode == Mode::Unthrottled || self.paced_extras) {
            plan.push((Carrier::ConfirmedPorts, EXTRA_SIZE));
            plan.push((Carrier::RawClient, EXTRA_SIZE));
        }
        plan
    }

    /// The carriers any row uses.
    fn carriers(&self) -> Vec<Carrier> {
        Carrier::ALL
            .into_iter()
            .filter(|&c| c == Carrier::Ports || !self.no_extras)
            .collect()
    }
}

/// Which part of the round trip a row times.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum Leg {
    /// Put (or publish) to the echo's arrival back.
    RoundTrip,
    /// The echo's put to its arrival at the measuring in-port, by the
    /// message's `x-sent-ns` (the ports' own latency figure).
    OneWay,
}

/// One row: a transport, carrier, leg, mode and size.
#[derive(Debug, Clone, Serialize)]
pub struct PortsRow {
    /// What carried the messages.
    pub transport: Transport,
    /// Ports, confirmed ports or the raw client.
    pub carrier: Carrier,
    /// Round trip, or the ports' one-way latency.
    pub leg: Leg,
    /// Paced or unthrottled.
    pub mode: Mode,
    /// Payload size, bytes.
    pub size: usize,
    /// Round trips that failed (not in the statistics).
    pub lost: usize,
    /// Mean, quartiles, extremes, µs.
    #[serde(flatten)]
    pub stats: BoxStats,
}

/// The result of a `ports` run.
#[derive(Debug, Clone, Serialize)]
pub struct PortsReport {
    /// The options it ran with.
    pub config: PortsArgs,
    /// CPU cores of the machine.
    pub cores: usize,
    /// Worker threads of the runtime it ran on.
    pub worker_threads: usize,
    /// How loaded the machine was before the run.
    pub load_before: Option<MachineLoad>,
    /// And after.
    pub load_after: Option<MachineLoad>,
    /// Transports left out because their broker could not be reached.
    pub skipped: Vec<Transport>,
    /// Puts or publishes the echo tasks could not make.
    pub echo_failures: u64,
    /// One per transport, carrier, mode and size.
    pub rows: Vec<PortsRow>,
}

/// Runs the scenario; prints the table and the targets unless `quiet`.
///
/// The measuring loop is a task like the echoes, on the runtime's workers
/// rather than on the caller's thread (under `block_on` every round trip
/// would cross threads twice more).
pub async fn run(args: &PortsArgs) -> Result<PortsReport> {
    if args.sizes.is_empty() || args.transports.is_empty() || args.modes.is_empty() {
        return Err("--sizes, --transports and --modes must each name one at least".into());
    }
    let args = args.clone();
    tokio::spawn(run_here(args))
        .await
        .map_err(|e| PerfError(format!("the ports run failed: {e}")))?
}

async fn run_here(args: PortsArgs) -> Result<PortsReport> {
    let cores = std::thread::available_parallelism().map_or(0, |n| n.get());
    let worker_threads = tokio::runtime::Handle::current().metrics().num_workers();
    if !args.quiet {
        println!("ports: {cores} cores, {worker_threads} tokio worker threads.");
        println!(
            "Round trip out-port → echo (in-port → out-port) → in-port, one message in flight; \
             {} paced (100 Hz) and {} unthrottled round trips per row (after {} and {} warm-up).\n",
            args.paced_count, args.unthrottled_count, args.paced_warmup, args.unthrottled_warmup
        );
    }
    let load_before = MachineLoad::now();
    // Started whatever the transports: an idle broker costs nothing.
    let broker = Broker::builder()
        .listen("127.0.0.1:0".parse().expect("a socket address"))
        .start()
        .await
        .map_err(|e| format!("cannot start the in-process broker: {e}"))?;
    let broker = Arc::new(broker);
    let (endpoints, skipped) = endpoints(&args, &broker).await?;

    let mut pairs: Vec<Vec<(Carrier, Pair)>> = Vec::new();
    for (_, endpoint) in &endpoints {
        let mut mine = Vec::new();
        for carrier in args.carriers() {
            mine.push((carrier, Pair::open(endpoint, carrier).await?));
        }
        pairs.push(mine);
    }

    let mut rows = Vec::new();
    for &mode in &args.modes {
        let (warmup, count) = args.counts(mode);
        for (carrier, size) in args.plan(mode) {
            let payload = Bytes::from(vec![b'x'; size]);
            for ((transport, _), mine) in endpoints.iter().zip(&mut pairs) {
                let Some((_, pair)) = mine.iter_mut().find(|(c, _)| *c == carrier) else {
                    continue;
                };
                eprintln!(
                    "{} / {} / {} / {size} B ...",
                    transport.label(),
                    carrier.label(),
                    mode.label()
                );
                let (samples, one_way, lost) =
                    measure(pair, mode, &payload, warmup, count, &args).await;
                if let Some(dir) = &args.dump {
                    let name = format!(
                        "{}_{}_{}_{size}_{}.txt",
                        transport.key(),
                        carrier.key(),
                        mode.label().replace(' ', ""),
                        rows.len()
                    );
                    let text: String = samples.values().iter().map(|s| format!("{s}\n")).collect();
                    std::fs::create_dir_all(dir)?;
                    std::fs::write(dir.join(name), text)?;
                }
                rows.push(PortsRow {
                    transport: *transport,
                    carrier,
                    leg: Leg::RoundTrip,
                    mode,
                    size,
                    lost,
                    stats: samples.box_stats(),
                });
                if !one_way.values().is_empty() {
                    rows.push(PortsRow {
                        transport: *transport,
                        carrier,
                        leg: Leg::OneWay,
                        mode,
                        size,
                        lost,
                        stats: one_way.box_stats(),
                    });
                }
            }
        }
    }

    let mut echo_failures = 0;
    for mine in pairs {
        for (carrier, pair) in mine {
            let failures = pair.close().await;
            if failures > 0 {
                eprintln!("echo ({}) failed {failures} puts", carrier.label());
            }
            echo_failures += failures;
        }
    }
    drop(endpoints);
    if let Ok(broker) = Arc::try_unwrap(broker) {
        broker.shutdown().await;
    }
    let report = PortsReport {
        config: args,
        cores,
        worker_threads,
        load_before,
        load_after: MachineLoad::now(),
        skipped,
        echo_failures,
        rows,
    };
    if !report.config.quiet {
        print!("{}", table(&report.rows));
        println!("\n{}", targets(&report.rows));
        let load = |l: &Option<MachineLoad>| l.map_or("unknown".to_owned(), |l| l.to_string());
        println!(
            "Before: {}; after: {}.",
            load(&report.load_before),
            load(&report.load_after)
        );
    }
    if let Some(path) = &report.config.json {
        crate::report::write_json(path, &report)?;
    }
    Ok(report)
}

/// The transports' endpoints; RabbitMQ is left out with a message when it
/// cannot be reached.
async fn endpoints(
    args: &PortsArgs,
    broker: &Arc<BrokerHandle>,
) -> Result<(Vec<(Transport, Endpoint)>, Vec<Transport>)> {
    let mut endpoints = Vec::new();
    let mut skipped = Vec::new();
    let busy_poll = (args.busy_poll_us > 0).then(|| Duration::from_micros(args.busy_poll_us));
    for &transport in &args.transports {
        let endpoint = match transport {
            Transport::InProcess => Endpoint::new(
                Connector::in_process(broker),
                PortProfile::default(),
                busy_poll,
            ),
            Transport::LeveretTcp => {
                let addr = broker.local_addrs()[0];
                let profile = PortProfile::new(&format!("amqp://guest:guest@{addr}/%2f"))?;
                Endpoint::new(Connector::tcp(profile.broker.clone()), profile, busy_poll)
            }
            Transport::RabbitMq => {
                let mut profile = PortProfile::new(&args.rabbit_url)?;
                profile.broker.connection_timeout = CONNECT_TIMEOUT;
                let connector = Connector::tcp(profile.broker.clone());
                match tokio::time::timeout(CONNECT_TIMEOUT, connector.connect()).await {
                    Ok(Ok(connection)) => {
                        let _ = connection.close().await;
                    }
                    Ok(Err(error)) => {
                        eprintln!(
                            "RabbitMQ at {} unreachable ({error}): its rows are skipped.",
                            args.rabbit_url
                        );
                        skipped.push(transport);
                        continue;
                    }
                    Err(_) => {
                        eprintln!(
                            "RabbitMQ at {} did not answer: its rows are skipped.",
                            args.rabbit_url
                        );
                        skipped.push(transport);
                        continue;
                    }
                }
                Endpoint::new(connector, profile, busy_poll)
            }
        };
        endpoints.push((transport, endpoint));
    }
    Ok((endpoints, skipped))
}

/// Runs `count` measured round trips after `warmup` unmeasured ones.
/// Returns the round trips, the one-way latencies where the carrier gives
/// them, and the number of failed round trips (not in the samples).
async fn measure(
    pair: &mut Pair,
    mode: Mode,
    payload: &Bytes,
    warmup: usize,
    count: usize,
    args: &PortsArgs,
) -> (Samples, Samples, usize) {
    let mut samples = Samples::default();
    let mut one_way = Samples::default();
    let mut failed = 0;
    let mut ticks = tokio::time::interval(PACE);
    // A late echo delays the next put rather than bunching puts up: there
    // is never more than one message in flight.
    ticks.set_missed_tick_behavior(MissedTickBehavior::Delay);
    let mut next = Instant::now();
    let mut evict = vec![0u8; args.evict_kib * 1024];
    for i in 0..warmup + count {
        if !evict.is_empty() {
            for line in evict.chunks_mut(64) {
                line[0] = line[0].wrapping_add(1);
            }
            std::hint::black_box(&mut evict);
        }
        if mode == Mode::Paced && args.spin_pace {
            next = (next + PACE).max(Instant::now());
            while Instant::now() < next {
                std::hint::spin_loop();
            }
        } else if mode == Mode::Paced {
            ticks.tick().await;
        }
        let start = Instant::now();
        let result = pair.round_trip(payload).await;
        let elapsed = start.elapsed();
        match result {
            Ok(leg) if i >= warmup => {
                samples.push(elapsed.as_nanos() as u64);
                if let Some(leg) = leg {
                    one_way.push(leg.as_nanos() as u64);
                }
            }
            Ok(_) => {}
            Err(error) => {
                failed += 1;
                if failed <= 3 {
                    eprintln!("  round trip failed: {error}");
                }
                tokio::time::sleep(LATE_ECHO_WAIT).await;
                pair.drain();
            }
        }
    }
    (samples, one_way, failed)
}

/// The rows as a table, with Leveret's loopback p99 over RabbitMQ's.
fn table(rows: &[PortsRow]) -> String {
    let mut table = Table::new(&[
        "transport",
        "carrier",
        "mode",
        "size",
        "n",
        "lost",
        "mean",
        "min",
        "q1",
        "median",
        "q3",
        "p99",
        "max",
        "p99 ÷ RabbitMQ",
    ]);
    for row in rows {
        let s = &row.stats;
        let ratio = match row.transport {
            Transport::LeveretTcp => rabbit_twin(rows, row).map_or_else(
                || "-".to_owned(),
                |r| format!("{:.2}", s.p99_us / r.stats.p99_us),
            ),
            _ => "-".to_owned(),
        };
        table.row(vec![
            row.transport.label().to_owned(),
            match row.leg {
                Leg::RoundTrip => row.carrier.label().to_owned(),
                Leg::OneWay => format!("{}, one way", row.carrier.label()),
            },
            row.mode.label().to_owned(),
            format!("{} B", row.size),
            s.count.to_string(),
            row.lost.to_string(),
            micros(s.mean_us),
            micros(s.min_us),
            micros(s.q1_us),
            micros(s.median_us),
            micros(s.q3_us),
            micros(s.p99_us),
            micros(s.max_us),
            ratio,
        ]);
    }
    table.render()
}

/// RabbitMQ's row for the same carrier, mode and size.
fn rabbit_twin<'a>(rows: &'a [PortsRow], row: &PortsRow) -> Option<&'a PortsRow> {
    rows.iter().find(|r| {
        r.transport == Transport::RabbitMq
            && r.carrier == row.carrier
            && r.leg == row.leg
            && r.mode == row.mode
            && r.size == row.size
            && r.stats.count > 0
    })
}

/// The comparison with the targets: issue 17's in-process figures
/// (back to back median and p99, 100 Hz p99), for the round trip and the
/// one-way leg, and Leveret's loopback p99 at most half of RabbitMQ's.
/// Only printed; nothing is asserted.
fn targets(rows: &[PortsRow]) -> String {
    let mut out = String::from("Targets (ports without confirms):\n");
    for mode in [Mode::Paced, Mode::Unthrottled] {
        let plain = |r: &&PortsRow| r.mode == mode && r.carrier == Carrier::Ports;
        for leg in [Leg::RoundTrip, Leg::OneWay] {
            let in_process: Vec<&PortsRow> = rows
                .iter()
                .filter(plain)
                .filter(|r| r.leg == leg && r.transport == Transport::InProcess)
                .filter(|r| r.stats.count > 0)
                .collect();
            let Some(worst) = in_process
                .iter()
                .max_by(|a, b| a.stats.p99_us.total_cmp(&b.stats.p99_us))
            else {
                continue;
            };
            let (median, p99) = match mode {
                Mode::Unthrottled => IN_PROCESS_UNTHROTTLED_TARGET_US,
                Mode::Paced => (f64::INFINITY, IN_PROCESS_PACED_P99_TARGET_US),
            };
            let met = in_process
                .iter()
                .filter(|r| r.stats.median_us <= median && r.stats.p99_us <= p99)
                .count();
            let leg = match leg {
                Leg::RoundTrip => "round trip",
                Leg::OneWay => "one way",
            };
            let wanted = match mode {
                Mode::Unthrottled => format!("median ≤ {median} µs, p99 ≤ {p99} µs"),
                Mode::Paced => format!("p99 ≤ {p99} µs"),
            };
            let _ = writeln!(
                out,
                "- {}, {leg}: in-process {wanted} in {met}/{} sizes (worst p99 {} at {} B)",
                mode.label(),
                in_process.len(),
                micros(worst.stats.p99_us),
                worst.size
            );
        }
        let ratios: Vec<(usize, f64)> = rows
            .iter()
            .filter(plain)
            .filter(|r| r.leg == Leg::RoundTrip && r.transport == Transport::LeveretTcp)
            .filter_map(|r| Some((r.size, r.stats.p99_us / rabbit_twin(rows, r)?.stats.p99_us)))
            .collect();
        if let Some(&(worst_size, worst)) = ratios.iter().max_by(|a, b| a.1.total_cmp(&b.1)) {
            let met = ratios
                .iter()
                .filter(|(_, ratio)| *ratio <= LOOPBACK_P99_RATIO_TARGET)
                .count();
            let _ = writeln!(
                out,
                "- {}: loopback p99 ≤ {LOOPBACK_P99_RATIO_TARGET} × RabbitMQ's in {met}/{} sizes (worst ratio {worst:.2} at {worst_size} B)",
                mode.label(),
                ratios.len(),
            );
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn extras_are_unthrottled_unless_asked_for() {
        let args = PortsArgs {
            sizes: vec![8, 128],
            ..PortsArgs::default()
        };
        let unthrottled = args.plan(Mode::Unthrottled);
        assert_eq!(
            unthrottled,
            [
                (Carrier::Ports, 8),
                (Carrier::Ports, 128),
                (Carrier::ConfirmedPorts, EXTRA_SIZE),
                (Carrier::RawClient, EXTRA_SIZE)
            ]
        );
        assert_eq!(
            args.plan(Mode::Paced),
            [(Carrier::Ports, 8), (Carrier::Ports, 128)]
        );
        let paced_extras = PortsArgs {
            paced_extras: true,
            ..args.clone()
        };
        assert_eq!(paced_extras.plan(Mode::Paced), unthrottled);
        let no_extras = PortsArgs {
            no_extras: true,
            paced_extras: true,
            ..args
        };
        assert_eq!(no_extras.plan(Mode::Unthrottled).len(), 2);
        assert_eq!(no_extras.carriers(), [Carrier::Ports]);
    }

    #[test]
    fn the_ratio_column_and_targets_pair_leveret_with_rabbitmq() {
        let row = |transport, p99_us| PortsRow {
            transport,
            carrier: Carrier::Ports,
            leg: Leg::RoundTrip,
            mode: Mode::Paced,
            size: 16,
            lost: 0,
            stats: BoxStats {
                count: 10,
                p99_us,
                ..BoxStats::default()
            },
        };
        let rows = [
            row(Transport::InProcess, 20.0),
            row(Transport::LeveretTcp, 100.0),
            row(Transport::RabbitMq, 400.0),
        ];
        let text = table(&rows);
        assert!(text.lines().nth(3).unwrap().ends_with("0.25"), "{text}");
        let text = targets(&rows);
        assert!(
            text.contains("100 Hz, round trip: in-process p99 ≤ 60 µs in 1/1 sizes"),
            "{text}"
        );
        assert!(
            text.contains("in 1/1 sizes (worst ratio 0.25 at 16 B)"),
            "{text}"
        );
    }
}
