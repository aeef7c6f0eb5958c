//! [`PortProfile`]: a port's connector profile. It carries the settings of
//! OpenRTM-aist's AMQP connector profile (broker host and port, exchange
//! name and type, queue name, binding key, whether to declare and bind the
//! queue, routing key; see [`PortProfile::from_properties`] for their
//! property names) and Leveret's own: durability, publisher confirms,
//! prefetch, the in-port's buffer and full policy, the out-port's window
//! and its [`Backpressure`], the put timeout (for `Block` only), the
//! lifespan, the [`Replay`] policy, mandatory publishing, the CDR options,
//! the in-port's own queue expiry, the reconnection backoff, the port's
//! name and how often it announces itself (see `announce`), the
//! [`Recording`] of its values to a stream, and the
//! [`Qos`] presets that set several at once. [`Connector`] says how a port
//! (re)opens its connection: TCP, an embedded broker, or a function.

use super::cdr::CdrOptions;
use super::openrtm::PortRole;
use leveret_client::ConnectionOptions;
use leveret_client::Result;
use leveret_client::{
    Channel, Connection, FieldTable, FieldValue, QueueBindOptions, QueueDeclareOptions, ShortStr,
};
use std::fmt;
use std::future::Future;
use std::pin::Pin;
use std::sync::Arc;
use std::time::Duration;

/// An exchange type.
#[derive(Debug, Clone, PartialEq, Eq, Default)]
pub enum ExchangeKind {
    /// Routing key equal to the binding key (OpenRTM's default).
    #[default]
    Direct,
    /// Every bound queue (broadcast).
    Fanout,
    /// Routing key matched against binding patterns.
    Topic,
    /// Header matching.
    Headers,
    /// Another type (a plugin's).
    Other(String),
}

impl ExchangeKind {
    /// The AMQP name of the type.
    pub fn as_str(&self) -> &str {
        match self {
            ExchangeKind::Direct => "direct",
            ExchangeKind::Fanout => "fanout",
            ExchangeKind::Topic => "topic",
            ExchangeKind::Headers => "headers",
            ExchangeKind::Other(name) => name,
        }
    }

    /// Parses a type as OpenRTM-aist's AMQP interface accepts it, in any
    /// case: the name (`direct`, `AMQP::direct`), its initial, or its
    /// number (0 direct, 1 fanout, 2 topic, 3 headers). A plugin's type
    /// (`x-…`) is taken as named; anything else is, as in OpenRTM's
    /// module, a consistent-hash exchange.
    pub fn parse(text: &str) -> Self {
        let lower = text.trim().to_ascii_lowercase();
        let name = lower.strip_prefix("amqp::").unwrap_or(&lower);
        match name {
            "0" | "d" | "direct" => ExchangeKind::Direct,
            "1" | "f" | "fanout" => ExchangeKind::Fanout,
            "2" | "t" | "topic" => ExchangeKind::Topic,
            "3" | "h" | "headers" => ExchangeKind::Headers,
            plugin if plugin.starts_with("x-") => ExchangeKind::Other(text.trim().to_owned()),
            _ => ExchangeKind::Other(CONSISTENT_HASH.to_owned()),
        }
    }
}

/// The type of RabbitMQ's consistent-hash exchange plugin, OpenRTM's
/// fallback for a type it does not know.
pub const CONSISTENT_HASH: &str = "x-consistent-hash";

impl fmt::Display for ExchangeKind {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.as_str())
    }
}

/// What an in-port does with a new value when its buffer is full.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum FullPolicy {
    /// Take nothing more until there is room: deliveries stay
    /// unacknowledged, so the broker stops at the prefetch count and keeps
    /// the rest queued. Nothing is lost; the publisher's queue grows.
    BlockBroker,
    /// Drop the oldest buffered value (OpenRTM's `overwrite`): a reader of
    /// the latest value never waits behind stale ones.
    #[default]
    DropOldest,
    /// Drop the new value (OpenRTM's `do_nothing`).
    DropNewest,
}

