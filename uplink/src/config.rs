//! A shovel's definition with RabbitMQ's dynamic-shovel parameter names
//! and meanings (`rabbitmqctl set_parameter shovel NAME '{...}'`, the
//! `parameters` of `definitions.json` with component `shovel`), read from
//! the JSON object RabbitMQ takes. What Leveret does not implement yet is
//! refused with a reason, never ignored.
//!
//! A shovel that would put every message back where it took it from is
//! refused here, and so are consumer arguments (`src-consumer-args`)
//! the shovel cannot honour: a stream offset with `no-ack` or an
//! exchange source, a form of `x-stream-offset` the broker would refuse.
//! Uses the protocol crate's JSON form of message properties and
//! arguments, the client crate's URI reading, and the broker's reading of
//! `x-stream-offset` (so that a declaration is refused for what a stream
//! would refuse, and nothing else).

use leveret_protocol::{BasicProperties, FieldTable, FieldValue, ShortStr};
use serde_json::{Map, Value};
use std::time::Duration;

/// When the source's message is acknowledged (`ack-mode`).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub enum AckMode {
    /// After the destination confirmed it (`on-confirm`, the default):
    /// nothing is lost.
    #[default]
    OnConfirm,
    /// As soon as it is published to the destination (`on-publish`).
    OnPublish,
    /// The source does not wait for acknowledgements at all (`no-ack`).
    NoAck,
}

/// When a shovel deletes itself (`src-delete-after`).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub enum DeleteAfter {
    /// Never (the default).
    #[default]
    Never,
    /// After forwarding as many messages as the source queue held when the
    /// shovel first started (`queue-length`).
    QueueLength,
    /// After forwarding this many messages.
    Count(u64),
}

/// Where a shovel takes messages from.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Source {
    /// `src-queue`.
    Queue(String),
    /// `src-exchange` with `src-exchange-key`: a durable queue of the
    /// shovel's own (`shovel.NAME`) is bound to it, so what is published
    /// while the link is down waits there.
    Exchange {
        /// The exchange.
        exchange: String,
        /// The binding key.
        key: String,
    },
}

/// Where a shovel publishes to.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Destination {
    /// `dest-queue`: through the default exchange.
    Queue(String),
    /// `dest-exchange`, with `dest-exchange-key` or else each message's
    /// own routing key.
    Exchange {
        /// The exchange.
        exchange: String,
        /// The routing key, if not the message's own.
        key: Option<String>,
    },
}

/// One shovel.
#[derive(Debug, Clone, PartialEq)]
pub struct ShovelConfig {
    /// The source broker (`src-uri`; `amqp://` with no host is the local
    /// broker, in process).
    pub src_uri: String,
    /// The source queue or exchange.
    pub source: Source,
    /// Unacknowledged messages the shovel holds at once
    /// (`src-prefetch-count`, default 1000).
    pub prefetch: u16,
    /// The arguments of the shovel's `basic.consume` at the source
    /// (`src-consumer-args`, RabbitMQ 3.10's consumer arguments:
    /// `x-stream-offset` to read a stream from an offset, `x-priority`,
    /// `x-cancel-on-ha-failover`). Every link starts with them, so a
    /// shovel reading a stream starts again from that offset after a
    /// restart or a lost link, as RabbitMQ's does.
    pub consumer_args: FieldTable,
    /// The destination brokers (`dest-uri`, one or a list: a cluster's
    /// nodes, tried in turn).
    pub dest_uris: Vec<String>,
    /// The destination queue or exchange.
    pub destination: Destination,
    /// Adds RabbitMQ's `x-shovelled` header (`dest-add-forward-headers`).
    pub add_forward_headers: bool,
    /// Properties set on every forwarded message, over its own
    /// (`dest-publish-properties`, RabbitMQ's property names: for example
    /// `{"delivery_mode": 2}`); `headers` replaces the message's headers.
    pub publish_properties: BasicProperties,
    /// When the shovel is done and deletes itself (`src-delete-after`).
    pub delete_after: DeleteAfter,
    /// `ack-mode`.
    pub ack_mode: AckMode,
    /// Wait before reconnecting, and after the destination refused a
    /// message (`reconnect-delay`, default 5 s).
    pub reconnect_delay: Duration,
    /// Body bytes forwarded per second at most (Leveret's
    /// `bandwidth-limit`; none by default): a link that comes back after an
    /// outage does not flood the collector or a cellular link.
    pub bandwidth_limit: Option<u64>,
    /// Messages forwarded per second at most (Leveret's
    /// `message-rate-limit`; none by default).
    pub message_rate_limit: Option<u64>,
}

