//! Property tests: whatever the codec encodes it decodes back unchanged,
//! arbitrary bytes never make it panic, and a frame stream decodes the same
//! however it is split across reads.

use bytes::{Bytes, BytesMut};
use leveret_protocol::{
    decode_frame, encode_method, parse_frame, BasicCancel, BasicConsume, BasicDeliver, BasicGetOk,
    BasicNack, BasicProperties, BasicPublish, BasicQos, BasicReturn, ChannelClose, ConnectionClose,
    ConnectionStart, ConnectionStartOk, ConnectionTune, ContentHeader, Decimal, ExchangeBind,
    ExchangeDeclare, FieldTable, FieldValue, Frame, Method, QueueBind, QueueDeclare, ShortStr,
};
use proptest::collection::vec;
use proptest::prelude::*;

// ---- strategies ----

fn short_str() -> impl Strategy<Value = ShortStr> {
    prop_oneof![
        4 => vec(any::<u8>(), 0..24),
        1 => vec(any::<u8>(), 0..=255),
    ]
    .prop_map(|v| ShortStr::try_from(Bytes::from(v)).expect("at most 255 bytes"))
}

fn long_str() -> impl Strategy<Value = Bytes> {
    vec(any::<u8>(), 0..64).prop_map(Bytes::from)
}

fn leaf_value() -> impl Strategy<Value = FieldValue> {
    prop_oneof![
        any::<bool>().prop_map(FieldValue::Bool),
        any::<i8>().prop_map(FieldValue::I8),
        any::<u8>().prop_map(FieldValue::U8),
        any::<i16>().prop_map(FieldValue::I16),
        any::<u16>().prop_map(FieldValue::U16),
        any::<i32>().prop_map(FieldValue::I32),
        any::<u32>().prop_map(FieldValue::U32),
        any::<i64>().prop_map(FieldValue::I64),
        any::<f32>()
            .prop_filter("NaN is not equal to itself", |v| !v.is_nan())
            .prop_map(FieldValue::F32),
        any::<f64>()
            .prop_filter("NaN is not equal to itself", |v| !v.is_nan())
            .prop_map(FieldValue::F64),
        (any::<u8>(), any::<u32>())
            .prop_map(|(scale, value)| FieldValue::Decimal(Decimal { scale, value })),
        long_str().prop_map(FieldValue::LongStr),
        long_str().prop_map(FieldValue::ByteArray),
        any::<u64>().prop_map(FieldValue::Timestamp),
        Just(FieldValue::Void),
    ]
}

/// Nested values: at most 4 levels of arrays and tables (the decoder
/// accepts 32).
fn field_value() -> impl Strategy<Value = FieldValue> {
    leaf_value().prop_recursive(4, 48, 6, |inner| {
        prop_oneof![
            vec(inner.clone(), 0..6).prop_map(FieldValue::Array),
            vec((short_str(), inner), 0..6)
                .prop_map(|entries| FieldValue::Table(entries.into_iter().collect())),
        ]
    })
}

fn field_table() -> impl Strategy<Value = FieldTable> {
    vec((short_str(), field_value()), 0..8).prop_map(|entries| entries.into_iter().collect())
}

prop_compose! {
    fn basic_properties()(
        strings in vec(proptest::option::of(short_str()), 11),
        headers in proptest::option::of(field_table()),
        delivery_mode in proptest::option::of(any::<u8>()),
        priority in proptest::option::of(any::<u8>()),
        timestamp in proptest::option::of(any::<u64>()),
    ) -> BasicProperties {
        let mut s = strings.into_iter();
        BasicProperties {
            content_type: s.next().unwrap(),
            content_encoding: s.next().unwrap(),
            headers,
            delivery_mode,
            priority,
            correlation_id: s.next().unwrap(),
            reply_to: s.next().unwrap(),
            expiration: s.next().unwrap(),
            message_id: s.next().unwrap(),
            timestamp,
            kind: s.next().unwrap(),
            user_id: s.next().unwrap(),
            app_id: s.next().unwrap(),
            cluster_id: s.next().unwrap(),
        }
    }
}

