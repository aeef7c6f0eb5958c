//! The log in memory: where each live key's current value lies (segment,
//! offset, length), and per segment how many bytes are still live. Values
//! are read back only by [`MessageLog::scan`] and by compaction.
//!
//! Uses `key`, `format`'s records and the broker's `word_hash`.
//!
//! [`MessageLog::scan`]: super::MessageLog::scan

use super::format::Record;
use super::key::LogKey;
use crate::word_hash::WordHashMap;
use std::collections::{BTreeMap, HashSet};

/// Where a live key's current value lies.
#[derive(Debug, Clone, Copy)]
pub(super) struct Location {
    pub(super) segment: u64,
    /// The value's offset in the segment file.
    pub(super) offset: u64,
    pub(super) len: u32,
}

/// What the log knows of one segment.
#[derive(Debug, Clone, Copy, Default)]
pub(super) struct Segment {
    /// Where its data ends (the end of its last good batch; the head's
    /// end mark lies there).
    pub(super) size: u64,
    /// Bytes of live values and keys in it.
    pub(super) live_bytes: u64,
    /// Live records in it.
    pub(super) live: u64,
}

/// Where every live key's value lies, and what is live in each segment.
#[derive(Debug, Default)]
pub(super) struct Index {
    pub(super) segments: BTreeMap<u64, Segment>,
    /// Hashed, not ordered: updated per message, sorted only by a scan.
    pub(super) keys: WordHashMap<LogKey, Location>,
    /// While salvaging: keys whose latest put, or removal, lay in an
    /// unreadable batch (see [`Losses`](super::Losses)).
    pub(super) unread_puts: HashSet<Vec<u8>>,
    pub(super) unread_removals: HashSet<Vec<u8>>,
}

impl Index {
    /// Records a put of `key` at `location`, retiring its older value.
    pub(super) fn put(&mut self, key: &[u8], location: Location) {
        self.supersede(key);
        let weight = location.len as u64 + key.len() as u64;
        if let Some(old) = self.keys.insert(LogKey::new(key), location) {
            self.retire(key.len(), old);
        }
        let segment = self.segments.entry(location.segment).or_default();
        segment.live += 1;
        segment.live_bytes += weight;
    }

    pub(super) fn remove(&mut self, key: &[u8]) {
        self.supersede(key);
        if let Some(old) = self.keys.remove(&LogKey::new(key)) {
            self.retire(key.len(), old);
        }
    }

    /// A readable write of `key` replaces whatever an unreadable batch
    /// before it did to the key (only while salvaging is there any).
    fn supersede(&mut self, key: &[u8]) {
        if !self.unread_puts.is_empty() || !self.unread_removals.is_empty() {
            self.unread_puts.remove(key);
            self.unread_removals.remove(key);
        }
    }

    /// Counts a value of a `key_len`-byte key at `old` as dead.
    fn retire(&mut self, key_len: usize, old: Location) {
        if let Some(segment) = self.segments.get_mut(&old.segment) {
            segment.live -= 1;
            segment.live_bytes -= old.len as u64 + key_len as u64;
        }
    }

    /// Applies a batch payload that starts at `offset` of `segment`.
    pub(super) fn apply(&mut self, segment: u64, payload_offset: u64, records: Vec<Record<'_>>) {
        for record in records {
            match record {
                Record::Put { key, value, at } => self.put(
                    key,
                    Location {
                        segment,
                        offset: payload_offset + at as u64,
                        len: value.len() as u32,
                    },
                ),
                Record::Remove { key } => self.remove(key),
                Record::Seal => {}
            }
        }
    }
}
