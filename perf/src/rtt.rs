//! The `rtt` scenario, the paper's round-trip experiment: a pinger
//! publishes to queue A; an echo client (its own connection) consumes A
//! and republishes each body, untouched, to queue B; the pinger consumes B
//! and measures the time from before its publish to the delivery of the
//! echo. Both use the default exchange and no-ack consumers.
//!
//! With `--rate 0` exactly one message is in flight (the next goes out as
//! soon as the echo is back); with `--rate 100` one goes out every 10 ms
//! whatever the echoes do, as in the paper. For each payload size
//! (default 8, 16, 32, 64 and 128 bytes): a few unmeasured warm-up
//! pings, then `repeat` series of `count` pings, `pause` seconds apart.
//! An echo that does not come back within `timeout` seconds counts as lost.

use crate::body::{read_seq, BodyWriter};
use crate::histogram::{BoxStats, Samples};
use crate::load::{connect, unique_prefix, DEFAULT_URL};
use crate::report::{micros, Table};
use crate::{PerfError, Result};
use leveret_client::{
    BasicConsumeOptions, BasicProperties, BasicPublishOptions, Channel, Consumer, FieldTable,
    QueueDeclareOptions, QueueDeleteOptions, ShortStr,
};
use serde::Serialize;
use std::collections::VecDeque;
use std::path::PathBuf;
use std::time::{Duration, Instant};

/// Options of the `rtt` subcommand.
#[derive(Debug, Clone, clap::Args, Serialize)]
pub struct RttArgs {
    /// Broker URL.
    #[arg(long, default_value = DEFAULT_URL)]
    pub url: String,
    /// Payload sizes in bytes.
    #[arg(long, value_delimiter = ',', default_value = "8,16,32,64,128")]
    pub sizes: Vec<usize>,
    /// Pings per series.
    #[arg(long, default_value_t = 1000)]
    pub count: usize,
    /// Series per size.
    #[arg(long, default_value_t = 1)]
    pub repeat: usize,
    /// Pings per second (0: one in flight, the next as soon as the echo is back).
    #[arg(long, default_value_t = 0.0)]
    pub rate: f64,
    /// Unmeasured pings before each size.
    #[arg(long, default_value_t = 100)]
    pub warmup: usize,
    /// Seconds between series.
    #[arg(long, default_value_t = 0.0)]
    pub pause: f64,
    /// Seconds after which a ping counts as lost.
    #[arg(long, default_value_t = 5.0)]
    pub timeout: f64,
    /// Write the report as JSON to this file.
    #[arg(long)]
    pub json: Option<PathBuf>,
    /// Write a box plot (SVG) to this file.
    #[arg(long)]
    pub svg: Option<PathBuf>,
    /// No summary table.
    #[arg(long)]
    pub quiet: bool,
}

impl Default for RttArgs {
    fn default() -> Self {
        RttArgs {
            url: DEFAULT_URL.to_owned(),
            sizes: vec![8, 16, 32, 64, 128],
            count: 1000,
            repeat: 1,
            rate: 0.0,
            warmup: 100,
            pause: 0.0,
            timeout: 5.0,
            json: None,
            svg: None,
            quiet: false,
        }
    }
}

/// Round-trip statistics of one payload size.
#[derive(Debug, Clone, Serialize)]
pub struct RttSize {
    /// Payload size, bytes.
    pub size: usize,
    /// Pings sent (measured).
    pub sent: usize,
    /// Echoes that never came back.
    pub lost: usize,
    /// Mean, quartiles, extremes, µs.
    #[serde(flatten)]
    pub stats: BoxStats,
}

/// The result of an `rtt` run.
#[derive(Debug, Clone, Serialize)]
pub struct RttReport {
    /// The options it ran with.
    pub config: RttArgs,
    /// One entry per payload size.
    pub sizes: Vec<RttSize>,
}

/// The pinger's side: its channel, its consumer of B, the queue A.
struct Pinger {
    channel: Channel,
    replies: Consumer,
    queue_a: ShortStr,
    next_seq: u64,
}

impl Pinger {
    async fn send(&mut self, writer: &mut BodyWriter) -> Result<u64> {
        let seq = self.next_seq;
        self.next_seq += 1;
        let body = writer.body(seq);
        self.channel
            .basic_publish(
                "",
                &self.queue_a,
                BasicPublishOptions::default(),
                BasicProperties::default(),
                body,
            )
            .await?;
        Ok(seq)
    }

