//! The heap an idle connection holds, measured by a counting allocator
//! (the live heap before and after many connections settle):
//! - an idle MQTT session (issue 32's idle-connection goal: 10,000 idle
//!   connections with a subscription each in at most 100 MB): [`SESSIONS`]
//!   raw 3.1.1 clients connect and subscribe at QoS 1 (the benchmark's
//!   idle clients, `perf/mqtt-throughput`);
//! - an AMQP connection (heartbeat 1 s) and an MQTT session that had a
//!   burst each way and then keep hearing from their client every 300 ms
//!   (heartbeats, PINGREQs): the buffers and the queue's and channel's
//!   room the burst grew are given back all the same.
//!
//! A change that makes each connection hold far more fails here. The
//! bounds are generous; the figures themselves are measured in `perf/`.

#[macro_use]
mod common;

use bytes::{Bytes, BytesMut};
use common::raw::{publish_frames, short, Method, Raw};
use common::*;
use leveret_broker::{Broker, BrokerHandle, Limits};
use leveret_mqtt::{
    decode_packet, Connect, Delivery, MqttString, Packet, ProtocolVersion, Publish, QoS,
    ReasonCode, SubAck, Subscribe, Subscription, SubscriptionOptions, TopicFilter, TopicName,
};
use leveret_protocol::{BasicAck, BasicConsume, BasicProperties, Frame, QueueDeclare};
use std::alloc::{GlobalAlloc, Layout, System};
use std::net::SocketAddr;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::Arc;
use std::time::Duration;
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::TcpStream;

/// Held by every test of this file for its whole run.
static SERIAL: tokio::sync::Mutex<()> = tokio::sync::Mutex::const_new(());

/// Idle sessions opened and measured together.
const SESSIONS: usize = 200;
/// The live heap an idle session with one subscription may hold, the
/// client's end of its socket in this process included. A debug build
/// holds about 12.1 KiB since the AMQP connection's outbox is a queue
/// that grows from nothing and gives its room back when the session goes
/// idle (`leveret_protocol::handoff`, not a tokio channel's block of 32
/// items); 14.5 KiB (a release build about as much) since the
/// session's and its AMQP connection's futures hold no room for their
/// set-up and close phases or their arguments and an idle session's read
/// buffer is parked at 64 bytes; 19 KiB before that, since the link's
/// queue of items to the AMQP connection grows from nothing
/// (`leveret_protocol::handoff`, not a tokio channel's block of 32 items)
/// and its frame queues hold a method's frame nowhere; 25 KiB before
/// that, 39 KiB before the rare phases of the session and of its AMQP
/// connection were boxed futures, the outbox's items small, the
/// connection's channels and the session's will boxed and the CONNECT no
/// longer kept, and 103 KiB before the sessions gave their read buffers
/// back when idle: this bound refuses all five.
const PER_SESSION_CAP: usize = 13 * 1024;

/// The system allocator, counting the bytes it holds live for this
/// process, in all and by the size of the allocations.
struct LiveHeap;

static LIVE_HEAP_BYTES: AtomicUsize = AtomicUsize::new(0);

/// Size classes of live allocations: class `c` holds the sizes up to
/// `2^c` bytes (class 0: up to 1 byte), the last one everything larger.
const SIZE_CLASSES: usize = 24;

/// Live allocations and their bytes by size class.
static LIVE_BY_CLASS: [(AtomicUsize, AtomicUsize); SIZE_CLASSES] =
    [const { (AtomicUsize::new(0), AtomicUsize::new(0)) }; SIZE_CLASSES];

fn size_class(size: usize) -> usize {
    (size.max(1).next_power_of_two().trailing_zeros() as usize).min(SIZE_CLASSES - 1)
}

fn count_alloc(size: usize) {
    LIVE_HEAP_BYTES.fetch_add(size, Ordering::Relaxed);
    let (count, bytes) = &LIVE_BY_CLASS[size_class(size)];
    count.fetch_add(1, Ordering::Relaxed);
    bytes.fetch_add(size, Ordering::Relaxed);
}

