//! The RabbitMQ queue arguments the broker acts on (`x-message-ttl`,
//! `x-expires`, `x-max-length`, `x-max-length-bytes`, `x-overflow`,
//! `x-dead-letter-*`, `x-max-priority`), validated with RabbitMQ's error
//! texts.

use crate::error::{AmqpError, AmqpResult};
use leveret_protocol::{FieldTable, FieldValue, ShortStr};

/// What happens when a queue reaches x-max-length or x-max-length-bytes.
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
}

impl QueueArgs {
    /// Validates and reads the arguments RabbitMQ defines; the error texts
    /// follow RabbitMQ's (`invalid arg 'x-message-ttl' for queue 'q' ...`).
    pub fn parse(arguments: &FieldTable, queue: &ShortStr, vhost: &ShortStr) -> AmqpResult<Self> {
        let invalid = |name: &str, why: String| {
            AmqpError::precondition_failed(format_args!(
                "invalid arg '{name}' for queue '{queue}' in vhost '{vhost}': {why}"
            ))
        };
        let non_negative = |name: &str, v: &FieldValue| -> AmqpResult<u64> {
            match v.as_i64() {
                Some(n) if n >= 0 => Ok(n as u64),
                Some(n) => Err(invalid(name, format!("{{value_negative,{n}}}"))),
                None => Err(invalid(name, format!("{{unacceptable_type,{:?}}}", v))),
            }
        };
        let text = |name: &str, v: &FieldValue| -> AmqpResult<ShortStr> {
            v.as_bytes()
                .and_then(|b| ShortStr::try_from(bytes::Bytes::copy_from_slice(b)).ok())
                .ok_or_else(|| invalid(name, format!("{{unacceptable_type,{:?}}}", v)))
        };
        let mut args = QueueArgs::default();
        for (key, value) in arguments.iter() {
            match key.as_bytes() {
                b"x-message-ttl" => args.message_ttl = Some(non_negative("x-message-ttl", value)?),
                b"x-expires" => match non_negative("x-expires", value)? {
                    0 => return Err(invalid("x-expires", "{value_zero,0}".into())),
                    n => args.expires = Some(n),
                },
                b"x-max-length" => args.max_length = Some(non_negative("x-max-length", value)?),
                b"x-max-length-bytes" => {
                    args.max_length_bytes = Some(non_negative("x-max-length-bytes", value)?)
                }
                b"x-overflow" => {
                    args.overflow = match value.as_bytes() {
                        Some(b"drop-head") => Overflow::DropHead,
                        Some(b"reject-publish") => Overflow::RejectPublish,
                        Some(b"reject-publish-dlx") => Overflow::RejectPublishDlx,
                        _ => {
                            return Err(invalid(
                                "x-overflow",
                                format!("{{unacceptable_value,{:?}}}", value),
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
                            format!("{{value_out_of_range,{n}}}"),
                        ))
                    }
                },
                _ => {}
            }
        }
        if args.dead_letter_routing_key.is_some() && args.dead_letter_exchange.is_none() {
            return Err(invalid(
                "x-dead-letter-routing-key",
                "Key 'x-dead-letter-exchange' is mandatory if 'x-dead-letter-routing-key' is defined".into(),
            ));
        }
        Ok(args)
    }
}