    /// The sequence number of the next echo (truncated to the body), or
    /// `None` when the consumer ended.
    async fn reply(&mut self, size: usize) -> Option<u64> {
        let delivery = self.replies.next().await?;
        Some(seq_of(&delivery.body, size))
    }

    /// `count` pings of `size` bytes; the round trips go to `samples`
    /// (if given); returns how many were lost.
    async fn series(
        &mut self,
        size: usize,
        count: usize,
        rate: f64,
        timeout: Duration,
        mut samples: Option<&mut Samples>,
    ) -> Result<usize> {
        let mut writer = BodyWriter::new(size);
        let mut lost = 0;
        if rate <= 0.0 {
            for _ in 0..count {
                let sent_at = Instant::now();
                let seq = truncate(self.send(&mut writer).await?, size);
                let deadline = tokio::time::Instant::from_std(sent_at + timeout);
                loop {
                    match tokio::time::timeout_at(deadline, self.reply(size)).await {
                        Ok(Some(got)) if got == seq => {
                            if let Some(s) = samples.as_deref_mut() {
                                s.push(sent_at.elapsed().as_nanos() as u64);
                            }
                            break;
                        }
                        // A late echo of an earlier, already lost ping.
                        Ok(Some(_)) => continue,
                        Ok(None) => return Err("the echo consumer ended".into()),
                        Err(_) => {
                            lost += 1;
                            break;
                        }
                    }
                }
            }
            return Ok(lost);
        }
        let mut ticker = tokio::time::interval(Duration::from_secs_f64(1.0 / rate));
        ticker.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
        let mut in_flight: VecDeque<(u64, Instant)> = VecDeque::new();
        let mut sent = 0;
        let mut last_sent = Instant::now();
        while sent < count || !in_flight.is_empty() {
            let give_up = tokio::time::Instant::from_std(last_sent + timeout);
            tokio::select! {
                _ = ticker.tick(), if sent < count => {
                    let at = Instant::now();
                    let seq = truncate(self.send(&mut writer).await?, size);
                    in_flight.push_back((seq, at));
                    sent += 1;
                    last_sent = at;
                }
                reply = self.reply(size) => {
                    let Some(got) = reply else {
                        return Err("the echo consumer ended".into());
                    };
                    let now = Instant::now();
                    // Echoes come back in order: anything older is lost.
                    while let Some(&(seq, at)) = in_flight.front() {
                        if seq == got {
                            in_flight.pop_front();
                            if let Some(s) = samples.as_deref_mut() {
                                s.push(now.duration_since(at).as_nanos() as u64);
                            }
                            break;
                        }
                        if !in_flight.iter().any(|&(s, _)| s == got) {
                            break; // a stray echo
                        }
                        in_flight.pop_front();
                        lost += 1;
                    }
                }
                _ = tokio::time::sleep_until(give_up), if sent >= count => {
                    lost += in_flight.len();
                    in_flight.clear();
                }
            }
        }
        Ok(lost)
    }
}

/// What a body of `size` bytes carries of `seq`.
fn truncate(seq: u64, size: usize) -> u64 {
    if size >= 8 {
        seq
    } else {
        seq & ((1u64 << (8 * size)) - 1)
    }
}

fn seq_of(body: &[u8], size: usize) -> u64 {
    if let Some(seq) = read_seq(body) {
        return seq;
    }
    let mut bytes = [0u8; 8];
    let n = body.len().min(8).min(size);
    bytes[..n].copy_from_slice(&body[..n]);
    u64::from_le_bytes(bytes)
}

/// Runs the round trip for every size; prints a table unless `quiet`.
///
/// The pinger, the echo client and their connections run on a thread of
/// their own with a single-threaded runtime, whatever runtime calls this:
/// with one message in flight there is nothing to parallelise, and every
/// hand-off between worker threads (a wake-up of a parked thread) would add
/// the load generator's own jitter to the broker's round trip.
pub async fn run(args: &RttArgs) -> Result<RttReport> {
    if args.sizes.is_empty() || args.sizes.contains(&0) {
        return Err("--sizes must list positive sizes".into());
    }
    let args = args.clone();
    let (done, report) = tokio::sync::oneshot::channel();
    std::thread::Builder::new()
        .name("rtt".into())
        .spawn(move || {
            let result = tokio::runtime::Builder::new_current_thread()
                .enable_all()
                .build()
                .map_err(|e| PerfError(format!("rtt runtime: {e}")))
                .and_then(|runtime| runtime.block_on(run_here(&args)));
            let _ = done.send(result);
        })
        .map_err(|e| format!("cannot start the rtt thread: {e}"))?;
    report.await.map_err(|_| "the rtt thread panicked")?
}

