//! The ports' accounting as invariants, through a frozen broker (a proxy
//! that stops forwarding, as SIGSTOP leaves the sockets), a cut link and
//! an overload, on both runtimes: every accepted message has exactly one
//! fate (`accepted == settled() + pending`), a message counted never
//! written (dropped unsent, expired) never reaches the in-port, every
//! confirmed one does, what is written stays within the window, and every
//! message that reaches the in-port has one fate there
//! (`arrived == received + buffered + stale + decode_errors + dropped +
//! skipped`). A stalled link is reported degraded and then well again.

mod common;

use common::{unique, within};
use leveret_broker::{Broker, BrokerHandle};
use leveret_client::{FieldValue, ShortStr};
use leveret_ports::{
    Connector, ExchangeKind, Fate, FullPolicy, InPort, InPortStats, OutPort, OutPortStats, Outcome,
    PortProfile, PortStatus, Qos, Time, TimedLong,
};
use leveret_tests::both_runtimes;
use leveret_tests::fault_proxy::FaultProxy as Proxy;
use std::collections::{HashMap, HashSet};
use std::net::SocketAddr;
use std::sync::{Arc, Mutex};
use std::time::Duration;

/// The command preset's window.
const WINDOW: u64 = 16;

async fn leveret() -> (Arc<BrokerHandle>, SocketAddr) {
    let handle = Broker::builder()
        .listen("127.0.0.1:0".parse().unwrap())
        .start()
        .await
        .expect("start an embedded Leveret");
    let addr = handle.local_addrs()[0];
    (Arc::new(handle), addr)
}

/// A queue of its own, and an in-port profile that keeps every value (no
/// lifespan: what it gets is what the out-port and the broker let through).
fn profile(addr: SocketAddr, queue: &str) -> PortProfile {
    let mut profile = PortProfile::new(&format!("amqp://guest:guest@{addr}/%2f"))
        .expect("broker URI")
        .backoff(Duration::from_millis(10), Duration::from_millis(200))
        .queue(queue)
        .routing_key(queue)
        .buffer(8192, FullPolicy::DropOldest);
    profile
        .queue_arguments
        .insert(ShortStr::from_static("x-expires"), FieldValue::I32(120_000));
    profile
}

fn long(data: i32) -> TimedLong {
    TimedLong {
        tm: Time::now(),
        data,
    }
}

fn out_invariant(stats: &OutPortStats) {
    assert_eq!(stats.accepted, stats.settled() + stats.pending, "{stats:?}");
    assert!(stats.in_flight <= stats.pending, "{stats:?}");
}

fn in_invariant(stats: &InPortStats) {
    assert_eq!(
        stats.arrived,
        stats.received
            + stats.buffered
            + stats.stale
            + stats.decode_errors
            + stats.dropped
            + stats.skipped,
        "{stats:?}"
    );
}

/// Every outcome an out-port reports, and the sequence numbers an in-port
/// is handed by its broker.
struct Ledger {
    outcomes: Arc<Mutex<Vec<Outcome>>>,
    arrived: Arc<Mutex<Vec<u64>>>,
}

impl Ledger {
    fn keep(output: &OutPort<TimedLong>, input: &InPort<TimedLong>) -> Ledger {
        let outcomes = Arc::new(Mutex::new(Vec::new()));
        let record = Arc::clone(&outcomes);
        output.on_outcome(move |outcome| record.lock().unwrap().push(*outcome));
        let arrived = Arc::new(Mutex::new(Vec::new()));
        let record = Arc::clone(&arrived);
        input.on_receive(move |sample| record.lock().unwrap().push(sample.seq.expect("stamped")));
        Ledger { outcomes, arrived }
    }

    /// Once the out-port has settled everything (`flush`, which sees the
    /// counters only once their outcomes are delivered) and the in-port
    /// has every confirmed value: each accepted message has one outcome,
    /// the one its counter says; none counted unsent arrived; every
    /// confirmed one did.
    async fn check(&self, output: &OutPort<TimedLong>, input: &InPort<TimedLong>) {
        within("everything settled", output.flush()).await;
        let stats = output.stats();
        out_invariant(&stats);
        assert_eq!(stats.pending, 0, "{stats:?}");
        let fates: HashMap<u64, Fate> = {
            let outcomes = self.outcomes.lock().unwrap();
            let fates: HashMap<u64, Fate> = outcomes.iter().map(|o| (o.seq, o.fate)).collect();
            assert_eq!(fates.len(), outcomes.len(), "one outcome per message");
            fates
        };
        assert_eq!(fates.len() as u64, stats.accepted, "{stats:?}");
        let count = |fate: Fate| fates.values().filter(|f| **f == fate).count() as u64;
        assert_eq!(
            (
                count(Fate::Confirmed),
                count(Fate::SentUnconfirmed),
                count(Fate::DroppedUnsent),
                count(Fate::Expired),
                count(Fate::Lost),
                count(Fate::Rejected) + count(Fate::Unroutable),
            ),
            (
                stats.confirmed,
                stats.sent_unconfirmed,
                stats.dropped_unsent,
                stats.expired,
                stats.lost,
                stats.rejected + stats.unroutable,
            ),
            "{stats:?}"
        );
        let confirmed: Vec<u64> = fates
            .iter()
            .filter(|(_, fate)| **fate == Fate::Confirmed)
            .map(|(seq, _)| *seq)
            .collect();
        let mut arrivals = input.watch_stats();
        within("every confirmed value at the in-port", async {
            loop {
                arrivals.borrow_and_update();
                let arrived: HashSet<u64> = self.arrived.lock().unwrap().iter().copied().collect();
                if confirmed.iter().all(|seq| arrived.contains(seq)) {
                    return;
                }
                arrivals.changed().await.expect("the in-port is open");
            }
        })
        .await;
        let arrived: HashSet<u64> = self.arrived.lock().unwrap().iter().copied().collect();
        for (seq, fate) in &fates {
            match fate {
                Fate::DroppedUnsent | Fate::Expired => {
                    assert!(!arrived.contains(seq), "{seq} counted {fate:?} arrived")
                }
                Fate::Confirmed => assert!(arrived.contains(seq), "confirmed {seq} never came"),
                _ => {}
            }
        }
        in_invariant(&input.stats());
    }