fn text<'a>(object: &'a Map<String, Value>, key: &str) -> Result<Option<&'a str>, String> {
    match object.get(key) {
        None | Some(Value::Null) => Ok(None),
        Some(Value::String(s)) => Ok(Some(s)),
        Some(other) => Err(format!("{key} must be a string, not {other}")),
    }
}

/// A prefetch count (`src-prefetch-count`, `prefetch-count`): 1000 by
/// default, as RabbitMQ's.
pub(crate) fn prefetch(object: &Map<String, Value>, key: &str) -> Result<u16, String> {
    match object.get(key) {
        None => Ok(1000),
        Some(n) => n
            .as_u64()
            .and_then(|n| u16::try_from(n).ok())
            .filter(|n| *n > 0)
            .ok_or_else(|| format!("{key} must be an integer from 1 to 65535")),
    }
}

/// `ack-mode`: `on-confirm` by default.
pub(crate) fn ack_mode(object: &Map<String, Value>) -> Result<AckMode, String> {
    match text(object, "ack-mode")? {
        None | Some("on-confirm") => Ok(AckMode::OnConfirm),
        Some("on-publish") => Ok(AckMode::OnPublish),
        Some("no-ack") => Ok(AckMode::NoAck),
        Some(other) => Err(format!("unknown ack-mode {other}")),
    }
}

/// RabbitMQ 3.10's consumer arguments (`rabbit_amqqueue:consume_args()`):
/// what `src-consumer-args` may hold.
const CONSUMER_ARGUMENTS: [&str; 3] = ["x-stream-offset", "x-priority", "x-cancel-on-ha-failover"];

/// The stream offset argument, which only a stream takes.
const STREAM_OFFSET: &str = "x-stream-offset";

/// `src-consumer-args`: an object of RabbitMQ 3.10's consumer arguments,
/// each of the type it takes; `x-stream-offset` in a form a stream takes
/// (JSON has no AMQP timestamp: a time is given as an interval back from
/// now). RabbitMQ 3.10 refuses unknown keys only and fails at consume on
/// a bad value; here the declaration is refused.
fn consumer_args(object: &Map<String, Value>) -> Result<FieldTable, String> {
    let args = match object.get("src-consumer-args") {
        None | Some(Value::Null) => return Ok(FieldTable::new()),
        Some(Value::Object(args)) => args,
        Some(other) => {
            return Err(format!(
                "src-consumer-args must be an object of consumer arguments, such as {{\"x-stream-offset\": \"first\"}}, not {other}"
            ))
        }
    };
    let mut table = FieldTable::new();
    for (key, value) in args {
        let (name, field) = match (key.as_str(), value) {
            (STREAM_OFFSET, _) => (STREAM_OFFSET, stream_offset(value)?),
            ("x-priority", Value::Number(n)) if n.is_i64() => (
                "x-priority",
                FieldValue::I64(n.as_i64().unwrap_or_default()),
            ),
            ("x-priority", _) => {
                return Err(format!(
                    "src-consumer-args: x-priority must be an integer, not {value}"
                ))
            }
            ("x-cancel-on-ha-failover", Value::Bool(b)) => {
                ("x-cancel-on-ha-failover", FieldValue::Bool(*b))
            }
            ("x-cancel-on-ha-failover", _) => {
                return Err(format!(
                    "src-consumer-args: x-cancel-on-ha-failover must be true or false, not {value}"
                ))
            }
            (other, _) => {
                let known = CONSUMER_ARGUMENTS.join(", ");
                return Err(format!(
                    "src-consumer-args: {other} is not a consumer argument (RabbitMQ 3.10 takes {known})"
                ));
            }
        };
        table.insert(ShortStr::from_static(name), field);
    }
    Ok(table)
}

