//! Robot data ports through broker outages, as a control loop lives them:
//! a frozen broker (a proxy that stops forwarding, as SIGSTOP would leave
//! the sockets), a cut link and a restart. The loop's `put` must never
//! wait on the network, and no command may arrive past its lifespan.

mod common;

use common::{unique, within, without_waiting};
use leveret_broker::{Broker, BrokerHandle};
use leveret_client::{FieldValue, ShortStr};
use leveret_ports::{
    Backpressure, Fate, FullPolicy, InPort, OutPort, Outcome, PortProfile, PortStatus, Qos, Replay,
    Time, TimedLong,
};
use leveret_tests::fault_proxy::FaultProxy as Proxy;
use leveret_tests::reserved_port::reserved_addr;
use std::net::SocketAddr;
use std::sync::{Arc, Mutex};
use std::time::Duration;

/// An embedded Leveret on a loopback port.
async fn leveret() -> (BrokerHandle, SocketAddr) {
    let handle = Broker::builder()
        .listen("127.0.0.1:0".parse().unwrap())
        .start()
        .await
        .expect("start an embedded Leveret");
    let addr = handle.local_addrs()[0];
    (handle, addr)
}

fn profile(addr: SocketAddr) -> PortProfile {
    let mut profile = PortProfile::new(&format!("amqp://guest:guest@{addr}/%2f"))
        .expect("broker URI")
        .backoff(Duration::from_millis(10), Duration::from_millis(200));
    profile
        .queue_arguments
        .insert(ShortStr::from_static("x-expires"), FieldValue::I32(120_000));
    profile
}

/// Puts a 100 Hz loop makes before, during and after a frozen broker.
const BEFORE: i32 = 20;
const FROZEN: i32 = 200;
const AFTER: i32 = 50;

/// A 100 Hz loop putting through a broker frozen for [`FROZEN`] of its
/// puts; what the port had pending at the thaw (proof it was frozen).
async fn loop_through_a_stall(output: &OutPort<TimedLong>, proxy: &Proxy, flavor: &str) -> u64 {
    let mut tick = tokio::time::interval(Duration::from_millis(10));
    let mut pending_at_thaw = 0;
    for count in 1..=BEFORE + FROZEN + AFTER {
        tick.tick().await;
        if count == BEFORE + 1 {
            proxy.freeze(true);
        }
        if count == BEFORE + FROZEN + 1 {
            pending_at_thaw = output.stats().pending;
            proxy.freeze(false);
        }
        let value = TimedLong {
            tm: Time::now(),
            data: count,
        };
        // Done at its first poll: it never waited, on the frozen link or
        // anything else (before, each put of a stall waited its whole
        // put timeout).
        let status = without_waiting(output.put(&value))
            .unwrap_or_else(|| panic!("{flavor}: put {count} waited"));
        assert!(status.is_accepted(), "{flavor}: put {count}: {status:?}");
    }
    pending_at_thaw
}

async fn puts_during_a_frozen_broker(flavor: &str) {
    let (_broker, addr) = leveret().await;
    let proxy = Proxy::start(addr).await;
    let queue = unique("frozen");
    let direct = profile(addr)
        .queue(&queue)
        .routing_key(&queue)
        .buffer(64, FullPolicy::BlockBroker);
    let input = InPort::<TimedLong>::connect(direct.clone())
        .await
        .expect("in-port");
    let mut proxied = direct;
    proxied.broker.port = proxy.addr.port();
    let output = OutPort::<TimedLong>::connect(proxied)
        .await
        .expect("out-port");
    let pending_at_thaw = loop_through_a_stall(&output, &proxy, flavor).await;
    assert!(
        pending_at_thaw >= FROZEN as u64,
        "{flavor}: the broker was frozen: {pending_at_thaw} pending"
    );
    within("everything confirmed after the thaw", output.flush()).await;
    let count = BEFORE + FROZEN + AFTER;
    for expected in 1..=count {
        let sample = within("every value", input.recv()).await.expect("open");
        assert_eq!(sample.value.data, expected, "in order, none lost");
    }
    let stats = output.stats();
    assert_eq!(stats.confirmed, count as u64, "{stats:?}");
}

