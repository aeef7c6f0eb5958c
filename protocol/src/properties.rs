//! Content headers: class, body size, and the basic class's fourteen
//! properties with their flag bits. A [`ContentHeader`] keeps the encoded
//! property bytes as received, so a broker can forward them to consumers
//! without decoding and re-encoding; [`BasicProperties`] is the decoded view.

use crate::error::{DecodeError, SyntaxProblem};
use crate::types::{FieldTable, ShortStr};
use crate::wire::{field_table, in_field, put_field_table, put_short_str, short_str, PResult};
use bytes::{Buf, BufMut, Bytes, BytesMut};
use nom::number::complete::{be_u16, be_u64, be_u8};

/// The properties of the basic class, each optional.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct BasicProperties {
    /// MIME content type.
    pub content_type: Option<ShortStr>,
    /// MIME content encoding.
    pub content_encoding: Option<ShortStr>,
    /// Application headers.
    pub headers: Option<FieldTable>,
    /// 1 = transient, 2 = persistent.
    pub delivery_mode: Option<u8>,
    /// Priority, 0 to 9.
    pub priority: Option<u8>,
    /// Application correlation identifier.
    pub correlation_id: Option<ShortStr>,
    /// Address to reply to.
    pub reply_to: Option<ShortStr>,
    /// Per-message TTL in milliseconds, as a decimal string (RabbitMQ).
    pub expiration: Option<ShortStr>,
    /// Application message identifier.
    pub message_id: Option<ShortStr>,
    /// Message timestamp, seconds since the epoch.
    pub timestamp: Option<u64>,
    /// Message type name (`type` in the spec).
    pub kind: Option<ShortStr>,
    /// Creating user id (RabbitMQ validates it against the connection's user).
    pub user_id: Option<ShortStr>,
    /// Creating application id.
    pub app_id: Option<ShortStr>,
    /// Reserved, must be empty.
    pub cluster_id: Option<ShortStr>,
}

/// Property flag bits, most significant first, in the order properties are
/// written on the wire.
mod flag {
    pub const CONTENT_TYPE: u16 = 1 << 15;
    pub const CONTENT_ENCODING: u16 = 1 << 14;
    pub const HEADERS: u16 = 1 << 13;
    pub const DELIVERY_MODE: u16 = 1 << 12;
    pub const PRIORITY: u16 = 1 << 11;
    pub const CORRELATION_ID: u16 = 1 << 10;
    pub const REPLY_TO: u16 = 1 << 9;
    pub const EXPIRATION: u16 = 1 << 8;
    pub const MESSAGE_ID: u16 = 1 << 7;
    pub const TIMESTAMP: u16 = 1 << 6;
    pub const TYPE: u16 = 1 << 5;
    pub const USER_ID: u16 = 1 << 4;
    pub const APP_ID: u16 = 1 << 3;
    pub const CLUSTER_ID: u16 = 1 << 2;
    /// Bit 0: another flag word follows.
    pub const CONTINUATION: u16 = 1;
    /// Bit 1 is not assigned in the basic class.
    pub const UNUSED: u16 = 1 << 1;
}

impl BasicProperties {
    /// Persistent delivery mode.
    pub const PERSISTENT: u8 = 2;

    /// Whether delivery-mode says persistent.
    pub fn is_persistent(&self) -> bool {
        self.delivery_mode == Some(Self::PERSISTENT)
    }

    /// Encodes the flag word and property list.
    pub fn encode(&self, buf: &mut BytesMut) {
        fn short(buf: &mut BytesMut, flags: &mut u16, bit: u16, value: &Option<ShortStr>) {
            if let Some(v) = value {
                *flags |= bit;
                put_short_str(buf, v);
            }
        }
        fn octet(buf: &mut BytesMut, flags: &mut u16, bit: u16, value: Option<u8>) {
            if let Some(v) = value {
                *flags |= bit;
                buf.put_u8(v);
            }
        }
        let flags_at = buf.len();
        buf.put_u16(0);
        let mut flags = 0u16;
        short(buf, &mut flags, flag::CONTENT_TYPE, &self.content_type);
        short(
            buf,
            &mut flags,
            flag::CONTENT_ENCODING,
            &self.content_encoding,
        );
        if let Some(headers) = &self.headers {
            flags |= flag::HEADERS;
            put_field_table(buf, headers);
        }
        octet(buf, &mut flags, flag::DELIVERY_MODE, self.delivery_mode);
        octet(buf, &mut flags, flag::PRIORITY, self.priority);
        short(buf, &mut flags, flag::CORRELATION_ID, &self.correlation_id);
        short(buf, &mut flags, flag::REPLY_TO, &self.reply_to);
        short(buf, &mut flags, flag::EXPIRATION, &self.expiration);
        short(buf, &mut flags, flag::MESSAGE_ID, &self.message_id);
        if let Some(ts) = self.timestamp {
            flags |= flag::TIMESTAMP;
            buf.put_u64(ts);
        }
        short(buf, &mut flags, flag::TYPE, &self.kind);
        short(buf, &mut flags, flag::USER_ID, &self.user_id);
        short(buf, &mut flags, flag::APP_ID, &self.app_id);
        short(buf, &mut flags, flag::CLUSTER_ID, &self.cluster_id);
        buf[flags_at..flags_at + 2].copy_from_slice(&flags.to_be_bytes());
    }

