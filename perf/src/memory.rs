//! The `memory` scenario: resident memory (`VmRSS` from `/proc`) of a
//! broker on this host, read after a settling pause,
//! - idle (whatever it holds already, no connection of ours);
//! - with `connections` idle connections, each with one channel and one
//!   exclusive, server-named queue;
//! - with `backlog` queued transient messages of `size` bytes in one
//!   queue without a consumer (published with confirms, so they are all
//!   in the queue when memory is read).
//!
//! The broker's PID comes from `--pid`, or from the process listening on
//! the URL's port, or from the only `beam.smp` / `leveret` process.

use crate::load::{
    connect, prepare_publisher, publish, unique_prefix, PublisherCounters, PublisherSpec,
    DEFAULT_URL,
};
use crate::procfs::{find_broker_pid, rss_bytes};
use crate::report::{mib, thousands};
use crate::{PerfError, Result};
use leveret_client::{FieldTable, QueueDeclareOptions, QueueDeleteOptions, ShortStr};
use serde::Serialize;
use std::path::PathBuf;
use std::sync::atomic::AtomicBool;
use std::sync::Arc;
use std::time::{Duration, Instant};
use tokio::sync::Semaphore;

/// Options of the `memory` subcommand.
#[derive(Debug, Clone, clap::Args, Serialize)]
pub struct MemoryArgs {
    /// Broker URL.
    #[arg(long, default_value = DEFAULT_URL)]
    pub url: String,
    /// The broker's PID (default: found from the URL's port).
    #[arg(long)]
    pub pid: Option<u32>,
    /// Idle connections to open, each with a channel and a queue (0: skip).
    #[arg(long, default_value_t = 0)]
    pub connections: usize,
    /// Messages to queue without a consumer (0: skip).
    #[arg(long, default_value_t = 0)]
    pub backlog: u64,
    /// Body size of the queued messages.
    #[arg(long, default_value_t = 16)]
    pub size: usize,
    /// Seconds to wait before each reading.
    #[arg(long, default_value_t = 2.0)]
    pub settle: f64,
    /// Write the report as JSON to this file.
    #[arg(long)]
    pub json: Option<PathBuf>,
    /// No summary.
    #[arg(long)]
    pub quiet: bool,
}

impl Default for MemoryArgs {
    fn default() -> Self {
        MemoryArgs {
            url: DEFAULT_URL.to_owned(),
            pid: None,
            connections: 0,
            backlog: 0,
            size: 16,
            settle: 2.0,
            json: None,
            quiet: false,
        }
    }
}

/// Memory with many idle connections.
#[derive(Debug, Clone, Copy, Serialize)]
pub struct ConnectionsMemory {
    /// Connections held open.
    pub connections: usize,
    /// Resident memory with them open, bytes.
    pub rss_bytes: u64,
    /// Over the idle figure, per connection, bytes.
    pub per_connection_bytes: f64,
    /// Seconds it took to open them.
    pub open_s: f64,
}

/// Memory with a backlog of queued messages.
#[derive(Debug, Clone, Copy, Serialize)]
pub struct BacklogMemory {
    /// Messages queued (as the broker counts them).
    pub messages: u64,
    /// Body size, bytes.
    pub size: usize,
    /// Resident memory with them queued, bytes.
    pub rss_bytes: u64,
    /// Over the idle figure, per message, bytes.
    pub per_message_bytes: f64,
    /// Seconds it took to publish them (confirmed).
    pub fill_s: f64,
}

/// The result of a `memory` run.
#[derive(Debug, Clone, Serialize)]
pub struct MemoryReport {
    /// The broker's PID.
    pub pid: u32,
    /// Resident memory idle, bytes.
    pub idle_bytes: u64,
    /// With idle connections, if asked for.
    pub connections: Option<ConnectionsMemory>,
    /// With a backlog, if asked for.
    pub backlog: Option<BacklogMemory>,
}

fn read_rss(pid: u32) -> Result<u64> {
    rss_bytes(pid).ok_or_else(|| PerfError(format!("cannot read VmRSS of pid {pid}")))
}

/// The broker's PID from the options.
pub fn broker_pid(args: &MemoryArgs) -> Result<u32> {
    args.pid
        .or_else(|| find_broker_pid(&args.url))
        .ok_or_else(|| PerfError("cannot find the broker's PID; give --pid".to_owned()))
}

/// Resident memory of the broker, idle.
pub async fn idle(pid: u32, settle: f64) -> Result<u64> {
    tokio::time::sleep(Duration::from_secs_f64(settle)).await;
    read_rss(pid)
}

