//! `/metrics/detailed`: RabbitMQ 3.10's endpoint of chosen metric
//! families, each per object, named `rabbitmq_detailed_*` (the cluster
//! families `rabbitmq_cluster_*`), followed by `rabbitmq_build_info` and
//! `rabbitmq_identity_info`. `family=NAME` (repeatable) chooses the
//! families, by RabbitMQ's names; without one the endpoint returns only
//! the two info families, as RabbitMQ's does. `vhost=NAME` (repeatable)
//! keeps the queue families to those vhosts (unknown names are ignored,
//! as RabbitMQ ignores them). Families RabbitMQ has and Leveret has no
//! true figures for (`ra_metrics`, `node_persister_metrics`,
//! `channel_exchange_metrics`, `channel_process_metrics`,
//! `channel_queue_metrics`, `channel_queue_exchange_metrics`, `auth_attempt_detailed_metrics`) are
//! accepted and yield nothing; so do unknown names.
//!
//! The per-queue families are written [`CHUNK`] queues at a time as the
//! client reads, as `/metrics/per-object` writes them.

use super::{escaped, sample, Exposition, MetricsContext, OptionalFigure, CHUNK};
use crate::management::json::{channel_name, connection_name};
use crate::process::ProcessFigures;
use axum::body::{Body, Bytes};
use leveret_broker::{Admin, QueueRef};
use prometheus::proto::MetricType;
use std::collections::{BTreeMap, HashSet, VecDeque};

/// The families of RabbitMQ's that `/metrics/detailed` answers with data,
/// in the order RabbitMQ writes them.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Family {
    ConnectionChurn,
    NodeCoarse,
    Node,
    AuthAttempts,
    QueueCoarse,
    QueueConsumerCount,
    Queue,
    Channel,
    ConnectionCoarse,
    Connection,
    VhostStatus,
    ExchangeBindings,
    ExchangeNames,
}

const FAMILIES: [(&str, Family); 13] = [
    ("connection_churn_metrics", Family::ConnectionChurn),
    ("node_coarse_metrics", Family::NodeCoarse),
    ("node_metrics", Family::Node),
    ("auth_attempt_metrics", Family::AuthAttempts),
    ("queue_coarse_metrics", Family::QueueCoarse),
    ("queue_consumer_count", Family::QueueConsumerCount),
    ("queue_metrics", Family::Queue),
    ("channel_metrics", Family::Channel),
    ("connection_coarse_metrics", Family::ConnectionCoarse),
    ("connection_metrics", Family::Connection),
    ("vhost_status", Family::VhostStatus),
    ("exchange_bindings", Family::ExchangeBindings),
    ("exchange_names", Family::ExchangeNames),
];

const PREFIX: &str = "rabbitmq_detailed_";
const CLUSTER_PREFIX: &str = "rabbitmq_cluster_";

/// What a request asked for.
#[derive(Debug, Default, PartialEq)]
pub struct Filters {
    families: Vec<Family>,
    /// `None`: every vhost.
    vhosts: Option<HashSet<String>>,
}

impl Filters {
    /// Reads `family=` and `vhost=` from a query string (each repeatable,
    /// percent-encoded, `+` for a space).
    pub fn parse(query: Option<&str>) -> Filters {
        let mut asked = HashSet::new();
        let mut vhosts: Option<HashSet<String>> = None;
        for pair in query.unwrap_or_default().split('&') {
            let (key, value) = pair.split_once('=').unwrap_or((pair, ""));
            let value = crate::management::percent_decoded(&value.replace('+', " "));
            match key {
                "family" => {
                    asked.insert(value);
                }
                "vhost" => {
                    vhosts.get_or_insert_with(HashSet::new).insert(value);
                }
                _ => {}
            }
        }
        let families = FAMILIES
            .iter()
            .filter(|(name, _)| asked.contains(*name))
            .map(|&(_, family)| family)
            // As RabbitMQ: queue_consumer_count is a subset of queue_metrics.
            .filter(|family| {
                *family != Family::QueueConsumerCount || !asked.contains("queue_metrics")
            })
            .collect();
        Filters { families, vhosts }
    }

    fn wants(&self, family: Family) -> bool {
        self.families.contains(&family)
    }
}

/// A family of per-queue samples (none for a queue without the figure).
type QueueFamily = (&'static str, MetricType, &'static str, OptionalFigure);

