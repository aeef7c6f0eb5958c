//! The frame envelope (type, channel, size, payload, frame-end 0xCE), the
//! protocol header, streaming frame decoding from a read buffer, and frame
//! encoding into a write buffer, including splitting a body by `frame_max`.

use crate::error::DecodeError;
use crate::method::Method;
use crate::properties::ContentHeader;
use bytes::{Buf, BufMut, Bytes, BytesMut};
use nom::bytes::complete::{tag, take};
use nom::number::complete::{be_u16, be_u32, be_u8};

/// The protocol header a 0.9.1 client sends first.
pub const PROTOCOL_HEADER: &[u8; 8] = b"AMQP\x00\x00\x09\x01";

/// Octets of envelope around a payload: type, channel, size, frame-end.
pub const FRAME_OVERHEAD: usize = 8;

/// The smallest frame_max a peer may negotiate (spec: frame-min-size).
pub const FRAME_MIN_SIZE: u32 = 4096;

/// The frame-end octet.
pub const FRAME_END: u8 = 0xCE;

const FRAME_METHOD: u8 = 1;
const FRAME_HEADER: u8 = 2;
const FRAME_BODY: u8 = 3;
const FRAME_HEARTBEAT: u8 = 8;

/// What the first bytes of a connection say.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ProtocolHeaderCheck {
    /// Fewer than 8 bytes so far, and they match so far.
    Incomplete,
    /// `AMQP 0 0 9 1`.
    Valid,
    /// Anything else: the server answers with its own header and closes.
    Invalid,
}

/// The header of AMQP 0-9 (class 1, instance 1, version 0-9), which
/// RabbitMQ answers with the 0-9-1 protocol, as the wire formats agree.
pub const LEGACY_0_9_HEADER: &[u8; 8] = b"AMQP\x01\x01\x00\x09";

/// Checks the protocol header at the start of `buf`: 0-9-1, or the legacy
/// 0-9 header that RabbitMQ also serves as 0-9-1.
pub fn check_protocol_header(buf: &[u8]) -> ProtocolHeaderCheck {
    let n = buf.len().min(PROTOCOL_HEADER.len());
    let matches = |header: &[u8; 8]| buf[..n] == header[..n];
    if !matches(PROTOCOL_HEADER) && !matches(LEGACY_0_9_HEADER) {
        ProtocolHeaderCheck::Invalid
    } else if n < PROTOCOL_HEADER.len() {
        ProtocolHeaderCheck::Incomplete
    } else {
        ProtocolHeaderCheck::Valid
    }
}

/// One AMQP frame.
#[derive(Debug, Clone, PartialEq)]
pub enum Frame {
    /// A method frame.
    Method {
        /// Channel number (0 for connection methods).
        channel: u16,
        /// The method.
        method: Method,
    },
    /// A content header frame.
    Header {
        /// Channel number.
        channel: u16,
        /// Class, body size, properties.
        header: ContentHeader,
    },
    /// A content body frame.
    Body {
        /// Channel number.
        channel: u16,
        /// A piece of the body.
        payload: Bytes,
    },
    /// A heartbeat (always channel 0).
    Heartbeat,
}

impl Frame {
    /// The channel this frame belongs to.
    pub fn channel(&self) -> u16 {
        match self {
            Frame::Method { channel, .. }
            | Frame::Header { channel, .. }
            | Frame::Body { channel, .. } => *channel,
            Frame::Heartbeat => 0,
        }
    }

    /// Encodes the frame, envelope included.
    pub fn encode(&self, buf: &mut BytesMut) {
        match self {
            Frame::Method { channel, method } => encode_method(*channel, method, buf),
            Frame::Header { channel, header } => encode_header(*channel, header, buf),
            Frame::Body { channel, payload } => {
                encode_envelope(FRAME_BODY, *channel, buf, |b| b.put_slice(payload))
            }
            Frame::Heartbeat => buf.put_slice(&[FRAME_HEARTBEAT, 0, 0, 0, 0, 0, 0, FRAME_END]),
        }
    }
}

/// How much of a frame a buffer holds.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum FrameCheck {
    /// At least `needed` more bytes are required.
    Incomplete {
        /// Bytes missing (a lower bound while the header itself is incomplete).
        needed: usize,
    },
    /// A whole frame of `len` bytes (envelope included) is at the front.
    Complete {
        /// The whole frame's length.
        len: usize,
    },
}

