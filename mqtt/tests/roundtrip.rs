//! Property tests: every valid packet of either version encodes and decodes
//! back unchanged; a packet stream decodes the same however it is split
//! across reads (byte by byte included); arbitrary or corrupted bytes never
//! make the decoder panic, and it never consumes more than the packet the
//! fixed header declares.

use bytes::{Bytes, BytesMut};
use leveret_mqtt::{
    check_packet, decode_packet, Auth, ConnAck, Connect, DecodeError, Delivery, Disconnect,
    MqttString, Packet, PacketCheck, PacketId, PacketType, Properties, PropertyContext, PropertyId,
    PropertyValues, ProtocolVersion, PubResponse, Publish, QoS, ReasonCode, RetainHandling, SubAck,
    Subscribe, Subscription, SubscriptionOptions, TopicFilter, TopicName, UnsubAck, Unsubscribe,
    Will,
};
use proptest::collection::vec;
use proptest::option::of;
use proptest::prelude::*;
use proptest::sample::select;
use std::num::{NonZeroU16, NonZeroU32};

const V3: ProtocolVersion = ProtocolVersion::V3_1_1;
const V5: ProtocolVersion = ProtocolVersion::V5;

// ---- strategies ----

fn text() -> impl Strategy<Value = MqttString> {
    vec(
        any::<char>().prop_filter("no U+0000", |c| *c != '\0'),
        0..10,
    )
    .prop_map(|chars| MqttString::try_from(chars.into_iter().collect::<String>()).unwrap())
}

fn binary() -> impl Strategy<Value = Bytes> {
    vec(any::<u8>(), 0..24).prop_map(Bytes::from)
}

fn level() -> impl Strategy<Value = String> {
    vec(select(vec!['a', 'b', 'ü', '$', '✓', ' ', '.']), 0..4)
        .prop_map(|chars| chars.into_iter().collect())
}

fn topic_name() -> impl Strategy<Value = TopicName> {
    vec(level(), 1..4).prop_filter_map("not empty", |levels| {
        let name = levels.join("/");
        (!name.is_empty()).then(|| TopicName::new(MqttString::try_from(name).unwrap()).unwrap())
    })
}

fn topic_filter() -> impl Strategy<Value = TopicFilter> {
    let filter_level = prop_oneof![4 => level(), 1 => Just("+".to_string())];
    (vec(filter_level, 1..4), any::<bool>(), of("[a-z]{1,4}")).prop_filter_map(
        "a valid filter",
        |(levels, hash, group)| {
            let mut filter = levels.join("/");
            if hash {
                filter.push_str("/#");
            }
            if let Some(group) = group {
                filter = format!("$share/{group}/{filter}");
            }
            TopicFilter::new(MqttString::try_from(filter).unwrap()).ok()
        },
    )
}

fn packet_id() -> impl Strategy<Value = PacketId> {
    (1..=u16::MAX).prop_map(|n| NonZeroU16::new(n).unwrap())
}

fn qos() -> impl Strategy<Value = QoS> {
    select(vec![QoS::AtMostOnce, QoS::AtLeastOnce, QoS::ExactlyOnce])
}

fn all_property_values() -> impl Strategy<Value = PropertyValues> {
    let a = (
        of(any::<bool>()),
        of(any::<u32>()),
        of(text()),
        of(topic_name()),
        of(binary()),
        vec(
            (1..=268_435_455u32).prop_map(|n| NonZeroU32::new(n).unwrap()),
            0..3,
        ),
        of(any::<u32>()),
        of(text()),
        of(any::<u16>()),
        of(text()),
        of(binary()),
        of(any::<bool>()),
    );
    let b = (
        of(any::<u32>()),
        of(any::<bool>()),
        of(text()),
        of(text()),
        of(text()),
        of(1..=u16::MAX),
        of(any::<u16>()),
        of(1..=u16::MAX),
        of(select(vec![QoS::AtMostOnce, QoS::AtLeastOnce])),
        of(any::<bool>()),
        vec((text(), text()), 0..3),
        of(1..=u32::MAX),
    );
    let c = (of(any::<bool>()), of(any::<bool>()), of(any::<bool>()));
    (a, b, c).prop_map(|(a, b, c)| PropertyValues {
        payload_format_utf8: a.0,
        message_expiry_interval: a.1,
        content_type: a.2,
        response_topic: a.3,
        correlation_data: a.4,
        subscription_identifiers: a.5,
        session_expiry_interval: a.6,
        assigned_client_identifier: a.7,
        server_keep_alive: a.8,
        authentication_method: a.9,
        authentication_data: a.10,
        request_problem_information: a.11,
        will_delay_interval: b.0,
        request_response_information: b.1,
        response_information: b.2,
        server_reference: b.3,
        reason_string: b.4,
        receive_maximum: b.5.and_then(NonZeroU16::new),
        topic_alias_maximum: b.6,
        topic_alias: b.7.and_then(NonZeroU16::new),
        maximum_qos: b.8,
        retain_available: b.9,
        user_properties: b.10,
        maximum_packet_size: b.11.and_then(NonZeroU32::new),
        wildcard_subscription_available: c.0,
        subscription_identifier_available: c.1,
        shared_subscription_available: c.2,
    })
}

