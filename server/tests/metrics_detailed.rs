//! The metric families issue 31 added, end to end against the `leveret`
//! binary with lapin as the client: each counter equals the events the
//! test caused (logins that passed and failed, publishes into queues,
//! messages that left queues for good by expiry, rejection and overflow,
//! with and without a dead-letter exchange, and where the dead-lettered
//! ones arrived), the channel and socket gauges match what is open, and
//! `/metrics/detailed` answers RabbitMQ 3.10's `family=` and `vhost=`
//! filters, streamed for many queues; promtool takes every endpoint.

mod common;

use common::ops::{basic, promtool_check, request, tool_available, OpsBroker};
use lapin::options::{
    BasicGetOptions, BasicPublishOptions, BasicQosOptions, BasicRejectOptions,
    ExchangeDeclareOptions, QueueBindOptions, QueueDeclareOptions,
};
use lapin::types::{AMQPValue, FieldTable};
use lapin::{BasicProperties, Channel, Connection, ConnectionProperties, ExchangeKind};
use std::net::SocketAddr;
use std::time::Duration;

/// The value of the sample written exactly as `series` (name and labels).
fn value(text: &str, series: &str) -> Option<f64> {
    text.lines()
        .find_map(|line| line.strip_prefix(series)?.strip_prefix(' '))
        .and_then(|v| v.trim().parse().ok())
}

async fn scrape(addr: SocketAddr, path: &str) -> String {
    let response = request(addr, "GET", path, &[], b"").await;
    assert_eq!(response.status, 200, "{}", response.text());
    response.text()
}

