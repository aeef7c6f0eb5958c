//! AMQP field tables and message properties to and from JSON, as
//! RabbitMQ's management API and its dynamic shovels' parameters write
//! them (`{"delivery_mode": 2, "headers": {...}}`). Behind the `json`
//! feature.

use crate::properties::BasicProperties;
use crate::types::{FieldArray, FieldTable, FieldValue, ShortStr};
use serde_json::{json, Map, Value};

/// A field value as RabbitMQ's management API shows it.
pub fn field_value(value: &FieldValue) -> Value {
    match value {
        FieldValue::Bool(b) => json!(b),
        FieldValue::I8(n) => json!(n),
        FieldValue::U8(n) => json!(n),
        FieldValue::I16(n) => json!(n),
        FieldValue::U16(n) => json!(n),
        FieldValue::I32(n) => json!(n),
        FieldValue::U32(n) => json!(n),
        FieldValue::I64(n) => json!(n),
        FieldValue::F32(n) => json!(n),
        FieldValue::F64(n) => json!(n),
        FieldValue::Decimal(d) => json!(format!("{d:?}")),
        FieldValue::LongStr(s) => json!(String::from_utf8_lossy(s)),
        FieldValue::ByteArray(b) => json!(String::from_utf8_lossy(b)),
        FieldValue::Array(items) => Value::Array(items.iter().map(field_value).collect()),
        FieldValue::Timestamp(t) => json!(t),
        FieldValue::Table(t) => table(t),
        FieldValue::Void => Value::Null,
    }
}

/// A field table as a JSON object.
pub fn table(table: &FieldTable) -> Value {
    Value::Object(
        table
            .iter()
            .map(|(k, v)| (k.to_string_lossy().into_owned(), field_value(v)))
            .collect(),
    )
}

/// A JSON value as an AMQP field value (integers as signed 64-bit, as
/// RabbitMQ's API converts them).
pub fn to_field_value(value: &Value) -> Result<FieldValue, String> {
    Ok(match value {
        Value::Null => FieldValue::Void,
        Value::Bool(b) => FieldValue::Bool(*b),
        Value::Number(n) => match n.as_i64() {
            Some(i) => FieldValue::I64(i),
            None => FieldValue::F64(n.as_f64().ok_or("number out of range")?),
        },
        Value::String(s) => FieldValue::string(s),
        Value::Array(items) => FieldValue::Array(
            items
                .iter()
                .map(to_field_value)
                .collect::<Result<FieldArray, _>>()?,
        ),
        Value::Object(_) => FieldValue::Table(to_table(value)?),
    })
}

/// A JSON object (or null) as a field table.
pub fn to_table(value: &Value) -> Result<FieldTable, String> {
    match value {
        Value::Null => Ok(FieldTable::new()),
        Value::Object(map) => map
            .iter()
            .map(|(k, v)| {
                let key = ShortStr::try_from(k.as_str())
                    .map_err(|_| format!("argument name longer than 255 bytes: {k:.40}"))?;
                Ok((key, to_field_value(v)?))
            })
            .collect(),
        other => Err(format!("arguments must be an object, not {other}")),
    }
}

/// Message properties from a JSON object of RabbitMQ's property names
/// (a publish's `properties`, a shovel's `dest-publish-properties`).
pub fn properties(value: Option<&Value>) -> Result<BasicProperties, String> {
    let mut p = BasicProperties::default();
    let map = match value {
        None | Some(Value::Null) => return Ok(p),
        Some(Value::Object(map)) => map,
        Some(other) => return Err(format!("properties must be an object, not {other}")),
    };
    for (key, value) in map {
        match key.as_str() {
            "content_type" => p.content_type = Some(short(value, key)?),
            "content_encoding" => p.content_encoding = Some(short(value, key)?),
            "headers" => p.headers = Some(to_table(value)?),
            "delivery_mode" => p.delivery_mode = Some(small(value, key, 2)? as u8),
            "priority" => p.priority = Some(small(value, key, 255)? as u8),
            "correlation_id" => p.correlation_id = Some(short(value, key)?),
            "reply_to" => p.reply_to = Some(short(value, key)?),
            "expiration" => p.expiration = Some(short(value, key)?),
            "message_id" => p.message_id = Some(short(value, key)?),
            "timestamp" => p.timestamp = Some(small(value, key, u64::MAX)?),
            "type" => p.kind = Some(short(value, key)?),
            "user_id" => p.user_id = Some(short(value, key)?),
            "app_id" => p.app_id = Some(short(value, key)?),
            "cluster_id" => p.cluster_id = Some(short(value, key)?),
            other => return Err(format!("unknown message property {other}")),
        }
    }
    Ok(p)
}

