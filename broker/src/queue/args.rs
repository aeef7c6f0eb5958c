//! The queue and consumer arguments a queue acts on, validated with
//! RabbitMQ 3.10's error texts: `x-message-ttl`, `x-expires`,
//! `x-max-length`, `x-max-length-bytes`, `x-overflow`, `x-dead-letter-*`,
//! `x-max-priority`, `x-single-active-consumer`, `x-queue-type`,
//! Leveret's `x-mqtt-shared-group` (a boolean; read by MQTT) (a
//! stream's are `stream::args`'s); those
//! taken with no effect are validated too, and those refused are refused
//! here (the list of them all is `crate::arguments`). For basic.consume:
//! `x-priority` and Leveret's `x-leveret-position`.

use crate::arguments::{self, integer, type_name, Scope};
use crate::error::{AmqpError, AmqpResult};
pub use crate::policy::Overflow;
use crate::policy::{argument_wins, stricter, Applied};
use leveret_protocol::{FieldTable, FieldValue, ShortStr};

/// The RabbitMQ queue arguments the broker acts on, validated.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct QueueArgs {
    /// x-message-ttl, ms.
    pub message_ttl: Option<u64>,
    /// x-expires, ms unused before the queue is deleted.
    pub expires: Option<u64>,
    /// x-max-length, messages.
    pub max_length: Option<u64>,
    /// x-max-length-bytes, body bytes.
    pub max_length_bytes: Option<u64>,
    /// x-overflow.
    pub overflow: Overflow,
    /// x-dead-letter-exchange.
    pub dead_letter_exchange: Option<ShortStr>,
    /// x-dead-letter-routing-key.
    pub dead_letter_routing_key: Option<ShortStr>,
    /// x-max-priority.
    pub max_priority: Option<u8>,
    /// x-single-active-consumer.
    pub single_active_consumer: bool,
}

/// RabbitMQ's largest expiry timer (`x-message-ttl`, `x-expires`), ms.
const MAX_EXPIRY: i64 = 4_294_967_295;

/// The queue types RabbitMQ knows.
const QUEUE_TYPES: [&[u8]; 3] = [b"classic", b"quorum", b"stream"];

