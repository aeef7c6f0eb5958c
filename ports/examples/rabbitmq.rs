//! Ports against RabbitMQ (or any AMQP 0.9.1 broker): velocity commands
//! (`RTC::TimedVelocity2D`) sent to a robot through a durable queue with
//! persistent messages and publisher confirms, so commands survive a broker
//! restart and are each executed once, in order.
//!
//! ```text
//! cargo run -p leveret-ports --example rabbitmq -- [amqp://guest:guest@localhost:5672/%2f] [count]
//! ```

use leveret_ports::{
    FullPolicy, InPort, OutPort, PortProfile, PortStatus, Time, TimedVelocity2D, Velocity2D,
};
use std::time::Duration;

#[tokio::main]
async fn main() -> Result<(), Box<dyn std::error::Error>> {
    let mut args = std::env::args().skip(1);
    let url = args
        .next()
        .unwrap_or_else(|| "amqp://guest:guest@localhost:5672/%2f".to_owned());
    let count: u32 = args.next().map(|s| s.parse()).transpose()?.unwrap_or(100);

    // Point to point through the default exchange: the routing key is the
    // queue's name. The profile could equally come from OpenRTM connector
    // properties with `PortProfile::from_properties`.
    let profile = PortProfile::new(&url)?
        .queue("leveret.example.cmd_vel")
        .routing_key("leveret.example.cmd_vel")
        .durable(true)
        .buffer(16, FullPolicy::BlockBroker)
        .put_timeout(Duration::from_secs(1));
    let robot = InPort::<TimedVelocity2D>::connect(profile.clone()).await?;
    let controller = OutPort::<TimedVelocity2D>::connect(profile).await?;
    let server = controller.link().borrow().clone();
    println!("connected to {url} ({server:?})");

    let sender = async {
        for i in 0..count {
            let command = TimedVelocity2D {
                tm: Time::now(),
                data: Velocity2D {
                    vx: 0.2,
                    vy: 0.0,
                    va: (f64::from(i) / 10.0).sin(),
                },
            };
            let status = controller.put(&command).await;
            if status != PortStatus::Ok {
                eprintln!("command {i}: {status:?}");
            }
        }
    };
    let executor = async {
        for _ in 0..count {
            let Some(sample) = robot.recv().await else {
                break;
            };
            let v = sample.value.data;
            if sample.seq.is_some_and(|s| s % 20 == 0) {
                println!(
                    "cmd #{:?}: vx {:.2} va {:+.3} ({:?} after put)",
                    sample.seq,
                    v.vx,
                    v.va,
                    sample.latency.unwrap_or_default()
                );
            }
        }
    };
    tokio::join!(sender, executor);
    println!("controller {:?}", controller.stats());
    println!("robot      {:?}", robot.stats());
    controller.close().await;
    robot.close().await;
    Ok(())
}
