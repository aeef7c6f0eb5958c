//! OMG CDR, little- or big-endian, as OpenRTM-aist marshals data port values (a
//! bare CDR stream, no encapsulation header; OpenRTM's default byte order
//! for its connectors is little-endian): every primitive is aligned to its
//! own size counted from the start of the value's stream, a string is a
//! `u32` length counting the terminating NUL, the bytes, then the NUL, and a
//! sequence is a `u32` element count followed by the elements.
//!
//! The RTC data types implemented here each begin with a [`Time`]: every
//! type of OpenRTM-aist's `BasicDataType.idl` but the wide-character ones
//! (`TimedWChar`, `TimedWString` and their sequences, whose encoding
//! depends on GIOP code set negotiation), and [`TimedPose2D`] and
//! [`TimedVelocity2D`] of `ExtendedDataTypes.idl`. Other IDL
//! structs can be written with [`CdrWriter`] and [`CdrReader`] through the
//! [`Cdr`] trait and then made port data with [`encode`] and [`decode`].

use super::data::DataError;
use bytes::{BufMut, Bytes, BytesMut};
use std::time::{Duration, SystemTime, UNIX_EPOCH};

mod render;
pub use render::render;

/// CDR's byte order (OpenRTM's connector property `serializer.cdr.endian`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Endian {
    /// Little-endian (OpenRTM's default).
    #[default]
    Little,
    /// Big-endian (network order).
    Big,
}

/// How CDR `string`s are turned into text and back.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Charset {
    /// UTF-8; a string that is not UTF-8 does not decode.
    #[default]
    Utf8,
    /// ISO 8859-1, omniORB's default native charset: each byte is one
    /// character U+0000..=U+00FF, so every string decodes (raw bytes come
    /// through losslessly as those characters); text with a character
    /// beyond U+00FF does not encode.
    Latin1,
}

/// The byte order and string charset of a CDR stream.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct CdrOptions {
    /// Byte order.
    pub endian: Endian,
    /// String charset.
    pub charset: Charset,
}

/// A value with a CDR form.
pub trait Cdr: Sized {
    /// Writes the value's fields in IDL order.
    fn write_cdr(&self, out: &mut CdrWriter<'_>) -> Result<(), DataError>;
    /// Reads the value's fields in IDL order.
    fn read_cdr(input: &mut CdrReader) -> Result<Self, DataError>;
}

/// Appends `value` to `buf` as a little-endian, UTF-8 CDR stream starting
/// at `buf`'s end.
pub fn encode<T: Cdr>(value: &T, buf: &mut BytesMut) -> Result<(), DataError> {
    encode_with(value, buf, CdrOptions::default())
}

/// [`encode`] in the given byte order and charset.
pub fn encode_with<T: Cdr>(
    value: &T,
    buf: &mut BytesMut,
    options: CdrOptions,
) -> Result<(), DataError> {
    value.write_cdr(&mut CdrWriter::with_options(buf, options))
}

/// Reads a `T` that must take the whole of `body` (little-endian, UTF-8).
pub fn decode<T: Cdr>(body: Bytes) -> Result<T, DataError> {
    decode_with(body, CdrOptions::default())
}

/// [`decode`] in the given byte order and charset.
pub fn decode_with<T: Cdr>(body: Bytes, options: CdrOptions) -> Result<T, DataError> {
    let mut input = CdrReader::with_options(body, options);
    let value = T::read_cdr(&mut input)?;
    input.finish()?;
    Ok(value)
}

/// Writes CDR, aligning relative to where it started.
#[derive(Debug)]
pub struct CdrWriter<'a> {
    buf: &'a mut BytesMut,
    start: usize,
    options: CdrOptions,
}

