//! An in-port receiving the poses `pose_out` publishes (fanout exchange
//! `poses`), printing one pose in ten and the port's statistics (received,
//! lost, out of order, duplicates, latency) every second.
//!
//! ```text
//! cargo run -p leveret-ports --example pose_in -- [amqp://guest:guest@localhost:5672/%2f] [seconds]
//! ```

use leveret_ports::{ExchangeKind, FullPolicy, InPort, PortProfile, TimedPose2D};
use std::time::Duration;

#[tokio::main]
async fn main() -> Result<(), Box<dyn std::error::Error>> {
    let mut args = std::env::args().skip(1);
    let url = args
        .next()
        .unwrap_or_else(|| "amqp://guest:guest@localhost:5672/%2f".to_owned());
    let seconds: Option<u64> = args.next().map(|s| s.parse()).transpose()?;
    // A server-named queue bound to the fanout: every in-port gets every
    // pose. Lossless buffering: the broker holds what we have not taken.
    let profile = PortProfile::new(&url)?
        .exchange("poses", ExchangeKind::Fanout)
        .buffer(1000, FullPolicy::BlockBroker);
    let port = InPort::<TimedPose2D>::connect(profile).await?;
    println!("receiving TimedPose2D from {url} (queue {})", port.queue());

    let mut report = tokio::time::interval(Duration::from_secs(1));
    let deadline = seconds.map(|s| tokio::time::Instant::now() + Duration::from_secs(s));
    loop {
        tokio::select! {
            sample = port.recv() => {
                let Some(sample) = sample else { break };
                if sample.seq.is_some_and(|seq| seq % 10 == 0) {
                    let p = sample.value.data;
                    println!(
                        "#{:>6} x {:+.3} y {:+.3} heading {:+.3} latency {:?}",
                        sample.seq.unwrap_or(0), p.position.x, p.position.y, p.heading,
                        sample.latency.unwrap_or_default()
                    );
                }
            }
            _ = report.tick() => {
                let s = port.stats();
                println!(
                    "received {} lost {} out-of-order {} duplicates {} dropped {} latency mean {:?} max {:?}",
                    s.received, s.lost, s.out_of_order, s.duplicates, s.dropped,
                    s.latency.mean(), s.latency.max
                );
            }
            _ = tokio::signal::ctrl_c() => break,
            _ = async { match deadline {
                Some(at) => tokio::time::sleep_until(at).await,
                None => std::future::pending().await,
            } } => break,
        }
    }
    println!("final {:?}", port.stats());
    port.close().await;
    Ok(())
}