/// Message properties as RabbitMQ shows them (only those set).
pub fn properties_json(p: &BasicProperties) -> Value {
    let mut out = Map::new();
    let mut put = |key: &str, value: Option<Value>| {
        if let Some(value) = value {
            out.insert(key.to_owned(), value);
        }
    };
    let s = |v: &Option<ShortStr>| v.as_ref().map(|s| json!(s.to_string_lossy()));
    put("content_type", s(&p.content_type));
    put("content_encoding", s(&p.content_encoding));
    put("headers", p.headers.as_ref().map(table));
    put("delivery_mode", p.delivery_mode.map(|m| json!(m)));
    put("priority", p.priority.map(|m| json!(m)));
    put("correlation_id", s(&p.correlation_id));
    put("reply_to", s(&p.reply_to));
    put("expiration", s(&p.expiration));
    put("message_id", s(&p.message_id));
    put("timestamp", p.timestamp.map(|t| json!(t)));
    put("type", s(&p.kind));
    put("user_id", s(&p.user_id));
    put("app_id", s(&p.app_id));
    put("cluster_id", s(&p.cluster_id));
    Value::Object(out)
}

fn short(value: &Value, key: &str) -> Result<ShortStr, String> {
    match value {
        Value::String(s) => {
            ShortStr::try_from(s.as_str()).map_err(|_| format!("{key} longer than 255 bytes"))
        }
        Value::Number(n) => ShortStr::try_from(n.to_string()).map_err(|_| key.to_owned()),
        other => Err(format!("{key} must be a string, not {other}")),
    }
}

fn small(value: &Value, key: &str, max: u64) -> Result<u64, String> {
    let n = match value {
        Value::Number(n) => n.as_u64(),
        Value::String(s) => s.parse().ok(),
        _ => None,
    };
    n.filter(|n| *n <= max)
        .ok_or_else(|| format!("{key} must be an integer from 0 to {max}"))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn arguments_round_trip_through_json() {
        let value = json!({"x-message-ttl": 60000, "x-dead-letter-exchange": "dlx",
                           "flag": true, "ratio": 0.5, "list": [1, "a"], "nested": {"k": null}});
        let table = to_table(&value).unwrap();
        assert_eq!(table.get("x-message-ttl"), Some(&FieldValue::I64(60000)));
        assert_eq!(super::table(&table), value);
        assert!(to_table(&json!([1])).is_err());
        assert!(to_table(&json!({"x".repeat(300): 1})).is_err());
    }

    #[test]
    fn properties_round_trip_and_unknown_ones_are_refused() {
        let value = json!({"content_type": "text/plain", "delivery_mode": 2,
                           "headers": {"a": 1}, "type": "kind", "priority": "5"});
        let p = properties(Some(&value)).unwrap();
        assert!(p.is_persistent());
        assert_eq!(p.priority, Some(5));
        let back = properties_json(&p);
        assert_eq!(back["type"], json!("kind"));
        assert_eq!(back["headers"], json!({"a": 1}));
        assert!(properties(Some(&json!({"colour": "red"}))).is_err());
        assert!(properties(Some(&json!({"delivery_mode": 7}))).is_err());
    }
}
