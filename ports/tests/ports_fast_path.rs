//! The in-process fast path as the ports see it, on both runtimes: an
//! in-port on an embedded broker takes its deliveries on the broker's
//! dispatching thread (the client's inline deliveries), and nothing a
//! robot relies on changes: values arrive in order, once, with the
//! out-port's and in-port's counters true (`accepted == confirmed`,
//! `arrived == received`, nothing duplicate, out of order or lost), the
//! queue stays in the broker's listing and counts every message published,
//! delivered and acknowledged; an in-port over TCP on the same broker (a
//! remote robot) gets the same values through the socket, in order.

mod common;

use common::{unique, within};
use leveret_broker::{Broker, BrokerHandle};
use leveret_ports::{
    Connector, ExchangeKind, FullPolicy, InPort, InPortStats, OutPort, PortProfile, PortStatus,
    Time, TimedLong,
};
use leveret_tests::both_runtimes;
use std::sync::Arc;
use std::time::Duration;

/// Values read one by one, then a burst read after it was all put.
const ONE_BY_ONE: i32 = 300;
const BURST: i32 = 700;
const TOTAL: u64 = (ONE_BY_ONE + BURST) as u64;

async fn leveret() -> Arc<BrokerHandle> {
    let handle = Broker::builder()
        .listen("127.0.0.1:0".parse().unwrap())
        .start()
        .await
        .expect("start an embedded Leveret");
    Arc::new(handle)
}

/// An in-port and an out-port on `queue` of the embedded `broker`, both in
/// process.
async fn in_process_pair(
    broker: &Arc<BrokerHandle>,
    queue: &str,
) -> (InPort<TimedLong>, OutPort<TimedLong>) {
    in_process_pair_spinning(broker, queue, None).await
}

/// [`in_process_pair`] with `recv_blocking`'s spin up to `spin`.
async fn in_process_pair_spinning(
    broker: &Arc<BrokerHandle>,
    queue: &str,
    spin: Option<Duration>,
) -> (InPort<TimedLong>, OutPort<TimedLong>) {
    let profile = PortProfile::default()
        .queue(queue)
        .routing_key(queue)
        .buffer(2048, FullPolicy::DropOldest)
        .spin(spin);
    let local = Connector::in_process(broker);
    let input = within(
        "in-port",
        InPort::<TimedLong>::connect_with(local.clone(), profile.clone()),
    )
    .await
    .expect("in-port");
    let output = within(
        "out-port",
        OutPort::<TimedLong>::connect_with(local, profile),
    )
    .await
    .expect("out-port");
    (input, output)
}

fn long(data: i32) -> TimedLong {
    TimedLong {
        tm: Time::now(),
        data,
    }
}

/// Puts `ONE_BY_ONE` values each read before the next, then `BURST` more
/// read once all are put; checks every reader got all, in order.
async fn put_and_read(output: &OutPort<TimedLong>, inputs: &[&InPort<TimedLong>]) {
    let read = |data: i32| async move {
        for input in inputs {
            let sample = within("a value", input.recv()).await.expect("port open");
            assert_eq!(sample.value.data, data, "in order, none missing");
            assert_eq!(
                sample.seq,
                Some(data as u64 + 1),
                "the out-port's numbering"
            );
        }
    };
    for data in 0..ONE_BY_ONE {
        assert_eq!(output.try_put(&long(data)), PortStatus::Ok);
        read(data).await;
    }
    for data in ONE_BY_ONE..ONE_BY_ONE + BURST {
        assert_eq!(output.try_put(&long(data)), PortStatus::Ok);
    }
    for data in ONE_BY_ONE..ONE_BY_ONE + BURST {
        read(data).await;
    }
    within("every confirm", output.flush()).await;
    let stats = output.stats();
    assert_eq!(
        (stats.accepted, stats.confirmed, stats.pending),
        (TOTAL, TOTAL, 0)
    );
}

fn assert_all_received(stats: InPortStats) {
    assert_eq!(
        (stats.arrived, stats.received, stats.buffered),
        (TOTAL, TOTAL, 0),
        "{stats:?}"
    );
    assert_eq!(
        (
            stats.duplicates,
            stats.out_of_order,
            stats.lost,
            stats.stale,
            stats.dropped,
            stats.skipped
        ),
        (0, 0, 0, 0, 0, 0),
        "{stats:?}"
    );
}

#[both_runtimes]
async fn in_process_ports_keep_order_counters_and_the_queue_listing() {
    let broker = leveret().await;
    let queue = unique("fast-path");
    let (input, output) = in_process_pair(&broker, &queue).await;

    put_and_read(&output, &[&input]).await;
    assert_all_received(input.stats());

    // The queue is the broker's as ever: listed, with its consumer, every
    // message counted published, delivered and (once the in-port's acks
    // are in) acknowledged, none left.
    let listed = within("every ack counted", async {
        loop {
            let listed = broker
                .queues()
                .into_iter()
                .find(|q| q.name == queue)
                .expect("the port's queue is listed");
            if listed.message_stats.ack == TOTAL {
                break listed;
            }
            tokio::time::sleep(Duration::from_millis(10)).await;
        }
    })
    .await;
    assert_eq!(listed.consumers, 1);
    assert_eq!(
        (
            listed.message_stats.publish,
            listed.message_stats.deliver,
            listed.messages_ready,
            listed.messages_unacknowledged
        ),
        (TOTAL, TOTAL, 0, 0)
    );
    output.close().await;
    input.close().await;
}