#[rustfmt::skip]
const QUEUE_COARSE: [QueueFamily; 3] = [
    ("queue_messages_ready", MetricType::GAUGE, "Messages ready to be delivered to consumers", |q| Some(q.messages_ready)),
    ("queue_messages_unacked", MetricType::GAUGE, "Messages delivered to consumers but not yet acknowledged", |q| Some(q.messages_unacknowledged)),
    ("queue_messages", MetricType::GAUGE, "Sum of ready and unacknowledged messages - total queue depth", |q| Some(q.messages())),
];
const QUEUE_CONSUMERS: QueueFamily = (
    "queue_consumers",
    MetricType::GAUGE,
    "Consumers on a queue",
    |q| Some(q.consumers),
);
/// `queue_metrics` beside the consumers, in RabbitMQ's order.
#[rustfmt::skip]
const QUEUE_METRICS: [QueueFamily; 5] = [
    ("queue_messages_persistent", MetricType::GAUGE, "Persistent messages", |q| Some(q.messages_persistent)),
    ("queue_messages_bytes", MetricType::GAUGE, "Size in bytes of ready and unacknowledged messages", |q| Some(q.message_bytes_ready + q.message_bytes_unacknowledged)),
    ("queue_messages_ready_bytes", MetricType::GAUGE, "Size in bytes of ready messages", |q| Some(q.message_bytes_ready)),
    ("queue_messages_unacked_bytes", MetricType::GAUGE, "Size in bytes of all unacknowledged messages", |q| Some(q.message_bytes_unacknowledged)),
    ("queue_head_message_timestamp", MetricType::GAUGE, "Timestamp of the first message in the queue, if any", |q| q.head_message_timestamp),
];

/// A piece of the body: text already written, or a per-queue family.
enum Piece {
    Text(String),
    Queues(QueueFamily),
}

/// `/metrics/detailed`'s body for `filters`.
pub async fn body(context: &MetricsContext, filters: &Filters) -> Body {
    let admin = &context.admin;
    let mut pieces = VecDeque::new();
    let mut out = Exposition::default();
    let overview = admin.overview();
    let process = ProcessFigures::read(&context.data_dir);
    let family = |out: &mut Exposition, name: &str, kind, help: &str, value: f64| {
        out.single(&format!("{PREFIX}{name}"), kind, help, &[], value)
    };
    if filters.wants(Family::ConnectionChurn) {
        let churn = &overview.churn;
        for (name, help, value) in super::churn_families(churn) {
            family(&mut out, name, MetricType::COUNTER, help, value as f64);
        }
    }
    let tcp_limit = super::tcp_sockets_limit(&overview, &process);
    if filters.wants(Family::NodeCoarse) {
        let coarse = [
            (
                "process_open_fds",
                "Open file descriptors",
                process.open_fds,
            ),
            (
                "process_open_tcp_sockets",
                "Open TCP sockets",
                Some(overview.tcp_connections),
            ),
            (
                "process_resident_memory_bytes",
                "Memory used in bytes",
                process.resident_memory_bytes,
            ),
            (
                "disk_space_available_bytes",
                "Disk space available in bytes",
                process.disk_free_bytes,
            ),
        ];
        for (name, help, value) in coarse {
            if let Some(value) = value {
                family(&mut out, name, MetricType::GAUGE, help, value as f64);
            }
        }
    }
    if filters.wants(Family::Node) {
        let node = [
            (
                "process_max_fds",
                "Open file descriptors limit",
                process.max_fds,
            ),
            (
                "process_max_tcp_sockets",
                "Open TCP sockets limit",
                tcp_limit,
            ),
            (
                "resident_memory_limit_bytes",
                "Memory high watermark in bytes",
                overview.resident_memory_limit,
            ),
            (
                "disk_space_available_limit_bytes",
                "Free disk space low watermark in bytes",
                Some(overview.disk_free_limit),
            ),
        ];
        for (name, help, value) in node {
            if let Some(value) = value {
                family(&mut out, name, MetricType::GAUGE, help, value as f64);
            }
        }
        family(
            &mut out,
            "erlang_uptime_seconds",
            MetricType::GAUGE,
            "Node uptime",
            overview.uptime.as_secs_f64(),
        );
    }
    if filters.wants(Family::AuthAttempts) {
        super::auth_attempt_families(&mut out, PREFIX, &overview.auth_attempts);
    }
    pieces.push_back(Piece::Text(std::mem::take(&mut out).encode()));

    if filters.wants(Family::QueueCoarse) {
        pieces.extend(QUEUE_COARSE.map(Piece::Queues));
    }
    if filters.wants(Family::QueueConsumerCount) || filters.wants(Family::Queue) {
        pieces.push_back(Piece::Queues(QUEUE_CONSUMERS));
    }
    if filters.wants(Family::Queue) {
        pieces.extend(QUEUE_METRICS.map(Piece::Queues));
    }
    let queues = if pieces.len() > 1 {
        queue_refs(admin, filters.vhosts.as_ref())
    } else {
        Vec::new()
    };

    if filters.wants(Family::Channel) {
        channel_families(&mut out, admin);
    }
    connection_families(&mut out, admin, filters);
    if filters.wants(Family::VhostStatus) {
        let status = out.family(
            &format!("{CLUSTER_PREFIX}vhost_status"),
            MetricType::GAUGE,
            "Whether a given vhost is running",
        );
        for vhost in admin.vhosts() {
            // A vhost Leveret lists is running: it has no other state.
            status
                .mut_metric()
                .push(sample(MetricType::GAUGE, &[("vhost", &vhost)], 1.0));
        }
    }
    if filters.wants(Family::ExchangeBindings) || filters.wants(Family::ExchangeNames) {
        exchange_families(&mut out, admin, filters);
    }
    super::info_families(&mut out, context, &overview, "detailed");
    pieces.push_back(Piece::Text(out.encode()));
    streamed(pieces, queues)
}

