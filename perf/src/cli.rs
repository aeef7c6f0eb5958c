//! The command line: `leveret-perf [--threads N] <subcommand> [options]`,
//! and the tokio runtime the subcommands run on.

use crate::compare::{self, CompareArgs};
use crate::memory::{self, MemoryArgs};
use crate::ports::{self, PortsArgs};
use crate::quality::{self, QualityArgs};
use crate::rtt::{self, RttArgs};
use crate::sink::{self, SinkArgs};
use crate::throughput::{self, ThroughputArgs};
use crate::Result;
use clap::{Parser, Subcommand};

/// Load generator for any AMQP 0.9.1 broker.
#[derive(Debug, Parser)]
#[command(name = "leveret-perf", version, about, long_about = None)]
pub struct Cli {
    /// Worker threads of the runtime (0: one per core).
    #[arg(long, global = true, default_value_t = 0)]
    pub threads: usize,
    /// What to run.
    #[command(subcommand)]
    pub command: Command,
}

/// The subcommands.
#[derive(Debug, Subcommand)]
pub enum Command {
    /// Publishers, consumers, queues: msgs/s, latency, lost and out-of-order.
    Throughput(ThroughputArgs),
    /// The paper's round trip through two queues and an echo client.
    Rtt(RttArgs),
    /// The paper's one-to-four broadcast: lost and out-of-order per consumer.
    Quality(QualityArgs),
    /// Resident memory of a local broker: idle, many connections, a backlog.
    Memory(MemoryArgs),
    /// Runs the scenario set against two brokers and tabulates the ratios.
    Compare(CompareArgs),
    /// Round trip of a pair of robot data ports: in-process, loopback TCP, RabbitMQ.
    Ports(PortsArgs),
    /// A control loop's `try_put` before, during and after a frozen broker.
    PortsStall(ports::stall::StallArgs),
    /// What recording costs `put`, and how a recording's playback keeps pace.
    PortsReplay(ports::replay::ReplayArgs),
    /// A null broker that confirms and drops everything: a generator's own ceiling.
    Sink(SinkArgs),
}

/// Runs a subcommand on the current runtime.
pub async fn execute(command: &Command) -> Result<()> {
    match command {
        Command::Throughput(args) => throughput::run(args).await.map(drop),
        Command::Rtt(args) => rtt::run(args).await.map(drop),
        Command::Quality(args) => quality::run(args).await.map(drop),
        Command::Memory(args) => memory::run(args).await.map(drop),
        Command::Compare(args) => compare::run(args).await.map(drop),
        Command::Ports(args) => ports::run(args).await.map(drop),
        Command::PortsStall(args) => ports::stall::run(args).await,
        Command::PortsReplay(args) => ports::replay::run(args).await,
        Command::Sink(args) => sink::run(args).await,
    }
}

/// Builds the runtime and runs the command line.
pub fn main_with(cli: Cli) -> Result<()> {
    let mut builder = tokio::runtime::Builder::new_multi_thread();
    if cli.threads > 0 {
        builder.worker_threads(cli.threads);
    }
    let runtime = builder.enable_all().build()?;
    runtime.block_on(execute(&cli.command))
}