macro_rules! writers {
    ($($(#[$doc:meta])* $name:ident: $t:ty),*) => {$(
        $(#[$doc])*
        pub fn $name(&mut self, value: $t) {
            self.align(std::mem::size_of::<$t>());
            match self.options.endian {
                Endian::Little => self.buf.put_slice(&value.to_le_bytes()),
                Endian::Big => self.buf.put_slice(&value.to_be_bytes()),
            }
        }
    )*};
}

impl<'a> CdrWriter<'a> {
    /// A little-endian, UTF-8 stream starting at the end of `buf`.
    pub fn new(buf: &'a mut BytesMut) -> Self {
        CdrWriter::with_options(buf, CdrOptions::default())
    }

    /// A stream in the given byte order and charset.
    pub fn with_options(buf: &'a mut BytesMut, options: CdrOptions) -> Self {
        let start = buf.len();
        CdrWriter {
            buf,
            start,
            options,
        }
    }

    /// Pads with zeros to a multiple of `size` from the stream's start.
    pub fn align(&mut self, size: usize) {
        let offset = self.buf.len() - self.start;
        let pad = (size - offset % size) % size;
        self.buf.put_bytes(0, pad);
    }

    /// An `octet` (or `char`).
    pub fn octet(&mut self, value: u8) {
        self.buf.put_u8(value);
    }

    /// A `boolean`: one octet, 0 or 1.
    pub fn boolean(&mut self, value: bool) {
        self.buf.put_u8(u8::from(value));
    }

    writers!(
        /// A `short`.
        short: i16,
        /// An `unsigned short`.
        ushort: u16,
        /// A `long`.
        long: i32,
        /// An `unsigned long`.
        ulong: u32,
        /// A `long long`.
        longlong: i64,
        /// An `unsigned long long`.
        ulonglong: u64,
        /// A `float`.
        float: f32,
        /// A `double`.
        double: f64
    );

    /// A `string` in the stream's charset: length with the NUL, bytes,
    /// NUL. Text containing NUL cannot be a CDR string.
    pub fn string(&mut self, value: &str) -> Result<(), DataError> {
        if value.contains('\0') {
            return Err(DataError::Invalid(
                "a CDR string cannot contain NUL".to_owned(),
            ));
        }
        let latin1;
        let bytes = match self.options.charset {
            Charset::Utf8 => value.as_bytes(),
            Charset::Latin1 => {
                latin1 = value
                    .chars()
                    .map(|c| u8::try_from(u32::from(c)))
                    .collect::<Result<Vec<u8>, _>>()
                    .map_err(|_| {
                        DataError::Invalid("text beyond Latin-1 in a Latin-1 string".to_owned())
                    })?;
                &latin1
            }
        };
        let length = u32::try_from(bytes.len() + 1)
            .map_err(|_| DataError::Invalid("string longer than 4 GiB".to_owned()))?;
        self.ulong(length);
        self.buf.put_slice(bytes);
        self.buf.put_u8(0);
        Ok(())
    }

    /// A sequence's element count (the elements follow).
    pub fn sequence_len(&mut self, len: usize) -> Result<(), DataError> {
        let len = u32::try_from(len)
            .map_err(|_| DataError::Invalid("sequence longer than u32::MAX".to_owned()))?;
        self.ulong(len);
        Ok(())
    }
}

/// Reads CDR, aligning relative to the start of its body.
#[derive(Debug)]
pub struct CdrReader {
    body: Bytes,
    pos: usize,
    options: CdrOptions,
}

macro_rules! readers {
    ($($(#[$doc:meta])* $name:ident: $t:ty),*) => {$(
        $(#[$doc])*
        pub fn $name(&mut self) -> Result<$t, DataError> {
            self.align(std::mem::size_of::<$t>())?;
            let bytes = self.take(std::mem::size_of::<$t>())?;
            let mut array = [0u8; std::mem::size_of::<$t>()];
            array.copy_from_slice(bytes);
            Ok(match self.options.endian {
                Endian::Little => <$t>::from_le_bytes(array),
                Endian::Big => <$t>::from_be_bytes(array),
            })
        }
    )*};
}

impl CdrReader {
    /// A little-endian, UTF-8 stream over `body`.
    pub fn new(body: Bytes) -> Self {
        CdrReader::with_options(body, CdrOptions::default())
    }

    /// A stream over `body` in the given byte order and charset.
    pub fn with_options(body: Bytes, options: CdrOptions) -> Self {
        CdrReader {
            body,
            pos: 0,
            options,
        }
    }

    fn take(&mut self, n: usize) -> Result<&[u8], DataError> {
        let available = self.body.len() - self.pos;
        if available < n {
            return Err(DataError::Truncated {
                offset: self.pos,
                needed: n - available,
            });
        }
        let start = self.pos;
        self.pos += n;
        Ok(&self.body[start..self.pos])
    }

    /// Skips the padding before a field of `size` bytes.
    pub fn align(&mut self, size: usize) -> Result<(), DataError> {
        let pad = (size - self.pos % size) % size;
        self.take(pad).map(drop)
    }

    /// Bytes not read yet.
    pub fn remaining(&self) -> usize {
        self.body.len() - self.pos
    }

    /// Fails unless everything was read.
    pub fn finish(&self) -> Result<(), DataError> {
        match self.remaining() {
            0 => Ok(()),
            n => Err(DataError::Trailing(n)),
        }
    }

    /// An `octet` (or `char`).
    pub fn octet(&mut self) -> Result<u8, DataError> {
        Ok(self.take(1)?[0])
    }

    /// A `boolean`.
    pub fn boolean(&mut self) -> Result<bool, DataError> {
        match self.octet()? {
            0 => Ok(false),
            1 => Ok(true),
            other => Err(DataError::Invalid(format!("{other} is not a CDR boolean"))),
        }
    }

    readers!(
        /// A `short`.
        short: i16,
        /// An `unsigned short`.
        ushort: u16,
        /// A `long`.
        long: i32,
        /// An `unsigned long`.
        ulong: u32,
        /// A `long long`.
        longlong: i64,
        /// An `unsigned long long`.
        ulonglong: u64,
        /// A `float`.
        float: f32,
        /// A `double`.
        double: f64
    );

    /// A `string`, in the stream's charset.
    pub fn string(&mut self) -> Result<String, DataError> {
        let charset = self.options.charset;
        let length = self.ulong()? as usize;
        if length == 0 {
            return Err(DataError::Invalid(
                "CDR string of length 0 (no NUL)".to_owned(),
            ));
        }
        let offset = self.pos;
        let bytes = self.take(length)?;
        let (text, nul) = bytes.split_at(length - 1);
        if nul != [0] || text.contains(&0) {
            return Err(DataError::Invalid(format!(
                "CDR string at offset {offset} is not NUL-terminated"
            )));
        }
        match charset {
            Charset::Utf8 => String::from_utf8(text.to_vec()).map_err(|_| DataError::Utf8),
            Charset::Latin1 => Ok(text.iter().map(|&b| char::from(b)).collect()),
        }
    }

    /// A sequence's element count, checked against the bytes left
    /// (`min_element` bytes each), so a corrupt count cannot allocate.
    pub fn sequence_len(&mut self, min_element: usize) -> Result<usize, DataError> {
        let len = self.ulong()? as usize;
        if len.saturating_mul(min_element) > self.remaining() {
            return Err(DataError::Truncated {
                offset: self.pos,
                needed: len * min_element - self.remaining(),
            });
        }
        Ok(len)
    }
}

/// `RTC::Time`: seconds and nanoseconds (since the Unix epoch, as
/// OpenRTM-aist stamps data).
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash, Default)]
pub struct Time {
    /// Seconds.
    pub sec: u32,
    /// Nanoseconds, below 1e9.
    pub nsec: u32,
}

impl Time {
    /// The current time.
    pub fn now() -> Self {
        Time::from(SystemTime::now())
    }
}

impl From<SystemTime> for Time {
    /// Saturates outside 1970..2106, as a `u32` of seconds must.
    fn from(time: SystemTime) -> Self {
        let since = time.duration_since(UNIX_EPOCH).unwrap_or_default();
        match u32::try_from(since.as_secs()) {
            Ok(sec) => Time {
                sec,
                nsec: since.subsec_nanos(),
            },
            Err(_) => Time {
                sec: u32::MAX,
                nsec: 999_999_999,
            },
        }
    }
}

impl From<Time> for SystemTime {
    fn from(time: Time) -> Self {
        UNIX_EPOCH + Duration::new(time.sec.into(), time.nsec.min(999_999_999))
    }
}

impl Cdr for Time {
    fn write_cdr(&self, out: &mut CdrWriter<'_>) -> Result<(), DataError> {
        out.ulong(self.sec);
        out.ulong(self.nsec);
        Ok(())
    }

    fn read_cdr(input: &mut CdrReader) -> Result<Self, DataError> {
        Ok(Time {
            sec: input.ulong()?,
            nsec: input.ulong()?,
        })
    }
}

/// The Timed* structs of OpenRTM's `BasicDataType.idl` beyond those
/// written out below: a time stamp and a `data` member.
macro_rules! timed_structs {
    ($($(#[$doc:meta])* $name:ident($t:ty) $(: $($derive:ident),*)?;)*) => {$(
        $(#[$doc])*
        #[derive(Debug, Clone, PartialEq, Default $($(, $derive)*)?)]
        pub struct $name {
            /// Time stamp.
            pub tm: Time,
            /// The value.
            pub data: $t,
        }
    )*};
}

timed_structs!(
    /// `RTC::TimedState` (a `short`).
    TimedState(i16): Copy, Eq;
    /// `RTC::TimedShort`.
    TimedShort(i16): Copy, Eq;
    /// `RTC::TimedUShort`.
    TimedUShort(u16): Copy, Eq;
    /// `RTC::TimedULong`.
    TimedULong(u32): Copy, Eq;
    /// `RTC::TimedFloat`.
    TimedFloat(f32): Copy;
    /// `RTC::TimedChar` (an IDL `char`: one byte, Latin-1).
    TimedChar(u8): Copy, Eq;
    /// `RTC::TimedBoolean`.
    TimedBoolean(bool): Copy, Eq;
    /// `RTC::TimedOctet`.
    TimedOctet(u8): Copy, Eq;
    /// `RTC::TimedShortSeq`.
    TimedShortSeq(Vec<i16>): Eq;
    /// `RTC::TimedLongSeq`.
    TimedLongSeq(Vec<i32>): Eq;
    /// `RTC::TimedUShortSeq`.
    TimedUShortSeq(Vec<u16>): Eq;
    /// `RTC::TimedULongSeq`.
    TimedULongSeq(Vec<u32>): Eq;
    /// `RTC::TimedFloatSeq`.
    TimedFloatSeq(Vec<f32>);
    /// `RTC::TimedCharSeq`.
    TimedCharSeq(Vec<u8>): Eq;
    /// `RTC::TimedBooleanSeq`.
    TimedBooleanSeq(Vec<bool>): Eq;
    /// `RTC::TimedOctetSeq`.
    TimedOctetSeq(Vec<u8>): Eq;
    /// `RTC::TimedStringSeq` (each string in the port's charset).
    TimedStringSeq(Vec<String>): Eq;
);

/// `RTC::TimedDouble`.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct TimedDouble {
    /// Time stamp.
    pub tm: Time,
    /// The value.
    pub data: f64,
}

/// `RTC::TimedLong` (an IDL `long` is 32 bits).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct TimedLong {
    /// Time stamp.
    pub tm: Time,
    /// The value.
    pub data: i32,
}

/// `RTC::TimedString`.
#[derive(Debug, Clone, PartialEq, Eq, Default)]
pub struct TimedString {
    /// Time stamp.
    pub tm: Time,
    /// The text (no NUL inside).
    pub data: String,
}

/// `RTC::TimedDoubleSeq`.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct TimedDoubleSeq {
    /// Time stamp.
    pub tm: Time,
    /// The values.
    pub data: Vec<f64>,
}

/// `RTC::Point2D`, metres.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct Point2D {
    /// X coordinate.
    pub x: f64,
    /// Y coordinate.
    pub y: f64,
}

