//! What a stream is declared and consumed with, validated with RabbitMQ
//! 3.10's replies: the declare rules (durable, not exclusive, not
//! auto-delete, not server-named), the stream arguments
//! (`x-max-length-bytes`, `x-max-age`, `x-stream-max-segment-size-bytes`;
//! every other argument RabbitMQ knows for queues is refused, as
//! `crate::arguments` lists), and a consumer's `x-stream-offset`.

use crate::arguments::duration::{duration_ms, DurationError};
use crate::arguments::{self, integer, type_name, Scope, MAX_SEGMENT_BYTES};
use crate::error::{AmqpError, AmqpResult};
use leveret_protocol::{FieldTable, FieldValue, ShortStr};

/// RabbitMQ's default segment size (500 MB).
pub const DEFAULT_SEGMENT_BYTES: u64 = 500_000_000;

/// The leader locators RabbitMQ 3.10 knows.
const LEADER_LOCATORS: [&[u8]; 4] = [b"client-local", b"balanced", b"random", b"least-leaders"];

/// A stream's retention and segment size.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct StreamArgs {
    /// `x-max-length-bytes`: most bytes kept (whole segments go).
    pub max_bytes: Option<u64>,
    /// `x-max-age`, in milliseconds.
    pub max_age_ms: Option<u64>,
    /// `x-stream-max-segment-size-bytes`.
    pub segment_bytes: u64,
}

impl StreamArgs {
    /// The segment size for a stream declared with `arguments` while
    /// `policy_size` (`stream-max-segment-size-bytes`) applies: the
    /// smaller where both set one (RabbitMQ 3.10's `args_policy_lookup`).
    pub fn with_policy_segment_size(
        mut self,
        arguments: &FieldTable,
        policy_size: Option<u64>,
    ) -> Self {
        let declared = arguments
            .get("x-stream-max-segment-size-bytes")
            .map(|_| self.segment_bytes);
        if let Some(size) = crate::policy::stricter(declared, policy_size) {
            self.segment_bytes = size;
        }
        self
    }
}

/// Where a stream consumer starts (`x-stream-offset`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum StartAt {
    /// The oldest record held.
    First,
    /// The start of the newest chunk.
    Last,
    /// The next record appended (the default).
    Next,
    /// This offset: the first held if that is gone; waited for if not yet
    /// written.
    Offset(u64),
    /// The first record at or after this time, ms since the epoch.
    Timestamp(i64),
}

/// Whether declare arguments ask for a stream.
pub fn is_stream(arguments: &FieldTable) -> bool {
    arguments.get("x-queue-type").and_then(FieldValue::as_bytes) == Some(b"stream")
}

/// RabbitMQ 3.10 answers a duration with no number first by failing in its
/// parser: the connection closes with 541.
fn parser_failure(what: &str, text: &[u8]) -> AmqpError {
    AmqpError::internal_error(format_args!(
        "{what} '{}' does not start with a number",
        String::from_utf8_lossy(text)
    ))
}

