//! The moving parts every scenario shares: connections, the queue
//! [`Topology`] (an exchange and its queues), the publisher loop and the
//! consumer loop.
//!
//! The publisher loop is built not to be the bottleneck: bodies come from
//! a reused buffer ([`BodyWriter`]), the exchange, routing key and
//! properties are cloned (reference counts, no allocation), and without
//! confirms nothing is awaited but room in the client's outbox, so
//! publishes are pipelined. With confirms, at most `confirm_window`
//! publishes are outstanding and the oldest is awaited when the window is
//! full.
//!
//! The consumer loop tracks sequence numbers ([`SeqTracker`]), records
//! latency from the timestamp in the body into a histogram for the
//! current progress interval and, during the measurement window, into the
//! window's histogram, and acknowledges with `multiple` every N deliveries
//! in manual-ack mode.

use crate::body::{make_seq, read_seq, read_timestamp, BodyWriter};
use crate::histogram::Histogram;
use crate::sequence::SeqTracker;
use crate::Result;
use leveret_client::{
    BasicAckOptions, BasicConsumeOptions, BasicProperties, BasicPublishOptions, BasicQosOptions,
    Channel, ConfirmFuture, Confirmation, Connection, ConnectionOptions, Consumer,
    ExchangeDeclareOptions, ExchangeDeleteOptions, FieldTable, QueueBindOptions,
    QueueDeclareOptions, QueueDeleteOptions, ShortStr,
};
use serde::Serialize;
use std::collections::VecDeque;
use std::future::IntoFuture;
use std::sync::atomic::{AtomicBool, AtomicU64, AtomicU8, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Duration;

/// The URL used when none is given.
pub const DEFAULT_URL: &str = "amqp://guest:guest@127.0.0.1:5672/%2f";

/// Phase of a run, as consumers see it.
pub const PHASE_WARMUP: u8 = 0;
/// Measuring: latency goes into the window's histogram.
pub const PHASE_MEASURE: u8 = 1;
/// Publishers stopped; consumers drain.
pub const PHASE_DRAIN: u8 = 2;

/// Exchange type of a topology.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum ExchangeKind {
    /// Each publisher's messages go to one queue (publisher `p` to queue `p mod Q`).
    Direct,
    /// Every message goes to every queue.
    Fanout,
}

impl ExchangeKind {
    fn name(self) -> &'static str {
        match self {
            ExchangeKind::Direct => "direct",
            ExchangeKind::Fanout => "fanout",
        }
    }
}

/// A name prefix no other run uses: process id and a counter.
pub fn unique_prefix(tag: &str) -> String {
    static NEXT: AtomicU64 = AtomicU64::new(0);
    let n = NEXT.fetch_add(1, Ordering::Relaxed);
    format!("leveret-perf-{}-{n}-{tag}", std::process::id())
}

/// Connects with a connection name the broker's tools show.
pub async fn connect(url: &str, name: &str) -> Result<Connection> {
    let mut options = ConnectionOptions::from_uri(url)?;
    options.connection_name = Some(format!("leveret-perf {name}"));
    options.connection_timeout = Duration::from_secs(30);
    Ok(Connection::connect_with(options).await?)
}

fn short(s: &str) -> Result<ShortStr> {
    ShortStr::try_from(s).map_err(|e| crate::PerfError(format!("name {s:?}: {e}")))
}

/// An exchange and its queues.
#[derive(Debug, Clone)]
pub struct Topology {
    /// The exchange.
    pub exchange: ShortStr,
    /// Its type.
    pub kind: ExchangeKind,
    /// The queues bound to it.
    pub queues: Vec<ShortStr>,
    /// Whether the exchange and queues are durable.
    pub durable: bool,
}

impl Topology {
    /// Names for an exchange and `queues` queues under a fresh prefix.
    pub fn new(tag: &str, kind: ExchangeKind, queues: usize, durable: bool) -> Result<Self> {
        let prefix = unique_prefix(tag);
        Ok(Topology {
            exchange: short(&format!("{prefix}-{}", kind.name()))?,
            kind,
            queues: (0..queues.max(1))
                .map(|q| short(&format!("{prefix}-q{q}")))
                .collect::<Result<_>>()?,
            durable,
        })
    }

    /// Declares the exchange and queues and binds them.
    pub async fn declare(&self, channel: &Channel) -> Result<()> {
        channel
            .exchange_declare(
                &self.exchange,
                self.kind.name(),
                ExchangeDeclareOptions {
                    durable: self.durable,
                    ..Default::default()
                },
                FieldTable::new(),
            )
            .await?;
        for queue in &self.queues {
            channel
                .queue_declare(
                    queue,
                    QueueDeclareOptions {
                        durable: self.durable,
                        ..Default::default()
                    },
                    FieldTable::new(),
                )
                .await?;
            let key = match self.kind {
                ExchangeKind::Direct => queue.clone(),
                ExchangeKind::Fanout => ShortStr::default(),
            };
            channel
                .queue_bind(
                    queue,
                    &self.exchange,
                    key,
                    QueueBindOptions::default(),
                    FieldTable::new(),
                )
                .await?;
        }
        Ok(())
    }