/// Both runtime flavours, one after the other (run in parallel, they would
/// preempt each other's loops).
#[test]
fn put_never_waits_on_a_frozen_broker() {
    let current = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .unwrap();
    current.block_on(puts_during_a_frozen_broker("current-thread"));
    let multi = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()
        .unwrap();
    multi.block_on(puts_during_a_frozen_broker("multi-thread"));
}

fn long(data: i32) -> TimedLong {
    TimedLong {
        tm: Time::now(),
        data,
    }
}

/// An out-port started before its broker exists, with a window of 3.
fn port_without_broker(addr: SocketAddr, backpressure: Backpressure) -> OutPort<TimedLong> {
    let mut profile = profile(addr)
        .exchange("amq.fanout", leveret_ports::ExchangeKind::Fanout)
        .backpressure(backpressure)
        .put_timeout(Duration::from_millis(50));
    profile.max_unconfirmed = 3;
    OutPort::start(profile).expect("starts without a broker")
}

#[tokio::test]
async fn backpressure_drop_oldest_reports_what_it_drops() {
    let output = port_without_broker(reserved_addr(), Backpressure::DropOldest);
    let mut outcomes = output.outcomes();
    let seen = Arc::new(Mutex::new(Vec::new()));
    let record = Arc::clone(&seen);
    output.on_outcome(move |outcome| record.lock().unwrap().push(*outcome));
    for data in 1..=5 {
        assert_eq!(output.try_put(&long(data)), PortStatus::ConnectionLost);
    }
    let dropped = [
        Outcome {
            seq: 1,
            fate: Fate::DroppedUnsent,
        },
        Outcome {
            seq: 2,
            fate: Fate::DroppedUnsent,
        },
    ];
    assert_eq!(outcomes.try_recv().unwrap(), dropped[0]);
    assert_eq!(outcomes.try_recv().unwrap(), dropped[1]);
    assert!(outcomes.try_recv().is_err());
    assert_eq!(*seen.lock().unwrap(), dropped);
    let stats = output.stats();
    assert_eq!(
        (
            stats.accepted,
            stats.dropped_unsent,
            stats.pending,
            stats.send_full
        ),
        (5, 2, 3, 0)
    );
    assert_eq!(*output.watch_stats().borrow(), stats);
}

#[tokio::test]
async fn backpressure_drop_newest_refuses_at_once() {
    let output = port_without_broker(reserved_addr(), Backpressure::DropNewest);
    let statuses: Vec<_> = (1..=5).map(|data| output.try_put(&long(data))).collect();
    use PortStatus::{ConnectionLost as Kept, SendFull as Full};
    assert_eq!(statuses, [Kept, Kept, Kept, Full, Full]);
    assert_eq!(
        without_waiting(output.put(&long(6))),
        Some(PortStatus::SendFull),
        "refused without waiting"
    );
    let stats = output.stats();
    assert_eq!(
        (stats.accepted, stats.send_full, stats.dropped_unsent),
        (3, 3, 0)
    );
}

/// Block waits up to its deadline, in `put` and `put_blocking`, never in
/// `try_put`; once the broker appears the window drains and a blocked put
/// gets in.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn backpressure_block_waits_up_to_its_deadline() {
    let addr = reserved_addr();
    let output = Arc::new(port_without_broker(addr, Backpressure::Block));
    for data in 1..=3 {
        assert_eq!(output.put(&long(data)).await, PortStatus::ConnectionLost);
    }
    assert_eq!(output.try_put(&long(4)), PortStatus::SendFull);
    // `put` waits for room (pending at its first poll), then refuses at
    // its deadline; so does `put_blocking`, blocking its thread.
    let value = long(4);
    let mut put = std::pin::pin!(output.put(&value));
    assert!(without_waiting(put.as_mut()).is_none(), "it waits for room");
    assert_eq!(put.await, PortStatus::SendFull);
    let blocking = Arc::clone(&output);
    let refused = tokio::task::spawn_blocking(move || blocking.put_blocking(&long(4)))
        .await
        .unwrap();
    assert_eq!(refused, PortStatus::SendFull);
    assert_eq!(output.stats().send_full, 3);

    // The broker comes up where the port was told to look.
    let _broker = Broker::builder().listen(addr).start().await.expect("start");
    let mut link = output.link();
    within(
        "the port connects in the background",
        link.wait_for(|s| s.up),
    )
    .await
    .unwrap();
    within("the window drains", output.flush()).await;
    let blocking = Arc::clone(&output);
    let status = tokio::task::spawn_blocking(move || blocking.put_blocking(&long(5)))
        .await
        .unwrap();
    assert_eq!(status, PortStatus::Ok);
    within("all sent", output.flush()).await;
    let stats = output.stats();
    // amq.fanout has no queue bound: each message comes back unroutable.
    assert_eq!(
        (stats.accepted, stats.unroutable, stats.confirmed),
        (4, 4, 0)
    );
}

