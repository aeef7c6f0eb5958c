//! MQTT 5.0 PUBLISH properties ↔ AMQP basic properties, as RabbitMQ
//! 3.13's plugin maps them: Content Type ↔ `content-type`; Correlation
//! Data ↔ `correlation-id` when it is UTF-8 of at most 255 bytes, else the
//! header `x-correlation-id`; Response Topic ↔ `reply-to` (as a routing
//! key: `/` ↔ `.`); User Properties ↔ headers with long-string values;
//! Message Expiry Interval ↔ `expiration` (milliseconds), with the
//! publish's `timestamp` so that a delivery says the expiry left; the
//! Payload Format Indicator ↔ the header [`PAYLOAD_FORMAT_HEADER`] (0 or
//! 1), as a subscriber must get it unaltered (MQTT-3.3.2-4). Headers
//! named `x-mqtt-…` are the broker's own, not user properties. Only 5.0
//! sessions read or write them (and 5.0 wills).

use super::mapping;
use bytes::Bytes;
use leveret_mqtt::{MqttString, Properties, TopicName};
use leveret_protocol::{BasicProperties, FieldTable, FieldValue, ShortStr};
use std::time::{SystemTime, UNIX_EPOCH};

/// What the headers of the broker's own (`link`'s marks) start with: they
/// are not 5.0 user properties.
const MQTT_HEADER_PREFIX: &str = "x-mqtt-";

/// Seconds since the epoch at `time` (AMQP's timestamp).
pub(super) fn epoch_seconds(time: SystemTime) -> u64 {
    time.duration_since(UNIX_EPOCH).map_or(0, |d| d.as_secs())
}

/// The header that holds correlation data `correlation-id` cannot.
const CORRELATION_HEADER: &str = "x-correlation-id";
/// The header that holds a publish's Payload Format Indicator: 1 for
/// UTF-8, 0 for unspecified bytes.
pub(super) const PAYLOAD_FORMAT_HEADER: &str = "x-mqtt-payload-format-indicator";

/// Sets `amqp` from a 5.0 PUBLISH's (or will's) properties, published
/// at `now`.
pub(super) fn to_amqp(mqtt: &Properties, amqp: &mut BasicProperties, now: SystemTime) {
    if let Some(content_type) = &mqtt.content_type {
        amqp.content_type = ShortStr::try_from(content_type.as_str()).ok();
    }
    if let Some(topic) = &mqtt.response_topic {
        amqp.reply_to = mapping::routing_key(topic.as_str());
    }
    if let Some(seconds) = mqtt.message_expiry_interval {
        let millis = u64::from(seconds) * 1000;
        amqp.expiration = ShortStr::try_from(millis.to_string()).ok();
        amqp.timestamp = Some(epoch_seconds(now));
    }
    let mut headers = amqp.headers.take().unwrap_or_default();
    if let Some(utf8) = mqtt.payload_format_utf8 {
        headers.insert(
            ShortStr::from_static(PAYLOAD_FORMAT_HEADER),
            FieldValue::U8(u8::from(utf8)),
        );
    }
    if let Some(data) = &mqtt.correlation_data {
        match std::str::from_utf8(data)
            .ok()
            .and_then(|s| ShortStr::try_from(s).ok())
        {
            Some(id) => amqp.correlation_id = Some(id),
            None => headers.insert(
                ShortStr::from_static(CORRELATION_HEADER),
                FieldValue::LongStr(data.clone()),
            ),
        }
    }
    for (name, value) in &mqtt.user_properties {
        if let Ok(name) = ShortStr::try_from(name.as_str()) {
            headers.insert(name, FieldValue::string(value.as_str()));
        }
    }
    amqp.headers = (!headers.is_empty()).then_some(headers);
}

/// Whether a message with `amqp`'s expiration, published at its
/// timestamp, has expired by `now` (never without both). The timestamp
/// is in whole seconds, so the message is taken as published at the end
/// of its second: it never expires early, at most a second late (and a
/// delivery until then says 1 s left, as [`from_amqp`] does).
pub(super) fn expired(amqp: &BasicProperties, now: SystemTime) -> bool {
    let Some(millis) = amqp
        .expiration
        .as_ref()
        .and_then(|e| e.as_str()?.parse::<u64>().ok())
    else {
        return false;
    };
    let Some(published) = amqp.timestamp else {
        return false;
    };
    let now_millis = now
        .duration_since(UNIX_EPOCH)
        .map_or(0, |d| u64::try_from(d.as_millis()).unwrap_or(u64::MAX));
    let published_by = published.saturating_add(1).saturating_mul(1000);
    now_millis >= published_by.saturating_add(millis)
}