/// Scrapes until every `(series, value)` holds (counters reach the
/// scrape asynchronously), or fails naming the first that does not.
async fn scrape_until(addr: SocketAddr, path: &str, wanted: &[(&str, f64)]) -> String {
    let deadline = tokio::time::Instant::now() + Duration::from_secs(20);
    loop {
        let text = scrape(addr, path).await;
        let wrong = wanted
            .iter()
            .find(|(series, expected)| value(&text, series) != Some(*expected));
        let Some((series, expected)) = wrong else {
            return text;
        };
        assert!(
            tokio::time::Instant::now() < deadline,
            "{series} never reached {expected} (is {:?}):\n{text}",
            value(&text, series)
        );
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
}

fn check_with_promtool(text: &str, what: &str) {
    if !tool_available("promtool", "prometheus") {
        return;
    }
    match promtool_check(text) {
        None => panic!("promtool vanished"),
        Some(Ok(())) => {}
        Some(Err(problems)) => panic!("promtool check metrics on {what}:\n{problems}\n{text}"),
    }
}

fn arguments(pairs: &[(&str, AMQPValue)]) -> FieldTable {
    let mut table = FieldTable::default();
    for (key, value) in pairs {
        table.insert((*key).into(), value.clone());
    }
    table
}

async fn declare(ch: &Channel, name: &str, args: &[(&str, AMQPValue)]) {
    ch.queue_declare(name, QueueDeclareOptions::default(), arguments(args))
        .await
        .unwrap_or_else(|e| panic!("declare {name}: {e}"));
}

async fn publish(ch: &Channel, exchange: &str, routing_key: &str, count: usize) {
    for _ in 0..count {
        ch.basic_publish(
            exchange,
            routing_key,
            BasicPublishOptions::default(),
            b"counted",
            BasicProperties::default(),
        )
        .await
        .expect("publish")
        .await
        .expect("confirm");
    }
}

/// Gets one message from `queue` and rejects it without requeue.
async fn get_and_reject(ch: &Channel, queue: &str) {
    let message = ch
        .basic_get(queue, BasicGetOptions::default())
        .await
        .expect("get")
        .unwrap_or_else(|| panic!("a message in {queue}"));
    message
        .delivery
        .acker
        .reject(BasicRejectOptions { requeue: false })
        .await
        .expect("reject");
}

fn amqp_url(broker: &OpsBroker, password: &str) -> String {
    format!("amqp://guest:{password}@{}/%2f", broker.amqp)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_new_counters_equal_the_events() {
    let broker = OpsBroker::start("metrics-counters", &[]);
    let idle = scrape(broker.metrics, "/metrics").await;
    assert_eq!(
        value(&idle, "rabbitmq_auth_attempts_total{protocol=\"amqp091\"}"),
        Some(0.0)
    );
    assert_eq!(value(&idle, "rabbitmq_process_open_tcp_sockets"), Some(0.0));
    let max_sockets = value(&idle, "rabbitmq_process_max_tcp_sockets").expect("socket limit");
    let max_fds = value(&idle, "rabbitmq_process_max_fds").expect("fd limit");
    assert!(max_sockets > 0.0 && max_sockets <= max_fds, "{idle}");

    // Logins: three that pass, two with a wrong password.
    let mut connections = Vec::new();
    for _ in 0..3 {
        let conn =
            Connection::connect(&amqp_url(&broker, "guest"), ConnectionProperties::default())
                .await
                .expect("connect");
        connections.push(conn);
    }
    for _ in 0..2 {
        let refused =
            Connection::connect(&amqp_url(&broker, "wrong"), ConnectionProperties::default()).await;
        assert!(refused.is_err(), "a wrong password is refused");
    }
    let ch = connections[0].create_channel().await.expect("channel");
    ch.confirm_select(Default::default())
        .await
        .expect("confirms");

    // Publishes into queues: 5 to one queue, 3 fanned out to two.
    declare(&ch, "single", &[]).await;
    declare(&ch, "fan-a", &[]).await;
    declare(&ch, "fan-b", &[]).await;
    ch.exchange_declare(
        "fan",
        ExchangeKind::Fanout,
        ExchangeDeclareOptions::default(),
        FieldTable::default(),
    )
    .await
    .expect("exchange");
    for queue in ["fan-a", "fan-b"] {
        ch.queue_bind(
            queue,
            "fan",
            "",
            QueueBindOptions::default(),
            FieldTable::default(),
        )
        .await
        .expect("bind");
    }
    publish(&ch, "", "single", 5).await;
    publish(&ch, "fan", "", 3).await;

    // Dead-lettering: a fanout "dlx" into "dead".
    ch.exchange_declare(
        "dlx",
        ExchangeKind::Fanout,
        ExchangeDeclareOptions::default(),
        FieldTable::default(),
    )
    .await
    .expect("dlx");
    declare(&ch, "dead", &[]).await;
    ch.queue_bind(
        "dead",
        "dlx",
        "",
        QueueBindOptions::default(),
        FieldTable::default(),
    )
    .await
    .expect("bind dead");
    let dlx = (
        "x-dead-letter-exchange",
        AMQPValue::LongString("dlx".into()),
    );
    let missing = (
        "x-dead-letter-exchange",
        AMQPValue::LongString("nowhere".into()),
    );
    // Overflow: no dead-letter exchange, 5 into 2 places (3 dropped);
    // with one, 3 into 1 place (2 dead-lettered).
    declare(&ch, "short", &[("x-max-length", AMQPValue::LongLongInt(2))]).await;
    publish(&ch, "", "short", 5).await;
    declare(
        &ch,
        "short-dlx",
        &[("x-max-length", AMQPValue::LongLongInt(1)), dlx.clone()],
    )
    .await;
    publish(&ch, "", "short-dlx", 3).await;
    // Rejection: one from "single" (no dead-letter exchange), one from a
    // queue whose dead-letter exchange does not exist (dropped too, as
    // RabbitMQ counts it), two from one with "dlx".
    get_and_reject(&ch, "single").await;
    declare(&ch, "reject-missing", &[missing]).await;
    publish(&ch, "", "reject-missing", 1).await;
    get_and_reject(&ch, "reject-missing").await;
    declare(&ch, "reject-dlx", std::slice::from_ref(&dlx)).await;
    publish(&ch, "", "reject-dlx", 2).await;
    get_and_reject(&ch, "reject-dlx").await;
    get_and_reject(&ch, "reject-dlx").await;
    // Expiry: 2 with a 1 ms TTL and "dlx", found expired by a get.
    declare(
        &ch,
        "ttl-dlx",
        &[("x-message-ttl", AMQPValue::LongLongInt(1)), dlx.clone()],
    )
    .await;
    publish(&ch, "", "ttl-dlx", 2).await;
    tokio::time::sleep(Duration::from_millis(50)).await;
    let expired = ch
        .basic_get("ttl-dlx", BasicGetOptions::default())
        .await
        .expect("get");
    assert!(expired.is_none(), "the messages expired");

    // A channel with unacked deliveries and prefetch limits.
    let consumer_ch = connections[1].create_channel().await.expect("channel");
    consumer_ch
        .basic_qos(7, BasicQosOptions { global: false })
        .await
        .expect("qos");
    consumer_ch
        .basic_qos(11, BasicQosOptions { global: true })
        .await
        .expect("global qos");
    for _ in 0..2 {
        consumer_ch
            .basic_get("fan-a", BasicGetOptions::default())
            .await
            .expect("get")
            .expect("a message in fan-a");
    }

    let dead_lettered = |reason: &str, strategy: &str| {
        format!("rabbitmq_global_messages_dead_lettered_{reason}_total{{queue_type=\"rabbit_classic_queue\",dead_letter_strategy=\"{strategy}\"}}")
    };
    // Every message published to a queue: 5 + 2 × 3 + 5 + 3 + 1 + 2 + 2,
    // plus the 2 + 2 + 2 dead-lettered copies "dead" took.
    let published_into_queues = (5 + 6 + 5 + 3 + 1 + 2 + 2 + 6) as f64;
    let expected = [
        (
            "rabbitmq_auth_attempts_succeeded_total{protocol=\"amqp091\"}".to_owned(),
            3.0,
        ),
        (
            "rabbitmq_auth_attempts_failed_total{protocol=\"amqp091\"}".to_owned(),
            2.0,
        ),
        (
            "rabbitmq_auth_attempts_total{protocol=\"amqp091\"}".to_owned(),
            5.0,
        ),
        (
            "rabbitmq_auth_attempts_total{protocol=\"mqtt\"}".to_owned(),
            0.0,
        ),
        (
            "rabbitmq_queue_messages_published_total".to_owned(),
            published_into_queues,
        ),
        (dead_lettered("maxlen", "disabled"), 3.0),
        (dead_lettered("maxlen", "at_most_once"), 2.0),
        (dead_lettered("rejected", "disabled"), 2.0),
        (dead_lettered("rejected", "at_most_once"), 2.0),
        (dead_lettered("expired", "disabled"), 0.0),
        (dead_lettered("expired", "at_most_once"), 2.0),
        ("rabbitmq_process_open_tcp_sockets".to_owned(), 3.0),
        ("rabbitmq_channel_messages_unacked".to_owned(), 2.0),
        ("rabbitmq_consumer_prefetch".to_owned(), 7.0),
        ("rabbitmq_channel_prefetch".to_owned(), 11.0),
        ("rabbitmq_channel_consumers".to_owned(), 0.0),
        ("rabbitmq_connection_channels".to_owned(), 2.0),
        ("rabbitmq_channels".to_owned(), 2.0),
    ];
    let wanted: Vec<(&str, f64)> = expected.iter().map(|(s, v)| (s.as_str(), *v)).collect();
    let text = scrape_until(broker.metrics, "/metrics", &wanted).await;
    check_with_promtool(&text, "/metrics");

    // Accepted = sum of fates: each message published into a queue is
    // still there (ready or unacked), was acked, or left for good.
    let per_object = scrape(broker.metrics, "/metrics/per-object").await;
    check_with_promtool(&per_object, "/metrics/per-object");
    let sum_of = |family: &str| -> f64 {
        per_object
            .lines()
            .filter(|line| line.starts_with(&format!("{family}{{")))
            .filter_map(|line| line.rsplit(' ').next()?.parse::<f64>().ok())
            .sum()
    };
    let left_for_good: f64 = ["maxlen", "rejected", "expired"]
        .iter()
        .flat_map(|reason| ["disabled", "at_most_once"].map(|s| dead_lettered(reason, s)))
        .filter_map(|series| value(&text, &series))
        .sum();
    let published = sum_of("rabbitmq_queue_messages_published_total");
    assert_eq!(published, published_into_queues, "{per_object}");
    assert_eq!(
        sum_of("rabbitmq_queue_messages")
            + sum_of("rabbitmq_queue_messages_acked_total")
            + left_for_good,
        published,
        "{per_object}"
    );
    // What went to "dlx" arrived in "dead".
    let at_most_once: f64 = ["maxlen", "rejected", "expired"]
        .iter()
        .filter_map(|reason| value(&text, &dead_lettered(reason, "at_most_once")))
        .sum();
    assert_eq!(
        value(
            &per_object,
            "rabbitmq_queue_messages_ready{vhost=\"/\",queue=\"dead\"}"
        ),
        Some(at_most_once)
    );

    for conn in connections {
        conn.close(200, "bye").await.expect("close");
    }
    scrape_until(
        broker.metrics,
        "/metrics",
        &[("rabbitmq_process_open_tcp_sockets", 0.0)],
    )
    .await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn detailed_answers_the_families_and_vhosts_asked_for() {
    let broker = OpsBroker::start("metrics-detailed", &[]);
    let admin = basic("guest", "guest");
    let put = request(
        broker.http,
        "PUT",
        "/api/vhosts/other",
        &[
            ("authorization", &admin),
            ("content-type", "application/json"),
        ],
        b"{}",
    )
    .await;
    assert!(put.status == 201 || put.status == 204, "{}", put.text());
    let put = request(
        broker.http,
        "PUT",
        "/api/permissions/other/guest",
        &[
            ("authorization", &admin),
            ("content-type", "application/json"),
        ],
        br#"{"configure":".*","write":".*","read":".*"}"#,
    )
    .await;
    assert!(put.status == 201 || put.status == 204, "{}", put.text());

    let root = Connection::connect(&broker.amqp_url(), ConnectionProperties::default())
        .await
        .expect("connect");
    let ch = root.create_channel().await.expect("channel");
    ch.confirm_select(Default::default())
        .await
        .expect("confirms");
    declare(&ch, "root-q", &[]).await;
    publish(&ch, "", "root-q", 4).await;
    ch.basic_qos(5, BasicQosOptions::default())
        .await
        .expect("qos");
    let other = Connection::connect(
        &format!("amqp://guest:guest@{}/other", broker.amqp),
        ConnectionProperties::default(),
    )
    .await
    .expect("connect to other");
    let other_ch = other.create_channel().await.expect("channel");
    other_ch
        .confirm_select(Default::default())
        .await
        .expect("confirms");
    declare(&other_ch, "other-q", &[]).await;
    publish(&other_ch, "", "other-q", 6).await;

    // Without a family, only the two info families, as RabbitMQ.
    let bare = scrape(broker.metrics, "/metrics/detailed").await;
    let types: Vec<&str> = bare.lines().filter(|l| l.starts_with("# TYPE")).collect();
    assert_eq!(
        types,
        [
            "# TYPE rabbitmq_build_info gauge",
            "# TYPE rabbitmq_identity_info gauge"
        ],
        "{bare}"
    );
    assert!(bare.contains("rabbitmq_endpoint=\"detailed\""), "{bare}");

    let ready = |vhost: &str, queue: &str| {
        format!("rabbitmq_detailed_queue_messages_ready{{vhost=\"{vhost}\",queue=\"{queue}\"}}")
    };
    let all = scrape_until(
        broker.metrics,
        "/metrics/detailed?family=queue_coarse_metrics&family=queue_metrics",
        &[
            (&ready("/", "root-q"), 4.0),
            (&ready("other", "other-q"), 6.0),
        ],
    )
    .await;
    check_with_promtool(&all, "/metrics/detailed (queues)");
    assert_eq!(
        value(
            &all,
            "rabbitmq_detailed_queue_messages_ready_bytes{vhost=\"other\",queue=\"other-q\"}"
        ),
        Some(6.0 * 7.0)
    );
    assert!(!all.contains("rabbitmq_detailed_channel"), "{all}");
    assert!(
        !all.contains("rabbitmq_queue_messages_ready"),
        "no aggregated names: {all}"
    );

    let only_other = scrape(
        broker.metrics,
        "/metrics/detailed?family=queue_coarse_metrics&vhost=other",
    )
    .await;
    assert_eq!(value(&only_other, &ready("other", "other-q")), Some(6.0));
    assert_eq!(
        value(&only_other, &ready("/", "root-q")),
        None,
        "{only_other}"
    );
    let both = scrape(
        broker.metrics,
        "/metrics/detailed?family=queue_coarse_metrics&vhost=other&vhost=%2F",
    )
    .await;
    assert_eq!(value(&both, &ready("/", "root-q")), Some(4.0));
    assert_eq!(value(&both, &ready("other", "other-q")), Some(6.0));
    // Malformed parameters are skipped, never an error.
    let odd = scrape(
        broker.metrics,
        "/metrics/detailed?family=%ZZ&&=&family&vhost=%FF%FE&family=queue_coarse_metrics&vhost=other",
    )
    .await;
    assert_eq!(value(&odd, &ready("other", "other-q")), Some(6.0), "{odd}");
    check_with_promtool(&odd, "/metrics/detailed (malformed parameters)");
    // A vhost that does not exist is ignored: nothing matches.
    let none = scrape(
        broker.metrics,
        "/metrics/detailed?family=queue_coarse_metrics&vhost=nosuch",
    )
    .await;
    assert!(!none.contains("rabbitmq_detailed_queue"), "{none}");

    let rest = scrape(
        broker.metrics,
        "/metrics/detailed?family=channel_metrics&family=connection_metrics&family=auth_attempt_metrics\
         &family=vhost_status&family=exchange_names&family=exchange_bindings&family=connection_churn_metrics\
         &family=node_coarse_metrics&family=node_metrics&family=ra_metrics",
    )
    .await;
    check_with_promtool(&rest, "/metrics/detailed (every family)");
    let prefetch: Vec<&str> = rest
        .lines()
        .filter(|l| l.starts_with("rabbitmq_detailed_consumer_prefetch{channel="))
        .collect();
    assert_eq!(prefetch.len(), 2, "one sample per channel: {rest}");
    assert!(prefetch.iter().any(|l| l.ends_with(" 5")), "{rest}");
    let channels: Vec<&str> = rest
        .lines()
        .filter(|l| l.starts_with("rabbitmq_detailed_connection_channels{"))
        .collect();
    assert_eq!(channels.len(), 2, "{rest}");
    assert_eq!(
        value(
            &rest,
            "rabbitmq_detailed_auth_attempts_succeeded_total{protocol=\"amqp091\"}"
        ),
        Some(2.0)
    );
    assert_eq!(
        value(&rest, "rabbitmq_cluster_vhost_status{vhost=\"other\"}"),
        Some(1.0)
    );
    assert_eq!(
        value(
            &rest,
            "rabbitmq_cluster_exchange_name{vhost=\"other\",exchange=\"amq.topic\",type=\"topic\"}"
        ),
        Some(1.0)
    );
    assert_eq!(
        value(&rest, "rabbitmq_detailed_connections_opened_total"),
        Some(2.0)
    );
    assert_eq!(
        value(&rest, "rabbitmq_detailed_process_open_tcp_sockets"),
        Some(2.0)
    );
    assert!(value(&rest, "rabbitmq_detailed_resident_memory_limit_bytes").is_some());
    assert!(!rest.contains("raft"), "{rest}");
    root.close(200, "bye").await.expect("close");
    other.close(200, "bye").await.expect("close");
}

/// More queues than one chunk (1000): the queue families are streamed
/// (chunked), each family's HELP once and one sample per queue.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn detailed_queue_families_of_many_queues_are_streamed_whole() {
    let broker = OpsBroker::start("metrics-detailed-many", &[]);
    let conn = Connection::connect(&broker.amqp_url(), ConnectionProperties::default())
        .await
        .expect("connect");
    let ch = conn.create_channel().await.expect("channel");
    let count = 2500;
    for i in 0..count {
        declare(&ch, &format!("many-{i:05}"), &[]).await;
    }
    let response = request(
        broker.metrics,
        "GET",
        "/metrics/detailed?family=queue_coarse_metrics&family=queue_consumer_count",
        &[],
        b"",
    )
    .await;
    assert_eq!(response.status, 200);
    assert_eq!(response.header("transfer-encoding"), Some("chunked"));
    let text = response.text();
    for family in [
        "rabbitmq_detailed_queue_messages_ready",
        "rabbitmq_detailed_queue_messages",
        "rabbitmq_detailed_queue_consumers",
    ] {
        assert_eq!(
            text.matches(&format!("# HELP {family} ")).count(),
            1,
            "{family}"
        );
        let samples = text
            .lines()
            .filter(|line| line.starts_with(&format!("{family}{{")))
            .count();
        assert_eq!(samples, count, "{family}: one sample per queue");
    }
    check_with_promtool(&text, "/metrics/detailed of many queues");
    conn.close(200, "bye").await.expect("close");
}

/// The connection traffic counters against a raw client whose bytes are
/// known: the 8-byte protocol header in, connection.start out (every byte
/// the client read), then a hang-up; on `/metrics` they stay counted once
/// the connection is gone. Per connection on `/metrics/detailed`, an open
/// lapin connection has sent and received bytes.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn connection_traffic_counts_the_bytes_each_way() {
    use tokio::io::{AsyncReadExt, AsyncWriteExt};
    let broker = OpsBroker::start("metrics-traffic", &[]);
    let mut raw = tokio::net::TcpStream::connect(broker.amqp)
        .await
        .expect("connect");
    raw.write_all(b"AMQP\x00\x00\x09\x01")
        .await
        .expect("header");
    // connection.start: a 7-byte frame header, the payload it announces,
    // and the frame-end octet.
    let mut header = [0u8; 7];
    raw.read_exact(&mut header).await.expect("frame header");
    let size = u32::from_be_bytes([header[3], header[4], header[5], header[6]]) as usize;
    let mut rest = vec![0u8; size + 1];
    raw.read_exact(&mut rest).await.expect("connection.start");
    assert_eq!(rest[size], 0xCE, "frame end");
    let start_bytes = (7 + size + 1) as f64;
    drop(raw);
    let text = scrape_until(
        broker.metrics,
        "/metrics",
        &[
            ("rabbitmq_connection_incoming_bytes_total", 8.0),
            ("rabbitmq_connection_outgoing_bytes_total", start_bytes),
        ],
    )
    .await;
    let reads = value(&text, "rabbitmq_connection_incoming_packets_total").expect("reads");
    let writes = value(&text, "rabbitmq_connection_outgoing_packets_total").expect("writes");
    assert!((1.0..=8.0).contains(&reads), "{text}");
    assert!((1.0..=start_bytes).contains(&writes), "{text}");

    let conn = Connection::connect(&broker.amqp_url(), ConnectionProperties::default())
        .await
        .expect("connect");
    let ch = conn.create_channel().await.expect("channel");
    declare(&ch, "traffic", &[]).await;
    let detailed = scrape(
        broker.metrics,
        "/metrics/detailed?family=connection_coarse_metrics&family=connection_metrics",
    )
    .await;
    check_with_promtool(&detailed, "/metrics/detailed (connections)");
    for family in [
        "connection_incoming_bytes_total",
        "connection_outgoing_bytes_total",
        "connection_incoming_packets_total",
        "connection_outgoing_packets_total",
    ] {
        let samples: Vec<f64> = detailed
            .lines()
            .filter(|l| l.starts_with(&format!("rabbitmq_detailed_{family}{{channel=")))
            .filter_map(|l| l.rsplit(' ').next()?.parse().ok())
            .collect();
        assert_eq!(
            samples.len(),
            1,
            "{family}: the one open connection: {detailed}"
        );
        assert!(samples[0] > 0.0, "{family}: {detailed}");
    }
    // The totals count the closed raw connection and the open one.
    let totals = scrape(broker.metrics, "/metrics").await;
    let incoming = value(&totals, "rabbitmq_connection_incoming_bytes_total").expect("in");
    assert!(incoming > 8.0, "{totals}");
    conn.close(200, "bye").await.expect("close");
}

/// RabbitMQ's `queue_metrics` figures Leveret keeps: the bytes of ready
/// and unacked messages, persistent messages (in a durable queue, ready
/// and unacked; none counted in a transient queue, as RabbitMQ), and the
/// head message's `timestamp`, followed through gets, an ack and a
/// requeue, on `/metrics`, `/metrics/per-object` and `/metrics/detailed`.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn queue_bytes_persistence_and_head_timestamp_follow_the_messages() {
    use lapin::options::{BasicAckOptions, BasicNackOptions};
    let broker = OpsBroker::start("metrics-queue-figures", &[]);
    let conn = Connection::connect(&broker.amqp_url(), ConnectionProperties::default())
        .await
        .expect("connect");
    let ch = conn.create_channel().await.expect("channel");
    ch.confirm_select(Default::default())
        .await
        .expect("confirms");
    ch.queue_declare(
        "kept",
        QueueDeclareOptions {
            durable: true,
            ..Default::default()
        },
        FieldTable::default(),
    )
    .await
    .expect("declare");
    declare(&ch, "transient", &[]).await;
    // Into "kept": 10 + 20 persistent bytes with timestamps 1001 and
    // 1002, then 40 transient bytes with none.
    let sends: [(usize, bool, Option<u64>); 3] = [
        (10, true, Some(1001)),
        (20, true, Some(1002)),
        (40, false, None),
    ];
    for (size, persistent, timestamp) in sends {
        let mut properties = BasicProperties::default();
        if persistent {
            properties = properties.with_delivery_mode(2);
        }
        if let Some(timestamp) = timestamp {
            properties = properties.with_timestamp(timestamp);
        }
        for queue in ["kept", "transient"] {
            ch.basic_publish(
                "",
                queue,
                BasicPublishOptions::default(),
                &vec![b'x'; size],
                properties.clone(),
            )
            .await
            .expect("publish")
            .await
            .expect("confirm");
        }
    }
    let kept = |family: &str| format!("rabbitmq_queue_{family}{{vhost=\"/\",queue=\"kept\"}}");
    let text = scrape_until(
        broker.metrics,
        "/metrics/per-object",
        &[
            (&kept("messages_bytes"), 70.0),
            (&kept("messages_unacked_bytes"), 0.0),
            (&kept("messages_persistent"), 2.0),
            (&kept("head_message_timestamp"), 1001.0),
            (
                "rabbitmq_queue_messages_persistent{vhost=\"/\",queue=\"transient\"}",
                0.0,
            ),
        ],
    )
    .await;
    check_with_promtool(&text, "/metrics/per-object");

    // Two gets: the persistent ones are unacked, the head has no timestamp.
    let mut deliveries = Vec::new();
    for _ in 0..2 {
        let message = ch
            .basic_get("kept", BasicGetOptions::default())
            .await
            .expect("get")
            .expect("a message");
        deliveries.push(message.delivery);
    }
    let text = scrape_until(
        broker.metrics,
        "/metrics/per-object",
        &[
            (&kept("messages_bytes"), 70.0),
            (&kept("messages_unacked_bytes"), 30.0),
            (&kept("messages_ready_bytes"), 40.0),
            (&kept("messages_persistent"), 2.0),
        ],
    )
    .await;
    assert_eq!(
        value(&text, &kept("head_message_timestamp")),
        None,
        "{text}"
    );
    // The aggregated sums: "transient" holds 70 ready bytes.
    scrape_until(
        broker.metrics,
        "/metrics",
        &[
            ("rabbitmq_queue_messages_bytes", 140.0),
            ("rabbitmq_queue_messages_unacked_bytes", 30.0),
            ("rabbitmq_queue_messages_persistent", 2.0),
        ],
    )
    .await;

    // Ack the first (10 bytes), requeue the second: it is the head again.
    deliveries[0]
        .ack(BasicAckOptions::default())
        .await
        .expect("ack");
    deliveries[1]
        .nack(BasicNackOptions {
            requeue: true,
            ..Default::default()
        })
        .await
        .expect("nack");
    let detailed =
        |family: &str| format!("rabbitmq_detailed_queue_{family}{{vhost=\"/\",queue=\"kept\"}}");
    let text = scrape_until(
        broker.metrics,
        "/metrics/detailed?family=queue_metrics",
        &[
            (&detailed("messages_bytes"), 60.0),
            (&detailed("messages_unacked_bytes"), 0.0),
            (&detailed("messages_ready_bytes"), 60.0),
            (&detailed("messages_persistent"), 1.0),
            (&detailed("head_message_timestamp"), 1002.0),
            (&detailed("consumers"), 0.0),
        ],
    )
    .await;
    check_with_promtool(&text, "/metrics/detailed?family=queue_metrics");
    conn.close(200, "bye").await.expect("close");
}

