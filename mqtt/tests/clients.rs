//! Bytes real clients sent, recorded by `fixtures/capture.py` against a
//! loopback server, in MQTT 3.1.1 and 5.0: Eclipse Paho's Python client
//! (paho-mqtt 2.2.0) and Mosquitto's mosquitto_sub and mosquitto_pub
//! (2.0.11). Each stream decodes to exactly the packets the client was
//! asked to send. Paho's packets re-encode to Paho's own bytes; Mosquitto
//! lists 5.0 properties in its own order (User Property first), so its
//! packets re-encode to the same length and decode back to themselves.

use bytes::{Bytes, BytesMut};
use leveret_mqtt::{
    decode_packet, Delivery, MqttString, Packet, ProtocolVersion, PubResponse, QoS, RetainHandling,
    SubscriptionOptions, TopicFilter, TopicName,
};
use std::num::NonZeroU32;

/// How a recorded packet must re-encode.
#[derive(Clone, Copy, PartialEq)]
enum Reencode {
    /// To the very bytes it came from.
    Identical,
    /// To as many bytes, decoding to the same packet.
    SameLength,
}

/// Decodes a whole recorded stream, checking how each packet re-encodes.
fn decode_stream(
    bytes: &'static [u8],
    version: ProtocolVersion,
    reencode: Reencode,
) -> Vec<Packet> {
    let mut buf = BytesMut::from(bytes);
    let mut packets = Vec::new();
    while !buf.is_empty() {
        let before = buf.clone();
        let packet = decode_packet(&mut buf, version, 1 << 20)
            .expect("the client's packets decode")
            .expect("the stream holds whole packets");
        let len = before.len() - buf.len();
        let mut again = BytesMut::new();
        assert_eq!(packet.encode(version, &mut again).unwrap(), len);
        if reencode == Reencode::Identical {
            assert_eq!(
                &again[..],
                &before[..len],
                "{packet:?} re-encodes to the client's bytes"
            );
        }
        let decoded = decode_packet(&mut again, version, 1 << 20)
            .unwrap()
            .unwrap();
        assert_eq!(decoded, packet);
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
        Reencode::Identical,
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
    let packets = decode_stream(
        include_bytes!("fixtures/paho-v5.bin"),
        ProtocolVersion::V5,
        Reencode::Identical,
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

/// mosquitto_sub -E (subscribe, wait for the SUBACK, disconnect), then
/// mosquitto_pub -q 2 -r with a will.
fn mosquitto_session(version: ProtocolVersion, bytes: &'static [u8]) -> Vec<Packet> {
    let packets = decode_stream(bytes, version, Reencode::SameLength);
    let kinds: Vec<_> = packets.iter().map(Packet::packet_type).collect();
    use leveret_mqtt::PacketType::*;
    assert_eq!(
        kinds,
        [Connect, Subscribe, Disconnect, Connect, Publish, PubRel, Disconnect]
    );
    let Packet::Connect(sub) = &packets[0] else {
        unreachable!()
    };
    assert_eq!(sub.version, version);
    assert_eq!(sub.client_id, "leveret-sub");
    assert!(!sub.clean_start, "-c asks for a persistent session");
    assert_eq!(sub.keep_alive, 20);
    assert_eq!(sub.username.as_ref().unwrap(), "robot");
    let Packet::Subscribe(s) = &packets[1] else {
        unreachable!()
    };
    let filters: Vec<_> = s
        .subscriptions
        .iter()
        .map(|s| (s.filter.as_str(), s.options.qos))
        .collect();
    assert_eq!(
        filters,
        [
            ("sensors/+/lidar", QoS::AtLeastOnce),
            ("jobs/#", QoS::AtLeastOnce)
        ]
    );

    let Packet::Connect(publisher) = &packets[3] else {
        unreachable!()
    };
    assert_eq!(publisher.client_id, "leveret-pub");
    let will = publisher.will.as_ref().unwrap();
    assert_eq!(
        (will.topic.as_str(), &will.payload[..]),
        ("robots/r1/status", &b"offline"[..])
    );
    assert_eq!((will.qos, will.retain), (QoS::AtLeastOnce, true));
    let Packet::Publish(p) = &packets[4] else {
        unreachable!()
    };
    assert_eq!(p.topic.as_str(), "robots/r1/pose");
    assert_eq!(&p.payload[..], b"x=1.5 y=-2");
    assert_eq!(p.delivery.qos(), QoS::ExactlyOnce);
    assert!(p.retain);
    assert_eq!(
        packets[5],
        Packet::PubRel(PubResponse::new(p.delivery.packet_id().unwrap()))
    );
    packets
}

#[test]
fn mosquitto_v311_session() {
    let packets = mosquitto_session(
        ProtocolVersion::V3_1_1,
        include_bytes!("fixtures/mosquitto-v311.bin"),
    );
    assert!(packets.iter().all(|p| match p {
        Packet::Publish(p) => p.properties.is_empty(),
        _ => true,
    }));
}

#[test]
fn mosquitto_v5_session() {
    let packets = mosquitto_session(
        ProtocolVersion::V5,
        include_bytes!("fixtures/mosquitto-v5.bin"),
    );
    let Packet::Connect(sub) = &packets[0] else {
        unreachable!()
    };
    assert_eq!(sub.properties.session_expiry_interval, Some(3600));
    assert_eq!(sub.properties.receive_maximum.map(|n| n.get()), Some(10));
    let Packet::Subscribe(s) = &packets[1] else {
        unreachable!()
    };
    assert_eq!(s.properties.user_properties, [(s_("team"), s_("nav"))]);
    let Packet::Connect(publisher) = &packets[3] else {
        unreachable!()
    };
    assert_eq!(
        publisher.properties.maximum_packet_size.map(|n| n.get()),
        Some(65_536)
    );
    let Packet::Publish(p) = &packets[4] else {
        unreachable!()
    };
    let props = &p.properties;
    assert_eq!(props.user_properties, [(s_("robot"), s_("r1"))]);
    assert_eq!(props.content_type.as_ref().unwrap(), "text/plain");
    assert_eq!(props.message_expiry_interval, Some(30));
    assert_eq!(
        props.response_topic,
        Some(TopicName::from_static("replies/r1"))
    );
    assert_eq!(props.correlation_data, Some(Bytes::from_static(b"42")));
}

fn s_(text: &'static str) -> MqttString {
    s(text)
}
