//! In-process one-way latency at the application, in one run, of three
//! transports carrying the same 32-byte value from a sender thread to a
//! receiver thread (issue 34 item 3):
//!
//! - Leveret's ports on an embedded broker (`Connector::in_process`): an
//!   `OutPort<Vec<u8>>` (`try_put`) to an `InPort<Vec<u8>>`
//!   (`recv_blocking`) through the default exchange and a queue;
//! - Zenoh, publisher and subscriber in the same session (peer mode, no
//!   listener, no scouting), the subscriber's FIFO channel read with
//!   blocking `recv`;
//! - `std::sync::mpsc`.
//!
//! Two modes: back to back (the next value is sent once the receiver has
//! the previous one) and 1 kHz (the sender sleeps to absolute deadlines 1 ms
//! apart; the receiver thread sleeps between values). Latency is the
//! receiver's clock reading minus the sender's, taken just before the send
//! call, both on one monotonic origin. At 1 kHz the send call's own time is
//! measured too (`try_put` for Leveret).
//!
//! ```text
//! cargo run --release -- [back-to-back count] [1 kHz count] [rounds] [ports]
//! ```
//!
//! With `ports` as the fourth argument only Leveret's rows run (for a
//! profile of the ports alone).
//!
//! Beside the latencies each row prints what a value cost in CPU
//! (`getrusage`): the receiver thread's CPU time and voluntary context
//! switches per value (`RUSAGE_THREAD`: what a spinning receive costs), and
//! the whole process's CPU time per value (`RUSAGE_SELF`: the sender, the
//! broker's workers and the receiver; in back-to-back mode it includes the
//! sender's spin waiting for the receiver).

use leveret_broker::Broker;
use leveret_ports::{Connector, InPort, OutPort, PortProfile, PortStatus};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{mpsc, Arc, OnceLock};
use std::time::{Duration, Instant};
use zenoh::Wait;

const SIZE: usize = 32;

fn origin() -> Instant {
    static ORIGIN: OnceLock<Instant> = OnceLock::new();
    *ORIGIN.get_or_init(Instant::now)
}

fn now_ns() -> u64 {
    origin().elapsed().as_nanos() as u64
}

/// A 32-byte value carrying its send time.
fn stamped(seq: u64) -> Vec<u8> {
    let mut value = vec![0u8; SIZE];
    value[..8].copy_from_slice(&now_ns().to_le_bytes());
    value[8..16].copy_from_slice(&seq.to_le_bytes());
    value
}

fn sent_at(value: &[u8]) -> u64 {
    u64::from_le_bytes(value[..8].try_into().expect("8 bytes"))
}

/// How a transport's sender and receiver are driven.
trait Sender: Send + 'static {
    /// Sends the value; false if the transport refused it.
    fn send(&mut self, value: Vec<u8>) -> bool;
}

trait Receiver: Send + 'static {
    /// The next value, blocking the thread; None when the run is over.
    fn recv(&mut self) -> Option<Vec<u8>>;
}

struct Results {
    latencies_ns: Vec<u64>,
    send_ns: Vec<u64>,
    refused: u64,
    /// The receiver thread's use over the run.
    receiver: Usage,
    /// The whole process's use over the run.
    process: Usage,
}

/// CPU time and voluntary context switches, from `getrusage`.
#[derive(Clone, Copy, Default)]
struct Usage {
    cpu_ns: u64,
    voluntary_switches: u64,
}

impl Usage {
    fn of(who: libc::c_int) -> Usage {
        // SAFETY: getrusage only writes the struct it is given.
        let mut usage: libc::rusage = unsafe { std::mem::zeroed() };
        let rc = unsafe { libc::getrusage(who, &mut usage) };
        assert_eq!(rc, 0, "getrusage");
        let ns = |t: libc::timeval| t.tv_sec as u64 * 1_000_000_000 + t.tv_usec as u64 * 1000;
        Usage {
            cpu_ns: ns(usage.ru_utime) + ns(usage.ru_stime),
            voluntary_switches: usage.ru_nvcsw as u64,
        }
    }

