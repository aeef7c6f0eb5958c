//! The `ports-stall` scenario: what a control loop's `try_put` costs
//! before, during and after a frozen broker, the figures the ports' tests
//! no longer assert (they prove only that `put` never waits). An embedded
//! Leveret listens on loopback; an out-port with the `Command` preset
//! reaches it through a proxy that stops forwarding for the frozen phase
//! (as SIGSTOP leaves a broker's sockets), an in-port directly. A loop on
//! a thread of its own puts at the given rate, each period at an absolute
//! deadline. Per phase it prints the puts' wall time (p50, p99, max), how
//! many puts saw the loop's thread switch out voluntarily (from
//! `/proc/thread-self/status`: a put that slept or waited on a lock), the
//! statuses returned, and at the end the ports' counters (the in-port's
//! latency is from put to the robot task's `recv`) and when the link was
//! reported degraded and well again.

use crate::Result;
use leveret_broker::Broker;
use leveret_ports::{InPort, OutPort, PortProfile, Qos, Time, TimedLong};
use leveret_tests::fault_proxy::FaultProxy;
use std::collections::BTreeMap;
use std::sync::Arc;
use std::time::{Duration, Instant};

/// The options of `ports-stall`.
#[derive(Debug, Clone, clap::Args)]
pub struct StallArgs {
    /// Puts per second.
    #[arg(long, default_value_t = 1000)]
    pub rate: u32,
    /// Seconds before the freeze.
    #[arg(long, default_value_t = 1.0)]
    pub before: f64,
    /// Seconds the broker stays frozen.
    #[arg(long, default_value_t = 5.0)]
    pub frozen: f64,
    /// Seconds after the thaw.
    #[arg(long, default_value_t = 2.0)]
    pub after: f64,
}

/// The loop's phases.
const PHASES: [&str; 3] = ["before", "frozen", "after"];

/// What the loop saw in one phase.
#[derive(Debug, Default)]
struct Phase {
    puts: Vec<Duration>,
    switched: usize,
    statuses: BTreeMap<String, usize>,
}

/// Runs the scenario and prints its figures.
pub async fn run(args: &StallArgs) -> Result<()> {
    let broker = Broker::builder()
        .listen("127.0.0.1:0".parse().map_err(|e| format!("{e}"))?)
        .start()
        .await
        .map_err(|e| format!("starting the broker: {e}"))?;
    let addr = broker.local_addrs()[0];
    let proxy = Arc::new(FaultProxy::start(addr).await);
    let base = PortProfile::new(&format!("amqp://guest:guest@{addr}/%2f"))?
        .queue("leveret.perf.stall")
        .routing_key("leveret.perf.stall")
        .qos(Qos::Command);
    let input = Arc::new(InPort::<TimedLong>::connect(base.clone()).await?);
    // The robot takes every command (its latency is measured then).
    let reader = {
        let input = Arc::clone(&input);
        tokio::spawn(async move { while input.recv().await.is_some() {} })
    };
    let (window, lifespan) = (base.max_unconfirmed, base.lifespan.unwrap_or_default());
    let mut proxied = base;
    proxied.broker.port = proxy.addr.port();
    let output = OutPort::<TimedLong>::connect(proxied).await?;
    let mut link = output.link();
    let watcher = tokio::spawn(async move {
        let started = Instant::now();
        let mut changes = Vec::new();
        while link.changed().await.is_ok() {
            let state = link.borrow_and_update().state();
            changes.push((started.elapsed(), state.as_str()));
        }
        changes
    });

    let period = Duration::from_secs(1) / args.rate.max(1);
    let ends = [
        args.before,
        args.before + args.frozen,
        args.before + args.frozen + args.after,
    ]
    .map(Duration::from_secs_f64);
    let frozen = Arc::clone(&proxy);
    let phases = tokio::task::spawn_blocking(move || {
        let mut phases: Vec<Phase> = PHASES.iter().map(|_| Phase::default()).collect();
        let start = Instant::now();
        let mut phase = 0;
        for n in 1u32.. {
            let deadline = start + period * n;
            if let Some(wait) = deadline.checked_duration_since(Instant::now()) {
                std::thread::sleep(wait);
            }
            let now = deadline - start;
            if now >= ends[2] {
                break;
            }
            let current = ends.iter().position(|end| now < *end).unwrap_or(2);
            if current != phase {
                phase = current;
                frozen.freeze(phase == 1);
            }
            let value = TimedLong {
                tm: Time::now(),
                data: n as i32,
            };
            let switches = voluntary_switches();
            let before = Instant::now();
            let status = output.try_put(&value);
            let took = before.elapsed();
            let record = &mut phases[phase];
            record.puts.push(took);
            if voluntary_switches() != switches {
                record.switched += 1;
            }
            *record.statuses.entry(format!("{status:?}")).or_default() += 1;
        }
        (phases, output)
    })
    .await
    .map_err(|e| format!("the control loop: {e}"))?;
    let (phases, output) = phases;
    let flushed = tokio::time::timeout(Duration::from_secs(10), output.flush()).await;

    println!(
        "ports-stall: try_put at {} Hz, Command preset (window {window}, lifespan {lifespan:?}), \
         broker frozen {:.1} s",
        args.rate, args.frozen
    );
    for (name, mut phase) in PHASES.iter().zip(phases) {
        phase.puts.sort();
        let at = |q: f64| {
            phase
                .puts
                .get(((phase.puts.len().saturating_sub(1)) as f64 * q) as usize)
                .copied()
                .unwrap_or_default()
        };
        println!(
            "{name:>7}: {} puts, p50 {:?}, p99 {:?}, max {:?}; {} with a voluntary context switch; {:?}",
            phase.puts.len(),
            at(0.5),
            at(0.99),
            at(1.0),
            phase.switched,
            phase.statuses
        );
    }
    if flushed.is_err() {
        println!("the out-port had not settled everything 10 s after the thaw");
    }
    println!("out-port: {:?}", output.stats());
    println!("in-port: {:?}", input.stats());
    reader.abort();
    drop(output);
    let changes = watcher.await.map_err(|e| format!("{e}"))?;
    for (at, state) in changes {
        println!("link {state} at {:.3} s", at.as_secs_f64());
    }
    Ok(())
}

/// This thread's voluntary context switches so far (0 where `/proc` does
/// not say).
fn voluntary_switches() -> u64 {
    std::fs::read_to_string("/proc/thread-self/status")
        .ok()
        .and_then(|status| {
            status
                .lines()
                .find_map(|line| line.strip_prefix("voluntary_ctxt_switches:"))
                .and_then(|count| count.trim().parse().ok())
        })
        .unwrap_or(0)
}