fn method() -> impl Strategy<Value = Method> {
    prop_oneof![
        (
            any::<u16>(),
            short_str(),
            short_str(),
            any::<bool>(),
            any::<bool>()
        )
            .prop_map(|(ticket, exchange, routing_key, mandatory, immediate)| {
                BasicPublish {
                    ticket,
                    exchange,
                    routing_key,
                    mandatory,
                    immediate,
                }
                .into()
            }),
        (
            short_str(),
            any::<u64>(),
            any::<bool>(),
            short_str(),
            short_str()
        )
            .prop_map(
                |(consumer_tag, delivery_tag, redelivered, exchange, routing_key)| BasicDeliver {
                    consumer_tag,
                    delivery_tag,
                    redelivered,
                    exchange,
                    routing_key
                }
                .into()
            ),
        (
            any::<u64>(),
            any::<bool>(),
            short_str(),
            short_str(),
            any::<u32>()
        )
            .prop_map(
                |(delivery_tag, redelivered, exchange, routing_key, message_count)| BasicGetOk {
                    delivery_tag,
                    redelivered,
                    exchange,
                    routing_key,
                    message_count
                }
                .into()
            ),
        (any::<u16>(), short_str(), short_str(), short_str()).prop_map(
            |(reply_code, reply_text, exchange, routing_key)| BasicReturn {
                reply_code,
                reply_text,
                exchange,
                routing_key
            }
            .into()
        ),
        (
            any::<u16>(),
            short_str(),
            short_str(),
            any::<[bool; 5]>(),
            field_table()
        )
            .prop_map(|(ticket, exchange, kind, b, arguments)| ExchangeDeclare {
                ticket,
                exchange,
                kind,
                passive: b[0],
                durable: b[1],
                auto_delete: b[2],
                internal: b[3],
                no_wait: b[4],
                arguments
            }
            .into()),
        (any::<u16>(), short_str(), any::<[bool; 5]>(), field_table()).prop_map(
            |(ticket, queue, b, arguments)| QueueDeclare {
                ticket,
                queue,
                passive: b[0],
                durable: b[1],
                exclusive: b[2],
                auto_delete: b[3],
                no_wait: b[4],
                arguments
            }
            .into()
        ),
        (
            any::<u16>(),
            short_str(),
            short_str(),
            short_str(),
            any::<bool>(),
            field_table()
        )
            .prop_map(
                |(ticket, queue, exchange, routing_key, no_wait, arguments)| QueueBind {
                    ticket,
                    queue,
                    exchange,
                    routing_key,
                    no_wait,
                    arguments
                }
                .into()
            ),
        (
            any::<u16>(),
            short_str(),
            short_str(),
            short_str(),
            any::<bool>(),
            field_table()
        )
            .prop_map(
                |(ticket, destination, source, routing_key, no_wait, arguments)| ExchangeBind {
                    ticket,
                    destination,
                    source,
                    routing_key,
                    no_wait,
                    arguments
                }
                .into()
            ),
        (
            any::<u16>(),
            short_str(),
            short_str(),
            any::<[bool; 4]>(),
            field_table()
        )
            .prop_map(|(ticket, queue, consumer_tag, b, arguments)| BasicConsume {
                ticket,
                queue,
                consumer_tag,
                no_local: b[0],
                no_ack: b[1],
                exclusive: b[2],
                no_wait: b[3],
                arguments
            }
            .into()),
        (short_str(), any::<bool>()).prop_map(|(consumer_tag, no_wait)| BasicCancel {
            consumer_tag,
            no_wait
        }
        .into()),
        (any::<u64>(), any::<bool>(), any::<bool>()).prop_map(
            |(delivery_tag, multiple, requeue)| BasicNack {
                delivery_tag,
                multiple,
                requeue
            }
            .into()
        ),
        (any::<u32>(), any::<u16>(), any::<bool>()).prop_map(
            |(prefetch_size, prefetch_count, global)| BasicQos {
                prefetch_size,
                prefetch_count,
                global
            }
            .into()
        ),
        (any::<u16>(), short_str(), any::<u16>(), any::<u16>()).prop_map(
            |(reply_code, reply_text, class_id, method_id)| ConnectionClose {
                reply_code,
                reply_text,
                class_id,
                method_id
            }
            .into()
        ),
        (any::<u16>(), short_str(), any::<u16>(), any::<u16>()).prop_map(
            |(reply_code, reply_text, class_id, method_id)| ChannelClose {
                reply_code,
                reply_text,
                class_id,
                method_id
            }
            .into()
        ),
        (
            any::<u8>(),
            any::<u8>(),
            field_table(),
            long_str(),
            long_str()
        )
            .prop_map(
                |(version_major, version_minor, server_properties, mechanisms, locales)| {
                    ConnectionStart {
                        version_major,
                        version_minor,
                        server_properties,
                        mechanisms,
                        locales,
                    }
                    .into()
                }
            ),
        (field_table(), short_str(), long_str(), short_str()).prop_map(
            |(client_properties, mechanism, response, locale)| ConnectionStartOk {
                client_properties,
                mechanism,
                response,
                locale
            }
            .into()
        ),
        (any::<u16>(), any::<u32>(), any::<u16>()).prop_map(
            |(channel_max, frame_max, heartbeat)| ConnectionTune {
                channel_max,
                frame_max,
                heartbeat
            }
            .into()
        ),
    ]
}