/// The queues of the chosen vhosts.
fn queue_refs(admin: &Admin, vhosts: Option<&HashSet<String>>) -> Vec<QueueRef> {
    let mut queues = admin.queue_refs();
    if let Some(vhosts) = vhosts {
        queues.retain(|queue| vhosts.contains(queue.vhost()));
    }
    queues
}

/// RabbitMQ's `channel_metrics`, one
/// sample per channel labelled with the channel's name.
fn channel_families(out: &mut Exposition, admin: &Admin) {
    let channels = admin.channels();
    let names: Vec<String> = channels
        .iter()
        .map(|c| channel_name(c.connection_id, &c.connection_peer, c.number))
        .collect();
    for (name, help, figure) in super::CHANNEL_METRICS {
        let family = out.family(&format!("{PREFIX}{name}"), MetricType::GAUGE, help);
        for (channel, label) in channels.iter().zip(&names) {
            family.mut_metric().push(sample(
                MetricType::GAUGE,
                &[("channel", label)],
                figure(channel) as f64,
            ));
        }
    }
}

/// `connection_coarse_metrics` (bytes) and `connection_metrics` (reads,
/// writes and channels), one sample per connection labelled, as
/// RabbitMQ labels them, `channel` (with the connection's name).
/// In-process connections have no socket, and no traffic samples.
fn connection_families(out: &mut Exposition, admin: &Admin, filters: &Filters) {
    let coarse = filters.wants(Family::ConnectionCoarse);
    let metrics = filters.wants(Family::Connection);
    if !coarse && !metrics {
        return;
    }
    let connections = admin.connections();
    let names: Vec<String> = connections
        .iter()
        .map(|c| connection_name(c.id, &c.peer))
        .collect();
    let traffic: Vec<_> = connections
        .iter()
        .zip(&names)
        .filter_map(|(c, name)| Some((c.traffic?, name)))
        .collect();
    let families = super::traffic_families(&Default::default());
    let chosen = families
        .iter()
        .enumerate()
        .filter(|(at, _)| if *at < 2 { coarse } else { metrics });
    for (at, (name, help, _)) in chosen {
        let family = out.family(&format!("{PREFIX}{name}"), MetricType::COUNTER, help);
        for (figures, label) in &traffic {
            let value = super::traffic_families(figures)[at].2;
            family.mut_metric().push(sample(
                MetricType::COUNTER,
                &[("channel", label)],
                value as f64,
            ));
        }
    }
    if metrics {
        let channels = out.family(
            &format!("{PREFIX}connection_channels"),
            MetricType::GAUGE,
            "Channels on a connection",
        );
        for (c, name) in connections.iter().zip(&names) {
            channels.mut_metric().push(sample(
                MetricType::GAUGE,
                &[("channel", name)],
                c.channels as f64,
            ));
        }
    }
}

