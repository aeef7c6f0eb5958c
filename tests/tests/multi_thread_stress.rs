//! The broker embedded on a multi-thread runtime (4 workers) under load from
//! many connections at once, checked frame by frame as a client sees them.
//!
//! Each of [`CONNECTIONS`] raw connections has a consuming channel with
//! [`QUEUES_PER_CHANNEL`] consumers (per-consumer prefetch, channel-wide
//! `global` prefetch, both, or a no-ack consumer among them) and a publishing
//! channel in confirm mode that spreads its messages over every connection's
//! queues, so each consuming channel is fed by several queues dispatching on
//! several threads at once. Consumers settle with a mix of multiple-acks and
//! single acks. What must hold:
//!
//! - delivery tags on every channel go up by exactly 1 in the order the
//!   client reads them (no tag skipped, none overtaken by a later one);
//! - the unacked deliveries the client holds never exceed a consumer's
//!   prefetch nor the channel's global prefetch (the client counts an ack as
//!   done when it sends it, so its count is never above the broker's; a
//!   full window is held for one round trip before it is settled, so a
//!   delivery let out beyond the limit is seen);
//! - publisher confirms come in order (each ack past the previous one, a
//!   single ack exactly the next tag), none is a nack, every publish is
//!   confirmed;
//! - every message is delivered exactly once, never marked redelivered.
//!
//! The connections speak raw frames (encoded with `leveret_protocol`) because
//! client libraries split a channel's deliveries into per-consumer streams
//! and hide the order tags and confirms arrived in. The test runs on a
//! multi-thread runtime only: that is the point of it (the rest of the suite
//! runs on both).

#[macro_use]
mod common;

use bytes::{Buf, Bytes, BytesMut};
use common::raw::{
    method_frame, publish_frames, short, BasicProperties, Frame, Method, Raw, ShortStr,
};
use common::*;
use leveret_protocol::{
    decode_frame, BasicAck, BasicConsume, BasicQos, ConfirmSelect, ConnectionClose, QueueDeclare,
};
use std::collections::{BTreeMap, HashSet};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::tcp::{OwnedReadHalf, OwnedWriteHalf};
use tokio::sync::{mpsc, watch, Notify};
use tokio::task::JoinSet;

const CONNECTIONS: usize = 16;
const QUEUES_PER_CHANNEL: usize = 3;
const MESSAGES_PER_PUBLISHER: u64 = 2500;
/// Unconfirmed publishes a publisher lets out before waiting for confirms.
const CONFIRM_WINDOW: u64 = 200;
/// How long the whole exchange may take before the test calls it a stall.
const STALL: Duration = Duration::from_secs(60);

const CONSUMING: u16 = 1;
const PUBLISHING: u16 = 2;

#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn many_connections_see_ordered_tags_bounded_prefetch_and_ordered_confirms() {
    let b = broker().await;
    let mut connections = Vec::with_capacity(CONNECTIONS);
    for index in 0..CONNECTIONS {
        connections.push(Connection::open(&b, index).await);
    }
    let queues: Arc<Vec<String>> = Arc::new(
        connections
            .iter()
            .flat_map(|c| c.plan.queues.iter().cloned())
            .collect(),
    );

    let progress = Arc::new(Progress::default());
    let mut readers = JoinSet::new();
    let mut publishers = JoinSet::new();
    let mut writers = Vec::with_capacity(CONNECTIONS);
    for connection in connections {
        let (reader, writer) = connection.raw.socket.into_split();
        let (frames, outgoing) = mpsc::unbounded_channel::<Bytes>();
        tokio::spawn(write_all(writer, outgoing));
        let (confirmed_tx, confirmed_rx) = watch::channel(0u64);
        let checker = Checker::new(connection.index, connection.plan, confirmed_tx);
        readers.spawn(read_and_check(
            reader,
            connection.raw.buf,
            checker,
            frames.clone(),
            Arc::clone(&progress),
        ));
        writers.push(frames.clone());
        publishers.spawn(publish_all(
            connection.index,
            Arc::clone(&queues),
            frames,
            confirmed_rx,
        ));
    }

    let expected = CONNECTIONS as u64 * MESSAGES_PER_PUBLISHER;
    let started = Instant::now();
    loop {
        let notified = progress.changed.notified();
        let delivered = progress.delivered.load(Ordering::SeqCst);
        let confirmed = progress.confirmed.load(Ordering::SeqCst);
        if delivered == expected && confirmed == expected {
            break;
        }
        tokio::select! {
            () = notified => {}
            ended = readers.join_next() => panic!("a connection ended early: {ended:?}"),
            () = tokio::time::sleep(STALL.saturating_sub(started.elapsed())) => panic!(
                "stalled: {delivered} of {expected} delivered, {confirmed} confirmed"
            ),
        }
    }
    while let Some(published) = publishers.join_next().await {
        published.expect("publisher finished");
    }

    // Every connection closes; each reader returns what it received.
    for frames in writers {
        let close = ConnectionClose {
            reply_code: 200,
            reply_text: short("done"),
            class_id: 0,
            method_id: 0,
        };
        send(&frames, 0, close.into());
    }
    let mut seen = HashSet::with_capacity(expected as usize);
    while let Some(ended) = readers.join_next().await {
        let received = ended.expect("reader did not panic");
        for id in received {
            assert!(seen.insert(id), "message {id:#x} delivered twice");
        }
    }
    assert_eq!(seen.len() as u64, expected, "every message delivered once");
    for publisher in 0..CONNECTIONS as u64 {
        for seq in 0..MESSAGES_PER_PUBLISHER {
            assert!(seen.contains(&message_id(publisher, seq)));
        }
    }
    b.stop().await;
}

