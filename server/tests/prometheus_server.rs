//! A real Prometheus server (Debian's `prometheus`) scrapes Leveret every
//! second and answers, through its HTTP API, the queries of RabbitMQ's
//! stock "RabbitMQ-Overview" Grafana dashboard, written the way the
//! dashboard writes them (joined to `rabbitmq_identity_info` on
//! `instance, job`, filtered by cluster, namespace and endpoint): each
//! answers with a series, and the figures are the broker's. Skips loudly
//! outside CI when prometheus is not installed; fails under CI.

mod common;

use common::ops::{request, tool_available, OpsBroker};
use lapin::options::{BasicPublishOptions, QueueDeclareOptions};
use lapin::types::FieldTable;
use lapin::{BasicProperties, Connection, ConnectionProperties};
use serde_json::Value;
use std::net::SocketAddr;
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

/// A Prometheus server scraping one target; killed when dropped.
struct Prometheus {
    child: Child,
    dir: std::path::PathBuf,
    addr: SocketAddr,
}

impl Prometheus {
    fn start(target: SocketAddr) -> Prometheus {
        let dir = std::env::temp_dir().join(format!("leveret-prometheus-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir).expect("prometheus dir");
        let config = dir.join("prometheus.yml");
        std::fs::write(
            &config,
            format!(
                "global:\n  scrape_interval: 1s\n  evaluation_interval: 1s\n\
                 scrape_configs:\n  - job_name: leveret\n    static_configs:\n      - targets: ['{target}']\n"
            ),
        )
        .expect("config");
        let addr = leveret_tests::reserved_port::reserved_addr();
        let child = Command::new("prometheus")
            .arg(format!("--config.file={}", config.display()))
            .arg(format!(
                "--storage.tsdb.path={}",
                dir.join("data").display()
            ))
            .arg(format!("--web.listen-address={addr}"))
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .expect("start prometheus");
        Prometheus { child, dir, addr }
    }

    /// The result vector of an instant query, or `None` if Prometheus is
    /// not answering yet.
    async fn query(&self, promql: &str) -> Option<Vec<Value>> {
        let path = format!("/api/v1/query?query={}", percent_encode(promql));
        let connect = tokio::net::TcpStream::connect(self.addr).await;
        if connect.is_err() {
            return None;
        }
        drop(connect);
        let response = request(self.addr, "GET", &path, &[], b"").await;
        let body: Value = serde_json::from_slice(&response.body).ok()?;
        assert_eq!(body["status"], "success", "{promql}: {body}");
        body["data"]["result"].as_array().cloned()
    }

    /// Waits (up to 60 s) until `promql` has a series whose value passes
    /// `wanted`; returns that value.
    async fn until(&self, promql: &str, wanted: impl Fn(f64) -> bool) -> f64 {
        let deadline = Instant::now() + Duration::from_secs(60);
        let mut last = None;
        loop {
            if let Some(result) = self.query(promql).await {
                let values: Vec<f64> = result.iter().filter_map(sample_value).collect();
                if let Some(v) = values.iter().copied().find(|v| wanted(*v)) {
                    return v;
                }
                last = Some(result);
            }
            assert!(
                Instant::now() < deadline,
                "Prometheus never answered {promql} as wanted; last answer: {last:?}"
            );
            tokio::time::sleep(Duration::from_millis(250)).await;
        }
    }
}

impl Drop for Prometheus {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
        let _ = std::fs::remove_dir_all(&self.dir);
    }
}

fn sample_value(series: &Value) -> Option<f64> {
    series["value"][1].as_str()?.parse().ok()
}

fn percent_encode(text: &str) -> String {
    text.bytes()
        .map(|b| match b {
            b'A'..=b'Z' | b'a'..=b'z' | b'0'..=b'9' | b'-' | b'_' | b'.' | b'~' => {
                (b as char).to_string()
            }
            _ => format!("%{b:02X}"),
        })
        .collect()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn prometheus_answers_the_overview_dashboards_queries() {
    if !tool_available("prometheus", "prometheus") {
        return;
    }
    let broker = OpsBroker::start("prometheus-server", &[]);
    let prometheus = Prometheus::start(broker.metrics);
    prometheus.until("up{job=\"leveret\"}", |v| v == 1.0).await;

    // The dashboard's variables: the cluster from rabbitmq_identity_info
    // (its `rabbitmq_cluster` variable is `label_values(rabbitmq_identity_info, rabbitmq_cluster)`),
    // no namespace (set only by Kubernetes scrape configs), the endpoint.
    prometheus
        .until("count(rabbitmq_identity_info)", |v| v == 1.0)
        .await;
    let identity = prometheus
        .query("rabbitmq_identity_info")
        .await
        .and_then(|found| found.first().map(|first| first["metric"].clone()))
        .expect("rabbitmq_identity_info");
    let cluster = identity["rabbitmq_cluster"]
        .as_str()
        .expect("a cluster label");
    let endpoint = identity["rabbitmq_endpoint"]
        .as_str()
        .expect("an endpoint label");
    assert!(identity["rabbitmq_node"]
        .as_str()
        .is_some_and(|n| n.starts_with("leveret@")));
    let join = |labels: &str| {
        format!(
            "on(instance, job) group_left({labels}) rabbitmq_identity_info{{rabbitmq_cluster=\"{cluster}\", namespace=\"\", rabbitmq_endpoint=\"{endpoint}\"}}"
        )
    };
    let node_join = join("rabbitmq_cluster, rabbitmq_node");

    let conn = Connection::connect(&broker.amqp_url(), ConnectionProperties::default())
        .await
        .expect("connect");
    let ch = conn.create_channel().await.expect("channel");
    ch.queue_declare(
        "dashboard",
        QueueDeclareOptions::default(),
        FieldTable::default(),
    )
    .await
    .expect("declare");
    for _ in 0..25 {
        ch.basic_publish(
            "",
            "dashboard",
            BasicPublishOptions::default(),
            b"reading",
            BasicProperties::default(),
        )
        .await
        .expect("publish");
    }

    // The single-stat panels across the top.
    let ready = format!(
        "sum(rabbitmq_queue_messages_ready * {})",
        join("rabbitmq_cluster")
    );
    assert_eq!(prometheus.until(&ready, |v| v == 25.0).await, 25.0);
    let unacked = format!(
        "sum(rabbitmq_queue_messages_unacked * {})",
        join("rabbitmq_cluster")
    );
    assert_eq!(prometheus.until(&unacked, |v| v == 0.0).await, 0.0);
    for (gauge, expected) in [
        ("rabbitmq_connections", 1.0),
        ("rabbitmq_channels", 1.0),
        ("rabbitmq_queues", 1.0),
        ("rabbitmq_global_consumers", 0.0),
        ("rabbitmq_global_publishers", 1.0),
    ] {
        let promql = format!("sum({gauge} * {})", join("rabbitmq_cluster"));
        prometheus.until(&promql, |v| v == expected).await;
    }
    let nodes = format!("count(rabbitmq_build_info * {})", join("rabbitmq_cluster"));
    prometheus.until(&nodes, |v| v == 1.0).await;
    // The nodes table reads the build labels off rabbitmq_build_info.
    let build = prometheus
        .query(&format!("rabbitmq_build_info * {node_join}"))
        .await
        .expect("answers");
    assert!(
        build[0]["metric"]["rabbitmq_version"].is_string(),
        "{build:?}"
    );
    assert!(
        build[0]["metric"]["erlang_version"].is_string(),
        "{build:?}"
    );

    // Resource panels: memory and disk before the alarms, file descriptors.
    let memory = format!(
        "(rabbitmq_resident_memory_limit_bytes * {node_join}) - (rabbitmq_process_resident_memory_bytes * {node_join})"
    );
    prometheus.until(&memory, |v| v > 0.0).await;
    let disk = format!(
        "rabbitmq_disk_space_available_bytes * {node_join} - rabbitmq_disk_space_available_limit_bytes * {node_join}"
    );
    prometheus.until(&disk, |v| v.is_finite()).await;
    let fds = format!(
        "(rabbitmq_process_max_fds * {node_join}) - (rabbitmq_process_open_fds * {node_join})"
    );
    prometheus.until(&fds, |v| v > 0.0).await;
    // "TCP sockets available": the socket limit less the one connection.
    let sockets = format!(
        "(rabbitmq_process_max_tcp_sockets * {node_join}) - (rabbitmq_process_open_tcp_sockets * {node_join})"
    );
    let max_sockets = prometheus
        .until(
            &format!("rabbitmq_process_max_tcp_sockets * {node_join}"),
            |v| v > 0.0,
        )
        .await;
    prometheus.until(&sockets, |v| v == max_sockets - 1.0).await;
    // The "Publishers" stat of the 3.10 dashboard: channels less the
    // consumers on channels (one channel, no consumer).
    let publishers = format!(
        "sum(rabbitmq_channels * {cluster}) - sum(rabbitmq_channel_consumers * {cluster})",
        cluster = join("rabbitmq_cluster")
    );
    prometheus.until(&publishers, |v| v == 1.0).await;

    // Rate panels: messages, and churn.
    for counter in [
        "rabbitmq_global_messages_received_total",
        "rabbitmq_global_messages_routed_total",
        "rabbitmq_connections_opened_total",
        "rabbitmq_channels_opened_total",
        "rabbitmq_queues_declared_total",
        "rabbitmq_queues_created_total",
    ] {
        let promql = format!("sum(rate({counter}[60s]) * {node_join}) by(rabbitmq_node)");
        prometheus.until(&promql, |v| v > 0.0).await;
    }
    for counter in [
        "rabbitmq_global_messages_received_confirm_total",
        "rabbitmq_global_messages_confirmed_total",
        "rabbitmq_global_messages_delivered_consume_auto_ack_total",
        "rabbitmq_global_messages_delivered_consume_manual_ack_total",
        "rabbitmq_global_messages_redelivered_total",
        "rabbitmq_global_messages_acknowledged_total",
        "rabbitmq_global_messages_unroutable_dropped_total",
        "rabbitmq_global_messages_unroutable_returned_total",
        "rabbitmq_connections_closed_total",
        "rabbitmq_channels_closed_total",
        "rabbitmq_queues_deleted_total",
    ] {
        let promql = format!("sum(rate({counter}[60s]) * {node_join}) by(rabbitmq_node)");
        prometheus.until(&promql, |v| v == 0.0).await;
    }
    conn.close(200, "bye").await.expect("close");
}
