//! Every packet in each version against byte vectors written from the
//! specifications' figures and examples (MQTT 3.1.1 and 5.0, chapter 3),
//! and every rule a single packet can break, with the reason code it maps to.

use super::*;
use crate::error::{DecodeError, EncodeError};
use crate::frame::decode_packet;
use crate::properties::{PropertyId, PropertyValues};
use crate::string::MqttString;
use crate::topic::TopicError;
use bytes::BytesMut;
use std::num::{NonZeroU16, NonZeroU32};

const V3: ProtocolVersion = ProtocolVersion::V3_1_1;
const V5: ProtocolVersion = ProtocolVersion::V5;

fn id(n: u16) -> PacketId {
    NonZeroU16::new(n).unwrap()
}

fn s(text: &'static str) -> MqttString {
    MqttString::from_static(text)
}

fn decode(bytes: &[u8], version: ProtocolVersion) -> Result<Packet, DecodeError> {
    let mut buf = BytesMut::from(bytes);
    let packet = decode_packet(&mut buf, version, 1 << 20)?.expect("a whole packet");
    assert!(buf.is_empty(), "{} bytes left", buf.len());
    Ok(packet)
}

/// `bytes` decodes to `packet` in `version`, and `packet` encodes to `bytes`.
fn golden(bytes: &[u8], version: ProtocolVersion, packet: Packet) {
    assert_eq!(decode(bytes, version).unwrap(), packet);
    let mut buf = BytesMut::new();
    assert_eq!(packet.encode(version, &mut buf).unwrap(), bytes.len());
    assert_eq!(&buf[..], bytes);
    assert_eq!(packet.encoded_len(version).unwrap(), bytes.len());
}

fn invalid(bytes: &[u8], version: ProtocolVersion) -> (PacketType, &'static str, Problem) {
    match decode(bytes, version) {
        Err(DecodeError::Invalid {
            packet,
            field,
            problem,
        }) => (packet, field, problem),
        other => panic!("expected an invalid field, got {other:?}"),
    }
}

fn props(values: PropertyValues) -> Properties {
    values.into()
}

fn encode_err(packet: &Packet, version: ProtocolVersion) -> (&'static str, Problem) {
    let mut buf = BytesMut::from(&b"kept"[..]);
    let err = packet.encode(version, &mut buf).unwrap_err();
    assert_eq!(
        &buf[..],
        b"kept",
        "a refused packet leaves the buffer as it was"
    );
    match err {
        EncodeError::Invalid { field, problem, .. } => (field, problem),
        other => panic!("expected an invalid field, got {other:?}"),
    }
}

// ---- CONNECT ----

#[test]
fn connect_v311_spec_example() {
    // 3.1.1 figure 3.6: "MQTT", level 4, flags 0xCE (user name, password,
    // will QoS 1, will flag, clean session), keep alive 10; then client id,
    // will topic, will message, user name, password.
    let bytes = [
        0x10, 0x1F, 0x00, 0x04, b'M', b'Q', b'T', b'T', 0x04, 0xCE, 0x00, 0x0A, //
        0x00, 0x03, b'c', b'i', b'd', //
        0x00, 0x03, b'w', b'/', b't', //
        0x00, 0x03, b'b', b'y', b'e', //
        0x00, 0x01, b'u', 0x00, 0x01, b'p',
    ];
    golden(
        &bytes,
        V3,
        Packet::Connect(Box::new(Connect {
            version: V3,
            clean_start: true,
            keep_alive: 10,
            properties: Properties::default(),
            client_id: s("cid"),
            will: Some(Will {
                properties: Properties::default(),
                topic: TopicName::from_static("w/t"),
                payload: Bytes::from_static(b"bye"),
                qos: QoS::AtLeastOnce,
                retain: false,
            }),
            username: Some(s("u")),
            password: Some(Bytes::from_static(b"p")),
        })),
    );
}

#[test]
fn connect_v5_spec_example() {
    // 5.0 figure 3-6: level 5, flags 0xC2 (user name, password, clean
    // start), keep alive 10, properties of length 5: Session Expiry
    // Interval 10.
    let bytes = [
        0x10, 0x1B, 0x00, 0x04, b'M', b'Q', b'T', b'T', 0x05, 0xC2, 0x00, 0x0A, //
        0x05, 0x11, 0x00, 0x00, 0x00, 0x0A, //
        0x00, 0x03, b'c', b'i', b'd', 0x00, 0x01, b'u', 0x00, 0x01, b'p',
    ];
    golden(
        &bytes,
        V5,
        Packet::Connect(Box::new(Connect {
            version: V5,
            clean_start: true,
            keep_alive: 10,
            properties: props(PropertyValues {
                session_expiry_interval: Some(10),
                ..Default::default()
            }),
            client_id: s("cid"),
            will: None,
            username: Some(s("u")),
            password: Some(Bytes::from_static(b"p")),
        })),
    );
}

