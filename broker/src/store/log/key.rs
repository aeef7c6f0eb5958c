//! [`LogKey`]: a message log key as the log's index holds it. The index
//! is a hash map touched two or three times per persistent message (and
//! sorted only when scanned), so its keys avoid what `Vec<u8>` costs
//! there: an allocation per put, and hashing or comparing byte by byte.
//! The codec's message log keys are 9 or 17 bytes; up to [`INLINE`] bytes
//! a key is three big-endian words, hashed a word at a time and compared
//! inline; a longer one stays on the heap.
//!
//! Uses only the standard library.

use std::cmp::Ordering;
use std::hash::{Hash, Hasher};

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

impl Hash for LogKey {
    /// A word at a time (a derived hash would feed an inline key's words
    /// to the hasher as 24 separate bytes).
    #[inline]
    fn hash<H: Hasher>(&self, state: &mut H) {
        match self {
            LogKey::Inline { words, len } => {
                state.write_u64(words[0]);
                state.write_u64(words[1]);
                state.write_u64(words[2] ^ u64::from(*len));
            }
            LogKey::Long(bytes) => state.write(bytes),
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

    /// The codec's keys for neighbouring and strided ids and positions
    /// (message records: `m` id; index entries: `i` queue position) spread
    /// over the buckets of a table as large as hashbrown gives 4,096 keys,
    /// and over its 7-bit tags.
    #[test]
    fn neighbouring_keys_spread_over_the_buckets() {
        use crate::word_hash::WordHasher;
        use std::hash::{BuildHasher, BuildHasherDefault};
        let build = BuildHasherDefault::<WordHasher>::default();
        let message = |id: u64| [&b"m"[..], &id.to_be_bytes()].concat();
        let index = |seq: u64| [&b"i"[..], &7u64.to_be_bytes(), &seq.to_be_bytes()].concat();
        for stride in [1u64, 2, 256, 4096, 1 << 16, 1 << 40] {
            for key in [&message as &dyn Fn(u64) -> Vec<u8>, &index] {
                let mut buckets = vec![0u32; 8192];
                let mut tags = std::collections::HashSet::new();
                for n in 0..4096u64 {
                    let hash = build.hash_one(LogKey::new(&key(n * stride + (5 << 40))));
                    buckets[(hash % 8192) as usize] += 1;
                    tags.insert(hash >> 57);
                }
                let fullest = buckets.iter().max().copied().unwrap_or(0);
                assert!(fullest <= 8, "stride {stride}: {fullest} in one bucket");
                assert!(tags.len() >= 100, "stride {stride}: {} tags", tags.len());
            }
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
