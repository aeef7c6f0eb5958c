//! AMQP value types shared by method arguments, field tables and content
//! properties: short strings, long strings, decimals, field values, tables
//! and arrays. Long strings are `Bytes` handles into the received frame, so
//! decoding them never copies; short strings of up to 23 bytes are copied
//! into the value itself, which is cheaper than a shared handle's reference
//! count, and longer ones are handles too.

use bytes::Bytes;
use std::cmp::Ordering;
use std::fmt;
use std::hash::{Hash, Hasher};

/// Long string (`longstr`): up to 2^32-1 bytes, binary safe.
pub type LongStr = Bytes;

/// An AMQP short string: at most 255 bytes.
///
/// AMQP does not require short strings to be UTF-8, and RabbitMQ accepts any
/// bytes in names, so the value is kept as raw bytes. Equality and hashing
/// are byte-wise, which makes `ShortStr` usable directly as a registry key.
///
/// Up to 23 bytes are stored inline, so that decoding, cloning and dropping
/// the typical exchange name or routing key touches no reference count;
/// longer strings (and static ones) are `Bytes` handles.
#[derive(Clone)]
pub struct ShortStr(Repr);

/// Bytes a short string can hold inline while `ShortStr` stays as small as
/// a `Bytes` handle (the handle's vtable pointer is the enum's niche).
const INLINE_CAP: usize = 23;

#[derive(Clone)]
enum Repr {
    Inline { len: u8, bytes: [u8; INLINE_CAP] },
    Shared(Bytes),
}

/// A string given to [`ShortStr`] was longer than 255 bytes.
#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error)]
#[error("short string of {0} bytes exceeds 255 bytes")]
pub struct ShortStrTooLong(pub usize);

impl ShortStr {
    /// The longest short string, in bytes.
    pub const MAX_LEN: usize = 255;

    /// A short string from a static string; fails to compile (or panics in a
    /// non-const context) when the string is longer than 255 bytes.
    pub const fn from_static(s: &'static str) -> Self {
        assert!(
            s.len() <= Self::MAX_LEN,
            "short string longer than 255 bytes"
        );
        if s.is_empty() {
            return ShortStr(EMPTY);
        }
        ShortStr(Repr::Shared(Bytes::from_static(s.as_bytes())))
    }

    /// Copies `bytes` (at most 23 long) inline.
    fn inline(bytes: &[u8]) -> Self {
        debug_assert!(bytes.len() <= INLINE_CAP);
        let mut buf = [0u8; INLINE_CAP];
        buf[..bytes.len()].copy_from_slice(bytes);
        ShortStr(Repr::Inline {
            len: bytes.len() as u8,
            bytes: buf,
        })
    }

    /// Wraps bytes that are known to be at most 255 long.
    pub(crate) fn from_bytes_unchecked(bytes: Bytes) -> Self {
        debug_assert!(bytes.len() <= Self::MAX_LEN);
        if bytes.is_empty() {
            return ShortStr(EMPTY);
        }
        ShortStr(Repr::Shared(bytes))
    }

    /// A short string read from a frame: `bytes` (at most 255 long) is a
    /// slice of `src`. Short ones are copied inline, long ones become a
    /// handle into `src`.
    pub(crate) fn from_frame(src: &Bytes, bytes: &[u8]) -> Self {
        if bytes.len() <= INLINE_CAP {
            Self::inline(bytes)
        } else {
            Self::from_bytes_unchecked(src.slice_ref(bytes))
        }
    }

    /// The raw bytes.
    pub fn as_bytes(&self) -> &[u8] {
        match &self.0 {
            Repr::Inline { len, bytes } => &bytes[..usize::from(*len)],
            Repr::Shared(b) => b,
        }
    }

    /// The value as UTF-8, if it is valid UTF-8.
    pub fn as_str(&self) -> Option<&str> {
        std::str::from_utf8(self.as_bytes()).ok()
    }

    /// The value as text, with invalid UTF-8 replaced.
    pub fn to_string_lossy(&self) -> std::borrow::Cow<'_, str> {
        String::from_utf8_lossy(self.as_bytes())
    }

    /// Length in bytes.
    pub fn len(&self) -> usize {
        match &self.0 {
            Repr::Inline { len, .. } => usize::from(*len),
            Repr::Shared(b) => b.len(),
        }
    }

    /// Whether the string is empty.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// The value as a `Bytes` handle (a copy for an inline string).
    pub fn into_bytes(self) -> Bytes {
        match self.0 {
            Repr::Inline { .. } => Bytes::copy_from_slice(self.as_bytes()),
            Repr::Shared(b) => b,
        }
    }
}