async fn run_here(args: &RttArgs) -> Result<RttReport> {
    let prefix = unique_prefix("rtt");
    let queue_a = ShortStr::try_from(format!("{prefix}-a")).map_err(|e| e.to_string())?;
    let queue_b = ShortStr::try_from(format!("{prefix}-b")).map_err(|e| e.to_string())?;

    let echo_connection = connect(&args.url, "rtt echo").await?;
    let echo_channel = echo_connection.open_channel().await?;
    let ping_connection = connect(&args.url, "rtt pinger").await?;
    let ping_channel = ping_connection.open_channel().await?;
    for queue in [&queue_a, &queue_b] {
        ping_channel
            .queue_declare(queue, QueueDeclareOptions::default(), FieldTable::new())
            .await?;
    }
    let result = async {
        let no_ack = BasicConsumeOptions {
            no_ack: true,
            ..Default::default()
        };
        let mut requests = echo_channel
            .basic_consume(&queue_a, "", no_ack, FieldTable::new())
            .await?;
        let echo = {
            let channel = echo_channel.clone();
            let queue_b = queue_b.clone();
            tokio::spawn(async move {
                while let Some(delivery) = requests.next().await {
                    let sent = channel
                        .basic_publish(
                            "",
                            &queue_b,
                            BasicPublishOptions::default(),
                            BasicProperties::default(),
                            delivery.body,
                        )
                        .await;
                    if sent.is_err() {
                        break;
                    }
                }
            })
        };
        let replies = ping_channel
            .basic_consume(&queue_b, "", no_ack, FieldTable::new())
            .await?;
        let mut pinger = Pinger {
            channel: ping_channel.clone(),
            replies,
            queue_a: queue_a.clone(),
            next_seq: 0,
        };
        let timeout = Duration::from_secs_f64(args.timeout);
        let mut sizes = Vec::new();
        for &size in &args.sizes {
            pinger
                .series(size, args.warmup, args.rate, timeout, None)
                .await?;
            let mut samples = Samples::default();
            let mut lost = 0;
            for r in 0..args.repeat {
                if r > 0 && args.pause > 0.0 {
                    tokio::time::sleep(Duration::from_secs_f64(args.pause)).await;
                }
                lost += pinger
                    .series(size, args.count, args.rate, timeout, Some(&mut samples))
                    .await?;
            }
            sizes.push(RttSize {
                size,
                sent: args.count * args.repeat,
                lost,
                stats: samples.box_stats(),
            });
        }
        echo.abort();
        Ok::<_, PerfError>(sizes)
    }
    .await;
    for queue in [&queue_a, &queue_b] {
        let _ = ping_channel
            .queue_delete(queue, QueueDeleteOptions::default())
            .await;
    }
    let _ = echo_connection.close().await;
    let _ = ping_connection.close().await;
    let report = RttReport {
        config: args.clone(),
        sizes: result?,
    };
    if !args.quiet {
        print_table(&report);
    }
    if let Some(path) = &args.json {
        crate::report::write_json(path, &report)?;
    }
    if let Some(path) = &args.svg {
        let groups: Vec<crate::svg::Group> = report
            .sizes
            .iter()
            .map(|s| crate::svg::Group {
                label: format!("{} B", s.size),
                boxes: vec![(String::new(), s.stats)],
            })
            .collect();
        let title = if args.rate > 0.0 {
            format!("Round trip at {} Hz", args.rate)
        } else {
            "Round trip, one message in flight".to_owned()
        };
        let svg = crate::svg::box_plot(&title, &groups, &[]);
        std::fs::write(path, svg).map_err(|e| format!("cannot write {}: {e}", path.display()))?;
    }
    Ok(report)
}

/// Prints one row per size.
pub fn print_table(report: &RttReport) {
    let c = &report.config;
    println!(
        "--- round trip through two queues and an echo client: {} x {} pings per size, {}",
        c.repeat,
        c.count,
        if c.rate > 0.0 {
            format!("{} Hz", c.rate)
        } else {
            "one in flight".to_owned()
        }
    );
    let mut table = Table::new(&[
        "size", "lost", "mean", "min", "q1", "median", "q3", "p99", "max",
    ]);
    for s in &report.sizes {
        let b = &s.stats;
        table.row(vec![
            format!("{} B", s.size),
            s.lost.to_string(),
            micros(b.mean_us),
            micros(b.min_us),
            micros(b.q1_us),
            micros(b.median_us),
            micros(b.q3_us),
            micros(b.p99_us),
            micros(b.max_us),
        ]);
    }
    print!("{}", table.render());
}
