//! OMG CDR, little- or big-endian, as OpenRTM-aist marshals data port values (a
//! bare CDR stream, no encapsulation header; OpenRTM's default byte order
//! for its connectors is little-endian): every primitive is aligned to its
//! own size counted from the start of the value's stream, a string is a
//! `u32` length counting the terminating NUL, the bytes, then the NUL, and a
//! sequence is a `u32` element count followed by the elements.
//!
//! A `wchar` and a `wstring` are UTF-16, as omniORB marshals them once
//! its ORB is initialised (OpenRTM-aist always initialises it first): a
//! `wchar` is the octet count 2 and the code unit big-endian, a `wstring`
//! its length in octets, a byte order mark and the code units, no
//! terminator (see [`CdrWriter::wstring`] for the bytes written and
//! [`CdrReader::wstring`] for what is read).
//!
//! This module owns the codec: [`CdrWriter`] and [`CdrReader`], the [`Cdr`]
//! trait and its impls for the IDL primitives, `string`, `wchar` (a
//! `char` up to U+FFFF), `wstring` ([`WString`]) and `sequence<T>`
//! (whose reader bounds a count by the bytes left before allocating), and
//! `idl_structs!`, the one way an IDL struct is declared here: its Rust
//! struct, its CDR form (the members one after another in IDL order) and,
//! as port data, that CDR named by its CORBA repository id
//! (`IDL:RTC/<name>:1.0`). The RTC types are declared in one file per
//! OpenRTM-aist IDL file, and re-exported both here and at
//! [`ports`](super):
//! - `basic`: [`Time`] and every type of `BasicDataType.idl`, the
//!   wide-character ones ([`TimedWChar`], [`TimedWString`] and their
//!   sequences) included;
//! - `extended`: every type of `ExtendedDataTypes.idl` ([`RGBColour`],
//!   the 2D and 3D geometry from [`Point2D`] to [`OAP`], [`Quaternion`],
//!   and their `Timed*` wrappers);
//! - `interface`: the sensor and device types of
//!   `InterfaceDataTypes.idl` most used ([`RangeData`], [`CameraImage`],
//!   [`PointCloud`], [`GPSData`], [`INSData`], …; its module docs name
//!   the ones not yet here).
//!
//! Other IDL structs can be written with [`CdrWriter`] and [`CdrReader`]
//! through the [`Cdr`] trait and then made port data with [`encode`] and
//! [`decode`].

use super::data::DataError;
use bytes::{BufMut, Bytes, BytesMut};

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

/// The `content-type` of CDR bodies in little-endian order (the CDR
/// types' `PortData::CONTENT_TYPE`, OpenRTM's default order).
pub const CONTENT_TYPE_LITTLE: &str = "application/x-omg-cdr; endian=little";
/// The `content-type` of CDR bodies in big-endian order.
pub const CONTENT_TYPE_BIG: &str = "application/x-omg-cdr; endian=big";

