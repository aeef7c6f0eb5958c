//! The plain structs the broker's state is read into, with RabbitMQ's
//! field meanings (its management API's `messages`, `messages_ready`,
//! `messages_unacknowledged`, `consumers`, `message_stats`, ...), and
//! [`QueueRef`], a handle for reading one queue's figures later. The
//! operator layer's `Admin` fills them (`admin::inspect`) for the
//! embedding API and the `leveret` binary's HTTP listeners.
//!
//! Uses the queue (a [`QueueRef`] reads its figures) and the shared
//! pieces (`policy`, `stats`); nothing of the operator layer.

use crate::policy::Applied;
use crate::queue::Queue;
pub use crate::queue::StreamFigures;
use crate::stats::SocketTraffic;
use leveret_protocol::{FieldTable, ShortStr};
use std::sync::Arc;
use std::time::{Duration, SystemTime};

/// Broker-wide figures: RabbitMQ's `/api/overview` and
/// `rabbitmq_global_*` metrics.
#[derive(Debug, Clone, PartialEq)]
pub struct Overview {
    /// The product name announced to clients.
    pub product: String,
    /// Leveret's version.
    pub version: &'static str,
    /// Time since the broker started.
    pub uptime: Duration,
    /// How many of each kind of object exist now.
    pub object_totals: ObjectTotals,
    /// Messages in all queues.
    pub queue_totals: QueueTotals,
    /// Message counters since start.
    pub message_stats: GlobalMessageStats,
    /// Connection, channel and queue churn since start.
    pub churn: ChurnTotals,
    /// Channels that have published and are still open.
    pub publishers: u64,
    /// The memory high watermark: queued-message bytes above which
    /// publishers are blocked.
    pub memory_high_watermark: usize,
    /// The bytes counted against it now (queued messages, transactions'
    /// publishes, bodies being received).
    pub memory_used: usize,
    /// The resident-memory watermark in bytes (RabbitMQ's
    /// `vm_memory_high_watermark`): resident memory above it blocks
    /// publishers. `None` where resident memory is not watched.
    pub resident_memory_limit: Option<u64>,
    /// Whether the memory alarm is set now.
    pub memory_alarm: bool,
    /// Free disk bytes below which publishers are blocked.
    pub disk_free_limit: u64,
    /// Whether the disk alarm is set now.
    pub disk_alarm: bool,
    /// Busy polling's figures, if the broker busy-polls.
    pub busy_poll: Option<BusyPollFigures>,
    /// Bytes and reads on every client socket since start.
    pub socket_traffic: SocketTrafficFigures,
    /// TCP client connections served now (in-process ones not counted).
    pub tcp_connections: u64,
    /// The most served at once (`connection_max`), if limited.
    pub tcp_connections_limit: Option<u64>,
    /// Logins by protocol (RabbitMQ's `auth_attempt_metrics`).
    pub auth_attempts: Vec<AuthAttemptFigures>,
    /// Messages queues let go for good, by what became of them
    /// (RabbitMQ's `messages_dead_lettered_*` of classic queues).
    pub dead_lettered: Vec<DeadLetteredFigures>,
}

/// What went through client sockets (RabbitMQ's `recv_oct`, `recv_cnt`,
/// `send_oct`, `send_cnt`). Over TLS, the bytes are those of the
/// decrypted stream.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct SocketTrafficFigures {
    /// Bytes read.
    pub received_bytes: u64,
    /// Reads that returned bytes.
    pub reads: u64,
    /// Bytes written.
    pub sent_bytes: u64,
    /// Writes that took bytes.
    pub writes: u64,
}

impl SocketTrafficFigures {
    pub(crate) fn read(traffic: &SocketTraffic) -> Self {
        SocketTrafficFigures {
            received_bytes: traffic.received_bytes.get(),
            reads: traffic.reads.get(),
            sent_bytes: traffic.sent_bytes.get(),
            writes: traffic.writes.get(),
        }
    }
}

/// One protocol's logins since start.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct AuthAttemptFigures {
    /// As RabbitMQ labels it: `amqp091` or `mqtt`.
    pub protocol: &'static str,
    /// Logins that passed.
    pub succeeded: u64,
    /// Logins refused.
    pub failed: u64,
}