    fn thread() -> Usage {
        Usage::of(libc::RUSAGE_THREAD)
    }

    fn process() -> Usage {
        Usage::of(libc::RUSAGE_SELF)
    }

    fn since(self, start: Usage) -> Usage {
        Usage {
            cpu_ns: self.cpu_ns - start.cpu_ns,
            voluntary_switches: self.voluntary_switches - start.voluntary_switches,
        }
    }
}

enum Mode {
    BackToBack,
    Paced(Duration),
}

/// Runs `count` values through a sender and a receiver thread.
fn run(mut tx: impl Sender, mut rx: impl Receiver, count: u64, mode: Mode) -> Results {
    let received = Arc::new(AtomicU64::new(0));
    let receiver = {
        let received = received.clone();
        std::thread::spawn(move || {
            let mut latencies = Vec::with_capacity(count as usize);
            let start = Usage::thread();
            while latencies.len() < count as usize {
                let Some(value) = rx.recv() else { break };
                let at = now_ns();
                latencies.push(at.saturating_sub(sent_at(&value)));
                received.fetch_add(1, Ordering::Release);
            }
            (latencies, Usage::thread().since(start))
        })
    };
    let process_start = Usage::process();
    let mut send_ns = Vec::with_capacity(count as usize);
    let mut refused = 0;
    let start = Instant::now() + Duration::from_millis(5);
    for seq in 0..count {
        match mode {
            Mode::BackToBack => {
                // Spin until the previous value arrived (one in flight).
                let deadline = Instant::now() + Duration::from_secs(2);
                while received.load(Ordering::Acquire) < seq - refused {
                    std::hint::spin_loop();
                    if Instant::now() > deadline {
                        break;
                    }
                }
            }
            Mode::Paced(period) => {
                let at = start + period * seq as u32;
                let now = Instant::now();
                if at > now {
                    std::thread::sleep(at - now);
                }
            }
        }
        let value = stamped(seq);
        let before = Instant::now();
        let ok = tx.send(value);
        send_ns.push(before.elapsed().as_nanos() as u64);
        if !ok {
            refused += 1;
        }
    }
    // Give the receiver what is in flight, then end it.
    let deadline = Instant::now() + Duration::from_secs(2);
    while received.load(Ordering::Acquire) < count - refused && Instant::now() < deadline {
        std::thread::sleep(Duration::from_micros(100));
    }
    drop(tx);
    let (latencies_ns, receiver) = receiver.join().expect("receiver thread");
    Results {
        latencies_ns,
        send_ns,
        refused,
        receiver,
        process: Usage::process().since(process_start),
    }
}

fn percentile(sorted: &[u64], p: f64) -> f64 {
    if sorted.is_empty() {
        return f64::NAN;
    }
    let index = ((sorted.len() - 1) as f64 * p).round() as usize;
    sorted[index] as f64 / 1000.0
}

struct Row {
    transport: &'static str,
    mode: &'static str,
    count: u64,
    results: Results,
}

impl Row {
    fn print(&mut self) {
        self.results.latencies_ns.sort_unstable();
        self.results.send_ns.sort_unstable();
        let l = &self.results.latencies_ns;
        let s = &self.results.send_ns;
        let per_value = |x: u64| x as f64 / l.len().max(1) as f64;
        println!(
            "{:<22} {:<12} {:>6}/{:<6} {:>8.2} {:>8.2} {:>9.2} {:>10.2} {:>10.2} {:>9.2} {:>8.2} {:>9.2}",
            self.transport,
            self.mode,
            l.len(),
            self.count,
            percentile(l, 0.5),
            percentile(l, 0.99),
            percentile(l, 0.999),
            percentile(s, 0.5),
            percentile(s, 0.99),
            per_value(self.results.receiver.cpu_ns) / 1000.0,
            per_value(self.results.receiver.voluntary_switches),
            per_value(self.results.process.cpu_ns) / 1000.0,
        );
    }
}

