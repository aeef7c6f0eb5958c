//! `leveretctl port list`, `port stats NAME`, `port echo NAME`, `port hz
//! NAME` and `port bw NAME` (and the dispatch of `port record` and `port
//! replay`, which the `recorder` module owns): the robot data ports connected to a broker,
//! from the announcements they publish on `leveret.ports`
//! (leveret-ports' `PortDirectory`; the wire contract is in its
//! `announce` module), and the messages on their topics. These
//! speak AMQP to `--amqp-url`, not the management API, so they work the
//! same against RabbitMQ. This module owns the commands and their output;
//! it uses leveret-client (connection, port directory, `cdr::render`) on a
//! current-thread tokio runtime of its own, and the ctl's `Failure`s.

use crate::{emit, info, Cli, Failure};
use clap::Subcommand;
use leveret_client::{
    BasicConsumeOptions, BasicQosOptions, BasicRejectOptions, Channel, Connection,
    ConnectionOptions, Consumer, Delivery, Error, FieldTable, FieldValue, QueueBindOptions,
    QueueDeclareOptions,
};
use leveret_ports::{
    announced_counters, cdr, CdrOptions, PortAnnouncement, PortDirectory, PortRole, PortState,
    PORT_HEADER, SENT_HEADER, SEQ_HEADER,
};
use std::collections::{HashMap, VecDeque};
use std::fmt::Write as _;
use std::time::{Duration, SystemTime, UNIX_EPOCH};
use tokio::time::Instant;

/// The port commands.
#[derive(Debug, Subcommand)]
pub enum PortCommand {
    /// Lists the ports that announce themselves, listening a little more
    /// than one of their intervals: name, direction, type, exchange, key,
    /// queue, state, accepted, confirmed, received, lost by default; any
    /// of id, exchange_type, content_type, interval_ms, confirms, durable,
    /// lifespan_ms, link, connects, losses, last_error, latency_count,
    /// latency_min_ns, latency_mean_ns, latency_p50_ns, latency_p99_ns,
    /// latency_max_ns, or a counter's name, as columns.
    List {
        columns: Vec<String>,
        /// Seconds to listen at least (longer if a port announces less often).
        #[arg(long, default_value = "1.5", value_name = "SECONDS")]
        wait: f64,
    },
    /// Prints a port's counters each time it announces itself, with the
    /// message rates since its previous announcement and, for an in-port,
    /// its latencies; until --count announcements, the port's close, or
    /// (exit status 1) three of its intervals without a word.
    Stats {
        name: String,
        /// Stop after this many announcements.
        #[arg(long, value_name = "N")]
        count: Option<u64>,
        /// Seconds to wait for the port to announce itself (exit status 1
        /// if it does not).
        #[arg(long, default_value = "3", value_name = "SECONDS")]
        wait: f64,
    },
    /// Prints the messages on a port's exchange and key as they arrive
    /// (decoded by its type, else as text, else in hex), through a queue
    /// of its own: the port keeps all of its messages. A port on the
    /// default exchange has no exchange to copy from: the echo peeks at
    /// its queue, handing each message it takes straight back (the port's
    /// reader still gets it, marked redelivered, perhaps out of order).
    Echo {
        name: String,
        /// Stop after this many messages.
        #[arg(long, value_name = "N")]
        count: Option<u64>,
        /// Seconds to wait for the port to announce itself (exit status 1
        /// if it does not).
        #[arg(long, default_value = "3", value_name = "SECONDS")]
        wait: f64,
    },
    /// Prints the rate at which a port's messages arrive (as rostopic hz):
    /// each second, over the last --window messages, the rate and the
    /// shortest, longest and standard deviation of the gaps between them.
    /// Taps the port's topic as `port echo` does (on the default exchange
    /// by peeking: it sees new messages only while the queue's reader
    /// takes them).
    Hz {
        name: String,
        #[command(flatten)]
        window: WindowArgs,
    },
    /// Prints the bandwidth of a port's messages (as rostopic bw): each
    /// second, over the last --window messages, bytes per second and the
    /// mean, smallest and largest body. Taps the port's topic as `port
    /// hz` does.
    Bw {
        name: String,
        #[command(flatten)]
        window: WindowArgs,
    },
    /// Records a port's messages to a stream, from now on: binds the
    /// stream (declared with the retention given) to the port's exchange
    /// and key. A port on the default exchange cannot be recorded. The
    /// binding lasts as long as the exchange (a transient one loses it on
    /// a broker restart); a port profile's `record` binds on every
    /// connection instead.
    Record(crate::recorder::RecordArgs),
    /// Plays a stream back (as rosbag play): from --start to --end, at
    /// --rate times the recorded pace (or --fast), printing each record
    /// (offset, sequence number, send time, topic, value) or, with
    /// --publish, republishing it with its original headers.
    Replay(crate::recorder::ReplayArgs),
}

