//! Malformed input: every kind of broken frame or payload comes back as an
//! exact `DecodeError`, with the reply code the connection must be closed
//! with, and never as a panic.

use bytes::{Bytes, BytesMut};
use leveret_protocol::{
    check_frame, decode_frame, parse_frame, BasicProperties, ContentHeader, DecodeError,
    ErrorScope, FieldTable, Frame, FrameCheck, Method, ReplyCode, SyntaxProblem,
};

/// Wraps a payload in a frame envelope by hand.
fn frame(kind: u8, channel: u16, payload: &[u8]) -> BytesMut {
    let mut buf = BytesMut::new();
    buf.extend_from_slice(&[kind]);
    buf.extend_from_slice(&channel.to_be_bytes());
    buf.extend_from_slice(&(payload.len() as u32).to_be_bytes());
    buf.extend_from_slice(payload);
    buf.extend_from_slice(&[0xce]);
    buf
}

fn decode_one(mut buf: BytesMut) -> Result<Frame, DecodeError> {
    decode_frame(&mut buf, 4096).map(|f| f.expect("a whole frame is buffered"))
}

fn syntax(location: &'static str, field: &'static str, problem: SyntaxProblem) -> DecodeError {
    DecodeError::Syntax {
        location,
        field,
        problem,
    }
}

// ---- frame envelope ----

#[test]
fn bad_frame_end() {
    let mut buf = frame(
        1,
        1,
        b"\x00\x3c\x00\x50\x00\x00\x00\x00\x00\x00\x00\x01\x00",
    );
    let last = buf.len() - 1;
    buf[last] = 0x00;
    let err = decode_one(buf).unwrap_err();
    assert_eq!(err, DecodeError::BadFrameEnd { found: 0x00 });
    assert_eq!(err.reply_code(), ReplyCode::FrameError);
    assert_eq!(err.reply_code().code(), 501);
    assert_eq!(err.reply_code().scope(), ErrorScope::Connection);
    assert_eq!(err.method_ids(), (0, 0));
    assert_eq!(err.to_string(), "frame end octet is 0x00, expected 0xce");
}

#[test]
fn bad_frame_end_on_a_heartbeat() {
    let err = decode_one(BytesMut::from(&b"\x08\x00\x00\x00\x00\x00\x00\xcd"[..])).unwrap_err();
    assert_eq!(err, DecodeError::BadFrameEnd { found: 0xcd });
}

#[test]
fn oversize_frame_is_refused_from_the_seven_byte_header() {
    // Declares 4097 payload bytes, one over frame_max 4096.
    let mut buf = BytesMut::from(&b"\x03\x00\x01\x00\x00\x10\x01"[..]);
    let err = decode_frame(&mut buf, 4096).unwrap_err();
    assert_eq!(
        err,
        DecodeError::FrameTooLarge {
            size: 4097,
            frame_max: 4096
        }
    );
    assert_eq!(err.reply_code(), ReplyCode::FrameError);
    assert_eq!(
        err.to_string(),
        "frame payload of 4097 bytes exceeds frame_max of 4096 bytes"
    );
    // Nothing was consumed.
    assert_eq!(buf.len(), 7);
}

#[test]
fn payload_of_frame_max_passes_and_one_more_does_not() {
    // RabbitMQ 3.10 compares the payload alone with frame_max, tolerating
    // the 8 envelope octets; so does the codec.
    let fits = frame(3, 1, &[0u8; 4096]);
    assert_eq!(fits.len(), 4104);
    assert_eq!(
        check_frame(&fits, 4096).unwrap(),
        FrameCheck::Complete { len: 4104 }
    );
    let over = frame(3, 1, &[0u8; 4097]);
    assert_eq!(
        check_frame(&over, 4096).unwrap_err(),
        DecodeError::FrameTooLarge {
            size: 4097,
            frame_max: 4096
        }
    );
    // frame_max 0 means no limit.
    assert!(decode_frame(&mut over.clone(), 0).unwrap().is_some());
}

#[test]
fn largest_declared_size_without_a_limit_waits_for_its_payload() {
    assert_eq!(
        check_frame(b"\x03\x00\x01\xff\xff\xff\xff", 0).unwrap(),
        FrameCheck::Incomplete {
            needed: u32::MAX as usize + 1
        }
    );
}