/// `exchange_bindings` and `exchange_names`: every exchange but the
/// default and internal ones, as RabbitMQ lists them.
fn exchange_families(out: &mut Exposition, admin: &Admin, filters: &Filters) {
    let exchanges: Vec<_> = admin
        .exchanges()
        .into_iter()
        .filter(|e| !e.internal && !e.name.is_empty())
        .collect();
    if filters.wants(Family::ExchangeBindings) {
        let mut bindings: BTreeMap<(String, String), u64> = BTreeMap::new();
        for binding in admin.bindings() {
            *bindings.entry((binding.vhost, binding.source)).or_default() += 1;
        }
        let family = out.family(
            &format!("{CLUSTER_PREFIX}exchange_bindings"),
            MetricType::GAUGE,
            "Number of bindings for an exchange. This value is cluster-wide.",
        );
        for e in &exchanges {
            let count = bindings
                .get(&(e.vhost.clone(), e.name.clone()))
                .copied()
                .unwrap_or(0);
            let labels = [
                ("vhost", e.vhost.as_str()),
                ("exchange", e.name.as_str()),
                ("type", e.kind),
            ];
            family
                .mut_metric()
                .push(sample(MetricType::GAUGE, &labels, count as f64));
        }
    }
    if filters.wants(Family::ExchangeNames) {
        let family = out.family(
            &format!("{CLUSTER_PREFIX}exchange_name"),
            MetricType::GAUGE,
            "Enumerates exchanges without any additional info. This value is cluster-wide. A cheaper alternative to `exchange_bindings`",
        );
        for e in &exchanges {
            let labels = [
                ("vhost", e.vhost.as_str()),
                ("exchange", e.name.as_str()),
                ("type", e.kind),
            ];
            family
                .mut_metric()
                .push(sample(MetricType::GAUGE, &labels, 1.0));
        }
    }
}

/// One chunk of a per-queue family: its HELP and TYPE lines when
/// `first`, then a sample per queue, read as its turn comes.
fn queue_chunk(family: &QueueFamily, queues: &[QueueRef], first: bool) -> String {
    use std::fmt::Write;
    let (name, kind, help, figure) = family;
    let mut text = String::new();
    if first {
        let kind = if *kind == MetricType::COUNTER {
            "counter"
        } else {
            "gauge"
        };
        let _ = write!(
            text,
            "# HELP {PREFIX}{name} {help}\n# TYPE {PREFIX}{name} {kind}\n"
        );
    }
    for queue in queues {
        if let Some(value) = figure(&queue.info()) {
            let _ = writeln!(
                text,
                "{PREFIX}{name}{{vhost=\"{}\",queue=\"{}\"}} {value}",
                escaped(queue.vhost()),
                escaped(queue.name()),
            );
        }
    }
    text
}

/// The body: the first text piece, each per-queue family [`CHUNK`]
/// queues at a time with a yield between chunks, the last text piece.
fn streamed(pieces: VecDeque<Piece>, queues: Vec<QueueRef>) -> Body {
    let stream = futures_util::stream::unfold(
        (pieces, queues, 0usize),
        |(mut pieces, queues, mut at)| async move {
            loop {
                match pieces.front()? {
                    Piece::Text(_) => {
                        let Some(Piece::Text(text)) = pieces.pop_front() else {
                            unreachable!("the front is text");
                        };
                        return Some((
                            Ok::<_, std::io::Error>(Bytes::from(text)),
                            (pieces, queues, 0),
                        ));
                    }
                    Piece::Queues(family) => {
                        if at >= queues.len() {
                            pieces.pop_front();
                            at = 0;
                            continue;
                        }
                        tokio::task::yield_now().await;
                        let end = (at + CHUNK).min(queues.len());
                        let text = queue_chunk(family, &queues[at..end], at == 0);
                        return Some((Ok(Bytes::from(text)), (pieces, queues, end)));
                    }
                }
            }
        },
    );
    Body::from_stream(stream)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn families_and_vhosts_are_read_from_repeated_parameters() {
        let filters = Filters::parse(Some(
            "family=queue_coarse_metrics&vhost=%2F&family=channel_metrics&vhost=a+b&family=nonsense",
        ));
        assert_eq!(filters.families, [Family::QueueCoarse, Family::Channel]);
        let vhosts = filters.vhosts.expect("vhosts");
        assert!(vhosts.contains("/") && vhosts.contains("a b") && vhosts.len() == 2);
        assert_eq!(Filters::parse(None), Filters::default());
    }

    #[test]
    fn queue_consumer_count_gives_way_to_queue_metrics() {
        let both = Filters::parse(Some("family=queue_consumer_count&family=queue_metrics"));
        assert_eq!(both.families, [Family::Queue]);
        let alone = Filters::parse(Some("family=queue_consumer_count"));
        assert_eq!(alone.families, [Family::QueueConsumerCount]);
    }
}
