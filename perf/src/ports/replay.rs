//! The `ports-replay` scenario: the recorder's figures the tests do not
//! assert. An embedded Leveret with a data directory (removed at the end)
//! listens on loopback; an out-port puts `TimedPose2D` at the given rate
//! for the given time, first without recording, then with its profile
//! recording to a stream (the puts' wall time per phase, p50/p99/max: what
//! recording costs `put`), with a live in-port reading. Then a `Player`
//! plays the recording at each rate asked for: per playback, the values
//! played, the recorded span of send times, the wall time the playback
//! took against the recorded span divided by the rate, and how late each
//! value came against its due time (p50/p99/max).

use crate::Result;
use leveret_broker::Broker;
use leveret_ports::{
    ExchangeKind, InPort, OutPort, PlayOptions, Player, PortProfile, Pose2D, Position, Recording,
    Time, TimedPose2D,
};
use std::time::{Duration, Instant};

/// The options of `ports-replay`.
#[derive(Debug, Clone, clap::Args)]
pub struct ReplayArgs {
    /// Puts per second.
    #[arg(long, default_value_t = 100)]
    pub hz: u32,
    /// Seconds recorded (and as many put before, without recording).
    #[arg(long, default_value_t = 5.0)]
    pub seconds: f64,
    /// Playback rates (0: as fast as possible).
    #[arg(long, value_delimiter = ',', default_value = "1,10,0")]
    pub rates: Vec<f64>,
}

/// The value at quantile `q` of sorted `values`.
fn at(values: &[Duration], q: f64) -> Duration {
    values
        .get((values.len().saturating_sub(1) as f64 * q) as usize)
        .copied()
        .unwrap_or_default()
}

/// Puts `count` poses at `hz`; each put's wall time, sorted.
async fn put_phase(output: &OutPort<TimedPose2D>, hz: u32, count: u64) -> Vec<Duration> {
    let mut tick = tokio::time::interval(Duration::from_secs(1) / hz.max(1));
    let mut puts = Vec::new();
    for i in 0..count {
        tick.tick().await;
        let pose = TimedPose2D {
            tm: Time::now(),
            data: Pose2D {
                heading: i as f64,
                ..Default::default()
            },
        };
        let started = Instant::now();
        output.put(&pose).await;
        puts.push(started.elapsed());
    }
    puts.sort();
    puts
}

/// Runs the scenario and prints its figures.
pub async fn run(args: &ReplayArgs) -> Result<()> {
    let dir = std::env::temp_dir().join(format!("leveret-perf-replay-{}", std::process::id()));
    let broker = Broker::builder()
        .listen("127.0.0.1:0".parse().map_err(|e| format!("{e}"))?)
        .data_dir(&dir)
        .start()
        .await
        .map_err(|e| format!("starting the broker: {e}"))?;
    let addr = broker.local_addrs()[0];
    let base = PortProfile::new(&format!("amqp://guest:guest@{addr}/%2f"))?
        .exchange("poses", ExchangeKind::Fanout)
        .announce_interval(None);
    let recorded = base
        .clone()
        .record(Recording::to("poses.rec").max_age("1h"));
    let live = InPort::<TimedPose2D>::connect(base.clone()).await?;
    let reader = tokio::spawn(async move { while live.recv().await.is_some() {} });
    let count = (f64::from(args.hz) * args.seconds) as u64;
    println!(
        "ports-replay: TimedPose2D at {} Hz, {count} puts per phase, embedded Leveret over loopback TCP",
        args.hz
    );
    for (name, profile) in [("plain", base), ("recording", recorded.clone())] {
        let output = OutPort::<TimedPose2D>::connect(profile).await?;
        let puts = put_phase(&output, args.hz, count).await;
        println!(
            "{name:>10}: put p50 {:?}, p99 {:?}, max {:?}; {:?}",
            at(&puts, 0.5),
            at(&puts, 0.99),
            at(&puts, 1.0),
            output.stats()
        );
        output.close().await;
    }
    for &rate in &args.rates {
        let options = PlayOptions {
            start: Position::First,
            end: Some(Position::Offset(count - 1)),
            rate: (rate > 0.0).then_some(rate),
            idle: None,
        };
        let mut player = Player::<TimedPose2D>::open(&recorded, options).await?;
        let started = Instant::now();
        let mut first_sent = None;
        let mut late = Vec::new();
        let mut played = 0u64;
        let mut span = Duration::ZERO;
        while let Some(value) = player.next().await? {
            let now = started.elapsed();
            let sent = value
                .sample
                .sent_at
                .ok_or("a value without its send time")?;
            let first = *first_sent.get_or_insert(sent);
            span = sent.duration_since(first).unwrap_or_default();
            if rate > 0.0 {
                late.push(now.saturating_sub(span.div_f64(rate)));
            }
            played += 1;
        }
        let wall = started.elapsed();
        player.close().await;
        late.sort();
        let pace = if rate > 0.0 {
            format!(
                "due {:?}; late p50 {:?}, p99 {:?}, max {:?}",
                span.div_f64(rate),
                at(&late, 0.5),
                at(&late, 0.99),
                at(&late, 1.0)
            )
        } else {
            format!("{:.0} values/s", played as f64 / wall.as_secs_f64())
        };
        println!(
            "replay {}: {played} values, recorded span {span:?}, took {wall:?}; {pace}",
            if rate > 0.0 {
                format!("{rate}x")
            } else {
                "fast".to_owned()
            }
        );
    }
    reader.abort();
    drop(broker);
    let _ = std::fs::remove_dir_all(&dir);
    Ok(())
}