#[tokio::test]
async fn an_in_port_starts_before_its_broker() {
    let addr = reserved_addr();
    let queue = unique("early");
    let profile = profile(addr).queue(&queue).routing_key(&queue);
    let input = InPort::<TimedLong>::start(profile.clone());
    assert!(!input.link().borrow().up);
    let _broker = Broker::builder().listen(addr).start().await.expect("start");
    within("in-port up", input.link().wait_for(|s| s.up))
        .await
        .unwrap();
    let output = OutPort::<TimedLong>::connect(profile)
        .await
        .expect("out-port");
    assert_eq!(output.put(&long(7)).await, PortStatus::Ok);
    let sample = within("value", input.recv()).await.unwrap();
    assert_eq!(sample.value.data, 7);
}

/// A `cmd_vel` stream through a 1 s outage: with the `command` preset no
/// value reaches the robot past its lifespan (before: the whole outage was
/// replayed in one burst, values up to 1 s old).
#[tokio::test]
async fn no_stale_command_after_an_outage() {
    stale_commands_through_an_outage(None).await;
}

/// The lifespan alone (replaying everything still within it) keeps stale
/// values out too.
#[tokio::test]
async fn no_stale_command_after_an_outage_with_replay_all() {
    stale_commands_through_an_outage(Some(Replay::All)).await;
}

async fn stale_commands_through_an_outage(replay: Option<Replay>) {
    let (_broker, addr) = leveret().await;
    let mut proxy = Proxy::start(addr).await;
    let queue = unique("cmd_vel");
    let base = profile(addr).queue(&queue).routing_key(&queue);
    let lifespan = Duration::from_millis(200);
    // The receiver applies no lifespan of its own: what it gets is what
    // the out-port and the broker let through.
    let input = InPort::<TimedLong>::connect(base.clone().buffer(4096, FullPolicy::DropOldest))
        .await
        .expect("in-port");
    // Each value's age as it reaches the in-port (the callbacks run then).
    let ages = Arc::new(Mutex::new(Vec::new()));
    let record = Arc::clone(&ages);
    input.on_receive(move |sample| {
        let age = sample.sent_at.and_then(|sent| sent.elapsed().ok());
        record.lock().unwrap().push((sample.value.data, age));
    });
    let mut command = base.qos(Qos::Command).lifespan(lifespan);
    if let Some(replay) = replay {
        // Everything put during the outage is kept: only the lifespan
        // stands between it and the robot.
        command = command.replay(replay).keep_last(1000);
    }
    command.broker.port = proxy.addr.port();
    let output = OutPort::<TimedLong>::connect(command)
        .await
        .expect("out-port");
    let mut tick = tokio::time::interval(Duration::from_millis(10));
    let mut data = 0;
    let mut put_during_outage = 0;
    for phase in ["before", "outage", "after"] {
        if phase == "outage" {
            proxy.stop().await;
            within("the loss", output.link().wait_for(|s| !s.up))
                .await
                .unwrap();
        }
        if phase == "after" {
            proxy = Proxy::start_at(proxy.addr, addr).await;
            within("the reconnection", output.link().wait_for(|s| s.up))
                .await
                .unwrap();
        }
        for _ in 0..100 {
            tick.tick().await;
            data += 1;
            let status = output.put(&long(data)).await;
            if phase == "outage" {
                put_during_outage += 1;
                assert_eq!(status, PortStatus::ConnectionLost);
            }
        }
    }
    within("all settled", output.flush()).await;
    let mut received = Vec::new();
    while received.last() != Some(&data) {
        let sample = within("the last command", input.recv()).await.unwrap();
        received.push(sample.value.data);
    }
    for (data, age) in ages.lock().unwrap().iter() {
        let age = age.expect("stamped");
        assert!(
            // A generous margin for a loaded machine's scheduling; values
            // replayed from the outage would be 1 s old and more.
            age <= lifespan + Duration::from_millis(500),
            "command {data} reached the in-port {age:?} after it was put"
        );
    }
    let stats = output.stats();
    eprintln!("received {} of {data}; out-port {stats:?}", received.len());
    assert!(
        stats.expired + stats.dropped_unsent >= put_during_outage - 20,
        "{stats:?}"
    );
    assert!(received.windows(2).all(|w| w[0] < w[1]), "in order");
}

