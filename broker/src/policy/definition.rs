//! A policy's definition read and checked, key by key, with the rules
//! RabbitMQ 3.10's validators apply (`rabbit_policies`): the keys Leveret
//! acts on for each kind of policy, the keys RabbitMQ knows and Leveret
//! refuses (named as such), and any other key refused as RabbitMQ refuses
//! it ("not recognised").

use super::PolicyKind;
use leveret_protocol::ShortStr;

/// What happens when a queue reaches its maximum length (`x-overflow`,
/// the `overflow` policy key).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Overflow {
    /// Drop (or dead-letter) the oldest messages.
    #[default]
    DropHead,
    /// Refuse the new message (nack with confirms).
    RejectPublish,
    /// As reject-publish, and dead-letter the refused message.
    RejectPublishDlx,
}

impl Overflow {
    /// Reads RabbitMQ's word.
    pub fn parse(word: &[u8]) -> Option<Overflow> {
        match word {
            b"drop-head" => Some(Overflow::DropHead),
            b"reject-publish" => Some(Overflow::RejectPublish),
            b"reject-publish-dlx" => Some(Overflow::RejectPublishDlx),
            _ => None,
        }
    }
}

/// A value in a policy's definition, as JSON gives it.
#[derive(Debug, Clone, PartialEq)]
pub enum PolicyValue {
    /// A whole number.
    Integer(i64),
    /// A string.
    Text(String),
    /// Anything else, by its type's name (`float`, `bool`, `list`…),
    /// kept only to name it in a refusal.
    Other(String),
}

/// The keys of a definition Leveret acts on, read. Keys accepted with no
/// effect (`queue-mode`, `queue-version`) and the federation keys (acted
/// on by the `leveret` binary's federation) are in the spec only.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Definition {
    /// `message-ttl`, ms.
    pub message_ttl: Option<u64>,
    /// `expires`, ms.
    pub expires: Option<u64>,
    /// `max-length`, messages.
    pub max_length: Option<u64>,
    /// `max-length-bytes`, body bytes.
    pub max_length_bytes: Option<u64>,
    /// `overflow`.
    pub overflow: Option<Overflow>,
    /// `dead-letter-exchange`.
    pub dead_letter_exchange: Option<ShortStr>,
    /// `dead-letter-routing-key`.
    pub dead_letter_routing_key: Option<ShortStr>,
    /// `alternate-exchange`.
    pub alternate_exchange: Option<ShortStr>,
    /// `max-age` (a stream key), ms.
    pub max_age_ms: Option<u64>,
    /// `stream-max-segment-size-bytes` (a stream key).
    pub stream_max_segment_size_bytes: Option<u64>,
    /// `federation-upstream`.
    pub federation_upstream: Option<String>,
    /// `federation-upstream-set`.
    pub federation_upstream_set: Option<String>,
}

/// RabbitMQ's largest expiry timer (`message-ttl`, `expires`), ms.
const MAX_EXPIRY: i64 = 4_294_967_295;

/// Keys an operator policy may hold in RabbitMQ 3.10 that Leveret acts on.
pub const OPERATOR_KEYS: [&str; 4] = ["expires", "message-ttl", "max-length", "max-length-bytes"];

/// Keys RabbitMQ 3.10 knows in a policy that Leveret does not act on, and
/// why.
const REFUSED_KEYS: &[(&str, &str)] = &[
    ("ha-mode", "Leveret has no mirrored queues"),
    ("ha-params", "Leveret has no mirrored queues"),
    ("ha-sync-mode", "Leveret has no mirrored queues"),
    ("ha-sync-batch-size", "Leveret has no mirrored queues"),
    ("ha-promote-on-shutdown", "Leveret has no mirrored queues"),
    ("ha-promote-on-failure", "Leveret has no mirrored queues"),
    ("queue-master-locator", "Leveret is a single node"),
    ("queue-leader-locator", "Leveret is a single node"),
    (
        "delivery-limit",
        "a quorum queue key; Leveret has no quorum queues",
    ),
    (
        "max-in-memory-length",
        "a quorum queue key; Leveret has no quorum queues",
    ),
    (
        "max-in-memory-bytes",
        "a quorum queue key; Leveret has no quorum queues",
    ),
    (
        "federation-upstream-pattern",
        "Leveret has no named upstream sets",
    ),
];