/// The options of `port hz` and `port bw`.
#[derive(Debug, clap::Args)]
pub struct WindowArgs {
    /// The messages measured over: the latest this many.
    #[arg(long, default_value = "1000", value_name = "N")]
    window: usize,
    /// Stop after this many reports.
    #[arg(long, value_name = "N")]
    count: Option<u64>,
    /// Seconds to wait for the port to announce itself (exit status 1 if
    /// it does not).
    #[arg(long, default_value = "3", value_name = "SECONDS")]
    wait: f64,
}

/// The longest `port list` listens, whatever the ports' intervals.
const MAX_LISTEN: Duration = Duration::from_secs(60);

/// How long a peeking echo holds a message it has printed already before
/// handing it back again.
const HAND_BACK_PAUSE: Duration = Duration::from_millis(20);

/// The bytes of a body shown in hex, at most.
const HEX_BYTES: usize = 64;

/// The columns `port list` shows when none are asked for.
const DEFAULT_COLUMNS: &[&str] = &[
    "name",
    "direction",
    "type",
    "exchange",
    "key",
    "queue",
    "state",
    "accepted",
    "confirmed",
    "received",
    "lost",
];

/// The counters `port stats` shows a rate for (messages per second).
const RATED: &[&str] = &["accepted", "confirmed", "arrived", "received"];

/// Runs a port command.
pub fn run(cli: &Cli, command: &PortCommand) -> Result<(), Failure> {
    let runtime = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()?;
    runtime.block_on(async {
        match command {
            PortCommand::List { columns, wait } => list(cli, columns, seconds(*wait)?).await,
            PortCommand::Stats { name, count, wait } => {
                stats(cli, name, *count, seconds(*wait)?).await
            }
            PortCommand::Echo { name, count, wait } => {
                echo(cli, name, *count, seconds(*wait)?).await
            }
            PortCommand::Hz { name, window } => measure(cli, name, window, Measure::Rate).await,
            PortCommand::Bw { name, window } => {
                measure(cli, name, window, Measure::Bandwidth).await
            }
            PortCommand::Record(args) => crate::recorder::record(cli, args).await,
            PortCommand::Replay(args) => crate::recorder::replay(cli, args).await,
        }
    })
}

fn seconds(value: f64) -> Result<Duration, Failure> {
    Duration::try_from_secs_f64(value)
        .ok()
        .filter(|wait| !wait.is_zero())
        .ok_or_else(|| Failure::Usage(format!("--wait {value}: not a number of seconds")))
}

/// A connection to `--amqp-url`: unreachable is status 69, refused 1.
pub(crate) async fn connect(cli: &Cli) -> Result<Connection, Failure> {
    let mut options = ConnectionOptions::from_uri(&cli.amqp_url)
        .map_err(|e| Failure::Usage(format!("--amqp-url: {e}")))?;
    options.connection_name = Some("leveretctl".to_owned());
    if !cli.amqp_url.contains("connection_timeout=") {
        options.connection_timeout = Duration::from_secs(10);
    }
    let place = format!("{}:{}", options.host, options.port);
    Connection::connect_with(options)
        .await
        .map_err(|error| match error {
            Error::ConnectionClosed(reason) => {
                Failure::Refused(format!("the broker at {place} refused: {reason}"))
            }
            error => Failure::Unavailable(format!("cannot reach the broker at {place}: {error}")),
        })
}