/// A value the broker holds past its lifespan (its in-port away) is
/// never delivered: the out-port publishes it with the rest of its
/// lifespan as AMQP `expiration`.
#[tokio::test]
async fn the_broker_drops_values_past_their_lifespan() {
    let (_broker, addr) = leveret().await;
    let queue = unique("expiring");
    let base = profile(addr).queue(&queue).routing_key(&queue);
    let input = InPort::<TimedLong>::connect(base.clone())
        .await
        .expect("in-port");
    input.close().await;
    // A lifespan a loaded machine delivers a fresh value well within.
    let output = OutPort::<TimedLong>::connect(base.clone().lifespan(Duration::from_secs(1)))
        .await
        .expect("out-port");
    for data in 1..=5 {
        assert_eq!(output.put(&long(data)).await, PortStatus::Ok);
    }
    within("confirmed", output.flush()).await;
    assert_eq!(output.stats().confirmed, 5);
    // The lifespan passing is the event waited for.
    tokio::time::sleep(Duration::from_millis(1500)).await;
    let input = InPort::<TimedLong>::connect(base).await.expect("in-port");
    assert_eq!(output.put(&long(6)).await, PortStatus::Ok);
    let sample = within("the fresh value", input.recv()).await.unwrap();
    assert_eq!(sample.value.data, 6, "the stale ones were dropped");
}

/// An in-port with a lifespan drops what arrives older than it.
#[tokio::test]
async fn an_in_port_drops_values_older_than_its_lifespan() {
    let (_broker, addr) = leveret().await;
    let queue = unique("stale-in");
    let base = profile(addr).queue(&queue).routing_key(&queue);
    // Published without a lifespan (an old value, e.g. from another
    // port), received by a port that wants fresh ones.
    let output = OutPort::<TimedLong>::connect(base.clone())
        .await
        .expect("out-port");
    assert_eq!(output.put(&long(1)).await, PortStatus::Ok);
    within("confirmed", output.flush()).await;
    // A lifespan a loaded machine delivers a fresh value well within.
    tokio::time::sleep(Duration::from_millis(1500)).await;
    let input = InPort::<TimedLong>::connect(base.lifespan(Duration::from_secs(1)))
        .await
        .expect("in-port");
    assert_eq!(output.put(&long(2)).await, PortStatus::Ok);
    let sample = within("the fresh value", input.recv()).await.unwrap();
    assert_eq!(sample.value.data, 2);
    assert_eq!(input.stats().stale, 1);
}

