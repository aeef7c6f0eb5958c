//! The Prometheus endpoint: `/metrics` (aggregated) and
//! `/metrics/per-object` (one series per queue), with the metric names,
//! types, HELP texts and labels of RabbitMQ's `rabbitmq_prometheus`
//! plugin, so its Grafana dashboards work unchanged. The exposition is
//! Prometheus text format 0.0.4, as that plugin serves it, written by the
//! `prometheus` crate's encoder: in 0.0.4 a counter's family name keeps
//! its `_total`, as RabbitMQ's do; OpenMetrics (what `prometheus-client`
//! writes) moves `_total` to the samples, and `promtool check metrics`
//! (2.42) then reads every counter as an untyped family without help. The `untyped` families of RabbitMQ's (`rabbitmq_build_info`,
//! `rabbitmq_identity_info`, `rabbitmq_alarms_*`) are gauges here: that
//! encoder cannot write untyped samples; dashboards read them the same.
//!
//! A scrape reads the broker through [`Admin`] on the listeners' thread:
//! queues are read a chunk at a time with a yield between chunks, so one
//! scrape of many queues never holds that thread for long either, and
//! `/metrics/per-object` writes its per-queue families a chunk at a time
//! as the client reads: its memory is a chunk's, not the document's.

mod detailed;

use crate::process::ProcessFigures;
use crate::uplink::Shovels;
use axum::body::{Body, Bytes};
use axum::extract::{DefaultBodyLimit, State};
use axum::http::header::CONTENT_TYPE;
use axum::response::IntoResponse;
use axum::routing::get;
use axum::Router;
use leveret_broker::{
    Admin, AuthAttemptFigures, ChurnTotals, DeadLetteredFigures, HistogramFigures, Overview,
    QueueInfo, QueueRef, SocketTrafficFigures,
};
use prometheus::proto::{
    Bucket, Counter, Gauge, Histogram, LabelPair, Metric, MetricFamily, MetricType,
};
use std::path::PathBuf;
use std::sync::Arc;

/// Queues read between two yields.
const CHUNK: usize = 1000;
/// The one protocol Leveret speaks, as RabbitMQ labels it.
const PROTOCOL: (&str, &str) = ("protocol", "amqp091");
/// Leveret's queues are all of the classic kind.
const QUEUE_TYPE: (&str, &str) = ("queue_type", "rabbit_classic_queue");

/// Which endpoint is being scraped.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Endpoint {
    /// `/metrics`: sums over queues, no per-object labels.
    Aggregated,
    /// `/metrics/per-object`: queue metrics labelled by vhost and queue.
    PerObject,
}

impl Endpoint {
    fn label(self) -> &'static str {
        match self {
            Endpoint::Aggregated => "aggregated",
            Endpoint::PerObject => "per-object",
        }
    }
}

/// What a scrape needs besides the broker.
#[derive(Debug, Clone)]
pub struct MetricsContext {
    /// The broker.
    pub admin: Admin,
    /// `leveret@HOST`.
    pub node: String,
    /// Where disk space is measured.
    pub data_dir: PathBuf,
    /// The uplink's shovels.
    pub shovels: Shovels,
}

/// Families in the order they are added.
#[derive(Default)]
struct Exposition {
    families: Vec<MetricFamily>,
}

impl Exposition {
    fn family(&mut self, name: &str, kind: MetricType, help: &str) -> &mut MetricFamily {
        let mut family = MetricFamily::default();
        family.set_name(name.to_owned());
        family.set_help(help.to_owned());
        family.set_field_type(kind);
        self.families.push(family);
        self.families.last_mut().expect("just pushed")
    }

    /// A family with one sample.
    fn single(
        &mut self,
        name: &str,
        kind: MetricType,
        help: &str,
        labels: &[(&str, &str)],
        value: f64,
    ) {
        let family = self.family(name, kind, help);
        family.mut_metric().push(sample(kind, labels, value));
    }

    fn counter(&mut self, name: &str, help: &str, value: u64) {
        self.single(name, MetricType::COUNTER, help, &[], value as f64);
    }

    fn gauge(&mut self, name: &str, help: &str, value: u64) {
        self.single(name, MetricType::GAUGE, help, &[], value as f64);
    }

