//! An out-port publishing a robot's pose (`RTC::TimedPose2D`, CDR) at
//! 100 Hz to the fanout exchange `poses`, printing the port's statistics
//! every second.
//!
//! ```text
//! cargo run -p leveret-ports --example pose_out -- [amqp://guest:guest@localhost:5672/%2f] [seconds]
//! ```
//! Run `pose_in` against the same broker to receive the poses.

use leveret_ports::{
    ExchangeKind, OutPort, Point2D, PortProfile, PortStatus, Pose2D, Time, TimedPose2D,
};
use std::time::Duration;

#[tokio::main]
async fn main() -> Result<(), Box<dyn std::error::Error>> {
    let mut args = std::env::args().skip(1);
    let url = args
        .next()
        .unwrap_or_else(|| "amqp://guest:guest@localhost:5672/%2f".to_owned());
    let seconds: Option<u64> = args.next().map(|s| s.parse()).transpose()?;
    let profile = PortProfile::new(&url)?
        .exchange("poses", ExchangeKind::Fanout)
        .put_timeout(Duration::from_millis(50));
    let port = OutPort::<TimedPose2D>::connect(profile).await?;
    println!("publishing TimedPose2D at 100 Hz to {url} (exchange poses)");

    let mut tick = tokio::time::interval(Duration::from_millis(10));
    tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Skip);
    let mut report = tokio::time::interval(Duration::from_secs(1));
    let deadline = seconds.map(|s| tokio::time::Instant::now() + Duration::from_secs(s));
    let mut step = 0u64;
    loop {
        tokio::select! {
            _ = tick.tick() => {
                // Drive around a circle of radius 2 m, one lap per 20 s.
                let angle = step as f64 * std::f64::consts::TAU / 2000.0;
                let pose = TimedPose2D {
                    tm: Time::now(),
                    data: Pose2D {
                        position: Point2D { x: 2.0 * angle.cos(), y: 2.0 * angle.sin() },
                        heading: angle + std::f64::consts::FRAC_PI_2,
                    },
                };
                match port.put(&pose).await {
                    PortStatus::Ok => {}
                    status => eprintln!("put #{step}: {status:?}"),
                }
                step += 1;
            }
            _ = report.tick() => {
                let link = port.link().borrow().clone();
                println!("{:?} link up: {} (connects {})", port.stats(), link.up, link.connects);
            }
            _ = tokio::signal::ctrl_c() => break,
            _ = async { match deadline {
                Some(at) => tokio::time::sleep_until(at).await,
                None => std::future::pending().await,
            } } => break,
        }
    }
    tokio::time::timeout(Duration::from_secs(5), port.flush())
        .await
        .ok();
    println!("final {:?}", port.stats());
    port.close().await;
    Ok(())
}
