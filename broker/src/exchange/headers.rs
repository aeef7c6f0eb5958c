//! The headers exchange's match: `x-match` all or any (and RabbitMQ's
//! `all-with-x` / `any-with-x`) over the binding's arguments against the
//! message's headers. Binding arguments starting with `x-` are not matched
//! unless a `-with-x` mode asks for them; a void binding value matches any
//! value of that header.

use leveret_protocol::{FieldTable, FieldValue};

/// Whether a message with `headers` matches a binding with `arguments`.
pub fn matches(arguments: &FieldTable, headers: Option<&FieldTable>) -> bool {
    let mode = arguments.get("x-match").and_then(FieldValue::as_bytes);
    let (any, with_x) = match mode {
        Some(b"any") => (true, false),
        Some(b"any-with-x") => (true, true),
        Some(b"all-with-x") => (false, true),
        _ => (false, false),
    };
    let mut considered = arguments
        .iter()
        .filter(|(k, _)| with_x || !k.as_bytes().starts_with(b"x-"));
    let matches_one = |(key, expected): (&leveret_protocol::ShortStr, &FieldValue)| {
        let Some(actual) = headers.and_then(|h| h.iter().find(|(k, _)| *k == key).map(|(_, v)| v))
        else {
            return false;
        };
        matches!(expected, FieldValue::Void) || same_value(expected, actual)
    };
    if any {
        considered.any(matches_one)
    } else {
        considered.all(matches_one)
    }
}

/// Values compare as RabbitMQ compares them: integers by value whatever
/// their width or signedness (an `I` 1 matches an `l` 1), all else exactly.
fn same_value(expected: &FieldValue, actual: &FieldValue) -> bool {
    match (expected.as_i64(), actual.as_i64()) {
        (Some(a), Some(b)) => a == b,
        _ => expected == actual,
    }
}

/// Whether `x-match` holds a value RabbitMQ accepts.
pub fn valid_x_match(arguments: &FieldTable) -> bool {
    match arguments.get("x-match") {
        None => true,
        Some(v) => matches!(
            v.as_bytes(),
            Some(b"all" | b"any" | b"all-with-x" | b"any-with-x")
        ),
    }
}