/// What an AMQP error on an open connection means for the exit status:
/// the broker refused (1), or it is gone (69).
pub(crate) fn broker_failure(error: Error) -> Failure {
    match error {
        Error::ChannelClosed(reason) | Error::ConnectionClosed(reason) => {
            Failure::Refused(format!("the broker refused: {reason}"))
        }
        error => Failure::Unavailable(format!("lost the broker: {error}")),
    }
}

/// The next announcement, or a failure once the connection has ended.
async fn next(directory: &mut PortDirectory) -> Result<PortAnnouncement, Failure> {
    directory
        .next()
        .await
        .ok_or_else(|| Failure::Unavailable("the broker closed the connection".to_owned()))
}

async fn list(cli: &Cli, columns: &[String], wait: Duration) -> Result<(), Failure> {
    let connection = connect(cli).await?;
    let mut directory = PortDirectory::watch(&connection)
        .await
        .map_err(broker_failure)?;
    info(cli, "Listing ports ...")?;
    let started = Instant::now();
    let mut deadline = started + wait;
    loop {
        tokio::select! {
            announcement = next(&mut directory) => {
                // A bit more than the longest interval heard, so every
                // port has announced once.
                let interval = announcement?.interval.mul_f64(1.2).min(MAX_LISTEN);
                deadline = deadline.max(started + interval);
            }
            () = tokio::time::sleep_until(deadline) => break,
        }
    }
    let ports = directory.ports();
    let names: Vec<&str> = if columns.is_empty() {
        DEFAULT_COLUMNS.to_vec()
    } else {
        columns.iter().map(String::as_str).collect()
    };
    // Counters are columns even when no port listed has them (and a
    // newer port's counters are columns too once it is heard).
    let counters = announced_counters();
    let unknown: Vec<&str> = names
        .iter()
        .copied()
        .filter(|name| {
            !FIELD_COLUMNS.contains(name)
                && !counters.contains(name)
                && !ports.iter().any(|port| port.counter(name).is_some())
        })
        .collect();
    if !unknown.is_empty() {
        return Err(Failure::Usage(format!(
            "unknown columns {}; known: {}, or a counter's name",
            unknown.join(", "),
            FIELD_COLUMNS.join(", ")
        )));
    }
    let mut out = String::new();
    if !cli.no_table_headers {
        let _ = writeln!(out, "{}", names.join("\t"));
    }
    for port in &ports {
        let row: Vec<String> = names.iter().map(|name| cell(port, name)).collect();
        let _ = writeln!(out, "{}", row.join("\t"));
    }
    emit(&out)
}

/// The columns of `port list` that are fields of an announcement.
const FIELD_COLUMNS: &[&str] = &[
    "name",
    "id",
    "direction",
    "type",
    "content_type",
    "exchange",
    "exchange_type",
    "key",
    "queue",
    "state",
    "interval_ms",
    "confirms",
    "durable",
    "lifespan_ms",
    "link",
    "connects",
    "losses",
    "last_error",
    "latency_count",
    "latency_min_ns",
    "latency_mean_ns",
    "latency_p50_ns",
    "latency_p99_ns",
    "latency_max_ns",
];

/// Column `name` of `port`'s row: a field, or a counter (empty if the
/// port has no such counter).
fn cell(port: &PortAnnouncement, name: &str) -> String {
    let nanos = |value: Duration| value.as_nanos().to_string();
    let latency = port.latency;
    match name {
        "name" => port.name.clone(),
        "id" => port.id.clone(),
        "direction" => port.role.direction().to_owned(),
        "type" => port.data_type.clone(),
        "content_type" => port.content_type.clone(),
        "exchange" => port.exchange.clone(),
        "exchange_type" => port.exchange_kind.to_string(),
        "key" => port.key.clone(),
        "queue" => port.queue.clone(),
        "state" => port.state.as_str().to_owned(),
        "interval_ms" => port.interval.as_millis().to_string(),
        "confirms" => port.confirms.to_string(),
        "durable" => port.durable.to_string(),
        "lifespan_ms" => port
            .lifespan
            .map(|lifespan| lifespan.as_millis().to_string())
            .unwrap_or_default(),
        "link" => port.link.state().as_str().to_owned(),
        "connects" => port.link.connects.to_string(),
        "losses" => port.link.losses.to_string(),
        "last_error" => port.link.last_error.clone().unwrap_or_default(),
        "latency_count" => latency.map(|l| l.count.to_string()).unwrap_or_default(),
        "latency_min_ns" => latency.map(|l| nanos(l.min)).unwrap_or_default(),
        "latency_mean_ns" => latency.map(|l| nanos(l.mean)).unwrap_or_default(),
        "latency_p50_ns" => latency.map(|l| nanos(l.p50)).unwrap_or_default(),
        "latency_p99_ns" => latency.map(|l| nanos(l.p99)).unwrap_or_default(),
        "latency_max_ns" => latency.map(|l| nanos(l.max)).unwrap_or_default(),
        counter => port
            .counter(counter)
            .map(|value| value.to_string())
            .unwrap_or_default(),
    }
}

