//! Wire primitives: nom parsers for AMQP's argument types (integers, bits,
//! short and long strings, field tables and arrays) and their encoders.
//!
//! Parsers work on `&[u8]` slices of a frame payload that is already fully
//! buffered, so they use nom's `complete` parsers; strings are returned as
//! `Bytes` handles into the payload (`Bytes::slice_ref`), without copying.

use crate::error::SyntaxProblem;
use crate::types::{Decimal, FieldArray, FieldTable, FieldValue, LongStr, ShortStr};
use bytes::{BufMut, Bytes, BytesMut};
use nom::bytes::complete::take;
use nom::number::complete::{
    be_f32, be_f64, be_i16, be_i32, be_i64, be_i8, be_u16, be_u32, be_u64, be_u8,
};

/// A parse failure inside a payload, before it is given its location.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) struct WireError {
    pub(crate) problem: SyntaxProblem,
    pub(crate) field: &'static str,
}

impl WireError {
    pub(crate) fn new(problem: SyntaxProblem) -> Self {
        WireError { problem, field: "" }
    }
}

impl<'a> nom::error::ParseError<&'a [u8]> for WireError {
    fn from_error_kind(_input: &'a [u8], _kind: nom::error::ErrorKind) -> Self {
        WireError::new(SyntaxProblem::Truncated)
    }

    fn append(_input: &'a [u8], _kind: nom::error::ErrorKind, other: Self) -> Self {
        other
    }
}

pub(crate) type PResult<'a, T> = nom::IResult<&'a [u8], T, WireError>;

/// Names the field that failed in an error coming out of `result`.
pub(crate) fn in_field<'a, T>(result: PResult<'a, T>, field: &'static str) -> PResult<'a, T> {
    result.map_err(|e| {
        e.map(|mut w| {
            if w.field.is_empty() {
                w.field = field;
            }
            w
        })
    })
}

fn fail<T>(problem: SyntaxProblem) -> PResult<'static, T> {
    Err(nom::Err::Failure(WireError::new(problem)))
}

/// Bit-packing state while decoding a method's arguments: consecutive `bit`
/// arguments share octets, low bit first.
#[derive(Default)]
pub(crate) struct BitReader {
    byte: u8,
    used: u8,
}

impl BitReader {
    fn reset(&mut self) {
        self.used = 0;
    }
}

/// Bit-packing state while encoding a method's arguments.
#[derive(Default)]
pub(crate) struct BitWriter {
    position: usize,
    used: u8,
}

impl BitWriter {
    fn reset(&mut self) {
        self.used = 0;
    }
}

/// A method argument type: how it is read and written, with bit packing.
pub(crate) trait Arg: Sized {
    fn read<'a>(src: &Bytes, input: &'a [u8], bits: &mut BitReader) -> PResult<'a, Self>;
    fn write(&self, buf: &mut BytesMut, bits: &mut BitWriter);
}

impl Arg for bool {
    fn read<'a>(_src: &Bytes, input: &'a [u8], bits: &mut BitReader) -> PResult<'a, Self> {
        let mut input = input;
        if bits.used == 0 || bits.used == 8 {
            let (rest, byte) = be_u8(input)?;
            input = rest;
            bits.byte = byte;
            bits.used = 0;
        }
        let value = bits.byte & (1 << bits.used) != 0;
        bits.used += 1;
        Ok((input, value))
    }

    fn write(&self, buf: &mut BytesMut, bits: &mut BitWriter) {
        if bits.used == 0 || bits.used == 8 {
            bits.position = buf.len();
            bits.used = 0;
            buf.put_u8(0);
        }
        if *self {
            buf[bits.position] |= 1 << bits.used;
        }
        bits.used += 1;
    }
}

