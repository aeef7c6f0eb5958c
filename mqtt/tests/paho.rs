//! Bytes a real client sent: Eclipse Paho's Python client (paho-mqtt
//! 2.2.0), recorded by `fixtures/capture.py` against a loopback server, in
//! MQTT 3.1.1 and 5.0. The stream decodes to exactly the packets the script
//! asked for, and each packet re-encodes to Paho's own bytes.

use bytes::{Bytes, BytesMut};
use leveret_mqtt::{
    decode_packet, Delivery, MqttString, Packet, ProtocolVersion, PubResponse, QoS, RetainHandling,
    SubscriptionOptions, TopicFilter, TopicName,
};
use std::num::NonZeroU32;

/// Decodes a whole recorded stream, checking each packet re-encodes to the
/// bytes it came from.
fn decode_stream(bytes: &'static [u8], version: ProtocolVersion) -> Vec<Packet> {
    let mut buf = BytesMut::from(bytes);
    let mut packets = Vec::new();
    while !buf.is_empty() {
        let before = buf.clone();
        let packet = decode_packet(&mut buf, version, 1 << 20)
            .expect("Paho's packets decode")
            .expect("the stream holds whole packets");
        let len = before.len() - buf.len();
        let mut again = BytesMut::new();
        assert_eq!(packet.encode(version, &mut again).unwrap(), len);
        assert_eq!(
            &again[..],
            &before[..len],
            "{packet:?} re-encodes to Paho's bytes"
        );
        packets.push(packet);
    }
    packets
}

fn s(text: &'static str) -> MqttString {
    MqttString::from_static(text)
}

fn options(qos: QoS) -> SubscriptionOptions {
    SubscriptionOptions {
        qos,
        ..Default::default()
    }
}

#[test]
fn paho_v311_session() {
    let packets = decode_stream(
        include_bytes!("fixtures/paho-v311.bin"),
        ProtocolVersion::V3_1_1,
    );
    let kinds: Vec<_> = packets.iter().map(Packet::packet_type).collect();
    use leveret_mqtt::PacketType::*;
    assert_eq!(
        kinds,
        [
            Connect,
            Subscribe,
            Publish,
            Publish,
            Publish,
            Unsubscribe,
            PubRel,
            Disconnect
        ]
    );
    let Packet::Connect(connect) = &packets[0] else {
        unreachable!()
    };
    assert_eq!(connect.version, ProtocolVersion::V3_1_1);
    assert!(connect.clean_start);
    assert_eq!(connect.keep_alive, 30);
    assert_eq!(connect.client_id, "leveret-fixture");
    assert_eq!(connect.username.as_ref().unwrap(), "robot");
    assert_eq!(connect.password.as_deref(), Some(&b"s3cret"[..]));
    let will = connect.will.as_ref().unwrap();
    assert_eq!(will.topic.as_str(), "robots/r1/status");
    assert_eq!(&will.payload[..], b"offline");
    assert_eq!((will.qos, will.retain), (QoS::AtLeastOnce, true));

    let Packet::Subscribe(sub) = &packets[1] else {
        unreachable!()
    };
    let filters: Vec<_> = sub
        .subscriptions
        .iter()
        .map(|s| (s.filter.as_str(), s.options))
        .collect();
    assert_eq!(
        filters,
        [
            ("sensors/+/lidar", options(QoS::AtLeastOnce)),
            ("jobs/#", options(QoS::ExactlyOnce))
        ]
    );

    let Packet::Publish(p) = &packets[2] else {
        unreachable!()
    };
    assert_eq!(
        (p.delivery, p.topic.as_str()),
        (Delivery::AtMostOnce, "sensors/r1/lidar")
    );
    assert_eq!(&p.payload[..], br#"{"range":1.5}"#);
    let Packet::Publish(p) = &packets[3] else {
        unreachable!()
    };
    assert_eq!(p.delivery.qos(), QoS::AtLeastOnce);
    assert_eq!(p.payload.len(), 200);
    let Packet::Publish(p) = &packets[4] else {
        unreachable!()
    };
    assert_eq!(p.delivery.qos(), QoS::ExactlyOnce);
    assert!(p.retain);
    assert_eq!(std::str::from_utf8(&p.payload).unwrap(), "überprüfen ✓");
    let Packet::Unsubscribe(u) = &packets[5] else {
        unreachable!()
    };
    assert_eq!(u.filters, [TopicFilter::from_static("jobs/#")]);
    // PUBREL answers the PUBREC of the QoS 2 publish.
    assert_eq!(
        packets[6],
        Packet::PubRel(PubResponse::new(p.delivery.packet_id().unwrap()))
    );
}

#[test]
fn paho_v5_session() {
    let packets = decode_stream(include_bytes!("fixtures/paho-v5.bin"), ProtocolVersion::V5);
    let kinds: Vec<_> = packets.iter().map(Packet::packet_type).collect();
    use leveret_mqtt::PacketType::*;
    assert_eq!(
        kinds,
        [
            Connect,
            Subscribe,
            Publish,
            Publish,
            Publish,
            Unsubscribe,
            PubRel,
            Disconnect
        ]
    );
    let Packet::Connect(connect) = &packets[0] else {
        unreachable!()
    };
    assert_eq!(connect.version, ProtocolVersion::V5);
    assert!(connect.properties.is_empty());
    let will = connect.will.as_ref().unwrap();
    assert_eq!(will.properties.will_delay_interval, Some(5));
    assert_eq!(will.properties.content_type.as_ref().unwrap(), "text/plain");

    let Packet::Subscribe(sub) = &packets[1] else {
        unreachable!()
    };
    assert_eq!(
        sub.properties.subscription_identifiers,
        [NonZeroU32::new(42).unwrap()]
    );
    assert_eq!(
        sub.subscriptions[0].options,
        SubscriptionOptions {
            qos: QoS::AtLeastOnce,
            no_local: true,
            retain_as_published: true,
            retain_handling: RetainHandling::DoNotSend,
        }
    );
    let shared = sub.subscriptions[1].filter.shared().unwrap();
    assert_eq!((shared.group, shared.filter), ("fleet", "jobs/#"));

    let Packet::Publish(p) = &packets[2] else {
        unreachable!()
    };
    let props = &p.properties;
    assert_eq!(props.payload_format_utf8, Some(true));
    assert_eq!(props.message_expiry_interval, Some(60));
    assert_eq!(props.content_type.as_ref().unwrap(), "application/json");
    assert_eq!(
        props.response_topic,
        Some(TopicName::from_static("replies/r1"))
    );
    assert_eq!(props.correlation_data, Some(Bytes::from_static(&[1, 2, 3])));
    assert_eq!(
        props.user_properties,
        [(s("robot"), s("r1")), (s("unit"), s("m"))]
    );
    assert_eq!(&p.payload[..], br#"{"range":1.5}"#);
    let Packet::Publish(p) = &packets[4] else {
        unreachable!()
    };
    assert_eq!(p.delivery.qos(), QoS::ExactlyOnce);
    assert_eq!(
        packets[6],
        Packet::PubRel(PubResponse::new(p.delivery.packet_id().unwrap()))
    );
}