    /// Decodes a flag word (or several, with continuation) and the
    /// property list from `src`, which must hold exactly that.
    pub fn decode(src: &Bytes) -> Result<BasicProperties, DecodeError> {
        let mut props = BasicProperties::default();
        match parse_properties(src, src, &mut props) {
            Ok(([], ())) => Ok(props),
            Ok((rest, ())) => Err(header_error("", SyntaxProblem::TrailingBytes(rest.len()))),
            Err(nom::Err::Error(e) | nom::Err::Failure(e)) => Err(header_error(e.field, e.problem)),
            Err(nom::Err::Incomplete(_)) => Err(header_error("", SyntaxProblem::Truncated)),
        }
    }
}

fn header_error(field: &'static str, problem: SyntaxProblem) -> DecodeError {
    DecodeError::Syntax {
        location: "content header",
        field,
        problem,
    }
}

/// Parses the flag words and the properties they announce into `props`
/// (which starts out empty), returning what follows them. Properties are
/// written in place rather than returned: `BasicProperties` is a few
/// hundred bytes, and moving it through nom's result tuples cost more than
/// parsing a typical header.
fn parse_properties<'a>(
    src: &Bytes,
    input: &'a [u8],
    props: &mut BasicProperties,
) -> PResult<'a, ()> {
    let (mut input, flags) = in_field(be_u16(input), "property_flags")?;
    // Further flag words may follow; the basic class has no properties in
    // them, so any bit set there (other than continuation) is unknown.
    let mut word = flags;
    while word & flag::CONTINUATION != 0 {
        let (rest, next) = in_field(be_u16(input), "property_flags")?;
        if next & !flag::CONTINUATION != 0 {
            return unknown_property();
        }
        input = rest;
        word = next;
    }
    if flags & flag::UNUSED != 0 {
        return unknown_property();
    }
    // Each present property, in wire order; absent ones cost one test.
    macro_rules! read {
        ($bit:ident, $name:literal, $slot:ident, $parser:expr) => {
            if flags & flag::$bit != 0 {
                let (rest, v) = in_field($parser(input), $name)?;
                props.$slot = Some(v);
                input = rest;
            }
        };
    }
    let short = |input| short_str(src, input);
    read!(CONTENT_TYPE, "content_type", content_type, short);
    read!(
        CONTENT_ENCODING,
        "content_encoding",
        content_encoding,
        short
    );
    read!(HEADERS, "headers", headers, |i| field_table(src, i));
    read!(DELIVERY_MODE, "delivery_mode", delivery_mode, be_u8);
    read!(PRIORITY, "priority", priority, be_u8);
    read!(CORRELATION_ID, "correlation_id", correlation_id, short);
    read!(REPLY_TO, "reply_to", reply_to, short);
    read!(EXPIRATION, "expiration", expiration, short);
    read!(MESSAGE_ID, "message_id", message_id, short);
    read!(TIMESTAMP, "timestamp", timestamp, be_u64);
    read!(TYPE, "type", kind, short);
    read!(USER_ID, "user_id", user_id, short);
    read!(APP_ID, "app_id", app_id, short);
    read!(CLUSTER_ID, "cluster_id", cluster_id, short);
    Ok((input, ()))
}

fn unknown_property<T>() -> PResult<'static, T> {
    Err(nom::Err::Failure(crate::wire::WireError::new(
        SyntaxProblem::UnknownProperty,
    )))
}

/// A content header frame's payload: class, body size, and the encoded
/// property flags and list, kept as received.
#[derive(Debug, Clone, PartialEq)]
pub struct ContentHeader {
    /// The content class (60 for basic).
    pub class_id: u16,
    /// Total size of the body frames that follow.
    pub body_size: u64,
    /// Encoded property flags and property list.
    pub property_bytes: Bytes,
}

impl ContentHeader {
    /// The basic class id, the only content class in AMQP 0.9.1.
    pub const BASIC_CLASS: u16 = 60;

    /// A basic-class header with `properties` encoded.
    pub fn new(body_size: u64, properties: &BasicProperties) -> Self {
        let mut buf = BytesMut::with_capacity(16);
        properties.encode(&mut buf);
        ContentHeader {
            class_id: Self::BASIC_CLASS,
            body_size,
            property_bytes: buf.freeze(),
        }
    }

