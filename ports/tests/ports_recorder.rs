//! Ports as a flight recorder (issue 33, item 3): an out-port whose
//! profile records to a stream, the recording played back by a `Player`
//! from an offset or a time, to an end, at the recorded pace or faster,
//! with the original sequence numbers and send times. On both runtimes,
//! against an embedded Leveret with a data directory (streams live on
//! disk), or the broker LEVERET_TEST_AMQP_URL names (RabbitMQ 3.10
//! passes them). The tests assert values, counts and order, never wall-clock
//! figures.

mod common;

use common::{unique, within, without_waiting};
use leveret_broker::{Broker, BrokerHandle};
use leveret_client::Error;
use leveret_ports::{
    Connector, ExchangeKind, FullPolicy, InPort, OutPort, PlayOptions, Playback, Player, Point2D,
    PortProfile, PortStatus, Pose2D, Position, Recording, Replayed, Sample, Time, TimedLong,
    TimedPose2D,
};
use leveret_tests::both_runtimes;
use std::sync::Arc;
use std::time::Duration;

/// The broker the tests use: an embedded Leveret with a data directory
/// (removed with it), or, with LEVERET_TEST_AMQP_URL set, that broker.
struct Env {
    uri: String,
    leveret: Option<Arc<BrokerHandle>>,
    _dir: tempfile::TempDir,
}

impl Env {
    async fn new() -> Env {
        let dir = tempfile::tempdir().expect("tempdir");
        if let Ok(uri) = std::env::var("LEVERET_TEST_AMQP_URL") {
            if !uri.is_empty() {
                return Env {
                    uri,
                    leveret: None,
                    _dir: dir,
                };
            }
        }
        let handle = Broker::builder()
            .listen("127.0.0.1:0".parse().unwrap())
            .data_dir(dir.path())
            .start()
            .await
            .expect("start an embedded Leveret");
        let addr = handle.local_addrs()[0];
        Env {
            uri: format!("amqp://guest:guest@{addr}/%2f"),
            leveret: Some(Arc::new(handle)),
            _dir: dir,
        }
    }

    fn profile(&self) -> PortProfile {
        PortProfile::new(&self.uri)
            .expect("uri")
            .buffer(100_000, FullPolicy::BlockBroker)
            .announce_interval(None)
    }

    /// In-process to the embedded Leveret, else TCP.
    fn connector(&self) -> Connector {
        match &self.leveret {
            Some(leveret) => Connector::in_process(leveret),
            None => Connector::from(&self.profile()),
        }
    }
}

/// Waits until the broker has confirmed `count` of the out-port's values.
async fn confirmed<T: leveret_ports::PortData>(output: &OutPort<T>, count: u64) {
    let mut stats = output.watch_stats();
    within(
        "the broker confirms every value",
        stats.wait_for(|s| s.confirmed >= count),
    )
    .await
    .expect("port alive");
}

/// Plays everything `player` yields.
async fn play_all<T: leveret_ports::PortData>(mut player: Player<T>) -> Vec<Replayed<T>> {
    let mut played = Vec::new();
    while let Some(replayed) = within("the next played value", player.next())
        .await
        .expect("playback")
    {
        played.push(replayed);
    }
    assert_eq!(player.decode_errors(), 0);
    player.close().await;
    played
}

/// The span of `samples`' send times.
fn span<T>(samples: &[Sample<T>]) -> Duration {
    let first = samples.first().and_then(|s| s.sent_at).expect("sent_at");
    let last = samples.last().and_then(|s| s.sent_at).expect("sent_at");
    last.duration_since(first).expect("in order")
}