impl FullPolicy {
    /// Parses OpenRTM's `buffer.write.full_policy` values (`block`,
    /// `overwrite`, `do_nothing`) and this crate's names.
    pub fn parse(text: &str) -> Option<Self> {
        match text.to_ascii_lowercase().as_str() {
            "block" | "block_broker" | "blockbroker" => Some(FullPolicy::BlockBroker),
            "overwrite" | "drop_oldest" | "dropoldest" => Some(FullPolicy::DropOldest),
            "do_nothing" | "drop_newest" | "dropnewest" => Some(FullPolicy::DropNewest),
            _ => None,
        }
    }
}

/// What an out-port does with a new value when its window (values waiting
/// to be sent or confirmed) is full. Whatever it is, `put` never waits on
/// the network unless told to ([`Backpressure::Block`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Backpressure {
    /// Drop the oldest value of the window (keep the last N): a stream of
    /// states, where the newest value matters most.
    #[default]
    DropOldest,
    /// Refuse the new value ([`super::PortStatus::SendFull`]).
    DropNewest,
    /// Wait for room, at most the put timeout, then refuse the value.
    Block,
}

/// What an out-port sends after a reconnection, of the values the broker
/// had not confirmed when the link dropped and those put while it was
/// down. The lifespan applies whatever the policy: a value older than it
/// is never sent.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Replay {
    /// Every value still in the window (and within its lifespan).
    #[default]
    All,
    /// The newest value only (a setpoint: the older ones are superseded).
    Latest,
    /// None of what was unconfirmed when the link dropped (values put
    /// while it is down are still sent).
    Nothing,
}

/// A QoS preset, named after what robot developers know from ROS 2: each
/// sets the profile's reliability and freshness settings together (see
/// [`PortProfile::qos`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[non_exhaustive]
pub enum Qos {
    /// Sensor streams: best effort (no confirms), only the latest value
    /// kept and replayed, 100 ms lifespan, an in-port buffer of one.
    SensorData,
    /// Commands (`cmd_vel`): confirmed, 200 ms lifespan, no stale replay
    /// (only the latest within its lifespan), a window of 16 dropping the
    /// oldest.
    Command,
    /// Nothing lost: confirmed, durable and persistent, no lifespan,
    /// replay everything, `put` waits for room (blocking backpressure)
    /// and the in-port holds the broker back rather than drop.
    Reliable,
    /// Telemetry and logs: best effort, a 10 s lifespan, the last 1000
    /// values kept and replayed.
    Telemetry,
}

/// Reconnection delays: the first retry after `initial`, doubling up to
/// `max`; back to `initial` once a link is up again.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Backoff {
    /// Delay before the first retry.
    pub initial: Duration,
    /// Longest delay between retries.
    pub max: Duration,
}

impl Default for Backoff {
    fn default() -> Self {
        Backoff {
            initial: Duration::from_millis(50),
            max: Duration::from_secs(5),
        }
    }
}

impl Backoff {
    /// The delay after `failures` consecutive failed attempts (0 = the
    /// first retry).
    pub fn delay(&self, failures: u32) -> Duration {
        let factor = 1u32.checked_shl(failures.min(31)).unwrap_or(u32::MAX);
        self.initial.saturating_mul(factor).min(self.max)
    }
}