    fn histogram(&mut self, name: &str, help: &str, figures: &HistogramFigures) {
        let mut histogram = Histogram::default();
        histogram.set_sample_count(figures.count);
        histogram.set_sample_sum(figures.sum);
        histogram.set_bucket(
            figures
                .buckets
                .iter()
                // The encoder writes `+Inf` itself, from the count.
                .filter(|(bound, _)| bound.is_finite())
                .map(|(bound, count)| {
                    let mut bucket = Bucket::default();
                    bucket.set_upper_bound(*bound);
                    bucket.set_cumulative_count(*count);
                    bucket
                })
                .collect(),
        );
        let mut metric = Metric::default();
        metric.set_histogram(histogram);
        self.family(name, MetricType::HISTOGRAM, help)
            .mut_metric()
            .push(metric);
    }

    /// The text; per-object families with no objects are left out, as the
    /// format has no empty families.
    fn encode(mut self) -> String {
        self.families
            .retain(|family| !family.get_metric().is_empty());
        let mut text = String::new();
        if let Err(e) = prometheus::TextEncoder::new().encode_utf8(&self.families, &mut text) {
            tracing::error!(error = %e, "cannot encode metrics");
        }
        text
    }
}

fn sample(kind: MetricType, labels: &[(&str, &str)], value: f64) -> Metric {
    let mut metric = Metric::default();
    let pairs = labels
        .iter()
        .map(|(name, value)| {
            let mut pair = LabelPair::default();
            pair.set_name((*name).to_owned());
            pair.set_value((*value).to_owned());
            pair
        })
        .collect();
    metric.set_label(pairs);
    if kind == MetricType::COUNTER {
        let mut counter = Counter::default();
        counter.set_value(value);
        metric.set_counter(counter);
    } else {
        let mut gauge = Gauge::default();
        gauge.set_value(value);
        metric.set_gauge(gauge);
    }
    metric
}

/// The per-queue metrics, each read from a [`QueueInfo`].
type QueueFigure = fn(&QueueInfo) -> u64;
const QUEUE_METRICS: [(&str, MetricType, &str, QueueFigure); 16] = [
    ("rabbitmq_queue_messages_ready", MetricType::GAUGE, "Messages ready to be delivered to consumers", |q| q.messages_ready),
    ("rabbitmq_queue_messages_unacked", MetricType::GAUGE, "Messages delivered to consumers but not yet acknowledged", |q| q.messages_unacknowledged),
    ("rabbitmq_queue_messages", MetricType::GAUGE, "Sum of ready and unacknowledged messages - total queue depth", |q| q.messages()),
    ("rabbitmq_queue_consumers", MetricType::GAUGE, "Consumers on a queue", |q| q.consumers),
    ("rabbitmq_queue_messages_ready_bytes", MetricType::GAUGE, "Size in bytes of ready messages", |q| q.message_bytes_ready),
    ("rabbitmq_queue_get_ack_total", MetricType::COUNTER, "Total number of messages fetched from a queue with basic.get in manual acknowledgement mode", |q| q.message_stats.get),
    ("rabbitmq_queue_get_total", MetricType::COUNTER, "Total number of messages fetched from a queue with basic.get in automatic acknowledgement mode", |q| q.message_stats.get_no_ack),
    ("rabbitmq_queue_messages_delivered_ack_total", MetricType::COUNTER, "Total number of messages delivered from a queue to consumers in manual acknowledgement mode", |q| q.message_stats.deliver),
    ("rabbitmq_queue_messages_delivered_total", MetricType::COUNTER, "Total number of messages delivered from a queue to consumers in automatic acknowledgement mode", |q| q.message_stats.deliver_no_ack),
    ("rabbitmq_queue_messages_redelivered_total", MetricType::COUNTER, "Total number of messages redelivered from a queue to consumers", |q| q.message_stats.redeliver),
    ("rabbitmq_queue_messages_acked_total", MetricType::COUNTER, "Total number of messages acknowledged by consumers on a queue", |q| q.message_stats.ack),
    ("rabbitmq_queue_get_empty_total", MetricType::COUNTER, "Total number of times basic.get operations fetched no message on a queue", |q| q.message_stats.get_empty),
    ("rabbitmq_queue_messages_published_total", MetricType::COUNTER, "Total number of messages published to queues", |q| q.message_stats.publish),
    ("rabbitmq_queue_messages_bytes", MetricType::GAUGE, "Size in bytes of ready and unacknowledged messages", |q| q.message_bytes_ready + q.message_bytes_unacknowledged),
    ("rabbitmq_queue_messages_unacked_bytes", MetricType::GAUGE, "Size in bytes of all unacknowledged messages", |q| q.message_bytes_unacknowledged),
    ("rabbitmq_queue_messages_persistent", MetricType::GAUGE, "Persistent messages", |q| q.messages_persistent),
];
/// A queue's figure where it has one (no sample otherwise).
type OptionalFigure = fn(&QueueInfo) -> Option<u64>;
/// The per-queue families of `/metrics/per-object` after [`QUEUE_INFO`]
/// that not every queue has: RabbitMQ's head timestamp (queues whose head
/// message has a `timestamp` property) and Leveret's per-stream families
/// (classic queues have no samples in them).
const OPTIONAL_METRICS: [(&str, &str, OptionalFigure); 5] = [
    (
        "rabbitmq_queue_head_message_timestamp",
        "Timestamp of the first message in the queue, if any",
        |q| q.head_message_timestamp,
    ),
    (
        "leveret_stream_first_offset",
        "The oldest offset a stream holds",
        |q| Some(q.stream.as_ref()?.first_offset),
    ),
    (
        "leveret_stream_last_offset",
        "The newest offset a stream holds (no sample while it is empty)",
        |q| q.stream.as_ref()?.last_offset,
    ),
    (
        "leveret_stream_segments",
        "Segment files a stream keeps",
        |q| Some(q.stream.as_ref()?.segments),
    ),
    (
        "leveret_stream_disk_bytes",
        "Bytes of the segment files a stream keeps",
        |q| Some(q.stream.as_ref()?.bytes),
    ),
];
/// The `queue_type` label of a stream, as RabbitMQ names it.
const STREAM_QUEUE_TYPE: &str = "rabbit_stream_queue";
/// `/metrics/per-object`'s family of queue details.
const QUEUE_INFO: (&str, &str) = (
    "rabbitmq_queue_info",
    "A metric with a constant '1' value and labels that provide some queue details",
);

