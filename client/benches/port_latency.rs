//! Round-trip latency of a pair of robot data ports, measured the way the
//! AMQP RT-Middleware paper does (section VI-A): the measuring task puts a
//! payload on an [`OutPort`]; an echo task takes it from an [`InPort`] and
//! puts it on a second out-port; the measuring task takes it back from a
//! second in-port. One message is in flight at a time. For each payload
//! size (8, 16, 32, 64 and 128 bytes) and each transport (Leveret
//! in-process, Leveret over loopback TCP, RabbitMQ over loopback TCP) it
//! runs two modes: paced at 100 Hz (1,000 round trips, as in the paper) and
//! unthrottled (5,000 round trips after a warm-up, the next put as soon as
//! the echo is back). Ports are transient and unconfirmed (the control-loop
//! case); extra rows at 64 bytes show the ports with publisher confirms and
//! a raw `leveret-client` publish/consume round trip over the same
//! topology (four connections, manual acks), which is what the ports cost
//! on top of the client and broker.
//!
//! This is a benchmark, not a test: it prints a Markdown table and asserts
//! nothing about timings.
//!
//! ```text
//! cargo bench -p leveret-client --bench port_latency --all-features
//! cargo bench -p leveret-client --bench port_latency --all-features -- --quick
//! ```
//!
//! Run without `--bench` (as `cargo test --benches` does; `cargo bench`
//! passes it), it only makes a few unthrottled round trips per path and
//! transport, to check that everything works.
//!
//! Options (after `--`):
//! - `--quick` (or `LEVERET_BENCH_QUICK=1`): a tenth of the round trips;
//! - `--sizes 8,64`, `--transports in-process,leveret-tcp,rabbitmq`,
//!   `--modes paced,unthrottled`: a subset;
//! - `--no-extras`: no confirm and raw-client rows; `--paced-extras`: those
//!   rows at 100 Hz too (by default they are unthrottled only);
//! - `--worker-threads N`: the tokio runtime's workers (default one per
//!   core); the broker, the ports and both loops share them;
//! - diagnostics: `--spin-pace` paces the 100 Hz mode by busy-waiting
//!   instead of sleeping (with `--worker-threads 1`, the CPU never idles
//!   between round trips); `--evict-kib N` writes N KiB before each round
//!   trip, untimed, to run it with cold caches but no idle time;
//!   `--dump DIR` writes each row's samples (ns, in the order taken) to a
//!   file in DIR.
//!
//! `LEVERET_BENCH_RABBIT_URL` names the RabbitMQ broker (default
//! `amqp://guest:guest@127.0.0.1:5672/%2f`); its rows are skipped with a
//! message when it cannot be reached.

use bytes::Bytes;
use leveret_broker::{Broker, BrokerHandle};
use leveret_client::ports::{Connector, FullPolicy, InPort, OutPort, PortProfile, PortStatus};
use leveret_client::{
    BasicAckOptions, BasicConsumeOptions, BasicProperties, BasicPublishOptions, BasicQosOptions,
    Channel, Connection, Consumer, FieldTable, QueueDeclareOptions, ShortStr,
};
use std::error::Error;
use std::fmt::Write as _;
use std::sync::Arc;
use std::time::{Duration, Instant};
use tokio::sync::oneshot;
use tokio::task::JoinHandle;
use tokio::time::MissedTickBehavior;

const DEFAULT_RABBIT_URL: &str = "amqp://guest:guest@127.0.0.1:5672/%2f";
const DEFAULT_SIZES: [usize; 5] = [8, 16, 32, 64, 128];
/// Payload size of the extra rows (confirms, raw client).
const EXTRA_SIZE: usize = 64;
/// The paper's rate: one put every 10 ms.
const PACE: Duration = Duration::from_millis(10);
/// An echo that takes longer than this counts as lost.
const ECHO_TIMEOUT: Duration = Duration::from_secs(5);
/// Connecting to a broker (and skipping RabbitMQ when it is not there).
const CONNECT_TIMEOUT: Duration = Duration::from_secs(3);

type BenchResult<T> = Result<T, Box<dyn Error + Send + Sync>>;

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Transport {
    InProcess,
    LeveretTcp,
    RabbitMq,
}

