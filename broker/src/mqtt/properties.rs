//! MQTT 5.0 PUBLISH properties ↔ AMQP basic properties, as RabbitMQ
//! 3.13's plugin maps them: Content Type ↔ `content-type`; Correlation
//! Data ↔ `correlation-id` when it is UTF-8 of at most 255 bytes, else the
//! header `x-correlation-id`; Response Topic ↔ `reply-to` (as a routing
//! key: `/` ↔ `.`); User Properties ↔ headers with long-string values;
//! Message Expiry Interval → `expiration` (milliseconds). Only 5.0
//! sessions read or write them.

use super::link::PUBLISH_QOS_HEADER;
use super::mapping;
use bytes::Bytes;
use leveret_mqtt::{MqttString, Properties, TopicName};
use leveret_protocol::{BasicProperties, FieldTable, FieldValue, ShortStr};

/// The header that holds correlation data `correlation-id` cannot.
const CORRELATION_HEADER: &str = "x-correlation-id";

/// Sets `amqp` from a 5.0 PUBLISH's properties.
pub(super) fn to_amqp(mqtt: &Properties, amqp: &mut BasicProperties) {
    if let Some(content_type) = &mqtt.content_type {
        amqp.content_type = ShortStr::try_from(content_type.as_str()).ok();
    }
    if let Some(topic) = &mqtt.response_topic {
        amqp.reply_to = mapping::routing_key(topic.as_str());
    }
    if let Some(seconds) = mqtt.message_expiry_interval {
        let millis = u64::from(seconds) * 1000;
        amqp.expiration = ShortStr::try_from(millis.to_string()).ok();
    }
    let mut headers = amqp.headers.take().unwrap_or_default();
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

/// A 5.0 delivery's PUBLISH properties from a message's.
pub(super) fn from_amqp(amqp: &BasicProperties) -> Properties {
    let mut mqtt = Properties::default();
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
            (PUBLISH_QOS_HEADER, _) => {}
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
        to_amqp(&mqtt, &mut amqp);
        assert_eq!(amqp.correlation_id, None);
        let back = from_amqp(&amqp);
        assert_eq!(back.correlation_data, mqtt.correlation_data);
        assert!(
            back.user_properties.is_empty(),
            "the header is no user property"
        );
    }

    #[test]
    fn the_qos_header_is_no_user_property() {
        let mut headers = FieldTable::new();
        headers.insert(ShortStr::from_static(PUBLISH_QOS_HEADER), FieldValue::U8(2));
        let amqp = BasicProperties {
            headers: Some(headers),
            ..Default::default()
        };
        assert!(from_amqp(&amqp).user_properties.is_empty());
    }
}
