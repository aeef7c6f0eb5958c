//! Byte-literal vectors for every method in the table, checked by hand
//! against the AMQP 0.9.1 wire format (RabbitMQ's amqp0-9-1 spec with its
//! extensions): class id and method id as big-endian shorts, then the
//! arguments in order; consecutive bits share octets, low bit first;
//! shortstr = octet length + bytes, longstr = long length + bytes, table =
//! long byte length + (shortstr name, tag, value)*.

use super::*;
use crate::frame::{decode_frame, encode_content, encode_header, encode_method, Frame};
use crate::properties::{BasicProperties, ContentHeader};
use crate::types::FieldValue;
use std::collections::BTreeSet;

fn s(v: &'static str) -> ShortStr {
    ShortStr::from_static(v)
}

fn l(v: &'static [u8]) -> LongStr {
    Bytes::from_static(v)
}

fn table(entries: Vec<(&'static str, FieldValue)>) -> FieldTable {
    entries.into_iter().map(|(k, v)| (s(k), v)).collect()
}

/// Every method in the table, with its expected payload.
fn vectors() -> Vec<(Method, &'static [u8])> {
    vec![
        // ---- connection (10) ----
        (
            ConnectionStart {
                version_major: 0,
                version_minor: 9,
                server_properties: table(vec![("product", FieldValue::string("leveret"))]),
                mechanisms: l(b"PLAIN AMQPLAIN"),
                locales: l(b"en_US"),
            }
            .into(),
            b"\x00\x0a\x00\x0a\x00\x09\
              \x00\x00\x00\x14\x07productS\x00\x00\x00\x07leveret\
              \x00\x00\x00\x0ePLAIN AMQPLAIN\
              \x00\x00\x00\x05en_US",
        ),
        (
            ConnectionStartOk {
                client_properties: table(vec![(
                    "capabilities",
                    FieldValue::Table(table(vec![("publisher_confirms", FieldValue::Bool(true))])),
                )]),
                mechanism: s("PLAIN"),
                response: l(b"\0guest\0guest"),
                locale: s("en_US"),
            }
            .into(),
            b"\x00\x0a\x00\x0b\
              \x00\x00\x00\x27\x0ccapabilitiesF\x00\x00\x00\x15\x12publisher_confirmst\x01\
              \x05PLAIN\
              \x00\x00\x00\x0c\x00guest\x00guest\
              \x05en_US",
        ),
        (
            ConnectionSecure {
                challenge: l(b"chal"),
            }
            .into(),
            b"\x00\x0a\x00\x14\x00\x00\x00\x04chal",
        ),
        (
            ConnectionSecureOk {
                response: l(b"resp"),
            }
            .into(),
            b"\x00\x0a\x00\x15\x00\x00\x00\x04resp",
        ),
        (
            ConnectionTune {
                channel_max: 2047,
                frame_max: 131_072,
                heartbeat: 60,
            }
            .into(),
            b"\x00\x0a\x00\x1e\x07\xff\x00\x02\x00\x00\x00\x3c",
        ),
        (
            ConnectionTuneOk {
                channel_max: 0x0102,
                frame_max: 4096,
                heartbeat: 0,
            }
            .into(),
            b"\x00\x0a\x00\x1f\x01\x02\x00\x00\x10\x00\x00\x00",
        ),
        (
            ConnectionOpen {
                virtual_host: s("/"),
                capabilities: s(""),
                insist: true,
            }
            .into(),
            b"\x00\x0a\x00\x28\x01/\x00\x01",
        ),
        (
            ConnectionOpenOk { known_hosts: s("") }.into(),
            b"\x00\x0a\x00\x29\x00",
        ),
        (
            ConnectionClose {
                reply_code: 320,
                reply_text: s("bye"),
                class_id: 60,
                method_id: 40,
            }
            .into(),
            b"\x00\x0a\x00\x32\x01\x40\x03bye\x00\x3c\x00\x28",
        ),
        (ConnectionCloseOk {}.into(), b"\x00\x0a\x00\x33"),
        (
            ConnectionBlocked {
                reason: s("low on memory"),
            }
            .into(),
            b"\x00\x0a\x00\x3c\x0dlow on memory",
        ),
        (ConnectionUnblocked {}.into(), b"\x00\x0a\x00\x3d"),
        (
            ConnectionUpdateSecret {
                new_secret: l(b"tok"),
                reason: s("refresh"),
            }
            .into(),
            b"\x00\x0a\x00\x46\x00\x00\x00\x03tok\x07refresh",
        ),
        (ConnectionUpdateSecretOk {}.into(), b"\x00\x0a\x00\x47"),
        // ---- channel (20) ----
        (
            ChannelOpen { out_of_band: s("") }.into(),
            b"\x00\x14\x00\x0a\x00",
        ),
        (
            ChannelOpenOk { channel_id: l(b"") }.into(),
            b"\x00\x14\x00\x0b\x00\x00\x00\x00",
        ),
        (ChannelFlow { active: true }.into(), b"\x00\x14\x00\x14\x01"),
        (
            ChannelFlowOk { active: false }.into(),
            b"\x00\x14\x00\x15\x00",
        ),
        (
            ChannelClose {
                reply_code: 404,
                reply_text: s("NOT_FOUND"),
                class_id: 50,
                method_id: 10,
            }
            .into(),
            b"\x00\x14\x00\x28\x01\x94\x09NOT_FOUND\x00\x32\x00\x0a",
        ),
        (ChannelCloseOk {}.into(), b"\x00\x14\x00\x29"),
        // ---- access (30) ----
        (
            // Bits: exclusive=0 passive=1 active=1 write=0 read=1 -> 0b1_0110.
            AccessRequest {
                realm: s("/data"),
                exclusive: false,
                passive: true,
                active: true,
                write: false,
                read: true,
            }
            .into(),
            b"\x00\x1e\x00\x0a\x05/data\x16",
        ),
        (
            AccessRequestOk { ticket: 1 }.into(),
            b"\x00\x1e\x00\x0b\x00\x01",
        ),
        // ---- exchange (40) ----
        (
            // Bits: passive=0 durable=1 auto_delete=0 internal=1 no_wait=0 -> 0b0_1010.
            ExchangeDeclare {
                ticket: 0,
                exchange: s("logs"),
                kind: s("topic"),
                passive: false,
                durable: true,
                auto_delete: false,
                internal: true,
                no_wait: false,
                arguments: table(vec![("alternate-exchange", FieldValue::string("ae"))]),
            }
            .into(),
            b"\x00\x28\x00\x0a\x00\x00\x04logs\x05topic\x0a\
              \x00\x00\x00\x1a\x12alternate-exchangeS\x00\x00\x00\x02ae",
        ),
        (ExchangeDeclareOk {}.into(), b"\x00\x28\x00\x0b"),
        (
            ExchangeDelete {
                ticket: 0,
                exchange: s("logs"),
                if_unused: true,
                no_wait: true,
            }
            .into(),
            b"\x00\x28\x00\x14\x00\x00\x04logs\x03",
        ),
        (ExchangeDeleteOk {}.into(), b"\x00\x28\x00\x15"),
        (
            ExchangeBind {
                ticket: 0,
                destination: s("dst"),
                source: s("src"),
                routing_key: s("a.#"),
                no_wait: false,
                arguments: FieldTable::new(),
            }
            .into(),
            b"\x00\x28\x00\x1e\x00\x00\x03dst\x03src\x03a.#\x00\x00\x00\x00\x00",
        ),
        (ExchangeBindOk {}.into(), b"\x00\x28\x00\x1f"),
        (
            ExchangeUnbind {
                ticket: 0,
                destination: s("dst"),
                source: s("src"),
                routing_key: s(""),
                no_wait: true,
                arguments: table(vec![("k", FieldValue::Void)]),
            }
            .into(),
            b"\x00\x28\x00\x28\x00\x00\x03dst\x03src\x00\x01\x00\x00\x00\x03\x01kV",
        ),
        (ExchangeUnbindOk {}.into(), b"\x00\x28\x00\x33"),
        // ---- queue (50) ----
        (
            // Bits: passive=0 durable=1 exclusive=0 auto_delete=0 no_wait=0.
            QueueDeclare {
                ticket: 0,
                queue: s("tasks"),
                passive: false,
                durable: true,
                exclusive: false,
                auto_delete: false,
                no_wait: false,
                arguments: table(vec![
                    ("x-message-ttl", FieldValue::I32(60_000)),
                    ("x-queue-type", FieldValue::string("quorum")),
                ]),
            }
            .into(),
            b"\x00\x32\x00\x0a\x00\x00\x05tasks\x02\
              \x00\x00\x00\x2b\
              \x0dx-message-ttlI\x00\x00\xea\x60\
              \x0cx-queue-typeS\x00\x00\x00\x06quorum",
        ),
        (
            QueueDeclareOk {
                queue: s("amq.gen-1"),
                message_count: 3,
                consumer_count: 0x0102_0304,
            }
            .into(),
            b"\x00\x32\x00\x0b\x09amq.gen-1\x00\x00\x00\x03\x01\x02\x03\x04",
        ),
        (
            QueueBind {
                ticket: 0,
                queue: s("tasks"),
                exchange: s("logs"),
                routing_key: s("info"),
                no_wait: true,
                arguments: FieldTable::new(),
            }
            .into(),
            b"\x00\x32\x00\x14\x00\x00\x05tasks\x04logs\x04info\x01\x00\x00\x00\x00",
        ),
        (QueueBindOk {}.into(), b"\x00\x32\x00\x15"),
        (
            QueuePurge {
                ticket: 0,
                queue: s("tasks"),
                no_wait: false,
            }
            .into(),
            b"\x00\x32\x00\x1e\x00\x00\x05tasks\x00",
        ),
        (
            QueuePurgeOk { message_count: 42 }.into(),
            b"\x00\x32\x00\x1f\x00\x00\x00\x2a",
        ),
        (
            // Bits: if_unused=0 if_empty=1 no_wait=1 -> 0b110.
            QueueDelete {
                ticket: 0,
                queue: s("tasks"),
                if_unused: false,
                if_empty: true,
                no_wait: true,
            }
            .into(),
            b"\x00\x32\x00\x28\x00\x00\x05tasks\x06",
        ),
        (
            QueueDeleteOk { message_count: 7 }.into(),
            b"\x00\x32\x00\x29\x00\x00\x00\x07",
        ),
        (
            QueueUnbind {
                ticket: 0,
                queue: s("tasks"),
                exchange: s("logs"),
                routing_key: s("info"),
                arguments: table(vec![("b", FieldValue::Bool(true))]),
            }
            .into(),
            b"\x00\x32\x00\x32\x00\x00\x05tasks\x04logs\x04info\x00\x00\x00\x04\x01bt\x01",
        ),
        (QueueUnbindOk {}.into(), b"\x00\x32\x00\x33"),
        // ---- basic (60) ----
        (
            BasicQos {
                prefetch_size: 0,
                prefetch_count: 100,
                global: true,
            }
            .into(),
            b"\x00\x3c\x00\x0a\x00\x00\x00\x00\x00\x64\x01",
        ),
        (BasicQosOk {}.into(), b"\x00\x3c\x00\x0b"),
        (
            // Bits: no_local=0 no_ack=1 exclusive=1 no_wait=0 -> 0b0110.
            BasicConsume {
                ticket: 0,
                queue: s("tasks"),
                consumer_tag: s("ctag-1"),
                no_local: false,
                no_ack: true,
                exclusive: true,
                no_wait: false,
                arguments: table(vec![("x-priority", FieldValue::I32(5))]),
            }
            .into(),
            b"\x00\x3c\x00\x14\x00\x00\x05tasks\x06ctag-1\x06\
              \x00\x00\x00\x10\x0ax-priorityI\x00\x00\x00\x05",
        ),
        (
            BasicConsumeOk {
                consumer_tag: s("ctag-1"),
            }
            .into(),
            b"\x00\x3c\x00\x15\x06ctag-1",
        ),
        (
            BasicCancel {
                consumer_tag: s("ctag-1"),
                no_wait: true,
            }
            .into(),
            b"\x00\x3c\x00\x1e\x06ctag-1\x01",
        ),
        (
            BasicCancelOk {
                consumer_tag: s("ctag-1"),
            }
            .into(),
            b"\x00\x3c\x00\x1f\x06ctag-1",
        ),
        (
            BasicPublish {
                ticket: 0,
                exchange: s("logs"),
                routing_key: s("info"),
                mandatory: true,
                immediate: false,
            }
            .into(),
            b"\x00\x3c\x00\x28\x00\x00\x04logs\x04info\x01",
        ),
        (
            BasicReturn {
                reply_code: 312,
                reply_text: s("NO_ROUTE"),
                exchange: s("logs"),
                routing_key: s("none"),
            }
            .into(),
            b"\x00\x3c\x00\x32\x01\x38\x08NO_ROUTE\x04logs\x04none",
        ),
        (
            BasicDeliver {
                consumer_tag: s("ctag-1"),
                delivery_tag: 0x0102_0304_0506_0708,
                redelivered: true,
                exchange: s(""),
                routing_key: s("tasks"),
            }
            .into(),
            b"\x00\x3c\x00\x3c\x06ctag-1\x01\x02\x03\x04\x05\x06\x07\x08\x01\x00\x05tasks",
        ),
        (
            BasicGet {
                ticket: 0,
                queue: s("tasks"),
                no_ack: true,
            }
            .into(),
            b"\x00\x3c\x00\x46\x00\x00\x05tasks\x01",
        ),
        (
            BasicGetOk {
                delivery_tag: 9,
                redelivered: false,
                exchange: s("logs"),
                routing_key: s("info"),
                message_count: 2,
            }
            .into(),
            b"\x00\x3c\x00\x47\x00\x00\x00\x00\x00\x00\x00\x09\x00\x04logs\x04info\x00\x00\x00\x02",
        ),
        (
            BasicGetEmpty { cluster_id: s("") }.into(),
            b"\x00\x3c\x00\x48\x00",
        ),
        (
            BasicAck {
                delivery_tag: 5,
                multiple: true,
            }
            .into(),
            b"\x00\x3c\x00\x50\x00\x00\x00\x00\x00\x00\x00\x05\x01",
        ),
        (
            BasicReject {
                delivery_tag: u64::MAX,
                requeue: false,
            }
            .into(),
            b"\x00\x3c\x00\x5a\xff\xff\xff\xff\xff\xff\xff\xff\x00",
        ),
        (
            BasicRecoverAsync { requeue: true }.into(),
            b"\x00\x3c\x00\x64\x01",
        ),
        (
            BasicRecover { requeue: false }.into(),
            b"\x00\x3c\x00\x6e\x00",
        ),
        (BasicRecoverOk {}.into(), b"\x00\x3c\x00\x6f"),
        (
            // Bits: multiple=0 requeue=1 -> 0b10.
            BasicNack {
                delivery_tag: 3,
                multiple: false,
                requeue: true,
            }
            .into(),
            b"\x00\x3c\x00\x78\x00\x00\x00\x00\x00\x00\x00\x03\x02",
        ),
        // ---- confirm (85) ----
        (
            ConfirmSelect { no_wait: false }.into(),
            b"\x00\x55\x00\x0a\x00",
        ),
        (ConfirmSelectOk {}.into(), b"\x00\x55\x00\x0b"),
        // ---- tx (90) ----
        (TxSelect {}.into(), b"\x00\x5a\x00\x0a"),
        (TxSelectOk {}.into(), b"\x00\x5a\x00\x0b"),
        (TxCommit {}.into(), b"\x00\x5a\x00\x14"),
        (TxCommitOk {}.into(), b"\x00\x5a\x00\x15"),
        (TxRollback {}.into(), b"\x00\x5a\x00\x1e"),
        (TxRollbackOk {}.into(), b"\x00\x5a\x00\x1f"),
    ]
}

fn encode(method: &Method) -> BytesMut {
    let mut buf = BytesMut::new();
    method.encode(&mut buf);
    buf
}

#[test]
fn every_vector_encodes_to_its_bytes() {
    for (method, wire) in vectors() {
        assert_eq!(
            &encode(&method)[..],
            wire,
            "encoding {} does not match its vector",
            method.name()
        );
    }
}

#[test]
fn every_vector_decodes_to_its_method() {
    for (method, wire) in vectors() {
        let decoded = Method::decode(&Bytes::from_static(wire))
            .unwrap_or_else(|e| panic!("{} vector does not decode: {e}", method.name()));
        assert_eq!(decoded, method, "decoding the {} vector", method.name());
    }
}

#[test]
fn vector_ids_match_the_payload_and_the_name() {
    for (method, wire) in vectors() {
        let class_id = u16::from_be_bytes([wire[0], wire[1]]);
        let method_id = u16::from_be_bytes([wire[2], wire[3]]);
        assert_eq!(
            (method.class_id(), method.method_id()),
            (class_id, method_id)
        );
        assert_eq!(Method::name_of(class_id, method_id), Some(method.name()));
    }
}

/// The vectors cover the whole table: every (class, method) pair the
/// table knows has exactly one vector, so a method added to the table
/// without a vector fails here.
#[test]
fn vectors_cover_every_method_in_the_table() {
    let mut table_ids = BTreeSet::new();
    for class_id in 0..=200u16 {
        for method_id in 0..=200u16 {
            if Method::name_of(class_id, method_id).is_some() {
                table_ids.insert((class_id, method_id));
            }
        }
    }
    let vectors = vectors();
    let vector_ids: BTreeSet<_> = vectors
        .iter()
        .map(|(m, _)| (m.class_id(), m.method_id()))
        .collect();
    assert_eq!(vector_ids.len(), vectors.len(), "a method has two vectors");
    assert_eq!(vector_ids, table_ids);
    assert_eq!(table_ids.len(), 66);
}

/// The spec's (and RabbitMQ's) ids for the extensions and the oddities.
#[test]
fn extension_and_odd_ids() {
    let ids = |m: Method| (m.class_id(), m.method_id(), m.name());
    assert_eq!(
        ids(ExchangeUnbindOk {}.into()),
        (40, 51, "exchange.unbind-ok")
    );
    assert_eq!(ids(BasicNack::default().into()), (60, 120, "basic.nack"));
    assert_eq!(
        ids(ConfirmSelect::default().into()),
        (85, 10, "confirm.select")
    );
    assert_eq!(
        ids(ConnectionBlocked::default().into()),
        (10, 60, "connection.blocked")
    );
    assert_eq!(
        ids(ConnectionUpdateSecret::default().into()),
        (10, 70, "connection.update-secret")
    );
    assert_eq!(
        ids(BasicRecoverAsync::default().into()),
        (60, 100, "basic.recover-async")
    );
    assert_eq!(Method::name_of(40, 41), None);
}

#[test]
fn only_publish_return_deliver_and_get_ok_carry_content() {
    let with_content: Vec<&str> = vectors()
        .iter()
        .filter(|(m, _)| m.has_content())
        .map(|(m, _)| m.name())
        .collect();
    assert_eq!(
        with_content,
        [
            "basic.publish",
            "basic.return",
            "basic.deliver",
            "basic.get-ok"
        ]
    );
}

/// Each bit of a five-bit method lands in its own position, low bit first.
#[test]
fn exchange_declare_bits_each_in_place() {
    let base = ExchangeDeclare {
        exchange: s("x"),
        kind: s("direct"),
        ..Default::default()
    };
    type SetBit = fn(&mut ExchangeDeclare);
    let cases: [(SetBit, u8); 5] = [
        (|m| m.passive = true, 0x01),
        (|m| m.durable = true, 0x02),
        (|m| m.auto_delete = true, 0x04),
        (|m| m.internal = true, 0x08),
        (|m| m.no_wait = true, 0x10),
    ];
    for (set, bit) in cases {
        let mut m = base.clone();
        set(&mut m);
        let wire = encode(&m.clone().into());
        let mut expected = b"\x00\x28\x00\x0a\x00\x00\x01x\x06direct".to_vec();
        expected.push(bit);
        expected.extend_from_slice(b"\x00\x00\x00\x00");
        assert_eq!(&wire[..], &expected[..]);
        assert_eq!(Method::decode(&wire.freeze()).unwrap(), m.into());
    }
}

#[test]
fn nack_bit_combinations() {
    for (multiple, requeue, octet) in [
        (false, false, 0u8),
        (true, false, 1),
        (false, true, 2),
        (true, true, 3),
    ] {
        let m: Method = BasicNack {
            delivery_tag: 1,
            multiple,
            requeue,
        }
        .into();
        let mut expected = b"\x00\x3c\x00\x78\x00\x00\x00\x00\x00\x00\x00\x01".to_vec();
        expected.push(octet);
        assert_eq!(&encode(&m)[..], &expected[..]);
        assert_eq!(Method::decode(&Bytes::from(expected)).unwrap(), m);
    }
}

/// Every proper prefix of every vector (past the ids) is a syntax error
/// that names the method, and points at a field when there are args.
#[test]
fn every_truncated_vector_names_its_method() {
    for (method, wire) in vectors() {
        for cut in 4..wire.len() {
            let err = Method::decode(&Bytes::copy_from_slice(&wire[..cut])).unwrap_err();
            match err {
                DecodeError::Syntax {
                    location,
                    field,
                    problem: SyntaxProblem::Truncated,
                } => {
                    assert_eq!(location, method.name());
                    assert!(
                        !field.is_empty(),
                        "{} cut at {cut}: no field",
                        method.name()
                    );
                }
                other => panic!("{} cut at {cut}: {other:?}", method.name()),
            }
            assert_eq!(err.reply_code(), crate::ReplyCode::FrameError);
        }
        for cut in 0..4.min(wire.len()) {
            assert!(matches!(
                Method::decode(&Bytes::copy_from_slice(&wire[..cut])),
                Err(DecodeError::Syntax {
                    location: "method frame",
                    problem: SyntaxProblem::Truncated,
                    ..
                })
            ));
        }
    }
}

/// One byte past the last argument is TrailingBytes(1), for every method.
#[test]
fn every_vector_with_a_trailing_byte_is_refused() {
    for (method, wire) in vectors() {
        let mut long = wire.to_vec();
        long.push(0);
        assert_eq!(
            Method::decode(&Bytes::from(long)).unwrap_err(),
            DecodeError::Syntax {
                location: method.name(),
                field: "",
                problem: SyntaxProblem::TrailingBytes(1),
            }
        );
    }
}

// ---- full frames: basic.publish + content header + body ----

const PUBLISH_TRIPLE: &[u8] = b"\
    \x01\x00\x01\x00\x00\x00\x11\
        \x00\x3c\x00\x28\x00\x00\x04logs\x04info\x00\
    \xce\
    \x02\x00\x01\x00\x00\x00\x1a\
        \x00\x3c\x00\x00\x00\x00\x00\x00\x00\x00\x00\x10\
        \x90\x00\x0atext/plain\x02\
    \xce\
    \x03\x00\x01\x00\x00\x00\x10\
        0123456789abcdef\
    \xce";

fn publish() -> BasicPublish {
    BasicPublish {
        ticket: 0,
        exchange: s("logs"),
        routing_key: s("info"),
        mandatory: false,
        immediate: false,
    }
}

fn publish_properties() -> BasicProperties {
    BasicProperties {
        content_type: Some(s("text/plain")),
        delivery_mode: Some(2),
        ..Default::default()
    }
}

#[test]
fn publish_triple_encodes_to_its_frames() {
    let mut buf = BytesMut::new();
    encode_method(1, &publish().into(), &mut buf);
    encode_header(1, &ContentHeader::new(16, &publish_properties()), &mut buf);
    Frame::Body {
        channel: 1,
        payload: Bytes::from_static(b"0123456789abcdef"),
    }
    .encode(&mut buf);
    assert_eq!(&buf[..], PUBLISH_TRIPLE);

    // encode_content writes the same header and body frames.
    let mut props = BytesMut::new();
    publish_properties().encode(&mut props);
    let mut via_content = BytesMut::new();
    encode_method(1, &publish().into(), &mut via_content);
    encode_content(1, 60, &props, b"0123456789abcdef", 4096, &mut via_content);
    assert_eq!(&via_content[..], PUBLISH_TRIPLE);
}

#[test]
fn publish_triple_decodes_to_its_frames() {
    let mut buf = BytesMut::from(PUBLISH_TRIPLE);
    let method = decode_frame(&mut buf, 4096).unwrap().unwrap();
    assert_eq!(
        method,
        Frame::Method {
            channel: 1,
            method: publish().into()
        }
    );
    let header = match decode_frame(&mut buf, 4096).unwrap().unwrap() {
        Frame::Header { channel: 1, header } => header,
        other => panic!("expected a header on channel 1, got {other:?}"),
    };
    assert_eq!(header.class_id, 60);
    assert_eq!(header.body_size, 16);
    assert_eq!(&header.property_bytes[..], b"\x90\x00\x0atext/plain\x02");
    assert_eq!(header.properties().unwrap(), publish_properties());
    assert_eq!(
        decode_frame(&mut buf, 4096).unwrap(),
        Some(Frame::Body {
            channel: 1,
            payload: Bytes::from_static(b"0123456789abcdef")
        })
    );
    assert!(buf.is_empty());
    assert_eq!(decode_frame(&mut buf, 4096).unwrap(), None);
}

#[test]
fn content_body_is_split_by_frame_max() {
    // frame_max 20 leaves 12 payload bytes per body frame: 12 + 4.
    let mut buf = BytesMut::new();
    encode_content(7, 60, b"\x00\x00", b"0123456789abcdef", 20, &mut buf);
    assert_eq!(
        &buf[..],
        b"\x02\x00\x07\x00\x00\x00\x0e\
          \x00\x3c\x00\x00\x00\x00\x00\x00\x00\x00\x00\x10\x00\x00\xce\
          \x03\x00\x07\x00\x00\x00\x0c0123456789ab\xce\
          \x03\x00\x07\x00\x00\x00\x04cdef\xce"
    );
}