impl Transport {
    const ALL: [Transport; 3] = [
        Transport::InProcess,
        Transport::LeveretTcp,
        Transport::RabbitMq,
    ];

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

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Mode {
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
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Path {
    /// Out-ports and in-ports; with or without publisher confirms.
    Ports { confirms: bool },
    /// `basic.publish` and a consumer on plain channels, same topology.
    Raw,
}

impl Path {
    fn label(self) -> &'static str {
        match self {
            Path::Ports { confirms: false } => "ports",
            Path::Ports { confirms: true } => "ports + confirms",
            Path::Raw => "raw client",
        }
    }
}

struct Options {
    /// Run as a test (no `--bench`): a few round trips, to see it works.
    smoke: bool,
    sizes: Vec<usize>,
    transports: Vec<Transport>,
    modes: Vec<Mode>,
    extras: bool,
    paced_extras: bool,
    spin_pace: bool,
    evict_kib: usize,
    dump: Option<std::path::PathBuf>,
    paced_count: usize,
    paced_warmup: usize,
    unthrottled_count: usize,
    unthrottled_warmup: usize,
    worker_threads: Option<usize>,
    rabbit_url: String,
}

impl Options {
    fn parse() -> BenchResult<Self> {
        let mut quick =
            std::env::var("LEVERET_BENCH_QUICK").is_ok_and(|v| !v.is_empty() && v != "0");
        let mut sizes = DEFAULT_SIZES.to_vec();
        let mut transports = Transport::ALL.to_vec();
        let mut modes = vec![Mode::Paced, Mode::Unthrottled];
        let mut extras = true;
        let mut paced_extras = false;
        let mut spin_pace = false;
        let mut evict_kib = 0;
        let mut dump = None;
        // `cargo bench` passes `--bench`; `cargo test --benches` does not,
        // and then one short unthrottled row per path and transport only
        // checks that everything runs.
        let mut bench = false;
        let mut worker_threads = None;
        let mut args = std::env::args().skip(1);
        while let Some(arg) = args.next() {
            let mut value = |name: &str| args.next().ok_or_else(|| format!("{name} needs a value"));
            match arg.as_str() {
                "--quick" => quick = true,
                "--bench" => bench = true,
                "--no-extras" => extras = false,
                "--paced-extras" => paced_extras = true,
                "--spin-pace" => spin_pace = true,
                "--evict-kib" => evict_kib = value("--evict-kib")?.parse()?,
                "--dump" => dump = Some(value("--dump")?.into()),
                "--sizes" => {
                    sizes = value("--sizes")?
                        .split(',')
                        .map(str::parse)
                        .collect::<Result<_, _>>()?;
                }
                "--transports" => {
                    transports = value("--transports")?
                        .split(',')
                        .map(|name| {
                            Transport::ALL
                                .into_iter()
                                .find(|t| t.key() == name)
                                .ok_or_else(|| format!("unknown transport {name:?}"))
                        })
                        .collect::<Result<_, _>>()?;
                }
                "--modes" => {
                    modes = value("--modes")?
                        .split(',')
                        .map(|name| match name {
                            "paced" => Ok(Mode::Paced),
                            "unthrottled" => Ok(Mode::Unthrottled),
                            _ => Err(format!("unknown mode {name:?}")),
                        })
                        .collect::<Result<_, _>>()?;
                }
                "--worker-threads" => worker_threads = Some(value("--worker-threads")?.parse()?),
                // Other harness flags.
                _ => {}
            }
        }
        let scale = if quick { 10 } else { 1 };
        let smoke = !bench;
        if smoke {
            sizes.truncate(1);
            modes = vec![Mode::Unthrottled];
        }
        Ok(Options {
            smoke,
            sizes,
            transports,
            modes,
            extras,
            paced_extras,
            spin_pace,
            evict_kib,
            dump,
            paced_count: 1_000 / scale,
            paced_warmup: if quick { 5 } else { 20 },
            unthrottled_count: if smoke { 20 } else { 5_000 / scale },
            unthrottled_warmup: if smoke { 5 } else { 1_000 / scale },
            worker_threads,
            rabbit_url: std::env::var("LEVERET_BENCH_RABBIT_URL")
                .unwrap_or_else(|_| DEFAULT_RABBIT_URL.to_owned()),
        })
    }