/// Counters the readers raise and the test waits on.
#[derive(Default)]
struct Progress {
    delivered: AtomicU64,
    confirmed: AtomicU64,
    changed: Notify,
}

impl Progress {
    fn add(&self, counter: &AtomicU64, n: u64) {
        counter.fetch_add(n, Ordering::SeqCst);
        self.changed.notify_one();
    }
}

/// How one connection's consuming channel is set up.
struct Plan {
    /// basic.qos with global=false (0 = none): each consumer's limit.
    per_consumer: u16,
    /// basic.qos with global=true (0 = none): the channel's limit.
    global: u16,
    /// The queues it consumes from, consumer `k` on `queues[k]`.
    queues: Vec<String>,
    /// Which consumers take deliveries without acks.
    no_ack: Vec<bool>,
}

impl Plan {
    /// Four kinds, in turn: per-consumer prefetch, global prefetch, both,
    /// and both with a no-ack consumer beside (its deliveries take tags but
    /// no credit).
    fn for_connection(index: usize) -> Plan {
        let (per_consumer, global, with_no_ack) = match index % 4 {
            0 => (5, 0, false),
            1 => (0, 4, false),
            2 => (3, 5, false),
            _ => (4, 6, true),
        };
        Plan {
            per_consumer,
            global,
            queues: (0..QUEUES_PER_CHANNEL)
                .map(|k| unique(&format!("stress-{index}-{k}")))
                .collect(),
            no_ack: (0..QUEUES_PER_CHANNEL)
                .map(|k| with_no_ack && k == 0)
                .collect(),
        }
    }
}

/// A raw connection, its channels open and its consumers started.
struct Connection {
    index: usize,
    raw: Raw,
    plan: Plan,
}

impl Connection {
    async fn open(b: &TestBroker, index: usize) -> Connection {
        let mut raw = Raw::open(b).await;
        let plan = Plan::for_connection(index);
        raw.open_channel(CONSUMING).await;
        raw.open_channel(PUBLISHING).await;
        for queue in &plan.queues {
            let declare = QueueDeclare {
                queue: short(queue),
                ..Default::default()
            };
            raw.call(CONSUMING, declare, |m| {
                matches!(m, Method::QueueDeclareOk(_))
            })
            .await;
        }
        for (prefetch_count, global) in [(plan.per_consumer, false), (plan.global, true)] {
            if prefetch_count > 0 {
                let qos = BasicQos {
                    prefetch_size: 0,
                    prefetch_count,
                    global,
                };
                raw.call(CONSUMING, qos, |m| matches!(m, Method::BasicQosOk(_)))
                    .await;
            }
        }
        for (k, queue) in plan.queues.iter().enumerate() {
            let consume = BasicConsume {
                queue: short(queue),
                consumer_tag: consumer_tag(k),
                no_ack: plan.no_ack[k],
                ..Default::default()
            };
            raw.call(CONSUMING, consume, |m| {
                matches!(m, Method::BasicConsumeOk(_))
            })
            .await;
        }
        raw.call(PUBLISHING, ConfirmSelect { no_wait: false }, |m| {
            matches!(m, Method::ConfirmSelectOk(_))
        })
        .await;
        Connection { index, raw, plan }
    }
}

/// Sends what the connection's tasks queue, in order, until they are done.
async fn write_all(mut socket: OwnedWriteHalf, mut outgoing: mpsc::UnboundedReceiver<Bytes>) {
    while let Some(bytes) = outgoing.recv().await {
        if socket.write_all(&bytes).await.is_err() {
            return;
        }
    }
}