    /// Deletes the queues and the exchange.
    pub async fn delete(&self, channel: &Channel) -> Result<()> {
        for queue in &self.queues {
            channel
                .queue_delete(queue, QueueDeleteOptions::default())
                .await?;
        }
        channel
            .exchange_delete(&self.exchange, ExchangeDeleteOptions::default())
            .await?;
        Ok(())
    }

    /// The routing key publisher `p` uses.
    pub fn routing_key(&self, p: usize) -> ShortStr {
        match self.kind {
            ExchangeKind::Direct => self.queues[p % self.queues.len()].clone(),
            ExchangeKind::Fanout => ShortStr::default(),
        }
    }

    /// The queue consumer `c` consumes from.
    pub fn queue_of_consumer(&self, c: usize) -> usize {
        c % self.queues.len()
    }

    /// Whether publisher `p`'s messages reach queue `q`.
    pub fn reaches(&self, p: usize, q: usize) -> bool {
        match self.kind {
            ExchangeKind::Direct => p % self.queues.len() == q,
            ExchangeKind::Fanout => true,
        }
    }
}

/// What one publisher does.
#[derive(Debug, Clone)]
pub struct PublisherSpec {
    /// Its id, in the top bits of its sequence numbers.
    pub id: u16,
    /// Exchange to publish to.
    pub exchange: ShortStr,
    /// Routing key.
    pub routing_key: ShortStr,
    /// Persistent (delivery mode 2) rather than transient messages.
    pub persistent: bool,
    /// Body size, bytes.
    pub size: usize,
    /// Messages per second (0 = as fast as possible).
    pub rate: f64,
    /// Messages to publish (0 = until stopped).
    pub count: u64,
    /// Outstanding confirms allowed (0 = no confirm mode).
    pub confirm_window: usize,
    /// Counter of the first message.
    pub first: u64,
}

/// A publisher's counters, readable while it runs.
#[derive(Debug, Default)]
pub struct PublisherCounters {
    /// Messages handed to the client.
    pub published: AtomicU64,
    /// Confirmed with `basic.ack`.
    pub acked: AtomicU64,
    /// Refused with `basic.nack`.
    pub nacked: AtomicU64,
    /// Nanoseconds from each publish to its confirm, as seen by a
    /// publisher that waits for its oldest confirm when its window is
    /// full (the usual state under load); cleared when the measurement
    /// window starts.
    pub confirm_latency: std::sync::Mutex<Histogram>,
}

impl PublisherCounters {
    /// The confirm latency histogram (held briefly, never across an await).
    pub fn confirm_latency(&self) -> std::sync::MutexGuard<'_, Histogram> {
        self.confirm_latency
            .lock()
            .unwrap_or_else(|e| e.into_inner())
    }
}

/// How a publisher run ended.
#[derive(Debug, Clone, Copy, Default, Serialize)]
pub struct PublisherOutcome {
    /// Counter of the next message.
    pub next: u64,
    /// Messages published in this run.
    pub published: u64,
    /// Confirmed with `basic.ack`.
    pub acked: u64,
    /// Refused with `basic.nack`.
    pub nacked: u64,
    /// Still unconfirmed when the publisher gave up waiting.
    pub unconfirmed: u64,
}

/// How long a publisher waits for its last confirms.
const CONFIRM_GRACE: Duration = Duration::from_secs(30);

/// Puts a channel in confirm mode if the spec asks for it.
pub async fn prepare_publisher(channel: &Channel, spec: &PublisherSpec) -> Result<()> {
    if spec.confirm_window > 0 {
        channel.confirm_select().await?;
    }
    Ok(())
}