#[test]
fn unknown_frame_type() {
    let err = decode_one(frame(4, 1, b"")).unwrap_err();
    assert_eq!(err, DecodeError::UnknownFrameType(4));
    assert_eq!(err.reply_code(), ReplyCode::FrameError);
}

#[test]
fn heartbeat_with_payload() {
    let err = decode_one(frame(8, 0, b"\x00\x00")).unwrap_err();
    assert_eq!(
        err,
        DecodeError::BadHeartbeat {
            channel: 0,
            size: 2
        }
    );
    assert_eq!(err.reply_code(), ReplyCode::FrameError);
}

#[test]
fn heartbeat_on_a_channel() {
    let err = decode_one(frame(8, 3, b"")).unwrap_err();
    assert_eq!(
        err,
        DecodeError::BadHeartbeat {
            channel: 3,
            size: 0
        }
    );
    // RabbitMQ 3.10 answers a heartbeat on a channel with 505.
    assert_eq!(err.reply_code(), ReplyCode::UnexpectedFrame);
}

#[test]
fn parse_frame_on_a_cut_frame_is_truncated_not_a_panic() {
    let whole = frame(3, 1, b"abc").freeze();
    for cut in 0..whole.len() {
        assert_eq!(
            parse_frame(whole.slice(..cut)).unwrap_err(),
            syntax("frame", "", SyntaxProblem::Truncated),
            "cut at {cut}"
        );
    }
}

// ---- method payloads ----

#[test]
fn method_frame_shorter_than_its_ids() {
    let err = decode_one(frame(1, 1, b"\x00\x3c\x00")).unwrap_err();
    assert_eq!(
        err,
        syntax("method frame", "class_id", SyntaxProblem::Truncated)
    );
    assert_eq!(err.reply_code(), ReplyCode::FrameError);
}

#[test]
fn truncated_argument_names_method_and_field() {
    // basic.publish whose routing-key says 10 bytes but has 4.
    let err = decode_one(frame(1, 1, b"\x00\x3c\x00\x28\x00\x00\x04logs\x0ainfo")).unwrap_err();
    assert_eq!(
        err,
        syntax("basic.publish", "routing_key", SyntaxProblem::Truncated)
    );
    // RabbitMQ 3.10 closes with 501 and the method's ids for arguments it
    // cannot decode.
    assert_eq!(err.reply_code().code(), 501);
    assert_eq!(err.method_ids(), (60, 40));
    assert_eq!(
        err.to_string(),
        "malformed basic.publish.routing_key: truncated"
    );
}

#[test]
fn missing_bit_octet_names_the_first_bit() {
    // basic.publish with no octet for mandatory/immediate.
    let err = decode_one(frame(1, 1, b"\x00\x3c\x00\x28\x00\x00\x04logs\x04info")).unwrap_err();
    assert_eq!(
        err,
        syntax("basic.publish", "mandatory", SyntaxProblem::Truncated)
    );
}

#[test]
fn truncated_integer_argument() {
    // basic.ack with a 7-byte delivery tag.
    let err = Method::decode(&Bytes::from_static(
        b"\x00\x3c\x00\x50\x00\x00\x00\x00\x00\x00\x01",
    ))
    .unwrap_err();
    assert_eq!(
        err,
        syntax("basic.ack", "delivery_tag", SyntaxProblem::Truncated)
    );
}

#[test]
fn unknown_method_in_a_known_class() {
    let err = decode_one(frame(1, 1, b"\x00\x3c\x00\x29")).unwrap_err();
    assert_eq!(
        err,
        DecodeError::UnknownMethod {
            class_id: 60,
            method_id: 41
        }
    );
    assert_eq!(err.reply_code(), ReplyCode::CommandInvalid);
    assert_eq!(err.reply_code().code(), 503);
    assert_eq!(err.method_ids(), (60, 41));
    assert_eq!(err.to_string(), "unknown method 60.41");
}

#[test]
fn unknown_class() {
    let err = Method::decode(&Bytes::from_static(b"\x00\x63\x00\x0a\x01\x02")).unwrap_err();
    assert_eq!(
        err,
        DecodeError::UnknownMethod {
            class_id: 99,
            method_id: 10
        }
    );
    assert_eq!(err.reply_code().code(), 503);
}

