//! The stall-budget harness (issue 12): an in-process broker alone on a
//! current-thread runtime of its own thread, a bystander connection on
//! that same thread whose round trips are measured in the thread's CPU
//! time while an attack runs ([`Probe`]), retries on a fresh broker
//! ([`within_bounds`]), and a connection written by hand that sends
//! thousands of methods in one write ([`Flood`]).
//!
//! Why CPU time: the bystander and the broker share one thread, so the
//! CPU time that thread spends between the bystander's publish and its
//! delivery is the broker's work that held the bystander up (its own
//! share, the attack's slices that ran in between, the runtime's turns).
//! Time the thread spent waiting for a CPU is not in it, so a loaded
//! machine cannot fail these tests; a wall clock would measure the
//! machine. Against an external broker (`LEVERET_TEST_AMQP_URL`) there is
//! no broker thread to measure: the bystander must still be served, and
//! its wall-clock round trips are reported, not asserted.

use super::*;
use bytes::{Bytes, BytesMut};
use leveret_broker::{Broker, Limits};
use leveret_protocol::{
    decode_frame, encode_content, encode_method, BasicConsume, BasicProperties, BasicPublish,
    ChannelOpen, ConnectionOpen, ConnectionStartOk, ConnectionTuneOk, FieldTable, Frame, Method,
    QueueDeclare, ShortStr, PROTOCOL_HEADER,
};
use std::future::Future;
use std::time::{Duration, Instant};
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::TcpStream;
use tokio::sync::{oneshot, watch};

/// The most broker-thread CPU time a bystander's round trip may take
/// while an attack runs, beyond the most it took just before (a few
/// hundred microseconds in a debug build): ten times the broker's budget
/// of about a millisecond per piece of work.
pub const WORST_ROUND_TRIP: Duration = Duration::from_millis(10);

/// `release` in a release build, `debug` in a debug one.
pub const fn sized(release: usize, debug: usize) -> usize {
    if cfg!(debug_assertions) {
        debug
    } else {
        release
    }
}

/// Taken by each test for its whole run: the tests measure latency, so
/// one's attack must not run beside another's probe.
static ONE_AT_A_TIME: tokio::sync::Mutex<()> = tokio::sync::Mutex::const_new(());

/// The broker under test: an in-process Leveret alone on its own thread
/// with the given limits, or
/// the external broker named by `LEVERET_TEST_AMQP_URL`.
pub struct Target {
    pub url: String,
    pub addr: String,
    /// The in-process broker's MQTT listener (`None` for an external
    /// broker).
    pub mqtt_addr: Option<std::net::SocketAddr>,
    /// The in-process broker's runtime, whose one thread the probe shares.
    runtime: Option<tokio::runtime::Handle>,
    /// The in-process broker's administration handle.
    admin: Option<leveret_broker::Admin>,
    stop: Option<tokio::sync::oneshot::Sender<()>>,
}

impl Target {
    pub async fn start(limits: Limits) -> Self {
        let external = std::env::var(leveret_tests::URL_ENV).is_ok_and(|u| !u.trim().is_empty());
        if external {
            let broker = broker().await;
            return Target {
                url: broker.url().to_owned(),
                addr: broker.addr(),
                mqtt_addr: None,
                runtime: None,
                admin: None,
                stop: None,
            };
        }
        let (started, addresses) = std::sync::mpsc::channel();
        let (stop, stopped) = tokio::sync::oneshot::channel::<()>();
        std::thread::spawn(move || {
            let runtime = tokio::runtime::Builder::new_current_thread()
                .enable_all()
                .build()
                .expect("runtime");
            runtime.block_on(async move {
                let any: std::net::SocketAddr = "127.0.0.1:0".parse().expect("static address");
                let builder = Broker::builder().limits(limits).mqtt_listen(any);
                let broker = TestBroker::leveret(builder).await;
                let addresses = (
                    broker.url().to_owned(),
                    broker.addr(),
                    broker.mqtt_addr(),
                    tokio::runtime::Handle::current(),
                    broker.admin().expect("in process"),
                );
                started.send(addresses).expect("the test waits");
                let _ = stopped.await;
                broker.stop().await;
            });
        });
        let (url, addr, mqtt_addr, runtime, admin) = addresses.recv().expect("broker starts");
        Target {
            url,
            addr,
            mqtt_addr,
            runtime: Some(runtime),
            admin: Some(admin),
            stop: Some(stop),
        }
    }