    fn counts(&self, mode: Mode) -> (usize, usize) {
        match mode {
            Mode::Paced => (self.paced_warmup, self.paced_count),
            Mode::Unthrottled => (self.unthrottled_warmup, self.unthrottled_count),
        }
    }
}

/// How to reach one broker.
struct Endpoint {
    transport: Transport,
    connector: Connector,
    profile: PortProfile,
}

/// A profile for the bench's ports: transient, prefetch and buffer large
/// enough never to matter with one message in flight, nothing dropped.
fn bench_profile(base: PortProfile) -> PortProfile {
    base.buffer(16, FullPolicy::BlockBroker)
        .prefetch(16)
        .put_timeout(Duration::from_secs(2))
        .durable(false)
}

/// A round-trip loop: the measuring side's ends and the echo task.
enum Pair {
    Ports {
        output: OutPort<Bytes>,
        input: InPort<Bytes>,
        stop: oneshot::Sender<()>,
        echo: JoinHandle<u64>,
    },
    Raw {
        publisher: Channel,
        consumer: Consumer,
        queue: ShortStr,
        connections: [Connection; 2],
        stop: oneshot::Sender<()>,
        echo: JoinHandle<u64>,
    },
}

impl Pair {
    async fn open(endpoint: &Endpoint, path: Path) -> BenchResult<Pair> {
        match path {
            Path::Ports { confirms } => Pair::open_ports(endpoint, confirms).await,
            Path::Raw => Pair::open_raw(endpoint).await,
        }
    }

    /// Four ports, each with its own connection; the in-ports consume
    /// server-named exclusive queues and the out-ports publish to them
    /// through the default exchange.
    async fn open_ports(endpoint: &Endpoint, confirms: bool) -> BenchResult<Pair> {
        let profile = endpoint.profile.clone().confirms(confirms);
        let connector = &endpoint.connector;
        let echo_in = InPort::<Bytes>::connect_with(connector.clone(), profile.clone()).await?;
        let input = InPort::<Bytes>::connect_with(connector.clone(), profile.clone()).await?;
        let to_echo = profile
            .clone()
            .routing_key(echo_in.queue().to_string_lossy());
        let output = OutPort::<Bytes>::connect_with(connector.clone(), to_echo).await?;
        let back = profile.routing_key(input.queue().to_string_lossy());
        let echo_out = OutPort::<Bytes>::connect_with(connector.clone(), back).await?;
        let (stop, stopped) = oneshot::channel();
        let echo = tokio::spawn(echo_ports(echo_in, echo_out, stopped));
        Ok(Pair::Ports {
            output,
            input,
            stop,
            echo,
        })
    }

    /// The same topology without ports: four connections, a consumer with
    /// manual acks on each side's server-named queue, and publishes of the
    /// bare body (no headers) through the default exchange.
    async fn open_raw(endpoint: &Endpoint) -> BenchResult<Pair> {
        let (echo_in_conn, echo_in_channel) = raw_connect(&endpoint.connector).await?;
        let (echo_queue, echo_consumer) = raw_consume(echo_in_channel).await?;
        let (in_conn, in_channel) = raw_connect(&endpoint.connector).await?;
        let (queue, consumer) = raw_consume(in_channel).await?;
        let (out_conn, publisher) = raw_connect(&endpoint.connector).await?;
        let (echo_out_conn, echo_publisher) = raw_connect(&endpoint.connector).await?;
        let (stop, stopped) = oneshot::channel();
        let echo = tokio::spawn(echo_raw(
            echo_consumer,
            echo_publisher,
            queue,
            [echo_in_conn, echo_out_conn],
            stopped,
        ));
        Ok(Pair::Raw {
            publisher,
            consumer,
            queue: echo_queue,
            connections: [in_conn, out_conn],
            stop,
            echo,
        })
    }

    /// One round trip: sends `payload` and waits for its echo.
    async fn round_trip(&mut self, payload: &Bytes) -> BenchResult<()> {
        match self {
            Pair::Ports { output, input, .. } => {
                let status = output.put(payload).await;
                if status != PortStatus::Ok {
                    return Err(format!("put: {status:?}").into());
                }
                match tokio::time::timeout(ECHO_TIMEOUT, input.recv()).await {
                    Ok(Some(_)) => Ok(()),
                    Ok(None) => Err("the in-port closed".into()),
                    Err(_) => Err("no echo within the timeout".into()),
                }
            }
            Pair::Raw {
                publisher,
                consumer,
                queue,
                ..
            } => {
                publisher
                    .basic_publish(
                        "",
                        &*queue,
                        BasicPublishOptions::default(),
                        BasicProperties::default(),
                        payload.clone(),
                    )
                    .await?;
                match tokio::time::timeout(ECHO_TIMEOUT, consumer.next()).await {
                    Ok(Some(delivery)) => {
                        // Inside the timed section, but it only queues a
                        // frame on the connection's outbox.
                        delivery.ack().await?;
                        Ok(())
                    }
                    Ok(None) => Err("the consumer ended".into()),
                    Err(_) => Err("no echo within the timeout".into()),
                }
            }
        }
    }