impl QueueArgs {
    /// Validates and reads the arguments RabbitMQ defines, with its error
    /// texts (`invalid arg 'x-message-ttl' for queue 'q' in vhost '/':
    /// {value_negative,-1}`); refuses those `crate::arguments` lists as
    /// refused. Arguments RabbitMQ does not know are left alone.
    pub fn parse(arguments: &FieldTable, queue: &ShortStr, vhost: &ShortStr) -> AmqpResult<Self> {
        let resource = format!("queue '{queue}' in vhost '{vhost}'");
        let invalid = |name: &str, why: String| {
            AmqpError::precondition_failed(format_args!(
                "invalid arg '{name}' for {resource}: {why}"
            ))
        };
        let int = |name: &str, v: &FieldValue| -> AmqpResult<i64> {
            integer(v)
                .ok_or_else(|| invalid(name, format!("\"expected integer, got {}\"", type_name(v))))
        };
        let non_negative = |name: &str, v: &FieldValue| -> AmqpResult<u64> {
            match int(name, v)? {
                n if n >= 0 => Ok(n as u64),
                n => Err(invalid(name, format!("{{value_negative,{n}}}"))),
            }
        };
        let expiry = |name: &str, v: &FieldValue| -> AmqpResult<u64> {
            match non_negative(name, v)? {
                n if n as i64 > MAX_EXPIRY => {
                    Err(invalid(name, format!("{{value_too_large,{n}}}")))
                }
                n => Ok(n),
            }
        };
        let text = |name: &str, v: &FieldValue| -> AmqpResult<ShortStr> {
            match v {
                FieldValue::LongStr(b) => ShortStr::try_from(bytes::Bytes::copy_from_slice(b))
                    .map_err(|_| invalid(name, "{value_too_long}".into())),
                other => Err(invalid(
                    name,
                    format!("{{unacceptable_type,{}}}", type_name(other)),
                )),
            }
        };
        let one_of =
            |name: &str, v: &FieldValue, allowed: &[&[u8]], what: &str| -> AmqpResult<()> {
                match v {
                    FieldValue::LongStr(b) if allowed.contains(&&b[..]) => Ok(()),
                    FieldValue::LongStr(b) => Err(invalid(
                        name,
                        format!("\"unsupported {what} '{}'\"", String::from_utf8_lossy(b)),
                    )),
                    other => Err(invalid(
                        name,
                        format!("{{unacceptable_type,{}}}", type_name(other)),
                    )),
                }
            };
        if let Some(kind) = arguments.get("x-queue-type") {
            one_of("x-queue-type", kind, &QUEUE_TYPES, "queue type")?;
            if kind.as_bytes() != Some(b"classic") {
                return Err(invalid(
                    "x-queue-type",
                    format!(
                        "queue type '{}' is not available: this broker has classic queues and streams",
                        String::from_utf8_lossy(kind.as_bytes().unwrap_or_default())
                    ),
                ));
            }
        }
        let mut args = QueueArgs::default();
        for (key, value) in arguments.iter() {
            match key.as_bytes() {
                b"x-message-ttl" => args.message_ttl = Some(expiry("x-message-ttl", value)?),
                b"x-expires" => match expiry("x-expires", value)? {
                    0 => return Err(invalid("x-expires", "{value_zero,0}".into())),
                    n => args.expires = Some(n),
                },
                b"x-max-length" => args.max_length = Some(non_negative("x-max-length", value)?),
                b"x-max-length-bytes" => {
                    args.max_length_bytes = Some(non_negative("x-max-length-bytes", value)?)
                }
                b"x-overflow" => {
                    args.overflow = match value {
                        FieldValue::LongStr(b) => Overflow::parse(b)
                            .ok_or_else(|| invalid("x-overflow", "invalid_overflow".into()))?,
                        other => {
                            return Err(invalid(
                                "x-overflow",
                                format!("{{unacceptable_type,{}}}", type_name(other)),
                            ))
                        }
                    }
                }
                b"x-dead-letter-exchange" => {
                    args.dead_letter_exchange = Some(text("x-dead-letter-exchange", value)?)
                }
                b"x-dead-letter-routing-key" => {
                    args.dead_letter_routing_key = Some(text("x-dead-letter-routing-key", value)?)
                }
                b"x-max-priority" => match non_negative("x-max-priority", value)? {
                    n @ 0..=255 => args.max_priority = Some(n as u8),
                    n => {
                        return Err(invalid(
                            "x-max-priority",
                            format!("{{max_value_exceeded,{n}}}"),
                        ))
                    }
                },
                b"x-single-active-consumer" => match value {
                    FieldValue::Bool(on) => args.single_active_consumer = *on,
                    other => {
                        return Err(invalid(
                            "x-single-active-consumer",
                            format!("{{unacceptable_type,{}}}", type_name(other)),
                        ))
                    }
                },
                b"x-mqtt-shared-group" | b"x-mqtt-session" => {
                    if !matches!(value, FieldValue::Bool(_)) {
                        return Err(invalid(
                            &String::from_utf8_lossy(key.as_bytes()),
                            format!("{{unacceptable_type,{}}}", type_name(value)),
                        ));
                    }
                }
                b"x-queue-mode" => {
                    one_of("x-queue-mode", value, &[b"default", b"lazy"], "queue mode")?
                }
                b"x-queue-version" => match non_negative("x-queue-version", value)? {
                    1 | 2 => {}
                    n => {
                        return Err(invalid(
                            "x-queue-version",
                            format!("\"unsupported queue version '{n}'\""),
                        ))
                    }
                },
                b"x-queue-master-locator" => one_of(
                    "x-queue-master-locator",
                    value,
                    &[b"min-masters", b"client-local", b"random"],
                    "queue master locator",
                )?,
                other => {
                    if let Some(refused) = arguments::known(Scope::Queue, other)
                        .and_then(|argument| arguments::refusal(argument, &resource))
                    {
                        return Err(refused);
                    }
                }
            }
        }
        if args.dead_letter_routing_key.is_some() && args.dead_letter_exchange.is_none() {
            return Err(invalid(
                "x-dead-letter-routing-key",
                "routing_key_but_no_dlx_defined".into(),
            ));
        }
        Ok(args)
    }
}