/// Valid properties for `context` in `version`: none before 5.0, and in
/// 5.0 only those the context allows, with its rules kept.
fn properties(version: ProtocolVersion, context: PropertyContext) -> BoxedStrategy<Properties> {
    if !version.is_v5() {
        return Just(Properties::default()).boxed();
    }
    all_property_values()
        .prop_map(move |mut v| {
            use PropertyId as P;
            let allowed = |id: PropertyId| id.allowed_in(context);
            macro_rules! keep {
                ($($field:ident: $id:ident),*) => {$(
                    if !allowed(P::$id) {
                        v.$field = Default::default();
                    }
                )*};
            }
            keep!(
                payload_format_utf8: PayloadFormatIndicator,
                message_expiry_interval: MessageExpiryInterval,
                content_type: ContentType,
                response_topic: ResponseTopic,
                correlation_data: CorrelationData,
                subscription_identifiers: SubscriptionIdentifier,
                session_expiry_interval: SessionExpiryInterval,
                assigned_client_identifier: AssignedClientIdentifier,
                server_keep_alive: ServerKeepAlive,
                authentication_method: AuthenticationMethod,
                authentication_data: AuthenticationData,
                request_problem_information: RequestProblemInformation,
                will_delay_interval: WillDelayInterval,
                request_response_information: RequestResponseInformation,
                response_information: ResponseInformation,
                server_reference: ServerReference,
                reason_string: ReasonString,
                receive_maximum: ReceiveMaximum,
                topic_alias_maximum: TopicAliasMaximum,
                topic_alias: TopicAlias,
                maximum_qos: MaximumQos,
                retain_available: RetainAvailable,
                user_properties: UserProperty,
                maximum_packet_size: MaximumPacketSize,
                wildcard_subscription_available: WildcardSubscriptionAvailable,
                subscription_identifier_available: SubscriptionIdentifierAvailable,
                shared_subscription_available: SharedSubscriptionAvailable
            );
            if context == PropertyContext::Subscribe {
                v.subscription_identifiers.truncate(1);
            }
            if v.authentication_data.is_some() && v.authentication_method.is_none() {
                v.authentication_method = Some(MqttString::from_static("SCRAM-SHA-1"));
            }
            Properties::from(v)
        })
        .boxed()
}

/// The reason codes `packet` may carry in `version`.
fn reason(version: ProtocolVersion, packet: PacketType) -> BoxedStrategy<ReasonCode> {
    let codes: Vec<ReasonCode> = (0..=255u8)
        .filter_map(ReasonCode::from_u8)
        .filter(|code| match (version.is_v5(), packet) {
            (true, _) => code.allowed_in(packet),
            (false, PacketType::ConnAck) => code.to_v3_connack().is_some(),
            (false, PacketType::SubAck) => code.in_v3_suback(),
            (false, _) => *code == ReasonCode::Success,
        })
        .collect();
    select(codes).boxed()
}

fn connect(version: ProtocolVersion) -> impl Strategy<Value = Packet> {
    let connect_version = if version.is_v5() {
        Just(V5).boxed()
    } else {
        select(vec![ProtocolVersion::V3_1, V3]).boxed()
    };
    connect_version.prop_flat_map(|v| {
        let will = (
            properties(v, PropertyContext::Will),
            topic_name(),
            binary(),
            qos(),
            any::<bool>(),
        )
            .prop_map(|(properties, topic, payload, qos, retain)| Will {
                properties,
                topic,
                payload,
                qos,
                retain,
            });
        (
            any::<bool>(),
            any::<u16>(),
            properties(v, PropertyContext::Connect),
            text(),
            of(will),
            of(text()),
            of(binary()),
        )
            .prop_map(
                move |(
                    clean_start,
                    keep_alive,
                    properties,
                    client_id,
                    will,
                    username,
                    password,
                )| {
                    // Before 5.0 a password needs a user name.
                    let username = match (&username, &password) {
                        (None, Some(_)) if !v.is_v5() => Some(MqttString::from_static("user")),
                        _ => username,
                    };
                    Packet::Connect(Box::new(Connect {
                        version: v,
                        clean_start,
                        keep_alive,
                        properties,
                        client_id,
                        will,
                        username,
                        password,
                    }))
                },
            )
    })
}