    /// Without a link loss every message written reaches the in-port:
    /// waits until those the out-port counts written (confirmed or
    /// sent-unconfirmed) have all arrived, and no more.
    async fn written_all_arrive(&self, output: &OutPort<TimedLong>, input: &InPort<TimedLong>) {
        let stats = output.stats();
        let written = stats.confirmed + stats.sent_unconfirmed;
        let mut arrivals = input.watch_stats();
        within(
            "every written value at the in-port",
            arrivals.wait_for(|s| s.arrived >= written),
        )
        .await
        .unwrap();
        assert_eq!(input.stats().arrived, written, "{stats:?}");
        assert_eq!(input.stats().duplicates, 0);
    }
}

/// A command stream into a broker that stops answering: the out-port
/// writes no more than its window, reports the stall (link state, put
/// result, counter) and clears it when the broker answers again; nothing
/// counted unsent arrives afterwards, and a reader with the commands'
/// lifespan counts what the stall held back stale, never handing it over.
#[both_runtimes]
async fn a_frozen_broker_is_noticed_bounded_and_accounted() {
    let (_broker, addr) = leveret().await;
    let proxy = Proxy::start(addr).await;
    let queue = unique("frozen-cmd");
    let base = profile(addr, &queue).exchange(unique("frozen-cmds"), ExchangeKind::Fanout);
    let input = InPort::<TimedLong>::connect(base.clone())
        .await
        .expect("in-port");
    // A second reader, with the commands' lifespan: what the stall held
    // back arrives stale.
    let mut fresh_only = base.clone().queue(unique("frozen-fresh"));
    fresh_only.lifespan = base.clone().qos(Qos::Command).lifespan;
    let fresh = InPort::<TimedLong>::connect(fresh_only)
        .await
        .expect("in-port");
    let mut command = base.qos(Qos::Command);
    assert_eq!(command.max_unconfirmed as u64, WINDOW);
    command.broker.port = proxy.addr.port();
    let output = OutPort::<TimedLong>::connect(command)
        .await
        .expect("out-port");
    let ledger = Ledger::keep(&output, &input);
    for data in 1..=20 {
        assert_eq!(output.try_put(&long(data)), PortStatus::Ok);
    }
    within("the first values confirmed", output.flush()).await;

    proxy.freeze(true);
    let mut link = output.link();
    let mut data = 20;
    within("the stall reported", async {
        while !link.borrow_and_update().degraded {
            data += 1;
            assert!(output.try_put(&long(data)).is_accepted());
            let stats = output.stats();
            out_invariant(&stats);
            assert!(stats.in_flight <= WINDOW, "{stats:?}");
            tokio::time::sleep(Duration::from_millis(1)).await;
        }
    })
    .await;
    assert!(link.borrow().up, "degraded, not down");
    for _ in 0..200 {
        data += 1;
        assert_eq!(output.try_put(&long(data)), PortStatus::Degraded);
        tokio::task::yield_now().await;
    }
    let stats = output.stats();
    out_invariant(&stats);
    assert_eq!(stats.stalls, 1, "{stats:?}");
    assert!(stats.pending <= WINDOW, "{stats:?}");

    proxy.freeze(false);
    within("the stall cleared", link.wait_for(|s| s.up && !s.degraded))
        .await
        .unwrap();
    ledger.check(&output, &input).await;
    let stats = output.stats();
    assert_eq!(stats.accepted, data as u64);
    assert!(
        stats.dropped_unsent + stats.expired >= 200 - WINDOW,
        "most of the stall's values never written: {stats:?}"
    );
    ledger.written_all_arrive(&output, &input).await;
    let written = stats.confirmed + stats.sent_unconfirmed;
    within(
        "every written value at the second reader",
        fresh.watch_stats().wait_for(|s| s.arrived == written),
    )
    .await
    .unwrap();
    let taken = std::iter::from_fn(|| fresh.try_recv()).count() as u64;
    let fresh_stats = fresh.stats();
    in_invariant(&fresh_stats);
    assert!(
        fresh_stats.stale >= 1,
        "what the frozen broker held arrived past its lifespan: {fresh_stats:?}"
    );
    assert_eq!(
        (fresh_stats.received, fresh_stats.buffered),
        (taken, 0),
        "{fresh_stats:?}"
    );
    // Written during the stall: at most a window; after it, at most what
    // the window held.
    let arrived = ledger.arrived.lock().unwrap().len() as u64;
    assert!(arrived <= 20 + 2 * WINDOW, "{arrived} arrived; {stats:?}");
    assert_eq!(output.try_put(&long(data + 1)), PortStatus::Ok);
}