/// Messages that left classic queues for good by expiry, rejection
/// (basic.reject or basic.nack without requeue) or overflow, by
/// RabbitMQ's `dead_letter_strategy`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct DeadLetteredFigures {
    /// `disabled` (dropped: no dead-letter exchange, or a missing one) or
    /// `at_most_once` (republished to the dead-letter exchange).
    pub strategy: &'static str,
    /// Their TTL passed.
    pub expired: u64,
    /// Rejected or nacked without requeue.
    pub rejected: u64,
    /// Dropped by x-max-length or x-max-length-bytes.
    pub maxlen: u64,
}

/// What busy polling has cost (see `BrokerBuilder::busy_poll`).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct BusyPollFigures {
    /// Socket reads by all connections.
    pub socket_reads: u64,
    /// Windows the broker's thread polled through instead of sleeping.
    pub windows: u64,
    /// Time the broker's thread spent polling in those windows.
    pub polling: Duration,
    /// Times polling stopped early because other threads were waiting for
    /// a CPU.
    pub yielded_to_cpu_pressure: u64,
}

/// Counts of live objects (RabbitMQ's `object_totals`).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct ObjectTotals {
    /// Open connections (handshake done).
    pub connections: u64,
    /// Open channels.
    pub channels: u64,
    /// Exchanges, the predefined ones included.
    pub exchanges: u64,
    /// Queues.
    pub queues: u64,
    /// Consumers.
    pub consumers: u64,
}

/// Message counts over queues (RabbitMQ's `queue_totals`).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct QueueTotals {
    /// Ready to be delivered.
    pub messages_ready: u64,
    /// Delivered and not yet acknowledged.
    pub messages_unacknowledged: u64,
}

impl QueueTotals {
    /// Ready plus unacknowledged.
    pub fn messages(&self) -> u64 {
        self.messages_ready + self.messages_unacknowledged
    }
}

/// Broker-wide message counters since start, with RabbitMQ's
/// `rabbitmq_global_messages_*_total` meanings.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct GlobalMessageStats {
    /// Messages received from publishers.
    pub received: u64,
    /// Messages received on channels in confirm mode.
    pub received_confirm: u64,
    /// Messages routed to at least one queue.
    pub routed: u64,
    /// Non-mandatory messages dropped as unroutable.
    pub unroutable_dropped: u64,
    /// Mandatory messages returned as unroutable.
    pub unroutable_returned: u64,
    /// Publisher confirms sent.
    pub confirmed: u64,
    /// Deliveries to consumers that must ack.
    pub delivered_consume_manual_ack: u64,
    /// Deliveries to no-ack consumers.
    pub delivered_consume_auto_ack: u64,
    /// basic.get answers that must be acked.
    pub delivered_get_manual_ack: u64,
    /// basic.get answers with no-ack.
    pub delivered_get_auto_ack: u64,
    /// basic.get calls that found nothing.
    pub get_empty: u64,
    /// Deliveries of messages delivered before.
    pub redelivered: u64,
    /// Acknowledgements.
    pub acknowledged: u64,
}

impl GlobalMessageStats {
    /// Every delivery, by consume or get, with or without ack
    /// (`rabbitmq_global_messages_delivered_total`).
    pub fn delivered(&self) -> u64 {
        self.delivered_consume_manual_ack
            + self.delivered_consume_auto_ack
            + self.delivered_get_manual_ack
            + self.delivered_get_auto_ack
    }
}

/// Churn since start (`rabbitmq_*_opened_total` and so on).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct ChurnTotals {
    /// Connections whose handshake completed.
    pub connections_opened: u64,
    /// Of those, closed.
    pub connections_closed: u64,
    /// Channels opened.
    pub channels_opened: u64,
    /// Channels closed.
    pub channels_closed: u64,
    /// queue.declare calls (not passive).
    pub queues_declared: u64,
    /// Queues created.
    pub queues_created: u64,
    /// Queues deleted.
    pub queues_deleted: u64,
}