fn limit(frame_max: u32) -> u64 {
    if frame_max == 0 {
        u64::from(u32::MAX)
    } else {
        u64::from(frame_max)
    }
}

/// Checks whether `buf` starts with a whole frame, without decoding it.
/// The declared payload size is checked against `frame_max` (0 = no
/// limit) as soon as the 7-byte header is in, before any payload is
/// buffered. Like RabbitMQ, the check leaves out the 8 envelope octets, so
/// a client that counts frame_max as payload size is still served; frames
/// this crate encodes always fit frame_max whole.
pub fn check_frame(buf: &[u8], frame_max: u32) -> Result<FrameCheck, DecodeError> {
    if buf.len() < 7 {
        return Ok(FrameCheck::Incomplete {
            needed: FRAME_OVERHEAD - buf.len(),
        });
    }
    let size = u32::from_be_bytes([buf[3], buf[4], buf[5], buf[6]]);
    if u64::from(size) > limit(frame_max) {
        return Err(DecodeError::FrameTooLarge {
            size: u64::from(size),
            frame_max,
        });
    }
    let total = u64::from(size) + FRAME_OVERHEAD as u64;
    // Bounded by frame_max (a u32), so it fits in usize.
    let total = total as usize;
    if buf.len() < total {
        Ok(FrameCheck::Incomplete {
            needed: total - buf.len(),
        })
    } else {
        Ok(FrameCheck::Complete { len: total })
    }
}

/// Takes one frame off the front of `buf` if it holds a whole one.
/// `Ok(None)` means more bytes are needed; payloads become `Bytes` slices
/// of the buffer, so bodies are never copied. A frame that fails to decode
/// has still been taken off the buffer.
pub fn decode_frame(buf: &mut BytesMut, frame_max: u32) -> Result<Option<Frame>, DecodeError> {
    let len = match check_frame(buf, frame_max)? {
        FrameCheck::Incomplete { .. } => return Ok(None),
        FrameCheck::Complete { len } => len,
    };
    // check_frame saw the 7-byte header and the whole frame is buffered.
    let kind = buf[0];
    let channel = u16::from_be_bytes([buf[1], buf[2]]);
    let end = buf[len - 1];
    // The frame's handle is narrowed to its payload in place (Bytes'
    // advance and truncate touch no reference count).
    let mut payload = buf.split_to(len).freeze();
    if end != FRAME_END {
        return Err(DecodeError::BadFrameEnd { found: end });
    }
    payload.advance(7);
    payload.truncate(len - FRAME_OVERHEAD);
    decode_payload(kind, channel, payload, Some)
}

/// Parses exactly one whole frame (as found by [`check_frame`]).
pub fn parse_frame(frame: Bytes) -> Result<Frame, DecodeError> {
    let (kind, channel, payload, end) = match envelope(&frame) {
        Ok((_, parts)) => parts,
        Err(_) => {
            return Err(DecodeError::Syntax {
                location: "frame",
                field: "",
                problem: crate::error::SyntaxProblem::Truncated,
            })
        }
    };
    if let Some(found) = end {
        return Err(DecodeError::BadFrameEnd { found });
    }
    let payload = frame.slice_ref(payload);
    decode_payload(kind, channel, payload, |frame| frame)
}

/// Decodes a frame's payload by its type. The frame is handed to `wrap`
/// as it is built, so that decode_frame's `Some(frame)` is constructed in
/// place rather than copied (a frame is over a hundred bytes).
#[inline]
fn decode_payload<T>(
    kind: u8,
    channel: u16,
    payload: Bytes,
    wrap: impl FnOnce(Frame) -> T,
) -> Result<T, DecodeError> {
    match kind {
        FRAME_METHOD => Ok(wrap(Frame::Method {
            channel,
            method: Method::decode(&payload)?,
        })),
        FRAME_HEADER => Ok(wrap(Frame::Header {
            channel,
            header: ContentHeader::decode_owned(payload)?,
        })),
        FRAME_BODY => Ok(wrap(Frame::Body { channel, payload })),
        FRAME_HEARTBEAT if channel == 0 && payload.is_empty() => Ok(wrap(Frame::Heartbeat)),
        FRAME_HEARTBEAT => Err(DecodeError::BadHeartbeat {
            channel,
            size: payload.len() as u32,
        }),
        other => Err(DecodeError::UnknownFrameType(other)),
    }
}

