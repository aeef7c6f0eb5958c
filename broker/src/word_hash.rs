//! A hasher for small integer keys the broker's hot paths look up per
//! frame or per op: a multiply per word (FxHash's), a few cycles where
//! std's SipHash takes tens of nanoseconds.
//!
//! Only for keys whose chosen collisions cost little: numbers the broker
//! hands out itself (message ids, queue positions), or a peer's channel
//! numbers, of which there are at most 65,536, so however a peer picks
//! them a lookup probes a bounded, short run. Never for names or other
//! byte strings a peer chooses freely: those keep SipHash.
//!
//! Uses only std.

use std::collections::HashMap;
use std::hash::{BuildHasherDefault, Hasher};

/// A `HashMap` hashed by [`WordHasher`].
pub type WordHashMap<K, V> = HashMap<K, V, BuildHasherDefault<WordHasher>>;

/// Hashes a key word by word: rotate, xor, multiply by an odd constant.
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
        self.0
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

    #[test]
    fn channels_a_peer_picks_to_collide_are_still_found_quickly() {
        // Every number sharing its low bits: the worst a peer can choose.
        let mut map = WordHashMap::default();
        for n in (0..=u16::MAX).step_by(64) {
            map.insert(n, n);
        }
        assert!((0..=u16::MAX).step_by(64).all(|n| map.get(&n) == Some(&n)));
        assert_eq!(map.len(), 1024);
    }
}