fn publish(version: ProtocolVersion) -> impl Strategy<Value = Packet> {
    let delivery = prop_oneof![
        Just(Delivery::AtMostOnce),
        packet_id().prop_map(Delivery::AtLeastOnce),
        packet_id().prop_map(Delivery::ExactlyOnce),
    ];
    (
        any::<bool>(),
        delivery,
        any::<bool>(),
        topic_name(),
        any::<bool>(),
        properties(version, PropertyContext::Publish),
        binary(),
    )
        .prop_map(
            |(dup, delivery, retain, topic, drop_topic, properties, payload)| {
                // An alias may stand for the topic (5.0 only: earlier versions
                // have no properties).
                let topic = if drop_topic && properties.topic_alias.is_some() {
                    TopicName::default()
                } else {
                    topic
                };
                Packet::Publish(Publish {
                    dup: dup && delivery != Delivery::AtMostOnce,
                    delivery,
                    retain,
                    topic,
                    properties,
                    payload,
                })
            },
        )
}

fn pub_response(version: ProtocolVersion) -> impl Strategy<Value = Packet> {
    let kinds = [
        PacketType::PubAck,
        PacketType::PubRec,
        PacketType::PubRel,
        PacketType::PubComp,
    ];
    select(kinds.to_vec()).prop_flat_map(move |kind| {
        (
            packet_id(),
            reason(version, kind),
            properties(version, PropertyContext::PubResponse),
        )
            .prop_map(move |(packet_id, reason, properties)| {
                let r = PubResponse {
                    packet_id,
                    reason,
                    properties,
                };
                match kind {
                    PacketType::PubAck => Packet::PubAck(r),
                    PacketType::PubRec => Packet::PubRec(r),
                    PacketType::PubRel => Packet::PubRel(r),
                    _ => Packet::PubComp(r),
                }
            })
    })
}

fn subscribe(version: ProtocolVersion) -> impl Strategy<Value = Packet> {
    let retain_handling = select(vec![
        RetainHandling::SendAtSubscribe,
        RetainHandling::SendIfNewSubscription,
        RetainHandling::DoNotSend,
    ]);
    let subscription = (
        topic_filter(),
        qos(),
        any::<bool>(),
        any::<bool>(),
        retain_handling,
    )
        .prop_map(
            move |(filter, qos, no_local, retain_as_published, retain_handling)| {
                let options = if version.is_v5() {
                    SubscriptionOptions {
                        qos,
                        no_local: no_local && filter.shared().is_none(),
                        retain_as_published,
                        retain_handling,
                    }
                } else {
                    SubscriptionOptions {
                        qos,
                        ..Default::default()
                    }
                };
                Subscription { filter, options }
            },
        );
    (
        packet_id(),
        properties(version, PropertyContext::Subscribe),
        vec(subscription, 1..4),
    )
        .prop_map(|(packet_id, properties, subscriptions)| {
            Packet::Subscribe(Subscribe {
                packet_id,
                properties,
                subscriptions,
            })
        })
}

