//! The arguments RabbitMQ 3.10 knows for queue.declare, exchange.declare
//! and basic.consume, in one list ([`ARGUMENTS`]) that says for each what
//! Leveret does with it: acts on it, takes it with no effect (and why that
//! is what RabbitMQ does on one node), or refuses it with 406 naming it.
//! `docs/arguments.md` is generated from this list (a test compares them).
//!
//! Also RabbitMQ's equivalence check of a redeclaration
//! ([`first_inequivalent`]): only the arguments the list marks as
//! compared, and numbers by value whatever their AMQP width or signedness
//! (pika sends small integers as 32-bit, the management API and
//! definitions as 64-bit), as `rabbit_misc:assert_args_equivalence` does.
//!
//! Arguments outside the list are kept as declared, shown in listings and
//! not compared, with no effect: RabbitMQ 3.10 does the same with
//! arguments it does not know (an application's or a plugin's own).

use crate::error::AmqpError;
use leveret_protocol::{FieldTable, FieldValue};

/// What declares or uses an argument.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Scope {
    /// queue.declare.
    Queue,
    /// exchange.declare.
    Exchange,
    /// basic.consume.
    Consumer,
}

/// What Leveret does with an argument.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Support {
    /// Validated as RabbitMQ validates it and acted on.
    Implemented,
    /// Validated as RabbitMQ validates it and kept, with no effect; the
    /// text says why that is RabbitMQ's behaviour on one node too.
    NoEffect(&'static str),
    /// Refused: 406 PRECONDITION_FAILED with a text naming it; the text
    /// here says why.
    Refused(&'static str),
}

/// One argument RabbitMQ knows.
#[derive(Debug, Clone, Copy)]
pub struct Argument {
    /// Its name.
    pub name: &'static str,
    /// Where it is given.
    pub scope: Scope,
    /// What Leveret does with it.
    pub support: Support,
    /// Compared when the queue or exchange is declared again (a
    /// difference is 406 `inequivalent arg`), as in RabbitMQ.
    pub compared: bool,
    /// What a stream (`x-queue-type: stream`) does with it, when it is a
    /// queue's or a consumer's argument: `support` above is a classic
    /// queue's. A stream compares every argument it takes on redeclaration.
    pub on_stream: Option<Support>,
    /// What it means.
    pub meaning: &'static str,
}

const QUORUM_OR_STREAM: &str =
    "belongs to quorum queues or streams; RabbitMQ refuses it on a classic queue with the same text";

const NOT_ON_STREAMS: &str =
    "RabbitMQ 3.10 refuses it on a stream (`of queue type rabbit_stream_queue`), and so does Leveret";

const ONE_NODE: &str = "on one node every stream has one replica, led here";

const fn queue(name: &'static str, support: Support, meaning: &'static str) -> Argument {
    Argument {
        name,
        scope: Scope::Queue,
        support,
        // RabbitMQ compares every argument of a classic queue's type.
        compared: !matches!(support, Support::Refused(_)),
        on_stream: Some(Support::Refused(NOT_ON_STREAMS)),
        meaning,
    }
}

/// A queue argument a stream takes too (`on_stream`).
const fn stream_too(
    name: &'static str,
    support: Support,
    on_stream: Support,
    meaning: &'static str,
) -> Argument {
    Argument {
        on_stream: Some(on_stream),
        ..queue(name, support, meaning)
    }
}

const fn other_type(name: &'static str, meaning: &'static str) -> Argument {
    queue(name, Support::Refused(QUORUM_OR_STREAM), meaning)
}

/// An argument of quorum queues or streams that a stream takes.
const fn stream_only(name: &'static str, on_stream: Support, meaning: &'static str) -> Argument {
    stream_too(name, Support::Refused(QUORUM_OR_STREAM), on_stream, meaning)
}

/// The header a consumer that asks for it (basic.consume argument
/// `x-leveret-position: true`) finds on each delivery: the queue's name for
/// positions and the message's position in it, `NAME.SEQ`. The same message
/// delivered again (after a requeue, a reconnect, a restart) carries the
/// same value and no other message ever does, so a forwarder (the uplink's
/// shovels) can give its destination a stable id to drop duplicates by.
pub const POSITION_HEADER: &str = "x-leveret-position";

/// The queue argument that marks the queue of an MQTT shared subscription
/// group as declared by a member (`true`; any other boolean marks
/// nothing): only such a queue is given its group's `x-expires` (see
/// `crate::mqtt`'s shares). Not compared on redeclaration, so an AMQP
/// redeclaration or a definitions import of a group queue, with or
/// without it, finds it equivalent; nor is a marked queue's `x-expires`,
/// which MQTT keeps at its group's (an export's is stale by the time it
/// is imported again: `--definitions` at every start).
pub const MQTT_SHARED_GROUP: &str = "x-mqtt-shared-group";

/// Whether a queue's `arguments` mark it as an MQTT group's queue
/// ([`MQTT_SHARED_GROUP`] `true`; any other value marks nothing).
pub fn marks_an_mqtt_group_queue(arguments: &FieldTable) -> bool {
    arguments.get(MQTT_SHARED_GROUP) == Some(&FieldValue::Bool(true))
}

/// The queue argument that marks an MQTT session's own queue
/// (`mqtt-subscription-<client id>qos<N>`) as declared or resumed by the
/// session (`true`; any other boolean marks nothing): only such a queue is given
/// the session expiry cap at start (see `crate::mqtt`'s expiry), never
/// one an AMQP client declared under that name (unless it copied the
/// mark). Neither it nor a marked queue's `x-expires` (which MQTT keeps
/// at its session's) is compared on redeclaration, as
/// [`MQTT_SHARED_GROUP`].
pub const MQTT_SESSION: &str = "x-mqtt-session";

/// Whether a queue's `arguments` mark it as an MQTT session's own queue
/// ([`MQTT_SESSION`] `true`; any other value marks nothing).
pub fn marks_an_mqtt_session_queue(arguments: &FieldTable) -> bool {
    arguments.get(MQTT_SESSION) == Some(&FieldValue::Bool(true))
}

/// Whether a queue's `arguments` mark it as one MQTT keeps the
/// `x-expires` of (a session's or a shared subscription group's).
pub fn marks_an_mqtt_queue(arguments: &FieldTable) -> bool {
    marks_an_mqtt_group_queue(arguments) || marks_an_mqtt_session_queue(arguments)
}

/// Every argument RabbitMQ 3.10 knows (and Leveret's own
/// `x-leveret-position`, `x-mqtt-shared-group` and `x-mqtt-session`), with what Leveret
/// does with it.
pub const ARGUMENTS: &[Argument] = &[
    queue("x-message-ttl", Support::Implemented, "messages expire after this many milliseconds in the queue"),
    queue("x-expires", Support::Implemented, "the queue is deleted after this many milliseconds unused"),
    queue("x-max-length", Support::Implemented, "most ready messages; `x-overflow` says what happens beyond"),
    stream_too("x-max-length-bytes", Support::Implemented, Support::Implemented, "most ready body bytes; `x-overflow` says what happens beyond. On a stream: most bytes kept, oldest whole segments removed beyond"),
    queue("x-overflow", Support::Implemented, "`drop-head`, `reject-publish` or `reject-publish-dlx`"),
    queue("x-dead-letter-exchange", Support::Implemented, "where expired, rejected and dropped messages go"),
    queue("x-dead-letter-routing-key", Support::Implemented, "their routing key there (needs `x-dead-letter-exchange`)"),
    queue("x-max-priority", Support::Implemented, "message priorities 0 to this (at most 255) are honoured"),
    queue("x-single-active-consumer", Support::Implemented, "one consumer at a time gets messages; the next registered takes over when it goes"),
    stream_too("x-queue-type", Support::Implemented, Support::Implemented, "`classic` (the same as none) or `stream`; `quorum` is refused: this broker has no quorum queues"),
    queue("x-queue-mode", Support::NoEffect("a storage hint (`default` or `lazy`) that changes no behaviour a client sees; RabbitMQ 3.12 ignores it too"), "`lazy` kept messages on disk in RabbitMQ before 3.12"),
    queue("x-queue-version", Support::NoEffect("a storage format choice (1 or 2) that changes no behaviour a client sees"), "the classic queue index version in RabbitMQ"),
    queue("x-queue-master-locator", Support::NoEffect("on one node every locator chooses this node"), "`min-masters`, `client-local` or `random`: the node a queue starts on in a cluster"),
    other_type("x-delivery-limit", "quorum queues: dead-letter after this many redeliveries"),
    other_type("x-dead-letter-strategy", "quorum queues: `at-most-once` or `at-least-once` dead-lettering"),
    other_type("x-quorum-initial-group-size", "quorum queues: replicas at creation"),
    other_type("x-max-in-memory-length", "quorum queues: most messages kept in memory"),
    other_type("x-max-in-memory-bytes", "quorum queues: most bytes kept in memory"),
    stream_only("x-max-age", Support::Implemented, "streams: retention by age (`Y`, `M`, `D`, `h`, `m`, `s`: `7D`); whole segments whose newest message is older go"),
    stream_only("x-stream-max-segment-size-bytes", Support::Implemented, "streams: segment file size (500 MB unless given; at most 3 GB, as RabbitMQ)"),
    stream_only("x-initial-cluster-size", Support::NoEffect(ONE_NODE), "streams: replicas at creation"),
    stream_only("x-queue-leader-locator", Support::NoEffect(ONE_NODE), "quorum queues and streams: the node the leader starts on"),
    Argument {
        name: MQTT_SHARED_GROUP,
        scope: Scope::Queue,
        support: Support::Implemented,
        compared: false,
        on_stream: Some(Support::Refused("MQTT group queues are classic queues")),
        meaning: "Leveret's own (boolean), set by MQTT members on the shared subscription group queues they declare: `true` lets MQTT keep the queue's `x-expires` at its persistent members' longest Session Expiry Interval (1 ms once it has none, so it goes; after a restart too); neither it nor a marked queue's `x-expires` is compared on redeclaration",
    },
    Argument {
        name: MQTT_SESSION,
        scope: Scope::Queue,
        support: Support::Implemented,
        compared: false,
        on_stream: Some(Support::Refused("MQTT session queues are classic queues")),
        meaning: "Leveret's own (boolean), set by MQTT sessions on the `mqtt-subscription-<client id>qos<N>` queues they declare or resume: `true` lets MQTT give the queue the session expiry cap at start (an unmarked queue of that name is left alone then, unless its session holds QoS 2 or shared subscription state); neither it nor a marked queue's `x-expires` is compared on redeclaration",
    },
    Argument {
        name: "alternate-exchange",
        scope: Scope::Exchange,
        support: Support::Implemented,
        compared: true,
        on_stream: None,
        meaning: "where messages this exchange cannot route go",
    },
    Argument {
        name: "hash-header",
        scope: Scope::Exchange,
        support: Support::Implemented,
        compared: false,
        on_stream: None,
        meaning: "`x-consistent-hash` exchanges: hash this header's value instead of the routing key",
    },
    Argument {
        name: "hash-property",
        scope: Scope::Exchange,
        support: Support::Refused("`x-consistent-hash` exchanges hash the routing key or a header (`hash-header`) here, not a message property"),
        compared: false,
        on_stream: None,
        meaning: "`x-consistent-hash` exchanges: hash this message property instead of the routing key",
    },
    Argument {
        name: "x-priority",
        scope: Scope::Consumer,
        support: Support::Implemented,
        compared: false,
        on_stream: Some(Support::Refused(NOT_ON_STREAMS)),
        meaning: "consumer priority (an integer): higher ones get messages while they have prefetch room, lower ones the rest",
    },
    Argument {
        name: "x-cancel-on-ha-failover",
        scope: Scope::Consumer,
        support: Support::NoEffect("this broker has no mirrors, so there is never a failover to cancel on"),
        compared: false,
        on_stream: Some(Support::NoEffect("this broker has no mirrors, so there is never a failover to cancel on")),
        meaning: "mirrored classic queues: cancel the consumer when the queue fails over",
    },
    Argument {
        name: "x-stream-offset",
        scope: Scope::Consumer,
        support: Support::Refused(QUORUM_OR_STREAM),
        compared: false,
        on_stream: Some(Support::Implemented),
        meaning: "streams: where to start reading: `first`, `last` (the newest chunk), `next` (the default), an offset, a timestamp, or an interval back from now (`10m`)",
    },
    Argument {
        name: "x-credit",
        scope: Scope::Consumer,
        support: Support::Refused("credit-based flow (`basic.credit`, RabbitMQ's bridge for AMQP 1.0) is not built; basic.qos limits consumers here"),
        compared: false,
        on_stream: Some(Support::Refused("credit-based flow (`basic.credit`, RabbitMQ's bridge for AMQP 1.0) is not built; basic.qos limits consumers here")),
        meaning: "start the consumer in credit mode",
    },
    Argument {
        name: POSITION_HEADER,
        scope: Scope::Consumer,
        support: Support::Implemented,
        compared: false,
        on_stream: Some(Support::NoEffect("a stream's deliveries carry `x-stream-offset`, as stable a position")),
        meaning: "Leveret's own (boolean): each delivery carries its queue position in this header",
    },
];

/// The list's entry for `name` in `scope`.
pub fn known(scope: Scope, name: &[u8]) -> Option<&'static Argument> {
    ARGUMENTS
        .iter()
        .find(|a| a.scope == scope && a.name.as_bytes() == name)
}