/// Waits up to `wait` for a port named `name`; exit status 1 if none
/// announces itself.
pub(crate) async fn find(
    directory: &mut PortDirectory,
    name: &str,
    wait: Duration,
) -> Result<PortAnnouncement, Failure> {
    let not_found = || Failure::Refused(format!("no port named {name:?} announced itself"));
    tokio::time::timeout(wait, async {
        loop {
            let announcement = next(directory).await?;
            if announcement.name == name && announcement.state == PortState::Up {
                return Ok(announcement);
            }
        }
    })
    .await
    .map_err(|_| not_found())?
}

async fn stats(cli: &Cli, name: &str, count: Option<u64>, wait: Duration) -> Result<(), Failure> {
    let connection = connect(cli).await?;
    let mut directory = PortDirectory::watch(&connection)
        .await
        .map_err(broker_failure)?;
    let first = find(&mut directory, name, wait).await?;
    info(cli, &format!("Statistics of port {name} ..."))?;
    let mut previous: HashMap<String, PortAnnouncement> = HashMap::new();
    let mut printed = 0;
    let mut announcement = first;
    loop {
        emit(&stats_line(&announcement, previous.get(&announcement.id)))?;
        printed += 1;
        if count.is_some_and(|count| printed >= count) {
            return Ok(());
        }
        if announcement.state == PortState::Closed && directory.named(name).is_empty() {
            return Ok(());
        }
        // Silent for three of its intervals: gone without a word.
        let silence = wait.max(announcement.interval.saturating_mul(3));
        previous.insert(announcement.id.clone(), announcement);
        announcement = tokio::time::timeout(silence, async {
            loop {
                let next = next(&mut directory).await?;
                if next.name == name {
                    return Ok::<_, Failure>(next);
                }
            }
        })
        .await
        .map_err(|_| Failure::Refused(format!("port {name:?} went silent")))??;
    }
}

/// One `port stats` line: `NAME DIRECTION STATE counter=value …`, with
/// `counter/s=rate` since `previous` for the message counters, the
/// latencies in ms, the link, and the instance's id.
fn stats_line(port: &PortAnnouncement, previous: Option<&PortAnnouncement>) -> String {
    let mut line = format!(
        "{} {} {}",
        port.name,
        port.role.direction(),
        port.state.as_str()
    );
    let elapsed = previous
        .map(|previous| port.sent_ns.saturating_sub(previous.sent_ns) as f64 / 1e9)
        .filter(|seconds| *seconds > 0.0);
    for (counter, value) in &port.stats {
        let _ = write!(line, " {counter}={value}");
        let before = previous.and_then(|previous| previous.counter(counter));
        if let (true, Some(before), Some(seconds)) =
            (RATED.contains(&counter.as_str()), before, elapsed)
        {
            let rate = value.saturating_sub(before) as f64 / seconds;
            let _ = write!(line, " {counter}/s={rate:.1}");
        }
    }
    if let Some(latency) = port.latency {
        let ms = |value: Duration| value.as_secs_f64() * 1e3;
        let _ = write!(
            line,
            " latency_min_ms={:.3} latency_mean_ms={:.3} latency_p50_ms={:.3} \
             latency_p99_ms={:.3} latency_max_ms={:.3}",
            ms(latency.min),
            ms(latency.mean),
            ms(latency.p50),
            ms(latency.p99),
            ms(latency.max)
        );
    }
    let _ = writeln!(
        line,
        " link={} connects={} losses={} port={}",
        port.link.state().as_str(),
        port.link.connects,
        port.link.losses,
        port.id
    );
    line
}