/// The basic.consume arguments a queue acts on, validated.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct ConsumerArgs {
    /// `x-priority` (0 without one).
    pub priority: i64,
    /// `x-leveret-position`: deliveries carry
    /// [`POSITION_HEADER`](super::POSITION_HEADER).
    pub wants_position: bool,
}

impl ConsumerArgs {
    /// Validates and reads basic.consume's arguments for a consumer of
    /// `queue`, with RabbitMQ's texts; refuses those `crate::arguments`
    /// lists as refused.
    pub fn parse(arguments: &FieldTable, queue: &ShortStr, vhost: &ShortStr) -> AmqpResult<Self> {
        let resource = format!("queue '{queue}' in vhost '{vhost}'");
        let invalid = |name: &str, why: String| {
            AmqpError::precondition_failed(format_args!(
                "invalid arg '{name}' for {resource}: {why}"
            ))
        };
        let mut args = ConsumerArgs::default();
        for (key, value) in arguments.iter() {
            match key.as_bytes() {
                b"x-priority" => {
                    args.priority = integer(value).ok_or_else(|| {
                        invalid(
                            "x-priority",
                            format!("\"expected integer, got {}\"", type_name(value)),
                        )
                    })?
                }
                b"x-cancel-on-ha-failover" if !matches!(value, FieldValue::Bool(_)) => {
                    return Err(invalid(
                        "x-cancel-on-ha-failover",
                        format!("{{unacceptable_type,{}}}", type_name(value)),
                    ))
                }
                name if name == super::POSITION_HEADER.as_bytes() => match value {
                    FieldValue::Bool(wanted) => args.wants_position = *wanted,
                    other => {
                        return Err(invalid(
                            super::POSITION_HEADER,
                            format!("{{unacceptable_type,{}}}", type_name(other)),
                        ))
                    }
                },
                other => {
                    if let Some(refused) = arguments::known(Scope::Consumer, other)
                        .and_then(|argument| arguments::refusal(argument, &resource))
                    {
                        return Err(refused);
                    }
                }
            }
        }
        Ok(args)
    }
}

impl QueueArgs {
    /// What the queue acts on: these arguments (read from `declared`, the
    /// table they came from, which tells an argument given from a default)
    /// combined with the policies that apply, by RabbitMQ's rules (see
    /// `crate::policy`'s `combine`).
    pub fn with_policies(&self, declared: &FieldTable, applied: &Applied) -> QueueArgs {
        QueueArgs {
            message_ttl: stricter(applied.message_ttl(), self.message_ttl),
            expires: stricter(applied.expires(), self.expires),
            max_length: stricter(applied.max_length(), self.max_length),
            max_length_bytes: stricter(applied.max_length_bytes(), self.max_length_bytes),
            overflow: argument_wins(
                applied.overflow(),
                declared.get("x-overflow").map(|_| self.overflow),
            )
            .unwrap_or_default(),
            dead_letter_exchange: argument_wins(
                applied.dead_letter_exchange(),
                self.dead_letter_exchange.clone(),
            ),
            dead_letter_routing_key: argument_wins(
                applied.dead_letter_routing_key(),
                self.dead_letter_routing_key.clone(),
            ),
            max_priority: self.max_priority,
            single_active_consumer: self.single_active_consumer,
        }
    }
}