#[test]
fn bad_table_tag_in_arguments() {
    // queue.declare with arguments {"k": 'Q' ...}: 'Q' is no type tag.
    let err = decode_one(frame(
        1,
        1,
        b"\x00\x32\x00\x0a\x00\x00\x01q\x00\x00\x00\x00\x04\x01kQ\x00",
    ))
    .unwrap_err();
    assert_eq!(
        err,
        syntax(
            "queue.declare",
            "arguments",
            SyntaxProblem::BadFieldTag(b'Q')
        )
    );
    assert_eq!(err.reply_code(), ReplyCode::FrameError);
    assert_eq!(
        err.to_string(),
        "malformed queue.declare.arguments: unknown field type tag 0x51"
    );
}

#[test]
fn bad_tag_deep_inside_a_nested_table() {
    // basic.consume arguments {"a": F{"b": A['Z']}}.
    let err = Method::decode(&Bytes::from_static(
        b"\x00\x3c\x00\x14\x00\x00\x01q\x00\x00\
          \x00\x00\x00\x0f\x01aF\x00\x00\x00\x08\x01bA\x00\x00\x00\x01Z",
    ))
    .unwrap_err();
    assert_eq!(
        err,
        syntax(
            "basic.consume",
            "arguments",
            SyntaxProblem::BadFieldTag(b'Z')
        )
    );
}

#[test]
fn shortstr_longer_than_its_frame() {
    // basic.consume whose queue name claims 200 bytes; the frame is fine.
    let err = decode_one(frame(1, 1, b"\x00\x3c\x00\x14\x00\x00\xc8tasks")).unwrap_err();
    assert_eq!(
        err,
        syntax("basic.consume", "queue", SyntaxProblem::Truncated)
    );
}

#[test]
fn longstr_longer_than_its_frame() {
    // connection.start-ok whose response claims 4 GiB.
    let err = decode_one(frame(
        1,
        0,
        b"\x00\x0a\x00\x0b\x00\x00\x00\x00\x05PLAIN\xff\xff\xff\xff\x00guest",
    ))
    .unwrap_err();
    assert_eq!(
        err,
        syntax("connection.start-ok", "response", SyntaxProblem::Truncated)
    );
}

#[test]
fn table_longer_than_its_frame() {
    let err = decode_one(frame(
        1,
        1,
        b"\x00\x32\x00\x0a\x00\x00\x01q\x00\x00\x00\x01\x00\x01kV",
    ))
    .unwrap_err();
    assert_eq!(
        err,
        syntax("queue.declare", "arguments", SyntaxProblem::Truncated)
    );
}

#[test]
fn string_inside_a_table_longer_than_the_table() {
    // The table says 8 bytes; its long string says 5 but only 1 fits.
    let err = Method::decode(&Bytes::from_static(
        b"\x00\x32\x00\x0a\x00\x00\x01q\x00\x00\x00\x00\x08\x01kS\x00\x00\x00\x05a\
          bcde",
    ))
    .unwrap_err();
    assert_eq!(
        err,
        syntax("queue.declare", "arguments", SyntaxProblem::Truncated)
    );
}

#[test]
fn trailing_bytes_after_last_argument() {
    let err = decode_one(frame(
        1,
        1,
        b"\x00\x3c\x00\x50\x00\x00\x00\x00\x00\x00\x00\x01\x00\xaa\xbb",
    ))
    .unwrap_err();
    assert_eq!(
        err,
        syntax("basic.ack", "", SyntaxProblem::TrailingBytes(2))
    );
    assert_eq!(err.reply_code(), ReplyCode::FrameError);
    assert_eq!(err.to_string(), "malformed basic.ack: 2 trailing bytes");
}

#[test]
fn trailing_bytes_after_a_method_without_arguments() {
    let err = Method::decode(&Bytes::from_static(b"\x00\x5a\x00\x0a\x00")).unwrap_err();
    assert_eq!(
        err,
        syntax("tx.select", "", SyntaxProblem::TrailingBytes(1))
    );
}

#[test]
fn nesting_past_the_limit_is_invalid() {
    // 40 arrays inside each other: each is 'A' + u32 length.
    let mut inner: Vec<u8> = b"V".to_vec();
    for _ in 0..40 {
        let mut outer = b"A".to_vec();
        outer.extend_from_slice(&(inner.len() as u32).to_be_bytes());
        outer.extend_from_slice(&inner);
        inner = outer;
    }
    let mut value = b"\x01k".to_vec();
    value.extend_from_slice(&inner);
    let mut table = (value.len() as u32).to_be_bytes().to_vec();
    table.extend_from_slice(&value);
    let err = FieldTable::decode(&Bytes::from(table)).unwrap_err();
    assert_eq!(err, syntax("field table", "", SyntaxProblem::InvalidValue));
}