/// The refusal of an argument the list marks refused: RabbitMQ's text for
/// an argument of another queue type, Leveret's reason otherwise.
pub fn refusal(argument: &Argument, resource: &str) -> Option<AmqpError> {
    let Support::Refused(why) = argument.support else {
        return None;
    };
    Some(if why == QUORUM_OR_STREAM {
        AmqpError::precondition_failed(format_args!(
            "invalid arg '{}' for {resource} of queue type rabbit_classic_queue",
            argument.name
        ))
    } else {
        AmqpError::precondition_failed(format_args!(
            "invalid arg '{}' for {resource}: {why}",
            argument.name
        ))
    })
}

/// The refusal of an argument on a stream, if a stream refuses it (see
/// [`Argument::on_stream`]), with RabbitMQ's text.
pub fn stream_refusal(argument: &Argument, resource: &str) -> Option<AmqpError> {
    let Some(Support::Refused(why)) = argument.on_stream else {
        return None;
    };
    Some(if why == NOT_ON_STREAMS {
        AmqpError::precondition_failed(format_args!(
            "invalid arg '{}' for {resource} of queue type rabbit_stream_queue",
            argument.name
        ))
    } else {
        AmqpError::precondition_failed(format_args!(
            "invalid arg '{}' for {resource}: {why}",
            argument.name
        ))
    })
}

