//! # leveret-perf
//!
//! A load generator for any AMQP 0.9.1 broker, built on `leveret-client`.
//! Seven subcommands (see `leveret-perf --help`):
//!
//! - `throughput`: P publishers, C consumers, Q queues; transient or
//!   persistent, confirms with a window, no-ack or manual acks; a progress
//!   line every second and a summary with publish/consume rates, latency
//!   percentiles and lost / out-of-order counts per consumer.
//! - `rtt`: the paper's round trip through two queues and an echo client,
//!   one message in flight or at a fixed rate, per payload size.
//! - `quality`: the paper's one-to-four broadcast, counting lost and
//!   out-of-order messages per consumer.
//! - `compare`: a scenario set run against two brokers one after the other,
//!   printed as a table of figures and ratios.
//! - `memory`: resident memory of a local broker idle, with many idle
//!   connections, and with a backlog of queued messages.
//! - `ports`: the paper's round trip through a pair of robot data ports
//!   (`leveret_ports`), over a Leveret broker this process starts
//!   (in-process and loopback TCP) and RabbitMQ, paced at 100 Hz and
//!   unthrottled, with confirmed-port and raw-client rows beside them.
//! - `sink`: a null broker that confirms and drops every publish, to
//!   measure a generator's own ceiling (ours or another's).
//!
//! Every subcommand can write its full result as JSON (`--json FILE`);
//! `rtt` and `compare` can draw a box plot as SVG (`--svg FILE`).
//!
//! # Method
//! Message bodies carry a sequence number (publisher id in the top 16
//! bits) and, from 16 bytes up, the send time in nanoseconds since a
//! process-wide epoch, so latency is measured by one clock (publishers and
//! consumers run in the same process). Publishers and consumers use
//! separate connections. Rates are counted over a fixed window after a
//! warm-up.
//!
//! # Layout
//! - `cli`: the command line (clap) and the runtime that runs it.
//! - `body`: the message layout and the clock.
//! - `histogram`: a log-linear latency histogram; exact-sample statistics.
//! - `sequence`: per-consumer sequence tracking (lost, gaps, out of order, duplicates).
//! - `load`: publisher and consumer tasks, and the queue topology they share.
//! - `throughput`, `rtt`, `quality`, `memory`, `ports`: the scenarios.
//! - `sink`: the null broker.
//! - `compare`: runs scenarios against two brokers and tabulates ratios.
//! - `procfs`: resident memory, CPU time, the PID behind a listening port,
//!   the machine's busy time, load average and CPU pressure.
//! - `svg`: the hand-written box plot.
//! - `report`: number formatting and JSON output.
#![forbid(unsafe_code)]
#![deny(missing_docs)]

pub mod body;
pub mod cli;
pub mod compare;
pub mod histogram;
pub mod load;
pub mod memory;
pub mod ports;
pub mod procfs;
pub mod quality;
pub mod report;
pub mod rtt;
pub mod sequence;
pub mod sink;
pub mod svg;
pub mod throughput;

use std::fmt;

/// Anything that stops a run: a client error, I/O, a bad argument.
#[derive(Debug, Clone)]
pub struct PerfError(pub String);

impl fmt::Display for PerfError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(&self.0)
    }
}

impl std::error::Error for PerfError {}

impl From<leveret_client::Error> for PerfError {
    fn from(e: leveret_client::Error) -> Self {
        PerfError(format!("AMQP: {e}"))
    }
}

impl From<std::io::Error> for PerfError {
    fn from(e: std::io::Error) -> Self {
        PerfError(format!("I/O: {e}"))
    }
}

impl From<serde_json::Error> for PerfError {
    fn from(e: serde_json::Error) -> Self {
        PerfError(format!("JSON: {e}"))
    }
}

impl From<String> for PerfError {
    fn from(s: String) -> Self {
        PerfError(s)
    }
}

impl From<&str> for PerfError {
    fn from(s: &str) -> Self {
        PerfError(s.to_owned())
    }
}

/// The result type of this crate.
pub type Result<T, E = PerfError> = std::result::Result<T, E>;