fn count_dealloc(size: usize) {
    LIVE_HEAP_BYTES.fetch_sub(size, Ordering::Relaxed);
    let (count, bytes) = &LIVE_BY_CLASS[size_class(size)];
    count.fetch_sub(1, Ordering::Relaxed);
    bytes.fetch_sub(size, Ordering::Relaxed);
}

// SAFETY: every call is forwarded unchanged to `System`; the counters are
// the only addition.
unsafe impl GlobalAlloc for LiveHeap {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        let block = System.alloc(layout);
        if !block.is_null() {
            count_alloc(layout.size());
        }
        block
    }
    unsafe fn alloc_zeroed(&self, layout: Layout) -> *mut u8 {
        let block = System.alloc_zeroed(layout);
        if !block.is_null() {
            count_alloc(layout.size());
        }
        block
    }
    unsafe fn dealloc(&self, block: *mut u8, layout: Layout) {
        System.dealloc(block, layout);
        count_dealloc(layout.size());
    }
    unsafe fn realloc(&self, block: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        let moved = System.realloc(block, layout, new_size);
        if !moved.is_null() {
            count_dealloc(layout.size());
            count_alloc(new_size);
        }
        moved
    }
}

#[global_allocator]
static ALLOCATOR: LiveHeap = LiveHeap;

/// Live allocations and bytes by size class, now.
fn live_by_class() -> [(usize, usize); SIZE_CLASSES] {
    std::array::from_fn(|class| {
        let (count, bytes) = &LIVE_BY_CLASS[class];
        (count.load(Ordering::Relaxed), bytes.load(Ordering::Relaxed))
    })
}

/// Prints what `sessions` sessions added between `before` and `after`, per
/// session and by size class (with `--nocapture`): where the heap goes.
fn print_by_class(
    before: &[(usize, usize); SIZE_CLASSES],
    after: &[(usize, usize); SIZE_CLASSES],
    sessions: usize,
) {
    println!("size class      allocations/session   bytes/session");
    for class in 0..SIZE_CLASSES {
        let count = after[class].0 as f64 - before[class].0 as f64;
        let bytes = after[class].1 as f64 - before[class].1 as f64;
        if count != 0.0 || bytes != 0.0 {
            let n = sessions as f64;
            println!(
                "<= {:>9}   {:>18.2}   {:>13.0}",
                1usize << class,
                count / n,
                bytes / n
            );
        }
    }
}

fn live_heap() -> usize {
    LIVE_HEAP_BYTES.load(Ordering::Relaxed)
}

async fn start() -> BrokerHandle {
    let any: SocketAddr = "127.0.0.1:0".parse().unwrap();
    Broker::builder()
        .listen(any)
        .mqtt_listen(any)
        .user("robot", "secret")
        .permission("robot", "/", leveret_broker::Permission::full())
        .limits(Limits::default())
        .start()
        .await
        .expect("broker starts")
}

fn mqtt_string(text: &str) -> MqttString {
    MqttString::from_utf8(Bytes::copy_from_slice(text.as_bytes())).unwrap()
}