/// A port's messages as they flow, for `echo`, `hz` and `bw`: through a
/// queue of the tap's own bound to the port's exchange and key, or, for a
/// port on the default exchange, by peeking at the port's queue (each
/// message handed straight back; one seen again is skipped).
struct Tap {
    port: PortAnnouncement,
    consumer: Consumer,
    /// The queue peeked at, for a port on the default exchange.
    peeked: Option<String>,
    /// Peeking: the last sequence number taken per sender, to take a
    /// message that comes back to the tap only once.
    taken: HashMap<String, i64>,
}

impl Tap {
    /// Finds the port named `name` (an out-port of that name rather than
    /// an in-port, if there is one) and taps its messages.
    async fn open(cli: &Cli, name: &str, wait: Duration) -> Result<Tap, Failure> {
        let connection = connect(cli).await?;
        let mut directory = PortDirectory::watch(&connection)
            .await
            .map_err(broker_failure)?;
        let mut port = find(&mut directory, name, wait).await?;
        if port.role == PortRole::InPort {
            // An out-port of the same name is the one to tap, if there is
            // one: listen one of its intervals more for it.
            let more = port.interval.mul_f64(1.2).min(wait);
            let _ = tokio::time::timeout(more, async {
                loop {
                    match next(&mut directory).await {
                        Ok(other) if other.name == name && other.role == PortRole::OutPort => {
                            port = other;
                            return;
                        }
                        Ok(_) => {}
                        Err(_) => return,
                    }
                }
            })
            .await;
        }
        // Its consumer, no longer drained, would pause the connection.
        directory.close().await;
        let channel = connection.open_channel().await.map_err(broker_failure)?;
        let (consumer, peeked) = if port.exchange.is_empty() {
            let queue = if port.key.is_empty() {
                port.queue.clone()
            } else {
                port.key.clone()
            };
            (peek(&channel, &queue).await?, Some(queue))
        } else {
            (copy(&channel, &port).await?, None)
        };
        Ok(Tap {
            port,
            consumer,
            peeked,
            taken: HashMap::new(),
        })
    }

    /// The port and how it is tapped, for the first line of output.
    fn describe(&self) -> String {
        let through = match &self.peeked {
            Some(queue) => format!(
                "default exchange: peeking at queue {queue:?}, each message handed straight back"
            ),
            None => format!("exchange {:?}, key {:?}", self.port.exchange, self.port.key),
        };
        format!(
            "port {} ({} {}, {through})",
            self.port.name,
            self.port.role.direction(),
            self.port.data_type
        )
    }

    /// The next message not taken before.
    async fn next(&mut self) -> Result<Delivery, Failure> {
        loop {
            let Some(delivery) = self.consumer.next().await else {
                return Err(Failure::Unavailable(
                    "the broker ended the tap's consumer".to_owned(),
                ));
            };
            if self.peeked.is_none() {
                return Ok(delivery);
            }
            let headers = delivery.properties.headers.as_ref();
            let sender = headers
                .and_then(|h| h.get(PORT_HEADER))
                .and_then(FieldValue::as_bytes)
                .map(|b| String::from_utf8_lossy(b).into_owned())
                .unwrap_or_default();
            let seq = headers
                .and_then(|h| h.get(SEQ_HEADER))
                .and_then(FieldValue::as_i64)
                .unwrap_or(i64::MAX);
            let last = self.taken.entry(sender).or_insert(i64::MIN);
            let again = seq <= *last;
            if again {
                // Back to the tap rather than the port's reader (none is
                // consuming, or it is busy): a pause, so the two do not
                // pass it to and fro.
                tokio::time::sleep(HAND_BACK_PAUSE).await;
            }
            delivery
                .reject(BasicRejectOptions { requeue: true })
                .await
                .map_err(broker_failure)?;
            if !again {
                *last = seq;
                return Ok(delivery);
            }
        }
    }
}