/// The `content-type` a port's messages carry: its type's, with a CDR
/// type's byte order as the port's options set it.
pub(crate) fn content_type(type_content_type: &'static str, options: &CdrOptions) -> &'static str {
    match (type_content_type, options.endian) {
        (CONTENT_TYPE_LITTLE, Endian::Big) => CONTENT_TYPE_BIG,
        _ => type_content_type,
    }
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

    /// A `wchar` as omniORB writes it with UTF-16 as the wide code set
    /// (GIOP 1.2): the octet count 2, then the code unit big-endian in
    /// either byte order. A character beyond U+FFFF is two code units and
    /// cannot be one `wchar`.
    pub fn wchar(&mut self, value: char) -> Result<(), DataError> {
        let unit = u16::try_from(u32::from(value)).map_err(|_| {
            DataError::Invalid(format!(
                "{value:?} is beyond U+FFFF: not one UTF-16 code unit, so not a wchar"
            ))
        })?;
        self.buf.put_u8(2);
        self.buf.put_u16(unit);
        Ok(())
    }

    /// A `wstring` as omniORB on a little-endian host writes it (GIOP 1.2,
    /// UTF-16): the length in octets (in the stream's byte order), then
    /// the little-endian byte order mark `FF FE` and the UTF-16 code units
    /// little-endian, in either stream byte order; no terminator. The
    /// empty string is the length 0 alone. Text containing NUL cannot be a
    /// `wstring` (omniORB refuses it too).
    pub fn wstring(&mut self, value: &str) -> Result<(), DataError> {
        if value.contains('\0') {
            return Err(DataError::Invalid(
                "a CDR wstring cannot contain NUL".to_owned(),
            ));
        }
        if value.is_empty() {
            self.ulong(0);
            return Ok(());
        }
        let length = value
            .encode_utf16()
            .count()
            .checked_add(1)
            .and_then(|units| units.checked_mul(2))
            .and_then(|octets| u32::try_from(octets).ok())
            .ok_or_else(|| DataError::Invalid("wstring longer than 4 GiB".to_owned()))?;
        self.ulong(length);
        self.buf.put_slice(&[0xff, 0xfe]);
        for unit in value.encode_utf16() {
            self.buf.put_u16_le(unit);
        }
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

    /// A `wchar` (GIOP 1.2, UTF-16): the octet count 2 and a big-endian
    /// code unit, or 4 and a byte order mark (`FE FF` big-endian, `FF FE`
    /// little-endian) then the unit, as omniORB reads it, in either stream
    /// byte order. Any other count does not decode, nor (unlike omniORB,
    /// which passes it on) a surrogate: half a character beyond U+FFFF,
    /// which a `char` cannot hold.
    pub fn wchar(&mut self) -> Result<char, DataError> {
        let offset = self.pos;
        let invalid =
            |what: String| DataError::Invalid(format!("CDR wchar at offset {offset} {what}"));
        let unit = match self.octet()? {
            2 => {
                let bytes = self.take(2)?;
                u16::from_be_bytes([bytes[0], bytes[1]])
            }
            4 => match *self.take(4)? {
                [0xfe, 0xff, high, low] => u16::from_be_bytes([high, low]),
                [0xff, 0xfe, low, high] => u16::from_le_bytes([low, high]),
                _ => return Err(invalid("has 4 octets but no byte order mark".to_owned())),
            },
            n => {
                return Err(invalid(format!(
                    "has {n} octets (2, or 4 with a byte order mark)"
                )))
            }
        };
        char::from_u32(unit.into()).ok_or_else(|| invalid(format!("is the surrogate {unit:#06x}")))
    }

    /// A `wstring` (GIOP 1.2, UTF-16), as omniORB reads it: the length in
    /// octets (even; no terminator), then the code units, big-endian
    /// unless a leading byte order mark says otherwise (`FE FF`
    /// big-endian, `FF FE` little-endian; the mark is dropped, a later
    /// U+FEFF is a character), in either stream byte order. An odd length
    /// does not decode, nor (stricter than omniORB, whose C++ mapping
    /// passes them on or cuts the text at the NUL) unpaired surrogates and
    /// NUL. Nothing is allocated before the length is checked against the
    /// bytes left.
    pub fn wstring(&mut self) -> Result<String, DataError> {
        let length = self.ulong()? as usize;
        let offset = self.pos;
        let invalid =
            |what: &str| DataError::Invalid(format!("CDR wstring at offset {offset} {what}"));
        if length % 2 != 0 {
            return Err(invalid("has an odd number of octets"));
        }
        let (big_endian, units) = match self.take(length)? {
            [0xfe, 0xff, units @ ..] => (true, units),
            [0xff, 0xfe, units @ ..] => (false, units),
            units => (true, units),
        };
        let units = units.chunks_exact(2).map(|pair| {
            let pair = [pair[0], pair[1]];
            if big_endian {
                u16::from_be_bytes(pair)
            } else {
                u16::from_le_bytes(pair)
            }
        });
        let mut text = String::with_capacity(length / 2);
        for c in char::decode_utf16(units) {
            match c {
                Ok('\0') => return Err(invalid("contains NUL")),
                Ok(c) => text.push(c),
                Err(e) => {
                    return Err(invalid(&format!(
                        "has the unpaired surrogate {:#06x}",
                        e.unpaired_surrogate()
                    )))
                }
            }
        }
        Ok(text)
    }

    /// A sequence's element count, checked against the bytes left
    /// (`min_element` bytes each), so a corrupt count cannot allocate.
    pub fn sequence_len(&mut self, min_element: usize) -> Result<usize, DataError> {
        let len = self.ulong()? as usize;
        // Saturating: on a 32-bit target the product of a corrupt count
        // could overflow.
        let least = len.saturating_mul(min_element);
        if least > self.remaining() {
            return Err(DataError::Truncated {
                offset: self.pos,
                needed: least - self.remaining(),
            });
        }
        Ok(len)
    }
}

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

/// A `wchar`: one UTF-16 code unit, so a character up to U+FFFF (see
/// [`CdrWriter::wchar`]).
impl Cdr for char {
    fn write_cdr(&self, out: &mut CdrWriter<'_>) -> Result<(), DataError> {
        out.wchar(*self)
    }

    fn read_cdr(input: &mut CdrReader) -> Result<Self, DataError> {
        input.wchar()
    }
}

/// A `wchar` element: its octet count and one code unit at least.
impl CdrElement for char {
    const MIN_SIZE: usize = 3;
}

/// An IDL `wstring`: text whose CDR form is UTF-16 (see
/// [`CdrWriter::wstring`] and [`CdrReader::wstring`]) whatever the
/// stream's [`Charset`], which is for `string`s only.
#[derive(Debug, Clone, PartialEq, Eq, PartialOrd, Ord, Hash, Default)]
pub struct WString(pub String);

impl From<String> for WString {
    fn from(text: String) -> Self {
        WString(text)
    }
}

impl From<&str> for WString {
    fn from(text: &str) -> Self {
        WString(text.to_owned())
    }
}

impl std::ops::Deref for WString {
    type Target = str;

    fn deref(&self) -> &str {
        &self.0
    }
}

impl std::fmt::Display for WString {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(&self.0)
    }
}

impl Cdr for WString {
    fn write_cdr(&self, out: &mut CdrWriter<'_>) -> Result<(), DataError> {
        out.wstring(&self.0)
    }

    fn read_cdr(input: &mut CdrReader) -> Result<Self, DataError> {
        input.wstring().map(WString)
    }
}

/// A `wstring` element: its length at least (the empty string).
impl CdrElement for WString {
    const MIN_SIZE: usize = 4;
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

/// Declares IDL structs of the `RTC` module, members in IDL order: each
/// a `pub` Rust struct deriving `Debug, Clone, PartialEq, Default` (and the
/// derives in brackets), its [`Cdr`] form (each member's, in order) and its
/// [`PortData`](super::PortData) impl: CDR named `IDL:RTC/<name>:1.0`.
macro_rules! idl_structs {
    ($(
        $(#[$doc:meta])*
        $name:ident $([$($derive:ident),+])? {
            $($(#[$member_doc:meta])* $member:ident: $t:ty),+ $(,)?
        }
    )*) => {$(
        $(#[$doc])*
        #[derive(Debug, Clone, PartialEq, Default $($(, $derive)+)?)]
        pub struct $name {
            $($(#[$member_doc])* pub $member: $t,)+
        }

        impl $crate::cdr::Cdr for $name {
            fn write_cdr(
                &self,
                out: &mut $crate::cdr::CdrWriter<'_>,
            ) -> Result<(), $crate::DataError> {
                $($crate::cdr::Cdr::write_cdr(&self.$member, out)?;)+
                Ok(())
            }

            fn read_cdr(
                input: &mut $crate::cdr::CdrReader,
            ) -> Result<Self, $crate::DataError> {
                // A struct expression evaluates its fields in the order
                // written: IDL order.
                Ok($name {
                    $($member: $crate::cdr::Cdr::read_cdr(input)?,)+
                })
            }
        }

        impl $crate::PortData for $name {
            const CONTENT_TYPE: &'static str = $crate::cdr::CONTENT_TYPE_LITTLE;
            const TYPE_NAME: Option<&'static str> =
                Some(concat!("IDL:RTC/", stringify!($name), ":1.0"));

            fn encode(&self, buf: &mut ::bytes::BytesMut) -> Result<(), $crate::DataError> {
                $crate::cdr::encode(self, buf)
            }

            fn decode(body: ::bytes::Bytes) -> Result<Self, $crate::DataError> {
                $crate::cdr::decode(body)
            }

            fn encode_with(
                &self,
                buf: &mut ::bytes::BytesMut,
                options: $crate::cdr::CdrOptions,
            ) -> Result<(), $crate::DataError> {
                $crate::cdr::encode_with(self, buf, options)
            }

            fn decode_with(
                body: ::bytes::Bytes,
                options: $crate::cdr::CdrOptions,
            ) -> Result<Self, $crate::DataError> {
                $crate::cdr::decode_with(body, options)
            }
        }
    )*};
}

/// Declares `RTC::Timed*` structs through `idl_structs!`: a time stamp
/// `tm`, then the `data` member of the given type.
macro_rules! timed_structs {
    ($($(#[$doc:meta])* $name:ident($t:ty) $([$($derive:ident),+])?;)*) => {
        idl_structs!($(
            $(#[$doc])*
            $name $([$($derive),+])? {
                /// Time stamp.
                tm: $crate::cdr::Time,
                /// The value.
                data: $t,
            }
        )*);
    };
}

pub(super) mod basic;
pub(super) mod extended;
pub(super) mod interface;
#[cfg(test)]
mod testing;

pub use basic::*;
pub use extended::*;
pub use interface::*;

#[cfg(test)]
mod tests {
    use super::testing::{bytes, TM, TM_CDR};
    use super::*;
    use crate::PortData;

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
    fn hostile_wide_characters_are_errors_not_panics_or_allocations() {
        let invalid = |body: Vec<u8>, decode: fn(Bytes) -> Result<(), DataError>| {
            let error = decode(Bytes::from(body.clone())).unwrap_err();
            assert!(
                matches!(error, DataError::Invalid(_) | DataError::Truncated { .. }),
                "{body:02x?}: {error}"
            );
        };
        let wchar = |body: Bytes| TimedWChar::decode(body).map(drop);
        let wstring = |body: Bytes| TimedWString::decode(body).map(drop);
        // A wchar of 0, 1, 3, 5 or 255 octets; of 4 without a mark; a
        // surrogate, bare or after a mark.
        for unit in [
            &[0][..],
            &[1, 0x41],
            &[3, 0, 0x41, 0],
            &[5, 0xfe, 0xff, 0, 0x41, 0],
            &[255, 0, 0x41],
            &[4, 0, 0x41, 0, 0x42],
            &[2, 0xd8, 0x3d],
            &[2, 0xdc, 0],
            &[4, 0xff, 0xfe, 0x3d, 0xd8],
        ] {
            invalid(bytes(&[&TM_CDR, unit]), wchar);
        }
        // A wstring of an odd number of octets; unpaired surrogates, with
        // either mark and without; NUL; a length beyond the body.
        for (length, units) in [
            (3, &[0xff, 0xfe, 0x41][..]),
            (1, &[0x41]),
            (4, &[0xff, 0xfe, 0x3d, 0xd8]),
            (4, &[0xfe, 0xff, 0xdc, 0]),
            (6, &[0xff, 0xfe, 0x3d, 0xd8, 0x41, 0]),
            (6, &[0xff, 0xfe, 0, 0xde, 0x3d, 0xd8]),
            (2, &[0xd8, 0x3d]),
            (4, &[0, 0x41, 0, 0]),
            (u32::MAX - 1, &[0xff, 0xfe, 0x41, 0]),
            (u32::MAX, &[0xff, 0xfe, 0x41, 0]),
        ] {
            invalid(bytes(&[&TM_CDR, &length.to_le_bytes(), units]), wstring);
        }
        // Four billion elements claimed, a few bytes there: refused before
        // any allocation.
        let huge = bytes(&[&TM_CDR, &[0xff, 0xff, 0xff, 0xff], &[2, 0, 0x41]]);
        invalid(huge.clone(), |body| TimedWCharSeq::decode(body).map(drop));
        invalid(huge, |body| TimedWStringSeq::decode(body).map(drop));
        let huge = bytes(&[&TM_CDR, &[0xff, 0xff, 0xff, 0x3f], &[0; 64]]);
        invalid(huge, |body| TimedWStringSeq::decode(body).map(drop));

        // Arbitrary bytes after a time stamp, as each wide type: an error
        // or a value, never a panic.
        let mut state = 0x2545_f491_4f6c_dd1d_u64;
        let mut next = move || {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            state
        };
        for _ in 0..20_000 {
            let len = (next() % 24) as usize;
            let mut tail: Vec<u8> = (0..len)
                .map(|_| {
                    let random = next();
                    let byte = (random >> 8) as u8;
                    // Mostly small numbers, marks and surrogate halves.
                    [byte % 8, 0xfe, 0xff, 0xd8, 0xdc, byte][(random % 6) as usize]
                })
                .collect();
            if tail.len() >= 4 && next() % 2 == 0 {
                // Often a count or length the body could hold.
                let small = (next() % 20) as u32;
                tail[..4].copy_from_slice(&small.to_le_bytes());
            }
            let body = Bytes::from(bytes(&[&TM_CDR, &tail]));
            let _ = TimedWChar::decode(body.clone());
            let _ = TimedWString::decode(body.clone());
            let _ = TimedWCharSeq::decode(body.clone());
            let _ = TimedWStringSeq::decode(body);
        }
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
    fn every_idl_struct_is_port_data_named_by_its_repository_id() {
        assert_eq!(Time::TYPE_NAME, Some("IDL:RTC/Time:1.0"));
        assert_eq!(TimedLong::TYPE_NAME, Some("IDL:RTC/TimedLong:1.0"));
        assert_eq!(Pose2D::TYPE_NAME, Some("IDL:RTC/Pose2D:1.0"));
        assert_eq!(
            TimedPose2D::CONTENT_TYPE,
            "application/x-omg-cdr; endian=little"
        );
    }

    #[test]
    fn a_ports_content_type_says_its_byte_order() {
        let big = CdrOptions {
            endian: Endian::Big,
            ..CdrOptions::default()
        };
        assert_eq!(
            content_type(TimedPose2D::CONTENT_TYPE, &big),
            "application/x-omg-cdr; endian=big"
        );
        assert_eq!(
            content_type(TimedPose2D::CONTENT_TYPE, &CdrOptions::default()),
            TimedPose2D::CONTENT_TYPE
        );
        assert_eq!(
            content_type("text/plain; charset=utf-8", &big),
            "text/plain; charset=utf-8"
        );
    }
}