/// Opens `n` idle connections (one channel, one exclusive queue each),
/// reads the broker's memory, closes them.
pub async fn with_connections(
    url: &str,
    pid: u32,
    n: usize,
    settle: f64,
    idle_bytes: u64,
) -> Result<ConnectionsMemory> {
    let started = Instant::now();
    let gate = Arc::new(Semaphore::new(64));
    let mut tasks = Vec::with_capacity(n);
    for i in 0..n {
        let gate = Arc::clone(&gate);
        let url = url.to_owned();
        tasks.push(tokio::spawn(async move {
            let _permit = gate.acquire_owned().await;
            let connection = connect(&url, &format!("idle {i}")).await?;
            let channel = connection.open_channel().await?;
            channel
                .queue_declare(
                    "",
                    QueueDeclareOptions {
                        exclusive: true,
                        ..Default::default()
                    },
                    FieldTable::new(),
                )
                .await?;
            Ok::<_, PerfError>((connection, channel))
        }));
    }
    let mut held = Vec::with_capacity(n);
    let mut failure = None;
    for task in tasks {
        match task.await {
            Ok(Ok(pair)) => held.push(pair),
            Ok(Err(e)) => failure = Some(e),
            Err(e) => failure = Some(PerfError(e.to_string())),
        }
    }
    let open_s = started.elapsed().as_secs_f64();
    let reading = match failure {
        Some(e) => Err(PerfError(format!(
            "opened only {} of {n} connections: {e}",
            held.len()
        ))),
        None => {
            tokio::time::sleep(Duration::from_secs_f64(settle)).await;
            read_rss(pid)
        }
    };
    let closes: Vec<_> = held
        .into_iter()
        .map(|(connection, channel)| {
            tokio::spawn(async move {
                drop(channel);
                let _ = connection.close().await;
            })
        })
        .collect();
    for close in closes {
        let _ = close.await;
    }
    let rss = reading?;
    Ok(ConnectionsMemory {
        connections: n,
        rss_bytes: rss,
        per_connection_bytes: (rss as f64 - idle_bytes as f64) / n.max(1) as f64,
        open_s,
    })
}

/// Queues `messages` transient messages of `size` bytes without a
/// consumer, reads the broker's memory, deletes the queue.
pub async fn with_backlog(
    url: &str,
    pid: u32,
    messages: u64,
    size: usize,
    settle: f64,
    idle_bytes: u64,
) -> Result<BacklogMemory> {
    let queue = ShortStr::try_from(unique_prefix("backlog")).map_err(|e| e.to_string())?;
    let connection = connect(url, "backlog").await?;
    let channel = connection.open_channel().await?;
    channel
        .queue_declare(&queue, QueueDeclareOptions::default(), FieldTable::new())
        .await?;
    let result = async {
        let spec = PublisherSpec {
            id: 0,
            exchange: ShortStr::default(),
            routing_key: queue.clone(),
            persistent: false,
            size: size.max(8),
            rate: 0.0,
            count: messages,
            confirm_window: 1024,
            first: 0,
        };
        prepare_publisher(&channel, &spec).await?;
        let started = Instant::now();
        publish(
            &channel,
            &spec,
            &PublisherCounters::default(),
            &AtomicBool::new(false),
        )
        .await?;
        let fill_s = started.elapsed().as_secs_f64();
        let info = channel
            .queue_declare(
                &queue,
                QueueDeclareOptions {
                    passive: true,
                    ..Default::default()
                },
                FieldTable::new(),
            )
            .await?;
        tokio::time::sleep(Duration::from_secs_f64(settle)).await;
        let rss = read_rss(pid)?;
        Ok::<_, PerfError>(BacklogMemory {
            messages: u64::from(info.message_count),
            size: spec.size,
            rss_bytes: rss,
            per_message_bytes: (rss as f64 - idle_bytes as f64)
                / f64::from(info.message_count.max(1)),
            fill_s,
        })
    }
    .await;
    let _ = channel
        .queue_delete(&queue, QueueDeleteOptions::default())
        .await;
    let _ = connection.close().await;
    result
}

/// Runs the readings asked for; prints them unless `quiet`.
pub async fn run(args: &MemoryArgs) -> Result<MemoryReport> {
    let pid = broker_pid(args)?;
    let idle_bytes = idle(pid, args.settle).await?;
    let connections = if args.connections > 0 {
        Some(with_connections(&args.url, pid, args.connections, args.settle, idle_bytes).await?)
    } else {
        None
    };
    let backlog = if args.backlog > 0 {
        let idle_now = idle(pid, args.settle).await?;
        Some(
            with_backlog(
                &args.url,
                pid,
                args.backlog,
                args.size,
                args.settle,
                idle_now,
            )
            .await?,
        )
    } else {
        None
    };
    let report = MemoryReport {
        pid,
        idle_bytes,
        connections,
        backlog,
    };
    if !args.quiet {
        println!("--- memory of pid {pid}");
        println!("idle: {}", mib(idle_bytes as f64));
        if let Some(c) = &report.connections {
            println!(
                "{} idle connections (1 channel, 1 queue each): {} ({} per connection; opened in {:.1} s)",
                thousands(c.connections as f64),
                mib(c.rss_bytes as f64),
                thousands(c.per_connection_bytes) + " B",
                c.open_s
            );
        }
        if let Some(b) = &report.backlog {
            println!(
                "{} queued {} B messages: {} ({} per message; filled in {:.1} s)",
                thousands(b.messages as f64),
                b.size,
                mib(b.rss_bytes as f64),
                thousands(b.per_message_bytes) + " B",
                b.fill_s
            );
        }
    }
    if let Some(path) = &args.json {
        crate::report::write_json(path, &report)?;
    }
    Ok(report)
}
