//! A shovel through a faulty link (leveret-tests' fault proxy between the
//! robot and the fleet broker): the link gone for a minute
//! (`LEVERET_UPLINK_OUTAGE_SECS` for a longer run) while the robot keeps
//! publishing, with the drain starting at the first attempt after its
//! return (attempts are at most 5 s apart); 200 ms
//! of latency with 256 kbit/s; connections cut in the middle of a frame,
//! again and again. Every message confirmed to the robot arrives; with
//! the client's `Dedupe` (message ids), exactly once, in order.

use leveret_broker::{Broker, BrokerHandle};
use leveret_client::{
    BasicGetOptions, BasicProperties, BasicPublishOptions, Channel, Connection, Dedupe, FieldTable,
    QueueDeclareOptions, ShortStr,
};
use leveret_test_macros::both_runtimes;
use leveret_tests::fault_proxy::FaultProxy;
use leveret_uplink::{Shovel, ShovelConfig, ShovelState};
use serde_json::json;
use std::sync::Arc;
use std::time::Duration;
use tokio::time::Instant;

struct Link {
    robot: Arc<BrokerHandle>,
    fleet: BrokerHandle,
    proxy: FaultProxy,
    publisher: Channel,
    _local: Connection,
    fleet_channel: Channel,
    _fleet_connection: Connection,
    shovel: Option<Shovel>,
}

async fn link(reconnect_delay: f64) -> Link {
    let robot = Arc::new(Broker::builder().start().await.expect("robot"));
    let local = Connection::in_process(&robot).await.expect("local");
    let publisher = local.open_channel().await.expect("channel");
    publisher.confirm_select().await.expect("confirms");
    let durable = QueueDeclareOptions {
        durable: true,
        ..Default::default()
    };
    publisher
        .queue_declare("telemetry", durable, FieldTable::new())
        .await
        .expect("declare");
    let fleet = Broker::builder()
        .listen("127.0.0.1:0".parse().unwrap())
        .start()
        .await
        .expect("fleet");
    let proxy = FaultProxy::start(fleet.local_addrs()[0]).await;
    let fleet_connection = Connection::connect(&format!(
        "amqp://guest:guest@{}/%2f",
        fleet.local_addrs()[0]
    ))
    .await
    .expect("fleet");
    let fleet_channel = fleet_connection.open_channel().await.expect("channel");
    fleet_channel
        .queue_declare("telemetry", durable, FieldTable::new())
        .await
        .expect("declare");
    let config = ShovelConfig::from_json(&json!({
        "src-uri": "amqp://", "src-queue": "telemetry", "src-prefetch-count": 64,
        "dest-uri": format!("amqp://guest:guest@{}/%2f?heartbeat=2", proxy.addr),
        "dest-queue": "telemetry", "reconnect-delay": reconnect_delay,
    }))
    .expect("parameters");
    let shovel = Shovel::start("faults", config, Some(&robot));
    Link {
        robot,
        fleet,
        proxy,
        publisher,
        _local: local,
        fleet_channel,
        _fleet_connection: fleet_connection,
        shovel: Some(shovel),
    }
}

impl Link {
    fn shovel(&self) -> &Shovel {
        self.shovel.as_ref().expect("running")
    }

    async fn publish(&self, from: u32, to: u32, size: usize) {
        for n in from..to {
            let mut body = format!("{n}:").into_bytes();
            body.resize(size.max(body.len()), b'.');
            let properties = BasicProperties {
                delivery_mode: Some(2),
                message_id: ShortStr::try_from(format!("m-{n}")).ok(),
                ..Default::default()
            };
            let confirm = self
                .publisher
                .basic_publish(
                    "",
                    "telemetry",
                    BasicPublishOptions::default(),
                    properties,
                    body.into(),
                )
                .await
                .expect("publish");
            assert!(confirm.await.expect("confirm").is_ack());
        }
    }

    /// Waits (up to `within`) for `count` distinct messages at the fleet;
    /// them in order of first arrival, and how many came twice.
    async fn arrived(&self, count: usize, within: Duration) -> (Vec<u32>, usize) {
        let mut dedupe = Dedupe::new(100_000);
        let (mut first, mut duplicates) = (Vec::new(), 0);
        let deadline = Instant::now() + within;
        while first.len() < count {
            assert!(
                Instant::now() < deadline,
                "{} of {count} arrived: {:?}",
                first.len(),
                self.shovel().status()
            );
            match self
                .fleet_channel
                .basic_get("telemetry", BasicGetOptions { no_ack: true })
                .await
                .expect("get")
            {
                Some(message) => {
                    let n = String::from_utf8_lossy(&message.body)
                        .split(':')
                        .next()
                        .and_then(|n| n.parse().ok())
                        .expect("numbered");
                    if dedupe.first_time(&message.delivery.properties) {
                        first.push(n);
                    } else {
                        duplicates += 1;
                    }
                }
                None => tokio::time::sleep(Duration::from_millis(20)).await,
            }
        }
        (first, duplicates)
    }