async fn echo(cli: &Cli, name: &str, count: Option<u64>, wait: Duration) -> Result<(), Failure> {
    let mut tap = Tap::open(cli, name, wait).await?;
    info(cli, &format!("Echoing {} ...", tap.describe()))?;
    let options = tap.port.cdr.unwrap_or_default();
    let mut printed = 0;
    while count.is_none_or(|count| printed < count) {
        let delivery = tap.next().await?;
        let header = |key: &str| {
            delivery
                .properties
                .headers
                .as_ref()
                .and_then(|h| h.get(key))
                .and_then(FieldValue::as_i64)
        };
        let type_name = delivery
            .properties
            .kind
            .as_ref()
            .map(|kind| kind.to_string_lossy().into_owned())
            .unwrap_or_else(|| tap.port.data_type.clone());
        let seq = header(SEQ_HEADER).map_or_else(|| "-".to_owned(), |seq| seq.to_string());
        let age = header(SENT_HEADER).map_or_else(
            || "-".to_owned(),
            |sent| format!("{:.3}", (now_ns().saturating_sub(sent)) as f64 / 1e6),
        );
        emit(&format!(
            "seq={seq} age_ms={age} {}\n",
            show(&type_name, delivery.body.clone(), options)
        ))?;
        printed += 1;
    }
    Ok(())
}

/// What `port hz` and `port bw` report.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Measure {
    Rate,
    Bandwidth,
}

/// How often `port hz` and `port bw` report.
const REPORT_EVERY: Duration = Duration::from_secs(1);

async fn measure(cli: &Cli, name: &str, args: &WindowArgs, what: Measure) -> Result<(), Failure> {
    if args.window < 2 {
        return Err(Failure::Usage(format!(
            "--window {}: at least 2 messages",
            args.window
        )));
    }
    let mut tap = Tap::open(cli, name, seconds(args.wait)?).await?;
    let verb = match what {
        Measure::Rate => "Rate",
        Measure::Bandwidth => "Bandwidth",
    };
    info(cli, &format!("{verb} of {} ...", tap.describe()))?;
    let mut window = Arrivals::new(args.window);
    let mut ticker = tokio::time::interval_at(Instant::now() + REPORT_EVERY, REPORT_EVERY);
    let mut arrived_since_report = false;
    let mut printed = 0;
    while args.count.is_none_or(|count| printed < count) {
        tokio::select! {
            delivery = tap.next() => {
                window.push(Instant::now(), delivery?.body.len());
                arrived_since_report = true;
            }
            _ = ticker.tick() => {
                match (arrived_since_report, window.figures()) {
                    (true, Some(figures)) => {
                        emit(&figures.line(what))?;
                        printed += 1;
                    }
                    _ => info(cli, "no new messages")?,
                }
                arrived_since_report = false;
            }
        }
    }
    Ok(())
}

/// The arrival times and body sizes of the latest messages.
#[derive(Debug)]
struct Arrivals {
    latest: VecDeque<(Instant, usize)>,
    capacity: usize,
}

/// What a window of arrivals says: the gaps between messages and their
/// sizes.
#[derive(Debug, Clone, Copy, PartialEq)]
struct Figures {
    messages: usize,
    /// From the first arrival to the last.
    span: Duration,
    min_gap: Duration,
    max_gap: Duration,
    /// The gaps' standard deviation, seconds.
    gap_std_s: f64,
    /// Bytes after the first message (what arrived during the span).
    bytes_after_first: usize,
    total_bytes: usize,
    min_bytes: usize,
    max_bytes: usize,
}

impl Arrivals {
    fn new(capacity: usize) -> Self {
        Arrivals {
            latest: VecDeque::with_capacity(capacity),
            capacity,
        }
    }

    fn push(&mut self, at: Instant, bytes: usize) {
        if self.latest.len() == self.capacity {
            self.latest.pop_front();
        }
        self.latest.push_back((at, bytes));
    }