/// Publishes until `count` messages are out or `stop` is set.
pub async fn publish(
    channel: &Channel,
    spec: &PublisherSpec,
    counters: &PublisherCounters,
    stop: &AtomicBool,
) -> Result<PublisherOutcome> {
    let properties = BasicProperties {
        delivery_mode: Some(if spec.persistent { 2 } else { 1 }),
        ..Default::default()
    };
    let options = BasicPublishOptions::default();
    let mut writer = BodyWriter::new(spec.size);
    let mut window: VecDeque<(tokio::time::Instant, ConfirmFuture)> =
        VecDeque::with_capacity(spec.confirm_window);
    let mut outcome = PublisherOutcome {
        next: spec.first,
        ..Default::default()
    };
    let start = tokio::time::Instant::now();
    let period = (spec.rate > 0.0).then(|| Duration::from_secs_f64(1.0 / spec.rate));
    let settle = |answer: Confirmation,
                  published_at: tokio::time::Instant,
                  outcome: &mut PublisherOutcome| {
        let waited = published_at.elapsed().as_nanos() as u64;
        counters.confirm_latency().record(waited);
        match answer {
            Confirmation::Nack => {
                outcome.nacked += 1;
                counters.nacked.fetch_add(1, Ordering::Relaxed);
            }
            _ => {
                outcome.acked += 1;
                counters.acked.fetch_add(1, Ordering::Relaxed);
            }
        }
    };
    while !stop.load(Ordering::Relaxed) && (spec.count == 0 || outcome.published < spec.count) {
        if let Some(period) = period {
            let due = start + period.mul_f64(outcome.published as f64);
            if due > tokio::time::Instant::now() {
                tokio::time::sleep_until(due).await;
            }
        }
        let body = writer.body(make_seq(spec.id, outcome.next));
        let published_at = tokio::time::Instant::now();
        let confirm = channel
            .basic_publish(
                &spec.exchange,
                &spec.routing_key,
                options,
                properties.clone(),
                body,
            )
            .await?;
        outcome.next += 1;
        outcome.published += 1;
        counters.published.fetch_add(1, Ordering::Relaxed);
        if spec.confirm_window > 0 {
            window.push_back((published_at, confirm.into_future()));
            while window.len() >= spec.confirm_window {
                if let Some((at, oldest)) = window.pop_front() {
                    settle(oldest.await?, at, &mut outcome);
                }
            }
        }
    }
    let deadline = tokio::time::Instant::now() + CONFIRM_GRACE;
    while let Some((at, oldest)) = window.pop_front() {
        match tokio::time::timeout_at(deadline, oldest).await {
            Ok(answer) => settle(answer?, at, &mut outcome),
            Err(_) => {
                outcome.unconfirmed = window.len() as u64 + 1;
                break;
            }
        }
    }
    Ok(outcome)
}

/// How a consumer acknowledges.
#[derive(Debug, Clone, Copy, Serialize)]
pub struct ConsumerSpec {
    /// Manual acks (otherwise no-ack).
    pub manual_ack: bool,
    /// Prefetch count (0 = none).
    pub prefetch: u16,
    /// Acknowledge with `multiple` every this many deliveries.
    pub ack_every: u32,
}

/// What a consumer records and the reporter reads.
#[derive(Debug, Default)]
pub struct ConsumerState {
    /// Latency since the last progress line.
    pub interval: Histogram,
    /// Latency over the measurement window.
    pub window: Histogram,
    /// Sequence tracking.
    pub tracker: SeqTracker,
}

/// A consumer's counters, readable while it runs.
#[derive(Debug, Default)]
pub struct ConsumerStats {
    /// Deliveries so far.
    pub received: AtomicU64,
    /// Histograms and sequence state.
    pub state: Mutex<ConsumerState>,
}

impl ConsumerStats {
    /// Locks the state.
    pub fn state(&self) -> std::sync::MutexGuard<'_, ConsumerState> {
        self.state.lock().unwrap_or_else(|e| e.into_inner())
    }
}

/// Sets the prefetch and starts consuming `queue`.
pub async fn start_consumer(
    channel: &Channel,
    queue: &ShortStr,
    spec: &ConsumerSpec,
) -> Result<Consumer> {
    if spec.prefetch > 0 {
        channel
            .basic_qos(spec.prefetch, BasicQosOptions::default())
            .await?;
    }
    Ok(channel
        .basic_consume(
            queue,
            "",
            BasicConsumeOptions {
                no_ack: !spec.manual_ack,
                ..Default::default()
            },
            FieldTable::new(),
        )
        .await?)
}

/// Consumes until the stream ends (its connection is closed).
pub async fn consume(
    mut consumer: Consumer,
    spec: ConsumerSpec,
    stats: Arc<ConsumerStats>,
    phase: Arc<AtomicU8>,
) {
    let channel = consumer.channel().clone();
    let ack_every = spec.ack_every.max(1);
    let mut unacked = 0u32;
    let mut acking = spec.manual_ack;
    while let Some(delivery) = consumer.next().await {
        let now = crate::body::now_ns();
        {
            let measuring = phase.load(Ordering::Relaxed) == PHASE_MEASURE;
            let mut state = stats.state();
            state.tracker.record(read_seq(&delivery.body));
            if let Some(sent) = read_timestamp(&delivery.body) {
                let latency = now.saturating_sub(sent);
                state.interval.record(latency);
                if measuring {
                    state.window.record(latency);
                }
            }
        }
        stats.received.fetch_add(1, Ordering::Relaxed);
        if acking {
            unacked += 1;
            if unacked >= ack_every {
                unacked = 0;
                let options = BasicAckOptions { multiple: true };
                if channel
                    .basic_ack(delivery.delivery_tag, options)
                    .await
                    .is_err()
                {
                    acking = false;
                }
            }
        }
    }
}