/// Publishes this connection's messages over every queue, at most
/// [`CONFIRM_WINDOW`] unconfirmed at a time.
async fn publish_all(
    publisher: usize,
    queues: Arc<Vec<String>>,
    frames: mpsc::UnboundedSender<Bytes>,
    mut confirmed: watch::Receiver<u64>,
) {
    for seq in 0..MESSAGES_PER_PUBLISHER {
        confirmed
            .wait_for(|&upto| seq < upto + CONFIRM_WINDOW)
            .await
            .expect("the reader is running");
        let queue = &queues[(publisher * 7 + seq as usize) % queues.len()];
        let body = message_id(publisher as u64, seq).to_be_bytes();
        let publish = publish_frames(PUBLISHING, "", queue, &BasicProperties::default(), &body, 0);
        frames.send(publish).expect("the writer is running");
    }
}

/// Reads every frame of one connection and checks it as it comes; returns
/// the ids of the messages delivered to it once the connection is closed.
async fn read_and_check(
    mut socket: OwnedReadHalf,
    mut buf: BytesMut,
    mut checker: Checker,
    frames: mpsc::UnboundedSender<Bytes>,
    progress: Arc<Progress>,
) -> Vec<u64> {
    loop {
        while let Some(frame) = decode_frame(&mut buf, 0).expect("valid frame") {
            match checker.frame(frame) {
                Step::Continue => {}
                Step::Delivered { reply } => {
                    if let Some(method) = reply {
                        send(&frames, CONSUMING, method);
                    }
                    progress.add(&progress.delivered, 1);
                }
                Step::Probed { ack } => send(&frames, CONSUMING, ack.into()),
                Step::Confirmed(n) => progress.add(&progress.confirmed, n),
                Step::Closed => return checker.received,
            }
        }
        let read = socket.read_buf(&mut buf).await.expect("read");
        assert!(
            read > 0,
            "connection {} closed by the broker",
            checker.index
        );
    }
}

/// What one frame meant.
enum Step {
    Continue,
    /// A delivery, and what to send on the consuming channel (an ack, or
    /// the probe that precedes settling a full window).
    Delivered {
        reply: Option<Method>,
    },
    /// The probe's answer: the window held, settle it now.
    Probed {
        ack: BasicAck,
    },
    /// This many more publishes confirmed.
    Confirmed(u64),
    /// connection.close-ok (the test closes once everything arrived).
    Closed,
}

/// The client-side bookkeeping of one connection, checking each frame.
struct Checker {
    index: usize,
    plan: Plan,
    /// The delivery whose content is still to come.
    pending: Option<(usize, u64)>,
    last_tag: u64,
    /// Unacked deliveries: tag to consumer.
    unacked: BTreeMap<u64, usize>,
    unacked_per_consumer: Vec<u16>,
    received: Vec<u64>,
    confirmed_upto: u64,
    confirmed: watch::Sender<u64>,
    random: u64,
    /// A probe is out: settle the window when its answer comes.
    probing: bool,
}

impl Checker {
    fn new(index: usize, plan: Plan, confirmed: watch::Sender<u64>) -> Checker {
        Checker {
            index,
            unacked_per_consumer: vec![0; plan.queues.len()],
            plan,
            pending: None,
            last_tag: 0,
            unacked: BTreeMap::new(),
            received: Vec::new(),
            confirmed_upto: 0,
            confirmed,
            random: 0x9E37_79B9_7F4A_7C15 ^ index as u64,
            probing: false,
        }
    }

