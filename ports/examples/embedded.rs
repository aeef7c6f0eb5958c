//! A robot with its own broker: Leveret embedded in the process, the
//! robot's own ports connected in-process (no network, no TCP stack), and a
//! TCP listener so remote robots and tools can connect too, e.g.
//! `pose_in amqp://guest:guest@127.0.0.1:5673/%2f`.
//!
//! The local out-port publishes poses to the fanout exchange `poses` at
//! 100 Hz; a local in-port reads the newest pose each 100 ms control cycle.
//!
//! ```text
//! cargo run -p leveret-ports --example embedded --features embedded -- [127.0.0.1:5673] [seconds]
//! ```

use leveret_broker::Broker;
use leveret_ports::{
    Connector, ExchangeKind, InPort, OutPort, Point2D, PortProfile, Pose2D, Time, TimedPose2D,
};
use std::sync::Arc;
use std::time::Duration;

#[tokio::main]
async fn main() -> Result<(), Box<dyn std::error::Error>> {
    let mut args = std::env::args().skip(1);
    let listen = args.next().unwrap_or_else(|| "127.0.0.1:5673".to_owned());
    let seconds: Option<u64> = args.next().map(|s| s.parse()).transpose()?;
    let broker = Arc::new(Broker::builder().listen(listen.parse()?).start().await?);
    println!(
        "embedded Leveret; remote robots: amqp://guest:guest@{}/%2f",
        broker.local_addrs()[0]
    );

    // The same profile as over TCP; only the connector differs.
    let profile = PortProfile::default().exchange("poses", ExchangeKind::Fanout);
    let local = Connector::in_process(&broker);
    let output = OutPort::<TimedPose2D>::connect_with(local.clone(), profile.clone()).await?;
    let input = InPort::<TimedPose2D>::connect_with(local, profile).await?;

    let mut tick = tokio::time::interval(Duration::from_millis(10));
    let mut control = tokio::time::interval(Duration::from_millis(100));
    let deadline = seconds.map(|s| tokio::time::Instant::now() + Duration::from_secs(s));
    let mut x = 0.0;
    loop {
        tokio::select! {
            _ = tick.tick() => {
                x += 0.01;
                let pose = TimedPose2D {
                    tm: Time::now(),
                    data: Pose2D { position: Point2D { x, y: 0.0 }, heading: 0.0 },
                };
                output.put(&pose).await;
            }
            _ = control.tick() => {
                if let Some(sample) = input.read() {
                    println!(
                        "control cycle: newest pose x {:.2} (seq {:?}, latency {:?})",
                        sample.value.data.position.x, sample.seq, sample.latency.unwrap_or_default()
                    );
                }
            }
            _ = tokio::signal::ctrl_c() => break,
            _ = async { match deadline {
                Some(at) => tokio::time::sleep_until(at).await,
                None => std::future::pending().await,
            } } => break,
        }
    }
    println!("out-port {:?}\nin-port {:?}", output.stats(), input.stats());
    output.close().await;
    input.close().await;
    // The connectors hold the broker weakly: it can be taken back to shut
    // it down cleanly.
    if let Ok(broker) = Arc::try_unwrap(broker) {
        broker.shutdown().await;
    }
    Ok(())
}