fn frame() -> impl Strategy<Value = Frame> {
    prop_oneof![
        3 => (any::<u16>(), method()).prop_map(|(channel, method)| Frame::Method { channel, method }),
        2 => (any::<u16>(), any::<u64>(), basic_properties()).prop_map(
            |(channel, body_size, props)| Frame::Header {
                channel,
                header: ContentHeader::new(body_size, &props),
            }
        ),
        2 => (any::<u16>(), vec(any::<u8>(), 0..300)).prop_map(|(channel, body)| Frame::Body {
            channel,
            payload: Bytes::from(body),
        }),
        1 => Just(Frame::Heartbeat),
    ]
}

// ---- helpers ----

fn encoded(frame: &Frame) -> BytesMut {
    let mut buf = BytesMut::new();
    frame.encode(&mut buf);
    buf
}

/// Decodes everything in `buf` with `frame_max`, stopping at the first
/// error or when more bytes are needed. Checks that a decoded frame
/// re-encodes to bytes that decode to the same encoding (a byte check, so
/// it holds for NaN floats too).
fn decode_all_and_reencode(mut buf: BytesMut, frame_max: u32) {
    while let Ok(Some(frame)) = decode_frame(&mut buf, frame_max) {
        let first = encoded(&frame);
        let mut again = first.clone();
        let decoded = decode_frame(&mut again, 0)
            .expect("a re-encoded frame decodes")
            .expect("a re-encoded frame is whole");
        assert!(again.is_empty());
        assert_eq!(encoded(&decoded), first);
    }
}