macro_rules! numeric_arg {
    ($($ty:ty => $parse:ident, $put:ident;)*) => {$(
        impl Arg for $ty {
            fn read<'a>(_src: &Bytes, input: &'a [u8], bits: &mut BitReader) -> PResult<'a, Self> {
                bits.reset();
                $parse(input)
            }
            fn write(&self, buf: &mut BytesMut, bits: &mut BitWriter) {
                bits.reset();
                buf.$put(*self);
            }
        }
    )*};
}

numeric_arg! {
    u8 => be_u8, put_u8;
    u16 => be_u16, put_u16;
    u32 => be_u32, put_u32;
    u64 => be_u64, put_u64;
}

impl Arg for ShortStr {
    fn read<'a>(src: &Bytes, input: &'a [u8], bits: &mut BitReader) -> PResult<'a, Self> {
        bits.reset();
        short_str(src, input)
    }
    fn write(&self, buf: &mut BytesMut, bits: &mut BitWriter) {
        bits.reset();
        put_short_str(buf, self);
    }
}

impl Arg for LongStr {
    fn read<'a>(src: &Bytes, input: &'a [u8], bits: &mut BitReader) -> PResult<'a, Self> {
        bits.reset();
        long_str(src, input)
    }
    fn write(&self, buf: &mut BytesMut, bits: &mut BitWriter) {
        bits.reset();
        put_long_str(buf, self);
    }
}

impl Arg for FieldTable {
    fn read<'a>(src: &Bytes, input: &'a [u8], bits: &mut BitReader) -> PResult<'a, Self> {
        bits.reset();
        field_table(src, input)
    }
    fn write(&self, buf: &mut BytesMut, bits: &mut BitWriter) {
        bits.reset();
        put_field_table(buf, self);
    }
}

/// `shortstr`: an octet length and that many bytes.
pub(crate) fn short_str<'a>(src: &Bytes, input: &'a [u8]) -> PResult<'a, ShortStr> {
    let (input, len) = be_u8(input)?;
    let (input, bytes) = take(len)(input)?;
    Ok((input, ShortStr::from_frame(src, bytes)))
}

/// `longstr`: a 32-bit length and that many bytes.
pub(crate) fn long_str<'a>(src: &Bytes, input: &'a [u8]) -> PResult<'a, LongStr> {
    let (input, len) = be_u32(input)?;
    let (input, bytes) = take(len)(input)?;
    Ok((input, src.slice_ref(bytes)))
}

/// Deepest nesting of tables and arrays accepted, so a hostile peer cannot
/// exhaust the stack with `F` inside `F` inside `F`…
const MAX_NESTING: u8 = 32;

/// `table`: a 32-bit byte length, then name/value pairs.
pub(crate) fn field_table<'a>(src: &Bytes, input: &'a [u8]) -> PResult<'a, FieldTable> {
    nested_table(src, input, 0)
}

fn nested_table<'a>(src: &Bytes, input: &'a [u8], depth: u8) -> PResult<'a, FieldTable> {
    let (input, len) = be_u32(input)?;
    let (rest, mut body) = take(len)(input)?;
    let mut table = FieldTable::new();
    while !body.is_empty() {
        let (after_key, key) = short_str(src, body)?;
        let (after_value, value) = field_value(src, after_key, depth)?;
        table.push_unchecked(key, value);
        body = after_value;
    }
    Ok((rest, table))
}

fn field_array<'a>(src: &Bytes, input: &'a [u8], depth: u8) -> PResult<'a, FieldArray> {
    let (input, len) = be_u32(input)?;
    let (rest, mut body) = take(len)(input)?;
    let mut values = Vec::new();
    while !body.is_empty() {
        let (after, value) = field_value(src, body, depth)?;
        values.push(value);
        body = after;
    }
    Ok((rest, values))
}