    /// The window's figures, once it holds two messages at different times.
    fn figures(&self) -> Option<Figures> {
        let (first, _) = *self.latest.front()?;
        let (last, _) = *self.latest.back()?;
        let span = last.duration_since(first);
        if self.latest.len() < 2 || span.is_zero() {
            return None;
        }
        let gaps: Vec<Duration> = self
            .latest
            .iter()
            .zip(self.latest.iter().skip(1))
            .map(|((a, _), (b, _))| b.duration_since(*a))
            .collect();
        let mean = span.as_secs_f64() / gaps.len() as f64;
        let variance = gaps
            .iter()
            .map(|gap| (gap.as_secs_f64() - mean).powi(2))
            .sum::<f64>()
            / gaps.len() as f64;
        let sizes = || self.latest.iter().map(|(_, bytes)| *bytes);
        let total_bytes: usize = sizes().sum();
        Some(Figures {
            messages: self.latest.len(),
            span,
            min_gap: gaps.iter().copied().min()?,
            max_gap: gaps.iter().copied().max()?,
            gap_std_s: variance.sqrt(),
            bytes_after_first: total_bytes - self.latest.front()?.1,
            total_bytes,
            min_bytes: sizes().min()?,
            max_bytes: sizes().max()?,
        })
    }
}

impl Figures {
    /// Messages per second over the span.
    fn rate_hz(&self) -> f64 {
        (self.messages - 1) as f64 / self.span.as_secs_f64()
    }

    /// Bytes per second over the span.
    fn bytes_per_s(&self) -> f64 {
        self.bytes_after_first as f64 / self.span.as_secs_f64()
    }

    /// One report line of `port hz` or `port bw`.
    fn line(&self, what: Measure) -> String {
        match what {
            Measure::Rate => format!(
                "rate_hz={:.3} min_s={:.6} max_s={:.6} std_s={:.6} window={}\n",
                self.rate_hz(),
                self.min_gap.as_secs_f64(),
                self.max_gap.as_secs_f64(),
                self.gap_std_s,
                self.messages
            ),
            Measure::Bandwidth => format!(
                "bytes_per_s={:.1} mean_bytes={:.1} min_bytes={} max_bytes={} window={}\n",
                self.bytes_per_s(),
                self.total_bytes as f64 / self.messages as f64,
                self.min_bytes,
                self.max_bytes,
                self.messages
            ),
        }
    }
}

/// A body as its value (a CDR type the client implements), else as text,
/// else in hex (the first [`HEX_BYTES`] bytes).
pub(crate) fn show(type_name: &str, body: bytes::Bytes, options: CdrOptions) -> String {
    if let Some(value) = cdr::render(type_name, body.clone(), options) {
        return value;
    }
    if let Ok(text) = std::str::from_utf8(&body) {
        return format!("{text:?}");
    }
    let mut hex = String::from("0x");
    for byte in body.iter().take(HEX_BYTES) {
        let _ = write!(hex, "{byte:02x}");
    }
    if body.len() > HEX_BYTES {
        let _ = write!(hex, "… ({} bytes)", body.len());
    }
    hex
}

/// The echo's queue for a port on a named exchange: its own, bound with
/// the port's key, so the port keeps every message.
async fn copy(channel: &Channel, port: &PortAnnouncement) -> Result<Consumer, Failure> {
    let queue = channel
        .queue_declare(
            "",
            QueueDeclareOptions {
                exclusive: true,
                auto_delete: true,
                ..Default::default()
            },
            FieldTable::new(),
        )
        .await
        .map_err(broker_failure)?;
    channel
        .queue_bind(
            &queue.name,
            port.exchange.as_str(),
            port.key.as_str(),
            QueueBindOptions::default(),
            FieldTable::new(),
        )
        .await
        .map_err(|error| match broker_failure(error) {
            Failure::Refused(why) => {
                Failure::Refused(format!("binding to exchange {:?}: {why}", port.exchange))
            }
            other => other,
        })?;
    channel
        .basic_consume(
            &queue.name,
            "",
            BasicConsumeOptions {
                no_ack: true,
                exclusive: true,
                ..Default::default()
            },
            FieldTable::new(),
        )
        .await
        .map_err(broker_failure)
}