/// A port's connector profile.
#[derive(Debug, Clone)]
pub struct PortProfile {
    /// The broker (host, port, credentials, vhost, heartbeat…).
    pub broker: ConnectionOptions,
    /// Exchange to publish to and bind to; empty for the default exchange
    /// (then `routing_key` names the queue). Names starting with `amq.`
    /// are used as they are, never declared.
    pub exchange: String,
    /// The exchange's type, when it is declared.
    pub exchange_kind: ExchangeKind,
    /// The in-port's queue; empty for a queue of the port's own
    /// (`leveret.port.<id>`, not exclusive) that outlives its
    /// reconnections, so nothing sent while it reconnects is lost, and
    /// that the broker deletes once unused for [`queue_expires`]
    /// (the port deletes it itself when closed).
    ///
    /// [`queue_expires`]: PortProfile::queue_expires
    pub queue: String,
    /// Key binding the queue to the exchange.
    pub binding_key: String,
    /// OpenRTM's `bind`. An in-port always declares its queue; with
    /// `bind` it also declares the exchange and binds the queue to it. An
    /// out-port always declares the exchange; with `bind` (and a queue
    /// name) it also declares the queue and binds it, so messages
    /// published before the in-port starts are kept.
    pub declare_queue: bool,
    /// Key the out-port publishes with.
    pub routing_key: String,
    /// Declare the exchange and queue durable (they survive a broker
    /// restart).
    pub durable: bool,
    /// Publish persistent messages (delivery mode 2): in a durable queue
    /// they survive a broker restart.
    pub persistent: bool,
    /// Extra `queue.declare` arguments (`x-expires`, `x-max-length`…).
    pub queue_arguments: FieldTable,
    /// Publisher confirms: the out-port keeps each message until the
    /// broker confirms it (`put` never waits for that), resends what was
    /// unconfirmed after a reconnection, and notices a broker that stops
    /// confirming ([`PortProfile::stall_timeout`]). Without them a message
    /// in flight when the link drops may be lost.
    pub confirms: bool,
    /// Deliveries the broker sends the in-port before it acknowledges any.
    pub prefetch: u16,
    /// Values the in-port buffers for its reader.
    pub buffer_size: usize,
    /// What the in-port does when the buffer is full.
    pub full_policy: FullPolicy,
    /// Opt-in busy polling for the in-port: `recv` and `recv_blocking`
    /// look for a value without sleeping for up to this long before they
    /// wait. It spends the CPU the wait would have saved; in return a value
    /// arriving within the window is picked up without waking an idle CPU
    /// and thread (tens to hundreds of microseconds). For a control loop
    /// that reads a value every period, a window of at least the period
    /// keeps its thread from ever going idle. `None` (the default): no
    /// window (see [`PortProfile::spin`] for `recv_blocking`'s adaptive
    /// spin).
    pub busy_poll: Option<Duration>,
    /// Opt-in adaptive spin for `InPort::recv_blocking` without a busy-poll
    /// window: before its thread sleeps, a wait looks for a value for a
    /// budget of 2 µs up to this ceiling (doubled when a value came while
    /// it spun, halved when it had to sleep; it starts at 16 µs or the
    /// ceiling), then yields the processor twice, then sleeps. A wait
    /// whose timeout is zero or past does not spin. `None` or zero: no
    /// spin, the thread sleeps at once.
    ///
    /// Off by default: it buys the median at the cost of the tail. On a
    /// loaded 2-core machine, with a 64 µs ceiling, back-to-back values
    /// went from p50 15.5 to 3.0 µs but p99 from 70 µs to 3.7-12 ms
    /// (`docs/performance.md`): a receiver that rarely sleeps is preempted
    /// for whole time slices when the machine is oversubscribed, where one
    /// that sleeps is woken with the scheduler's preference. A command
    /// loop cares about its tail; turn the spin on where a core is spare
    /// for the receiver and the median matters more.
    pub spin: Option<Duration>,
    /// Longest time `OutPort::put` waits for room with
    /// [`Backpressure::Block`] (never for the network).
    pub put_timeout: Duration,
    /// The out-port's window: values it keeps until sent and confirmed
    /// (and resends after a reconnection), and the most written to the
    /// connection and not yet confirmed, so a frozen broker never has more
    /// than this many of the port's messages in its socket; when full,
    /// the [`Backpressure`] policy applies.
    pub max_unconfirmed: usize,
    /// The most bytes (of bodies) the out-port has written and not yet
    /// confirmed (one message is always let through).
    pub max_unconfirmed_bytes: usize,
    /// How long the broker may confirm nothing of the out-port's (or,
    /// without confirms, take nothing from its connection) before the
    /// link counts as degraded ([`super::LinkStatus::degraded`],
    /// [`super::PortStatus::Degraded`]); `None`: the default of
    /// [`PortProfile::stall_timeout`].
    pub stall_after: Option<Duration>,
    /// Reconnection delays.
    pub backoff: Backoff,
    /// The byte order and string charset of CDR bodies.
    pub cdr: CdrOptions,
    /// How long a value stays useful: the out-port never sends a value
    /// older than this (it is reported expired), and what it sends carries
    /// the rest as its AMQP `expiration`, so the broker drops it once
    /// stale; the in-port drops (and counts as `stale`) a value older than
    /// this by its `x-sent-ns`. `None`: values never go stale.
    pub lifespan: Option<Duration>,
    /// What the out-port does when its window is full.
    pub backpressure: Backpressure,
    /// What the out-port sends again after a reconnection.
    pub replay: Replay,
    /// Publish with `mandatory`: the broker returns a message no queue
    /// receives, and the out-port counts it `unroutable` rather than
    /// confirmed.
    pub mandatory: bool,
    /// An in-port with no queue name makes one of its own (named after
    /// the port, not exclusive) that outlives its reconnections, so nothing
    /// sent while it reconnects is lost; the broker deletes it once unused
    /// for this long (`x-expires`).
    pub queue_expires: Duration,
    /// The port's name in its announcements and in its connection's name
    /// (`leveret port out NAME`); `None`: one made of the profile (see
    /// [`PortProfile::port_name`]).
    pub name: Option<String>,
    /// How often the port announces itself on the `leveret.ports`
    /// exchange (see [`super::PORTS_EXCHANGE`]): once when its link comes
    /// up, then at this interval. `None` or zero: never.
    pub announce_interval: Option<Duration>,
    /// The out-port records every value it publishes to this stream (see
    /// [`Recording`]); `None`: no recording.
    pub record: Option<Recording>,
}