#[both_runtimes]
async fn a_remote_in_port_beside_a_local_one_gets_the_same_values() {
    let broker = leveret().await;
    let addr = broker.local_addrs()[0];
    let exchange = unique("fast-path-fanout");
    let base = PortProfile::new(&format!("amqp://guest:guest@{addr}/%2f"))
        .expect("broker URI")
        .exchange(&exchange, ExchangeKind::Fanout)
        .buffer(2048, FullPolicy::DropOldest);
    let local = Connector::in_process(&broker);
    let near = within(
        "in-process in-port",
        InPort::<TimedLong>::connect_with(local.clone(), base.clone().queue(unique("near"))),
    )
    .await
    .expect("in-port");
    let far = within(
        "TCP in-port",
        InPort::<TimedLong>::connect(base.clone().queue(unique("far"))),
    )
    .await
    .expect("in-port");
    let output = within("out-port", OutPort::<TimedLong>::connect_with(local, base))
        .await
        .expect("out-port");

    put_and_read(&output, &[&near, &far]).await;
    assert_all_received(near.stats());
    assert_all_received(far.stats());
    output.close().await;
    near.close().await;
    far.close().await;
}

/// An `on_receive` callback is the application's code: it may call into
/// the broker, here listing the queues (each listed under its lock). It
/// runs on the reader, never on the dispatching thread that holds the
/// port's queue's lock, so nothing waits on itself.
#[both_runtimes]
async fn a_callback_that_calls_into_the_broker_runs_off_the_dispatching_thread() {
    let broker = leveret().await;
    let queue = unique("fast-path-callback");
    let (input, output) = in_process_pair(&broker, &queue).await;
    let seen = Arc::new(std::sync::atomic::AtomicU64::new(0));
    let (in_callback, listing) = (Arc::clone(&seen), Arc::clone(&broker));
    input.on_receive(move |_| {
        // Every queue's figures, the port's own among them, each read
        // under its queue's lock.
        assert!(!listing.queues().is_empty());
        in_callback.fetch_add(1, std::sync::atomic::Ordering::SeqCst);
    });
    put_and_read(&output, &[&input]).await;
    assert_eq!(seen.load(std::sync::atomic::Ordering::SeqCst), TOTAL);
    assert_all_received(input.stats());
    output.close().await;
    input.close().await;
}

/// Persistent values put in process into a durable queue are on disk once
/// confirmed, whichever thread handled their publish (the putting thread
/// on the fast path): a broker started again on the same data directory
/// has every one of them, and the out-port's counters add up.
#[both_runtimes]
async fn confirmed_persistent_puts_survive_a_restart() {
    const COUNT: i32 = 200;
    let dir = tempfile::tempdir().expect("tempdir");
    let broker = Arc::new(
        Broker::builder()
            .data_dir(dir.path())
            .start()
            .await
            .expect("start"),
    );
    let queue = unique("durable-fast");
    let profile = PortProfile::default()
        .queue(&queue)
        .routing_key(&queue)
        .durable(true);
    let output = within(
        "out-port",
        OutPort::<TimedLong>::connect_with(Connector::in_process(&broker), profile),
    )
    .await
    .expect("out-port");
    for data in 0..COUNT {
        assert_eq!(output.try_put(&long(data)), PortStatus::Ok);
        // One at a time, so most take the fast path (nothing waits before
        // them).
        within("confirmed", output.flush()).await;
    }
    let stats = output.stats();
    assert_eq!(
        (stats.accepted, stats.confirmed, stats.pending),
        (COUNT as u64, COUNT as u64, 0),
        "{stats:?}"
    );
    output.close().await;
    Arc::into_inner(broker)
        .expect("the only handle")
        .shutdown()
        .await;
    let again = Broker::builder()
        .data_dir(dir.path())
        .start()
        .await
        .expect("restart on the same data directory");
    let listed = again
        .queues()
        .into_iter()
        .find(|q| q.name == queue)
        .expect("the durable queue is back");
    assert_eq!(listed.messages_ready, COUNT as u64, "every confirmed value");
    again.shutdown().await;
}

/// This thread's CPU time and voluntary context switches so far, from
/// `/proc/thread-self` (what `getrusage(RUSAGE_THREAD)` reports).
#[cfg(target_os = "linux")]
fn thread_usage() -> (Duration, u64) {
    let schedstat = std::fs::read_to_string("/proc/thread-self/schedstat").expect("schedstat");
    let cpu_ns: u64 = schedstat
        .split_whitespace()
        .next()
        .and_then(|ns| ns.parse().ok())
        .expect("cpu time");
    let status = std::fs::read_to_string("/proc/thread-self/status").expect("status");
    let voluntary = status
        .lines()
        .find_map(|line| line.strip_prefix("voluntary_ctxt_switches:"))
        .and_then(|count| count.trim().parse().ok())
        .expect("voluntary_ctxt_switches");
    (Duration::from_nanos(cpu_ns), voluntary)
}