#[test]
fn connect_v5_with_will_properties_and_password_alone() {
    // 5.0 lifts 3.1.1's rule that a password needs a user name.
    let bytes = [
        0x10, 0x1E, 0x00, 0x04, b'M', b'Q', b'T', b'T', 0x05, 0x74, 0x00, 0x00, //
        0x03, 0x21, 0x00, 0x05, // receive maximum 5
        0x00, 0x00, // empty client id
        0x05, 0x18, 0x00, 0x00, 0x00, 0x1E, // will delay 30
        0x00, 0x01, b't', 0x00, 0x00, // will topic "t", empty will payload
        0x00, 0x01, b'p',
    ];
    golden(
        &bytes,
        V5,
        Packet::Connect(Box::new(Connect {
            version: V5,
            clean_start: false,
            keep_alive: 0,
            properties: props(PropertyValues {
                receive_maximum: NonZeroU16::new(5),
                ..Default::default()
            }),
            client_id: MqttString::default(),
            will: Some(Will {
                properties: props(PropertyValues {
                    will_delay_interval: Some(30),
                    ..Default::default()
                }),
                topic: TopicName::from_static("t"),
                payload: Bytes::new(),
                qos: QoS::ExactlyOnce,
                retain: true,
            }),
            username: None,
            password: Some(Bytes::from_static(b"p")),
        })),
    );
}

#[test]
fn connect_v31_is_decoded_by_its_own_level() {
    let bytes = [
        0x10, 0x11, 0x00, 0x06, b'M', b'Q', b'I', b's', b'd', b'p', 0x03, 0x02, 0x00, 0x3C, //
        0x00, 0x03, b'c', b'i', b'd',
    ];
    let expected = Packet::Connect(Box::new(Connect {
        version: ProtocolVersion::V3_1,
        clean_start: true,
        keep_alive: 60,
        properties: Properties::default(),
        client_id: s("cid"),
        will: None,
        username: None,
        password: None,
    }));
    // Whatever the connection's version, CONNECT names its own.
    assert_eq!(decode(&bytes, V5).unwrap(), expected);
    golden(&bytes, V3, expected);
}

#[test]
fn connect_unsupported_protocol_says_which_connack_to_answer() {
    let connect = |name: &[u8], level: u8| {
        let mut bytes = vec![0x10, 0x00, 0x00, name.len() as u8];
        bytes.extend_from_slice(name);
        bytes.extend_from_slice(&[level, 0x02, 0x00, 0x00, 0x00, 0x00]);
        bytes[1] = (bytes.len() - 2) as u8;
        decode(&bytes, V3).unwrap_err()
    };
    for (name, level, reply) in [
        (&b"MQTT"[..], 6, V3),
        (b"MQTT", 3, V3),
        (b"MQIsdp", 4, V3),
        (b"MQTX", 5, V5),
    ] {
        let err = connect(name, level);
        assert_eq!(
            err,
            DecodeError::Invalid {
                packet: PacketType::Connect,
                field: "protocol level",
                problem: Problem::UnsupportedProtocol(level),
            }
        );
        assert_eq!(err.reason_code(), ReasonCode::UnsupportedProtocolVersion);
        assert_eq!(err.connack_refusal(), Some(reply));
    }
    // 3.1.1's CONNACK for it: return code 1.
    let mut buf = BytesMut::new();
    Packet::ConnAck(ConnAck {
        session_present: false,
        reason: ReasonCode::UnsupportedProtocolVersion,
        properties: Properties::default(),
    })
    .encode(V3, &mut buf)
    .unwrap();
    assert_eq!(&buf[..], [0x20, 0x02, 0x00, 0x01]);
}

#[test]
fn connect_flag_rules() {
    let with_flags = |level: u8, flags: u8| {
        let mut bytes = vec![
            0x10, 0x00, 0x00, 0x04, b'M', b'Q', b'T', b'T', level, flags, 0x00, 0x00,
        ];
        if level == 5 {
            bytes.push(0x00);
        }
        bytes.extend_from_slice(&[0x00, 0x00]);
        bytes[1] = (bytes.len() - 2) as u8;
        invalid(&bytes, V3)
    };
    assert_eq!(with_flags(4, 0x03).2, Problem::ReservedBitsSet);
    assert_eq!(with_flags(4, 0x08).2, Problem::WillFieldsWithoutWill);
    assert_eq!(with_flags(4, 0x20).2, Problem::WillFieldsWithoutWill);
    assert_eq!(with_flags(4, 0x1C).2, Problem::InvalidQos);
    assert_eq!(with_flags(4, 0x40).2, Problem::PasswordWithoutUsername);
    assert_eq!(with_flags(5, 0x01).2, Problem::ReservedBitsSet);
    assert_eq!(
        Problem::ReservedBitsSet.reason_code(),
        ReasonCode::MalformedPacket
    );
    let no_user = Packet::Connect(Box::new(Connect {
        version: V3,
        clean_start: true,
        keep_alive: 0,
        properties: Properties::default(),
        client_id: s("c"),
        will: None,
        username: None,
        password: Some(Bytes::from_static(b"p")),
    }));
    assert_eq!(
        encode_err(&no_user, V3),
        ("password", Problem::PasswordWithoutUsername)
    );
}

