//! Wire primitives: nom parsers for MQTT's data representations (1.5: two
//! and four byte integers, variable byte integers, UTF-8 strings, binary
//! data) over a fully buffered packet, and their encoders.
//!
//! Encoders write to a [`Sink`]: a packet is written once to a [`Counter`]
//! to learn its remaining length and check every rule, then to the
//! `BytesMut`, so one function per packet does both and a packet that
//! breaks a rule leaves the buffer untouched.

use crate::error::Problem;
use crate::string::MqttString;
use bytes::{BufMut, Bytes, BytesMut};
use nom::bytes::complete::take;
use nom::number::complete::be_u16;

/// A failure inside a packet, with the field it happened in.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) struct Fault {
    pub(crate) problem: Problem,
    pub(crate) field: &'static str,
}

impl Fault {
    pub(crate) fn new(problem: Problem, field: &'static str) -> Self {
        Fault { problem, field }
    }
}

impl<'a> nom::error::ParseError<&'a [u8]> for Fault {
    fn from_error_kind(_input: &'a [u8], _kind: nom::error::ErrorKind) -> Self {
        Fault::new(Problem::Truncated, "")
    }

    fn append(_input: &'a [u8], _kind: nom::error::ErrorKind, other: Self) -> Self {
        other
    }
}

pub(crate) type PResult<'a, T> = nom::IResult<&'a [u8], T, Fault>;

/// Fails with `problem`.
pub(crate) fn fail<'a, T>(problem: Problem) -> PResult<'a, T> {
    Err(nom::Err::Failure(Fault::new(problem, "")))
}

/// Names the field that failed in an error coming out of `result`, unless
/// an inner parser already did.
pub(crate) fn in_field<'a, T>(result: PResult<'a, T>, field: &'static str) -> PResult<'a, T> {
    result.map_err(|e| {
        e.map(|mut f| {
            if f.field.is_empty() {
                f.field = field;
            }
            f
        })
    })
}

/// The largest variable byte integer: four bytes of seven bits.
pub(crate) const VBI_MAX: u32 = 268_435_455;

/// Reads a variable byte integer from the start of `input`: its value and
/// length, `None` if `input` ends first, or why it is malformed (a fifth
/// byte, or a longer form than the value needs: MQTT-1.5.5-1).
pub(crate) fn read_vbi(input: &[u8]) -> Result<Option<(u32, usize)>, Problem> {
    let mut value = 0u32;
    for (i, &byte) in input.iter().take(4).enumerate() {
        value |= u32::from(byte & 0x7f) << (7 * i);
        if byte & 0x80 == 0 {
            if byte == 0 && i > 0 {
                return Err(Problem::NonMinimalInteger);
            }
            return Ok(Some((value, i + 1)));
        }
    }
    if input.len() >= 4 {
        Err(Problem::IntegerTooLong)
    } else {
        Ok(None)
    }
}

/// A variable byte integer inside a buffered packet.
pub(crate) fn vbi(input: &[u8]) -> PResult<'_, u32> {
    match read_vbi(input) {
        Ok(Some((value, len))) => Ok((&input[len..], value)),
        Ok(None) => fail(Problem::Truncated),
        Err(problem) => fail(problem),
    }
}

/// Binary data: a two-byte length and that many bytes, as a slice.
pub(crate) fn binary_slice(input: &[u8]) -> PResult<'_, &[u8]> {
    let (input, len) = be_u16(input)?;
    take(len)(input)
}

/// Binary data as a handle into the packet, `src`.
pub(crate) fn binary<'a>(src: &Bytes, input: &'a [u8]) -> PResult<'a, Bytes> {
    let (rest, bytes) = binary_slice(input)?;
    Ok((rest, src.slice_ref(bytes)))
}

/// A UTF-8 encoded string as a handle into the packet, `src`.
pub(crate) fn string<'a>(src: &Bytes, input: &'a [u8]) -> PResult<'a, MqttString> {
    let (rest, bytes) = binary_slice(input)?;
    match MqttString::from_utf8(src.slice_ref(bytes)) {
        Ok(s) => Ok((rest, s)),
        Err(e) => fail(match e {
            crate::string::StringError::NullCharacter => Problem::NullCharacter,
            _ => Problem::InvalidUtf8,
        }),
    }
}

