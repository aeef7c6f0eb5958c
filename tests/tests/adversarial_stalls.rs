//! The stall budget (issue 12): work whose size a client chooses must not
//! hold the broker's thread. Each test builds a big piece of state, then
//! runs the heavy operation on it while a bystander connection on the
//! broker's thread measures its round trips in that thread's CPU time
//! ([`Probe`]); the worst must stay under [`WORST_ROUND_TRIP`] beyond what
//! it was just before. The
//! probe keeps running for [`AFTERMATH`] after the operation's reply,
//! since the broker finishes such work in the background, a slice at a
//! time.
//!
//! Sizes: a million messages in a release build (`cargo test --release`),
//! a hundred thousand in a debug build, whose every step is ten times
//! slower; 10,000 queues for the fanout and for the closing owner.
//! The figures of a release run (`cargo test --release -p leveret-tests
//! --test adversarial_stalls -- --nocapture`) are kept in `perf/results/`.

#[macro_use]
mod common;

use common::stall::*;
use common::*;
use leveret_broker::Limits;
use leveret_protocol::{BasicProperties, ExchangeDeclare, Method, QueueBind, QueueDeclare};
use std::time::{Duration, Instant};
use tokio::io::{AsyncReadExt, AsyncWriteExt};

/// Messages in the big queue.
const MESSAGES: usize = sized(1_000_000, 100_000);
/// Queues the fanout reaches.
const FANOUT_QUEUES: usize = 10_000;
/// Exclusive queues of the closing connection.
const EXCLUSIVE_QUEUES: usize = 10_000;
/// How long the probe keeps going after the operation's reply.
const AFTERMATH: Duration = Duration::from_millis(500);

fn table(entries: &[(&str, leveret_protocol::FieldValue)]) -> leveret_protocol::FieldTable {
    entries
        .iter()
        .map(|(key, value)| (short(key), value.clone()))
        .collect()
}

/// A queue named `prefix…` with `arguments`, sent [`MESSAGES`] messages
/// by a hand-written connection; returns the count it then holds.
async fn full_queue(
    target: &Target,
    prefix: &str,
    arguments: leveret_protocol::FieldTable,
) -> (Flood, String, u32) {
    let mut flood = Flood::open(&target.addr).await;
    let queue = unique(prefix);
    let declare = QueueDeclare {
        queue: short(&queue),
        arguments,
        ..Default::default()
    };
    flood.send(&frames(1, [declare.into()])).await;
    flood
        .expect(|m| matches!(m, Method::QueueDeclareOk(_)))
        .await;
    let count = flood
        .publish_many(
            ("", &queue),
            MESSAGES,
            &BasicProperties::default(),
            b"0123456789abcdef",
            &queue,
        )
        .await;
    (flood, queue, count)
}