/// `RTC::Pose2D`.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct Pose2D {
    /// Position.
    pub position: Point2D,
    /// Heading, radians.
    pub heading: f64,
}

/// `RTC::TimedPose2D`.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct TimedPose2D {
    /// Time stamp.
    pub tm: Time,
    /// The pose.
    pub data: Pose2D,
}

/// `RTC::Velocity2D`.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct Velocity2D {
    /// Along x, m/s.
    pub vx: f64,
    /// Along y, m/s.
    pub vy: f64,
    /// Yaw rate, rad/s.
    pub va: f64,
}

/// `RTC::TimedVelocity2D`.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct TimedVelocity2D {
    /// Time stamp.
    pub tm: Time,
    /// The velocities.
    pub data: Velocity2D,
}

// The IDL members, each encoded as CDR encodes that type; a Timed* struct
// is its time stamp followed by its `data` member.

/// An IDL type that can be a sequence's element: the least bytes one
/// takes, so a corrupt sequence count cannot make a reader allocate more
/// than the body could hold.
pub trait CdrElement: Cdr {
    /// The fewest bytes one element takes.
    const MIN_SIZE: usize;
}

/// The IDL primitives, by the writer and reader of each.
macro_rules! cdr_primitives {
    ($($t:ty: $write:ident / $read:ident, $size:expr;)*) => {$(
        impl Cdr for $t {
            fn write_cdr(&self, out: &mut CdrWriter<'_>) -> Result<(), DataError> {
                out.$write(*self);
                Ok(())
            }

            fn read_cdr(input: &mut CdrReader) -> Result<Self, DataError> {
                input.$read()
            }
        }

        impl CdrElement for $t {
            const MIN_SIZE: usize = $size;
        }
    )*};
}

