//! The flush: the head synced, then its flushed length recorded (see
//! `bookkeeping` for why a confirm may follow), then retention's share of
//! the work: dead segments deleted and a little compacted; the index given
//! back room once a backlog has drained.
//!
//! Uses `retention`, `state`, `bookkeeping`, `files` and `index`.

use super::bookkeeping::{FlushedRecord, FLUSHED};
use super::files::{io_error, segment_path};
use super::format::HEADER;
use super::state::MessageLog;
use crate::store::StoreError;

/// The index is given back room once it holds under a quarter of it (and
/// has room for more than this many keys): a hash map never shrinks by
/// itself, so a drained backlog would keep its size until a restart.
const INDEX_ROOM_KEPT: usize = 4096;

impl MessageLog {
    /// Makes every write so far durable; then deletes the oldest segments
    /// with nothing live, and compacts a little.
    pub fn flush(&self) -> Result<(), StoreError> {
        let mut state = self.state();
        if state.dirty {
            let number = state.head_number;
            state
                .head
                .sync_data()
                .map_err(|e| io_error(&segment_path(&self.dir, number), e))?;
            state.dirty = false;
            // Recorded only now, after the sync, and before any confirm
            // for what it covers is sent (see `bookkeeping`'s docs).
            let record = FlushedRecord {
                sequence: state.flushed.sequence + 1,
                segment: number,
                length: state.index.segments.get(&number).map_or(HEADER, |s| s.size),
            };
            record
                .write(&state.flushed_file)
                .map_err(|e| io_error(&self.dir.join(FLUSHED.name), e))?;
            state.flushed = record;
        }
        let keys = &mut state.index.keys;
        if keys.capacity() > INDEX_ROOM_KEPT && keys.capacity() > 4 * keys.len() {
            keys.shrink_to(2 * keys.len());
        }
        self.delete_dead(&mut state)?;
        self.compact(&mut state)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::store::log::testing::*;
    use crate::store::log::{Bookkeeping, OnDamage};
    use crate::store::KvOp;

    #[test]
    fn the_index_gives_back_room_once_a_backlog_drains() {
        let dir = temp_dir("index-room");
        let log = MessageLog::open(&dir, OnDamage::Refuse, Bookkeeping::Adopted).unwrap();
        let keys: Vec<String> = (0..100_000).map(|n| format!("k{n}")).collect();
        let puts: Vec<KvOp> = keys.iter().map(|k| put(k, "v")).collect();
        log.write(&puts, false).unwrap();
        log.flush().unwrap();
        let full = log.state().index.keys.capacity();
        assert!(full >= 100_000);
        let removes: Vec<KvOp> = keys[10..].iter().map(|k| remove(k)).collect();
        log.write(&removes, false).unwrap();
        log.flush().unwrap();
        let left = log.state().index.keys.capacity();
        assert!(left <= INDEX_ROOM_KEPT.max(64), "{full} -> {left}");
        assert_eq!(pairs(&log).len(), 10);
        drop(log);
        let _ = std::fs::remove_dir_all(&dir);
    }
}