#[test]
fn connect_will_topic_must_be_a_name() {
    let header = [
        0x00, 0x04, b'M', b'Q', b'T', b'T', 0x04, 0x04, 0x00, 0x00, 0x00, 0x00,
    ];
    let with_will_topic = |topic: &[u8]| {
        let mut bytes = vec![0x10, 0x00];
        bytes.extend_from_slice(&header);
        bytes.extend_from_slice(&(topic.len() as u16).to_be_bytes());
        bytes.extend_from_slice(topic);
        bytes.extend_from_slice(&[0x00, 0x00]);
        bytes[1] = (bytes.len() - 2) as u8;
        invalid(&bytes, V3)
    };
    assert_eq!(
        with_will_topic(b"#"),
        (
            PacketType::Connect,
            "will topic",
            Problem::InvalidTopicName(TopicError::Wildcard)
        )
    );
    assert_eq!(
        with_will_topic(b""),
        (
            PacketType::Connect,
            "will topic",
            Problem::InvalidTopicName(TopicError::Empty)
        )
    );
}

// ---- CONNACK ----

#[test]
fn connack_v311() {
    golden(
        &[0x20, 0x02, 0x01, 0x00],
        V3,
        Packet::ConnAck(ConnAck {
            session_present: true,
            reason: ReasonCode::Success,
            properties: Properties::default(),
        }),
    );
    golden(
        &[0x20, 0x02, 0x00, 0x05],
        V3,
        Packet::ConnAck(ConnAck {
            session_present: false,
            reason: ReasonCode::NotAuthorized,
            properties: Properties::default(),
        }),
    );
    assert_eq!(
        invalid(&[0x20, 0x02, 0x00, 0x06], V3).2,
        Problem::InvalidReasonCode(6)
    );
    assert_eq!(
        invalid(&[0x20, 0x02, 0x02, 0x00], V3).2,
        Problem::ReservedBitsSet
    );
    let busy = Packet::ConnAck(ConnAck {
        session_present: false,
        reason: ReasonCode::ServerBusy,
        properties: Properties::default(),
    });
    assert_eq!(
        encode_err(&busy, V3),
        ("reason code", Problem::InvalidReasonCode(0x89))
    );
}

#[test]
fn connack_v5_with_capabilities() {
    golden(
        &[0x20, 0x03, 0x00, 0x00, 0x00],
        V5,
        Packet::ConnAck(ConnAck {
            session_present: false,
            reason: ReasonCode::Success,
            properties: Properties::default(),
        }),
    );
    golden(
        &[
            0x20, 0x0D, 0x00, 0x00, 0x0A, 0x21, 0x00, 0x0A, 0x22, 0x00, 0x05, 0x24, 0x01, 0x25,
            0x00,
        ],
        V5,
        Packet::ConnAck(ConnAck {
            session_present: false,
            reason: ReasonCode::Success,
            properties: props(PropertyValues {
                receive_maximum: NonZeroU16::new(10),
                topic_alias_maximum: Some(5),
                maximum_qos: Some(QoS::AtLeastOnce),
                retain_available: Some(false),
                ..Default::default()
            }),
        }),
    );
    golden(
        &[0x20, 0x03, 0x00, 0x95, 0x00],
        V5,
        Packet::ConnAck(ConnAck {
            session_present: false,
            reason: ReasonCode::PacketTooLarge,
            properties: Properties::default(),
        }),
    );
    // Maximum QoS 2 does not exist: a server with QoS 2 leaves it out.
    assert_eq!(
        invalid(&[0x20, 0x05, 0x00, 0x00, 0x02, 0x24, 0x02], V5).2,
        Problem::InvalidPropertyValue(PropertyId::MaximumQos)
    );
    // Granted QoS 1 is a SUBACK code.
    assert_eq!(
        invalid(&[0x20, 0x03, 0x00, 0x01, 0x00], V5).2,
        Problem::InvalidReasonCode(1)
    );
}

// ---- PUBLISH ----

#[test]
fn publish_v311_spec_example() {
    // 3.1.1 figure 3.11: topic "a/b", packet identifier 10.
    golden(
        &[
            0x32, 0x09, 0x00, 0x03, b'a', b'/', b'b', 0x00, 0x0A, b'h', b'i',
        ],
        V3,
        Packet::Publish(Publish {
            dup: false,
            delivery: Delivery::AtLeastOnce(id(10)),
            retain: false,
            topic: TopicName::from_static("a/b"),
            properties: Properties::default(),
            payload: Bytes::from_static(b"hi"),
        }),
    );
    golden(
        &[0x31, 0x05, 0x00, 0x03, b'a', b'/', b'b'],
        V3,
        Packet::Publish(Publish {
            dup: false,
            delivery: Delivery::AtMostOnce,
            retain: true,
            topic: TopicName::from_static("a/b"),
            properties: Properties::default(),
            payload: Bytes::new(),
        }),
    );
    golden(
        &[0x3C, 0x07, 0x00, 0x03, b'a', b'/', b'b', 0x00, 0x0B],
        V3,
        Packet::Publish(Publish {
            dup: true,
            delivery: Delivery::ExactlyOnce(id(11)),
            retain: false,
            topic: TopicName::from_static("a/b"),
            properties: Properties::default(),
            payload: Bytes::new(),
        }),
    );
}