/// Each shovel's state (a `1` labelled with it) and counts, labelled
/// with the shovel's name and vhost.
fn shovel_metrics(out: &mut Exposition, shovels: &Shovels) {
    use leveret_uplink::ShovelState;
    let shovels = shovels.list();
    let state = out.family(
        "leveret_shovel_state",
        MetricType::GAUGE,
        "1 for each shovel, labelled with its state: starting, running, blocked or terminated",
    );
    for s in &shovels {
        let name = match s.status.state {
            ShovelState::Connecting => "starting",
            ShovelState::Running => "running",
            ShovelState::Blocked => "blocked",
            ShovelState::Terminated => "terminated",
        };
        let labels = [
            ("shovel", s.name.as_str()),
            ("vhost", s.vhost.as_str()),
            ("state", name),
        ];
        state
            .mut_metric()
            .push(sample(MetricType::GAUGE, &labels, 1.0));
    }
    type Count = fn(&leveret_uplink::ShovelStatus) -> u64;
    let counts: [(&str, &str, Count); 4] = [
        (
            "leveret_shovel_forwarded_total",
            "Messages the shovel's destination took",
            |s| s.forwarded,
        ),
        (
            "leveret_shovel_refused_total",
            "Messages the shovel's destination refused (nacked or returned), left at the source",
            |s| s.refused,
        ),
        (
            "leveret_shovel_dropped_loops_total",
            "Messages the shovel dropped (acknowledged, not forwarded) because they had already gone through it: its source and destination form a loop",
            |s| s.dropped_loops,
        ),
        (
            "leveret_shovel_restarts_total",
            "Times the shovel's link ended and started again",
            |s| s.restarts,
        ),
    ];
    for (metric, help, count) in counts {
        let family = out.family(metric, MetricType::COUNTER, help);
        for s in &shovels {
            let labels = [("shovel", s.name.as_str()), ("vhost", s.vhost.as_str())];
            family.mut_metric().push(sample(
                MetricType::COUNTER,
                &labels,
                count(&s.status) as f64,
            ));
        }
    }
}

/// The sums over every queue of [`QUEUE_METRICS`]' figures and of the
/// ready bytes, read a chunk at a time, yielding between chunks.
async fn queue_sums(refs: &[QueueRef]) -> ([u64; QUEUE_METRICS.len()], u64) {
    let mut sums = [0u64; QUEUE_METRICS.len()];
    let mut ready_bytes = 0u64;
    for chunk in refs.chunks(CHUNK) {
        for queue in chunk {
            let info = queue.info();
            for (sum, (.., figure)) in sums.iter_mut().zip(QUEUE_METRICS) {
                *sum = sum.saturating_add(figure(&info));
            }
            ready_bytes = ready_bytes.saturating_add(info.message_bytes_ready);
        }
        tokio::task::yield_now().await;
    }
    (sums, ready_bytes)
}