// ---- content headers ----

#[test]
fn header_frame_shorter_than_class_weight_and_size() {
    let err = decode_one(frame(
        2,
        1,
        b"\x00\x3c\x00\x00\x00\x00\x00\x00\x00\x00\x00\x10",
    ))
    .unwrap_err();
    assert_eq!(
        err,
        syntax("content header", "body_size", SyntaxProblem::Truncated)
    );
    assert_eq!(err.reply_code(), ReplyCode::FrameError);
}

#[test]
fn unknown_property_flag() {
    // Bit 1 is not a basic property.
    let header = ContentHeader::decode(&Bytes::from_static(
        b"\x00\x3c\x00\x00\x00\x00\x00\x00\x00\x00\x00\x00\x00\x02",
    ))
    .unwrap();
    assert_eq!(
        header.properties().unwrap_err(),
        syntax("content header", "", SyntaxProblem::UnknownProperty)
    );
    // A continuation word with any property bit in it.
    assert_eq!(
        BasicProperties::decode(&Bytes::from_static(b"\x00\x01\x80\x00")).unwrap_err(),
        syntax("content header", "", SyntaxProblem::UnknownProperty)
    );
}

#[test]
fn property_longer_than_the_header() {
    // content-type claims 10 bytes, has 4.
    let err = BasicProperties::decode(&Bytes::from_static(b"\x80\x00\x0atext")).unwrap_err();
    assert_eq!(
        err,
        syntax("content header", "content_type", SyntaxProblem::Truncated)
    );
    // headers table claims more than there is.
    let err = BasicProperties::decode(&Bytes::from_static(b"\x20\x00\x00\x00\x00\x09\x01kV"))
        .unwrap_err();
    assert_eq!(
        err,
        syntax("content header", "headers", SyntaxProblem::Truncated)
    );
    // timestamp cut short.
    let err =
        BasicProperties::decode(&Bytes::from_static(b"\x00\x40\x00\x00\x00\x01")).unwrap_err();
    assert_eq!(
        err,
        syntax("content header", "timestamp", SyntaxProblem::Truncated)
    );
}

#[test]
fn bad_tag_in_headers_property() {
    let err = BasicProperties::decode(&Bytes::from_static(b"\x20\x00\x00\x00\x00\x03\x01k?"))
        .unwrap_err();
    assert_eq!(
        err,
        syntax(
            "content header",
            "headers",
            SyntaxProblem::BadFieldTag(b'?')
        )
    );
}

#[test]
fn trailing_bytes_after_properties() {
    let err = BasicProperties::decode(&Bytes::from_static(b"\x10\x00\x02\x00")).unwrap_err();
    assert_eq!(
        err,
        syntax("content header", "", SyntaxProblem::TrailingBytes(1))
    );
}

#[test]
fn missing_flag_word() {
    let err = BasicProperties::decode(&Bytes::from_static(b"\x10")).unwrap_err();
    assert_eq!(
        err,
        syntax("content header", "property_flags", SyntaxProblem::Truncated)
    );
}

// ---- streaming ----

#[test]
fn an_error_in_one_frame_does_not_hide_the_frame_before_it() {
    let mut buf = frame(3, 1, b"ok");
    buf.extend_from_slice(&frame(1, 1, b"\x00\x3c\x00\x29"));
    assert_eq!(
        decode_frame(&mut buf, 4096).unwrap(),
        Some(Frame::Body {
            channel: 1,
            payload: Bytes::from_static(b"ok")
        })
    );
    assert_eq!(
        decode_frame(&mut buf, 4096).unwrap_err(),
        DecodeError::UnknownMethod {
            class_id: 60,
            method_id: 41
        }
    );
}

#[test]
fn incomplete_frame_waits_whatever_its_contents() {
    // A frame with a bad end octet is not judged before it is all there.
    let whole = frame(1, 1, b"\x00\x5a\x00\x0a");
    for cut in 0..whole.len() {
        let mut buf = BytesMut::from(&whole[..cut]);
        assert_eq!(decode_frame(&mut buf, 4096).unwrap(), None, "cut at {cut}");
        assert_eq!(buf.len(), cut);
    }
}