impl Definition {
    /// Reads `given` for a policy of `kind`; the first key refused (or
    /// with a bad value) is the error.
    pub fn read(kind: PolicyKind, given: &[(String, PolicyValue)]) -> Result<Definition, String> {
        if given.is_empty() {
            return Err("a policy's definition needs at least one key".into());
        }
        let mut d = Definition::default();
        for (key, value) in given {
            if kind == PolicyKind::Operator && !OPERATOR_KEYS.contains(&key.as_str()) {
                return Err(match REFUSED_KEYS.iter().find(|(k, _)| k == key) {
                    Some((_, why)) => format!("{key}: not acted on by Leveret ({why})"),
                    None => format!(
                        "[{key}] are not recognised operator policy settings (Leveret's: {})",
                        OPERATOR_KEYS.join(", ")
                    ),
                });
            }
            let int = |min: i64, max: i64, what: &str| -> Result<u64, String> {
                match value {
                    PolicyValue::Integer(n) if (min..=max).contains(n) => Ok(*n as u64),
                    other => Err(format!("{} is not a valid {what}", shown(other))),
                }
            };
            let text = |what: &str| -> Result<ShortStr, String> {
                match value {
                    PolicyValue::Text(s) => ShortStr::try_from(s.as_str())
                        .map_err(|_| format!("{key}: longer than 255 bytes")),
                    other => Err(format!("{} is not a valid {what}", shown(other))),
                }
            };
            match key.as_str() {
                "message-ttl" => d.message_ttl = Some(int(0, MAX_EXPIRY, "message TTL")?),
                "expires" => d.expires = Some(int(1, MAX_EXPIRY, "queue expiry")?),
                "max-length" => d.max_length = Some(int(0, i64::MAX, "maximum length")?),
                "max-length-bytes" => {
                    d.max_length_bytes = Some(int(0, i64::MAX, "maximum length in bytes")?)
                }
                "max-age" => {
                    d.max_age_ms = Some(
                        match value {
                            PolicyValue::Text(s) => {
                                crate::arguments::duration::max_age_ms(s.as_bytes())
                            }
                            _ => None,
                        }
                        .ok_or_else(|| format!("{} is not a valid max age", shown(value)))?,
                    )
                }
                "stream-max-segment-size-bytes" => {
                    d.stream_max_segment_size_bytes = Some(int(
                        0,
                        crate::arguments::MAX_SEGMENT_BYTES as i64,
                        "segment size",
                    )?)
                }
                "overflow" => {
                    d.overflow = Some(
                        match value {
                            PolicyValue::Text(s) => Overflow::parse(s.as_bytes()),
                            _ => None,
                        }
                        .ok_or_else(|| format!("{} is not a valid overflow value", shown(value)))?,
                    )
                }
                "dead-letter-exchange" => {
                    d.dead_letter_exchange = Some(text("dead letter exchange name")?)
                }
                "dead-letter-routing-key" => {
                    d.dead_letter_routing_key = Some(text("dead letter routing key")?)
                }
                "alternate-exchange" => {
                    d.alternate_exchange = Some(text("alternate exchange name")?)
                }
                "queue-mode" => match value {
                    PolicyValue::Text(s) if s == "default" || s == "lazy" => {}
                    other => {
                        return Err(format!("{} is not a valid queue-mode value", shown(other)))
                    }
                },
                "queue-version" => match value {
                    PolicyValue::Integer(1 | 2) => {}
                    other => {
                        return Err(format!(
                            "{} is not a valid queue-version value",
                            shown(other)
                        ))
                    }
                },
                "federation-upstream" => {
                    d.federation_upstream = Some(text("federation upstream name")?.to_string())
                }
                "federation-upstream-set" => {
                    d.federation_upstream_set =
                        Some(text("federation upstream set name")?.to_string())
                }
                other => {
                    return Err(match REFUSED_KEYS.iter().find(|(k, _)| *k == other) {
                        Some((_, why)) => format!("{other}: not acted on by Leveret ({why})"),
                        None => format!("[{other}] are not recognised policy settings"),
                    })
                }
            }
        }
        if d.federation_upstream.is_some() && d.federation_upstream_set.is_some() {
            return Err(
                "federation-upstream and federation-upstream-set are mutually exclusive".into(),
            );
        }
        Ok(d)
    }
}

/// The keys a policy may hold to apply to a stream: RabbitMQ 3.10 applies
/// a policy to a stream only if every key is one of these (its other
/// stream keys, `queue-leader-locator` and `initial-cluster-size`, Leveret
/// refuses), and to a classic queue only if none is a stream-only key.
pub const STREAM_KEYS: [&str; 3] = [
    "max-length-bytes",
    "max-age",
    "stream-max-segment-size-bytes",
];

/// The stream keys a policy for a classic queue may not hold.
const STREAM_ONLY_KEYS: [&str; 2] = ["max-age", "stream-max-segment-size-bytes"];

/// Which kinds of queue a policy with these keys applies to, as RabbitMQ
/// 3.10's queue types judge it (`is_policy_applicable`): (classic
/// queues, streams).
pub fn applicable(given: &[(String, PolicyValue)]) -> (bool, bool) {
    let classic = given
        .iter()
        .all(|(key, _)| !STREAM_ONLY_KEYS.contains(&key.as_str()));
    let stream = given
        .iter()
        .all(|(key, _)| STREAM_KEYS.contains(&key.as_str()));
    (classic, stream)
}

fn shown(value: &PolicyValue) -> String {
    match value {
        PolicyValue::Integer(n) => n.to_string(),
        PolicyValue::Text(s) => format!("<<\"{s}\">>"),
        PolicyValue::Other(kind) => format!("a {kind}"),
    }
}