/// One chunk of a per-queue family of `/metrics/per-object`: family
/// `index` ([`QUEUE_METRICS`]' then [`QUEUE_INFO`]) for `queues`, each
/// read as its turn comes; the HELP and TYPE lines only when `first`.
/// Written as the `prometheus` crate's text encoder writes (label values
/// escaped alike), without building its structs for every sample.
fn per_queue_chunk(index: usize, queues: &[QueueRef], first: bool) -> String {
    use std::fmt::Write;
    let optional_index = index.checked_sub(QUEUE_METRICS.len() + 1);
    let (name, kind, help) = match (QUEUE_METRICS.get(index), optional_index) {
        (Some(&(name, kind, help, _)), _) => (name, kind, help),
        (None, Some(at)) => {
            let (name, help, _) = OPTIONAL_METRICS[at];
            (name, MetricType::GAUGE, help)
        }
        (None, None) => (QUEUE_INFO.0, MetricType::GAUGE, QUEUE_INFO.1),
    };
    let mut text = String::new();
    if first {
        let kind = if kind == MetricType::COUNTER {
            "counter"
        } else {
            "gauge"
        };
        let _ = write!(text, "# HELP {name} {help}\n# TYPE {name} {kind}\n");
    }
    for queue in queues {
        let (vhost, queue_name) = (escaped(queue.vhost()), escaped(queue.name()));
        let _ = match (QUEUE_METRICS.get(index), optional_index) {
            (Some(&(.., figure)), _) => writeln!(
                text,
                "{name}{{vhost=\"{vhost}\",queue=\"{queue_name}\"}} {}",
                figure(&queue.info())
            ),
            (None, Some(at)) => match (OPTIONAL_METRICS[at].2)(&queue.info()) {
                Some(value) => writeln!(
                    text,
                    "{name}{{vhost=\"{vhost}\",queue=\"{queue_name}\"}} {value}"
                ),
                None => Ok(()),
            },
            (None, None) => writeln!(
                text,
                "{name}{{vhost=\"{vhost}\",queue=\"{queue_name}\",{}=\"{}\",membership=\"leader\"}} 1",
                QUEUE_TYPE.0,
                if queue.info().stream.is_some() {
                    STREAM_QUEUE_TYPE
                } else {
                    QUEUE_TYPE.1
                }
            ),
        };
    }
    text
}

/// A label value as the text format escapes it: `\\`, `\n` and `\"`.
fn escaped(value: &str) -> std::borrow::Cow<'_, str> {
    if !value.contains(['\\', '\n', '"']) {
        return value.into();
    }
    value
        .replace('\\', "\\\\")
        .replace('\n', "\\n")
        .replace('"', "\\\"")
        .into()
}

/// `/metrics/per-object`'s body: `head` (every family but the per-queue
/// ones), then each per-queue family written [`CHUNK`] queues at a time
/// as the client reads, with a yield between chunks, so the document is
/// never whole in memory (a family's samples are read a little apart in
/// time, as RabbitMQ's plugin reads its tables).
fn per_object_body(head: String, queues: Vec<QueueRef>) -> Body {
    let families = if queues.is_empty() {
        0
    } else {
        QUEUE_METRICS.len() + 1 + OPTIONAL_METRICS.len()
    };
    let start = (Some(head), queues, 0usize, 0usize);
    let stream = futures_util::stream::unfold(start, move |(head, queues, index, at)| async move {
        if let Some(head) = head {
            return Some((
                Ok::<_, std::io::Error>(Bytes::from(head)),
                (None, queues, index, at),
            ));
        }
        if index >= families {
            return None;
        }
        tokio::task::yield_now().await;
        let end = (at + CHUNK).min(queues.len());
        let text = per_queue_chunk(index, &queues[at..end], at == 0);
        let next = if end == queues.len() {
            (index + 1, 0)
        } else {
            (index, end)
        };
        Some((Ok(Bytes::from(text)), (None, queues, next.0, next.1)))
    });
    Body::from_stream(stream)
}

/// The router of the metrics listener: `/metrics`, `/metrics/per-object`
/// and `/metrics/detailed` (GET only; no request body is read).
pub fn router(context: MetricsContext) -> Router {
    Router::new()
        .route("/metrics", get(aggregated))
        .route("/metrics/per-object", get(per_object))
        .route("/metrics/detailed", get(detailed))
        .layer(DefaultBodyLimit::max(0))
        .with_state(Arc::new(context))
}