cdr_primitives!(
    f64: double / double, 8;
    f32: float / float, 4;
    i32: long / long, 4;
    u32: ulong / ulong, 4;
    i16: short / short, 2;
    u16: ushort / ushort, 2;
    u8: octet / octet, 1;
    bool: boolean / boolean, 1;
);

/// A `string` element: its length and NUL at least.
impl CdrElement for String {
    const MIN_SIZE: usize = 5;
}

/// `sequence<T>`: the element count, then the elements.
impl<T: CdrElement> Cdr for Vec<T> {
    fn write_cdr(&self, out: &mut CdrWriter<'_>) -> Result<(), DataError> {
        out.sequence_len(self.len())?;
        for value in self {
            value.write_cdr(out)?;
        }
        Ok(())
    }

    fn read_cdr(input: &mut CdrReader) -> Result<Self, DataError> {
        let len = input.sequence_len(T::MIN_SIZE)?;
        (0..len).map(|_| T::read_cdr(input)).collect()
    }
}

impl Cdr for String {
    fn write_cdr(&self, out: &mut CdrWriter<'_>) -> Result<(), DataError> {
        out.string(self)
    }

    fn read_cdr(input: &mut CdrReader) -> Result<Self, DataError> {
        input.string()
    }
}

impl Cdr for Point2D {
    fn write_cdr(&self, out: &mut CdrWriter<'_>) -> Result<(), DataError> {
        out.double(self.x);
        out.double(self.y);
        Ok(())
    }