/// A frame's type, channel, payload, and its frame-end octet if that is wrong.
type Envelope<'a> = (u8, u16, &'a [u8], Option<u8>);

/// Splits a frame into type, channel, payload, and the wrong frame-end
/// octet if there is one.
fn envelope(input: &[u8]) -> nom::IResult<&[u8], Envelope<'_>> {
    let (input, kind) = be_u8(input)?;
    let (input, channel) = be_u16(input)?;
    let (input, size) = be_u32(input)?;
    let (input, payload) = take(size)(input)?;
    let end: nom::IResult<&[u8], &[u8]> = tag(&[FRAME_END][..])(input);
    match end {
        Ok((rest, _)) => Ok((rest, (kind, channel, payload, None))),
        Err(_) => {
            let (rest, found) = be_u8(input)?;
            Ok((rest, (kind, channel, payload, Some(found))))
        }
    }
}

/// Writes type, channel and a size placeholder, lets `payload` write the
/// payload, then patches the size and appends frame-end.
fn encode_envelope(
    kind: u8,
    channel: u16,
    buf: &mut BytesMut,
    payload: impl FnOnce(&mut BytesMut),
) {
    buf.put_u8(kind);
    buf.put_u16(channel);
    let size_at = buf.len();
    buf.put_u32(0);
    payload(buf);
    let size = (buf.len() - size_at - 4) as u32;
    buf[size_at..size_at + 4].copy_from_slice(&size.to_be_bytes());
    buf.put_u8(FRAME_END);
}

/// Encodes a method frame.
pub fn encode_method(channel: u16, method: &Method, buf: &mut BytesMut) {
    encode_envelope(FRAME_METHOD, channel, buf, |b| method.encode(b));
}

/// Encodes a content header frame.
pub fn encode_header(channel: u16, header: &ContentHeader, buf: &mut BytesMut) {
    encode_envelope(FRAME_HEADER, channel, buf, |b| header.encode(b));
}