async fn aggregated(State(context): State<Arc<MetricsContext>>) -> impl IntoResponse {
    let queues = context.admin.queue_refs();
    let text = scrape(&context, Endpoint::Aggregated, &queues).await;
    ([(CONTENT_TYPE, prometheus::TEXT_FORMAT)], text)
}

async fn per_object(State(context): State<Arc<MetricsContext>>) -> impl IntoResponse {
    let queues = context.admin.queue_refs();
    let head = scrape(&context, Endpoint::PerObject, &queues).await;
    (
        [(CONTENT_TYPE, prometheus::TEXT_FORMAT)],
        per_object_body(head, queues),
    )
}

async fn detailed(
    State(context): State<Arc<MetricsContext>>,
    uri: axum::http::Uri,
) -> impl IntoResponse {
    let filters = detailed::Filters::parse(uri.query());
    (
        [(CONTENT_TYPE, prometheus::TEXT_FORMAT)],
        detailed::body(&context, &filters).await,
    )
}

/// One scrape of `endpoint` over `queues`, as Prometheus text format
/// 0.0.4; for [`Endpoint::PerObject`], all but the per-queue families
/// (`per_object_body` streams those after it).
pub async fn scrape(context: &MetricsContext, endpoint: Endpoint, queues: &[QueueRef]) -> String {
    let (sums, ready_bytes) = queue_sums(queues).await;
    let overview = context.admin.overview();
    let process = ProcessFigures::read(&context.data_dir);
    let mut out = Exposition {
        families: Vec::new(),
    };
    for (name, help, value) in churn_families(&overview.churn) {
        out.counter(&format!("rabbitmq_{name}"), help, value);
    }

    let tcp_limit = tcp_sockets_limit(&overview, &process);
    let optional = [
        (
            "rabbitmq_process_open_tcp_sockets",
            "Open TCP sockets",
            Some(overview.tcp_connections),
        ),
        (
            "rabbitmq_process_max_tcp_sockets",
            "Open TCP sockets limit",
            tcp_limit,
        ),
        (
            "rabbitmq_process_open_fds",
            "Open file descriptors",
            process.open_fds,
        ),
        (
            "rabbitmq_process_resident_memory_bytes",
            "Memory used in bytes",
            process.resident_memory_bytes,
        ),
        (
            "rabbitmq_disk_space_available_bytes",
            "Disk space available in bytes",
            process.disk_free_bytes,
        ),
        (
            "rabbitmq_process_max_fds",
            "Open file descriptors limit",
            process.max_fds,
        ),
    ];
    for (name, help, value) in optional {
        if let Some(value) = value {
            out.gauge(name, help, value);
        }
    }
    // The Prometheus client libraries' process families, from the
    // process itself.
    let standard = [
        (
            "process_open_fds",
            "Number of open file descriptors.",
            process.open_fds.map(|n| n as f64),
        ),
        (
            "process_max_fds",
            "Maximum number of open file descriptors.",
            process.max_fds.map(|n| n as f64),
        ),
        (
            "process_start_time_seconds",
            "Start time of the process since unix epoch in seconds.",
            process.start_time_seconds,
        ),
    ];
    for (name, help, value) in standard {
        if let Some(value) = value {
            out.single(name, MetricType::GAUGE, help, &[], value);
        }
    }
    if let (Some(open), Some(max)) = (process.open_fds, process.max_fds) {
        // RabbitMQ's file-descriptor alarm: every descriptor is in use.
        out.gauge(
            "rabbitmq_alarms_file_descriptor_limit",
            "is 1 if file descriptor limit alarm is in effect",
            u64::from(open >= max),
        );
    }
    // RabbitMQ's figure is the resident-memory watermark (what Grafana's
    // "memory available before publishers blocked" subtracts from);
    // Leveret's second limit, on queued message bytes, has its own name
    // (below).
    if let Some(limit) = overview.resident_memory_limit {
        out.gauge(
            "rabbitmq_resident_memory_limit_bytes",
            "Memory high watermark in bytes",
            limit,
        );
    }
    out.gauge(
        "rabbitmq_disk_space_available_limit_bytes",
        "Free disk space low watermark in bytes",
        overview.disk_free_limit,
    );
    out.single(
        "rabbitmq_erlang_uptime_seconds",
        MetricType::GAUGE,
        "Node uptime",
        &[],
        overview.uptime.as_secs_f64(),
    );

    if endpoint == Endpoint::Aggregated {
        for ((name, kind, help, _), sum) in QUEUE_METRICS.into_iter().zip(sums) {
            out.single(name, kind, help, &[], sum as f64);
        }
    }

    let totals = &overview.object_totals;
    out.gauge(
        "rabbitmq_connections",
        "Connections currently open",
        totals.connections,
    );
    out.gauge(
        "rabbitmq_channels",
        "Channels currently open",
        totals.channels,
    );
    out.gauge(
        "rabbitmq_consumers",
        "Consumers currently connected",
        totals.consumers,
    );
    out.gauge("rabbitmq_queues", "Queues available", totals.queues);

    let m = &overview.message_stats;
    let protocol = [PROTOCOL];
    let global = [
        ("rabbitmq_global_messages_received_total", "Total number of messages received from publishers", m.received),
        ("rabbitmq_global_messages_received_confirm_total", "Total number of messages received from publishers expecting confirmations", m.received_confirm),
        ("rabbitmq_global_messages_routed_total", "Total number of messages routed to queues or streams", m.routed),
        ("rabbitmq_global_messages_unroutable_dropped_total", "Total number of messages published as non-mandatory into an exchange and dropped as unroutable", m.unroutable_dropped),
        ("rabbitmq_global_messages_unroutable_returned_total", "Total number of messages published as mandatory into an exchange and returned to the publisher as unroutable", m.unroutable_returned),
        ("rabbitmq_global_messages_confirmed_total", "Total number of messages confirmed to publishers", m.confirmed),
    ];
    for (name, help, value) in global {
        out.single(name, MetricType::COUNTER, help, &protocol, value as f64);
    }
    out.single(
        "rabbitmq_global_publishers",
        MetricType::GAUGE,
        "Current number of publishers",
        &protocol,
        overview.publishers as f64,
    );
    out.single(
        "rabbitmq_global_consumers",
        MetricType::GAUGE,
        "Current number of consumers",
        &protocol,
        totals.consumers as f64,
    );
    let by_queue_type = [PROTOCOL, QUEUE_TYPE];
    let deliveries = [
        ("rabbitmq_global_messages_delivered_total", "Total number of messages delivered to consumers", m.delivered()),
        ("rabbitmq_global_messages_delivered_consume_manual_ack_total", "Total number of messages delivered to consumers using basic.consume with manual acknowledgment", m.delivered_consume_manual_ack),
        ("rabbitmq_global_messages_delivered_consume_auto_ack_total", "Total number of messages delivered to consumers using basic.consume with automatic acknowledgment", m.delivered_consume_auto_ack),
        ("rabbitmq_global_messages_delivered_get_manual_ack_total", "Total number of messages delivered to consumers using basic.get with manual acknowledgment", m.delivered_get_manual_ack),
        ("rabbitmq_global_messages_delivered_get_auto_ack_total", "Total number of messages delivered to consumers using basic.get with automatic acknowledgment", m.delivered_get_auto_ack),
        ("rabbitmq_global_messages_get_empty_total", "Total number of times basic.get operations fetched no message", m.get_empty),
        ("rabbitmq_global_messages_redelivered_total", "Total number of messages redelivered to consumers", m.redelivered),
        ("rabbitmq_global_messages_acknowledged_total", "Total number of messages acknowledged by consumers", m.acknowledged),
    ];
    for (name, help, value) in deliveries {
        out.single(
            name,
            MetricType::COUNTER,
            help,
            &by_queue_type,
            value as f64,
        );
    }

    dead_lettered_families(&mut out, &overview.dead_lettered);
    auth_attempt_families(&mut out, "rabbitmq_", &overview.auth_attempts);
    if endpoint == Endpoint::Aggregated {
        channel_sums(&mut out, &context.admin, totals.channels);
        for (name, help, value) in traffic_families(&overview.socket_traffic) {
            out.counter(&format!("rabbitmq_{name}"), help, value);
        }
    }

    out.single(
        "rabbitmq_alarms_free_disk_space_watermark",
        MetricType::GAUGE,
        "is 1 if free disk space watermark alarm is in effect",
        &[],
        if overview.disk_alarm { 1.0 } else { 0.0 },
    );
    out.single(
        "rabbitmq_alarms_memory_used_watermark",
        MetricType::GAUGE,
        "is 1 if VM memory watermark alarm is in effect",
        &[],
        if overview.memory_alarm { 1.0 } else { 0.0 },
    );

    // Leveret's own.
    out.gauge(
        "leveret_queued_message_bytes",
        "Body bytes of the ready messages in all queues",
        ready_bytes,
    );
    out.gauge(
        "leveret_queued_bytes_limit_bytes",
        "Queued message bytes above which publishers are blocked",
        overview.memory_high_watermark as u64,
    );
    if let Some(busy) = overview.busy_poll {
        out.counter(
            "leveret_socket_reads_total",
            "Total number of reads from client sockets",
            busy.socket_reads,
        );
        out.counter(
            "leveret_busy_poll_windows_total",
            "Total number of windows in which the broker's thread polled for input instead of sleeping",
            busy.windows,
        );
        out.single(
            "leveret_busy_poll_seconds_total",
            MetricType::COUNTER,
            "Total time the broker's thread spent polling for input instead of sleeping",
            &[],
            busy.polling.as_secs_f64(),
        );
    }

    if let Some(persister) = context.admin.persister() {
        out.histogram(
            "leveret_persister_batch_ops",
            "Store operations written per group commit",
            &persister.batch_ops,
        );
        out.histogram(
            "leveret_persister_flush_seconds",
            "Time each group commit took to write and flush its operations",
            &persister.flush_seconds,
        );
    }

    shovel_metrics(&mut out, &context.shovels);

    info_families(&mut out, context, &overview, endpoint.label());
    out.encode()
}