fn acks_and_others(version: ProtocolVersion) -> impl Strategy<Value = Packet> {
    let connack = (
        any::<bool>(),
        reason(version, PacketType::ConnAck),
        properties(version, PropertyContext::ConnAck),
    )
        .prop_map(|(session_present, reason, properties)| {
            Packet::ConnAck(ConnAck {
                session_present,
                reason,
                properties,
            })
        });
    let suback = (
        packet_id(),
        properties(version, PropertyContext::SubAck),
        vec(reason(version, PacketType::SubAck), 0..4),
    )
        .prop_map(|(packet_id, properties, reasons)| {
            Packet::SubAck(SubAck {
                packet_id,
                properties,
                reasons,
            })
        });
    let unsubscribe = (
        packet_id(),
        properties(version, PropertyContext::Unsubscribe),
        vec(topic_filter(), 1..4),
    )
        .prop_map(|(packet_id, properties, filters)| {
            Packet::Unsubscribe(Unsubscribe {
                packet_id,
                properties,
                filters,
            })
        });
    let unsuback_reasons = if version.is_v5() {
        vec(reason(version, PacketType::UnsubAck), 0..4).boxed()
    } else {
        Just(Vec::new()).boxed()
    };
    let unsuback = (
        packet_id(),
        properties(version, PropertyContext::UnsubAck),
        unsuback_reasons,
    )
        .prop_map(|(packet_id, properties, reasons)| {
            Packet::UnsubAck(UnsubAck {
                packet_id,
                properties,
                reasons,
            })
        });
    let disconnect = (
        reason(version, PacketType::Disconnect),
        properties(version, PropertyContext::Disconnect),
    )
        .prop_map(|(reason, properties)| Packet::Disconnect(Disconnect { reason, properties }));
    let auth = (
        reason(V5, PacketType::Auth),
        properties(V5, PropertyContext::Auth),
    )
        .prop_map(|(reason, properties)| Packet::Auth(Auth { reason, properties }));
    let auth = if version.is_v5() {
        auth.boxed()
    } else {
        Just(Packet::PingReq).boxed()
    };
    prop_oneof![
        connack,
        suback,
        unsubscribe,
        unsuback,
        disconnect,
        auth,
        Just(Packet::PingReq),
        Just(Packet::PingResp),
    ]
}

fn packet(version: ProtocolVersion) -> impl Strategy<Value = Packet> {
    prop_oneof![
        1 => connect(version),
        3 => publish(version),
        1 => pub_response(version),
        1 => subscribe(version),
        2 => acks_and_others(version),
    ]
}

fn version() -> impl Strategy<Value = ProtocolVersion> {
    select(vec![V3, V5])
}

fn versioned_packets() -> impl Strategy<Value = (ProtocolVersion, Vec<Packet>)> {
    version().prop_flat_map(|v| (Just(v), vec(packet(v), 1..8)))
}

// ---- properties ----

fn round_trip(version: ProtocolVersion, packet: &Packet) -> Result<(), TestCaseError> {
    let mut buf = BytesMut::new();
    let len = packet
        .encode(version, &mut buf)
        .map_err(|e| TestCaseError::fail(format!("{e} for {packet:?}")))?;
    prop_assert_eq!(len, buf.len());
    prop_assert_eq!(packet.encoded_len(version).unwrap(), len);
    prop_assert_eq!(
        check_packet(&buf, len as u32).unwrap(),
        PacketCheck::Complete { len }
    );
    let decoded = decode_packet(&mut buf, version, len as u32)
        .unwrap()
        .unwrap();
    prop_assert!(buf.is_empty());
    prop_assert_eq!(&decoded, packet);
    Ok(())
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(512))]

    #[test]
    fn v311_packets_round_trip(packet in packet(V3)) {
        round_trip(V3, &packet)?;
    }

    #[test]
    fn v5_packets_round_trip(packet in packet(V5)) {
        round_trip(V5, &packet)?;
    }

    #[test]
    fn one_byte_under_the_size_limit_is_refused(packet in packet(V5)) {
        let mut buf = BytesMut::new();
        let len = packet.encode(V5, &mut buf).unwrap();
        let limit = len as u32 - 1;
        // Refused from the fixed header: at most 5 bytes are needed to know.
        let header = &buf[..buf.len().min(5)];
        prop_assert_eq!(
            check_packet(header, limit).unwrap_err(),
            DecodeError::PacketTooLarge { size: len as u64, max: limit }
        );
        let err = decode_packet(&mut buf, V5, limit).unwrap_err();
        prop_assert_eq!(err.reason_code(), ReasonCode::PacketTooLarge);
        prop_assert_eq!(buf.len(), len, "nothing is taken off the buffer");
    }

    #[test]
    fn a_stream_decodes_the_same_however_it_is_split(
        (version, packets) in versioned_packets(),
        splits in vec(1usize..64, 1..32),
    ) {
        let mut wire = BytesMut::new();
        for packet in &packets {
            packet.encode(version, &mut wire).unwrap();
        }
        for chunking in [None, Some(&splits)] {
            let mut buf = BytesMut::new();
            let mut decoded = Vec::new();
            let mut offset = 0;
            let mut sizes = chunking.into_iter().flatten().cycle();
            while offset < wire.len() {
                // Byte by byte, then in the generated chunk sizes.
                let size = sizes.next().copied().unwrap_or(1).min(wire.len() - offset);
                buf.extend_from_slice(&wire[offset..offset + size]);
                offset += size;
                while let Some(packet) = decode_packet(&mut buf, version, 1 << 20).unwrap() {
                    decoded.push(packet);
                }
            }
            prop_assert!(buf.is_empty());
            prop_assert_eq!(&decoded, &packets);
        }
    }

    #[test]
    fn arbitrary_bytes_never_panic_nor_overread(
        bytes in vec(any::<u8>(), 0..256),
        suffix in vec(any::<u8>(), 0..16),
        version in version(),
        max in prop_oneof![Just(u32::MAX), 0u32..300],
    ) {
        check_stream(&bytes, &suffix, version, max)?;
    }

    #[test]
    fn corrupted_packets_never_panic_nor_overread(
        (version, packets) in versioned_packets(),
        flips in vec((any::<prop::sample::Index>(), any::<u8>()), 1..4),
        suffix in vec(any::<u8>(), 0..16),
    ) {
        let mut wire = BytesMut::new();
        for packet in &packets {
            packet.encode(version, &mut wire).unwrap();
        }
        let mut bytes = wire.to_vec();
        for (at, value) in flips {
            let i = at.index(bytes.len());
            bytes[i] = value;
        }
        check_stream(&bytes, &suffix, version, u32::MAX)?;
    }
}