/// Keeps the probe going for [`AFTERMATH`], then reports it.
async fn finish_after(probe: Probe, during: &str) -> Result<(), String> {
    tokio::time::sleep(AFTERMATH).await;
    probe.finish(during).await
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn purging_a_huge_queue_leaves_others_served() {
    within_bounds(Limits::default(), |target| async move {
        let (_flood, queue, count) = full_queue(&target, "stall-purge", table(&[])).await;
        assert_eq!(count as usize, MESSAGES, "every message queued");
        let (_connection, channel) = target.open().await;
        let probe = Probe::start(&target).await;
        let started = Instant::now();
        let purged = tmo!(channel.queue_purge(&queue, lp::QueuePurgeOptions::default()))
            .expect("queue.purge");
        eprintln!("purge-ok after {:?}", started.elapsed());
        assert_eq!(purged as usize, MESSAGES);
        finish_after(probe, &format!("purging {MESSAGES} messages")).await
    })
    .await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn deleting_a_huge_queue_leaves_others_served() {
    within_bounds(Limits::default(), |target| async move {
        let (_flood, queue, count) = full_queue(&target, "stall-delete", table(&[])).await;
        assert_eq!(count as usize, MESSAGES, "every message queued");
        let (_connection, channel) = target.open().await;
        let probe = Probe::start(&target).await;
        let deleted = tmo!(channel.queue_delete(&queue, lp::QueueDeleteOptions::default()))
            .expect("queue.delete");
        assert_eq!(deleted as usize, MESSAGES);
        finish_after(probe, &format!("deleting a queue of {MESSAGES} messages")).await
    })
    .await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn closing_a_connection_with_a_huge_unacked_window_leaves_others_served() {
    within_bounds(Limits::default(), |target| async move {
        let (mut flood, queue, count) = full_queue(&target, "stall-unacked", table(&[])).await;
        assert_eq!(count as usize, MESSAGES, "every message queued");
        let (consuming, channel) = target.open().await;
        let mut deliveries = lp::consume_opts(
            &channel,
            &queue,
            "greedy",
            lp::BasicConsumeOptions::default(),
        )
        .await;
        for _ in 0..MESSAGES {
            lp::next(&mut deliveries).await;
        }
        let probe = Probe::start(&target).await;
        tmo!(consuming.close(200, "bye")).expect("connection.close");
        let requeued = within("the requeue", async {
            loop {
                let count = flood.message_count(&queue).await;
                if count as usize == MESSAGES {
                    break count;
                }
                tokio::task::yield_now().await;
            }
        })
        .await;
        assert_eq!(requeued as usize, MESSAGES);
        finish_after(
            probe,
            &format!("closing a connection with {MESSAGES} unacked deliveries"),
        )
        .await
    })
    .await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn one_multiple_ack_of_a_huge_window_leaves_others_served() {
    within_bounds(Limits::default(), |target| async move {
        let (_flood, queue, count) = full_queue(&target, "stall-ack", table(&[])).await;
        assert_eq!(count as usize, MESSAGES, "every message queued");
        let (_consuming, channel) = target.open().await;
        let mut deliveries = lp::consume_opts(
            &channel,
            &queue,
            "greedy",
            lp::BasicConsumeOptions::default(),
        )
        .await;
        let mut last = 0;
        for _ in 0..MESSAGES {
            last = lp::next(&mut deliveries).await.delivery_tag;
        }
        let probe = Probe::start(&target).await;
        tmo!(channel.basic_ack(last, lp::BasicAckOptions { multiple: true })).expect("basic.ack");
        // The channel is still usable, and nothing came back.
        tmo!(channel.basic_qos(1, lp::BasicQosOptions::default())).expect("basic.qos");
        finish_after(probe, &format!("one multiple ack of {MESSAGES} deliveries")).await
    })
    .await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn expiring_a_huge_queue_into_a_dead_letter_queue_leaves_others_served() {
    within_bounds(Limits::default(), |target| async move {
        let dead = unique("stall-expired");
        let mut flood = Flood::open(&target.addr).await;
        let declare = QueueDeclare {
            queue: short(&dead),
            ..Default::default()
        };
        flood.send(&frames(1, [declare.into()])).await;
        flood
            .expect(|m| matches!(m, Method::QueueDeclareOk(_)))
            .await;
        let ttl_ms = 2_000;
        let arguments = table(&[
            ("x-message-ttl", leveret_protocol::FieldValue::I64(ttl_ms)),
            (
                "x-dead-letter-exchange",
                leveret_protocol::FieldValue::string(""),
            ),
            (
                "x-dead-letter-routing-key",
                leveret_protocol::FieldValue::string(&dead),
            ),
        ]);
        // Expiry may begin while the queue fills (on a loaded machine);
        // every message must reach the dead-letter queue all the same.
        let (mut flood, queue, _) = full_queue(&target, "stall-ttl", arguments).await;
        let probe = Probe::start(&target).await;
        let moved = within("the expiry", async {
            loop {
                if flood.message_count(&queue).await == 0 {
                    break flood.message_count(&dead).await;
                }
                tokio::time::sleep(Duration::from_millis(20)).await;
            }
        })
        .await;
        assert_eq!(moved as usize, MESSAGES, "every message dead-lettered");
        finish_after(
            probe,
            &format!("expiring {MESSAGES} messages into a dead-letter queue"),
        )
        .await
    })
    .await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_fanout_to_thousands_of_queues_leaves_others_served() {
    within_bounds(Limits::default(), |target| async move {
        let mut flood = Flood::open(&target.addr).await;
        let fanout = unique("stall-fanout");
        let exchange = ExchangeDeclare {
            exchange: short(&fanout),
            kind: short("fanout"),
            ..Default::default()
        };
        let prefix = unique("stall-fq");
        let setup = (0..FANOUT_QUEUES).flat_map(|i| {
            let queue = short(&format!("{prefix}-{i}"));
            let declare: Method = QueueDeclare {
                queue: queue.clone(),
                no_wait: true,
                ..Default::default()
            }
            .into();
            let bind: Method = QueueBind {
                queue,
                exchange: short(&fanout),
                no_wait: true,
                ..Default::default()
            }
            .into();
            [declare, bind]
        });
        flood
            .send(&frames(1, std::iter::once(exchange.into()).chain(setup)))
            .await;
        flood
            .expect(|m| matches!(m, Method::ExchangeDeclareOk(_)))
            .await;
        let last = format!("{prefix}-{}", FANOUT_QUEUES - 1);
        assert_eq!(flood.message_count(&last).await, 0);

        let (_connection, channel) = target.open().await;
        tmo!(channel.confirm_select(lp::ConfirmSelectOptions::default())).expect("confirms");
        let probe = Probe::start(&target).await;
        const PUBLISHES: usize = 20;
        for _ in 0..PUBLISHES {
            let confirmation = lp::publish_confirmed(
                &channel,
                &fanout,
                "",
                b"to everyone",
                lp::BasicProperties::default(),
            )
            .await;
            assert!(confirmation.is_ack());
        }
        assert_eq!(flood.message_count(&last).await as usize, PUBLISHES);
        finish_after(
            probe,
            &format!("{PUBLISHES} publishes fanned out to {FANOUT_QUEUES} queues"),
        )
        .await
    })
    .await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn closing_the_owner_of_thousands_of_exclusive_queues_leaves_others_served() {
    within_bounds(Limits::default(), |target| async move {
        let mut owner = Flood::open(&target.addr).await;
        let prefix = unique("stall-excl");
        let declares = (0..EXCLUSIVE_QUEUES).map(|i| {
            QueueDeclare {
                queue: short(&format!("{prefix}-{i}")),
                exclusive: true,
                no_wait: true,
                ..Default::default()
            }
            .into()
        });
        owner.send(&frames(1, declares)).await;
        let last = format!("{prefix}-{}", EXCLUSIVE_QUEUES - 1);
        assert_eq!(owner.message_count(&last).await, 0);

        let (connection, _channel) = target.open().await;
        let probe = Probe::start(&target).await;
        drop(owner);
        // Gone once a passive declare says 404 rather than 405 (locked).
        within("the exclusive queues' deletion", async {
            loop {
                let channel = lp::channel(&connection).await;
                let passive = lp::QueueDeclareOptions {
                    passive: true,
                    ..Default::default()
                };
                match channel
                    .queue_declare(&last, passive, lp::FieldTable::default())
                    .await
                {
                    Err(e) if lp::code(&e).0 == 404 => break,
                    _ => tokio::task::yield_now().await,
                }
            }
        })
        .await;
        finish_after(
            probe,
            &format!("closing the owner of {EXCLUSIVE_QUEUES} exclusive queues"),
        )
        .await
    })
    .await;
}

/// Queues in the deleted vhost, each bound to a fanout.
const VHOST_QUEUES: usize = 10_000;

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn deleting_a_vhost_of_thousands_of_queues_leaves_others_served() {
    within_bounds(Limits::default(), |target| async move {
        let vhost = unique("stall-vhost");
        let populated = target
            .on_broker_thread({
                let vhost = vhost.clone();
                move |admin| async move {
                    admin.add_vhost(&vhost).await.expect("vhost");
                    let fanout = leveret_broker::ExchangeSettings {
                        kind: "fanout".into(),
                        ..Default::default()
                    };
                    admin
                        .declare_exchange(&vhost, "fan", fanout)
                        .await
                        .expect("fanout");
                    for i in 0..VHOST_QUEUES {
                        let queue = format!("q{i}");
                        admin
                            .declare_queue(&vhost, &queue, Default::default())
                            .await
                            .expect("queue");
                        let binding = leveret_broker::BindingSpec {
                            source: "fan".into(),
                            destination: queue,
                            destination_kind: leveret_broker::DestinationKind::Queue,
                            routing_key: String::new(),
                            arguments: Default::default(),
                        };
                        admin.bind(&vhost, binding).await.expect("bind");
                    }
                }
            })
            .await;
        if populated.is_none() {
            // An external broker: no Admin to delete a vhost with.
            return Ok(());
        }
        let probe = Probe::start(&target).await;
        let deleted = target
            .on_broker_thread(move |admin| async move { admin.delete_vhost(&vhost).await })
            .await;
        assert_eq!(deleted, Some(Ok(true)));
        finish_after(
            probe,
            &format!("deleting a vhost of {VHOST_QUEUES} queues bound to a fanout"),
        )
        .await
    })
    .await;
}

/// Queues on each side of the dead-letter multiplication.
const MULTIPLIED: usize = sized(1_000, 300);

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn dead_letters_multiplied_by_fanouts_leave_others_served() {
    within_bounds(Limits::default(), |target| async move {
        // A publish to `first` reaches MULTIPLIED queues that keep nothing
        // (x-max-length 0): each dead-letters it to `second`, a fanout to
        // MULTIPLIED more queues. One publish, MULTIPLIED² deliveries.
        let mut flood = Flood::open(&target.addr).await;
        let first = unique("stall-dl-first");
        let second = unique("stall-dl-second");
        let fanout = |name: &str| -> Method {
            ExchangeDeclare {
                exchange: short(name),
                kind: short("fanout"),
                no_wait: true,
                ..Default::default()
            }
            .into()
        };
        let mut setup = vec![fanout(&first), fanout(&second)];
        let prefix = unique("stall-dlq");
        for i in 0..MULTIPLIED {
            for (side, exchange, arguments) in [
                (
                    "a",
                    &first,
                    table(&[
                        ("x-max-length", leveret_protocol::FieldValue::I64(0)),
                        (
                            "x-dead-letter-exchange",
                            leveret_protocol::FieldValue::string(&second),
                        ),
                    ]),
                ),
                ("b", &second, table(&[])),
            ] {
                let queue = short(&format!("{prefix}-{side}-{i}"));
                setup.push(
                    QueueDeclare {
                        queue: queue.clone(),
                        arguments,
                        no_wait: true,
                        ..Default::default()
                    }
                    .into(),
                );
                setup.push(
                    QueueBind {
                        queue,
                        exchange: short(exchange),
                        no_wait: true,
                        ..Default::default()
                    }
                    .into(),
                );
            }
        }
        flood.send(&frames(1, setup)).await;
        let last = format!("{prefix}-b-{}", MULTIPLIED - 1);
        assert_eq!(flood.message_count(&last).await, 0);

        let (_connection, channel) = target.open().await;
        let probe = Probe::start(&target).await;
        lp::publish(&channel, &first, "", b"multiply me").await;
        within("the dead letters", async {
            while (flood.message_count(&last).await as usize) < MULTIPLIED {
                tokio::time::sleep(Duration::from_millis(20)).await;
            }
        })
        .await;
        finish_after(
            probe,
            &format!("one publish dead-lettered {MULTIPLIED} times to {MULTIPLIED} queues each"),
        )
        .await
    })
    .await;
}

/// QoS 0 publishes an MQTT client writes in one go.
const MQTT_PUBLISHES: usize = sized(1_000_000, 100_000);

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_mqtt_client_writing_a_flood_of_publishes_leaves_others_served() {
    within_bounds(Limits::default(), |target| async move {
        let Some(mqtt) = target.mqtt_addr else {
            // An external broker's MQTT port is not known here.
            return Ok(());
        };
        let mut flood = Flood::open(&target.addr).await;
        let queue = unique("stall-mqtt");
        let declare = QueueDeclare {
            queue: short(&queue),
            ..Default::default()
        };
        let bind = QueueBind {
            queue: short(&queue),
            exchange: short("amq.topic"),
            routing_key: short("flood.#"),
            ..Default::default()
        };
        flood.send(&frames(1, [declare.into(), bind.into()])).await;
        flood
            .expect(|m| matches!(m, Method::QueueDeclareOk(_)))
            .await;
        flood.expect(|m| matches!(m, Method::QueueBindOk(_))).await;

        let mut client = within("MQTT connect", tokio::net::TcpStream::connect(mqtt))
            .await
            .expect("the MQTT listener accepts");
        let mut connect = mqtt_string("MQTT");
        connect.extend_from_slice(&[4, 0xC2, 0, 0]); // 3.1.1, user, password, clean; no keepalive
        for field in ["stall-flood", "guest", "guest"] {
            connect.extend(mqtt_string(field));
        }
        let mut connack = [0u8; 4];
        within("CONNACK", async {
            client.write_all(&mqtt_packet(0x10, &connect)).await?;
            client.read_exact(&mut connack).await
        })
        .await
        .expect("CONNACK");
        assert_eq!(connack, [0x20, 2, 0, 0], "accepted");
        let mut publish = mqtt_string("flood/x");
        publish.extend_from_slice(b"0123456789abcdef");
        let one = mqtt_packet(0x30, &publish);
        let publishes: Vec<u8> = one
            .iter()
            .copied()
            .cycle()
            .take(one.len() * MQTT_PUBLISHES)
            .collect();

        let probe = Probe::start(&target).await;
        let mut pong = [0u8; 2];
        // All in one go, then a ping: answered once every publish before it is read.
        within("the flood and a ping", async {
            client.write_all(&publishes).await?;
            client.write_all(&[0xC0, 0]).await?;
            client.read_exact(&mut pong).await
        })
        .await
        .expect("PINGRESP");
        assert_eq!(pong, [0xD0, 0]);
        within("every publish queued", async {
            loop {
                let count = flood.message_count(&queue).await as usize;
                if count == MQTT_PUBLISHES {
                    break;
                }
                assert!(count < MQTT_PUBLISHES, "{count} queued");
                tokio::time::sleep(Duration::from_millis(20)).await;
            }
        })
        .await;
        finish_after(
            probe,
            &format!("{MQTT_PUBLISHES} MQTT QoS 0 publishes written at once"),
        )
        .await
    })
    .await;
}