/// The empty string, always inline: an empty `Bytes` (an empty literal's,
/// `Bytes::new()`'s) points at the dangling address 0x1, and glibc's
/// AVX-512 `memcmp` loads through both pointers even for 0 bytes (masked),
/// which at an unmapped address costs a microcode assist, many times a
/// comparison through a valid pointer. Every publish to the default
/// exchange compared its name with one (the profile is in
/// docs/performance.md).
const EMPTY: Repr = Repr::Inline {
    len: 0,
    bytes: [0; INLINE_CAP],
};

impl Default for ShortStr {
    fn default() -> Self {
        ShortStr(EMPTY)
    }
}

impl PartialEq for ShortStr {
    fn eq(&self, other: &Self) -> bool {
        self.as_bytes() == other.as_bytes()
    }
}

impl Eq for ShortStr {}

/// Hashes exactly as `[u8]` does, as `Borrow<[u8]>` requires.
impl Hash for ShortStr {
    fn hash<H: Hasher>(&self, state: &mut H) {
        self.as_bytes().hash(state);
    }
}

impl PartialOrd for ShortStr {
    fn partial_cmp(&self, other: &Self) -> Option<Ordering> {
        Some(self.cmp(other))
    }
}

impl Ord for ShortStr {
    fn cmp(&self, other: &Self) -> Ordering {
        self.as_bytes().cmp(other.as_bytes())
    }
}

impl TryFrom<Bytes> for ShortStr {
    type Error = ShortStrTooLong;
    /// Keeps the handle, whatever the length.
    fn try_from(bytes: Bytes) -> Result<Self, Self::Error> {
        if bytes.len() > Self::MAX_LEN {
            Err(ShortStrTooLong(bytes.len()))
        } else {
            Ok(ShortStr(Repr::Shared(bytes)))
        }
    }
}

impl TryFrom<&str> for ShortStr {
    type Error = ShortStrTooLong;
    fn try_from(s: &str) -> Result<Self, Self::Error> {
        if s.len() <= INLINE_CAP {
            Ok(Self::inline(s.as_bytes()))
        } else {
            Bytes::copy_from_slice(s.as_bytes()).try_into()
        }
    }
}

impl TryFrom<String> for ShortStr {
    type Error = ShortStrTooLong;
    fn try_from(s: String) -> Result<Self, Self::Error> {
        if s.len() <= INLINE_CAP {
            Ok(Self::inline(s.as_bytes()))
        } else {
            Bytes::from(s).try_into()
        }
    }
}

impl PartialEq<str> for ShortStr {
    fn eq(&self, other: &str) -> bool {
        self.as_bytes() == other.as_bytes()
    }
}

impl PartialEq<&str> for ShortStr {
    fn eq(&self, other: &&str) -> bool {
        self.as_bytes() == other.as_bytes()
    }
}

impl std::borrow::Borrow<[u8]> for ShortStr {
    fn borrow(&self) -> &[u8] {
        self.as_bytes()
    }
}

impl fmt::Display for ShortStr {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(&self.to_string_lossy())
    }
}

impl fmt::Debug for ShortStr {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        fmt::Debug::fmt(&*self.to_string_lossy(), f)
    }
}

/// A decimal value: `value` × 10^-`scale`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Default)]
pub struct Decimal {
    /// Number of decimal digits after the point.
    pub scale: u8,
    /// Unscaled value.
    pub value: u32,
}

/// One value in a field table or array, with RabbitMQ's type tags (the
/// AMQP 0-9-1 errata), which differ from the spec's for `s`, `u`, `i`, `l`.
#[derive(Debug, Clone, PartialEq)]
pub enum FieldValue {
    /// `t`: boolean, one octet.
    Bool(bool),
    /// `b`: signed 8-bit integer.
    I8(i8),
    /// `B`: unsigned 8-bit integer.
    U8(u8),
    /// `s`: signed 16-bit integer (RabbitMQ's tag; the spec used `s` for short strings).
    I16(i16),
    /// `u`: unsigned 16-bit integer.
    U16(u16),
    /// `I`: signed 32-bit integer.
    I32(i32),
    /// `i`: unsigned 32-bit integer.
    U32(u32),
    /// `l`: signed 64-bit integer.
    I64(i64),
    /// `f`: 32-bit IEEE float.
    F32(f32),
    /// `d`: 64-bit IEEE float.
    F64(f64),
    /// `D`: decimal.
    Decimal(Decimal),
    /// `S`: long string.
    LongStr(LongStr),
    /// `x`: byte array (RabbitMQ extension), long length prefix.
    ByteArray(Bytes),
    /// `A`: array of field values.
    Array(FieldArray),
    /// `T`: timestamp, seconds since the epoch.
    Timestamp(u64),
    /// `F`: nested field table.
    Table(FieldTable),
    /// `V`: no value.
    Void,
}