impl StreamArgs {
    /// Checks a stream's declaration (RabbitMQ's order: properties, then
    /// server naming, then arguments) and reads its arguments.
    pub fn parse(
        arguments: &FieldTable,
        durable: bool,
        exclusive: bool,
        auto_delete: bool,
        server_named: bool,
        queue: &ShortStr,
        vhost: &ShortStr,
    ) -> AmqpResult<Self> {
        let resource = format!("queue '{queue}' in vhost '{vhost}'");
        for (refused, property) in [
            (!durable, "non-durable"),
            (exclusive, "exclusive-owner"),
            (auto_delete, "auto-delete"),
        ] {
            if refused {
                return Err(AmqpError::precondition_failed(format_args!(
                    "invalid property '{property}' for {resource}"
                )));
            }
        }
        if server_named {
            return Err(AmqpError::precondition_failed(
                "Cannot declare a server-named queue for type rabbit_stream_queue",
            ));
        }
        let invalid = |name: &str, why: String| {
            AmqpError::precondition_failed(format_args!(
                "invalid arg '{name}' for {resource}: {why}"
            ))
        };
        let non_negative = |name: &str, v: &FieldValue| -> AmqpResult<u64> {
            match integer(v) {
                None => Err(invalid(
                    name,
                    format!("\"expected integer, got {}\"", type_name(v)),
                )),
                Some(n) if n < 0 => Err(invalid(name, format!("{{value_negative,{n}}}"))),
                Some(n) => Ok(n as u64),
            }
        };
        let mut args = StreamArgs {
            max_bytes: None,
            max_age_ms: None,
            segment_bytes: DEFAULT_SEGMENT_BYTES,
        };
        for (key, value) in arguments.iter() {
            let name = key.as_bytes();
            if let Some(refused) = arguments::known(Scope::Queue, name)
                .and_then(|argument| arguments::stream_refusal(argument, &resource))
            {
                return Err(refused);
            }
            match name {
                b"x-initial-cluster-size"
                    if non_negative("x-initial-cluster-size", value)? == 0 =>
                {
                    return Err(invalid("x-initial-cluster-size", "{value_zero,0}".into()));
                }
                b"x-queue-leader-locator" => match value {
                    FieldValue::LongStr(text) if LEADER_LOCATORS.contains(&&text[..]) => {}
                    _ => {
                        return Err(invalid(
                            "x-queue-leader-locator",
                            "invalid_queue_locator_arg".into(),
                        ))
                    }
                },
                b"x-max-length-bytes" => {
                    args.max_bytes = Some(non_negative("x-max-length-bytes", value)?)
                }
                b"x-stream-max-segment-size-bytes" => {
                    args.segment_bytes = non_negative("x-stream-max-segment-size-bytes", value)?;
                    if args.segment_bytes > MAX_SEGMENT_BYTES {
                        return Err(AmqpError::precondition_failed(
                            "Exceeded max value for x-stream-max-segment-size-bytes",
                        ));
                    }
                }
                b"x-max-age" => match value {
                    FieldValue::LongStr(text) => match duration_ms(text) {
                        Ok(ms) => args.max_age_ms = Some(ms),
                        Err(DurationError::Invalid) => {
                            return Err(invalid("x-max-age", "invalid_max_age".into()))
                        }
                        Err(DurationError::NoNumber) => {
                            return Err(parser_failure("x-max-age", text))
                        }
                    },
                    other => {
                        return Err(invalid(
                            "x-max-age",
                            format!("{{unacceptable_type,{}}}", type_name(other)),
                        ))
                    }
                },
                _ => {}
            }
        }
        Ok(args)
    }
}