fn field_value<'a>(src: &Bytes, input: &'a [u8], depth: u8) -> PResult<'a, FieldValue> {
    let (input, tag) = be_u8(input)?;
    Ok(match tag {
        b't' => {
            let (i, v) = be_u8(input)?;
            (i, FieldValue::Bool(v != 0))
        }
        b'b' => {
            let (i, v) = be_i8(input)?;
            (i, FieldValue::I8(v))
        }
        b'B' => {
            let (i, v) = be_u8(input)?;
            (i, FieldValue::U8(v))
        }
        b's' => {
            let (i, v) = be_i16(input)?;
            (i, FieldValue::I16(v))
        }
        b'u' => {
            let (i, v) = be_u16(input)?;
            (i, FieldValue::U16(v))
        }
        b'I' => {
            let (i, v) = be_i32(input)?;
            (i, FieldValue::I32(v))
        }
        b'i' => {
            let (i, v) = be_u32(input)?;
            (i, FieldValue::U32(v))
        }
        b'l' => {
            let (i, v) = be_i64(input)?;
            (i, FieldValue::I64(v))
        }
        b'f' => {
            let (i, v) = be_f32(input)?;
            (i, FieldValue::F32(v))
        }
        b'd' => {
            let (i, v) = be_f64(input)?;
            (i, FieldValue::F64(v))
        }
        b'D' => {
            let (i, scale) = be_u8(input)?;
            let (i, value) = be_u32(i)?;
            (i, FieldValue::Decimal(Decimal { scale, value }))
        }
        b'S' => {
            let (i, v) = long_str(src, input)?;
            (i, FieldValue::LongStr(v))
        }
        b'x' => {
            let (i, v) = long_str(src, input)?;
            (i, FieldValue::ByteArray(v))
        }
        b'T' => {
            let (i, v) = be_u64(input)?;
            (i, FieldValue::Timestamp(v))
        }
        b'V' => (input, FieldValue::Void),
        b'A' | b'F' if depth >= MAX_NESTING => return fail(SyntaxProblem::InvalidValue),
        b'A' => {
            let (i, v) = field_array(src, input, depth + 1)?;
            (i, FieldValue::Array(v))
        }
        b'F' => {
            let (i, v) = nested_table(src, input, depth + 1)?;
            (i, FieldValue::Table(v))
        }
        other => return fail(SyntaxProblem::BadFieldTag(other)),
    })
}

/// Writes a short string.
pub(crate) fn put_short_str(buf: &mut BytesMut, s: &ShortStr) {
    // ShortStr's constructors guarantee at most 255 bytes.
    buf.put_u8(s.len() as u8);
    buf.put_slice(s.as_bytes());
}

/// Writes a long string.
pub(crate) fn put_long_str(buf: &mut BytesMut, s: &[u8]) {
    buf.put_u32(len_u32(s.len()));
    buf.put_slice(s);
}

/// Lengths above 4 GiB cannot be framed at all; saturating keeps encoding
/// total, and such a value can never have been decoded in the first place.
fn len_u32(len: usize) -> u32 {
    u32::try_from(len).unwrap_or(u32::MAX)
}

/// Writes a field table: its length is patched in after its entries.
pub(crate) fn put_field_table(buf: &mut BytesMut, table: &FieldTable) {
    let start = buf.len();
    buf.put_u32(0);
    for (key, value) in table.iter() {
        put_short_str(buf, key);
        put_field_value(buf, value);
    }
    patch_len(buf, start);
}

fn patch_len(buf: &mut BytesMut, start: usize) {
    let len = len_u32(buf.len() - start - 4);
    buf[start..start + 4].copy_from_slice(&len.to_be_bytes());
}