    /// Drops echoes already waiting (after a failed round trip).
    fn drain(&mut self) {
        match self {
            Pair::Ports { input, .. } => while input.try_recv().is_some() {},
            // Unacknowledged, they stay with the consumer until the pair
            // closes; the prefetch window is large enough for a few.
            Pair::Raw { .. } => {}
        }
    }

    /// Stops the echo task and closes everything; returns the echo's
    /// failed puts.
    async fn close(self) -> u64 {
        match self {
            Pair::Ports {
                output,
                input,
                stop,
                echo,
            } => {
                let _ = stop.send(());
                let failures = echo.await.unwrap_or(0);
                output.close().await;
                input.close().await;
                failures
            }
            Pair::Raw {
                connections,
                stop,
                echo,
                ..
            } => {
                let _ = stop.send(());
                let failures = echo.await.unwrap_or(0);
                for connection in connections {
                    let _ = connection.close().await;
                }
                failures
            }
        }
    }
}

/// A connection and a channel on it.
async fn raw_connect(connector: &Connector) -> leveret_client::Result<(Connection, Channel)> {
    let connection = connector.connect().await?;
    let channel = connection.open_channel().await?;
    Ok((connection, channel))
}

/// A server-named exclusive queue and a manual-ack consumer on it.
async fn raw_consume(channel: Channel) -> leveret_client::Result<(ShortStr, Consumer)> {
    channel.basic_qos(16, BasicQosOptions::default()).await?;
    let declare = QueueDeclareOptions {
        exclusive: true,
        ..Default::default()
    };
    let queue = channel
        .queue_declare("", declare, FieldTable::new())
        .await?;
    let consumer = channel
        .basic_consume(
            &queue.name,
            "",
            BasicConsumeOptions::default(),
            FieldTable::new(),
        )
        .await?;
    Ok((queue.name, consumer))
}

/// Puts back every value the in-port receives, until told to stop.
async fn echo_ports(
    mut input: InPort<Bytes>,
    output: OutPort<Bytes>,
    mut stop: oneshot::Receiver<()>,
) -> u64 {
    let mut failures = 0;
    loop {
        tokio::select! {
            biased;
            _ = &mut stop => break,
            sample = input.recv() => match sample {
                Some(sample) => {
                    if output.put(&sample.value).await != PortStatus::Ok {
                        failures += 1;
                    }
                }
                None => break,
            },
        }
    }
    output.close().await;
    input.close().await;
    failures
}

/// Republishes every delivery's body to `queue`, then acknowledges it.
async fn echo_raw(
    mut consumer: Consumer,
    publisher: Channel,
    queue: ShortStr,
    connections: [Connection; 2],
    mut stop: oneshot::Receiver<()>,
) -> u64 {
    let mut failures = 0;
    loop {
        tokio::select! {
            biased;
            _ = &mut stop => break,
            delivery = consumer.next() => match delivery {
                Some(delivery) => {
                    let sent = publisher
                        .basic_publish(
                            "",
                            &queue,
                            BasicPublishOptions::default(),
                            BasicProperties::default(),
                            delivery.body.clone(),
                        )
                        .await;
                    let acked = consumer
                        .channel()
                        .basic_ack(delivery.delivery_tag, BasicAckOptions::default())
                        .await;
                    if sent.is_err() || acked.is_err() {
                        failures += 1;
                    }
                }
                None => break,
            },
        }
    }
    for connection in connections {
        let _ = connection.close().await;
    }
    failures
}

/// Latency summary of one row, in nanoseconds.
struct Summary {
    count: usize,
    mean: f64,
    min: u64,
    p25: u64,
    p50: u64,
    p75: u64,
    p99: u64,
    max: u64,
}

impl Summary {
    /// Sorts `samples` in place and summarises them.
    fn of(samples: &mut [u64]) -> Option<Summary> {
        if samples.is_empty() {
            return None;
        }
        samples.sort_unstable();
        // Nearest rank: the smallest sample with at least q of them at or
        // below it.
        let rank = |q: f64| {
            let n = samples.len();
            let index = ((q * n as f64).ceil() as usize).clamp(1, n) - 1;
            samples[index]
        };
        let total: u128 = samples.iter().map(|&s| u128::from(s)).sum();
        Some(Summary {
            count: samples.len(),
            mean: total as f64 / samples.len() as f64,
            min: samples[0],
            p25: rank(0.25),
            p50: rank(0.50),
            p75: rank(0.75),
            p99: rank(0.99),
            max: samples[samples.len() - 1],
        })
    }
}

struct Row {
    transport: Transport,
    path: Path,
    mode: Mode,
    size: usize,
    summary: Summary,
    lost: usize,
}

/// Runs `count` measured round trips after `warmup` unmeasured ones;
/// `samples` is reused across rows. Returns the number of failed round
/// trips (not in the samples).
async fn measure(
    pair: &mut Pair,
    mode: Mode,
    payload: &Bytes,
    warmup: usize,
    count: usize,
    samples: &mut Vec<u64>,
    options: &Options,
) -> usize {
    samples.clear();
    let mut failed = 0;
    let mut ticks = tokio::time::interval(PACE);
    // A late echo delays the next put rather than bunching puts up: there
    // is never more than one message in flight.
    ticks.set_missed_tick_behavior(MissedTickBehavior::Delay);
    let mut next = Instant::now();
    let mut evict = vec![0u8; options.evict_kib * 1024];
    for i in 0..warmup + count {
        if !evict.is_empty() {
            for line in evict.chunks_mut(64) {
                line[0] = line[0].wrapping_add(1);
            }
            std::hint::black_box(&mut evict);
        }
        if mode == Mode::Paced && options.spin_pace {
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
            Ok(()) if i >= warmup => samples.push(elapsed.as_nanos() as u64),
            Ok(()) => {}
            Err(error) => {
                failed += 1;
                if failed <= 3 {
                    eprintln!("  round trip failed: {error}");
                }
                // A late echo must not pass for the next one's.
                tokio::time::sleep(Duration::from_millis(100)).await;
                pair.drain();
            }
        }
    }
    failed
}

/// Connects the three transports; RabbitMQ is left out with a message
/// when it cannot be reached.
async fn endpoints(options: &Options, broker: &Arc<BrokerHandle>) -> BenchResult<Vec<Endpoint>> {
    let mut endpoints = Vec::new();
    for &transport in &options.transports {
        let endpoint = match transport {
            Transport::InProcess => Endpoint {
                transport,
                connector: Connector::in_process(broker),
                profile: bench_profile(PortProfile::default()),
            },
            Transport::LeveretTcp => {
                let addr = broker.local_addrs()[0];
                let profile = PortProfile::new(&format!("amqp://guest:guest@{addr}/%2f"))?;
                Endpoint {
                    transport,
                    connector: Connector::tcp(profile.broker.clone()),
                    profile: bench_profile(profile),
                }
            }
            Transport::RabbitMq => {
                let mut profile = PortProfile::new(&options.rabbit_url)?;
                profile.broker.connection_timeout = CONNECT_TIMEOUT;
                let connector = Connector::tcp(profile.broker.clone());
                match tokio::time::timeout(CONNECT_TIMEOUT, connector.connect()).await {
                    Ok(Ok(connection)) => {
                        let _ = connection.close().await;
                    }
                    Ok(Err(error)) => {
                        println!(
                            "RabbitMQ at {} unreachable ({error}): its rows are skipped.\n",
                            options.rabbit_url
                        );
                        continue;
                    }
                    Err(_) => {
                        println!(
                            "RabbitMQ at {} did not answer: its rows are skipped.\n",
                            options.rabbit_url
                        );
                        continue;
                    }
                }
                Endpoint {
                    transport,
                    connector,
                    profile: bench_profile(profile),
                }
            }
        };
        endpoints.push(endpoint);
    }
    Ok(endpoints)
}

async fn run(options: Options) -> BenchResult<Vec<Row>> {
    let listen = "127.0.0.1:0".parse()?;
    let broker = Arc::new(Broker::builder().listen(listen).start().await?);
    let endpoints = endpoints(&options, &broker).await?;

    // Every pair stays open for the whole run, and the transports take
    // turns size by size, so load from elsewhere on the machine spreads
    // over all of them alike.
    let mut plan: Vec<(Path, usize)> = options
        .sizes
        .iter()
        .map(|&size| (Path::Ports { confirms: false }, size))
        .collect();
    if options.extras {
        plan.push((Path::Ports { confirms: true }, EXTRA_SIZE));
        plan.push((Path::Raw, EXTRA_SIZE));
    }
    let mut pairs: Vec<Vec<(Path, Pair)>> = Vec::new();
    for endpoint in &endpoints {
        let mut mine = Vec::new();
        for path in [
            Path::Ports { confirms: false },
            Path::Ports { confirms: true },
            Path::Raw,
        ] {
            if path != (Path::Ports { confirms: false }) && !options.extras {
                continue;
            }
            mine.push((path, Pair::open(endpoint, path).await?));
        }
        pairs.push(mine);
    }

    let most = options.paced_count.max(options.unthrottled_count);
    let mut samples = Vec::with_capacity(most);
    let mut rows = Vec::new();
    for &mode in &options.modes {
        let (warmup, count) = options.counts(mode);
        for &(path, size) in &plan {
            // Extras are unthrottled only unless asked for: at 100 Hz a
            // row takes ten seconds.
            let extra = path != (Path::Ports { confirms: false });
            if extra && mode == Mode::Paced && !options.paced_extras {
                continue;
            }
            let payload = Bytes::from(vec![b'x'; size]);
            for (endpoint, mine) in endpoints.iter().zip(&mut pairs) {
                let Some((_, pair)) = mine.iter_mut().find(|(p, _)| *p == path) else {
                    continue;
                };
                eprintln!(
                    "{} / {} / {} / {size} B ...",
                    endpoint.transport.label(),
                    path.label(),
                    mode.label()
                );
                let lost =
                    measure(pair, mode, &payload, warmup, count, &mut samples, &options).await;
                if let Some(dir) = &options.dump {
                    let name = format!(
                        "{}_{}_{}_{size}_{}.txt",
                        endpoint.transport.key(),
                        path.label().replace(" + ", "-").replace(' ', "-"),
                        mode.label().replace(' ', ""),
                        rows.len()
                    );
                    let text: String = samples.iter().map(|s| format!("{s}\n")).collect();
                    std::fs::create_dir_all(dir)?;
                    std::fs::write(dir.join(name), text)?;
                }
                if let Some(summary) = Summary::of(&mut samples) {
                    rows.push(Row {
                        transport: endpoint.transport,
                        path,
                        mode,
                        size,
                        summary,
                        lost,
                    });
                }
            }
        }
    }

    for mine in pairs {
        for (path, pair) in mine {
            let failures = pair.close().await;
            if failures > 0 {
                eprintln!("echo ({}) failed {failures} puts", path.label());
            }
        }
    }
    drop(endpoints);
    if let Ok(broker) = Arc::try_unwrap(broker) {
        broker.shutdown().await;
    }
    Ok(rows)
}

fn micros(nanos: f64) -> String {
    format!("{:.1}", nanos / 1_000.0)
}

fn table(rows: &[Row]) -> String {
    let mut out = String::new();
    out.push_str(
        "| transport | path | mode | size (B) | n | mean | min | p25 | p50 | p75 | p99 | max | p99 / RabbitMQ p99 |\n",
    );
    out.push_str("|---|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|\n");
    for row in rows {
        let s = &row.summary;
        let ratio = if row.transport == Transport::LeveretTcp {
            rows.iter()
                .find(|r| {
                    r.transport == Transport::RabbitMq
                        && r.path == row.path
                        && r.mode == row.mode
                        && r.size == row.size
                })
                .map(|r| format!("{:.2}", s.p99 as f64 / r.summary.p99 as f64))
                .unwrap_or_else(|| "–".to_owned())
        } else {
            "–".to_owned()
        };
        let n = if row.lost > 0 {
            format!("{} ({} lost)", s.count, row.lost)
        } else {
            s.count.to_string()
        };
        let _ = writeln!(
            out,
            "| {} | {} | {} | {} | {} | {} | {} | {} | {} | {} | {} | {} | {} |",
            row.transport.label(),
            row.path.label(),
            row.mode.label(),
            row.size,
            n,
            micros(s.mean),
            micros(s.min as f64),
            micros(s.p25 as f64),
            micros(s.p50 as f64),
            micros(s.p75 as f64),
            micros(s.p99 as f64),
            micros(s.max as f64),
            ratio,
        );
    }
    out
}

/// The comparison with the targets set in the issue: in-process p99
/// under 50 µs, Leveret's loopback p99 at most half of RabbitMQ's. Only
/// printed; nothing is asserted.
fn targets(rows: &[Row]) -> String {
    let mut out = String::from("Targets (ports without confirms):\n");
    for mode in [Mode::Paced, Mode::Unthrottled] {
        let plain = |r: &&Row| r.mode == mode && r.path == (Path::Ports { confirms: false });
        let in_process: Vec<&Row> = rows
            .iter()
            .filter(plain)
            .filter(|r| r.transport == Transport::InProcess)
            .collect();
        if let Some(worst) = in_process.iter().max_by_key(|r| r.summary.p99) {
            let over = in_process
                .iter()
                .filter(|r| r.summary.p99 >= 50_000)
                .count();
            let _ = writeln!(
                out,
                "- {}: in-process p99 < 50 µs in {}/{} sizes (worst {} µs at {} B)",
                mode.label(),
                in_process.len() - over,
                in_process.len(),
                micros(worst.summary.p99 as f64),
                worst.size
            );
        }
        let ratios: Vec<(usize, f64)> = rows
            .iter()
            .filter(plain)
            .filter(|r| r.transport == Transport::LeveretTcp)
            .filter_map(|r| {
                let rabbit = rows
                    .iter()
                    .filter(plain)
                    .find(|q| q.transport == Transport::RabbitMq && q.size == r.size)?;
                Some((r.size, r.summary.p99 as f64 / rabbit.summary.p99 as f64))
            })
            .collect();
        if !ratios.is_empty() {
            let met = ratios.iter().filter(|(_, ratio)| *ratio <= 0.5).count();
            let worst = ratios
                .iter()
                .copied()
                .fold((0, 0.0), |a, b| if b.1 > a.1 { b } else { a });
            let _ = writeln!(
                out,
                "- {}: loopback p99 ≤ ½ RabbitMQ's in {met}/{} sizes (worst ratio {:.2} at {} B)",
                mode.label(),
                ratios.len(),
                worst.1,
                worst.0
            );
        }
    }
    out
}

/// The 1, 5 and 15 minute load averages and the share of the last ten
/// seconds some task waited for a CPU (Linux), for the record.
fn load_average() -> String {
    let load = std::fs::read_to_string("/proc/loadavg")
        .ok()
        .map(|text| {
            text.split_whitespace()
                .take(3)
                .collect::<Vec<_>>()
                .join(" ")
        })
        .unwrap_or_else(|| "unknown".to_owned());
    // "some avg10=1.23 avg60=… avg300=… total=…"
    let pressure = std::fs::read_to_string("/proc/pressure/cpu")
        .ok()
        .and_then(|text| {
            let some = text.lines().find(|l| l.starts_with("some"))?;
            let avg10 = some.split_whitespace().find(|f| f.starts_with("avg10="))?;
            Some(format!(", CPU pressure {}%", &avg10["avg10=".len()..]))
        })
        .unwrap_or_default();
    format!("{load}{pressure}")
}

fn main() -> BenchResult<()> {
    let options = Options::parse()?;
    let mut runtime = tokio::runtime::Builder::new_multi_thread();
    if let Some(threads) = options.worker_threads {
        runtime.worker_threads(threads);
    }
    let runtime = runtime.enable_all().build()?;
    let cores = std::thread::available_parallelism().map_or(0, |n| n.get());
    let workers = options.worker_threads.unwrap_or(cores);
    println!("port_latency: {cores} cores, {workers} tokio worker threads.");
    println!(
        "Round trip out-port → echo (in-port → out-port) → in-port, one message in flight; \
         {} paced (100 Hz) and {} unthrottled round trips per row (after {} and {} warm-up); times in µs.\n",
        options.paced_count, options.unthrottled_count, options.paced_warmup, options.unthrottled_warmup
    );
    let smoke = options.smoke;
    if smoke {
        println!("Smoke run (no --bench: run by `cargo test`); `cargo bench` measures.\n");
    }
    let before = load_average();
    // The measuring loop is a task like the echo, on the runtime's
    // workers, not on this thread (`block_on` would run it here and every
    // round trip would cross threads twice more).
    let rows = runtime.block_on(async { tokio::spawn(run(options)).await })??;
    println!("{}", table(&rows));
    if !smoke {
        println!("{}", targets(&rows));
    }
    println!("Load average before: {before}; after: {}.", load_average());
    Ok(())
}