#[test]
fn publish_v5_spec_example_and_properties() {
    // 5.0 figure 3-9: topic "a/b", packet identifier 10, no properties.
    golden(
        &[
            0x32, 0x0A, 0x00, 0x03, b'a', b'/', b'b', 0x00, 0x0A, 0x00, b'h', b'i',
        ],
        V5,
        Packet::Publish(Publish {
            dup: false,
            delivery: Delivery::AtLeastOnce(id(10)),
            retain: false,
            topic: TopicName::from_static("a/b"),
            properties: Properties::default(),
            payload: Bytes::from_static(b"hi"),
        }),
    );
    // An empty topic with a Topic Alias; subscription identifiers may repeat.
    golden(
        &[
            0x30, 0x0B, 0x00, 0x00, 0x07, 0x0B, 0x01, 0x0B, 0x02, 0x23, 0x00, 0x01, b'x',
        ],
        V5,
        Packet::Publish(Publish {
            dup: false,
            delivery: Delivery::AtMostOnce,
            retain: false,
            topic: TopicName::default(),
            properties: props(PropertyValues {
                subscription_identifiers: vec![
                    NonZeroU32::new(1).unwrap(),
                    NonZeroU32::new(2).unwrap(),
                ],
                topic_alias: NonZeroU16::new(1),
                ..Default::default()
            }),
            payload: Bytes::from_static(b"x"),
        }),
    );
    // Request/response properties and user properties, in identifier order.
    golden(
        &[
            0x30, 0x2A, 0x00, 0x01, b't', 0x24, //
            0x01, 0x01, // payload format: UTF-8
            0x02, 0x00, 0x00, 0x00, 0x3C, // message expiry 60
            0x03, 0x00, 0x04, b'j', b's', b'o', b'n', // content type
            0x08, 0x00, 0x01, b'r', // response topic
            0x09, 0x00, 0x02, 0x01, 0x02, // correlation data
            0x26, 0x00, 0x01, b'k', 0x00, 0x01, b'v', // user property
            0x26, 0x00, 0x01, b'k', 0x00, 0x00, // the same key again
            b'{', b'}',
        ],
        V5,
        Packet::Publish(Publish {
            dup: false,
            delivery: Delivery::AtMostOnce,
            retain: false,
            topic: TopicName::from_static("t"),
            properties: props(PropertyValues {
                payload_format_utf8: Some(true),
                message_expiry_interval: Some(60),
                content_type: Some(s("json")),
                response_topic: Some(TopicName::from_static("r")),
                correlation_data: Some(Bytes::from_static(&[1, 2])),
                user_properties: vec![(s("k"), s("v")), (s("k"), s(""))],
                ..Default::default()
            }),
            payload: Bytes::from_static(b"{}"),
        }),
    );
}

#[test]
fn publish_payload_is_a_slice_of_the_read_buffer() {
    let mut buf = BytesMut::from(&[0x30, 0x06, 0x00, 0x01, b't', b'a', b'b', b'c'][..]);
    let start = buf.as_ptr() as usize;
    let Some(Packet::Publish(p)) = decode_packet(&mut buf, V3, 100).unwrap() else {
        panic!("a publish")
    };
    assert_eq!(p.payload.as_ptr() as usize, start + 5);
    assert_eq!(p.topic.as_str().as_ptr() as usize, start + 4);
}