/// A transactional channel's held publishes and acks, on `/metrics` and
/// per channel on `/metrics/detailed`, until its commit; a confirm-mode
/// channel's publishes are unconfirmed only until confirmed.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn uncommitted_and_unconfirmed_work_is_shown_until_settled() {
    use lapin::options::BasicAckOptions;
    let broker = OpsBroker::start("metrics-uncommitted", &[]);
    let conn = Connection::connect(&broker.amqp_url(), ConnectionProperties::default())
        .await
        .expect("connect");
    let confirming = conn.create_channel().await.expect("channel");
    confirming
        .confirm_select(Default::default())
        .await
        .expect("confirms");
    declare(&confirming, "tx-q", &[]).await;
    publish(&confirming, "", "tx-q", 2).await;
    let tx = conn.create_channel().await.expect("channel");
    let got = tx
        .basic_get("tx-q", BasicGetOptions::default())
        .await
        .expect("get")
        .expect("a message");
    tx.tx_select().await.expect("tx.select");
    for _ in 0..3 {
        tx.basic_publish(
            "",
            "tx-q",
            BasicPublishOptions::default(),
            b"held",
            BasicProperties::default(),
        )
        .await
        .expect("publish");
    }
    got.delivery
        .ack(BasicAckOptions::default())
        .await
        .expect("ack");
    scrape_until(
        broker.metrics,
        "/metrics",
        &[
            ("rabbitmq_channel_messages_uncommitted", 3.0),
            ("rabbitmq_channel_acks_uncommitted", 1.0),
            ("rabbitmq_channel_messages_unconfirmed", 0.0),
            // As RabbitMQ's channel: the ack took the delivery off the
            // channel's unacked list into the transaction; the queue
            // still counts it until the commit.
            ("rabbitmq_channel_messages_unacked", 0.0),
            ("rabbitmq_queue_messages_unacked", 1.0),
        ],
    )
    .await;
    let detailed = scrape(broker.metrics, "/metrics/detailed?family=channel_metrics").await;
    check_with_promtool(&detailed, "/metrics/detailed?family=channel_metrics");
    let held: Vec<&str> = detailed
        .lines()
        .filter(|l| l.starts_with("rabbitmq_detailed_channel_messages_uncommitted{channel="))
        .collect();
    assert_eq!(held.len(), 2, "{detailed}");
    assert!(held.iter().any(|l| l.ends_with(" 3")), "{detailed}");
    tx.tx_commit().await.expect("commit");
    scrape_until(
        broker.metrics,
        "/metrics",
        &[
            ("rabbitmq_channel_messages_uncommitted", 0.0),
            ("rabbitmq_channel_acks_uncommitted", 0.0),
            ("rabbitmq_queue_messages_unacked", 0.0),
            ("rabbitmq_queue_messages_ready", 4.0),
        ],
    )
    .await;
    conn.close(200, "bye").await.expect("close");
}