/// A 3.1.1 client that connects (clean session, with `keep_alive`
/// seconds), subscribes to `idle/N/#` at QoS 1 and waits for both
/// acknowledgements, as the benchmark's idle clients do (with no
/// keepalive).
async fn idle_session(port: u16, index: usize, keep_alive: u16) -> TcpStream {
    let mut socket = tmo!(TcpStream::connect(("127.0.0.1", port))).unwrap();
    let version = ProtocolVersion::V3_1_1;
    let mut out = BytesMut::new();
    Packet::Connect(Box::new(Connect {
        version,
        clean_start: true,
        keep_alive,
        properties: Default::default(),
        client_id: mqtt_string(&format!("idle-{index}")),
        will: None,
        username: Some(mqtt_string("robot")),
        password: Some(Bytes::from_static(b"secret")),
    }))
    .encode(version, &mut out)
    .unwrap();
    Packet::Subscribe(Subscribe {
        packet_id: std::num::NonZeroU16::MIN,
        properties: Default::default(),
        subscriptions: vec![Subscription {
            filter: TopicFilter::new(mqtt_string(&format!("idle/{index}/#"))).unwrap(),
            options: SubscriptionOptions {
                qos: QoS::AtLeastOnce,
                ..Default::default()
            },
        }],
    })
    .encode(version, &mut out)
    .unwrap();
    tmo!(socket.write_all(&out)).unwrap();
    let mut buf = BytesMut::with_capacity(64);
    let mut acknowledged = (false, false);
    while acknowledged != (true, true) {
        match decode_packet(&mut buf, version, 1024).unwrap() {
            Some(Packet::ConnAck(ack)) => {
                assert_eq!(ack.reason, ReasonCode::Success);
                acknowledged.0 = true;
            }
            Some(Packet::SubAck(SubAck { reasons, .. })) => {
                assert_eq!(reasons, [ReasonCode::GrantedQos1]);
                acknowledged.1 = true;
            }
            Some(other) => panic!("unexpected {other:?}"),
            None => assert!(tmo!(socket.read_buf(&mut buf)).unwrap() > 0, "closed"),
        }
    }
    socket
}

#[both_runtimes]
async fn an_idle_session_with_a_subscription_holds_a_bounded_heap() {
    // The heap is the process's: no other test may allocate meanwhile.
    let _serial = SERIAL.lock().await;
    let handle = start().await;
    let port = handle.mqtt_addrs()[0].port();
    // One session first, so that what the first one starts (the
    // listener's and the vhost's lazily built state) is not counted.
    let warm = idle_session(port, SESSIONS, 0).await;
    tokio::time::sleep(Duration::from_millis(200)).await;
    let before = live_heap();
    let before_by_class = live_by_class();
    let mut sessions = Vec::with_capacity(SESSIONS);
    for index in 0..SESSIONS {
        sessions.push(idle_session(port, index, 0).await);
    }
    // The sessions settle into their idle state: their read buffers are
    // given back after a second without reads (polled, not slept for: a
    // loaded machine runs the timers late; `within`'s hang limit fails a
    // session that never gives them back).
    let per_session = || live_heap().saturating_sub(before) / SESSIONS;
    within("idle sessions give back their buffers", async {
        while per_session() > PER_SESSION_CAP {
            tokio::time::sleep(Duration::from_millis(100)).await;
        }
    })
    .await;
    // Still so a while later: what an idle session holds stays bounded.
    tokio::time::sleep(Duration::from_secs(2)).await;
    let per_session = per_session();
    println!("live heap per idle session: {per_session} bytes");
    print_by_class(&before_by_class, &live_by_class(), SESSIONS);
    assert!(
        per_session <= PER_SESSION_CAP,
        "an idle MQTT session holds {per_session} bytes of heap (at most {PER_SESSION_CAP})"
    );
    drop((warm, sessions));
    handle.shutdown().await;
}

/// AMQP connections, or MQTT sessions, that burst and then idle together.
const CONNECTIONS: usize = 20;
/// Messages each connection publishes and then consumes in one go.
const BURST: usize = 300;
/// Their body size: copied into the write buffer, not written by
/// reference.
const BURST_BODY: usize = 2048;
/// The heartbeat the AMQP connections ask for, seconds: one a second from
/// the broker, and the client's more often (at 300 ms), as clients send
/// theirs at half the interval or less.
const HEARTBEAT: u16 = 1;
/// The live heap an AMQP connection may hold once idle after its burst,
/// its queue, channel and consumer and the client's end of its socket
/// included (9.4 KiB measured). A burst grows the broker's read buffer
/// to 64 KiB, its write buffer beyond 128 KiB, the queue's room for
/// ready messages and the channel's for unacked ones to 20 and 32 KiB:
/// any one of them kept refuses this bound.
const PER_CONNECTION_CAP: usize = 24 * 1024;