    /// Runs `work` with the in-process broker's administration handle on
    /// the broker's own thread, so that its slices are what the probe
    /// measures; `None` against an external broker.
    pub async fn on_broker_thread<Work, Done>(&self, work: Work) -> Option<Done::Output>
    where
        Work: FnOnce(leveret_broker::Admin) -> Done,
        Done: Future + Send + 'static,
        Done::Output: Send + 'static,
    {
        let (runtime, admin) = (self.runtime.as_ref()?, self.admin.clone()?);
        let task = runtime.spawn(work(admin));
        Some(
            within("work on the broker thread", task)
                .await
                .expect("ran"),
        )
    }

    pub async fn connect(&self) -> lp::Connection {
        within(
            "lapin connect",
            lp::Connection::connect(&self.url, lp::ConnectionProperties::default()),
        )
        .await
        .expect("connects")
    }

    pub async fn open(&self) -> (lp::Connection, lp::Channel) {
        let connection = self.connect().await;
        let channel = lp::channel(&connection).await;
        (connection, channel)
    }
}

impl Drop for Target {
    /// Asks the broker to stop, without waiting: a broker stuck in an
    /// attack (the failure this file looks for) must not hang the test.
    fn drop(&mut self) {
        if let Some(stop) = self.stop.take() {
            let _ = stop.send(());
        }
    }
}

/// Round trips of a bystander connection, back to back until stopped.
pub struct Probe {
    /// The worst round trip in the [`QUIET_PERIOD`] before the attack.
    quiet_worst: Duration,
    /// Whether round trips are in the broker thread's CPU time (an
    /// in-process broker) or in wall time (an external one, not asserted).
    cpu_time: bool,
    stop: watch::Sender<bool>,
    task: tokio::task::JoinHandle<(Duration, usize)>,
}

/// How long the probe measures the quiet broker before an attack.
pub const QUIET_PERIOD: Duration = Duration::from_millis(200);

impl Probe {
    /// Measures the quiet round trip, then probes until stopped: on the
    /// in-process broker's own thread, timed by that thread's CPU clock.
    pub async fn start(target: &Target) -> Probe {
        let (stop, stopped) = watch::channel(false);
        let (quiet, quiet_measured) = oneshot::channel();
        let cpu_time = target.runtime.is_some();
        let probing = bystander(target.addr.clone(), cpu_time, quiet, stopped);
        let task = match &target.runtime {
            Some(runtime) => runtime.spawn(probing),
            None => tokio::spawn(probing),
        };
        let quiet_worst = within("the probe's quiet round trips", quiet_measured)
            .await
            .expect("the probe measured the quiet broker");
        Probe {
            quiet_worst,
            cpu_time,
            stop,
            task,
        }
    }

    /// Stops probing; an error report unless the worst round trip during
    /// the attack stayed under [`WORST_ROUND_TRIP`] beyond the quiet worst
    /// (in the broker thread's CPU time; an external broker only has to
    /// have served the bystander).
    pub async fn finish(self, during: &str) -> Result<(), String> {
        let _ = self.stop.send(true);
        let (worst, count) = within("the probe", self.task).await.expect("probe ran");
        let quiet = self.quiet_worst;
        let clock = if self.cpu_time {
            "broker thread CPU time"
        } else {
            "wall time, not asserted against an external broker"
        };
        let report = format!(
            "{during}: {count} round trips, worst {worst:?} (quiet worst {quiet:?}; {clock})"
        );
        eprintln!("{report}");
        if !self.cpu_time || worst < WORST_ROUND_TRIP + quiet {
            Ok(())
        } else {
            Err(report)
        }
    }
}