fn mutate(mut bytes: Vec<u8>, edits: &[(usize, u8)]) -> Vec<u8> {
    if !bytes.is_empty() {
        for &(at, value) in edits {
            let len = bytes.len();
            bytes[at % len] = value;
        }
    }
    bytes
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 512, ..ProptestConfig::default() })]

    // ---- encode then decode gives the original ----

    #[test]
    fn field_table_round_trips(table in field_table()) {
        let mut buf = BytesMut::new();
        table.encode(&mut buf);
        prop_assert_eq!(FieldTable::decode(&buf.freeze()).unwrap(), table);
    }

    #[test]
    fn field_value_round_trips_inside_a_table(key in short_str(), value in field_value()) {
        let mut table = FieldTable::new();
        table.insert(key.clone(), value.clone());
        let mut buf = BytesMut::new();
        table.encode(&mut buf);
        let decoded = FieldTable::decode(&buf.freeze()).unwrap();
        prop_assert_eq!(decoded.len(), 1);
        prop_assert_eq!(decoded.iter().next(), Some((&key, &value)));
    }

    #[test]
    fn basic_properties_round_trip(props in basic_properties()) {
        let mut buf = BytesMut::new();
        props.encode(&mut buf);
        prop_assert_eq!(BasicProperties::decode(&buf.freeze()).unwrap(), props.clone());
        let header = ContentHeader::new(7, &props);
        prop_assert_eq!(header.properties().unwrap(), props);
    }

    #[test]
    fn methods_round_trip(method in method()) {
        let mut buf = BytesMut::new();
        method.encode(&mut buf);
        prop_assert_eq!(Method::decode(&buf.freeze()).unwrap(), method);
    }

    #[test]
    fn frames_round_trip(frame in frame()) {
        let mut buf = encoded(&frame);
        let decoded = decode_frame(&mut buf, 0).unwrap().unwrap();
        prop_assert!(buf.is_empty());
        prop_assert_eq!(&decoded, &frame);
        if let Frame::Header { header, .. } = &decoded {
            prop_assert!(header.properties().is_ok());
        }
        prop_assert_eq!(parse_frame(encoded(&frame).freeze()).unwrap(), frame);
    }

    // ---- arbitrary bytes never panic ----

    #[test]
    fn decode_frame_never_panics(
        bytes in vec(any::<u8>(), 0..600),
        frame_max in prop_oneof![Just(0u32), Just(8), Just(64), Just(4096), any::<u32>()],
    ) {
        decode_all_and_reencode(BytesMut::from(&bytes[..]), frame_max);
        let _ = parse_frame(Bytes::from(bytes));
    }

    /// Mostly-valid frames: a valid envelope with a random type, channel
    /// and payload, so decoding gets past the envelope checks.
    #[test]
    fn decode_frame_never_panics_on_enveloped_payloads(
        kind in prop_oneof![Just(1u8), Just(2), Just(3), Just(8), any::<u8>()],
        channel in any::<u16>(),
        payload in vec(any::<u8>(), 0..300),
    ) {
        let mut buf = BytesMut::new();
        buf.extend_from_slice(&[kind]);
        buf.extend_from_slice(&channel.to_be_bytes());
        buf.extend_from_slice(&(payload.len() as u32).to_be_bytes());
        buf.extend_from_slice(&payload);
        buf.extend_from_slice(&[0xce]);
        decode_all_and_reencode(buf, 4096);
    }

    #[test]
    fn method_decode_never_panics(bytes in vec(any::<u8>(), 0..300)) {
        let _ = Method::decode(&Bytes::from(bytes));
    }

    /// Known ids with random arguments reach every argument decoder.
    #[test]
    fn method_decode_with_known_ids_never_panics(
        class_id in prop_oneof![Just(10u16), Just(20), Just(30), Just(40), Just(50), Just(60), Just(85), Just(90)],
        method_id in prop_oneof![(1u16..=12).prop_map(|m| m * 10), (1u16..=12).prop_map(|m| m * 10 + 1), Just(72)],
        args in vec(any::<u8>(), 0..200),
    ) {
        let mut payload = class_id.to_be_bytes().to_vec();
        payload.extend_from_slice(&method_id.to_be_bytes());
        payload.extend_from_slice(&args);
        if let Ok(method) = Method::decode(&Bytes::from(payload)) {
            let mut buf = BytesMut::new();
            method.encode(&mut buf);
            let again = Method::decode(&buf.clone().freeze()).unwrap();
            let mut buf2 = BytesMut::new();
            again.encode(&mut buf2);
            prop_assert_eq!(buf, buf2);
        }
    }

    #[test]
    fn properties_decode_never_panics(bytes in vec(any::<u8>(), 0..300)) {
        let bytes = Bytes::from(bytes);
        if let Ok(props) = BasicProperties::decode(&bytes) {
            let mut buf = BytesMut::new();
            props.encode(&mut buf);
            let again = BasicProperties::decode(&buf.clone().freeze()).unwrap();
            let mut buf2 = BytesMut::new();
            again.encode(&mut buf2);
            prop_assert_eq!(buf, buf2);
        }
        let _ = ContentHeader::decode(&bytes).map(|h| h.properties());
        let _ = FieldTable::decode(&bytes);
    }

    /// Valid encodings with a few bytes overwritten: near misses that get
    /// deep into the decoders.
    #[test]
    fn mutated_valid_frames_never_panic(
        frame in frame(),
        edits in vec((any::<usize>(), any::<u8>()), 1..4),
    ) {
        let bytes = mutate(encoded(&frame).to_vec(), &edits);
        decode_all_and_reencode(BytesMut::from(&bytes[..]), 0);
        if let Frame::Header { header, .. } = frame {
            let props = mutate(header.property_bytes.to_vec(), &edits);
            let _ = BasicProperties::decode(&Bytes::from(props));
        }
    }

    // ---- streaming ----

    /// A frame stream fed to decode_frame in arbitrary pieces yields the
    /// same frames as the stream decoded at once, and leaves nothing.
    #[test]
    fn split_stream_yields_the_same_frames(
        frames in vec(frame(), 1..8),
        cuts in vec(any::<prop::sample::Index>(), 0..12),
    ) {
        let mut stream = BytesMut::new();
        for frame in &frames {
            frame.encode(&mut stream);
        }
        let stream = stream.freeze();
        let mut points: Vec<usize> = cuts.iter().map(|i| i.index(stream.len() + 1)).collect();
        points.push(0);
        points.push(stream.len());
        points.sort_unstable();
        points.dedup();

        let mut read_buf = BytesMut::new();
        let mut decoded = Vec::new();
        for piece in points.windows(2) {
            read_buf.extend_from_slice(&stream[piece[0]..piece[1]]);
            while let Some(frame) = decode_frame(&mut read_buf, 0).unwrap() {
                decoded.push(frame);
            }
        }
        prop_assert!(read_buf.is_empty());
        prop_assert_eq!(decoded, frames);
    }
}

/// The method frame helper and Frame::encode write the same bytes.
#[test]
fn encode_method_matches_frame_encode() {
    let method: Method = BasicQos {
        prefetch_size: 0,
        prefetch_count: 10,
        global: false,
    }
    .into();
    let mut a = BytesMut::new();
    encode_method(3, &method, &mut a);
    let b = encoded(&Frame::Method { channel: 3, method });
    assert_eq!(a, b);
}
