//! [`MqttString`], MQTT's UTF-8 encoded string: at most 65,535 bytes of
//! well-formed UTF-8 without U+0000 (MQTT-1.5.3-1, -2), held as a `Bytes`
//! handle so that strings decoded from a packet share its buffer.

use bytes::Bytes;
use std::fmt;

/// Why bytes are not an MQTT string.
#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error)]
pub enum StringError {
    /// Longer than 65,535 bytes.
    #[error("string of {0} bytes exceeds 65535 bytes")]
    TooLong(usize),
    /// Not well-formed UTF-8 (this includes encoded surrogates U+D800 to
    /// U+DFFF and overlong forms).
    #[error("string is not well-formed UTF-8")]
    InvalidUtf8,
    /// Contains U+0000.
    #[error("string contains U+0000")]
    NullCharacter,
}

/// An MQTT UTF-8 encoded string. Every constructor checks the rules, so a
/// value always encodes to bytes a conforming peer accepts.
///
/// The characters the specifications discourage without forbidding
/// (control characters, non-characters) are accepted: a receiver may refuse
/// them but need not. A byte order mark is kept as U+FEFF, never stripped
/// (MQTT-1.5.3-3).
#[derive(Clone, Default, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct MqttString(Bytes);

impl MqttString {
    /// The longest string, in bytes.
    pub const MAX_LEN: usize = 65_535;

    /// A string from a static `str`; panics (at compile time in a const
    /// context) if it is too long or contains U+0000.
    pub const fn from_static(s: &'static str) -> Self {
        let bytes = s.as_bytes();
        assert!(
            bytes.len() <= Self::MAX_LEN,
            "MQTT string longer than 65535 bytes"
        );
        let mut i = 0;
        while i < bytes.len() {
            assert!(bytes[i] != 0, "MQTT string contains U+0000");
            i += 1;
        }
        MqttString(Bytes::from_static(bytes))
    }

    /// Checks `bytes` and wraps them without copying.
    pub fn from_utf8(bytes: Bytes) -> Result<Self, StringError> {
        if bytes.len() > Self::MAX_LEN {
            return Err(StringError::TooLong(bytes.len()));
        }
        if std::str::from_utf8(&bytes).is_err() {
            return Err(StringError::InvalidUtf8);
        }
        if bytes.contains(&0) {
            return Err(StringError::NullCharacter);
        }
        Ok(MqttString(bytes))
    }

    /// The text.
    pub fn as_str(&self) -> &str {
        // Every constructor checked the bytes are UTF-8; re-checking keeps
        // the crate free of unsafe code at a cost linear in a short string.
        std::str::from_utf8(&self.0).expect("an MqttString holds checked UTF-8")
    }

    /// The encoded bytes.
    pub fn as_bytes(&self) -> &[u8] {
        &self.0
    }

    /// The encoded bytes as a `Bytes` handle.
    pub fn into_bytes(self) -> Bytes {
        self.0
    }

    /// Length in bytes.
    pub fn len(&self) -> usize {
        self.0.len()
    }

    /// Whether the string is empty.
    pub fn is_empty(&self) -> bool {
        self.0.is_empty()
    }
}

impl TryFrom<&str> for MqttString {
    type Error = StringError;

    fn try_from(s: &str) -> Result<Self, StringError> {
        MqttString::from_utf8(Bytes::copy_from_slice(s.as_bytes()))
    }
}

impl TryFrom<String> for MqttString {
    type Error = StringError;

    fn try_from(s: String) -> Result<Self, StringError> {
        MqttString::from_utf8(Bytes::from(s))
    }
}

impl PartialEq<str> for MqttString {
    fn eq(&self, other: &str) -> bool {
        self.0 == other.as_bytes()
    }
}

impl PartialEq<&str> for MqttString {
    fn eq(&self, other: &&str) -> bool {
        self.0 == other.as_bytes()
    }
}

impl fmt::Debug for MqttString {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        fmt::Debug::fmt(self.as_str(), f)
    }
}

impl fmt::Display for MqttString {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.as_str())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn check(bytes: &[u8]) -> Result<MqttString, StringError> {
        MqttString::from_utf8(Bytes::copy_from_slice(bytes))
    }

    #[test]
    fn spec_example_is_accepted() {
        // MQTT 5.0 1.5.4 (3.1.1 1.5.3): "A𪛔" is 41 F0 AA 9B 94.
        let s = check(&[0x41, 0xF0, 0xAA, 0x9B, 0x94]).unwrap();
        assert_eq!(s.as_str(), "A\u{2A6D4}");
    }

    #[test]
    fn null_character_is_refused() {
        assert_eq!(check(b"a\0b"), Err(StringError::NullCharacter));
    }

    #[test]
    fn encoded_surrogates_are_refused() {
        // U+D800 and U+DFFF encoded as if they were characters.
        assert_eq!(check(&[0xED, 0xA0, 0x80]), Err(StringError::InvalidUtf8));
        assert_eq!(check(&[0xED, 0xBF, 0xBF]), Err(StringError::InvalidUtf8));
    }

    #[test]
    fn overlong_and_truncated_forms_are_refused() {
        // '/' as two bytes, and a lone lead byte.
        assert_eq!(check(&[0xC0, 0xAF]), Err(StringError::InvalidUtf8));
        assert_eq!(check(&[0xE2, 0x82]), Err(StringError::InvalidUtf8));
    }

    #[test]
    fn control_characters_and_non_characters_are_accepted() {
        assert!(check("\u{1}\u{7f}\u{9f}\u{fffe}".as_bytes()).is_ok());
    }

    #[test]
    fn byte_order_mark_is_kept() {
        // MQTT-1.5.3-3: EF BB BF is U+FEFF wherever it is, never skipped.
        let s = check(&[0xEF, 0xBB, 0xBF, b'a']).unwrap();
        assert_eq!(s.as_str(), "\u{feff}a");
        assert_eq!(s.len(), 4);
    }

    #[test]
    fn length_limit() {
        assert!(check(&vec![b'a'; 65_535]).is_ok());
        assert_eq!(
            check(&vec![b'a'; 65_536]),
            Err(StringError::TooLong(65_536))
        );
    }
}