#[test]
fn publish_rules() {
    // QoS 3, and DUP on QoS 0, are malformed fixed headers.
    for first in [0x36, 0x38] {
        let err = decode(&[first, 0x03, 0x00, 0x01, b't'], V3).unwrap_err();
        assert_eq!(
            err,
            DecodeError::BadFlags {
                packet: PacketType::Publish,
                flags: first & 0x0F
            }
        );
        assert_eq!(err.reason_code(), ReasonCode::MalformedPacket);
    }
    // Packet identifier 0.
    let (_, field, problem) = invalid(&[0x32, 0x05, 0x00, 0x01, b't', 0x00, 0x00], V3);
    assert_eq!((field, problem), ("packet id", Problem::ZeroPacketId));
    assert_eq!(problem.reason_code(), ReasonCode::ProtocolError);
    // Wildcards in a topic name.
    let (_, field, problem) = invalid(&[0x30, 0x05, 0x00, 0x03, b'a', b'/', b'+'], V3);
    assert_eq!(
        (field, problem),
        ("topic", Problem::InvalidTopicName(TopicError::Wildcard))
    );
    assert_eq!(problem.reason_code(), ReasonCode::TopicNameInvalid);
    // Empty topic: never in 3.1.1; in 5.0 only with a Topic Alias.
    assert_eq!(
        invalid(&[0x30, 0x02, 0x00, 0x00], V3).2,
        Problem::InvalidTopicName(TopicError::Empty)
    );
    assert_eq!(
        invalid(&[0x30, 0x03, 0x00, 0x00, 0x00], V5).2,
        Problem::EmptyTopicWithoutAlias
    );
    // Ill-formed UTF-8 (an encoded surrogate) and U+0000.
    let (_, field, problem) = invalid(&[0x30, 0x06, 0x00, 0x04, b'a', 0xED, 0xA0, 0x80], V3);
    assert_eq!((field, problem), ("topic", Problem::InvalidUtf8));
    assert_eq!(problem.reason_code(), ReasonCode::MalformedPacket);
    assert_eq!(
        invalid(&[0x30, 0x04, 0x00, 0x02, b'a', 0x00], V3).2,
        Problem::NullCharacter
    );
    // Topic alias 0, properties from other packets, repeats, unknown ids.
    let with_props = |p: &[u8]| {
        let mut bytes = vec![0x30, 0, 0x00, 0x01, b't', p.len() as u8];
        bytes.extend_from_slice(p);
        bytes[1] = (bytes.len() - 2) as u8;
        invalid(&bytes, V5).2
    };
    assert_eq!(
        with_props(&[0x23, 0x00, 0x00]),
        Problem::InvalidPropertyValue(PropertyId::TopicAlias)
    );
    assert_eq!(
        Problem::InvalidPropertyValue(PropertyId::TopicAlias).reason_code(),
        ReasonCode::TopicAliasInvalid
    );
    assert_eq!(
        with_props(&[0x11, 0x00, 0x00, 0x00, 0x01]),
        Problem::PropertyNotAllowed(PropertyId::SessionExpiryInterval)
    );
    assert_eq!(
        with_props(&[0x23, 0x00, 0x01, 0x23, 0x00, 0x02]),
        Problem::DuplicateProperty(PropertyId::TopicAlias)
    );
    assert_eq!(
        with_props(&[0x0B, 0x00]),
        Problem::InvalidPropertyValue(PropertyId::SubscriptionIdentifier)
    );
    assert_eq!(
        with_props(&[0x01, 0x02]),
        Problem::InvalidPropertyValue(PropertyId::PayloadFormatIndicator)
    );
    assert_eq!(with_props(&[0x7F, 0x00]), Problem::UnknownProperty(0x7F));
    assert_eq!(
        with_props(&[0x08, 0x00, 0x01, b'#']),
        Problem::InvalidTopicName(TopicError::Wildcard)
    );
    assert_eq!(with_props(&[0x02, 0x00, 0x00]), Problem::Truncated);
    // A property length running past the packet.
    assert_eq!(
        invalid(&[0x30, 0x04, 0x00, 0x01, b't', 0x05], V5).2,
        Problem::Truncated
    );
    assert_eq!(
        DecodeError::Invalid {
            packet: PacketType::Publish,
            field: "properties",
            problem: Problem::DuplicateProperty(PropertyId::TopicAlias)
        }
        .reason_code(),
        ReasonCode::ProtocolError
    );
}

#[test]
fn publish_encoding_rules() {
    let publish = |topic: &'static str, properties: Properties, dup: bool| {
        Packet::Publish(Publish {
            dup,
            delivery: Delivery::AtMostOnce,
            retain: false,
            topic: TopicName::from_static(topic),
            properties,
            payload: Bytes::new(),
        })
    };
    assert_eq!(
        encode_err(&publish("t", Properties::default(), true), V5),
        ("dup", Problem::DupOnQos0)
    );
    assert_eq!(
        encode_err(&publish("", Properties::default(), false), V5),
        ("topic", Problem::EmptyTopicWithoutAlias)
    );
    let alias = props(PropertyValues {
        topic_alias: NonZeroU16::new(3),
        ..Default::default()
    });
    assert_eq!(
        encode_err(&publish("t", alias.clone(), false), V3),
        ("properties", Problem::NotInVersion)
    );
    let session = props(PropertyValues {
        session_expiry_interval: Some(1),
        ..Default::default()
    });
    assert_eq!(
        encode_err(&publish("t", session, false), V5),
        (
            "properties",
            Problem::PropertyNotAllowed(PropertyId::SessionExpiryInterval)
        )
    );
    let auth_data = props(PropertyValues {
        correlation_data: Some(Bytes::from(vec![0u8; 65_536])),
        ..Default::default()
    });
    assert_eq!(
        encode_err(&publish("t", auth_data, false), V5),
        ("properties", Problem::TooLong(65_536))
    );
}

// ---- PUBACK, PUBREC, PUBREL, PUBCOMP ----

#[test]
fn publish_responses_v311() {
    let r = PubResponse::new(id(10));
    golden(&[0x40, 0x02, 0x00, 0x0A], V3, Packet::PubAck(r.clone()));
    golden(&[0x50, 0x02, 0x00, 0x0A], V3, Packet::PubRec(r.clone()));
    golden(&[0x62, 0x02, 0x00, 0x0A], V3, Packet::PubRel(r.clone()));
    golden(&[0x70, 0x02, 0x00, 0x0A], V3, Packet::PubComp(r));
    // PUBREL's flags are 0010 (MQTT-3.6.1-1); others' 0000.
    assert_eq!(
        decode(&[0x60, 0x02, 0x00, 0x0A], V3).unwrap_err(),
        DecodeError::BadFlags {
            packet: PacketType::PubRel,
            flags: 0
        }
    );
    assert!(matches!(
        decode(&[0x42, 0x02, 0x00, 0x0A], V3),
        Err(DecodeError::BadFlags { .. })
    ));
    // 3.1.1 has no reason code: a third byte is left over.
    assert_eq!(
        invalid(&[0x40, 0x03, 0x00, 0x0A, 0x00], V3).2,
        Problem::TrailingBytes(1)
    );
    assert_eq!(
        invalid(&[0x40, 0x02, 0x00, 0x00], V3).2,
        Problem::ZeroPacketId
    );
    let failed = Packet::PubAck(PubResponse {
        reason: ReasonCode::QuotaExceeded,
        ..PubResponse::new(id(1))
    });
    assert_eq!(
        encode_err(&failed, V3),
        ("reason code", Problem::NotInVersion)
    );
}