/// One queue (RabbitMQ's `/api/queues` object).
#[derive(Debug, Clone, PartialEq)]
pub struct QueueInfo {
    /// Its vhost.
    pub vhost: String,
    /// Its name.
    pub name: String,
    /// Survives restarts.
    pub durable: bool,
    /// Deleted when its last consumer goes.
    pub auto_delete: bool,
    /// The connection that owns it, if exclusive.
    pub exclusive_owner: Option<u64>,
    /// Arguments as declared.
    pub arguments: FieldTable,
    /// Messages ready to be delivered.
    pub messages_ready: u64,
    /// Messages delivered and not yet acknowledged.
    pub messages_unacknowledged: u64,
    /// Body bytes of the ready messages.
    pub message_bytes_ready: u64,
    /// Body bytes of the unacknowledged messages.
    pub message_bytes_unacknowledged: u64,
    /// Persistent messages (delivery-mode 2), ready and unacknowledged,
    /// in a durable classic queue (0 otherwise, as RabbitMQ counts).
    pub messages_persistent: u64,
    /// The `timestamp` property (seconds) of the message at the head.
    pub head_message_timestamp: Option<u64>,
    /// Consumers.
    pub consumers: u64,
    /// Counters since the queue was created.
    pub message_stats: QueueMessageStats,
    /// The policy and operator policy that apply.
    pub policies: Applied,
    /// A stream's offsets and files (`None` for a classic queue).
    pub stream: Option<StreamFigures>,
}

impl QueueInfo {
    /// Ready plus unacknowledged (RabbitMQ's `messages`).
    pub fn messages(&self) -> u64 {
        self.messages_ready + self.messages_unacknowledged
    }

    /// Its type as RabbitMQ names it in listings: `stream` or `classic`.
    pub fn kind(&self) -> &'static str {
        if crate::queue::is_stream(&self.arguments) {
            "stream"
        } else {
            "classic"
        }
    }
}

/// A queue's counters, named as in RabbitMQ's `message_stats`.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct QueueMessageStats {
    /// Messages that entered the queue.
    pub publish: u64,
    /// Deliveries to consumers that must ack.
    pub deliver: u64,
    /// Deliveries to no-ack consumers.
    pub deliver_no_ack: u64,
    /// basic.get answers that must be acked.
    pub get: u64,
    /// basic.get answers with no-ack.
    pub get_no_ack: u64,
    /// basic.get calls that found nothing.
    pub get_empty: u64,
    /// Redeliveries.
    pub redeliver: u64,
    /// Acknowledgements.
    pub ack: u64,
}

impl QueueMessageStats {
    /// Every delivery and get (RabbitMQ's `deliver_get`).
    pub fn deliver_get(&self) -> u64 {
        self.deliver + self.deliver_no_ack + self.get + self.get_no_ack
    }
}

/// One exchange (RabbitMQ's `/api/exchanges` object).
#[derive(Debug, Clone, PartialEq)]
pub struct ExchangeInfo {
    /// Its vhost.
    pub vhost: String,
    /// Its name (empty for the default exchange).
    pub name: String,
    /// `direct`, `fanout`, `topic` or `headers`.
    pub kind: &'static str,
    /// Survives restarts.
    pub durable: bool,
    /// Deleted when its last binding goes.
    pub auto_delete: bool,
    /// Only reachable through exchange-to-exchange bindings.
    pub internal: bool,
    /// Arguments as declared.
    pub arguments: FieldTable,
    /// The policy and operator policy that apply.
    pub policies: Applied,
}

/// What a binding leads to.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum DestinationKind {
    /// A queue.
    Queue,
    /// An exchange.
    Exchange,
}

impl DestinationKind {
    /// RabbitMQ's `destination_type`.
    pub fn as_str(self) -> &'static str {
        match self {
            DestinationKind::Queue => "queue",
            DestinationKind::Exchange => "exchange",
        }
    }
}

/// One binding (RabbitMQ's `/api/bindings` object). The default
/// exchange's implicit binding to every queue is listed too, as RabbitMQ
/// lists it.
#[derive(Debug, Clone, PartialEq)]
pub struct BindingInfo {
    /// Its vhost.
    pub vhost: String,
    /// The source exchange (empty for the default exchange).
    pub source: String,
    /// The destination's name.
    pub destination: String,
    /// Queue or exchange.
    pub destination_kind: DestinationKind,
    /// The binding key.
    pub routing_key: String,
    /// Binding arguments.
    pub arguments: FieldTable,
}