    fn frame(&mut self, frame: Frame) -> Step {
        let c = self.index;
        match frame {
            Frame::Method {
                channel: CONSUMING,
                method: Method::BasicDeliver(deliver),
            } => {
                assert!(
                    self.pending.is_none(),
                    "connection {c}: deliver inside a delivery"
                );
                assert_eq!(
                    deliver.delivery_tag,
                    self.last_tag + 1,
                    "connection {c}: delivery tags must go up by one as they arrive"
                );
                self.last_tag = deliver.delivery_tag;
                assert!(
                    !deliver.redelivered,
                    "connection {c}: nothing is redelivered"
                );
                let consumer = (0..self.plan.queues.len())
                    .find(|&k| deliver.consumer_tag == consumer_tag(k))
                    .unwrap_or_else(|| panic!("connection {c}: unknown consumer {deliver:?}"));
                self.pending = Some((consumer, deliver.delivery_tag));
                Step::Continue
            }
            Frame::Header {
                channel: CONSUMING,
                header,
            } => {
                assert!(
                    self.pending.is_some(),
                    "connection {c}: header without deliver"
                );
                assert_eq!(header.body_size, 8, "connection {c}: body size");
                Step::Continue
            }
            Frame::Body {
                channel: CONSUMING,
                mut payload,
            } => {
                let (consumer, tag) = self
                    .pending
                    .take()
                    .unwrap_or_else(|| panic!("connection {c}: body without deliver"));
                self.received.push(payload.get_u64());
                Step::Delivered {
                    reply: self.delivered(consumer, tag),
                }
            }
            Frame::Method {
                channel: PUBLISHING,
                method: Method::BasicAck(ack),
            } => {
                let before = self.confirmed_upto;
                if ack.multiple {
                    assert!(
                        ack.delivery_tag > before,
                        "connection {c}: confirm of {} (multiple) after {before}",
                        ack.delivery_tag
                    );
                } else {
                    assert_eq!(
                        ack.delivery_tag,
                        before + 1,
                        "connection {c}: confirms must come in order"
                    );
                }
                assert!(ack.delivery_tag <= MESSAGES_PER_PUBLISHER);
                self.confirmed_upto = ack.delivery_tag;
                self.confirmed.send_replace(self.confirmed_upto);
                Step::Confirmed(self.confirmed_upto - before)
            }
            Frame::Method {
                channel: CONSUMING,
                method: Method::QueueDeclareOk(_),
            } if self.probing => {
                self.probing = false;
                let newest = *self.unacked.keys().next_back().expect("a full window");
                Step::Probed {
                    ack: self.ack(newest, true),
                }
            }
            Frame::Method {
                channel: 0,
                method: Method::ConnectionCloseOk(_),
            } => Step::Closed,
            other => panic!("connection {c}: unexpected {other:?}"),
        }
    }

    /// Counts a delivery against the limits and decides what to ack.
    fn delivered(&mut self, consumer: usize, tag: u64) -> Option<Method> {
        let c = self.index;
        if self.plan.no_ack[consumer] {
            return None;
        }
        self.unacked.insert(tag, consumer);
        self.unacked_per_consumer[consumer] += 1;
        let own = self.unacked_per_consumer[consumer];
        let total = self.unacked.len();
        let (per_consumer, global) = (self.plan.per_consumer, self.plan.global);
        assert!(
            per_consumer == 0 || own <= per_consumer,
            "connection {c}: consumer {consumer} holds {own} unacked, prefetch {per_consumer}"
        );
        assert!(
            global == 0 || total <= usize::from(global),
            "connection {c}: channel holds {total} unacked, global prefetch {global}"
        );
        let at_limit = (per_consumer > 0 && own == per_consumer)
            || (global > 0 && total == usize::from(global));
        if self.probing {
            // Settled all at once when the probe's answer comes.
            return None;
        }
        if at_limit {
            // Nothing more may come until something is settled. Before
            // settling, a round trip on this connection (a passive declare):
            // a delivery the broker let out beyond the limit while this one
            // went out arrives before the answer and fails the check above.
            // Once the answer is in, one multiple-ack settles everything.
            self.probing = true;
            let probe = QueueDeclare {
                queue: short(&self.plan.queues[0]),
                passive: true,
                ..Default::default()
            };
            return Some(probe.into());
        }
        let roll = self.next_random();
        match roll % 8 {
            0 => {
                // A single ack of some outstanding delivery, not always the oldest.
                let pick = (roll >> 8) as usize % self.unacked.len();
                let tag = *self.unacked.keys().nth(pick)?;
                Some(self.ack(tag, false).into())
            }
            1 | 2 => Some(self.ack(*self.unacked.keys().next_back()?, true).into()),
            _ => None,
        }
    }

    /// Settles on the client side what `tag` (and `multiple`) acks.
    fn ack(&mut self, tag: u64, multiple: bool) -> BasicAck {
        let settled: Vec<u64> = if multiple {
            self.unacked.range(..=tag).map(|(&t, _)| t).collect()
        } else {
            vec![tag]
        };
        for t in settled {
            let consumer = self.unacked.remove(&t).expect("outstanding");
            self.unacked_per_consumer[consumer] -= 1;
        }
        BasicAck {
            delivery_tag: tag,
            multiple,
        }
    }

    /// xorshift64: deterministic per connection, no dependency.
    fn next_random(&mut self) -> u64 {
        let mut x = self.random;
        x ^= x << 13;
        x ^= x >> 7;
        x ^= x << 17;
        self.random = x;
        x
    }
}

/// Queues one method for the connection's writer.
fn send(frames: &mpsc::UnboundedSender<Bytes>, channel: u16, method: Method) {
    frames
        .send(method_frame(channel, method))
        .expect("the writer is running");
}

/// A message's id: its publisher and its sequence number there.
fn message_id(publisher: u64, seq: u64) -> u64 {
    (publisher << 32) | seq
}

fn consumer_tag(k: usize) -> ShortStr {
    short(&format!("consumer-{k}"))
}