#[test]
fn publish_responses_v5() {
    // The short form: a remaining length of 2 means Success, no properties.
    golden(
        &[0x40, 0x02, 0x00, 0x0A],
        V5,
        Packet::PubAck(PubResponse::new(id(10))),
    );
    // The reason code alone.
    golden(
        &[0x40, 0x03, 0x00, 0x0A, 0x10],
        V5,
        Packet::PubAck(PubResponse {
            reason: ReasonCode::NoMatchingSubscribers,
            ..PubResponse::new(id(10))
        }),
    );
    golden(
        &[0x62, 0x03, 0x00, 0x0A, 0x92],
        V5,
        Packet::PubRel(PubResponse {
            reason: ReasonCode::PacketIdentifierNotFound,
            ..PubResponse::new(id(10))
        }),
    );
    // A reason string.
    golden(
        &[
            0x50, 0x09, 0x00, 0x0A, 0x80, 0x05, 0x1F, 0x00, 0x02, b'n', b'o',
        ],
        V5,
        Packet::PubRec(PubResponse {
            packet_id: id(10),
            reason: ReasonCode::UnspecifiedError,
            properties: props(PropertyValues {
                reason_string: Some(s("no")),
                ..Default::default()
            }),
        }),
    );
    // Success with an explicit empty property list decodes to the short form.
    assert_eq!(
        decode(&[0x70, 0x04, 0x00, 0x0A, 0x00, 0x00], V5).unwrap(),
        Packet::PubComp(PubResponse::new(id(10)))
    );
    // Codes of other packets.
    assert_eq!(
        invalid(&[0x70, 0x03, 0x00, 0x0A, 0x10], V5).2,
        Problem::InvalidReasonCode(0x10)
    );
    assert_eq!(
        invalid(&[0x40, 0x03, 0x00, 0x0A, 0x04], V5).2,
        Problem::InvalidReasonCode(0x04)
    );
}

// ---- SUBSCRIBE and SUBACK ----

#[test]
fn subscribe_v311_spec_example() {
    // 3.1.1 figure 3.22: "a/b" at QoS 1 and "c/d" at QoS 2, packet identifier 10.
    let sub = |filter, qos| Subscription {
        filter: TopicFilter::from_static(filter),
        options: SubscriptionOptions {
            qos,
            ..Default::default()
        },
    };
    golden(
        &[
            0x82, 0x0E, 0x00, 0x0A, 0x00, 0x03, b'a', b'/', b'b', 0x01, 0x00, 0x03, b'c', b'/',
            b'd', 0x02,
        ],
        V3,
        Packet::Subscribe(Subscribe {
            packet_id: id(10),
            properties: Properties::default(),
            subscriptions: vec![sub("a/b", QoS::AtLeastOnce), sub("c/d", QoS::ExactlyOnce)],
        }),
    );
}

#[test]
fn subscribe_v5_options_and_identifier() {
    golden(
        &[
            0x82, 0x0B, 0x00, 0x0A, 0x02, 0x0B, 0x05, 0x00, 0x03, b'a', b'/', b'b', 0x2D,
        ],
        V5,
        Packet::Subscribe(Subscribe {
            packet_id: id(10),
            properties: props(PropertyValues {
                subscription_identifiers: vec![NonZeroU32::new(5).unwrap()],
                ..Default::default()
            }),
            subscriptions: vec![Subscription {
                filter: TopicFilter::from_static("a/b"),
                options: SubscriptionOptions {
                    qos: QoS::AtLeastOnce,
                    no_local: true,
                    retain_as_published: true,
                    retain_handling: RetainHandling::DoNotSend,
                },
            }],
        }),
    );
    let shared = Packet::Subscribe(Subscribe {
        packet_id: id(1),
        properties: Properties::default(),
        subscriptions: vec![Subscription {
            filter: TopicFilter::from_static("$share/g/a/+"),
            options: SubscriptionOptions {
                qos: QoS::AtMostOnce,
                retain_handling: RetainHandling::SendIfNewSubscription,
                ..Default::default()
            },
        }],
    });
    let mut buf = BytesMut::new();
    shared.encode(V5, &mut buf).unwrap();
    assert_eq!(decode(&buf, V5).unwrap(), shared);
}