/// RabbitMQ's `connection_churn_metrics`, without their prefix.
fn churn_families(churn: &ChurnTotals) -> [(&'static str, &'static str, u64); 7] {
    [
        (
            "connections_opened_total",
            "Total number of connections opened",
            churn.connections_opened,
        ),
        (
            "connections_closed_total",
            "Total number of connections closed or terminated",
            churn.connections_closed,
        ),
        (
            "channels_opened_total",
            "Total number of channels opened",
            churn.channels_opened,
        ),
        (
            "channels_closed_total",
            "Total number of channels closed",
            churn.channels_closed,
        ),
        (
            "queues_declared_total",
            "Total number of queues declared",
            churn.queues_declared,
        ),
        (
            "queues_created_total",
            "Total number of queues created",
            churn.queues_created,
        ),
        (
            "queues_deleted_total",
            "Total number of queues deleted",
            churn.queues_deleted,
        ),
    ]
}

/// The most TCP client sockets Leveret will hold: `connection_max` when
/// set, never more than the open-file limit (each socket is a file).
fn tcp_sockets_limit(overview: &Overview, process: &ProcessFigures) -> Option<u64> {
    match (overview.tcp_connections_limit, process.max_fds) {
        (Some(max), Some(fds)) => Some(max.min(fds)),
        (max, fds) => max.or(fds),
    }
}