/// The bystander: a hand-written connection (no client library, so all of
/// its work runs in this task) that publishes to its own queue and waits
/// for the delivery, back to back. Sends the worst quiet round trip on
/// `quiet` after [`QUIET_PERIOD`], then probes until `stopped`, at least
/// once; returns the worst round trip and how many it made.
async fn bystander(
    addr: String,
    cpu_time: bool,
    quiet: oneshot::Sender<Duration>,
    stopped: watch::Receiver<bool>,
) -> (Duration, usize) {
    let started = Instant::now();
    let now = move || {
        if cpu_time {
            thread_cpu_time()
        } else {
            started.elapsed()
        }
    };
    let mut connection = Flood::open(&addr).await;
    let declare = QueueDeclare {
        exclusive: true,
        ..Default::default()
    };
    connection.send(&frames(1, [declare.into()])).await;
    let Method::QueueDeclareOk(declared) = connection
        .expect(|m| matches!(m, Method::QueueDeclareOk(_)))
        .await
    else {
        unreachable!("matched above")
    };
    let queue = declared.queue.to_string_lossy().into_owned();
    let consume = BasicConsume {
        queue: declared.queue,
        consumer_tag: short("probe"),
        no_ack: true,
        ..Default::default()
    };
    connection.send(&frames(1, [consume.into()])).await;
    connection
        .expect(|m| matches!(m, Method::BasicConsumeOk(_)))
        .await;
    let ping = publish_frames(("", &queue), &BasicProperties::default(), b"ping");
    let mut quiet_worst = Duration::ZERO;
    while started.elapsed() < QUIET_PERIOD {
        quiet_worst = quiet_worst.max(connection.round_trip(&ping, now).await);
    }
    let _ = quiet.send(quiet_worst);
    let (mut worst, mut count) = (Duration::ZERO, 0);
    // At least one round trip, however quick the attack.
    loop {
        worst = worst.max(connection.round_trip(&ping, now).await);
        count += 1;
        if *stopped.borrow() {
            break (worst, count);
        }
    }
}

/// Attempts at an attack, each on a fresh broker, before a test fails.
pub const ATTEMPTS: usize = 5;

/// Runs `attack` on a fresh broker until a bystander's round trips stay
/// within bounds during it, at most [`ATTEMPTS`] times; fails with every
/// attempt's report. A broker that stalls on an input stalls on every
/// attempt (the blow-ups this file reproduces stall for seconds or never
/// finish), while CPU time that is not the broker's doing (page faults on
/// memory first touched, caches cold after the thread moved to another
/// CPU) does not repeat at will.
pub async fn within_bounds<Attack, Done>(limits: Limits, attack: Attack)
where
    Attack: Fn(Target) -> Done,
    Done: Future<Output = Result<(), String>>,
{
    let _alone = ONE_AT_A_TIME.lock().await;
    let mut reports = Vec::new();
    for _ in 0..ATTEMPTS {
        match attack(Target::start(limits.clone()).await).await {
            Ok(()) => return,
            Err(report) => reports.push(report),
        }
    }
    panic!(
        "a bystander's round trip took more than {WORST_ROUND_TRIP:?} of the broker thread's CPU time beyond the quiet worst on every attempt:\n{}",
        reports.join("\n")
    );
}

/// A connection written by hand, to send thousands of methods in one
/// write, as a hostile client would, with no client library in between.
pub struct Flood {
    socket: TcpStream,
    buf: BytesMut,
}

impl Flood {
    /// Logs in as guest on `/` and opens channel 1.
    pub async fn open(addr: &str) -> Flood {
        let socket = tmo!(TcpStream::connect(addr)).expect("tcp connect");
        let mut flood = Flood {
            socket,
            buf: BytesMut::new(),
        };
        flood.send(PROTOCOL_HEADER).await;
        flood
            .expect(|m| matches!(m, Method::ConnectionStart(_)))
            .await;
        let start_ok = ConnectionStartOk {
            client_properties: FieldTable::new(),
            mechanism: ShortStr::from_static("PLAIN"),
            response: Bytes::from_static(b"\0guest\0guest"),
            locale: ShortStr::from_static("en_US"),
        };
        flood.send(&frames(0, [start_ok.into()])).await;
        let Method::ConnectionTune(tune) = flood
            .expect(|m| matches!(m, Method::ConnectionTune(_)))
            .await
        else {
            unreachable!("matched above")
        };
        let tune_ok = ConnectionTuneOk {
            channel_max: tune.channel_max,
            frame_max: tune.frame_max,
            heartbeat: 0,
        };
        let open = ConnectionOpen {
            virtual_host: ShortStr::from_static("/"),
            ..Default::default()
        };
        flood.send(&frames(0, [tune_ok.into(), open.into()])).await;
        flood
            .expect(|m| matches!(m, Method::ConnectionOpenOk(_)))
            .await;
        flood
            .send(&frames(1, [ChannelOpen::default().into()]))
            .await;
        flood
            .expect(|m| matches!(m, Method::ChannelOpenOk(_)))
            .await;
        flood
    }