/// Encodes a content header and the body frames that carry `body`, each at
/// most `frame_max` bytes long (0 = no limit). An empty body has no body
/// frames. The header's `body_size` is written as `body.len()`.
pub fn encode_content(
    channel: u16,
    class_id: u16,
    property_bytes: &[u8],
    body: &[u8],
    frame_max: u32,
    buf: &mut BytesMut,
) {
    encode_envelope(FRAME_HEADER, channel, buf, |b| {
        b.put_u16(class_id);
        b.put_u16(0);
        b.put_u64(body.len() as u64);
        b.put_slice(property_bytes);
    });
    let chunk = (limit(frame_max) as usize)
        .saturating_sub(FRAME_OVERHEAD)
        .max(1);
    buf.reserve(body.len() + body.len().div_ceil(chunk) * FRAME_OVERHEAD);
    for piece in body.chunks(chunk) {
        encode_envelope(FRAME_BODY, channel, buf, |b| b.put_slice(piece));
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn protocol_header_checks() {
        assert_eq!(
            check_protocol_header(b"AMQ"),
            ProtocolHeaderCheck::Incomplete
        );
        assert_eq!(
            check_protocol_header(b"AMQP\x00\x00\x09\x01"),
            ProtocolHeaderCheck::Valid
        );
        assert_eq!(
            check_protocol_header(b"AMQP\x01\x01\x00\x09"),
            ProtocolHeaderCheck::Valid
        );
        assert_eq!(
            check_protocol_header(b"AMQP\x01\x01\x08\x00"),
            ProtocolHeaderCheck::Invalid
        );
        assert_eq!(
            check_protocol_header(b"AMQP\x00\x00\x09\x02"),
            ProtocolHeaderCheck::Invalid
        );
        assert_eq!(
            check_protocol_header(b"GET / HTTP/1.1"),
            ProtocolHeaderCheck::Invalid
        );
        assert_eq!(check_protocol_header(b""), ProtocolHeaderCheck::Incomplete);
    }

    #[test]
    fn heartbeat_vector() {
        let mut buf = BytesMut::new();
        Frame::Heartbeat.encode(&mut buf);
        assert_eq!(&buf[..], b"\x08\x00\x00\x00\x00\x00\x00\xce");
        assert_eq!(
            decode_frame(&mut buf, 4096).unwrap(),
            Some(Frame::Heartbeat)
        );
        assert!(buf.is_empty());
    }

    #[test]
    fn body_frame_vector() {
        let mut buf = BytesMut::from(&b"\x03\x00\x05\x00\x00\x00\x03abc\xce\x08"[..]);
        let frame = decode_frame(&mut buf, 4096).unwrap().unwrap();
        assert_eq!(
            frame,
            Frame::Body {
                channel: 5,
                payload: Bytes::from_static(b"abc")
            }
        );
        assert_eq!(&buf[..], b"\x08");
    }

    #[test]
    fn partial_buffer_says_how_much_is_missing() {
        let whole = b"\x03\x00\x01\x00\x00\x00\x04abcd\xce";
        assert_eq!(
            check_frame(&whole[..3], 4096).unwrap(),
            FrameCheck::Incomplete { needed: 5 }
        );
        assert_eq!(
            check_frame(&whole[..9], 4096).unwrap(),
            FrameCheck::Incomplete { needed: 3 }
        );
        assert_eq!(
            check_frame(whole, 4096).unwrap(),
            FrameCheck::Complete { len: 12 }
        );
        let mut buf = BytesMut::from(&whole[..11]);
        assert_eq!(decode_frame(&mut buf, 4096).unwrap(), None);
        assert_eq!(buf.len(), 11);
    }

    #[test]
    fn oversize_frame_refused_from_its_header_alone() {
        let err = check_frame(b"\x03\x00\x01\x00\x00\x10\x01", 4096).unwrap_err();
        assert_eq!(
            err,
            DecodeError::FrameTooLarge {
                size: 4097,
                frame_max: 4096
            }
        );
        assert_eq!(err.reply_code(), crate::ReplyCode::FrameError);
    }

    #[test]
    fn frame_exactly_frame_max_is_accepted() {
        let mut frame = BytesMut::new();
        encode_envelope(FRAME_BODY, 1, &mut frame, |b| b.put_bytes(7, 4088));
        assert_eq!(frame.len(), 4096);
        assert!(decode_frame(&mut frame, 4096).unwrap().is_some());
    }

    #[test]
    fn bad_frame_end_is_reported() {
        let mut buf = BytesMut::from(&b"\x03\x00\x01\x00\x00\x00\x01a\xcf"[..]);
        assert_eq!(
            decode_frame(&mut buf, 4096).unwrap_err(),
            DecodeError::BadFrameEnd { found: 0xcf }
        );
    }

    #[test]
    fn unknown_frame_type_is_reported() {
        let mut buf = BytesMut::from(&b"\x09\x00\x00\x00\x00\x00\x00\xce"[..]);
        assert_eq!(
            decode_frame(&mut buf, 4096).unwrap_err(),
            DecodeError::UnknownFrameType(9)
        );
    }

    #[test]
    fn heartbeat_on_a_channel_is_a_frame_error() {
        let mut buf = BytesMut::from(&b"\x08\x00\x02\x00\x00\x00\x00\xce"[..]);
        let err = decode_frame(&mut buf, 4096).unwrap_err();
        assert_eq!(
            err,
            DecodeError::BadHeartbeat {
                channel: 2,
                size: 0
            }
        );
    }

    #[test]
    fn content_splits_body_by_frame_max() {
        let body = vec![0xabu8; 10_000];
        let mut buf = BytesMut::new();
        encode_content(1, 60, b"\x00\x00", &body, 4096, &mut buf);
        let mut frames = Vec::new();
        while let Some(frame) = decode_frame(&mut buf, 4096).unwrap() {
            frames.push(frame);
        }
        assert_eq!(frames.len(), 4);
        let mut total = 0;
        for frame in &frames[1..] {
            match frame {
                Frame::Body { payload, .. } => {
                    assert!(payload.len() <= 4088);
                    total += payload.len();
                }
                other => panic!("expected body, got {other:?}"),
            }
        }
        assert_eq!(total, 10_000);
        match &frames[0] {
            Frame::Header { header, .. } => assert_eq!(header.body_size, 10_000),
            other => panic!("expected header, got {other:?}"),
        }
    }

    #[test]
    fn empty_body_has_no_body_frame() {
        let mut buf = BytesMut::new();
        encode_content(1, 60, b"\x00\x00", b"", 4096, &mut buf);
        assert!(matches!(
            decode_frame(&mut buf, 4096).unwrap(),
            Some(Frame::Header { .. })
        ));
        assert!(buf.is_empty());
    }
}