/// Where an out-port records its values: a stream queue
/// (`x-queue-type: stream`, durable) that the out-port declares with this
/// retention and binds to its exchange with its routing key, on every
/// (re)connection. The stream is one more queue the broker routes the
/// port's messages to: `put` and the port's readers are unchanged. A
/// recording needs a named exchange (a queue cannot be bound to the
/// default exchange); the out-port refuses a profile without one.
/// Since the stream takes every value, a `mandatory` out-port no longer
/// counts a value `unroutable` when no reader's queue is bound.
/// Read a recording back with [`super::Player`].
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Recording {
    /// The stream's name.
    pub stream: String,
    /// How long values are kept (`x-max-age`, RabbitMQ's units: `Y`, `M`,
    /// `D`, `h`, `m`, `s`, as in `"10m"`); `None`: no age limit.
    pub max_age: Option<String>,
    /// The most bytes kept (`x-max-length-bytes`); `None`: no size limit.
    pub max_length_bytes: Option<u64>,
}

impl Recording {
    /// A recording to the stream `stream`, kept without limit until one
    /// is set.
    pub fn to(stream: impl Into<String>) -> Self {
        Recording {
            stream: stream.into(),
            max_age: None,
            max_length_bytes: None,
        }
    }

    /// Keeps values for `age` (`"10m"`, `"1h"`, `"7D"`).
    pub fn max_age(mut self, age: impl Into<String>) -> Self {
        self.max_age = Some(age.into());
        self
    }

    /// Keeps at most `bytes` of values.
    pub fn max_length_bytes(mut self, bytes: u64) -> Self {
        self.max_length_bytes = Some(bytes);
        self
    }