impl FieldValue {
    /// The RabbitMQ wire tag for this value.
    pub fn tag(&self) -> u8 {
        match self {
            FieldValue::Bool(_) => b't',
            FieldValue::I8(_) => b'b',
            FieldValue::U8(_) => b'B',
            FieldValue::I16(_) => b's',
            FieldValue::U16(_) => b'u',
            FieldValue::I32(_) => b'I',
            FieldValue::U32(_) => b'i',
            FieldValue::I64(_) => b'l',
            FieldValue::F32(_) => b'f',
            FieldValue::F64(_) => b'd',
            FieldValue::Decimal(_) => b'D',
            FieldValue::LongStr(_) => b'S',
            FieldValue::ByteArray(_) => b'x',
            FieldValue::Array(_) => b'A',
            FieldValue::Timestamp(_) => b'T',
            FieldValue::Table(_) => b'F',
            FieldValue::Void => b'V',
        }
    }

    /// The value as an integer, for any of the integer types.
    pub fn as_i64(&self) -> Option<i64> {
        match *self {
            FieldValue::I8(v) => Some(v.into()),
            FieldValue::U8(v) => Some(v.into()),
            FieldValue::I16(v) => Some(v.into()),
            FieldValue::U16(v) => Some(v.into()),
            FieldValue::I32(v) => Some(v.into()),
            FieldValue::U32(v) => Some(v.into()),
            FieldValue::I64(v) => Some(v),
            FieldValue::Timestamp(v) => i64::try_from(v).ok(),
            _ => None,
        }
    }

    /// The value as bytes, for long strings and byte arrays.
    pub fn as_bytes(&self) -> Option<&[u8]> {
        match self {
            FieldValue::LongStr(b) | FieldValue::ByteArray(b) => Some(b),
            _ => None,
        }
    }

    /// A long-string value from text.
    pub fn string(s: &str) -> Self {
        FieldValue::LongStr(Bytes::copy_from_slice(s.as_bytes()))
    }
}

/// A field table: named values in the order they were written.
///
/// Tables are small (a handful of entries), so a vector with linear lookup
/// is both the fastest and the order-preserving choice.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct FieldTable(Vec<(ShortStr, FieldValue)>);

impl FieldTable {
    /// An empty table.
    pub fn new() -> Self {
        FieldTable(Vec::new())
    }

    /// The value stored under `key`, if any.
    pub fn get(&self, key: &str) -> Option<&FieldValue> {
        self.0
            .iter()
            .find(|(k, _)| k.as_bytes() == key.as_bytes())
            .map(|(_, v)| v)
    }

    /// Sets `key` to `value`, replacing an existing entry in place.
    pub fn insert(&mut self, key: ShortStr, value: FieldValue) {
        match self.0.iter_mut().find(|(k, _)| *k == key) {
            Some(entry) => entry.1 = value,
            None => self.0.push((key, value)),
        }
    }

    /// Removes and returns the value under `key`.
    pub fn remove(&mut self, key: &str) -> Option<FieldValue> {
        let index = self.0.iter().position(|(k, _)| k == key)?;
        Some(self.0.remove(index).1)
    }

    /// The entries in order.
    pub fn iter(&self) -> impl Iterator<Item = (&ShortStr, &FieldValue)> {
        self.0.iter().map(|(k, v)| (k, v))
    }

    /// Number of entries.
    pub fn len(&self) -> usize {
        self.0.len()
    }

    /// Whether the table has no entries.
    pub fn is_empty(&self) -> bool {
        self.0.is_empty()
    }

    /// Gives back the room beyond its entries, its nested tables' too:
    /// for a table kept for long (a connection's client properties).
    pub fn shrink_to_fit(&mut self) {
        for (_, value) in &mut self.0 {
            if let FieldValue::Table(table) = value {
                table.shrink_to_fit();
            }
        }
        self.0.shrink_to_fit();
    }