/// Reads a stream consumer's arguments: `x-stream-offset` (RabbitMQ 3.10's
/// forms and replies); refuses what `crate::arguments` says a stream's
/// consumer refuses (`x-priority`, as RabbitMQ does). `now_ms` turns an interval into a timestamp.
pub fn start_at(
    arguments: &FieldTable,
    queue: &ShortStr,
    vhost: &ShortStr,
    now_ms: i64,
) -> AmqpResult<StartAt> {
    let resource = format!("queue '{queue}' in vhost '{vhost}'");
    for (key, _) in arguments.iter() {
        if let Some(refused) = arguments::known(Scope::Consumer, key.as_bytes())
            .and_then(|argument| arguments::stream_refusal(argument, &resource))
        {
            return Err(refused);
        }
    }
    let Some(value) = arguments.get("x-stream-offset") else {
        return Ok(StartAt::Next);
    };
    Ok(match value {
        FieldValue::LongStr(text) => match &text[..] {
            b"first" => StartAt::First,
            b"last" => StartAt::Last,
            b"next" => StartAt::Next,
            other => match duration_ms(other) {
                Ok(ms) => StartAt::Timestamp(now_ms.saturating_sub(ms as i64)),
                Err(DurationError::Invalid) => {
                    return Err(AmqpError::precondition_failed(format_args!(
                        "invalid arg 'x-stream-offset' for {resource}: {{invalid_stream_offset_arg,{{longstr,<<\"{}\">>}}}}",
                        String::from_utf8_lossy(other)
                    )))
                }
                Err(DurationError::NoNumber) => {
                    return Err(parser_failure("x-stream-offset", other))
                }
            },
        },
        // AMQP timestamps are seconds.
        FieldValue::Timestamp(seconds) => {
            StartAt::Timestamp((*seconds as i64).saturating_mul(1000))
        }
        other => match integer(other) {
            Some(n) => StartAt::Offset(n.max(0) as u64),
            None => {
                return Err(AmqpError::internal_error(format_args!(
                    "x-stream-offset of type {} is not an offset",
                    type_name(other)
                )))
            }
        },
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn durations_take_rabbitmqs_units_and_refuse_the_rest() {
        let ms = |t: &str| duration_ms(t.as_bytes()).ok();
        assert_eq!(ms("7D"), Some(7 * 86_400_000));
        assert_eq!(ms("10m"), Some(600_000));
        assert_eq!(ms("1Y"), Some(365 * 86_400_000));
        assert_eq!(ms("1M"), Some(30 * 86_400_000));
        assert_eq!(ms("2h"), Some(7_200_000));
        assert_eq!(ms("30s"), Some(30_000));
        for bad in ["10", "0s", "1d", "1H", "10ms", "abc", "-1s", "first "] {
            assert_eq!(ms(bad), None, "{bad}");
        }
        assert!(matches!(duration_ms(b"abc"), Err(DurationError::NoNumber)));
        assert!(matches!(duration_ms(b"10"), Err(DurationError::Invalid)));
    }

    #[test]
    fn declare_rules_reply_as_rabbitmq_does() {
        let q = ShortStr::from_static("s");
        let v = ShortStr::from_static("/");
        let mut args = FieldTable::new();
        args.insert(
            ShortStr::from_static("x-queue-type"),
            FieldValue::string("stream"),
        );
        let text = |r: AmqpResult<StreamArgs>| r.unwrap_err().to_string();
        assert!(
            text(StreamArgs::parse(&args, false, false, false, false, &q, &v))
                .contains("invalid property 'non-durable'")
        );
        assert!(
            text(StreamArgs::parse(&args, true, true, false, false, &q, &v))
                .contains("invalid property 'exclusive-owner'")
        );
        assert!(
            text(StreamArgs::parse(&args, true, false, true, false, &q, &v))
                .contains("invalid property 'auto-delete'")
        );
        assert!(
            text(StreamArgs::parse(&args, true, false, false, true, &q, &v))
                .contains("server-named")
        );
        let ok = StreamArgs::parse(&args, true, false, false, false, &q, &v).unwrap();
        assert_eq!(ok.segment_bytes, DEFAULT_SEGMENT_BYTES);
        for (size, accepted) in [(MAX_SEGMENT_BYTES, true), (MAX_SEGMENT_BYTES + 1, false)] {
            let mut sized = args.clone();
            sized.insert(
                ShortStr::from_static("x-stream-max-segment-size-bytes"),
                FieldValue::I64(size as i64),
            );
            let parsed = StreamArgs::parse(&sized, true, false, false, false, &q, &v);
            match parsed {
                Ok(parsed) => assert!(accepted && parsed.segment_bytes == size),
                Err(e) => {
                    assert!(!accepted);
                    assert_eq!(
                        e.to_string(),
                        "406 PRECONDITION_FAILED - Exceeded max value for x-stream-max-segment-size-bytes"
                    );
                }
            }
        }
        let mut ttl = args.clone();
        ttl.insert(ShortStr::from_static("x-message-ttl"), FieldValue::I32(5));
        assert!(
            text(StreamArgs::parse(&ttl, true, false, false, false, &q, &v))
                .contains("of queue type rabbit_stream_queue")
        );
        let mut age = args.clone();
        age.insert(
            ShortStr::from_static("x-max-age"),
            FieldValue::string("10m"),
        );
        age.insert(
            ShortStr::from_static("x-max-length-bytes"),
            FieldValue::I64(1000),
        );
        let parsed = StreamArgs::parse(&age, true, false, false, false, &q, &v).unwrap();
        assert_eq!(
            (parsed.max_age_ms, parsed.max_bytes),
            (Some(600_000), Some(1000))
        );
    }

    #[test]
    fn every_offset_form_is_read() {
        let q = ShortStr::from_static("s");
        let v = ShortStr::from_static("/");
        let at = |value: FieldValue| {
            let mut args = FieldTable::new();
            args.insert(ShortStr::from_static("x-stream-offset"), value);
            start_at(&args, &q, &v, 1_000_000)
        };
        assert_eq!(at(FieldValue::string("first")).unwrap(), StartAt::First);
        assert_eq!(at(FieldValue::string("last")).unwrap(), StartAt::Last);
        assert_eq!(at(FieldValue::string("next")).unwrap(), StartAt::Next);
        assert_eq!(at(FieldValue::I64(5)).unwrap(), StartAt::Offset(5));
        assert_eq!(at(FieldValue::I32(-3)).unwrap(), StartAt::Offset(0));
        assert_eq!(
            at(FieldValue::Timestamp(7)).unwrap(),
            StartAt::Timestamp(7000)
        );
        assert_eq!(
            at(FieldValue::string("10s")).unwrap(),
            StartAt::Timestamp(990_000)
        );
        assert_eq!(at(FieldValue::string("10")).unwrap_err().code.code(), 406);
        assert_eq!(at(FieldValue::string("abc")).unwrap_err().code.code(), 541);
        assert_eq!(at(FieldValue::Bool(true)).unwrap_err().code.code(), 541);
    }
}
