//! The Prometheus endpoint of the `leveret` binary, end to end: every
//! listener on port 0, traffic from lapin, scrapes whose values move with
//! it under RabbitMQ's metric names and labels, `promtool check metrics`
//! on both endpoints, `/metrics/per-object` streamed in chunks for many
//! queues, and the listener's routes (methods, unknown paths).

mod common;

use common::ops::{promtool_check, request, tool_available, OpsBroker};
use futures_lite::StreamExt;
use lapin::options::{
    BasicAckOptions, BasicConsumeOptions, BasicPublishOptions, BasicQosOptions,
    ConfirmSelectOptions, QueueDeclareOptions,
};
use lapin::types::FieldTable;
use lapin::{BasicProperties, Connection, ConnectionProperties};
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
    assert_eq!(
        response.header("content-type"),
        Some("text/plain; version=0.0.4")
    );
    response.text()
}

/// Scrapes until `series` has `expected` (counters reach the broker's
/// thread asynchronously), or fails with the last scrape.
/// Scrapes `path` until one scrape shows every series at its expected
/// value (within a hang limit), and returns that scrape.
async fn scrape_until(addr: SocketAddr, path: &str, expected: &[(&str, f64)]) -> String {
    let deadline = tokio::time::Instant::now() + Duration::from_secs(10);
    loop {
        let text = scrape(addr, path).await;
        if expected
            .iter()
            .all(|(series, want)| value(&text, series) == Some(*want))
        {
            return text;
        }
        assert!(
            tokio::time::Instant::now() < deadline,
            "never {expected:?} in one scrape:\n{text}"
        );
        tokio::time::sleep(Duration::from_millis(20)).await;
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

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn scrapes_follow_traffic_under_rabbitmq_names() {
    let broker = OpsBroker::start("scrape", &[]);
    let idle = scrape(broker.metrics, "/metrics").await;
    let received = "rabbitmq_global_messages_received_total{protocol=\"amqp091\"}";
    assert_eq!(value(&idle, received), Some(0.0));
    assert_eq!(value(&idle, "rabbitmq_connections"), Some(0.0));
    assert!(
        idle.contains("# TYPE rabbitmq_global_messages_received_total counter"),
        "{idle}"
    );
    assert!(idle.contains("rabbitmq_identity_info{rabbitmq_node=\"leveret@"));
    assert!(idle.contains("rabbitmq_endpoint=\"aggregated\"} 1"));
    assert!(value(&idle, "rabbitmq_process_resident_memory_bytes").unwrap() > 0.0);

    let conn = Connection::connect(&broker.amqp_url(), ConnectionProperties::default())
        .await
        .expect("connect");
    let ch = conn.create_channel().await.expect("channel");
    ch.confirm_select(ConfirmSelectOptions::default())
        .await
        .expect("confirms");
    ch.queue_declare(
        "telemetry",
        QueueDeclareOptions::default(),
        FieldTable::default(),
    )
    .await
    .expect("declare");
    for i in 0..10u8 {
        ch.basic_publish(
            "",
            "telemetry",
            BasicPublishOptions::default(),
            &[i; 8],
            BasicProperties::default(),
        )
        .await
        .expect("publish")
        .await
        .expect("confirm");
    }
    let consumer_channel = conn.create_channel().await.expect("channel");
    consumer_channel
        .basic_qos(4, BasicQosOptions::default())
        .await
        .expect("qos");
    let mut consumer = consumer_channel
        .basic_consume(
            "telemetry",
            "",
            BasicConsumeOptions::default(),
            FieldTable::default(),
        )
        .await
        .expect("consume");
    for _ in 0..4 {
        let delivery = consumer.next().await.expect("delivery").expect("ok");
        delivery
            .acker
            .ack(BasicAckOptions::default())
            .await
            .expect("ack");
    }
    // Four acked; prefetch lets four more out unacked. A scrape reads the
    // queues before the global counters, and an ack gives the consumer its
    // credit back a moment before the queue counts it settled, so a
    // scrape may show the queue mid-way through the acks (CI saw 5 ready
    // and 4 unacked: one ack in, one redelivery out): wait for the end
    // state in one scrape.
    let acked = "rabbitmq_global_messages_acknowledged_total{protocol=\"amqp091\",queue_type=\"rabbit_classic_queue\"}";
    let text = scrape_until(
        broker.metrics,
        "/metrics",
        &[
            ("rabbitmq_queue_messages_ready", 2.0),
            ("rabbitmq_queue_messages_unacked", 4.0),
            (acked, 4.0),
        ],
    )
    .await;
    assert_eq!(value(&text, received), Some(10.0));
    assert_eq!(
        value(
            &text,
            "rabbitmq_global_messages_confirmed_total{protocol=\"amqp091\"}"
        ),
        Some(10.0)
    );
    assert_eq!(
        value(
            &text,
            "rabbitmq_global_messages_routed_total{protocol=\"amqp091\"}"
        ),
        Some(10.0)
    );
    assert_eq!(value(&text, "rabbitmq_queue_messages_ready"), Some(2.0));
    assert_eq!(value(&text, "rabbitmq_queue_messages"), Some(6.0));
    assert_eq!(value(&text, "rabbitmq_connections"), Some(1.0));
    assert_eq!(value(&text, "rabbitmq_channels"), Some(2.0));
    assert_eq!(value(&text, "rabbitmq_queues"), Some(1.0));
    assert_eq!(value(&text, "rabbitmq_consumers"), Some(1.0));
    assert_eq!(
        value(&text, "rabbitmq_global_publishers{protocol=\"amqp091\"}"),
        Some(1.0)
    );
    assert_eq!(value(&text, "rabbitmq_queues_created_total"), Some(1.0));
    assert_eq!(value(&text, "rabbitmq_connections_opened_total"), Some(1.0));
    assert_eq!(value(&text, "leveret_queued_message_bytes"), Some(16.0));
    assert!(value(&text, "leveret_socket_reads_total").unwrap() > 0.0);
    assert!(value(&text, "leveret_busy_poll_windows_total").unwrap() > 0.0);
    assert!(value(&text, "leveret_busy_poll_seconds_total").unwrap() > 0.0);
    // The store's group commits (at least the one recording the start).
    let groups = value(&text, "leveret_persister_batch_ops_count").expect("batch histogram");
    assert!(groups >= 1.0, "{text}");
    assert_eq!(
        value(&text, "leveret_persister_flush_seconds_bucket{le=\"+Inf\"}"),
        Some(groups),
        "{text}"
    );
    assert!(text.contains("# TYPE leveret_persister_flush_seconds histogram"));
    check_with_promtool(&text, "/metrics");

    let per_object = scrape(broker.metrics, "/metrics/per-object").await;
    assert_eq!(
        value(
            &per_object,
            "rabbitmq_queue_messages_ready{vhost=\"/\",queue=\"telemetry\"}"
        ),
        Some(2.0)
    );
    assert_eq!(
        value(
            &per_object,
            "rabbitmq_queue_messages_acked_total{vhost=\"/\",queue=\"telemetry\"}"
        ),
        Some(4.0)
    );
    assert!(per_object.contains("rabbitmq_queue_info{vhost=\"/\",queue=\"telemetry\",queue_type=\"rabbit_classic_queue\",membership=\"leader\"} 1"));
    assert!(per_object.contains("rabbitmq_endpoint=\"per-object\"} 1"));
    check_with_promtool(&per_object, "/metrics/per-object");

    conn.close(200, "bye").await.expect("close");
    let text = scrape_until(
        broker.metrics,
        "/metrics",
        &[("rabbitmq_connections_closed_total", 1.0)],
    )
    .await;
    // A close is counted after the connection is unlisted.
    assert_eq!(value(&text, "rabbitmq_connections"), Some(0.0));
    // The close's four unacked come back to the queue, which a scrape may
    // read before they do.
    scrape_until(
        broker.metrics,
        "/metrics",
        &[
            ("rabbitmq_queue_messages_ready", 6.0),
            ("rabbitmq_queue_messages_unacked", 0.0),
        ],
    )
    .await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_metrics_listener_answers_only_its_routes() {
    let broker = OpsBroker::start("bounds", &[]);
    let post = request(broker.metrics, "POST", "/metrics", &[], &[b'x'; 4096]).await;
    assert_eq!(post.status, 405);
    let unknown = request(broker.metrics, "GET", "/api/overview", &[], b"").await;
    assert_eq!(unknown.status, 404);
    // The connection bounds are operator_lockout.rs' subject.
}

/// `/metrics/per-object` over more queues than one chunk (1000) holds: the
/// body is streamed (chunked), every per-queue family appears once with
/// one sample per queue, and promtool accepts the whole.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn per_object_metrics_of_many_queues_are_streamed_whole() {
    let broker = OpsBroker::start("per-object-many", &[]);
    let conn = Connection::connect(&broker.amqp_url(), ConnectionProperties::default())
        .await
        .expect("connect");
    let ch = conn.create_channel().await.expect("channel");
    let count = 2500;
    for i in 0..count {
        ch.queue_declare(
            &format!("many-{i:05}"),
            QueueDeclareOptions::default(),
            FieldTable::default(),
        )
        .await
        .expect("declare");
    }
    let response = request(broker.metrics, "GET", "/metrics/per-object", &[], b"").await;
    assert_eq!(response.status, 200);
    assert_eq!(response.header("transfer-encoding"), Some("chunked"));
    let text = response.text();
    for family in [
        "rabbitmq_queue_messages_ready",
        "rabbitmq_queue_get_empty_total",
        "rabbitmq_queue_info",
    ] {
        let help = format!("# HELP {family} ");
        assert_eq!(text.matches(&help).count(), 1, "{family}'s HELP once");
        let samples = text
            .lines()
            .filter(|line| line.starts_with(&format!("{family}{{")))
            .count();
        assert_eq!(samples, count, "{family}: one sample per queue");
    }
    assert_eq!(
        value(
            &text,
            "rabbitmq_queue_messages_ready{vhost=\"/\",queue=\"many-02499\"}"
        ),
        Some(0.0)
    );
    assert_eq!(value(&text, "rabbitmq_queues"), Some(count as f64));
    check_with_promtool(&text, "/metrics/per-object of many queues");
}

/// The Prometheus client libraries' process families, read from the
/// process itself (issue 31): open descriptors below the allowed ones, the
/// start time between the test's clock before the launch and the scrape,
/// and RabbitMQ's file-descriptor alarm off; promtool takes the scrape.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn process_families_come_from_the_process() {
    let now = || {
        std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .expect("after 1970")
            .as_secs_f64()
    };
    let before = now();
    let broker = OpsBroker::start("process-families", &[]);
    let text = scrape(broker.metrics, "/metrics").await;
    let after = now();
    let open = value(&text, "process_open_fds").expect("process_open_fds");
    let max = value(&text, "process_max_fds").expect("process_max_fds");
    let started = value(&text, "process_start_time_seconds").expect("start time");
    assert!(open >= 5.0 && open < max, "{open} of {max}");
    // The start time has the kernel's clock-tick resolution (10 ms).
    assert!(
        started >= before.floor() - 1.0 && started <= after,
        "{before} <= {started} <= {after}"
    );
    assert_eq!(
        value(&text, "rabbitmq_alarms_file_descriptor_limit"),
        Some(0.0)
    );
    assert_eq!(
        value(&text, "rabbitmq_process_open_fds").map(|n| n >= 5.0),
        Some(true)
    );
    check_with_promtool(&text, "the process families");
}