impl BindingInfo {
    /// RabbitMQ's `properties_key`, which names a binding among those with
    /// the same ends: `~` for an empty key without arguments, else the key
    /// form-encoded as RabbitMQ encodes it (`a.#` is `a.%23`), followed
    /// with arguments by `~` and a hash of them (RabbitMQ's hash differs;
    /// clients take the key from a listing, never compute it).
    pub fn properties_key(&self) -> String {
        if self.arguments.is_empty() {
            return if self.routing_key.is_empty() {
                "~".to_owned()
            } else {
                quote_binding(&self.routing_key)
            };
        }
        // FNV-1a over the arguments' rendering: stable for a build.
        let rendered = format!("{:?}", self.arguments);
        let hash = rendered.bytes().fold(0xcbf2_9ce4_8422_2325_u64, |h, b| {
            (h ^ u64::from(b)).wrapping_mul(0x0000_0100_0000_01b3)
        });
        format!("{}~{hash:016x}", quote_binding(&self.routing_key))
    }
}

/// Form encoding as RabbitMQ quotes binding keys: letters, digits, `.`,
/// `-` and `_` stay, a space becomes `+`, every other byte `%XX`.
fn quote_binding(key: &str) -> String {
    let mut out = String::with_capacity(key.len());
    for byte in key.bytes() {
        match byte {
            b'a'..=b'z' | b'A'..=b'Z' | b'0'..=b'9' | b'.' | b'-' | b'_' => out.push(byte as char),
            b' ' => out.push('+'),
            other => out.push_str(&format!("%{other:02X}")),
        }
    }
    out
}

/// One client connection (RabbitMQ's `/api/connections` object).
#[derive(Debug, Clone, PartialEq)]
pub struct ConnectionInfo {
    /// Its id, unique for the broker's life.
    pub id: u64,
    /// The client's address (`host:port`), or `in-process`.
    pub peer: String,
    /// What the client speaks, as RabbitMQ lists it: `AMQP 0-9-1`, or
    /// `MQTT 3.1.1` / `MQTT 5.0` / `MQTT 3.1` for an MQTT session's link.
    pub protocol: &'static str,
    /// When it was accepted.
    pub connected_at: SystemTime,
    /// The authenticated user.
    pub user: String,
    /// The vhost it opened.
    pub vhost: String,
    /// What the client announced in connection.start-ok.
    pub client_properties: FieldTable,
    /// Negotiated frame-max.
    pub frame_max: u32,
    /// Negotiated channel-max.
    pub channel_max: u16,
    /// Negotiated heartbeat, seconds (0 = none).
    pub heartbeat_secs: u16,
    /// Open channels.
    pub channels: u64,
    /// Its byte stream's traffic (a socket, `connect_in_process`'s pipe,
    /// or an MQTT session's socket); `None` for a connection exchanging
    /// frames in-process (`connect_direct`'s).
    pub traffic: Option<SocketTrafficFigures>,
}

/// One channel (RabbitMQ's `/api/channels` object).
#[derive(Debug, Clone, PartialEq)]
pub struct ChannelInfo {
    /// The connection's id.
    pub connection_id: u64,
    /// The connection's peer address.
    pub connection_peer: String,
    /// Channel number.
    pub number: u16,
    /// The connection's user.
    pub user: String,
    /// The connection's vhost.
    pub vhost: String,
    /// Consumers on this channel.
    pub consumers: u64,
    /// Deliveries (consume and get) not yet acknowledged.
    pub messages_unacknowledged: u64,
    /// basic.qos per-consumer prefetch count.
    pub prefetch_count: u32,
    /// basic.qos global (channel-wide) prefetch count.
    pub global_prefetch_count: u32,
    /// In confirm mode.
    pub confirm: bool,
    /// In transactional mode.
    pub transactional: bool,
    /// Publishes awaiting their confirm.
    pub messages_unconfirmed: u64,
    /// Publishes held by the open transaction.
    pub messages_uncommitted: u64,
    /// Acks, nacks and rejects held by the open transaction.
    pub acks_uncommitted: u64,
}

/// One consumer (RabbitMQ's `/api/consumers` object).
#[derive(Debug, Clone, PartialEq)]
pub struct ConsumerInfo {
    /// The queue's vhost.
    pub vhost: String,
    /// The queue it consumes from.
    pub queue: String,
    /// Consumer tag.
    pub tag: String,
    /// Its connection's id.
    pub connection_id: u64,
    /// Its channel number.
    pub channel: u16,
    /// Deliveries must be acknowledged.
    pub ack_required: bool,
    /// Exclusive consumer.
    pub exclusive: bool,
    /// Per-consumer prefetch count (0 = none).
    pub prefetch_count: u32,
    /// `x-priority`.
    pub priority: i64,
    /// Whether the queue delivers to it: always, unless the queue has a
    /// single active consumer and this one waits.
    pub active: bool,
    /// RabbitMQ's `activity_status`: `up`, or on a queue with a single
    /// active consumer `single_active` or `waiting`.
    pub activity_status: &'static str,
}

