//! A 1 kHz control loop on a thread of its own, woken at absolute
//! deadlines (`clock_nanosleep(CLOCK_MONOTONIC, TIMER_ABSTIME)`, so a late
//! wake-up never shifts the periods after it), putting a velocity command
//! each period through an out-port; a robot thread takes the commands
//! from an in-port with `recv_blocking`. Both ports talk in-process to an
//! embedded Leveret, their tasks on a tokio runtime beside the two
//! threads. At the end it prints the loop's wake-up jitter (how late each
//! period started), the cost of `try_put` and the commands' latency from
//! put to the robot's `recv_blocking`, with the ports' counters.
//!
//! ```text
//! cargo run --release -p leveret-ports --features embedded --example control_1khz -- [seconds]
//! ```

use leveret_ports::{
    Connector, InPort, OutPort, PortProfile, PortStatus, Qos, Time, TimedVelocity2D, Velocity2D,
};
use rustix::thread::{clock_nanosleep_absolute, ClockId};
use rustix::time::{clock_gettime, Timespec};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::Duration;

/// The control period: 1 kHz.
const PERIOD_NS: i64 = 1_000_000;

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let seconds: i64 = std::env::args()
        .nth(1)
        .map(|s| s.parse())
        .transpose()?
        .unwrap_or(5);
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()?;
    let broker = Arc::new(runtime.block_on(leveret_broker::Broker::builder().start())?);
    let profile = PortProfile::default()
        .queue("cmd_vel")
        .routing_key("cmd_vel")
        .qos(Qos::Command);
    let local = Connector::in_process(&broker);
    let output = runtime.block_on(OutPort::<TimedVelocity2D>::connect_with(
        local.clone(),
        profile.clone(),
    ))?;
    let input =
        Arc::new(runtime.block_on(InPort::<TimedVelocity2D>::connect_with(local, profile))?);

    let stopped = Arc::new(AtomicBool::new(false));
    let robot = {
        let input = Arc::clone(&input);
        let stopped = Arc::clone(&stopped);
        std::thread::spawn(move || {
            let mut latencies = Vec::new();
            // Until the controller has stopped and its last command is in.
            loop {
                match input.recv_blocking(Duration::from_millis(100)) {
                    Some(sample) => latencies.extend(sample.latency),
                    None if stopped.load(Ordering::Acquire) => return latencies,
                    None => {}
                }
            }
        })
    };
    let periods = seconds * 1000;
    println!("{periods} periods of 1 ms on a thread timer, commands in-process to a robot thread");
    let control = std::thread::spawn(move || control_loop(&output, periods));
    let (lateness, put_costs, not_ok, stats) = control.join().expect("control loop");
    stopped.store(true, Ordering::Release);
    let latencies = robot.join().expect("robot");

    print_figures("wake-up jitter (late by)", lateness);
    print_figures("try_put", put_costs);
    print_figures("put to the robot's recv_blocking", latencies);
    println!("puts not Ok: {not_ok}");
    println!("out-port: {stats:?}");
    println!("in-port: {:?}", input.stats());
    drop(input);
    if let Some(broker) = Arc::into_inner(broker) {
        runtime.block_on(broker.shutdown());
    }
    Ok(())
}

/// Puts a command every period until `periods` have passed; how late each
/// period started and each `try_put`'s cost, the puts that were not `Ok`
/// and the out-port's counters at the end.
fn control_loop(
    output: &OutPort<TimedVelocity2D>,
    periods: i64,
) -> (
    Vec<Duration>,
    Vec<Duration>,
    u64,
    leveret_ports::OutPortStats,
) {
    let mut lateness = Vec::with_capacity(periods as usize);
    let mut put_costs = Vec::with_capacity(periods as usize);
    let mut not_ok = 0;
    let start = clock_gettime(ClockId::Monotonic);
    for n in 1..=periods {
        let deadline = add_ns(start, n * PERIOD_NS);
        // Interrupted by a signal: sleep again to the same deadline.
        while clock_nanosleep_absolute(ClockId::Monotonic, &deadline).is_err() {}
        lateness.push(since(deadline));
        let angle = n as f64 * std::f64::consts::TAU / 1000.0;
        let command = TimedVelocity2D {
            tm: Time::now(),
            data: Velocity2D {
                vx: 0.5,
                vy: 0.0,
                va: 0.2 * angle.sin(),
            },
        };
        let before = clock_gettime(ClockId::Monotonic);
        let status = output.try_put(&command);
        put_costs.push(since(before));
        if status != PortStatus::Ok {
            not_ok += 1;
        }
    }
    (lateness, put_costs, not_ok, output.stats())
}

fn add_ns(at: Timespec, ns: i64) -> Timespec {
    let total = at.tv_nsec + ns;
    Timespec {
        tv_sec: at.tv_sec + total.div_euclid(1_000_000_000),
        tv_nsec: total.rem_euclid(1_000_000_000),
    }
}

/// The monotonic time elapsed since `at` (zero if `at` is later).
fn since(at: Timespec) -> Duration {
    let now = clock_gettime(ClockId::Monotonic);
    let ns = (now.tv_sec - at.tv_sec) * 1_000_000_000 + (now.tv_nsec - at.tv_nsec);
    Duration::from_nanos(u64::try_from(ns).unwrap_or(0))
}

fn print_figures(what: &str, mut samples: Vec<Duration>) {
    if samples.is_empty() {
        println!("{what}: no samples");
        return;
    }
    samples.sort();
    let at = |q: f64| samples[((samples.len() - 1) as f64 * q) as usize];
    println!(
        "{what}: n {}, p50 {:?}, p99 {:?}, p99.9 {:?}, max {:?}",
        samples.len(),
        at(0.5),
        at(0.99),
        at(0.999),
        samples[samples.len() - 1]
    );
}