/// Decodes `bytes` to its end, checking that each call takes exactly the
/// packet the fixed header declared (or nothing), that bytes after a packet
/// never change how it decodes, and that whatever decodes re-encodes and
/// decodes to itself.
fn check_stream(
    bytes: &[u8],
    suffix: &[u8],
    version: ProtocolVersion,
    max: u32,
) -> Result<(), TestCaseError> {
    let mut buf = BytesMut::from(bytes);
    loop {
        let declared = check_packet(&buf, max);
        let before = buf.len();
        let mut with_suffix = buf.clone();
        with_suffix.extend_from_slice(suffix);
        let result = decode_packet(&mut buf, version, max);
        let consumed = before - buf.len();
        match (&declared, &result) {
            (Ok(PacketCheck::Complete { len }), Ok(Some(_)) | Err(DecodeError::Invalid { .. })) => {
                prop_assert_eq!(consumed, *len)
            }
            _ => prop_assert_eq!(consumed, 0),
        }
        if let Ok(PacketCheck::Complete { .. }) = declared {
            let again = decode_packet(&mut with_suffix, version, max);
            prop_assert_eq!(
                &again,
                &result,
                "bytes after the packet changed its decoding"
            );
        }
        match result {
            Ok(Some(packet)) => {
                let mut encoded = BytesMut::new();
                packet.encode(version, &mut encoded).map_err(|e| {
                    TestCaseError::fail(format!("decoded {packet:?} does not re-encode: {e}"))
                })?;
                let decoded = decode_packet(&mut encoded, version, u32::MAX)
                    .unwrap()
                    .unwrap();
                prop_assert_eq!(decoded, packet);
            }
            Ok(None) => return Ok(()),
            Err(DecodeError::Invalid { .. }) => {}
            Err(_) => return Ok(()),
        }
    }
}

/// The fuzz target's seeds (`fuzz/corpus/mqtt_decode/seed-*`) are valid
/// streams in the version their name says, and pass the fuzz target's
/// checks in both versions.
#[test]
fn fuzz_seeds_are_valid_streams() {
    let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../fuzz/corpus/mqtt_decode");
    let mut seeds = 0;
    for entry in std::fs::read_dir(&dir).unwrap() {
        let path = entry.unwrap().path();
        let name = path.file_name().unwrap().to_str().unwrap().to_string();
        if !name.starts_with("seed-") {
            continue;
        }
        seeds += 1;
        let bytes = std::fs::read(&path).unwrap();
        let version = if name.contains("v5") { V5 } else { V3 };
        let mut buf = BytesMut::from(&bytes[..]);
        let mut packets = 0;
        while let Some(_packet) =
            decode_packet(&mut buf, version, u32::MAX).unwrap_or_else(|e| panic!("{name}: {e}"))
        {
            packets += 1;
        }
        // Whole packets only, but for the one that declares 2 MiB.
        assert_eq!(
            buf.is_empty(),
            !name.contains("long-remaining-length"),
            "{name}"
        );
        assert!(packets > 0 || !buf.is_empty(), "{name}");
        for version in [V3, V5] {
            for max in [u32::MAX, 4096, u32::from(bytes[0])] {
                check_stream(&bytes, &[], version, max).unwrap();
            }
        }
    }
    assert_eq!(seeds, 9);
}
