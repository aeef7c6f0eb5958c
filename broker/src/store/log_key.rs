//! [`LogKey`]: a message log key as the log's index holds it. The index
//! is an ordered map touched two or three times per persistent message,
//! so its keys avoid what `Vec<u8>` costs there: an allocation per put
//! and a `memcmp` call per comparison (together about 5% of the broker's
//! CPU under persistent load). The codec's message log keys are 9 or 17
//! bytes; up to [`INLINE`] bytes a key is three big-endian words compared
//! inline, a longer one stays on the heap.
//!
//! Uses only the standard library.

use std::cmp::Ordering;

/// The longest key held inline.
pub const INLINE: usize = 24;

/// A key of the message log's index, ordered as its bytes are.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum LogKey {
    /// Up to [`INLINE`] bytes, zero-padded, as big-endian words: comparing
    /// the words, then the lengths, orders them as their bytes.
    Inline { words: [u64; 3], len: u8 },
    /// A longer key.
    Long(Box<[u8]>),
}

impl LogKey {
    /// The key of `bytes`.
    pub fn new(bytes: &[u8]) -> LogKey {
        if bytes.len() > INLINE {
            return LogKey::Long(bytes.into());
        }
        let mut padded = [0u8; INLINE];
        padded[..bytes.len()].copy_from_slice(bytes);
        let word = |at: usize| {
            let mut word = [0u8; 8];
            word.copy_from_slice(&padded[at..at + 8]);
            u64::from_be_bytes(word)
        };
        LogKey::Inline {
            words: [word(0), word(8), word(16)],
            len: bytes.len() as u8,
        }
    }

    /// The key's bytes.
    pub fn to_vec(&self) -> Vec<u8> {
        match self {
            LogKey::Inline { words, len } => {
                let mut bytes: Vec<u8> = words.iter().flat_map(|w| w.to_be_bytes()).collect();
                bytes.truncate(usize::from(*len));
                bytes
            }
            LogKey::Long(bytes) => bytes.to_vec(),
        }
    }
}

impl Ord for LogKey {
    /// Inline keys (every key the codec makes) compare word by word, in
    /// the caller's code: this runs a few dozen times per index update.
    #[inline]
    fn cmp(&self, other: &LogKey) -> Ordering {
        match (self, other) {
            (
                LogKey::Inline {
                    words: a,
                    len: a_len,
                },
                LogKey::Inline {
                    words: b,
                    len: b_len,
                },
            ) => (a[0], a[1], a[2], *a_len).cmp(&(b[0], b[1], b[2], *b_len)),
            (LogKey::Long(a), LogKey::Long(b)) => a.cmp(b),
            _ => self.to_vec().cmp(&other.to_vec()),
        }
    }
}

impl PartialOrd for LogKey {
    fn partial_cmp(&self, other: &LogKey) -> Option<Ordering> {
        Some(self.cmp(other))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    #[test]
    fn keys_round_trip_inline_and_long() {
        for len in [0, 1, 8, 9, 17, 24, 25, 100] {
            let bytes: Vec<u8> = (0..len as u8).map(|b| b.wrapping_mul(37)).collect();
            let key = LogKey::new(&bytes);
            assert_eq!(key.to_vec(), bytes);
            assert_eq!(matches!(key, LogKey::Inline { .. }), len <= INLINE);
        }
    }

    proptest! {
        /// Keys order exactly as their bytes, whichever way each is held;
        /// zero bytes and prefixes are the cases padding could confuse.
        #[test]
        fn keys_order_as_their_bytes(
            a in proptest::collection::vec(prop_oneof![Just(0u8), Just(1), any::<u8>()], 0..40),
            b in proptest::collection::vec(prop_oneof![Just(0u8), Just(1), any::<u8>()], 0..40),
        ) {
            let (ka, kb) = (LogKey::new(&a), LogKey::new(&b));
            prop_assert_eq!(ka.cmp(&kb), a.cmp(&b));
            prop_assert_eq!(ka == kb, a == b);
            let prefix = &a[..a.len() / 2];
            prop_assert_eq!(LogKey::new(prefix).cmp(&ka), prefix.cmp(&a[..]));
        }
    }
}