/// A connection with a 1 s heartbeat that has published [`BURST`]
/// messages in one write, consumed them all and acked them with one
/// multiple ack, holding none of them in its own buffer afterwards.
async fn burst_connection(broker: &TestBroker, index: usize) -> Raw {
    let mut raw = Raw::open_with_heartbeat(broker, HEARTBEAT).await;
    raw.open_channel(1).await;
    let queue = format!("burst-{index}");
    let declare = QueueDeclare {
        queue: short(&queue),
        exclusive: true,
        ..Default::default()
    };
    raw.call(1, declare, |m| matches!(m, Method::QueueDeclareOk(_)))
        .await;
    let body = vec![index as u8; BURST_BODY];
    let mut frames = BytesMut::new();
    for _ in 0..BURST {
        frames.extend_from_slice(&publish_frames(
            1,
            "",
            &queue,
            &BasicProperties::default(),
            &body,
            raw.frame_max,
        ));
    }
    raw.send_bytes(&frames).await;
    let consume = BasicConsume {
        queue: short(&queue),
        ..Default::default()
    };
    raw.call(1, consume, |m| matches!(m, Method::BasicConsumeOk(_)))
        .await;
    let mut received = 0;
    while received < BURST_BODY * BURST {
        if let Frame::Body { payload, .. } = raw.frame().await {
            received += payload.len();
        }
    }
    let ack = BasicAck {
        delivery_tag: BURST as u64,
        multiple: true,
    };
    raw.send(1, ack).await;
    raw.buf = BytesMut::new();
    raw
}

/// The live heap an MQTT session may hold once idle after its burst, the
/// client's end of its socket included: 17.1-20.8 KiB measured, 5.4-9.2
/// KiB more than an idle session that had no burst (an allocation of 4 to
/// 8 KiB in most sessions that this test does not yet place). The
/// session's read buffer of 64 KiB, kept, refuses it.
const PER_PINGING_SESSION_CAP: usize = 32 * 1024;

/// A session (keepalive 10 s: what matters is that it pings more often
/// than a second, not when the broker would give up on it) that has
/// published [`BURST`] QoS 0
/// messages to its own subscription in one write and read them all back,
/// holding none of them in its own buffer afterwards.
async fn burst_session(port: u16, index: usize) -> TcpStream {
    let mut socket = idle_session(port, index, 10).await;
    let version = ProtocolVersion::V3_1_1;
    let mut out = BytesMut::new();
    for _ in 0..BURST {
        Packet::Publish(Publish {
            dup: false,
            delivery: Delivery::AtMostOnce,
            retain: false,
            topic: TopicName::new(mqtt_string(&format!("idle/{index}/burst"))).unwrap(),
            properties: Default::default(),
            payload: Bytes::from(vec![index as u8; BURST_BODY]),
        })
        .encode(version, &mut out)
        .unwrap();
    }
    tmo!(socket.write_all(&out)).unwrap();
    let mut buf = BytesMut::new();
    let mut received = 0;
    while received < BURST {
        match decode_packet(&mut buf, version, 1 << 16).unwrap() {
            Some(Packet::Publish(publish)) => {
                assert_eq!(publish.payload.len(), BURST_BODY);
                received += 1;
            }
            Some(other) => panic!("unexpected {other:?}"),
            None => assert!(tmo!(socket.read_buf(&mut buf)).unwrap() > 0, "closed"),
        }
    }
    socket
}

/// An AMQP heartbeat frame.
const AMQP_HEARTBEAT: [u8; 8] = [8, 0, 0, 0, 0, 0, 0, 0xCE];
/// An MQTT PINGREQ.
const PINGREQ: [u8; 2] = [0xC0, 0];

/// Sockets a task of their own keeps talking to the broker, `beat` to
/// each every 300 ms, whatever the test is doing meanwhile (setting up
/// the next connection, measuring): none is closed for silence, and the
/// broker reads something from each every 300 ms.
struct KeptTalking {
    sockets: Arc<tokio::sync::Mutex<Vec<TcpStream>>>,
    task: tokio::task::JoinHandle<()>,
}