/// Values put while the link is down, with `Replay::Latest`: only the
/// newest is sent after the reconnection.
#[tokio::test]
async fn replay_latest_sends_only_the_newest_after_a_reconnection() {
    let (_broker, addr) = leveret().await;
    let mut proxy = Proxy::start(addr).await;
    let queue = unique("latest");
    let base = profile(addr).queue(&queue).routing_key(&queue);
    let input = InPort::<TimedLong>::connect(base.clone())
        .await
        .expect("in-port");
    let mut latest = base.replay(Replay::Latest);
    latest.broker.port = proxy.addr.port();
    let output = OutPort::<TimedLong>::connect(latest)
        .await
        .expect("out-port");
    proxy.stop().await;
    within("the loss", output.link().wait_for(|s| !s.up))
        .await
        .unwrap();
    for data in 1..=10 {
        assert_eq!(output.put(&long(data)).await, PortStatus::ConnectionLost);
    }
    let _back = Proxy::start_at(proxy.addr, addr).await;
    within("all settled", output.flush()).await;
    let sample = within("the newest", input.recv()).await.unwrap();
    assert_eq!(sample.value.data, 10);
    let stats = output.stats();
    assert_eq!((stats.dropped_unsent, stats.confirmed), (9, 1), "{stats:?}");
}

/// The default topology (an exchange, an in-port with no queue name)
/// through a cut link: nothing lost. Before, the in-port's queue was
/// server-named and exclusive, gone with its connection, and the broker
/// confirmed messages no queue received while it re-bound a new one.
#[tokio::test]
async fn the_default_topology_loses_nothing_across_a_cut() {
    const COUNT: i32 = 2_000;
    let (_broker, addr) = leveret().await;
    let proxy = Proxy::start(addr).await;
    let exchange = unique("poses");
    let mut base = profile(addr)
        .exchange(&exchange, leveret_ports::ExchangeKind::Fanout)
        .buffer(64, FullPolicy::BlockBroker)
        .backpressure(Backpressure::Block)
        .put_timeout(Duration::from_secs(5));
    base.broker.port = proxy.addr.port();
    let input = InPort::<TimedLong>::connect(base.clone())
        .await
        .expect("in-port");
    let output = OutPort::<TimedLong>::connect(base).await.expect("out-port");
    let cut_at = COUNT / 4;
    let publisher = async {
        for data in 1..=COUNT {
            if data == cut_at {
                assert_eq!(proxy.cut(), 2, "one connection per port");
            }
            assert!(output.put(&long(data)).await.is_accepted());
        }
        within("all settled", output.flush()).await;
    };
    let receiver = async {
        for expected in 1..=COUNT {
            let sample = within("every value", input.recv()).await.unwrap();
            assert_eq!(sample.value.data, expected, "none lost");
        }
    };
    tokio::join!(publisher, receiver);
    let stats = output.stats();
    assert_eq!(stats.confirmed, COUNT as u64, "{stats:?}");
}

#[tokio::test]
async fn a_profile_that_routes_nowhere_is_refused() {
    let (_broker, addr) = leveret().await;
    let error = OutPort::<TimedLong>::connect(profile(addr))
        .await
        .expect_err("no exchange, no routing key");
    assert!(error.to_string().contains("routes nowhere"), "{error}");
    assert!(OutPort::<TimedLong>::start(profile(addr)).is_err());
}

/// Published with `mandatory`: what no queue takes is counted unroutable,
/// never confirmed.
#[tokio::test]
async fn unroutable_values_are_counted_apart() {
    let (_broker, addr) = leveret().await;
    let exchange = unique("nobody");
    let base = profile(addr).exchange(&exchange, leveret_ports::ExchangeKind::Direct);
    let output = OutPort::<TimedLong>::connect(base.clone().routing_key("nowhere"))
        .await
        .expect("out-port");
    let mut outcomes = output.outcomes();
    for data in 1..=3 {
        assert_eq!(output.put(&long(data)).await, PortStatus::Ok);
    }
    within("settled", output.flush()).await;
    let stats = output.stats();
    assert_eq!((stats.unroutable, stats.confirmed), (3, 0), "{stats:?}");
    assert_eq!(
        outcomes.try_recv().unwrap(),
        Outcome {
            seq: 1,
            fate: Fate::Unroutable
        }
    );
}