    /// Declares the stream (durable, with this retention) and binds it to
    /// `exchange` with `routing_key` (ignored by a fanout exchange), so it
    /// receives what is published there from now on. Refuses the default
    /// exchange (empty), which no queue can be bound to.
    pub async fn declare(
        &self,
        channel: &Channel,
        exchange: &str,
        routing_key: &str,
    ) -> Result<()> {
        if exchange.is_empty() {
            return Err(leveret_client::Error::InvalidArgument(
                "recording needs a named exchange: the default exchange routes to one queue \
                 only, and no stream can be bound to it"
                    .to_owned(),
            ));
        }
        let options = QueueDeclareOptions {
            durable: true,
            ..Default::default()
        };
        let stream = channel
            .queue_declare(self.stream.as_str(), options, self.arguments())
            .await?;
        channel
            .queue_bind(
                &stream.name,
                exchange,
                routing_key,
                QueueBindOptions::default(),
                FieldTable::new(),
            )
            .await
    }

    /// The stream's declaration arguments.
    pub fn arguments(&self) -> FieldTable {
        let mut arguments = FieldTable::new();
        arguments.insert(
            ShortStr::from_static("x-queue-type"),
            FieldValue::string("stream"),
        );
        if let Some(age) = &self.max_age {
            arguments.insert(
                ShortStr::from_static("x-max-age"),
                FieldValue::string(age.as_str()),
            );
        }
        if let Some(bytes) = self.max_length_bytes {
            arguments.insert(
                ShortStr::from_static("x-max-length-bytes"),
                FieldValue::I64(i64::try_from(bytes).unwrap_or(i64::MAX)),
            );
        }
        arguments
    }
}

impl Default for PortProfile {
    fn default() -> Self {
        let broker = ConnectionOptions {
            connection_timeout: Duration::from_secs(10),
            heartbeat: 10,
            ..ConnectionOptions::default()
        };
        PortProfile {
            broker,
            exchange: String::new(),
            exchange_kind: ExchangeKind::Direct,
            queue: String::new(),
            binding_key: String::new(),
            declare_queue: true,
            routing_key: String::new(),
            durable: false,
            persistent: false,
            queue_arguments: FieldTable::new(),
            confirms: true,
            prefetch: 64,
            buffer_size: 128,
            full_policy: FullPolicy::DropOldest,
            busy_poll: None,
            spin: None,
            put_timeout: Duration::from_millis(500),
            max_unconfirmed: 1024,
            max_unconfirmed_bytes: 4 << 20,
            stall_after: None,
            backoff: Backoff::default(),
            cdr: CdrOptions::default(),
            lifespan: None,
            backpressure: Backpressure::DropOldest,
            replay: Replay::All,
            mandatory: true,
            queue_expires: Duration::from_secs(60),
            name: None,
            announce_interval: Some(Duration::from_secs(1)),
            record: None,
        }
    }
}

impl PortProfile {
    /// A profile for the broker at `uri` (`amqp://user:pass@host:port/vhost`)
    /// with the defaults: default exchange, confirms on, prefetch 64, a
    /// buffer of 128 dropping the oldest, a 500 ms put timeout.
    pub fn new(uri: &str) -> Result<Self> {
        let mut broker = ConnectionOptions::from_uri(uri)?;
        if !uri.contains("connection_timeout=") {
            broker.connection_timeout = Duration::from_secs(10);
        }
        if !uri.contains("heartbeat=") {
            broker.heartbeat = 10;
        }
        Ok(PortProfile {
            broker,
            ..PortProfile::default()
        })
    }

    /// Sets the exchange and its type.
    pub fn exchange(mut self, name: impl Into<String>, kind: ExchangeKind) -> Self {
        self.exchange = name.into();
        self.exchange_kind = kind;
        self
    }

    /// Sets the in-port's queue name.
    pub fn queue(mut self, name: impl Into<String>) -> Self {
        self.queue = name.into();
        self
    }

    /// Sets the binding key.
    pub fn binding_key(mut self, key: impl Into<String>) -> Self {
        self.binding_key = key.into();
        self
    }

    /// Sets the routing key.
    pub fn routing_key(mut self, key: impl Into<String>) -> Self {
        self.routing_key = key.into();
        self
    }