/// Queue arguments with what a classic queue here refuses taken out (an
/// `x-queue-type` other than `classic`, and the arguments of quorum queues
/// and streams), and the names of those taken out: for queues made
/// elsewhere or earlier, as a RabbitMQ export's quorum queue or a queue
/// stored before these were refused, kept as the classic queue they can be
/// here instead of being lost.
pub fn classic_queue_arguments(arguments: &FieldTable) -> (FieldTable, Vec<String>) {
    let mut kept = FieldTable::new();
    let mut dropped = Vec::new();
    for (key, value) in arguments.iter() {
        let refused = match key.as_bytes() {
            b"x-queue-type" => value.as_bytes() != Some(b"classic"),
            other => {
                known(Scope::Queue, other).is_some_and(|a| matches!(a.support, Support::Refused(_)))
            }
        };
        if refused {
            dropped.push(key.to_string_lossy().into_owned());
        } else {
            kept.insert(key.clone(), value.clone());
        }
    }
    (kept, dropped)
}

/// RabbitMQ's name for a field value's type, as its error texts give it.
pub fn type_name(value: &FieldValue) -> &'static str {
    match value {
        FieldValue::Bool(_) => "bool",
        FieldValue::I8(_) => "byte",
        FieldValue::U8(_) => "unsignedbyte",
        FieldValue::I16(_) => "short",
        FieldValue::U16(_) => "unsignedshort",
        FieldValue::I32(_) => "signedint",
        FieldValue::U32(_) => "unsignedint",
        FieldValue::I64(_) => "long",
        FieldValue::F32(_) => "float",
        FieldValue::F64(_) => "double",
        FieldValue::Decimal(_) => "decimal",
        FieldValue::LongStr(_) => "longstr",
        FieldValue::ByteArray(_) => "binary",
        FieldValue::Array(_) => "array",
        FieldValue::Timestamp(_) => "timestamp",
        FieldValue::Table(_) => "table",
        FieldValue::Void => "void",
    }
}