    fn read_cdr(input: &mut CdrReader) -> Result<Self, DataError> {
        Ok(Point2D {
            x: input.double()?,
            y: input.double()?,
        })
    }
}

impl Cdr for Pose2D {
    fn write_cdr(&self, out: &mut CdrWriter<'_>) -> Result<(), DataError> {
        self.position.write_cdr(out)?;
        out.double(self.heading);
        Ok(())
    }

    fn read_cdr(input: &mut CdrReader) -> Result<Self, DataError> {
        Ok(Pose2D {
            position: Point2D::read_cdr(input)?,
            heading: input.double()?,
        })
    }
}

impl Cdr for Velocity2D {
    fn write_cdr(&self, out: &mut CdrWriter<'_>) -> Result<(), DataError> {
        out.double(self.vx);
        out.double(self.vy);
        out.double(self.va);
        Ok(())
    }

    fn read_cdr(input: &mut CdrReader) -> Result<Self, DataError> {
        Ok(Velocity2D {
            vx: input.double()?,
            vy: input.double()?,
            va: input.double()?,
        })
    }
}

/// The Timed* types: `tm`, then `data`; as port data, CDR named by its
/// CORBA repository id.
macro_rules! timed_port_data {
    ($($t:ident),*) => {$(
        impl Cdr for $t {
            fn write_cdr(&self, out: &mut CdrWriter<'_>) -> Result<(), DataError> {
                self.tm.write_cdr(out)?;
                self.data.write_cdr(out)
            }

            fn read_cdr(input: &mut CdrReader) -> Result<Self, DataError> {
                Ok($t {
                    tm: Time::read_cdr(input)?,
                    data: Cdr::read_cdr(input)?,
                })
            }
        }

        impl super::data::PortData for $t {
            const CONTENT_TYPE: &'static str = "application/x-omg-cdr; endian=little";
            const TYPE_NAME: Option<&'static str> =
                Some(concat!("IDL:RTC/", stringify!($t), ":1.0"));

            fn encode(&self, buf: &mut BytesMut) -> Result<(), DataError> {
                encode(self, buf)
            }

            fn decode(body: Bytes) -> Result<Self, DataError> {
                decode(body)
            }

            fn encode_with(&self, buf: &mut BytesMut, options: CdrOptions) -> Result<(), DataError> {
                encode_with(self, buf, options)
            }

            fn decode_with(body: Bytes, options: CdrOptions) -> Result<Self, DataError> {
                decode_with(body, options)
            }
        }
    )*};
}

