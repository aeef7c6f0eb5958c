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

/// What Leveret does with a policy key.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum KeySupport {
    /// Read with RabbitMQ's checks and acted on.
    Implemented,
    /// Read with RabbitMQ's checks, listed, and without effect, for the
    /// reason given.
    NoEffect(&'static str),
    /// Refused (the policy is not set), for the reason given.
    Refused(&'static str),
}

/// A key RabbitMQ 3.10 knows in a policy definition.
#[derive(Debug, Clone, Copy)]
pub struct PolicyKey {
    /// The key.
    pub name: &'static str,
    /// What Leveret does with it.
    pub support: KeySupport,
    /// Whether an operator policy may hold it (RabbitMQ 3.10's operator
    /// policy keys, less those Leveret refuses).
    pub operator: bool,
    /// What it does in RabbitMQ.
    pub meaning: &'static str,
}

const fn key(
    name: &'static str,
    support: KeySupport,
    operator: bool,
    meaning: &'static str,
) -> PolicyKey {
    PolicyKey {
        name,
        support,
        operator,
        meaning,
    }
}

const NO_MIRRORS: KeySupport = KeySupport::Refused("Leveret has no mirrored queues");
const ONE_NODE: KeySupport = KeySupport::Refused("Leveret is a single node");
const NO_QUORUM: KeySupport =
    KeySupport::Refused("a quorum queue key; Leveret has no quorum queues");

/// Every key RabbitMQ 3.10 knows in a policy (`max-priority`, for one,
/// it does not: a queue argument only), and what Leveret does with it: `Definition::read` takes a key only if it is here and not refused,
/// and `docs/policy-keys.md` is generated from this list (a test compares
/// them and reads every key it lists).
pub const POLICY_KEYS: &[PolicyKey] = &[
    key("message-ttl", KeySupport::Implemented, true, "message TTL, ms; the smaller of it and `x-message-ttl` applies"),
    key("expires", KeySupport::Implemented, true, "queue expiry when unused, ms; the smaller of it and `x-expires` applies"),
    key("max-length", KeySupport::Implemented, true, "length limit, messages; the smaller of it and `x-max-length` applies"),
    key("max-length-bytes", KeySupport::Implemented, true, "length limit, body bytes; the smaller of it and `x-max-length-bytes` applies (on a stream: its retention)"),
    key("overflow", KeySupport::Implemented, false, "`drop-head`, `reject-publish` or `reject-publish-dlx`; `x-overflow` wins"),
    key("dead-letter-exchange", KeySupport::Implemented, false, "where dead letters go; `x-dead-letter-exchange` wins"),
    key("dead-letter-routing-key", KeySupport::Implemented, false, "their routing key; `x-dead-letter-routing-key` wins"),
    key("alternate-exchange", KeySupport::Implemented, false, "an exchange's alternate exchange; the `alternate-exchange` argument wins"),
    key("max-age", KeySupport::Implemented, false, "a stream's retention by age (`7D`, `1h`…)"),
    key("stream-max-segment-size-bytes", KeySupport::Implemented, false, "a stream's segment size"),
    key("federation-upstream", KeySupport::Implemented, false, "federates a matching exchange from this upstream"),
    key("federation-upstream-set", KeySupport::Implemented, false, "federates from this upstream set (only `all`: Leveret has no named sets)"),
    key("queue-mode", KeySupport::NoEffect("a storage hint (`default` or `lazy`) that changes nothing a client sees"), false, "`lazy` kept messages on disk in RabbitMQ before 3.12"),
    key("queue-version", KeySupport::NoEffect("a storage format choice (1 or 2) that changes nothing a client sees"), false, "the classic queue index version in RabbitMQ"),
    key("ha-mode", NO_MIRRORS, false, "classic queue mirroring"),
    key("ha-params", NO_MIRRORS, false, "classic queue mirroring"),
    key("ha-sync-mode", NO_MIRRORS, false, "classic queue mirroring"),
    key("ha-sync-batch-size", NO_MIRRORS, false, "classic queue mirroring"),
    key("ha-promote-on-shutdown", NO_MIRRORS, false, "classic queue mirroring"),
    key("ha-promote-on-failure", NO_MIRRORS, false, "classic queue mirroring"),
    key("queue-master-locator", ONE_NODE, false, "where a queue's leader is placed"),
    key("queue-leader-locator", ONE_NODE, false, "where a queue's leader is placed"),
    key("initial-cluster-size", ONE_NODE, false, "a stream's number of replicas"),
    key("delivery-limit", NO_QUORUM, false, "a quorum queue's redelivery limit"),
    key("max-in-memory-length", NO_QUORUM, false, "a quorum queue's in-memory limit"),
    key("max-in-memory-bytes", NO_QUORUM, false, "a quorum queue's in-memory limit"),
    key("dead-letter-strategy", NO_QUORUM, false, "a quorum queue's at-least-once dead-lettering"),
    key("federation-upstream-pattern", KeySupport::Refused("Leveret has no named upstream sets"), false, "federates from the upstreams whose names match"),
];

/// Why `key` may not be in a policy of `kind`, if it may not.
fn refusal(kind: PolicyKind, key: &str) -> Option<String> {
    let Some(known) = POLICY_KEYS.iter().find(|k| k.name == key) else {
        return Some(match kind {
            PolicyKind::User => format!("[{key}] are not recognised policy settings"),
            PolicyKind::Operator => operator_keys_refusal(key),
        });
    };
    match known.support {
        KeySupport::Refused(why) => Some(format!("{key}: not acted on by Leveret ({why})")),
        _ if kind == PolicyKind::Operator && !known.operator => Some(operator_keys_refusal(key)),
        _ => None,
    }
}

fn operator_keys_refusal(key: &str) -> String {
    let keys: Vec<&str> = POLICY_KEYS
        .iter()
        .filter(|k| k.operator)
        .map(|k| k.name)
        .collect();
    format!(
        "[{key}] are not recognised operator policy settings (Leveret's: {})",
        keys.join(", ")
    )
}

impl Definition {
    /// Reads `given` for a policy of `kind`; the first key refused (or
    /// with a bad value) is the error.
    pub fn read(kind: PolicyKind, given: &[(String, PolicyValue)]) -> Result<Definition, String> {
        if given.is_empty() {
            return Err("a policy's definition needs at least one key".into());
        }
        let mut d = Definition::default();
        for (key, value) in given {
            if let Some(why) = refusal(kind, key) {
                return Err(why);
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
                // Listed in `POLICY_KEYS` and not read here: refused
                // as unknown (the docs test reads every key listed).
                other => return Err(format!("[{other}] are not recognised policy settings")),
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