    /// Publishes `count` copies of `body` with `properties` through
    /// `exchange` with `key` on channel 1, without confirms, a few thousand
    /// per write; then a round trip on the same channel (queue.declare
    /// passive of `queue`), so every one has been routed when it returns
    /// `queue`'s message count.
    pub async fn publish_many(
        &mut self,
        (exchange, key): (&str, &str),
        count: usize,
        properties: &BasicProperties,
        body: &[u8],
        queue: &str,
    ) -> u32 {
        let one = publish_frames((exchange, key), properties, body);
        const PER_WRITE: usize = 4096;
        let mut sent = 0;
        while sent < count {
            let batch = PER_WRITE.min(count - sent);
            let mut buf = BytesMut::with_capacity(one.len() * batch);
            for _ in 0..batch {
                buf.extend_from_slice(&one);
            }
            self.send(&buf).await;
            sent += batch;
        }
        self.message_count(queue).await
    }

    /// `queue`'s message count, by queue.declare passive on channel 1.
    pub async fn message_count(&mut self, queue: &str) -> u32 {
        let passive = QueueDeclare {
            queue: short(queue),
            passive: true,
            ..Default::default()
        };
        self.send(&frames(1, [passive.into()])).await;
        let Method::QueueDeclareOk(ok) = self
            .expect(|m| matches!(m, Method::QueueDeclareOk(_)))
            .await
        else {
            unreachable!("matched above")
        };
        ok.message_count
    }

    pub async fn send(&mut self, bytes: &[u8]) {
        tmo!(self.socket.write_all(bytes)).expect("write");
    }

    /// Sends `publish` (to a queue this connection consumes from without
    /// acks) and waits for its delivery; how long that took by `clock`.
    async fn round_trip(&mut self, publish: &[u8], clock: impl Fn() -> Duration) -> Duration {
        let sent = clock();
        self.send(publish).await;
        self.expect(|m| matches!(m, Method::BasicDeliver(_))).await;
        clock() - sent
    }

    /// Reads methods until one that `wanted` accepts.
    pub async fn expect(&mut self, wanted: impl Fn(&Method) -> bool) -> Method {
        loop {
            match decode_frame(&mut self.buf, 0).expect("the broker sends valid frames") {
                Some(Frame::Method { method, .. }) if wanted(&method) => return method,
                Some(Frame::Method { method, .. }) => panic!("unexpected {method:?}"),
                Some(_) => continue,
                None => {
                    let read = tmo!(self.socket.read_buf(&mut self.buf)).expect("read");
                    assert_ne!(read, 0, "the broker closed the connection");
                }
            }
        }
    }
}

/// A basic.publish on channel 1 with its header and body, encoded.
pub fn publish_frames(
    (exchange, key): (&str, &str),
    properties: &BasicProperties,
    body: &[u8],
) -> BytesMut {
    let mut property_bytes = BytesMut::new();
    properties.encode(&mut property_bytes);
    let publish: Method = BasicPublish {
        exchange: short(exchange),
        routing_key: short(key),
        ..Default::default()
    }
    .into();
    let mut one = BytesMut::new();
    encode_method(1, &publish, &mut one);
    encode_content(1, 60, &property_bytes, body, 0, &mut one);
    one
}

/// Method frames, encoded one after the other.
pub fn frames(channel: u16, methods: impl IntoIterator<Item = Method>) -> BytesMut {
    let mut buf = BytesMut::new();
    for method in methods {
        encode_method(channel, &method, &mut buf);
    }
    buf
}

pub fn short(text: &str) -> ShortStr {
    ShortStr::try_from(text).expect("short string")
}