/// RabbitMQ's `auth_attempt_metrics`, labelled by protocol, named with
/// `prefix`.
fn auth_attempt_families(out: &mut Exposition, prefix: &str, attempts: &[AuthAttemptFigures]) {
    type Figure = fn(&AuthAttemptFigures) -> u64;
    let families: [(&str, &str, Figure); 3] = [
        (
            "auth_attempts_total",
            "Total number of authorization attempts",
            |a| a.succeeded + a.failed,
        ),
        (
            "auth_attempts_succeeded_total",
            "Total number of successful authentication attempts",
            |a| a.succeeded,
        ),
        (
            "auth_attempts_failed_total",
            "Total number of failed authentication attempts",
            |a| a.failed,
        ),
    ];
    for (name, help, figure) in families {
        let family = out.family(&format!("{prefix}{name}"), MetricType::COUNTER, help);
        for a in attempts {
            family.mut_metric().push(sample(
                MetricType::COUNTER,
                &[("protocol", a.protocol)],
                figure(a) as f64,
            ));
        }
    }
}

/// RabbitMQ 3.10's `rabbitmq_global_messages_dead_lettered_*_total` of
/// classic queues, labelled `queue_type` and `dead_letter_strategy`.
fn dead_lettered_families(out: &mut Exposition, figures: &[DeadLetteredFigures]) {
    type Figure = fn(&DeadLetteredFigures) -> u64;
    let families: [(&str, &str, Figure); 3] = [
        ("rabbitmq_global_messages_dead_lettered_expired_total", "Total number of messages dead-lettered due to message TTL exceeded", |d| d.expired),
        ("rabbitmq_global_messages_dead_lettered_rejected_total", "Total number of messages dead-lettered due to basic.reject or basic.nack", |d| d.rejected),
        ("rabbitmq_global_messages_dead_lettered_maxlen_total", "Total number of messages dead-lettered due to overflow drop-head or reject-publish-dlx", |d| d.maxlen),
    ];
    for (name, help, figure) in families {
        let family = out.family(name, MetricType::COUNTER, help);
        for d in figures {
            let labels = [QUEUE_TYPE, ("dead_letter_strategy", d.strategy)];
            family
                .mut_metric()
                .push(sample(MetricType::COUNTER, &labels, figure(d) as f64));
        }
    }
}