timed_port_data!(
    TimedDouble,
    TimedLong,
    TimedString,
    TimedDoubleSeq,
    TimedPose2D,
    TimedVelocity2D,
    TimedState,
    TimedShort,
    TimedUShort,
    TimedULong,
    TimedFloat,
    TimedChar,
    TimedBoolean,
    TimedOctet,
    TimedShortSeq,
    TimedLongSeq,
    TimedUShortSeq,
    TimedULongSeq,
    TimedFloatSeq,
    TimedCharSeq,
    TimedBooleanSeq,
    TimedOctetSeq,
    TimedStringSeq
);

#[cfg(test)]
mod tests {
    use super::*;
    use crate::ports::PortData;

    const TM: Time = Time {
        sec: 0x0102_0304,
        nsec: 0x0a0b_0c0d,
    };
    /// `TM` in little-endian CDR.
    const TM_CDR: [u8; 8] = [0x04, 0x03, 0x02, 0x01, 0x0d, 0x0c, 0x0b, 0x0a];

    fn bytes(parts: &[&[u8]]) -> Vec<u8> {
        parts.concat()
    }

    fn check<T: PortData + PartialEq + std::fmt::Debug>(value: T, expected: &[u8]) {
        let mut buf = BytesMut::new();
        value.encode(&mut buf).unwrap();
        assert_eq!(&buf[..], expected, "encoding of {value:?}");
        assert_eq!(T::decode(Bytes::copy_from_slice(expected)).unwrap(), value);
        // One byte short and one byte long are both refused.
        assert!(T::decode(Bytes::copy_from_slice(&expected[..expected.len() - 1])).is_err());
        let mut long = expected.to_vec();
        long.push(0);
        assert_eq!(
            T::decode(Bytes::from(long)).unwrap_err(),
            DataError::Trailing(1)
        );
    }

    #[test]
    fn timed_double() {
        let value = TimedDouble { tm: TM, data: 1.0 };
        // The double is aligned to 8: right after the 8-byte Time.
        check(value, &bytes(&[&TM_CDR, &[0, 0, 0, 0, 0, 0, 0xf0, 0x3f]]));
        assert_eq!(TimedDouble::TYPE_NAME, Some("IDL:RTC/TimedDouble:1.0"));
    }

    #[test]
    fn big_endian_as_serializer_cdr_endian_big() {
        let options = CdrOptions {
            endian: Endian::Big,
            ..CdrOptions::default()
        };
        let value = TimedDouble { tm: TM, data: 1.0 };
        let expected = [
            0x01, 0x02, 0x03, 0x04, 0x0a, 0x0b, 0x0c, 0x0d, 0x3f, 0xf0, 0, 0, 0, 0, 0, 0,
        ];
        let mut buf = BytesMut::new();
        value.encode_with(&mut buf, options).unwrap();
        assert_eq!(&buf[..], expected);
        let decoded = TimedDouble::decode_with(Bytes::copy_from_slice(&expected), options);
        assert_eq!(decoded.unwrap(), value);
        // The same bytes read little-endian are another value.
        assert_ne!(
            TimedDouble::decode(Bytes::copy_from_slice(&expected)).unwrap(),
            value
        );
    }

    #[test]
    fn latin1_strings_as_omniorb_marshals_them() {
        let latin1 = CdrOptions {
            charset: Charset::Latin1,
            ..CdrOptions::default()
        };
        // "café" in ISO 8859-1: é is the single byte 0xe9.
        let body = bytes(&[&TM_CDR, &[5, 0, 0, 0], b"caf\xe9\0"]);
        let value = TimedString {
            tm: TM,
            data: "café".into(),
        };
        assert_eq!(
            TimedString::decode(Bytes::copy_from_slice(&body)).unwrap_err(),
            DataError::Utf8,
            "not UTF-8"
        );
        let decoded = TimedString::decode_with(Bytes::copy_from_slice(&body), latin1).unwrap();
        assert_eq!(decoded, value);
        let mut buf = BytesMut::new();
        value.encode_with(&mut buf, latin1).unwrap();
        assert_eq!(&buf[..], body);
        let beyond = TimedString {
            tm: TM,
            data: "€".into(),
        };
        assert!(beyond.encode_with(&mut BytesMut::new(), latin1).is_err());
    }