/// An `x-stream-offset` from JSON: `first`, `last`, `next`, an offset (an
/// integer from 0) or an interval back from now (`10m`), as the broker's
/// streams read it.
fn stream_offset(value: &Value) -> Result<FieldValue, String> {
    let field = match value {
        Value::String(text) => FieldValue::string(text),
        Value::Number(n) if n.is_u64() => n.as_i64().map_or(FieldValue::Void, FieldValue::I64),
        // Negative, fractional, past i64 or not a number: the reader
        // refuses it.
        _ => FieldValue::Void,
    };
    let mut probe = FieldTable::new();
    probe.insert(ShortStr::from_static(STREAM_OFFSET), field.clone());
    let unnamed = ShortStr::from_static("src-queue");
    match leveret_broker::stream_start_at(&probe, &unnamed, &unnamed, 0) {
        Ok(_) => Ok(field),
        Err(_) => Err(format!(
            "src-consumer-args: x-stream-offset {value} is not an offset: \"first\", \"last\", \"next\", an offset (an integer from 0) or an interval back from now (\"10m\"; units Y, M, D, h, m, s)"
        )),
    }
}

/// `reconnect-delay` in seconds: 5 by default.
pub(crate) fn reconnect_delay(object: &Map<String, Value>) -> Result<Duration, String> {
    match object.get("reconnect-delay") {
        None => Ok(Duration::from_secs(5)),
        Some(n) => n
            .as_f64()
            .filter(|s| s.is_finite() && *s >= 0.0 && *s <= 86_400.0)
            .map(Duration::from_secs_f64)
            .ok_or_else(|| "reconnect-delay must be seconds, from 0 to 86400".to_owned()),
    }
}

/// One URI or a list of them (`src-uri`, `dest-uri`, `uri`).
pub(crate) fn uris(object: &Map<String, Value>, key: &str) -> Result<Vec<String>, String> {
    let list = match object.get(key) {
        Some(Value::String(s)) => vec![s.clone()],
        Some(Value::Array(items)) => items
            .iter()
            .map(|item| {
                item.as_str()
                    .map(str::to_owned)
                    .ok_or_else(|| format!("{key} must list strings"))
            })
            .collect::<Result<_, _>>()?,
        _ => return Err(format!("{key} is required (a URI or a list of URIs)")),
    };
    if list.is_empty() {
        return Err(format!("{key} is empty"));
    }
    Ok(list)
}

/// Why a shovel from `source` to `destination` would put every message
/// back where it took it from (and take it again, for ever, as fast as
/// the broker goes), if a destination URI names the source's broker and
/// vhost: a queue into itself (`dest-queue`, or the default exchange with
/// the queue's name as key), or an exchange into itself with each
/// message's own routing key, which routed it to the shovel's queue.
/// Loops this cannot see (two shovels, or a destination exchange that
/// routes back) are dropped as they come round (see `shovel.rs`).
fn loops_back(
    source: &Source,
    destination: &Destination,
    src_uri: &str,
    dest_uris: &[String],
) -> Option<String> {
    let into_itself = match (source, destination) {
        (Source::Queue(from), Destination::Queue(to)) => from == to,
        (Source::Queue(from), Destination::Exchange { exchange, key }) => {
            exchange.is_empty() && key.as_deref() == Some(from.as_str())
        }
        (Source::Exchange { exchange: from, .. }, Destination::Exchange { exchange, key }) => {
            from == exchange && key.is_none()
        }
        (Source::Exchange { .. }, Destination::Queue(_)) => false,
    };
    if !into_itself {
        return None;
    }
    let same_broker = dest_uris.iter().find(|to| same_broker(src_uri, to))?;
    let what = match source {
        Source::Queue(queue) => format!("src-queue and the destination are the same queue '{queue}'"),
        Source::Exchange { exchange, .. } => format!(
            "src-exchange and dest-exchange are the same exchange '{exchange}' and each message keeps the routing key that brought it"
        ),
    };
    Some(format!(
        "{what} on the same broker ({} and {}): the shovel would loop",
        crate::shovel::shown(src_uri),
        crate::shovel::shown(same_broker)
    ))
}

/// Whether two URIs name the same broker and vhost: the local broker
/// (`amqp://` with no host) with the same vhost, or the same scheme, host
/// (in any case), port (5672 or 5671 when none is written) and vhost,
/// whatever the credentials and query. URIs that do not read are compared
/// as text. `amqp://localhost` is not taken for the local broker: which
/// port this broker listens on is not known here.
fn same_broker(a: &str, b: &str) -> bool {
    let broker = |uri: &str| {
        let options = leveret_client::ConnectionOptions::from_uri(uri).ok()?;
        Some(if crate::shovel::is_local(uri) {
            (true, false, String::new(), 0, options.vhost)
        } else {
            (
                false,
                options.tls.is_some(),
                options.host.to_ascii_lowercase(),
                options.port,
                options.vhost,
            )
        })
    };
    match (broker(a), broker(b)) {
        (Some(a), Some(b)) => a == b,
        _ => a == b,
    }
}

