//! A hasher for small integer keys the broker's hot paths look up per
//! frame or per op: a multiply per word (FxHash's), then a finishing mix
//! (xor-shift, multiply, xor-shift) that makes every bit of the result,
//! the low bits a hash table picks its bucket from included, depend on
//! every bit of the key; a few cycles where std's SipHash takes tens of
//! nanoseconds. (A multiply carries a word's bits only upward: without the
//! mix, keys that differ only in a word's top bits, such as big-endian
//! positions one apart, share a bucket.)
//!
//! Only for keys whose chosen collisions cost little: numbers the broker
//! hands out itself (message ids, queue positions), or a peer's channel
//! numbers, of which there are at most 65,536, so however a peer picks
//! them a lookup probes a bounded, short run. Never for names or other
//! byte strings a peer chooses freely: those keep SipHash.
//!
//! Uses only std.

use std::collections::{HashMap, HashSet};
use std::hash::{BuildHasherDefault, Hasher};

/// A `HashMap` hashed by [`WordHasher`].
pub type WordHashMap<K, V> = HashMap<K, V, BuildHasherDefault<WordHasher>>;

/// A `HashSet` hashed by [`WordHasher`].
pub type WordHashSet<K> = HashSet<K, BuildHasherDefault<WordHasher>>;

/// Hashes a key word by word: rotate, xor, multiply by an odd constant;
/// finishes with a mix that spreads every bit over the whole result.
#[derive(Debug, Default)]
pub struct WordHasher(u64);

impl Hasher for WordHasher {
    fn write(&mut self, bytes: &[u8]) {
        for &byte in bytes {
            self.write_u64(u64::from(byte));
        }
    }

    fn write_u16(&mut self, word: u16) {
        self.write_u64(u64::from(word));
    }

    fn write_u64(&mut self, word: u64) {
        self.0 = (self.0.rotate_left(5) ^ word).wrapping_mul(0x517c_c1b7_2722_0a95);
    }

    fn write_usize(&mut self, word: usize) {
        self.write_u64(word as u64);
    }

    fn finish(&self) -> u64 {
        let mixed = (self.0 ^ (self.0 >> 32)).wrapping_mul(0x9e37_79b9_7f4a_7c15);
        mixed ^ (mixed >> 29)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_channel_number_hashes_apart() {
        use std::hash::BuildHasher;
        let build = BuildHasherDefault::<WordHasher>::default();
        let hashes: std::collections::HashSet<u64> =
            (0..=u16::MAX).map(|n| build.hash_one(n)).collect();
        assert_eq!(hashes.len(), 65_536);
    }

    /// The worst a peer can choose: channel numbers that share their low
    /// bits (every stride up to 4096). In a table of 64 buckets, as many
    /// as hashbrown gives their count, no bucket gets more than a few.
    #[test]
    fn channels_a_peer_picks_to_collide_spread_over_the_buckets() {
        use std::hash::BuildHasher;
        let build = BuildHasherDefault::<WordHasher>::default();
        for stride in [1u16, 2, 16, 64, 256, 512, 1024, 4096] {
            let mut buckets = [0u32; 64];
            for n in (0..=u16::MAX).step_by(usize::from(stride)).take(56) {
                buckets[(build.hash_one(n) % 64) as usize] += 1;
            }
            let fullest = buckets.iter().max().copied().unwrap_or(0);
            assert!(fullest <= 6, "stride {stride}: {fullest} in one bucket");
        }
    }
}