/// A channel's figure.
type ChannelFigure = fn(&leveret_broker::ChannelInfo) -> u64;
/// RabbitMQ's `channel_metrics`, without their prefix, in its order.
#[rustfmt::skip]
const CHANNEL_METRICS: [(&str, &str, ChannelFigure); 7] = [
    ("channel_consumers", "Consumers on a channel", |c| c.consumers),
    ("channel_messages_unacked", "Delivered but not yet acknowledged messages", |c| c.messages_unacknowledged),
    ("channel_messages_unconfirmed", "Published but not yet confirmed messages", |c| c.messages_unconfirmed),
    ("channel_messages_uncommitted", "Messages received in a transaction but not yet committed", |c| c.messages_uncommitted),
    ("channel_acks_uncommitted", "Message acknowledgements in a transaction not yet committed", |c| c.acks_uncommitted),
    ("consumer_prefetch", "Limit of unacknowledged messages for each consumer", |c| u64::from(c.prefetch_count)),
    ("channel_prefetch", "Total limit of unacknowledged messages for all consumers on a channel", |c| u64::from(c.global_prefetch_count)),
];

/// RabbitMQ's `channel_metrics` and `connection_channels` as `/metrics`
/// writes them: sums over every channel (`channels`: the open channels).
fn channel_sums(out: &mut Exposition, admin: &leveret_broker::Admin, channels: u64) {
    let mut sums = [0u64; CHANNEL_METRICS.len()];
    for c in admin.channels() {
        for (sum, (.., figure)) in sums.iter_mut().zip(CHANNEL_METRICS) {
            *sum += figure(&c);
        }
    }
    for ((name, help, _), sum) in CHANNEL_METRICS.into_iter().zip(sums) {
        out.gauge(&format!("rabbitmq_{name}"), help, sum);
    }
    out.gauge(
        "rabbitmq_connection_channels",
        "Channels on a connection",
        channels,
    );
}

/// RabbitMQ's `connection_coarse_metrics` and `connection_metrics`
/// counters, without their prefix: bytes, and the reads and writes that
/// moved them. On `/metrics` they count every client socket since start
/// (RabbitMQ sums the open connections only, so its sums fall when one
/// closes).
fn traffic_families(t: &SocketTrafficFigures) -> [(&'static str, &'static str, u64); 4] {
    [
        (
            "connection_incoming_bytes_total",
            "Total number of bytes received on a connection",
            t.received_bytes,
        ),
        (
            "connection_outgoing_bytes_total",
            "Total number of bytes sent on a connection",
            t.sent_bytes,
        ),
        (
            "connection_incoming_packets_total",
            "Total number of packets received on a connection",
            t.reads,
        ),
        (
            "connection_outgoing_packets_total",
            "Total number of packets sent on a connection",
            t.writes,
        ),
    ]
}

/// `rabbitmq_build_info` and `rabbitmq_identity_info`, which every
/// endpoint ends with.
fn info_families(
    out: &mut Exposition,
    context: &MetricsContext,
    overview: &Overview,
    endpoint: &str,
) {
    let version = overview.version;
    out.single(
        "rabbitmq_build_info",
        MetricType::GAUGE,
        "RabbitMQ & Erlang/OTP version info",
        &[
            ("product_name", overview.product.as_str()),
            ("product_version", version),
            ("rabbitmq_version", version),
            ("prometheus_plugin_version", version),
            ("prometheus_client_version", PROMETHEUS_CLIENT_VERSION),
            // The dashboard's nodes table has an Erlang/OTP column; Leveret
            // runs no Erlang, and says so rather than leave the cell blank.
            ("erlang_version", "none"),
        ],
        1.0,
    );
    // RabbitMQ's cluster name (the node's name until one is set).
    let cluster = crate::policies::cluster_name(&context.admin, &context.node);
    out.single(
        "rabbitmq_identity_info",
        MetricType::GAUGE,
        "RabbitMQ node & cluster identity info",
        &[
            ("rabbitmq_node", context.node.as_str()),
            ("rabbitmq_cluster", cluster.as_str()),
            ("rabbitmq_endpoint", endpoint),
        ],
        1.0,
    );
}

/// The `prometheus` crate's version, for `rabbitmq_build_info`.
const PROMETHEUS_CLIENT_VERSION: &str = "0.14";