/// The recorder test, scaled to CI: 100 Hz `TimedPose2D` for two
/// seconds through a fanout exchange with a live in-port, recorded; played
/// back at 1× and at 10×, each gives the live reader's sequence exactly:
/// the same values, sequence numbers and send times, in order (so the
/// played span of recorded send times is the original's).
#[both_runtimes]
async fn a_recorded_run_replays_identically_at_1x_and_10x() {
    const VALUES: u64 = 200;
    let env = Env::new().await;
    let stream = unique("poses-recording");
    let base = env
        .profile()
        .exchange(unique("poses"), ExchangeKind::Fanout);
    let recorded = base.clone().record(
        Recording::to(&stream)
            .max_age("1h")
            .max_length_bytes(64 << 20),
    );
    let live = InPort::<TimedPose2D>::connect(base).await.expect("in-port");
    let output = OutPort::<TimedPose2D>::connect(recorded.clone())
        .await
        .expect("out-port");

    let mut tick = tokio::time::interval(Duration::from_millis(10));
    for i in 0..VALUES {
        tick.tick().await;
        let pose = TimedPose2D {
            tm: Time::now(),
            data: Pose2D {
                position: Point2D {
                    x: i as f64,
                    y: -(i as f64) / 2.0,
                },
                heading: (i as f64) / 100.0,
            },
        };
        // Recording adds a queue, not a wait: `put` still never waits.
        assert_eq!(without_waiting(output.put(&pose)), Some(PortStatus::Ok));
    }
    confirmed(&output, VALUES).await;
    let mut original = Vec::new();
    for _ in 0..VALUES {
        original.push(within("the live value", live.recv()).await.expect("open"));
    }
    assert_eq!(live.stats().lost, 0);
    let seqs: Vec<u64> = original.iter().map(|s| s.seq.expect("seq")).collect();
    assert_eq!(seqs, (1..=VALUES).collect::<Vec<_>>());

    for rate in [1.0, 10.0] {
        let options = PlayOptions {
            start: Position::First,
            end: Some(Position::Offset(VALUES - 1)),
            rate: Some(rate),
            idle: None,
        };
        let player = Player::<TimedPose2D>::open(&recorded, options)
            .await
            .expect("player");
        let played = play_all(player).await;
        let offsets: Vec<u64> = played.iter().map(|p| p.offset).collect();
        assert_eq!(offsets, (0..VALUES).collect::<Vec<_>>(), "at {rate}x");
        let samples: Vec<Sample<TimedPose2D>> = played.into_iter().map(|p| p.sample).collect();
        for (played, original) in samples.iter().zip(&original) {
            assert_eq!(played.value, original.value, "at {rate}x");
            assert_eq!(played.seq, original.seq, "at {rate}x");
            assert_eq!(played.sent_at, original.sent_at, "at {rate}x");
            assert_eq!(played.latency, None);
        }
        assert_eq!(samples.len(), original.len());
        assert_eq!(span(&samples), span(&original), "at {rate}x");
    }
    output.close().await;
    live.close().await;
}

/// A recording played from an offset to an offset, from a time to a
/// time (the publisher's), and up to the end of what is recorded (idle);
/// a direct exchange's recording keeps only its port's routing key.
/// Through the in-process transport (on Leveret).
#[both_runtimes]
async fn playback_starts_and_ends_at_offsets_and_times() {
    const VALUES: i32 = 50;
    let env = Env::new().await;
    let connector = env.connector();
    let exchange = unique("longs");
    let stream = unique("longs-recording");
    let recorded = env
        .profile()
        .exchange(&exchange, ExchangeKind::Direct)
        .routing_key("mine")
        .record(Recording::to(&stream).max_age("10m"));
    let output = OutPort::<TimedLong>::connect_with(connector.clone(), recorded.clone())
        .await
        .expect("out-port");
    // Another key on the same exchange: not this port's, not recorded.
    let mut other_profile = recorded.clone().routing_key("theirs");
    other_profile.record = None;
    other_profile.mandatory = false;
    let other = OutPort::<TimedLong>::connect_with(connector.clone(), other_profile)
        .await
        .expect("other out-port");
    for i in 1..=VALUES {
        let value = TimedLong {
            tm: Time::now(),
            data: i,
        };
        assert_eq!(output.put(&value).await, PortStatus::Ok);
        assert_eq!(
            other
                .put(&TimedLong {
                    tm: Time::now(),
                    data: -i
                })
                .await,
            PortStatus::Ok
        );
    }
    confirmed(&output, VALUES as u64).await;
    confirmed(&other, VALUES as u64).await;

    let play = |options: PlayOptions| {
        let connector = connector.clone();
        let recorded = recorded.clone();
        async move {
            let player = Player::<TimedLong>::open_with(&connector, &recorded, options)
                .await
                .expect("player");
            play_all(player).await
        }
    };
    let data = |played: &[Replayed<TimedLong>]| -> Vec<i32> {
        played.iter().map(|p| p.sample.value.data).collect()
    };

    // Everything recorded, as fast as possible, ending when idle.
    let everything = play(PlayOptions {
        idle: Some(Duration::from_millis(500)),
        ..PlayOptions::default()
    })
    .await;
    assert_eq!(data(&everything), (1..=VALUES).collect::<Vec<_>>());

    // Offsets 10 to 19: the 11th to the 20th value.
    let by_offset = play(PlayOptions {
        start: Position::Offset(10),
        end: Some(Position::Offset(19)),
        ..PlayOptions::default()
    })
    .await;
    assert_eq!(data(&by_offset), (11..=20).collect::<Vec<_>>());

    // From the 30th value's send time to the 40th's, at 10x.
    let sent = |n: usize| everything[n - 1].sample.sent_at.expect("sent_at");
    let by_time = play(PlayOptions {
        start: Position::Time(sent(30)),
        end: Some(Position::Time(sent(40))),
        rate: Some(10.0),
        idle: None,
    })
    .await;
    assert_eq!(data(&by_time), (30..=40).collect::<Vec<_>>());
    let seqs: Vec<u64> = by_time.iter().map(|p| p.sample.seq.unwrap()).collect();
    assert_eq!(seqs, (30..=40).collect::<Vec<_>>());

    output.close().await;
    other.close().await;
}