/// A handle on one queue for reading its figures later, one at a time
/// (see [`crate::Admin::queue_refs`]).
#[derive(Debug, Clone)]
pub struct QueueRef {
    pub(crate) vhost: ShortStr,
    pub(crate) queue: Arc<Queue>,
}

impl QueueRef {
    /// The queue's vhost.
    pub fn vhost(&self) -> &str {
        self.vhost.as_str().unwrap_or_default()
    }

    /// The queue's name.
    pub fn name(&self) -> &str {
        self.queue.name.as_str().unwrap_or_default()
    }

    /// Its figures now; the queue's lock is held for a few loads.
    pub fn info(&self) -> QueueInfo {
        let queue = &self.queue;
        let depth = queue.depth();
        let c = &queue.stats;
        QueueInfo {
            vhost: self.vhost.to_string_lossy().into_owned(),
            name: queue.name.to_string_lossy().into_owned(),
            durable: queue.options.durable,
            auto_delete: queue.options.auto_delete,
            exclusive_owner: queue.options.exclusive_owner,
            arguments: queue.arguments(),
            messages_ready: depth.ready,
            messages_unacknowledged: depth.unacked,
            message_bytes_ready: depth.ready_bytes,
            message_bytes_unacknowledged: depth.unacked_bytes,
            messages_persistent: if queue.options.durable {
                depth.persistent
            } else {
                0
            },
            head_message_timestamp: queue.head_timestamp(),
            consumers: depth.consumers,
            message_stats: QueueMessageStats {
                publish: c.published.get(),
                deliver: c.delivered_manual_ack.get(),
                deliver_no_ack: c.delivered_auto_ack.get(),
                get: c.got_manual_ack.get(),
                get_no_ack: c.got_auto_ack.get(),
                get_empty: c.get_empty.get(),
                redeliver: c.redelivered.get(),
                ack: c.acknowledged.get(),
            },
            policies: queue.policies(),
            stream: queue.stream_figures(),
        }
    }

    /// Its consumers now.
    pub fn consumers(&self) -> Vec<ConsumerInfo> {
        self.queue
            .consumers_snapshot()
            .into_iter()
            .map(|(consumer, active)| ConsumerInfo {
                vhost: self.vhost.to_string_lossy().into_owned(),
                queue: self.queue.name.to_string_lossy().into_owned(),
                tag: consumer.tag.to_string_lossy().into_owned(),
                connection_id: consumer.channel.outbox.connection_id,
                channel: consumer.channel.id,
                ack_required: !consumer.no_ack,
                exclusive: consumer.exclusive,
                prefetch_count: consumer.prefetch,
                priority: consumer.priority,
                active,
                activity_status: match (self.queue.args.single_active_consumer, active) {
                    (false, _) => "up",
                    (true, true) => "single_active",
                    (true, false) => "waiting",
                },
            })
            .collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn binding(routing_key: &str, arguments: FieldTable) -> BindingInfo {
        BindingInfo {
            vhost: "/".into(),
            source: "x".into(),
            destination: "q".into(),
            destination_kind: DestinationKind::Queue,
            routing_key: routing_key.into(),
            arguments,
        }
    }

    #[test]
    fn properties_keys_are_quoted_as_rabbitmq_quotes_them() {
        assert_eq!(binding("", FieldTable::new()).properties_key(), "~");
        assert_eq!(binding("a.#", FieldTable::new()).properties_key(), "a.%23");
        assert_eq!(
            binding("x y~/z", FieldTable::new()).properties_key(),
            "x+y%7E%2Fz"
        );
        let mut arguments = FieldTable::new();
        arguments.insert(
            ShortStr::from_static("x-match"),
            leveret_protocol::FieldValue::string("all"),
        );
        let with_arguments = binding("k", arguments.clone()).properties_key();
        assert!(with_arguments.starts_with("k~"), "{with_arguments}");
        assert_eq!(with_arguments, binding("k", arguments).properties_key());
        assert_ne!(
            with_arguments,
            binding("k", FieldTable::new()).properties_key()
        );
    }
}