    async fn finish(mut self) {
        if let Some(shovel) = self.shovel.take() {
            shovel.stop().await;
        }
        self.fleet.shutdown().await;
        drop(self.robot);
    }
}

fn in_order(first: &[u32], count: u32) {
    assert_eq!(
        first,
        (0..count).collect::<Vec<_>>().as_slice(),
        "all, in order"
    );
}

/// The link gone for a minute while 500 messages are confirmed on the
/// robot; the drain starts at the shovel's first attempt after its return.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_minute_without_the_link_loses_nothing() {
    let outage = std::env::var("LEVERET_UPLINK_OUTAGE_SECS")
        .ok()
        .and_then(|s| s.parse().ok())
        .unwrap_or(60u64);
    let mut link = link(1.0).await;
    link.publish(0, 100, 64).await;
    let mut watch = link.shovel().watch();
    watch.wait_for(|s| s.forwarded >= 100).await.expect("alive");
    let addr = link.proxy.addr;
    let fleet_addr = link.fleet.local_addrs()[0];
    link.proxy.stop().await;
    let went = Instant::now();
    link.publish(100, 600, 64).await;
    tokio::time::timeout(
        Duration::from_secs(30),
        watch.wait_for(|s| s.state != ShovelState::Running),
    )
    .await
    .expect("the loss noticed (heartbeats)")
    .expect("alive");
    tokio::time::sleep_until(went + Duration::from_secs(outage)).await;
    let before = link.shovel().status().forwarded;
    link.proxy = FaultProxy::start_at(addr, fleet_addr).await;
    let back = Instant::now();
    let failures_before = link.shovel().status().restarts;
    // The shovel's own decision: its next attempt comes within its capped
    // backoff (5 s at most: `backoff_doubles_jitters_and_is_capped`), and
    // that attempt drains. One more failure is allowed, an attempt refused
    // just before the proxy listened again; a wall-clock bound here would
    // measure the machine.
    let drained = tokio::time::timeout(
        Duration::from_secs(30),
        watch.wait_for(|s| s.forwarded > before),
    )
    .await
    .unwrap_or_else(|_| {
        panic!(
            "no drain within 30 s of the link's return: {:?}",
            link.shovel().status()
        )
    })
    .expect("alive")
    .clone();
    assert!(
        drained.restarts <= failures_before + 1,
        "the first attempts after the link's return drain: {failures_before} restarts before, {drained:?}"
    );
    eprintln!("drain started {:?} after the link returned", back.elapsed());
    let (first, duplicates) = link.arrived(600, Duration::from_secs(60)).await;
    in_order(&first, 600);
    eprintln!("{outage} s outage: 600 of 600, {duplicates} duplicates before dedupe");
    link.finish().await;
}

#[both_runtimes]
async fn latency_and_a_slow_link_deliver_everything_in_order() {
    let link = link(0.2).await;
    link.proxy.set(|f| {
        f.latency = Duration::from_millis(200);
        f.bandwidth = Some(32_000);
    });
    link.publish(0, 200, 100).await;
    let (first, duplicates) = link.arrived(200, Duration::from_secs(60)).await;
    in_order(&first, 200);
    assert_eq!(duplicates, 0, "a slow link is not a broken one");
    link.finish().await;
}

#[both_runtimes]
async fn connections_cut_mid_frame_lose_nothing() {
    let link = link(0.1).await;
    // Each connection gets 1,500 bytes (the handshake and a message or
    // so), then breaks inside a frame; five times, while the robot
    // publishes.
    link.proxy.set(|f| f.cut_after = Some(1500));
    let cuts = async {
        for round in 0..5 {
            while link.proxy.faults().cut_after != Some(0) {
                tokio::time::sleep(Duration::from_millis(5)).await;
            }
            tokio::time::sleep(Duration::from_millis(100)).await;
            let budget = if round < 4 { Some(1500) } else { None };
            link.proxy.set(|f| f.cut_after = budget);
        }
    };
    tokio::join!(link.publish(0, 300, 1000), cuts);
    let (first, duplicates) = link.arrived(300, Duration::from_secs(60)).await;
    in_order(&first, 300);
    eprintln!("5 cuts mid-frame: 300 of 300, {duplicates} duplicates before dedupe");
    assert!(
        link.shovel().status().restarts >= 5,
        "{:?}",
        link.shovel().status()
    );
    link.finish().await;
}