/// Without confirms, what the broker returns as unroutable is counted
/// apart from the fates (each already counted sent-unconfirmed; the port
/// keeps nothing per returned message).
#[tokio::test]
async fn unroutable_values_are_counted_without_confirms_too() {
    let (_broker, addr) = leveret().await;
    let exchange = unique("nobody");
    let base = profile(addr)
        .exchange(&exchange, leveret_ports::ExchangeKind::Direct)
        .routing_key("nowhere")
        .confirms(false);
    let output = OutPort::<TimedLong>::connect(base).await.expect("out-port");
    for data in 1..=3 {
        assert_eq!(output.put(&long(data)).await, PortStatus::Ok);
    }
    let mut stats = output.watch_stats();
    within(
        "three returns",
        stats.wait_for(|s| s.returned_after_send == 3),
    )
    .await
    .unwrap();
    let stats = output.stats();
    assert_eq!(
        (stats.sent_unconfirmed, stats.unroutable, stats.settled()),
        (3, 0, 3),
        "each counted once: {stats:?}"
    );
}

/// Values past their lifespan leave a full window while the broker is
/// away, making room for fresh ones.
#[tokio::test]
async fn expired_values_make_room_while_the_link_is_down() {
    let mut profile = profile(reserved_addr())
        .exchange("amq.fanout", leveret_ports::ExchangeKind::Fanout)
        .backpressure(Backpressure::Block)
        .lifespan(Duration::from_millis(50));
    profile.max_unconfirmed = 2;
    let output = OutPort::<TimedLong>::start(profile).expect("starts");
    assert_eq!(output.try_put(&long(1)), PortStatus::ConnectionLost);
    assert_eq!(output.try_put(&long(2)), PortStatus::ConnectionLost);
    assert_eq!(output.try_put(&long(3)), PortStatus::SendFull);
    // The lifespan passing is the event waited for.
    tokio::time::sleep(Duration::from_millis(80)).await;
    assert_eq!(output.try_put(&long(4)), PortStatus::ConnectionLost);
    let stats = output.stats();
    assert_eq!(
        (stats.expired, stats.pending, stats.send_full),
        (2, 1, 1),
        "{stats:?}"
    );
}

/// A control loop on a thread of its own: `put_blocking` and
/// `recv_blocking`, the ports' tasks on the runtime.
#[test]
fn a_control_loop_on_its_own_thread() {
    let runtime = tokio::runtime::Runtime::new().unwrap();
    let (broker, addr) = runtime.block_on(leveret());
    let queue = unique("thread");
    let profile = profile(addr).queue(&queue).routing_key(&queue);
    let input = runtime
        .block_on(InPort::<TimedLong>::connect(profile.clone()))
        .expect("in-port");
    let output = runtime
        .block_on(OutPort::<TimedLong>::connect(profile))
        .expect("out-port");
    let control = std::thread::spawn(move || {
        assert!(input.recv_blocking(Duration::from_millis(20)).is_none());
        for data in 1..=20 {
            assert_eq!(output.put_blocking(&long(data)), PortStatus::Ok);
            let sample = input
                .recv_blocking(Duration::from_secs(10))
                .expect("the value back");
            assert_eq!(sample.value.data, data);
        }
    });
    control.join().expect("control loop");
    runtime.block_on(broker.shutdown());
}

/// An in-port's own queue outlives its reconnections but not its close.
#[tokio::test]
async fn an_in_ports_own_queue_goes_when_it_closes() {
    let (_broker, addr) = leveret().await;
    let exchange = unique("own");
    let base = profile(addr).exchange(&exchange, leveret_ports::ExchangeKind::Fanout);
    let input = InPort::<TimedLong>::connect(base).await.expect("in-port");
    let queue = input.queue();
    assert!(queue.as_bytes().starts_with(b"leveret.port."), "{queue:?}");
    let connection = leveret_client::Connection::connect(&format!("amqp://guest:guest@{addr}/%2f"))
        .await
        .unwrap();
    let passive = leveret_client::QueueDeclareOptions {
        passive: true,
        ..Default::default()
    };
    let channel = connection.open_channel().await.unwrap();
    let declared = channel
        .queue_declare(&queue, passive, leveret_client::FieldTable::new())
        .await;
    assert!(declared.is_ok(), "a named queue, not exclusive");
    input.close().await;
    let gone = channel
        .queue_declare(&queue, passive, leveret_client::FieldTable::new())
        .await;
    assert!(gone.is_err(), "deleted on close");
}