/// An integer of any AMQP width or signedness (RabbitMQ's integer types;
/// not a timestamp).
pub fn integer(value: &FieldValue) -> Option<i64> {
    match value {
        FieldValue::Timestamp(_) => None,
        other => other.as_i64(),
    }
}

/// Whether two values are equal as RabbitMQ compares arguments: integers
/// by value whatever their width, floats by value, strings and byte
/// arrays by their bytes, anything else by type and value.
fn equivalent(a: &FieldValue, b: &FieldValue) -> bool {
    match (integer(a), integer(b)) {
        (Some(x), Some(y)) => x == y,
        (Some(_), None) | (None, Some(_)) => false,
        (None, None) => match (a, b) {
            (FieldValue::F32(_) | FieldValue::F64(_), FieldValue::F32(_) | FieldValue::F64(_)) => {
                float(a) == float(b)
            }
            _ => match (a.as_bytes(), b.as_bytes()) {
                (Some(x), Some(y)) => x == y,
                _ => a == b,
            },
        },
    }
}

fn float(value: &FieldValue) -> f64 {
    match *value {
        FieldValue::F32(x) => x.into(),
        FieldValue::F64(x) => x,
        _ => f64::NAN,
    }
}

/// A value as RabbitMQ's equivalence errors show it.
fn shown(value: &FieldValue) -> String {
    match value {
        FieldValue::LongStr(b) | FieldValue::ByteArray(b) => {
            String::from_utf8_lossy(b).into_owned()
        }
        FieldValue::Bool(b) => b.to_string(),
        FieldValue::F32(x) => format!("{x:?}"),
        FieldValue::F64(x) => format!("{x:?}"),
        other => match integer(other) {
            Some(n) => n.to_string(),
            None => format!("{other:?}"),
        },
    }
}