    /// Durable exchange and queue, persistent messages.
    pub fn durable(mut self, durable: bool) -> Self {
        self.durable = durable;
        self.persistent = durable;
        self
    }

    /// Publisher confirms on or off.
    pub fn confirms(mut self, confirms: bool) -> Self {
        self.confirms = confirms;
        self
    }

    /// Sets the prefetch count.
    pub fn prefetch(mut self, prefetch: u16) -> Self {
        self.prefetch = prefetch;
        self
    }

    /// Sets the in-port buffer and its full policy.
    pub fn buffer(mut self, size: usize, policy: FullPolicy) -> Self {
        self.buffer_size = size;
        self.full_policy = policy;
        self
    }

    /// Sets the in-port's busy-poll window (see [`PortProfile::busy_poll`]).
    pub fn busy_poll(mut self, window: Duration) -> Self {
        self.busy_poll = Some(window);
        self
    }

    /// Sets the ceiling of `recv_blocking`'s adaptive spin, `None` for no
    /// spin (see [`PortProfile::spin`]).
    pub fn spin(mut self, ceiling: Option<Duration>) -> Self {
        self.spin = ceiling;
        self
    }

    /// Sets the put timeout.
    pub fn put_timeout(mut self, timeout: Duration) -> Self {
        self.put_timeout = timeout;
        self
    }

    /// Applies a QoS preset (settings it does not name are kept).
    pub fn qos(mut self, qos: Qos) -> Self {
        match qos {
            Qos::SensorData => {
                self.confirms = false;
                self.lifespan = Some(Duration::from_millis(100));
                self.max_unconfirmed = 1;
                self.backpressure = Backpressure::DropOldest;
                self.replay = Replay::Latest;
                self.buffer_size = 1;
                self.full_policy = FullPolicy::DropOldest;
            }
            Qos::Command => {
                self.confirms = true;
                self.lifespan = Some(Duration::from_millis(200));
                self.max_unconfirmed = 16;
                self.backpressure = Backpressure::DropOldest;
                self.replay = Replay::Latest;
                self.full_policy = FullPolicy::DropOldest;
            }
            Qos::Reliable => {
                self.confirms = true;
                self.durable = true;
                self.persistent = true;
                self.lifespan = None;
                self.backpressure = Backpressure::Block;
                self.replay = Replay::All;
                self.full_policy = FullPolicy::BlockBroker;
            }
            Qos::Telemetry => {
                self.confirms = false;
                self.lifespan = Some(Duration::from_secs(10));
                self.max_unconfirmed = 1000;
                self.backpressure = Backpressure::DropOldest;
                self.replay = Replay::All;
                self.full_policy = FullPolicy::DropOldest;
            }
        }
        self
    }

    /// How long the broker may confirm nothing before the out-port's link
    /// counts as degraded: [`PortProfile::stall_after`] if set, else
    /// twice the lifespan but at least 100 ms (a command stream notices a
    /// frozen broker before its commands would have gone stale twice
    /// over), else 2 s.
    pub fn stall_timeout(&self) -> Duration {
        self.stall_after.unwrap_or(match self.lifespan {
            Some(lifespan) => (lifespan * 2).max(Duration::from_millis(100)),
            None => Duration::from_secs(2),
        })
    }

    /// Sets the lifespan of values.
    pub fn lifespan(mut self, lifespan: Duration) -> Self {
        self.lifespan = Some(lifespan);
        self
    }

    /// Keeps at most `n` values in the out-port's window, dropping the
    /// oldest (1: latest only).
    pub fn keep_last(mut self, n: usize) -> Self {
        self.max_unconfirmed = n.max(1);
        self.backpressure = Backpressure::DropOldest;
        self
    }

    /// Sets the out-port's backpressure policy.
    pub fn backpressure(mut self, backpressure: Backpressure) -> Self {
        self.backpressure = backpressure;
        self
    }