    /// Decodes the properties.
    pub fn properties(&self) -> Result<BasicProperties, DecodeError> {
        BasicProperties::decode(&self.property_bytes)
    }

    /// Decodes a header frame's payload. Only the class, weight and size
    /// are read here; properties are checked by [`ContentHeader::properties`].
    pub fn decode(payload: &Bytes) -> Result<ContentHeader, DecodeError> {
        Self::decode_owned(payload.clone())
    }

    /// [`ContentHeader::decode`] taking the payload by value, so the
    /// property bytes are the payload itself, advanced past the fixed part.
    pub(crate) fn decode_owned(mut payload: Bytes) -> Result<ContentHeader, DecodeError> {
        if payload.len() < 14 {
            return Err(header_error("body_size", SyntaxProblem::Truncated));
        }
        let class_id = u16::from_be_bytes([payload[0], payload[1]]);
        let mut size = [0u8; 8];
        size.copy_from_slice(&payload[4..12]);
        payload.advance(12);
        Ok(ContentHeader {
            class_id,
            body_size: u64::from_be_bytes(size),
            property_bytes: payload,
        })
    }

    /// Encodes the header frame's payload (class, weight 0, size, properties).
    pub fn encode(&self, buf: &mut BytesMut) {
        buf.put_u16(self.class_id);
        buf.put_u16(0);
        buf.put_u64(self.body_size);
        buf.put_slice(&self.property_bytes);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::types::FieldValue;

    #[test]
    fn no_properties_is_a_zero_flag_word() {
        let header = ContentHeader::new(5, &BasicProperties::default());
        let mut buf = BytesMut::new();
        header.encode(&mut buf);
        assert_eq!(
            &buf[..],
            b"\x00\x3c\x00\x00\x00\x00\x00\x00\x00\x00\x00\x05\x00\x00"
        );
    }

    #[test]
    fn delivery_mode_and_content_type_vector() {
        let props = BasicProperties {
            content_type: Some(ShortStr::from_static("text/plain")),
            delivery_mode: Some(2),
            ..Default::default()
        };
        let mut buf = BytesMut::new();
        props.encode(&mut buf);
        assert_eq!(&buf[..], b"\x90\x00\x0atext/plain\x02");
        assert_eq!(BasicProperties::decode(&buf.freeze()).unwrap(), props);
    }

    #[test]
    fn all_fourteen_properties_round_trip_in_wire_order() {
        let s = |v: &'static str| Some(ShortStr::from_static(v));
        let mut headers = FieldTable::new();
        headers.insert(ShortStr::from_static("k"), FieldValue::I32(1));
        let props = BasicProperties {
            content_type: s("a"),
            content_encoding: s("b"),
            headers: Some(headers),
            delivery_mode: Some(1),
            priority: Some(9),
            correlation_id: s("c"),
            reply_to: s("d"),
            expiration: s("60000"),
            message_id: s("e"),
            timestamp: Some(0x0102_0304_0506_0708),
            kind: s("f"),
            user_id: s("g"),
            app_id: s("h"),
            cluster_id: s("i"),
        };
        let mut buf = BytesMut::new();
        props.encode(&mut buf);
        let expected: &[u8] = b"\xff\xfc\x01a\x01b\x00\x00\x00\x07\x01kI\x00\x00\x00\x01\x01\x09\
            \x01c\x01d\x0560000\x01e\x01\x02\x03\x04\x05\x06\x07\x08\x01f\x01g\x01h\x01i";
        assert_eq!(&buf[..], expected);
        assert_eq!(BasicProperties::decode(&buf.freeze()).unwrap(), props);
    }

    #[test]
    fn unknown_property_bit_is_refused() {
        let err = BasicProperties::decode(&Bytes::from_static(b"\x00\x02")).unwrap_err();
        assert!(matches!(
            err,
            DecodeError::Syntax {
                problem: SyntaxProblem::UnknownProperty,
                ..
            }
        ));
    }

    #[test]
    fn continuation_word_with_no_bits_is_accepted() {
        let props = BasicProperties::decode(&Bytes::from_static(b"\x10\x01\x00\x00\x02")).unwrap();
        assert_eq!(props.delivery_mode, Some(2));
    }

    #[test]
    fn truncated_property_names_its_field() {
        let err = BasicProperties::decode(&Bytes::from_static(b"\x80\x00\x05ab")).unwrap_err();
        assert_eq!(
            err,
            DecodeError::Syntax {
                location: "content header",
                field: "content_type",
                problem: SyntaxProblem::Truncated
            }
        );
    }

    #[test]
    fn short_header_payload_is_truncated() {
        assert!(ContentHeader::decode(&Bytes::from_static(b"\x00\x3c\x00\x00")).is_err());
    }
}