fn put_field_value(buf: &mut BytesMut, value: &FieldValue) {
    buf.put_u8(value.tag());
    match value {
        FieldValue::Bool(v) => buf.put_u8(u8::from(*v)),
        FieldValue::I8(v) => buf.put_i8(*v),
        FieldValue::U8(v) => buf.put_u8(*v),
        FieldValue::I16(v) => buf.put_i16(*v),
        FieldValue::U16(v) => buf.put_u16(*v),
        FieldValue::I32(v) => buf.put_i32(*v),
        FieldValue::U32(v) => buf.put_u32(*v),
        FieldValue::I64(v) => buf.put_i64(*v),
        FieldValue::F32(v) => buf.put_f32(*v),
        FieldValue::F64(v) => buf.put_f64(*v),
        FieldValue::Decimal(d) => {
            buf.put_u8(d.scale);
            buf.put_u32(d.value);
        }
        FieldValue::LongStr(v) | FieldValue::ByteArray(v) => put_long_str(buf, v),
        FieldValue::Timestamp(v) => buf.put_u64(*v),
        FieldValue::Void => {}
        FieldValue::Array(values) => {
            let start = buf.len();
            buf.put_u32(0);
            for v in values {
                put_field_value(buf, v);
            }
            patch_len(buf, start);
        }
        FieldValue::Table(t) => put_field_table(buf, t),
    }
}