/// A command stream through a cut link (replaying only the newest value
/// after the reconnection): the fates add up, and what was written on the
/// lost link and not replayed is counted lost, not dropped.
#[both_runtimes]
async fn a_cut_link_is_accounted() {
    let (_broker, addr) = leveret().await;
    let proxy = Proxy::start(addr).await;
    let queue = unique("cut-cmd");
    let base = profile(addr, &queue);
    let input = InPort::<TimedLong>::connect(base.clone())
        .await
        .expect("in-port");
    let mut command = base.qos(Qos::Command).lifespan(Duration::from_secs(5));
    command.broker.port = proxy.addr.port();
    let output = OutPort::<TimedLong>::connect(command)
        .await
        .expect("out-port");
    let ledger = Ledger::keep(&output, &input);
    let mut link = output.link();
    for data in 1..=600 {
        if data == 200 {
            assert_eq!(proxy.cut(), 1, "the out-port's connection");
        }
        assert!(output.try_put(&long(data)).is_accepted());
        out_invariant(&output.stats());
        tokio::task::yield_now().await;
    }
    within("a reconnection", link.wait_for(|s| s.connects >= 2))
        .await
        .unwrap();
    ledger.check(&output, &input).await;
    let stats = output.stats();
    assert_eq!(stats.accepted, 600);
    assert!(output.link().borrow().losses >= 1);
}

/// Far more values than the window and the in-port's buffer take, in
/// process: both sides' fates add up, and nothing counted unsent arrives.
#[both_runtimes]
async fn an_overload_is_accounted() {
    let (broker, addr) = leveret().await;
    let queue = unique("overload");
    let base = profile(addr, &queue);
    let local = Connector::in_process(&broker);
    let input = InPort::<TimedLong>::connect_with(
        local.clone(),
        base.clone().buffer(8, FullPolicy::DropOldest),
    )
    .await
    .expect("in-port");
    let output = OutPort::<TimedLong>::connect_with(local, base.qos(Qos::Command))
        .await
        .expect("out-port");
    let ledger = Ledger::keep(&output, &input);
    let mut taken = 0;
    for data in 1..=3000 {
        assert!(output.try_put(&long(data)).is_accepted());
        if data % 50 == 0 {
            out_invariant(&output.stats());
            taken += u64::from(input.read().is_some());
            tokio::task::yield_now().await;
        }
    }
    ledger.check(&output, &input).await;
    ledger.written_all_arrive(&output, &input).await;
    while input.try_recv().is_some() {
        taken += 1;
    }
    let stats = input.stats();
    in_invariant(&stats);
    assert_eq!((stats.received, stats.buffered), (taken, 0), "{stats:?}");
    assert_eq!(output.stats().accepted, 3000);
}

/// The window's byte bound: with room for two bodies in flight, a frozen
/// broker gets two messages written and no more; the rest wait unsent,
/// and all are sent once it thaws.
#[both_runtimes]
async fn the_bytes_in_flight_are_bounded() {
    let (_broker, addr) = leveret().await;
    let proxy = Proxy::start(addr).await;
    let queue = unique("bytes-bound");
    let base = profile(addr, &queue);
    let input = InPort::<TimedLong>::connect(base.clone())
        .await
        .expect("in-port");
    let body = {
        let mut body = bytes::BytesMut::new();
        leveret_ports::PortData::encode(&long(0), &mut body).expect("encodes");
        body.len()
    };
    let mut bounded = base;
    bounded.max_unconfirmed_bytes = 2 * body + body / 2;
    bounded.broker.port = proxy.addr.port();
    let output = OutPort::<TimedLong>::connect(bounded)
        .await
        .expect("out-port");
    let ledger = Ledger::keep(&output, &input);
    proxy.freeze(true);
    for data in 1..=10 {
        assert!(output.try_put(&long(data)).is_accepted());
        tokio::task::yield_now().await;
    }
    let stats = output.stats();
    out_invariant(&stats);
    assert_eq!((stats.in_flight, stats.pending), (2, 10), "{stats:?}");
    proxy.freeze(false);
    ledger.check(&output, &input).await;
    ledger.written_all_arrive(&output, &input).await;
    assert_eq!(output.stats().confirmed, 10);
}