impl KeptTalking {
    fn start(beat: &'static [u8]) -> KeptTalking {
        let sockets = Arc::new(tokio::sync::Mutex::new(Vec::<TcpStream>::new()));
        let talking = Arc::clone(&sockets);
        let task = tokio::spawn(async move {
            loop {
                for socket in talking.lock().await.iter_mut() {
                    tmo!(socket.write_all(beat)).expect("the broker reads");
                }
                tokio::time::sleep(Duration::from_millis(300)).await;
            }
        });
        KeptTalking { sockets, task }
    }

    async fn add(&self, socket: TcpStream) {
        self.sockets.lock().await.push(socket);
    }

    /// Stops the task; panics if it failed (a write the broker refused).
    async fn stop(self) {
        self.task.abort();
        if let Err(ended) = self.task.await {
            assert!(!ended.is_panic(), "a keep-alive write failed: {ended}");
        }
    }
}

/// Waits until the [`CONNECTIONS`] connections opened since `before`
/// hold at most `cap` bytes each, then a while longer, and checks they
/// still do. Prints the figure and where it goes (with `--nocapture`).
async fn settles_within(
    what: &str,
    before: usize,
    before_by_class: &[(usize, usize); SIZE_CLASSES],
    cap: usize,
) {
    let per_connection = || live_heap().saturating_sub(before) / CONNECTIONS;
    // Polled, not slept for: a loaded machine runs the timers late.
    within(what, async {
        while per_connection() > cap {
            tokio::time::sleep(Duration::from_millis(100)).await;
        }
    })
    .await;
    tokio::time::sleep(Duration::from_secs(2)).await;
    let per_connection = per_connection();
    println!("{what}: {per_connection} bytes a connection");
    print_by_class(before_by_class, &live_by_class(), CONNECTIONS);
    assert!(
        per_connection <= cap,
        "{what}: {per_connection} bytes a connection (at most {cap})"
    );
}

#[both_runtimes]
async fn mqtt_sessions_pinging_every_300_ms_give_a_bursts_room_back() {
    let _serial = SERIAL.lock().await;
    let handle = start().await;
    let port = handle.mqtt_addrs()[0].port();
    let talking = KeptTalking::start(&PINGREQ);
    // The first session, settled (its burst's room given back), so that
    // what the first one starts is not counted.
    talking.add(burst_session(port, CONNECTIONS).await).await;
    tokio::time::sleep(Duration::from_millis(2500)).await;
    let before = live_heap();
    let before_by_class = live_by_class();
    for index in 0..CONNECTIONS {
        talking.add(burst_session(port, index).await).await;
    }
    settles_within(
        "pinging MQTT sessions after a burst",
        before,
        &before_by_class,
        PER_PINGING_SESSION_CAP,
    )
    .await;
    assert_eq!(
        handle.admin().overview().object_totals.connections,
        CONNECTIONS as u64 + 1,
        "every session is open: none was closed for silence"
    );
    talking.stop().await;
    handle.shutdown().await;
}

#[both_runtimes]
async fn amqp_connections_exchanging_heartbeats_give_a_bursts_room_back() {
    let _serial = SERIAL.lock().await;
    let broker = TestBroker::leveret(Broker::builder()).await;
    let admin = broker.admin().expect("in-process broker");
    let talking = KeptTalking::start(&AMQP_HEARTBEAT);
    // The first connection, settled (its burst's room given back), so
    // that what the first one starts is not counted.
    talking
        .add(burst_connection(&broker, CONNECTIONS).await.socket)
        .await;
    tokio::time::sleep(Duration::from_millis(2500)).await;
    let before = live_heap();
    let before_by_class = live_by_class();
    for index in 0..CONNECTIONS {
        talking
            .add(burst_connection(&broker, index).await.socket)
            .await;
    }
    settles_within(
        "idle AMQP connections after a burst",
        before,
        &before_by_class,
        PER_CONNECTION_CAP,
    )
    .await;
    assert_eq!(
        admin.overview().object_totals.connections,
        CONNECTIONS as u64 + 1,
        "every connection is open: none was closed for silence"
    );
    talking.stop().await;
}