impl FieldTable {
    /// Decodes a table with its 32-bit length prefix; `src` must hold
    /// exactly one table.
    pub fn decode(src: &Bytes) -> Result<FieldTable, crate::DecodeError> {
        let error = |field: &'static str, problem| crate::DecodeError::Syntax {
            location: "field table",
            field,
            problem,
        };
        match field_table(src, src) {
            Ok(([], table)) => Ok(table),
            Ok((rest, _)) => Err(error("", SyntaxProblem::TrailingBytes(rest.len()))),
            Err(nom::Err::Error(e) | nom::Err::Failure(e)) => Err(error(e.field, e.problem)),
            Err(nom::Err::Incomplete(_)) => Err(error("", SyntaxProblem::Truncated)),
        }
    }

    /// Encodes the table with its 32-bit length prefix.
    pub fn encode(&self, buf: &mut BytesMut) {
        put_field_table(buf, self);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn decode_table(bytes: &'static [u8]) -> Result<FieldTable, WireError> {
        let src = Bytes::from_static(bytes);
        match field_table(&src, &src) {
            Ok(([], t)) => Ok(t),
            Ok(_) => panic!("table left bytes"),
            Err(nom::Err::Error(e)) | Err(nom::Err::Failure(e)) => Err(e),
            Err(nom::Err::Incomplete(_)) => panic!("complete parsers never ask for more"),
        }
    }

    #[test]
    fn table_with_every_rabbitmq_tag_decodes() {
        let bytes: &'static [u8] = b"\x00\x00\x00\x4a\
            \x01at\x01\
            \x01bb\xff\
            \x01cB\xfe\
            \x01ds\xff\xfe\
            \x01eu\x00\x02\
            \x01fI\xff\xff\xff\xfd\
            \x01gi\x00\x00\x00\x04\
            \x01hl\xff\xff\xff\xff\xff\xff\xff\xfb\
            \x01if\x3f\x80\x00\x00\
            \x01jD\x02\x00\x00\x01\x00\
            \x01kS\x00\x00\x00\x02hi\
            \x01lV";
        let table = decode_table(bytes).unwrap();
        assert_eq!(table.get("a"), Some(&FieldValue::Bool(true)));
        assert_eq!(table.get("b"), Some(&FieldValue::I8(-1)));
        assert_eq!(table.get("c"), Some(&FieldValue::U8(254)));
        assert_eq!(table.get("d"), Some(&FieldValue::I16(-2)));
        assert_eq!(table.get("e"), Some(&FieldValue::U16(2)));
        assert_eq!(table.get("f"), Some(&FieldValue::I32(-3)));
        assert_eq!(table.get("g"), Some(&FieldValue::U32(4)));
        assert_eq!(table.get("h"), Some(&FieldValue::I64(-5)));
        assert_eq!(table.get("i"), Some(&FieldValue::F32(1.0)));
        assert_eq!(
            table.get("j"),
            Some(&FieldValue::Decimal(Decimal {
                scale: 2,
                value: 256
            }))
        );
        assert_eq!(table.get("k"), Some(&FieldValue::string("hi")));
        assert_eq!(table.get("l"), Some(&FieldValue::Void));
        let mut out = BytesMut::new();
        put_field_table(&mut out, &table);
        assert_eq!(&out[..], bytes);
    }

    #[test]
    fn nested_array_table_timestamp_bytes_and_double() {
        let bytes: &'static [u8] = b"\x00\x00\x00\x2c\
            \x01aA\x00\x00\x00\x07\
            \x42\x07\
            \x46\x00\x00\x00\x00\
            \x01tT\x00\x00\x00\x00\x00\x00\x00\x09\
            \x01xx\x00\x00\x00\x01\xaa\
            \x01dd\x40\x00\x00\x00\x00\x00\x00\x00";
        let table = decode_table(bytes).unwrap();
        assert_eq!(
            table.get("a"),
            Some(&FieldValue::Array(vec![
                FieldValue::U8(7),
                FieldValue::Table(FieldTable::new())
            ]))
        );
        assert_eq!(table.get("t"), Some(&FieldValue::Timestamp(9)));
        assert_eq!(
            table.get("x"),
            Some(&FieldValue::ByteArray(Bytes::from_static(b"\xaa")))
        );
        assert_eq!(table.get("d"), Some(&FieldValue::F64(2.0)));
        let mut out = BytesMut::new();
        put_field_table(&mut out, &table);
        assert_eq!(&out[..], bytes);
    }

    #[test]
    fn unknown_tag_is_reported() {
        let err = decode_table(b"\x00\x00\x00\x03\x01aQ").unwrap_err();
        assert_eq!(err.problem, SyntaxProblem::BadFieldTag(b'Q'));
    }

    #[test]
    fn table_longer_than_its_input_is_truncated() {
        let err = decode_table(b"\x00\x00\x00\x09\x01at\x01").unwrap_err();
        assert_eq!(err.problem, SyntaxProblem::Truncated);
    }

    #[test]
    fn string_longer_than_table_is_truncated() {
        let err = decode_table(b"\x00\x00\x00\x05\x01aS\x00\x00").unwrap_err();
        assert_eq!(err.problem, SyntaxProblem::Truncated);
    }

    #[test]
    fn deep_nesting_is_refused_not_overflowed() {
        let mut buf = BytesMut::new();
        let mut inner = FieldValue::Void;
        for _ in 0..100 {
            inner = FieldValue::Array(vec![inner]);
        }
        let mut table = FieldTable::new();
        table.insert(ShortStr::from_static("deep"), inner);
        put_field_table(&mut buf, &table);
        let src = buf.freeze();
        let err = match field_table(&src, &src) {
            Err(nom::Err::Failure(e)) => e,
            other => panic!("expected failure, got {other:?}"),
        };
        assert_eq!(err.problem, SyntaxProblem::InvalidValue);
    }

    #[test]
    fn bits_pack_low_bit_first_and_wrap_after_eight() {
        let mut buf = BytesMut::new();
        let mut bits = BitWriter::default();
        for i in 0..10 {
            (i % 3 == 0).write(&mut buf, &mut bits);
        }
        7u8.write(&mut buf, &mut bits);
        true.write(&mut buf, &mut bits);
        assert_eq!(&buf[..], &[0b0100_1001, 0b0000_0010, 7, 1]);
        let src = buf.freeze();
        let mut reader = BitReader::default();
        let mut input: &[u8] = &src;
        for i in 0..10 {
            let (rest, bit) = bool::read(&src, input, &mut reader).unwrap();
            assert_eq!(bit, i % 3 == 0);
            input = rest;
        }
        let (rest, octet) = u8::read(&src, input, &mut reader).unwrap();
        assert_eq!(octet, 7);
        let (rest, bit) = bool::read(&src, rest, &mut reader).unwrap();
        assert!(bit);
        assert!(rest.is_empty());
    }
}