impl ShovelConfig {
    /// Whether the shovel reads a stream: its consumer arguments give an
    /// `x-stream-offset`, which a classic queue refuses.
    pub fn reads_stream(&self) -> bool {
        self.consumer_args.get(STREAM_OFFSET).is_some()
    }

    /// Reads RabbitMQ's JSON form of a shovel's parameters.
    pub fn from_json(value: &Value) -> Result<ShovelConfig, String> {
        let object = value
            .as_object()
            .ok_or("a shovel's parameters must be a JSON object")?;
        for key in object.keys() {
            let known = [
                "src-uri",
                "src-queue",
                "src-exchange",
                "src-exchange-key",
                "src-prefetch-count",
                "src-consumer-args",
                "src-protocol",
                "src-delete-after",
                "dest-uri",
                "dest-queue",
                "dest-exchange",
                "dest-exchange-key",
                "dest-protocol",
                "dest-add-forward-headers",
                "dest-publish-properties",
                "ack-mode",
                "reconnect-delay",
                "bandwidth-limit",
                "message-rate-limit",
            ];
            if !known.contains(&key.as_str()) {
                return Err(format!("{key} is not supported"));
            }
        }
        for key in ["src-protocol", "dest-protocol"] {
            if let Some(protocol) = text(object, key)? {
                if protocol != "amqp091" {
                    return Err(format!("{key} {protocol}: only amqp091"));
                }
            }
        }
        let delete_after = match object.get("src-delete-after") {
            None | Some(Value::Null) => DeleteAfter::Never,
            Some(Value::String(s)) if s == "never" => DeleteAfter::Never,
            Some(Value::String(s)) if s == "queue-length" => DeleteAfter::QueueLength,
            Some(n) => n
                .as_u64()
                .filter(|n| *n > 0)
                .map(DeleteAfter::Count)
                .ok_or_else(|| {
                    format!(
                        "src-delete-after {n}: \"never\", \"queue-length\" or a positive integer"
                    )
                })?,
        };
        if delete_after == DeleteAfter::QueueLength && object.get("src-queue").is_none() {
            return Err("src-delete-after \"queue-length\" needs a src-queue".into());
        }
        let publish_properties = match object.get("dest-publish-properties") {
            None | Some(Value::Null) => BasicProperties::default(),
            Some(value) => leveret_protocol::json::properties(Some(value))
                .map_err(|e| format!("dest-publish-properties: {e}"))?,
        };
        let source = match (text(object, "src-queue")?, text(object, "src-exchange")?) {
            (Some(queue), None) => Source::Queue(queue.to_owned()),
            (None, Some(exchange)) => Source::Exchange {
                exchange: exchange.to_owned(),
                key: text(object, "src-exchange-key")?.unwrap_or("#").to_owned(),
            },
            _ => return Err("give exactly one of src-queue and src-exchange".into()),
        };
        let destination = match (text(object, "dest-queue")?, text(object, "dest-exchange")?) {
            (Some(queue), None) => Destination::Queue(queue.to_owned()),
            (None, Some(exchange)) => Destination::Exchange {
                exchange: exchange.to_owned(),
                key: text(object, "dest-exchange-key")?.map(str::to_owned),
            },
            _ => return Err("give exactly one of dest-queue and dest-exchange".into()),
        };
        let prefetch = prefetch(object, "src-prefetch-count")?;
        let ack_mode = ack_mode(object)?;
        let consumer_args = consumer_args(object)?;
        if consumer_args.get(STREAM_OFFSET).is_some() {
            if let Source::Exchange { .. } = source {
                return Err("src-consumer-args: x-stream-offset reads a stream, and needs src-queue: with src-exchange the shovel consumes a classic queue of its own".into());
            }
            if ack_mode == AckMode::NoAck {
                return Err("ack-mode no-ack cannot read a stream (src-consumer-args x-stream-offset): a stream's consumers acknowledge what they take; use on-confirm or on-publish".into());
            }
            if consumer_args.get("x-priority").is_some() {
                return Err("src-consumer-args: x-priority with x-stream-offset: a stream refuses consumer priorities".into());
            }
            // A stream keeps its messages rather than holding them ready:
            // Leveret's queue.declare-ok counts none (RabbitMQ 3.10 counts
            // them), so the shovel would stop at once, forwarding nothing.
            if delete_after == DeleteAfter::QueueLength {
                return Err("src-delete-after \"queue-length\" cannot measure a stream (src-consumer-args x-stream-offset): a Leveret stream's queue.declare-ok counts no messages, so the shovel would stop at once; give a count".into());
            }
        }
        let reconnect_delay = reconnect_delay(object)?;
        let add_forward_headers = match object.get("dest-add-forward-headers") {
            None => false,
            Some(Value::Bool(b)) => *b,
            Some(_) => return Err("dest-add-forward-headers must be true or false".into()),
        };
        let limit = |key: &str| -> Result<Option<u64>, String> {
            match object.get(key) {
                None | Some(Value::Null) => Ok(None),
                Some(n) => n
                    .as_u64()
                    .filter(|n| *n > 0)
                    .map(Some)
                    .ok_or_else(|| format!("{key} must be a positive integer")),
            }
        };
        let src_uri = uris(object, "src-uri")?.remove(0);
        let dest_uris = uris(object, "dest-uri")?;
        if let Some(why) = loops_back(&source, &destination, &src_uri, &dest_uris) {
            return Err(why);
        }
        Ok(ShovelConfig {
            bandwidth_limit: limit("bandwidth-limit")?,
            message_rate_limit: limit("message-rate-limit")?,
            src_uri,
            source,
            prefetch,
            consumer_args,
            dest_uris,
            destination,
            add_forward_headers,
            publish_properties,
            delete_after,
            ack_mode,
            reconnect_delay,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use serde_json::json;

    #[test]
    fn a_shovel_from_a_queue_into_itself_is_refused() {
        let refused = ShovelConfig::from_json(&json!({
            "src-uri": "amqp://", "src-queue": "q", "dest-uri": ["amqp://fleet", "amqp://"], "dest-queue": "q",
        }))
        .unwrap_err();
        assert!(
            refused.contains("same queue 'q' on the same broker"),
            "{refused}"
        );
        // Another queue, or the same name on another broker or vhost, is
        // a shovel.
        for (dest_uri, dest_queue) in [
            ("amqp://", "other"),
            ("amqp://fleet", "q"),
            ("amqp:///robots", "q"),
            ("amqp://fleet:5673", "q"),
        ] {
            assert!(ShovelConfig::from_json(&json!({
                "src-uri": "amqp://", "src-queue": "q", "dest-uri": dest_uri, "dest-queue": dest_queue,
            }))
            .is_ok());
        }
    }

    #[test]
    fn loops_are_seen_through_credentials_default_vhosts_ports_and_exchanges() {
        for (src_uri, source, dest_uri, destination) in [
            // The same local vhost written three ways, other credentials.
            (
                "amqp://",
                json!({"src-queue": "q"}),
                "amqp://robot:pw@/%2f",
                json!({"dest-queue": "q"}),
            ),
            (
                "amqp:///%2F",
                json!({"src-queue": "q"}),
                "amqp:///",
                json!({"dest-queue": "q"}),
            ),
            // The default port, a host in capitals, a query.
            (
                "amqp://u:p@Fleet/v",
                json!({"src-queue": "q"}),
                "amqp://fleet:5672/v?heartbeat=5",
                json!({"dest-queue": "q"}),
            ),
            // The default exchange with the queue's name as key.
            (
                "amqp://",
                json!({"src-queue": "q"}),
                "amqp://",
                json!({"dest-exchange": "", "dest-exchange-key": "q"}),
            ),
            // An exchange into itself with each message's own key.
            (
                "amqp://",
                json!({"src-exchange": "amq.topic"}),
                "amqp://",
                json!({"dest-exchange": "amq.topic"}),
            ),
        ] {
            let mut value = json!({"src-uri": src_uri, "dest-uri": dest_uri});
            let object = value.as_object_mut().unwrap();
            object.extend(source.as_object().unwrap().clone());
            object.extend(destination.as_object().unwrap().clone());
            let refused = ShovelConfig::from_json(&value).unwrap_err();
            assert!(
                refused.contains("the shovel would loop"),
                "{value}: {refused}"
            );
            assert!(
                !refused.contains("pw@"),
                "credentials are not shown: {refused}"
            );
        }
        // An exchange into itself under another key may route elsewhere:
        // not refused (a loop is dropped as it comes round).
        assert!(ShovelConfig::from_json(&json!({
            "src-uri": "amqp://", "src-exchange": "amq.topic", "src-exchange-key": "a.#",
            "dest-uri": "amqp://", "dest-exchange": "amq.topic", "dest-exchange-key": "b.1",
        }))
        .is_ok());
    }

    #[test]
    fn rabbitmqs_parameters_and_defaults() {
        let config = ShovelConfig::from_json(&json!({
            "src-uri": "amqp://", "src-queue": "telemetry",
            "dest-uri": ["amqp://fleet-1", "amqp://fleet-2"], "dest-exchange": "robots",
            "dest-add-forward-headers": true, "reconnect-delay": 0.5,
        }))
        .unwrap();
        assert_eq!(config.source, Source::Queue("telemetry".into()));
        assert_eq!(config.dest_uris.len(), 2);
        assert_eq!(
            config.destination,
            Destination::Exchange {
                exchange: "robots".into(),
                key: None
            }
        );
        assert_eq!(config.ack_mode, AckMode::OnConfirm);
        assert_eq!(config.prefetch, 1000);
        assert_eq!(config.reconnect_delay, Duration::from_millis(500));
        let exchange = ShovelConfig::from_json(&json!({
            "src-uri": "amqp://", "src-exchange": "amq.topic",
            "dest-uri": "amqp://fleet", "dest-queue": "in", "ack-mode": "on-publish",
        }))
        .unwrap();
        assert_eq!(
            exchange.source,
            Source::Exchange {
                exchange: "amq.topic".into(),
                key: "#".into()
            }
        );
        assert_eq!(exchange.ack_mode, AckMode::OnPublish);
        assert_eq!(
            (exchange.bandwidth_limit, exchange.message_rate_limit),
            (None, None)
        );
        let limited = ShovelConfig::from_json(&json!({
            "src-uri": "amqp://", "src-queue": "q", "dest-uri": "amqp://x", "dest-queue": "q",
            "bandwidth-limit": 32000, "message-rate-limit": 100,
        }))
        .unwrap();
        assert_eq!(
            (limited.bandwidth_limit, limited.message_rate_limit),
            (Some(32000), Some(100))
        );
        let once = ShovelConfig::from_json(&json!({
            "src-uri": "amqp://", "src-queue": "q", "dest-uri": "amqp://x", "dest-queue": "q",
            "src-delete-after": 20, "dest-publish-properties": {"delivery_mode": 2, "app_id": "robot-7"},
        }))
        .unwrap();
        assert_eq!(once.delete_after, DeleteAfter::Count(20));
        assert_eq!(once.publish_properties.delivery_mode, Some(2));
        assert_eq!(
            once.publish_properties
                .app_id
                .as_ref()
                .map(|s| s.as_bytes()),
            Some(&b"robot-7"[..])
        );
        let drain = ShovelConfig::from_json(&json!({
            "src-uri": "amqp://", "src-queue": "q", "dest-uri": "amqp://x", "dest-queue": "q",
            "src-delete-after": "queue-length",
        }))
        .unwrap();
        assert_eq!(drain.delete_after, DeleteAfter::QueueLength);
    }

    #[test]
    fn src_consumer_args_read_a_stream_from_an_offset_or_are_refused() {
        let shovel = |args: Value, more: Value| {
            let mut value = json!({
                "src-uri": "amqp://", "src-queue": "log", "dest-uri": "amqp://fleet", "dest-queue": "log",
                "src-consumer-args": args,
            });
            value
                .as_object_mut()
                .unwrap()
                .extend(more.as_object().unwrap().clone());
            ShovelConfig::from_json(&value)
        };
        for (offset, field) in [
            (json!("first"), FieldValue::string("first")),
            (json!("next"), FieldValue::string("next")),
            (json!("last"), FieldValue::string("last")),
            (json!(500), FieldValue::I64(500)),
            (json!(0), FieldValue::I64(0)),
            (json!("10m"), FieldValue::string("10m")),
        ] {
            let config = shovel(
                json!({"x-stream-offset": offset}),
                json!({"ack-mode": "on-publish"}),
            )
            .unwrap_or_else(|e| panic!("{offset}: {e}"));
            assert!(config.reads_stream());
            assert_eq!(config.consumer_args.get("x-stream-offset"), Some(&field));
        }
        let classic = shovel(
            json!({"x-priority": 5, "x-cancel-on-ha-failover": true}),
            json!({}),
        )
        .unwrap();
        assert!(!classic.reads_stream());
        assert_eq!(
            classic.consumer_args.get("x-priority"),
            Some(&FieldValue::I64(5))
        );
        let none = shovel(Value::Null, json!({})).unwrap();
        assert!(none.consumer_args.is_empty() && !none.reads_stream());

        for (args, more, reason) in [
            (
                json!("first"),
                json!({}),
                "must be an object of consumer arguments",
            ),
            (
                json!({"x-foo": 1}),
                json!({}),
                "x-foo is not a consumer argument",
            ),
            (
                json!({"x-leveret-position": true}),
                json!({}),
                "is not a consumer argument",
            ),
            (
                json!({"x-stream-offset": "bogus"}),
                json!({}),
                "is not an offset",
            ),
            (
                json!({"x-stream-offset": "10"}),
                json!({}),
                "is not an offset",
            ),
            (
                json!({"x-stream-offset": -5}),
                json!({}),
                "is not an offset",
            ),
            (
                json!({"x-stream-offset": 1.5}),
                json!({}),
                "is not an offset",
            ),
            (
                json!({"x-stream-offset": u64::MAX}),
                json!({}),
                "is not an offset",
            ),
            (
                json!({"x-stream-offset": true}),
                json!({}),
                "is not an offset",
            ),
            (
                json!({"x-stream-offset": {"at": 1}}),
                json!({}),
                "is not an offset",
            ),
            (
                json!({"x-priority": "high"}),
                json!({}),
                "x-priority must be an integer",
            ),
            (
                json!({"x-cancel-on-ha-failover": 1}),
                json!({}),
                "true or false",
            ),
            (
                json!({"x-stream-offset": "first", "x-priority": 1}),
                json!({}),
                "a stream refuses consumer priorities",
            ),
            (
                json!({"x-stream-offset": "first"}),
                json!({"ack-mode": "no-ack"}),
                "no-ack cannot read a stream",
            ),
            (
                json!({"x-stream-offset": "first"}),
                json!({"src-queue": null, "src-exchange": "amq.topic"}),
                "needs src-queue",
            ),
            (
                json!({"x-stream-offset": "first"}),
                json!({"src-delete-after": "queue-length"}),
                "cannot measure a stream",
            ),
        ] {
            let refused = shovel(args.clone(), more).unwrap_err();
            assert!(refused.contains(reason), "{args}: {refused}");
        }
    }

    #[test]
    fn what_is_not_implemented_is_refused_with_a_reason() {
        for (value, reason) in [
            (
                json!({"src-uri": "amqp://", "dest-uri": "amqp://x", "dest-queue": "q"}),
                "src-queue",
            ),
            (
                json!({"src-uri": "amqp://", "src-queue": "q", "dest-uri": "amqp://x", "dest-queue": "q", "dest-publish-properties": {"colour": "red"}}),
                "unknown message property",
            ),
            (
                json!({"src-uri": "amqp://", "src-queue": "q", "dest-uri": "amqp://x", "dest-queue": "q", "src-federate": true}),
                "not supported",
            ),
            (
                json!({"src-uri": "amqp://", "src-exchange": "x", "dest-uri": "amqp://x", "dest-queue": "q", "src-delete-after": "queue-length"}),
                "needs a src-queue",
            ),
            (
                json!({"src-uri": "amqp://", "src-queue": "q", "dest-uri": [], "dest-queue": "q"}),
                "empty",
            ),
            (
                json!({"src-uri": "amqp://", "src-queue": "q", "dest-uri": "amqp://x", "dest-queue": "q", "src-delete-after": -5}),
                "positive integer",
            ),
            (
                json!({"src-uri": "amqp://", "src-queue": "q", "dest-uri": "amqp://x", "dest-queue": "q", "dest-protocol": "amqp10"}),
                "amqp091",
            ),
            (
                json!({"src-uri": "amqp://", "src-queue": "q", "dest-uri": "amqp://x", "dest-queue": "q", "bandwidth-limit": 0}),
                "positive",
            ),
        ] {
            let error = ShovelConfig::from_json(&value).unwrap_err();
            assert!(error.contains(reason), "{error}");
        }
    }
}