    /// Sets the out-port's replay policy.
    pub fn replay(mut self, replay: Replay) -> Self {
        self.replay = replay;
        self
    }

    /// Sets the reconnection backoff.
    pub fn backoff(mut self, initial: Duration, max: Duration) -> Self {
        self.backoff = Backoff { initial, max };
        self
    }

    /// Names the port (its announcements, its connection).
    pub fn name(mut self, name: impl Into<String>) -> Self {
        self.name = Some(name.into());
        self
    }

    /// Records the out-port's values to a stream (see [`Recording`]).
    pub fn record(mut self, recording: Recording) -> Self {
        self.record = Some(recording);
        self
    }

    /// Sets how often the port announces itself; `None` or zero: never.
    pub fn announce_interval(mut self, interval: Option<Duration>) -> Self {
        self.announce_interval = interval;
        self
    }

    /// The name of a port with this profile in `role`: the one set with
    /// [`PortProfile::name`], else one made of where its messages go. An
    /// out-port: `EXCHANGE/ROUTING_KEY` (`EXCHANGE` alone without a
    /// routing key, `ROUTING_KEY` alone on the default exchange). An
    /// in-port: its queue if the profile names one, else
    /// `EXCHANGE/BINDING_KEY` (`EXCHANGE` alone without a binding key).
    /// `unnamed` if that leaves nothing.
    pub fn port_name(&self, role: PortRole) -> String {
        if let Some(name) = &self.name {
            return name.clone();
        }
        let joined = |exchange: &str, key: &str| match (exchange.is_empty(), key.is_empty()) {
            (true, _) => key.to_owned(),
            (false, true) => exchange.to_owned(),
            (false, false) => format!("{exchange}/{key}"),
        };
        let name = match role {
            PortRole::OutPort => joined(&self.exchange, &self.routing_key),
            PortRole::InPort if !self.queue.is_empty() => self.queue.clone(),
            PortRole::InPort => joined(&self.exchange, &self.binding_key),
        };
        if name.is_empty() {
            "unnamed".to_owned()
        } else {
            name
        }
    }
}

type ConnectFuture = Pin<Box<dyn Future<Output = Result<Connection>> + Send>>;

/// Opens a connection, naming it (`connection_name`) unless its options
/// already do.
type Connect = dyn Fn(Option<Arc<str>>) -> ConnectFuture + Send + Sync;

/// How a port opens (and, after a loss, reopens) its connection. Cheap to
/// clone.
#[derive(Clone)]
pub struct Connector {
    connect: Arc<Connect>,
    describe: Arc<str>,
    /// The `connection_name` client property of its connections (the port
    /// sets it), unless the connection options name one.
    connection_name: Option<Arc<str>>,
}

impl fmt::Debug for Connector {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_tuple("Connector").field(&self.describe).finish()
    }
}

/// `options` with `name` as the connection's name, unless they have one.
fn named(options: &ConnectionOptions, name: Option<Arc<str>>) -> ConnectionOptions {
    let mut options = options.clone();
    if options.connection_name.is_none() {
        options.connection_name = name.map(|name| name.to_string());
    }
    options
}

impl Connector {
    /// TCP to the broker `options` name.
    pub fn tcp(options: ConnectionOptions) -> Self {
        let describe = format!("amqp://{}:{}", options.host, options.port);
        let options = Arc::new(options);
        Connector {
            connect: Arc::new(move |name| {
                let options = named(&options, name);
                Box::pin(Connection::connect_with(options))
            }),
            describe: describe.into(),
            connection_name: None,
        }
    }

    /// Connections made by `connect` (for a transport or setup of one's
    /// own; their names are its business).
    pub fn from_fn<F, Fut>(connect: F) -> Self
    where
        F: Fn() -> Fut + Send + Sync + 'static,
        Fut: Future<Output = Result<Connection>> + Send + 'static,
    {
        Connector {
            connect: Arc::new(move |_| Box::pin(connect())),
            describe: "custom".into(),
            connection_name: None,
        }
    }