    pub(crate) fn push_unchecked(&mut self, key: ShortStr, value: FieldValue) {
        self.0.push((key, value));
    }
}

impl FromIterator<(ShortStr, FieldValue)> for FieldTable {
    fn from_iter<I: IntoIterator<Item = (ShortStr, FieldValue)>>(iter: I) -> Self {
        let mut table = FieldTable::new();
        for (k, v) in iter {
            table.insert(k, v);
        }
        table
    }
}

/// A field array (`A`): values without names.
pub type FieldArray = Vec<FieldValue>;

#[cfg(test)]
mod tests {
    use super::*;
    use std::collections::hash_map::DefaultHasher;
    use std::collections::HashSet;

    fn hash_of<T: Hash + ?Sized>(value: &T) -> u64 {
        let mut hasher = DefaultHasher::new();
        value.hash(&mut hasher);
        hasher.finish()
    }

    /// However made, an empty short string's bytes point into the value
    /// itself, never at a dangling address (see [`EMPTY`]).
    #[test]
    fn empty_short_strings_point_at_memory_they_own() {
        let empties = [
            ShortStr::from_static(""),
            ShortStr::from_bytes_unchecked(Bytes::new()),
            ShortStr::from_bytes_unchecked(Bytes::from_static(b"")),
            ShortStr::from_frame(&Bytes::from_static(b"x"), b""),
            ShortStr::default(),
        ];
        for empty in &empties {
            let start = std::ptr::from_ref(empty) as usize;
            let at = empty.as_bytes().as_ptr() as usize;
            assert!((start..start + std::mem::size_of::<ShortStr>()).contains(&at));
            assert_eq!(empty, &ShortStr::default());
        }
    }

    #[test]
    fn short_str_is_as_small_as_a_bytes_handle() {
        assert_eq!(
            std::mem::size_of::<ShortStr>(),
            std::mem::size_of::<Bytes>()
        );
    }

    #[test]
    fn inline_and_shared_strings_compare_hash_and_order_by_bytes() {
        let frame = Bytes::from_static(b"xamq.directx");
        let decoded = ShortStr::from_frame(&frame, &frame[1..11]);
        let shared = ShortStr::try_from(Bytes::from_static(b"amq.direct")).unwrap();
        let fixed = ShortStr::from_static("amq.direct");
        assert!(matches!(decoded.0, Repr::Inline { .. }));
        assert!(matches!(shared.0, Repr::Shared(_)));
        assert_eq!(decoded, shared);
        assert_eq!(decoded, fixed);
        assert_eq!(decoded, "amq.direct");
        assert_eq!(hash_of(&decoded), hash_of(&shared));
        assert_eq!(hash_of(&decoded), hash_of(&b"amq.direct"[..]));
        assert!(decoded < ShortStr::from_static("amq.e"));
        assert!(decoded > ShortStr::from_static("amq"));
        let set: HashSet<ShortStr> = [decoded.clone()].into_iter().collect();
        assert!(set.contains(&b"amq.direct"[..]));
        assert_eq!(
            decoded.clone().into_bytes(),
            Bytes::from_static(b"amq.direct")
        );
        assert_eq!(ShortStr::default(), ShortStr::from_static(""));
        assert!(ShortStr::default().is_empty());
    }

    #[test]
    fn strings_past_the_inline_capacity_are_handles_into_the_frame() {
        let frame = Bytes::from(vec![b'a'; 300]);
        let at_cap = ShortStr::from_frame(&frame, &frame[..INLINE_CAP]);
        let past_cap = ShortStr::from_frame(&frame, &frame[..INLINE_CAP + 1]);
        let longest = ShortStr::from_frame(&frame, &frame[..255]);
        assert!(matches!(at_cap.0, Repr::Inline { .. }));
        assert!(matches!(past_cap.0, Repr::Shared(_)));
        assert_eq!(past_cap.as_bytes().as_ptr(), frame.as_ptr());
        assert_eq!(
            (at_cap.len(), past_cap.len(), longest.len()),
            (INLINE_CAP, INLINE_CAP + 1, 255)
        );
        let owned = ShortStr::try_from("x".repeat(40)).unwrap();
        assert_eq!(owned.len(), 40);
        assert_eq!(
            ShortStr::try_from("y".repeat(256)),
            Err(ShortStrTooLong(256))
        );
        assert_eq!(ShortStr::try_from("short").unwrap(), "short");
    }
}