/// Where an encoder writes: a buffer, or a [`Counter`] of bytes.
pub(crate) trait Sink {
    fn put(&mut self, bytes: &[u8]);
}

impl Sink for BytesMut {
    fn put(&mut self, bytes: &[u8]) {
        self.put_slice(bytes);
    }
}

/// Counts the bytes written to it.
#[derive(Default)]
pub(crate) struct Counter(pub(crate) usize);

impl Sink for Counter {
    fn put(&mut self, bytes: &[u8]) {
        self.0 += bytes.len();
    }
}

pub(crate) fn put_u8(s: &mut impl Sink, v: u8) {
    s.put(&[v]);
}

pub(crate) fn put_u16(s: &mut impl Sink, v: u16) {
    s.put(&v.to_be_bytes());
}

pub(crate) fn put_u32(s: &mut impl Sink, v: u32) {
    s.put(&v.to_be_bytes());
}

/// Writes a variable byte integer; callers keep `v` within [`VBI_MAX`].
pub(crate) fn put_vbi(s: &mut impl Sink, v: u32) {
    debug_assert!(v <= VBI_MAX);
    let mut v = v;
    let mut out = [0u8; 4];
    let mut len = 0;
    loop {
        let mut byte = (v % 128) as u8;
        v /= 128;
        if v > 0 {
            byte |= 0x80;
        }
        out[len] = byte;
        len += 1;
        if v == 0 || len == 4 {
            break;
        }
    }
    s.put(&out[..len]);
}

/// The number of bytes a variable byte integer takes.
pub(crate) fn vbi_len(v: usize) -> usize {
    match v {
        0..=127 => 1,
        128..=16_383 => 2,
        16_384..=2_097_151 => 3,
        _ => 4,
    }
}

pub(crate) fn put_string(s: &mut impl Sink, v: &MqttString) {
    // MqttString's constructors keep it within 65,535 bytes.
    put_u16(s, v.len() as u16);
    s.put(v.as_bytes());
}

/// Writes binary data, refusing more than 65,535 bytes.
pub(crate) fn put_binary(s: &mut impl Sink, v: &[u8], field: &'static str) -> Result<(), Fault> {
    let len = u16::try_from(v.len()).map_err(|_| Fault::new(Problem::TooLong(v.len()), field))?;
    put_u16(s, len);
    s.put(v);
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn encode(v: u32) -> Vec<u8> {
        let mut buf = BytesMut::new();
        put_vbi(&mut buf, v);
        buf.to_vec()
    }

    #[test]
    fn vbi_spec_table() {
        // MQTT 5.0 1.5.5 (3.1.1 2.2.3): the boundaries of each length.
        let table: [(u32, &[u8]); 8] = [
            (0, &[0x00]),
            (127, &[0x7F]),
            (128, &[0x80, 0x01]),
            (16_383, &[0xFF, 0x7F]),
            (16_384, &[0x80, 0x80, 0x01]),
            (2_097_151, &[0xFF, 0xFF, 0x7F]),
            (2_097_152, &[0x80, 0x80, 0x80, 0x01]),
            (268_435_455, &[0xFF, 0xFF, 0xFF, 0x7F]),
        ];
        for (value, bytes) in table {
            assert_eq!(encode(value), bytes, "{value}");
            assert_eq!(read_vbi(bytes), Ok(Some((value, bytes.len()))));
            assert_eq!(vbi_len(value as usize), bytes.len());
        }
    }

    #[test]
    fn vbi_malformed_and_incomplete() {
        assert_eq!(read_vbi(&[]), Ok(None));
        assert_eq!(read_vbi(&[0x80]), Ok(None));
        assert_eq!(read_vbi(&[0xFF, 0xFF, 0xFF]), Ok(None));
        assert_eq!(
            read_vbi(&[0xFF, 0xFF, 0xFF, 0xFF]),
            Err(Problem::IntegerTooLong)
        );
        assert_eq!(read_vbi(&[0x80, 0x00]), Err(Problem::NonMinimalInteger));
        assert_eq!(
            read_vbi(&[0xFF, 0x80, 0x00]),
            Err(Problem::NonMinimalInteger)
        );
        assert_eq!(read_vbi(&[0x05, 0xFF]), Ok(Some((5, 1))));
    }
}