    #[test]
    fn a_corrupt_sequence_count_allocates_nothing() {
        // Four billion booleans (one byte each) claimed, two bytes there.
        let body = bytes(&[&TM_CDR, &[0xff, 0xff, 0xff, 0xff, 1, 0]]);
        assert!(matches!(
            TimedBooleanSeq::decode(Bytes::from(body)),
            Err(DataError::Truncated { .. })
        ));
        let body = bytes(&[&TM_CDR, &[0xff, 0xff, 0xff, 0x0f], &[0; 16]]);
        assert!(TimedStringSeq::decode(Bytes::from(body)).is_err());
    }

    #[test]
    fn timed_long() {
        check(
            TimedLong { tm: TM, data: -2 },
            &bytes(&[&TM_CDR, &[0xfe, 0xff, 0xff, 0xff]]),
        );
    }

    #[test]
    fn timed_string() {
        check(
            TimedString {
                tm: TM,
                data: "go".into(),
            },
            // Length 3 counts the NUL.
            &bytes(&[&TM_CDR, &[3, 0, 0, 0], b"go\0"]),
        );
        check(
            TimedString {
                tm: TM,
                data: String::new(),
            },
            &bytes(&[&TM_CDR, &[1, 0, 0, 0, 0]]),
        );
        let mut buf = BytesMut::new();
        let nul = TimedString {
            tm: TM,
            data: "a\0b".into(),
        };
        assert!(nul.encode(&mut buf).is_err());
        let unterminated = bytes(&[&TM_CDR, &[2, 0, 0, 0], b"ab"]);
        assert!(TimedString::decode(Bytes::from(unterminated)).is_err());
    }

    #[test]
    fn timed_double_seq_pads_before_the_doubles() {
        check(
            TimedDoubleSeq {
                tm: TM,
                data: vec![1.0, -2.0],
            },
            &bytes(&[
                &TM_CDR,
                &[2, 0, 0, 0],
                // Count ends at 12: 4 bytes of padding to reach 16.
                &[0, 0, 0, 0],
                &[0, 0, 0, 0, 0, 0, 0xf0, 0x3f],
                &[0, 0, 0, 0, 0, 0, 0, 0xc0],
            ]),
        );
        // No element, no padding.
        check(
            TimedDoubleSeq {
                tm: TM,
                data: vec![],
            },
            &bytes(&[&TM_CDR, &[0, 0, 0, 0]]),
        );
        // A count larger than the body cannot allocate.
        let lying = bytes(&[&TM_CDR, &[0xff, 0xff, 0xff, 0x0f]]);
        assert!(matches!(
            TimedDoubleSeq::decode(Bytes::from(lying)),
            Err(DataError::Truncated { .. })
        ));
    }

    #[test]
    fn timed_pose_2d() {
        let value = TimedPose2D {
            tm: TM,
            data: Pose2D {
                position: Point2D { x: 1.0, y: 2.0 },
                heading: -2.0,
            },
        };
        check(
            value,
            &bytes(&[
                &TM_CDR,
                &[0, 0, 0, 0, 0, 0, 0xf0, 0x3f],
                &[0, 0, 0, 0, 0, 0, 0x00, 0x40],
                &[0, 0, 0, 0, 0, 0, 0x00, 0xc0],
            ]),
        );
    }

    #[test]
    fn timed_velocity_2d() {
        let value = TimedVelocity2D {
            tm: TM,
            data: Velocity2D {
                vx: 2.0,
                vy: 1.0,
                va: -2.0,
            },
        };
        check(
            value,
            &bytes(&[
                &TM_CDR,
                &[0, 0, 0, 0, 0, 0, 0x00, 0x40],
                &[0, 0, 0, 0, 0, 0, 0xf0, 0x3f],
                &[0, 0, 0, 0, 0, 0, 0x00, 0xc0],
            ]),
        );
    }

    #[test]
    fn alignment_is_relative_to_the_stream_start() {
        let mut buf = BytesMut::from(&b"xyz"[..]);
        let mut out = CdrWriter::new(&mut buf);
        out.octet(1);
        out.double(1.0);
        assert_eq!(&buf[..3], b"xyz");
        assert_eq!(buf.len(), 3 + 16);
        assert_eq!(&buf[3..11], &[1, 0, 0, 0, 0, 0, 0, 0]);
    }

    #[test]
    fn time_converts_both_ways() {
        let time = UNIX_EPOCH + Duration::new(5, 7);
        let tm = Time::from(time);
        assert_eq!(tm, Time { sec: 5, nsec: 7 });
        assert_eq!(SystemTime::from(tm), time);
    }
}