/// MQTT logins under RabbitMQ 3.10's `protocol="mqtt"` label, counted as
/// its plugin counts them (a login passes once the vhost has let it in; no
/// credentials, a wrong password and an unknown vhost fail), from
/// `mosquitto_sub` and `mosquitto_pub`: an open MQTT connection counts in
/// `rabbitmq_connections` and is listed with its protocol in
/// `/api/connections`; AMQP's logins stay apart; promtool takes it.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn mqtt_logins_are_counted_under_their_protocol() {
    if !tool_available("mosquitto_sub", "mosquitto-clients") {
        return;
    }
    let broker = OpsBroker::start("metrics-mqtt", &["--mqtt-listen", "127.0.0.1:0"]);
    let port = broker.mqtt_addr().port().to_string();
    let mosquitto = |program: &str, login: &[&str], rest: &[&str]| {
        let mut command = std::process::Command::new(program);
        command
            .args(["-h", "127.0.0.1", "-p", &port, "-V", "mqttv311"])
            .args(login)
            .args(rest)
            .stdout(std::process::Stdio::piped())
            .stderr(std::process::Stdio::piped());
        command
    };
    let guest = ["-u", "guest", "-P", "guest"];
    // A subscriber that stays until one message has come.
    let subscriber = mosquitto("mosquitto_sub", &guest, &["-i", "watcher", "-t", "m/#"])
        .args(["-C", "1", "-q", "1"])
        .spawn()
        .expect("mosquitto_sub runs");
    let open = [
        ("rabbitmq_connections", 1.0),
        (
            "rabbitmq_auth_attempts_succeeded_total{protocol=\"mqtt\"}",
            1.0,
        ),
    ];
    scrape_until(broker.metrics, "/metrics", &open).await;
    let auth = basic("guest", "guest");
    let listed = request(
        broker.http,
        "GET",
        "/api/connections",
        &[("Authorization", auth.as_str())],
        b"",
    )
    .await;
    let listed: serde_json::Value = serde_json::from_slice(&listed.body).expect("json");
    assert_eq!(listed[0]["protocol"], "MQTT 3.1.1", "{listed}");
    assert_eq!(
        listed[0]["client_properties"]["product"], "MQTT",
        "{listed}"
    );

    for (login, refused) in [
        (&["-u", "guest", "-P", "wrong"][..], "a wrong password"),
        (&[][..], "no credentials"),
        (
            &["-u", "nowhere:guest", "-P", "guest"][..],
            "an unknown vhost",
        ),
    ] {
        let output = mosquitto("mosquitto_pub", login, &["-t", "m/x", "-m", "no"])
            .output()
            .expect("mosquitto_pub runs");
        assert!(!output.status.success(), "{refused} let in: {output:?}");
    }
    let output = mosquitto(
        "mosquitto_pub",
        &guest,
        &["-t", "m/1", "-m", "hi", "-q", "1"],
    )
    .output()
    .expect("mosquitto_pub runs");
    assert!(output.status.success(), "{output:?}");
    let received = subscriber.wait_with_output().expect("mosquitto_sub ends");
    assert_eq!(String::from_utf8_lossy(&received.stdout).trim(), "hi");

    let counted = [
        (
            "rabbitmq_auth_attempts_succeeded_total{protocol=\"mqtt\"}",
            2.0,
        ),
        (
            "rabbitmq_auth_attempts_failed_total{protocol=\"mqtt\"}",
            3.0,
        ),
        ("rabbitmq_auth_attempts_total{protocol=\"mqtt\"}", 5.0),
        ("rabbitmq_auth_attempts_total{protocol=\"amqp091\"}", 0.0),
        ("rabbitmq_connections", 0.0),
    ];
    let text = scrape_until(broker.metrics, "/metrics", &counted).await;
    check_with_promtool(&text, "/metrics");
}