/// A 5.0 delivery's PUBLISH properties from a message's, delivered at
/// `now`: the Message Expiry Interval is what is left of the expiration
/// since the message's timestamp (the whole of it without one; at least a
/// second, as the core drops what has expired).
pub(super) fn from_amqp(amqp: &BasicProperties, now: SystemTime) -> Properties {
    let mut mqtt = Properties::default();
    if let Some(millis) = amqp
        .expiration
        .as_ref()
        .and_then(|e| e.as_str()?.parse::<u64>().ok())
    {
        let elapsed = amqp
            .timestamp
            .map_or(0, |t| epoch_seconds(now).saturating_sub(t));
        let left = millis.div_ceil(1000).saturating_sub(elapsed).max(1);
        mqtt.message_expiry_interval = Some(u32::try_from(left).unwrap_or(u32::MAX));
    }
    if let Some(content_type) = amqp.content_type.as_ref().and_then(|c| c.as_str()) {
        mqtt.content_type = MqttString::try_from(content_type).ok();
    }
    mqtt.response_topic = amqp
        .reply_to
        .as_ref()
        .and_then(mapping::topic)
        .and_then(|t| MqttString::try_from(t).ok())
        .and_then(|t| TopicName::new(t).ok());
    if let Some(id) = &amqp.correlation_id {
        mqtt.correlation_data = Some(Bytes::copy_from_slice(id.as_bytes()));
    }
    for (name, value) in amqp.headers.iter().flat_map(FieldTable::iter) {
        let Some(key) = name.as_str() else { continue };
        match (key, value) {
            (CORRELATION_HEADER, FieldValue::LongStr(data)) => {
                mqtt.correlation_data = Some(data.clone());
            }
            (PAYLOAD_FORMAT_HEADER, value) => {
                mqtt.payload_format_utf8 = match value.as_i64() {
                    Some(0) => Some(false),
                    Some(1) => Some(true),
                    _ => None,
                };
            }
            (key, _) if key.starts_with(MQTT_HEADER_PREFIX) => {}
            (_, FieldValue::LongStr(text)) => {
                let text = std::str::from_utf8(text).ok().map(MqttString::try_from);
                if let (Ok(key), Some(Ok(text))) = (MqttString::try_from(key), text) {
                    mqtt.user_properties.push((key, text));
                }
            }
            _ => {}
        }
    }
    mqtt
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn binary_correlation_data_round_trips_through_a_header() {
        let mut mqtt = Properties::default();
        mqtt.correlation_data = Some(Bytes::from_static(&[0xff, 0x00, 0x01]));
        let mut amqp = BasicProperties::default();
        to_amqp(&mqtt, &mut amqp, SystemTime::now());
        assert_eq!(amqp.correlation_id, None);
        let back = from_amqp(&amqp, SystemTime::now());
        assert_eq!(back.correlation_data, mqtt.correlation_data);
        assert!(
            back.user_properties.is_empty(),
            "the header is no user property"
        );
    }

    #[test]
    fn the_payload_format_indicator_reaches_a_subscriber_unaltered() {
        for indicator in [Some(true), Some(false), None] {
            let mut mqtt = Properties::default();
            mqtt.payload_format_utf8 = indicator;
            let mut amqp = BasicProperties::default();
            to_amqp(&mqtt, &mut amqp, SystemTime::now());
            let back = from_amqp(&amqp, SystemTime::now());
            assert_eq!(back.payload_format_utf8, indicator);
            assert!(back.user_properties.is_empty());
        }
        // Set by an AMQP publisher as any integer; other values say nothing.
        let with = |value| BasicProperties {
            headers: Some(FieldTable::from_iter([(
                ShortStr::from_static(PAYLOAD_FORMAT_HEADER),
                value,
            )])),
            ..Default::default()
        };
        let now = SystemTime::now();
        assert_eq!(
            from_amqp(&with(FieldValue::I32(1)), now).payload_format_utf8,
            Some(true)
        );
        assert_eq!(
            from_amqp(&with(FieldValue::I32(7)), now).payload_format_utf8,
            None
        );
    }

    #[test]
    fn a_message_expires_its_expiration_after_its_timestamp() {
        let mut mqtt = Properties::default();
        mqtt.message_expiry_interval = Some(2);
        let published = UNIX_EPOCH + std::time::Duration::from_secs(1_000_000);
        let mut amqp = BasicProperties::default();
        to_amqp(&mqtt, &mut amqp, published);
        let later = |millis| published + std::time::Duration::from_millis(millis);
        // Published somewhere in second 1,000,000: never early.
        assert!(!expired(&amqp, later(2_999)));
        assert!(expired(&amqp, later(3_000)));
        assert!(!expired(&BasicProperties::default(), later(u64::MAX >> 24)));
    }

    #[test]
    fn the_brokers_headers_are_no_user_properties() {
        use super::super::link::{PUBLISHER_HEADER, PUBLISH_QOS_HEADER, RETAIN_HEADER};
        let mut headers = FieldTable::new();
        headers.insert(ShortStr::from_static(PUBLISH_QOS_HEADER), FieldValue::U8(2));
        headers.insert(ShortStr::from_static(RETAIN_HEADER), FieldValue::Bool(true));
        headers.insert(
            ShortStr::from_static(PUBLISHER_HEADER),
            FieldValue::string("me"),
        );
        let amqp = BasicProperties {
            headers: Some(headers),
            ..Default::default()
        };
        assert!(from_amqp(&amqp, SystemTime::now())
            .user_properties
            .is_empty());
    }

    #[test]
    fn a_delivery_says_the_expiry_left() {
        let mut mqtt = Properties::default();
        mqtt.message_expiry_interval = Some(60);
        let published = UNIX_EPOCH + std::time::Duration::from_secs(1_000_000);
        let mut amqp = BasicProperties::default();
        to_amqp(&mqtt, &mut amqp, published);
        assert_eq!(amqp.expiration.as_ref().unwrap(), "60000");
        let later = |s| published + std::time::Duration::from_secs(s);
        assert_eq!(from_amqp(&amqp, later(0)).message_expiry_interval, Some(60));
        assert_eq!(
            from_amqp(&amqp, later(25)).message_expiry_interval,
            Some(35)
        );
        // Never 0 (the core drops an expired message), nor negative.
        assert_eq!(from_amqp(&amqp, later(99)).message_expiry_interval, Some(1));
        // An AMQP publish without a timestamp: the whole expiration, rounded up.
        let amqp = BasicProperties {
            expiration: Some(ShortStr::from_static("1500")),
            ..Default::default()
        };
        assert_eq!(from_amqp(&amqp, later(0)).message_expiry_interval, Some(2));
    }
}