/// The first argument of `scope` the list marks compared whose value in
/// `requested` is not equivalent to the one in `current`, with RabbitMQ's
/// text: `inequivalent arg 'K' for queue 'q' in vhost '/': received ...
/// but current is ...`. `x-queue-type: classic` is the same as none.
pub fn first_inequivalent(
    scope: Scope,
    current: &FieldTable,
    requested: &FieldTable,
    resource: &str,
) -> Option<AmqpError> {
    first_differing(
        ARGUMENTS.iter().filter(|a| a.scope == scope && a.compared),
        current,
        requested,
        resource,
    )
}

/// [`first_inequivalent`] for a stream's declaration: every queue argument
/// a stream takes is compared, as RabbitMQ compares them.
pub fn first_inequivalent_on_stream(
    current: &FieldTable,
    requested: &FieldTable,
    resource: &str,
) -> Option<AmqpError> {
    first_differing(
        ARGUMENTS.iter().filter(|a| {
            a.scope == Scope::Queue
                && matches!(
                    a.on_stream,
                    Some(Support::Implemented | Support::NoEffect(_))
                )
        }),
        current,
        requested,
        resource,
    )
}

fn first_differing<'a>(
    compared: impl Iterator<Item = &'a Argument>,
    current: &FieldTable,
    requested: &FieldTable,
    resource: &str,
) -> Option<AmqpError> {
    compared.into_iter().find_map(|argument| {
        let (was, now) = (current.get(argument.name), requested.get(argument.name));
        let (received, current) = match (was, now) {
            (None, None) => return None,
            (Some(a), Some(b)) if equivalent(a, b) => return None,
            (Some(a), Some(b)) => (format!("'{}'", shown(b)), format!("'{}'", shown(a))),
            _ if argument.name == "x-queue-type" && is_classic(was) && is_classic(now) => {
                return None
            }
            _ => (described(now), described(was)),
        };
        Some(inequivalent(argument.name, resource, &received, &current))
    })
}

fn is_classic(value: Option<&FieldValue>) -> bool {
    value.is_none_or(|v| v.as_bytes() == Some(b"classic"))
}

fn described(value: Option<&FieldValue>) -> String {
    match value {
        None => "none".to_owned(),
        Some(v) => format!("the value '{}' of type '{}'", shown(v), type_name(v)),
    }
}

/// RabbitMQ's `inequivalent arg` error.
pub fn inequivalent(key: &str, resource: &str, received: &str, current: &str) -> AmqpError {
    AmqpError::precondition_failed(format_args!(
        "inequivalent arg '{key}' for {resource}: received {received} but current is {current}"
    ))
}

pub mod duration;

/// RabbitMQ 3.10's largest stream segment size (3 GB), as
/// `x-stream-max-segment-size-bytes` and as the policy key.
pub const MAX_SEGMENT_BYTES: u64 = 3_000_000_000;

#[cfg(test)]
mod tests;