/// With the spin on (`PortProfile::spin`), `recv_blocking` spins at most
/// its ceiling before its thread sleeps, and no more: an idle in-port's
/// receiver sleeps through each wait (a voluntary context switch per wait)
/// and uses a small part of the time it waited in CPU; a value put
/// meanwhile is still received, once, in order. Reads `/proc`: Linux only.
#[cfg(target_os = "linux")]
#[both_runtimes]
async fn an_idle_in_ports_blocking_receiver_sleeps_after_a_bounded_spin() {
    const WAITS: u32 = 10;
    const WAIT: Duration = Duration::from_millis(50);
    let broker = leveret().await;
    let queue = unique("fast-path-idle");
    let (input, output) =
        in_process_pair_spinning(&broker, &queue, Some(Duration::from_micros(64))).await;
    let receiver = std::thread::spawn(move || {
        let (cpu_before, switches_before) = thread_usage();
        for _ in 0..WAITS {
            assert!(input.recv_blocking(WAIT).is_none(), "nothing was put");
        }
        let (cpu_after, switches_after) = thread_usage();
        (
            input,
            cpu_after - cpu_before,
            switches_after - switches_before,
        )
    });
    let (input, cpu, switches) =
        tokio::task::spawn_blocking(move || receiver.join().expect("receiver"))
            .await
            .expect("join");
    // A wait whose thread the scheduler held off the CPU past its whole
    // deadline (a loaded machine) returns without sleeping: most waits
    // must have slept, which a receiver that only spun never does.
    assert!(
        switches >= u64::from(WAITS / 2),
        "waits slept: {switches} voluntary switches in {WAITS} waits"
    );
    assert!(
        cpu < WAIT * WAITS / 2,
        "spun {cpu:?} of {:?} waited",
        WAIT * WAITS
    );
    // A value comes through a receiver that slept.
    assert_eq!(output.try_put(&long(7)), PortStatus::Ok);
    let (input, sample) = tokio::task::spawn_blocking(move || {
        let sample = input.recv_blocking(Duration::from_secs(10));
        (input, sample)
    })
    .await
    .expect("join");
    assert_eq!(sample.expect("the value").value.data, 7);
    assert_eq!(input.stats().received, 1);
    output.close().await;
    input.close().await;
}

/// A put that takes the fast path (its connection's loop free, nothing
/// before it) is settled before `try_put` returns, on the putting thread
/// alone: the value is in the in-port's buffer, the in-port's ack has been
/// handled by its connection's loop (run on this thread: the message is
/// acknowledged in the queue's listing) and the out-port's confirm has come
/// and been counted (`confirmed`, nothing pending), so no broker or port
/// task needs waking for it. On the current-thread runtime no task can run
/// between the put and the checks, so each holds at once; on the
/// multi-thread one, eventually.
#[both_runtimes]
async fn a_fast_path_put_is_delivered_acknowledged_and_confirmed_before_it_returns() {
    const PUTS: i32 = 50;
    let broker = leveret().await;
    let queue = unique("fast-path-settled");
    let (input, output) = in_process_pair(&broker, &queue).await;
    let at_once = tokio::runtime::Handle::current().runtime_flavor()
        == tokio::runtime::RuntimeFlavor::CurrentThread;
    let acked = |broker: &BrokerHandle| {
        let listed = broker
            .queues()
            .into_iter()
            .find(|q| q.name == queue)
            .expect("the port's queue is listed");
        (
            listed.message_stats.ack,
            listed.messages_ready,
            listed.messages_unacknowledged,
        )
    };
    for data in 0..PUTS {
        let done = data as u64 + 1;
        assert_eq!(output.try_put(&long(data)), PortStatus::Ok);
        if at_once {
            let sample = input
                .try_recv()
                .expect("in the buffer when the put returned");
            assert_eq!(sample.value.data, data);
            let stats = output.stats();
            assert_eq!((stats.confirmed, stats.pending), (done, 0), "{stats:?}");
            assert_eq!(acked(&broker), (done, 0, 0), "acknowledged already");
        } else {
            let sample = within("the value", input.recv()).await.expect("open");
            assert_eq!(sample.value.data, data);
            within("the confirm", output.flush()).await;
            within("the ack", async {
                while acked(&broker) != (done, 0, 0) {
                    tokio::time::sleep(Duration::from_millis(5)).await;
                }
            })
            .await;
        }
    }
    let stats = output.stats();
    assert_eq!(
        (
            stats.accepted,
            stats.confirmed,
            stats.settled(),
            stats.pending
        ),
        (PUTS as u64, PUTS as u64, PUTS as u64, 0)
    );
    output.close().await;
    input.close().await;
}