// --- std::sync::mpsc

struct MpscTx(Option<mpsc::Sender<Vec<u8>>>);
struct MpscRx(mpsc::Receiver<Vec<u8>>);

impl Sender for MpscTx {
    fn send(&mut self, value: Vec<u8>) -> bool {
        self.0.as_ref().expect("open").send(value).is_ok()
    }
}

impl Receiver for MpscRx {
    fn recv(&mut self) -> Option<Vec<u8>> {
        self.0.recv().ok()
    }
}

fn mpsc_pair() -> (MpscTx, MpscRx) {
    let (tx, rx) = mpsc::channel();
    (MpscTx(Some(tx)), MpscRx(rx))
}

// --- Zenoh, one session

struct ZenohTx(zenoh::pubsub::Publisher<'static>);
struct ZenohRx(
    zenoh::pubsub::Subscriber<zenoh::handlers::FifoChannelHandler<zenoh::sample::Sample>>,
);

impl Sender for ZenohTx {
    fn send(&mut self, value: Vec<u8>) -> bool {
        self.0.put(value).wait().is_ok()
    }
}

impl Receiver for ZenohRx {
    fn recv(&mut self) -> Option<Vec<u8>> {
        // Bounded so the run ends even if a value is lost.
        match self.0.recv_timeout(Duration::from_secs(3)) {
            Ok(Some(sample)) => Some(sample.payload().to_bytes().into_owned()),
            _ => None,
        }
    }
}

fn zenoh_session() -> zenoh::Session {
    let mut config = zenoh::Config::default();
    for (key, value) in [
        ("mode", r#""peer""#),
        ("listen/endpoints", "[]"),
        ("connect/endpoints", "[]"),
        ("scouting/multicast/enabled", "false"),
        ("scouting/gossip/enabled", "false"),
    ] {
        config.insert_json5(key, value).expect("zenoh config");
    }
    zenoh::open(config).wait().expect("zenoh session")
}

fn zenoh_pair(session: &zenoh::Session, key: &'static str) -> (ZenohTx, ZenohRx) {
    let subscriber = session.declare_subscriber(key).wait().expect("subscriber");
    let publisher = session.declare_publisher(key).wait().expect("publisher");
    (ZenohTx(publisher), ZenohRx(subscriber))
}

// --- Leveret ports on an embedded broker

struct PortTx(OutPort<Vec<u8>>);
struct PortRx(InPort<Vec<u8>>);

/// When each value reached the in-port's intake (its `on_receive`
/// callbacks, before the buffer), as latency from the sender's stamp: the
/// part of the path before the hand-over to the application's thread.
/// Only for the pair that registers a callback: an in-port with one takes
/// its deliveries on the connection's reader task, not inline on the
/// broker's dispatching thread, so it is a row of its own.
type Intake = Arc<std::sync::Mutex<Vec<u64>>>;

impl Sender for PortTx {
    fn send(&mut self, value: Vec<u8>) -> bool {
        self.0.try_put(&value) == PortStatus::Ok
    }
}

impl Receiver for PortRx {
    fn recv(&mut self) -> Option<Vec<u8>> {
        self.0
            .recv_blocking(Duration::from_secs(3))
            .map(|sample| sample.value)
    }
}

fn ports_pair(
    runtime: &tokio::runtime::Runtime,
    connector: &Connector,
    queue: &str,
    busy_poll: Option<Duration>,
    timed_intake: bool,
) -> (PortTx, PortRx, Intake) {
    let mut profile = PortProfile::default().queue(queue).routing_key(queue);
    profile.busy_poll = busy_poll;
    let intake = Intake::default();
    runtime.block_on(async {
        let input = InPort::<Vec<u8>>::connect_with(connector.clone(), profile.clone())
            .await
            .expect("in-port");
        if timed_intake {
            let times = intake.clone();
            input.on_receive(move |sample| {
                let at = now_ns();
                times
                    .lock()
                    .expect("intake")
                    .push(at.saturating_sub(sent_at(&sample.value)));
            });
        }
        let output = OutPort::<Vec<u8>>::connect_with(connector.clone(), profile)
            .await
            .expect("out-port");
        (PortTx(output), PortRx(input), intake)
    })
}

fn main() {
    let mut args = std::env::args().skip(1);
    let back_to_back: u64 = args.next().map_or(20_000, |a| a.parse().expect("count"));
    let paced: u64 = args.next().map_or(3_000, |a| a.parse().expect("count"));
    let rounds: u32 = args.next().map_or(1, |a| a.parse().expect("rounds"));
    let ports_only = args.next().is_some_and(|a| a == "ports");
    origin();

    let runtime = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()
        .expect("runtime");
    let broker = Arc::new(
        runtime
            .block_on(Broker::builder().start())
            .expect("embedded broker"),
    );
    let connector = Connector::in_process(&broker);
    let session = zenoh_session();

    println!(
        "{:<22} {:<12} {:>13} {:>8} {:>8} {:>9} {:>10} {:>10} {:>9} {:>8} {:>9}",
        "transport",
        "mode",
        "received",
        "p50 µs",
        "p99 µs",
        "p99.9 µs",
        "send p50",
        "send p99",
        "rx cpu µs",
        "rx vcsw",
        "cpu µs"
    );
    for round in 0..rounds {
        for (mode_name, paced_at, count) in [
            ("back-to-back", None, back_to_back),
            ("1 kHz", Some(Duration::from_millis(1)), paced),
        ] {
            let mode = || paced_at.map_or(Mode::BackToBack, Mode::Paced);
            let queue = format!("latency-{round}-{mode_name}");
            let (tx, rx, _) = ports_pair(&runtime, &connector, &queue, None, false);
            // A warm-up pair, then the measured ones.
            run(tx, rx, 1000, Mode::BackToBack);
            for (transport, busy_poll, timed_intake) in [
                ("leveret ports", None, false),
                (
                    "leveret busy-poll 2ms",
                    Some(Duration::from_millis(2)),
                    false,
                ),
                ("leveret + on_receive", None, true),
            ] {
                let name = format!("{queue}-{}-{timed_intake}", busy_poll.is_some());
                let (tx, rx, intake) =
                    ports_pair(&runtime, &connector, &name, busy_poll, timed_intake);
                let results = run(tx, rx, count, mode());
                let refused = results.refused;
                Row {
                    transport,
                    mode: mode_name,
                    count,
                    results,
                }
                .print();
                if timed_intake {
                    let intake = std::mem::take(&mut *intake.lock().expect("intake"));
                    let results = Results {
                        latencies_ns: intake,
                        send_ns: Vec::new(),
                        refused: 0,
                        receiver: Usage::default(),
                        process: Usage::default(),
                    };
                    Row {
                        transport: "  └ put→on_receive",
                        mode: mode_name,
                        count,
                        results,
                    }
                    .print();
                }
                if refused > 0 {
                    println!("  ({transport}: {refused} try_put refused)");
                }
            }
            if ports_only {
                continue;
            }

            let key: &'static str = Box::leak(format!("latency/{round}/{count}").into_boxed_str());
            let (tx, rx) = zenoh_pair(&session, key);
            let results = run(tx, rx, count, mode());
            Row {
                transport: "zenoh (same session)",
                mode: mode_name,
                count,
                results,
            }
            .print();

            let (tx, rx) = mpsc_pair();
            let results = run(tx, rx, count, mode());
            Row {
                transport: "std::sync::mpsc",
                mode: mode_name,
                count,
                results,
            }
            .print();
        }
    }
    drop(session);
    if let Ok(broker) = Arc::try_unwrap(broker) {
        runtime.block_on(broker.shutdown());
    }
}