    /// In-process connections to an embedded Leveret (user `guest`). The
    /// connector holds the broker weakly: once the last `Arc` is gone (or
    /// unwrapped to call `shutdown`), reconnecting fails.
    #[cfg(feature = "embedded")]
    pub fn in_process(broker: &Arc<leveret_broker::BrokerHandle>) -> Self {
        Connector::in_process_with(broker, ConnectionOptions::default())
    }

    /// [`Connector::in_process`] with explicit options (credentials,
    /// vhost, tuning).
    #[cfg(feature = "embedded")]
    pub fn in_process_with(
        broker: &Arc<leveret_broker::BrokerHandle>,
        options: ConnectionOptions,
    ) -> Self {
        let broker = Arc::downgrade(broker);
        let options = Arc::new(options);
        Connector {
            connect: Arc::new(move |name| {
                let broker = broker.clone();
                let options = named(&options, name);
                Box::pin(async move {
                    let Some(broker) = broker.upgrade() else {
                        return Err(leveret_client::Error::from(std::io::Error::new(
                            std::io::ErrorKind::NotConnected,
                            "the embedded broker is gone",
                        )));
                    };
                    // The pipe is opened at once; the broker is not kept
                    // alive by the handshake.
                    Connection::in_process_with(&broker, options).await
                })
            }),
            describe: "in-process".into(),
            connection_name: None,
        }
    }

    /// This connector, naming its connections `name` (the
    /// `connection_name` client property management tools show) where
    /// their options do not.
    pub(crate) fn naming(mut self, name: String) -> Self {
        self.connection_name = Some(name.into());
        self
    }

    /// Opens a connection.
    pub async fn connect(&self) -> Result<Connection> {
        (self.connect)(self.connection_name.clone()).await
    }
}

impl From<&PortProfile> for Connector {
    fn from(profile: &PortProfile) -> Self {
        Connector::tcp(profile.broker.clone())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_spin_is_off_unless_asked_for() {
        assert_eq!(PortProfile::default().spin, None);
        for qos in [Qos::SensorData, Qos::Command, Qos::Reliable, Qos::Telemetry] {
            assert_eq!(PortProfile::default().qos(qos).spin, None, "{qos:?}");
        }
        let ceiling = Some(Duration::from_micros(20));
        let spinning = PortProfile::default().spin(ceiling);
        assert_eq!(spinning.spin, ceiling);
        assert_eq!(spinning.spin(None).spin, None, "and off again");
    }

    #[test]
    fn exchange_kinds_as_openrtm_names_them_in_any_case() {
        assert_eq!(ExchangeKind::parse("0"), ExchangeKind::Direct);
        assert_eq!(ExchangeKind::parse("AMQP::topic"), ExchangeKind::Topic);
        assert_eq!(ExchangeKind::parse("H"), ExchangeKind::Headers);
        assert_eq!(ExchangeKind::parse("Fanout"), ExchangeKind::Fanout);
        assert_eq!(ExchangeKind::parse("DIRECT"), ExchangeKind::Direct);
        assert_eq!(ExchangeKind::parse("amqp::Headers"), ExchangeKind::Headers);
        let hash = ExchangeKind::Other(CONSISTENT_HASH.into());
        assert_eq!(ExchangeKind::parse("x-consistent-hash"), hash);
        assert_eq!(ExchangeKind::parse("fan-out"), hash);
        assert_eq!(
            ExchangeKind::parse("x-delayed-message"),
            ExchangeKind::Other("x-delayed-message".into())
        );
    }

    #[test]
    fn backoff_doubles_up_to_max() {
        let backoff = Backoff {
            initial: Duration::from_millis(10),
            max: Duration::from_millis(50),
        };
        let delays: Vec<_> = (0..5).map(|n| backoff.delay(n).as_millis()).collect();
        assert_eq!(delays, [10, 20, 40, 50, 50]);
        assert_eq!(backoff.delay(1000), Duration::from_millis(50));
    }
}