/// What cannot work is refused up front: a recording on the default
/// exchange (no stream can be bound to it), playing a profile that
/// records nothing, a rate that is not a positive factor.
#[both_runtimes]
async fn impossible_recordings_and_playbacks_are_refused() {
    let env = Env::new().await;
    let on_default = env
        .profile()
        .routing_key(unique("q"))
        .record(Recording::to(unique("s")));
    let refused = OutPort::<TimedLong>::connect(on_default.clone()).await;
    assert!(
        matches!(refused, Err(Error::InvalidArgument(_))),
        "{refused:?}"
    );
    let refused = OutPort::<TimedLong>::start(on_default);
    assert!(
        matches!(refused, Err(Error::InvalidArgument(_))),
        "{refused:?}"
    );

    let nothing = Player::<TimedLong>::open(&env.profile(), PlayOptions::default()).await;
    assert!(matches!(nothing, Err(Error::InvalidArgument(_))));

    let recorded = env
        .profile()
        .exchange(unique("x"), ExchangeKind::Fanout)
        .record(Recording::to(unique("s")));
    for rate in [0.0, -1.0, f64::NAN, f64::INFINITY] {
        let options = PlayOptions {
            rate: Some(rate),
            ..PlayOptions::default()
        };
        let refused = Player::<TimedLong>::open(&recorded, options).await;
        assert!(
            matches!(refused, Err(Error::InvalidArgument(_))),
            "rate {rate}"
        );
    }
}

/// A playback pointed at a queue that is not a stream is refused and takes
/// nothing from it: the queue's reader still gets every message.
#[both_runtimes]
async fn a_playback_of_a_classic_queue_is_refused_and_takes_nothing() {
    const VALUES: i32 = 3;
    let env = Env::new().await;
    let connector = env.connector();
    let queue = unique("classic");
    let classic = env.profile().queue(&queue).routing_key(&queue);
    let output = OutPort::<TimedLong>::connect_with(connector.clone(), classic.clone())
        .await
        .expect("out-port");
    for data in 1..=VALUES {
        let value = TimedLong {
            tm: Time::now(),
            data,
        };
        assert_eq!(output.put(&value).await, PortStatus::Ok);
    }
    confirmed(&output, VALUES as u64).await;

    // Leveret refuses the stream argument on a classic queue, as RabbitMQ
    // does (a broker that took it would deliver without `x-stream-offset`,
    // which the playback refuses without acknowledging).
    let refused = Playback::open(&connector, &queue, PlayOptions::default()).await;
    assert!(
        matches!(&refused, Err(Error::ChannelClosed(reason)) if reason.code == 406),
        "{refused:?}"
    );

    let input = InPort::<TimedLong>::connect_with(connector, classic)
        .await
        .expect("in-port");
    for data in 1..=VALUES {
        let sample = within("the queued value", input.recv())
            .await
            .expect("open");
        assert_eq!(sample.value.data, data);
    }
    output.close().await;
    input.close().await;
}

/// A playback through a connector resumes after a cut link from the
/// record after the last it handed out: every value once, in order.
#[both_runtimes]
async fn a_playback_resumes_after_a_cut_link() {
    const VALUES: u64 = 1000;
    const BEFORE_CUT: u64 = 300;
    let env = Env::new().await;
    let Some(leveret) = &env.leveret else {
        eprintln!("skipped: cuts the link with a proxy to the embedded Leveret");
        return;
    };
    let addr = leveret.local_addrs()[0];
    let recorded = env
        .profile()
        .exchange(unique("cut"), ExchangeKind::Fanout)
        .record(Recording::to(unique("cut-recording")));
    let output = OutPort::<TimedLong>::connect(recorded.clone())
        .await
        .expect("out-port");
    for data in 0..VALUES as i32 {
        let value = TimedLong {
            tm: Time::now(),
            data,
        };
        assert_eq!(output.put(&value).await, PortStatus::Ok);
    }
    confirmed(&output, VALUES).await;

    let proxy = leveret_tests::fault_proxy::FaultProxy::start(addr).await;
    let mut through_proxy = recorded.clone();
    through_proxy.broker.port = proxy.addr.port();
    let options = PlayOptions {
        end: Some(Position::Offset(VALUES - 1)),
        ..PlayOptions::default()
    };
    let mut player = Player::<TimedLong>::open(&through_proxy, options)
        .await
        .expect("player");
    let mut played = Vec::new();
    while let Some(replayed) = within("the next played value", player.next())
        .await
        .expect("playback")
    {
        played.push((replayed.offset, replayed.sample.value.data));
        if played.len() as u64 == BEFORE_CUT {
            assert_eq!(proxy.cut(), 1);
        }
    }
    player.close().await;
    let expected: Vec<(u64, i32)> = (0..VALUES).map(|n| (n, n as i32)).collect();
    assert_eq!(played, expected);
    output.close().await;
}