#[test]
fn subscribe_rules() {
    let sub = |version, filter: &[u8], options: u8| {
        let mut bytes = vec![0x82, 0, 0x00, 0x01];
        if version == V5 {
            bytes.push(0x00);
        }
        bytes.extend_from_slice(&(filter.len() as u16).to_be_bytes());
        bytes.extend_from_slice(filter);
        bytes.push(options);
        bytes[1] = (bytes.len() - 2) as u8;
        invalid(&bytes, version)
    };
    assert_eq!(sub(V3, b"a", 0x04).2, Problem::ReservedBitsSet);
    assert_eq!(sub(V3, b"a", 0x03).2, Problem::InvalidQos);
    assert_eq!(sub(V5, b"a", 0x40).2, Problem::ReservedBitsSet);
    assert_eq!(sub(V5, b"a", 0x03).2, Problem::InvalidSubscriptionOptions);
    assert_eq!(sub(V5, b"a", 0x30).2, Problem::InvalidSubscriptionOptions);
    assert_eq!(
        sub(V5, b"$share/g/a", 0x04).2,
        Problem::NoLocalOnSharedSubscription
    );
    let (packet, field, problem) = sub(V5, b"a/#/b", 0x00);
    assert_eq!(
        (packet, field, problem),
        (
            PacketType::Subscribe,
            "topic filter",
            Problem::InvalidTopicFilter(TopicError::MisplacedMultiLevelWildcard)
        )
    );
    assert_eq!(problem.reason_code(), ReasonCode::TopicFilterInvalid);
    assert_eq!(
        sub(V3, b"$share/g", 0x00).2,
        Problem::InvalidTopicFilter(TopicError::MalformedSharedSubscription)
    );
    assert_eq!(
        sub(V3, b"", 0x00).2,
        Problem::InvalidTopicFilter(TopicError::Empty)
    );
    // No filters at all.
    assert_eq!(
        invalid(&[0x82, 0x02, 0x00, 0x01], V3),
        (PacketType::Subscribe, "payload", Problem::NoTopicFilters)
    );
    // Flags must be 0010.
    assert!(matches!(
        decode(&[0x80, 0x06, 0x00, 0x01, 0x00, 0x01, b'a', 0x00], V3),
        Err(DecodeError::BadFlags { .. })
    ));
    // One subscription identifier at most on SUBSCRIBE.
    assert_eq!(
        invalid(
            &[0x82, 0x0A, 0x00, 0x01, 0x04, 0x0B, 0x01, 0x0B, 0x02, 0x00, 0x01, b'a', 0x00],
            V5
        )
        .2,
        Problem::DuplicateProperty(PropertyId::SubscriptionIdentifier)
    );
    // Options 3.1.1 cannot carry.
    let no_local = Packet::Subscribe(Subscribe {
        packet_id: id(1),
        properties: Properties::default(),
        subscriptions: vec![Subscription {
            filter: TopicFilter::from_static("a"),
            options: SubscriptionOptions {
                no_local: true,
                ..Default::default()
            },
        }],
    });
    assert_eq!(
        encode_err(&no_local, V3),
        ("subscription options", Problem::NotInVersion)
    );
}

#[test]
fn suback_both_versions() {
    // 3.1.1 figure 3.26: granted QoS 0, granted QoS 2, failure.
    golden(
        &[0x90, 0x05, 0x00, 0x0A, 0x00, 0x02, 0x80],
        V3,
        Packet::SubAck(SubAck {
            packet_id: id(10),
            properties: Properties::default(),
            reasons: vec![
                ReasonCode::GRANTED_QOS_0,
                ReasonCode::GrantedQos2,
                ReasonCode::UnspecifiedError,
            ],
        }),
    );
    golden(
        &[0x90, 0x06, 0x00, 0x0A, 0x00, 0x00, 0x01, 0xA2],
        V5,
        Packet::SubAck(SubAck {
            packet_id: id(10),
            properties: Properties::default(),
            reasons: vec![
                ReasonCode::Success,
                ReasonCode::GrantedQos1,
                ReasonCode::WildcardSubscriptionsNotSupported,
            ],
        }),
    );
    assert_eq!(
        invalid(&[0x90, 0x03, 0x00, 0x0A, 0x87], V3).2,
        Problem::InvalidReasonCode(0x87)
    );
    assert_eq!(
        invalid(&[0x90, 0x04, 0x00, 0x0A, 0x00, 0x92], V5).2,
        Problem::InvalidReasonCode(0x92)
    );
    let refused = Packet::SubAck(SubAck {
        packet_id: id(10),
        properties: Properties::default(),
        reasons: vec![ReasonCode::NotAuthorized],
    });
    assert_eq!(
        encode_err(&refused, V3),
        ("reason code", Problem::NotInVersion)
    );
}

// ---- UNSUBSCRIBE and UNSUBACK ----

#[test]
fn unsubscribe_both_versions() {
    // 3.1.1 figure 3.30: "a/b" and "c/d".
    let packet = Packet::Unsubscribe(Unsubscribe {
        packet_id: id(10),
        properties: Properties::default(),
        filters: vec![
            TopicFilter::from_static("a/b"),
            TopicFilter::from_static("c/d"),
        ],
    });
    golden(
        &[
            0xA2, 0x0C, 0x00, 0x0A, 0x00, 0x03, b'a', b'/', b'b', 0x00, 0x03, b'c', b'/', b'd',
        ],
        V3,
        packet.clone(),
    );
    golden(
        &[
            0xA2, 0x0D, 0x00, 0x0A, 0x00, 0x00, 0x03, b'a', b'/', b'b', 0x00, 0x03, b'c', b'/',
            b'd',
        ],
        V5,
        packet,
    );
    assert_eq!(
        invalid(&[0xA2, 0x03, 0x00, 0x0A, 0x00], V5).2,
        Problem::NoTopicFilters
    );
    assert!(matches!(
        decode(&[0xA0, 0x02, 0x00, 0x0A], V3),
        Err(DecodeError::BadFlags { .. })
    ));
}