/// The echo's consumer for a port on the default exchange, whose messages
/// go straight to `queue` (no exchange to bind a copy to): it shares the
/// queue with the port's reader, one message at a time, and hands each
/// message straight back (`basic.reject`, requeue). The reader still gets
/// every message, those the echo saw first marked redelivered and
/// possibly after a later one (its counters say so: out_of_order).
async fn peek(channel: &Channel, queue: &str) -> Result<Consumer, Failure> {
    channel
        .basic_qos(1, BasicQosOptions::default())
        .await
        .map_err(broker_failure)?;
    channel
        .basic_consume(queue, "", BasicConsumeOptions::default(), FieldTable::new())
        .await
        .map_err(|error| match broker_failure(error) {
            Failure::Refused(why) => Failure::Refused(format!("consuming from {queue:?}: {why}")),
            other => other,
        })
}

/// Nanoseconds since the Unix epoch.
fn now_ns() -> i64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map(|since| i64::try_from(since.as_nanos()).unwrap_or(i64::MAX))
        .unwrap_or(0)
}

#[cfg(test)]
mod tests {
    use super::*;
    use leveret_ports::{PortData, Time, TimedLong};

    #[test]
    fn a_window_gives_rate_gaps_and_sizes_of_its_latest_messages() {
        let start = Instant::now();
        let ms = |n: u64| start + Duration::from_millis(n);
        let mut window = Arrivals::new(4);
        window.push(ms(0), 1000);
        assert_eq!(window.figures(), None, "one message has no rate");
        // Gaps 10, 20, 10 ms over the last four: the first falls out.
        for (at, bytes) in [(10, 10), (30, 20), (40, 30), (50, 40)] {
            window.push(ms(at), bytes);
        }
        let figures = window.figures().expect("figures");
        assert_eq!(figures.messages, 4);
        assert_eq!(figures.span, Duration::from_millis(40));
        assert_eq!(
            (figures.min_gap, figures.max_gap),
            (Duration::from_millis(10), Duration::from_millis(20))
        );
        assert!((figures.rate_hz() - 75.0).abs() < 1e-9, "3 gaps in 40 ms");
        // Gaps 20, 10, 10 ms: mean 13.33 ms, deviation sqrt(200/9) ms.
        assert!((figures.gap_std_s - (200.0f64 / 9.0).sqrt() / 1e3).abs() < 1e-12);
        // 20 + 30 + 40 bytes arrived during the 40 ms.
        assert!((figures.bytes_per_s() - 2250.0).abs() < 1e-9);
        assert_eq!((figures.min_bytes, figures.max_bytes), (10, 40));
        assert_eq!(
            figures.line(Measure::Bandwidth),
            "bytes_per_s=2250.0 mean_bytes=25.0 min_bytes=10 max_bytes=40 window=4\n"
        );
        assert_eq!(
            figures.line(Measure::Rate),
            "rate_hz=75.000 min_s=0.010000 max_s=0.020000 std_s=0.004714 window=4\n"
        );
        let mut same_instant = Arrivals::new(4);
        same_instant.push(ms(5), 1);
        same_instant.push(ms(5), 1);
        assert_eq!(same_instant.figures(), None, "no span, no rate");
    }

    #[test]
    fn bodies_show_as_values_text_or_hex() {
        let value = TimedLong {
            tm: Time { sec: 1, nsec: 2 },
            data: -5,
        };
        let mut body = bytes::BytesMut::new();
        value.encode(&mut body).expect("encode");
        let name = TimedLong::TYPE_NAME.expect("named");
        assert_eq!(
            show(name, body.freeze(), CdrOptions::default()),
            format!("{value:?}")
        );
        let text = bytes::Bytes::from_static(b"go \"home\"");
        assert_eq!(
            show("unknown", text, CdrOptions::default()),
            "\"go \\\"home\\\"\""
        );
        let binary = bytes::Bytes::from(vec![0xffu8; 70]);
        let shown = show(name, binary, CdrOptions::default());
        assert!(
            shown.starts_with("0xffff") && shown.ends_with("… (70 bytes)"),
            "{shown}"
        );
    }
}