#[test]
fn unsuback_both_versions() {
    golden(
        &[0xB0, 0x02, 0x00, 0x0A],
        V3,
        Packet::UnsubAck(UnsubAck {
            packet_id: id(10),
            properties: Properties::default(),
            reasons: Vec::new(),
        }),
    );
    golden(
        &[0xB0, 0x05, 0x00, 0x0A, 0x00, 0x00, 0x11],
        V5,
        Packet::UnsubAck(UnsubAck {
            packet_id: id(10),
            properties: Properties::default(),
            reasons: vec![ReasonCode::Success, ReasonCode::NoSubscriptionExisted],
        }),
    );
    assert_eq!(
        invalid(&[0xB0, 0x03, 0x00, 0x0A, 0x00], V3).2,
        Problem::TrailingBytes(1)
    );
    assert_eq!(
        invalid(&[0xB0, 0x04, 0x00, 0x0A, 0x00, 0x01], V5).2,
        Problem::InvalidReasonCode(1)
    );
}

// ---- PINGREQ, PINGRESP, DISCONNECT, AUTH ----

#[test]
fn ping_and_disconnect() {
    for version in [V3, V5] {
        golden(&[0xC0, 0x00], version, Packet::PingReq);
        golden(&[0xD0, 0x00], version, Packet::PingResp);
        golden(
            &[0xE0, 0x00],
            version,
            Packet::Disconnect(Disconnect::default()),
        );
        assert_eq!(
            invalid(&[0xC0, 0x01, 0x00], version).2,
            Problem::TrailingBytes(1)
        );
        assert!(matches!(
            decode(&[0xC1, 0x00], version),
            Err(DecodeError::BadFlags { .. })
        ));
    }
    assert_eq!(
        invalid(&[0xE0, 0x01, 0x00], V3).2,
        Problem::TrailingBytes(1)
    );
    golden(
        &[0xE0, 0x01, 0x04],
        V5,
        Packet::Disconnect(Disconnect {
            reason: ReasonCode::DisconnectWithWill,
            properties: Properties::default(),
        }),
    );
    golden(
        &[0xE0, 0x07, 0x00, 0x05, 0x11, 0x00, 0x00, 0x00, 0x3C],
        V5,
        Packet::Disconnect(Disconnect {
            reason: ReasonCode::NORMAL_DISCONNECTION,
            properties: props(PropertyValues {
                session_expiry_interval: Some(60),
                ..Default::default()
            }),
        }),
    );
    assert_eq!(
        invalid(&[0xE0, 0x01, 0x01], V5).2,
        Problem::InvalidReasonCode(1)
    );
    let with_reason = Packet::Disconnect(Disconnect {
        reason: ReasonCode::ServerShuttingDown,
        properties: Properties::default(),
    });
    assert_eq!(
        encode_err(&with_reason, V3),
        ("reason code", Problem::NotInVersion)
    );
}

#[test]
fn auth_is_v5_only() {
    golden(&[0xF0, 0x00], V5, Packet::Auth(Auth::default()));
    golden(
        &[
            0xF0, 0x0F, 0x18, 0x0D, 0x15, 0x00, 0x05, b'S', b'C', b'R', b'A', b'M', 0x16, 0x00,
            0x02, 0x01, 0x02,
        ],
        V5,
        Packet::Auth(Auth {
            reason: ReasonCode::ContinueAuthentication,
            properties: props(PropertyValues {
                authentication_method: Some(s("SCRAM")),
                authentication_data: Some(Bytes::from_static(&[1, 2])),
                ..Default::default()
            }),
        }),
    );
    // Without properties, a reason other than Success keeps its property
    // length; a decoder also takes the reason alone.
    let reauthenticate = Packet::Auth(Auth {
        reason: ReasonCode::ReAuthenticate,
        properties: Properties::default(),
    });
    golden(&[0xF0, 0x02, 0x19, 0x00], V5, reauthenticate.clone());
    assert_eq!(decode(&[0xF0, 0x01, 0x19], V5).unwrap(), reauthenticate);
    assert_eq!(
        decode(&[0xF0, 0x00], V3).unwrap_err(),
        DecodeError::UnknownPacketType(15)
    );
    assert_eq!(
        encode_err(&Packet::Auth(Auth::default()), V3),
        ("packet type", Problem::NotInVersion)
    );
    // Authentication data needs a method.
    assert_eq!(
        invalid(&[0xF0, 0x07, 0x18, 0x05, 0x16, 0x00, 0x02, 0x01, 0x02], V5).2,
        Problem::AuthDataWithoutMethod
    );
}

#[test]
fn packet_type_zero_is_reserved() {
    for version in [V3, V5] {
        assert_eq!(
            decode(&[0x00, 0x00], version).unwrap_err(),
            DecodeError::UnknownPacketType(0)
        );
    }
}

#[test]
fn packets_stay_small() {
    // Properties are a handle: a packet is moved on every decode.
    assert!(
        std::mem::size_of::<Packet>() <= 96,
        "{}",
        std::mem::size_of::<Packet>()
    );
    assert_eq!(
        std::mem::size_of::<Properties>(),
        std::mem::size_of::<usize>()
    );
}
