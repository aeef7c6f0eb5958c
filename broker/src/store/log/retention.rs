//! Space: once every record of the oldest segments is dead (removed or
//! overwritten later) they are deleted, oldest first, so a removal always
//! lies in the same or a later segment than what it removes. A segment at
//! most half live that is the oldest is compacted: its live records are
//! appended again at the head, a bounded amount per flush, and the segment
//! is deleted after a later flush has made the copies durable. A message
//! held for a long time therefore pins at most its own bytes, never the
//! log behind it. A deleted segment's file may be kept as a spare, for
//! `files` to recycle.
//!
//! Uses `append` (compaction appends its copies), `state`, `format`,
//! `files`, `bookkeeping` and `index`.

use super::bookkeeping::Listed;
use super::files::{io_error, segment_path, sync_dir};
use super::format::{parse_records, Record, BATCH_HEADER, HEADER};
use super::key::LogKey;
use super::state::{MessageLog, State};
use crate::store::{KvOp, StoreError};
use std::fs::File;
use std::os::unix::fs::FileExt;

/// Dead segments' files kept for recycling at most (more are deleted).
pub(super) const SPARES: usize = 2;
/// Live bytes compaction copies per flush at most (the persister thread
/// stays responsive: a flush's extra work is bounded).
const COMPACT_BYTES: u64 = 1024 * 1024;

impl MessageLog {
    /// Deletes the oldest segments while they hold nothing live (never the
    /// head), oldest first: the segment list first leaves them out, then
    /// they go, with one sync of the directory. A deleted segment's file
    /// is kept as a spare while there are fewer than [`SPARES`].
    pub(super) fn delete_dead(&self, state: &mut State) -> Result<(), StoreError> {
        let dead: Vec<u64> = state
            .index
            .segments
            .iter()
            .take_while(|(&number, segment)| number != state.head_number && segment.live == 0)
            .map(|(&number, _)| number)
            .collect();
        let Some(&newest_dead) = dead.last() else {
            return Ok(());
        };
        let listed = Listed {
            first: newest_dead + 1,
            ..state.listed
        };
        self.record_list(state, listed)?;
        for number in dead {
            let path = segment_path(&self.dir, number);
            if state.spares.len() < SPARES {
                let spare = path.with_extension("spare");
                std::fs::rename(&path, &spare).map_err(|e| io_error(&path, e))?;
                state.spares.push(spare);
            } else {
                std::fs::remove_file(&path).map_err(|e| io_error(&path, e))?;
            }
            state.index.segments.remove(&number);
            if state.compacting.is_some_and(|(s, _)| s == number) {
                state.compacting = None;
            }
        }
        sync_dir(&self.dir)
    }

    /// Copies up to [`COMPACT_BYTES`] of the oldest segment's live records
    /// to the head, if it is at most half live (and not the head).
    pub(super) fn compact(&self, state: &mut State) -> Result<(), StoreError> {
        let Some((&oldest, segment)) = state.index.segments.first_key_value() else {
            return Ok(());
        };
        if oldest == state.head_number || segment.live_bytes * 2 > segment.size {
            return Ok(());
        }
        let end = segment.size;
        let mut at = match state.compacting {
            Some((s, at)) if s == oldest => at,
            _ => HEADER,
        };
        let path = segment_path(&self.dir, oldest);
        let file = File::open(&path).map_err(|e| io_error(&path, e))?;
        let mut moved: Vec<KvOp> = Vec::new();
        let mut moved_bytes = 0;
        while at < end && moved_bytes < COMPACT_BYTES {
            let mut header = [0; BATCH_HEADER];
            file.read_exact_at(&mut header, at)
                .map_err(|e| io_error(&path, e))?;
            let len = u32::from_le_bytes(header[..4].try_into().expect("4 bytes")) as usize;
            let payload_at = at + BATCH_HEADER as u64;
            if payload_at + len as u64 > end {
                // Read whole at open or written since: a file changed
                // under the log. Never allocate what it claims.
                return Err(StoreError::Engine(
                    format!("message log {}: a batch changed", path.display()).into(),
                ));
            }
            let mut payload = vec![0; len];
            file.read_exact_at(&mut payload, payload_at)
                .map_err(|e| io_error(&path, e))?;
            // It was checked when read at open or written since.
            let records = parse_records(&payload).ok_or_else(|| {
                StoreError::Engine(
                    format!("message log {}: a batch changed", path.display()).into(),
                )
            })?;
            for record in records {
                if let Record::Put { key, value, at } = record {
                    let live =
                        state.index.keys.get(&LogKey::new(key)).is_some_and(|l| {
                            l.segment == oldest && l.offset == payload_at + at as u64
                        });
                    if live {
                        moved_bytes += value.len() as u64;
                        moved.push((key.to_vec(), Some(value.to_vec())));
                    }
                }
            }
            at = payload_at + len as u64;
        }
        state.compacting = Some((oldest, at));
        if !moved.is_empty() {
            self.append(state, &moved)?;
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use crate::store::log::files::segment_path;
    use crate::store::log::format::BATCH_HEADER;
    use crate::store::log::testing::*;
    use crate::store::log::{Bookkeeping, MessageLog, OnDamage};

    #[test]
    fn dead_segments_are_deleted_oldest_first() {
        let dir = temp_dir("delete");
        let log =
            MessageLog::open_sized(&dir, OnDamage::Refuse, Bookkeeping::Adopted, 256).unwrap();
        for round in 0..20 {
            let key = format!("k{round}");
            log.write(&[put(&key, &"x".repeat(100))], false).unwrap();
            log.flush().unwrap();
            log.write(&[remove(&key)], false).unwrap();
            log.flush().unwrap();
        }
        // Everything is dead: only the head (and perhaps the segment it
        // followed) remain.
        assert!(files(&dir).len() <= 2, "{:?}", files(&dir));
        assert!(pairs(&log).is_empty());
        drop(log);
        let _ = std::fs::remove_dir_all(&dir);
    }

    #[test]
    fn a_long_held_record_is_moved_forward_instead_of_pinning_the_log() {
        let dir = temp_dir("compact");
        let log =
            MessageLog::open_sized(&dir, OnDamage::Refuse, Bookkeeping::Adopted, 512).unwrap();
        log.write(&[put("pinned", "held for a long time")], false)
            .unwrap();
        for round in 0..200 {
            let key = format!("k{round}");
            log.write(&[put(&key, &"x".repeat(100))], false).unwrap();
            log.write(&[remove(&key)], false).unwrap();
            log.flush().unwrap();
        }
        assert!(files(&dir).len() <= 3, "{:?}", files(&dir));
        assert_eq!(
            pairs(&log),
            vec![("pinned".into(), "held for a long time".into())]
        );
        drop(log);
        let log =
            MessageLog::open_sized(&dir, OnDamage::Refuse, Bookkeeping::Adopted, 512).unwrap();
        assert_eq!(
            pairs(&log),
            vec![("pinned".into(), "held for a long time".into())]
        );
        drop(log);
        let _ = std::fs::remove_dir_all(&dir);
    }

    #[test]
    fn dead_segments_files_are_recycled_and_their_old_batches_never_return() {
        let dir = temp_dir("recycle");
        let value = "v".repeat(50);
        // Segment 1: put a, remove a (then full).
        let log = MessageLog::open_sized(&dir, OnDamage::Refuse, Bookkeeping::Adopted, 90).unwrap();
        log.write(&[put("a", &value)], false).unwrap();
        log.write(&[remove("a")], false).unwrap();
        let removal_at = data_end(&log) - 12;
        // Segment 2 takes b; segment 1, dead, is kept as a spare.
        log.write(&[put("b", &value)], false).unwrap();
        log.write(&[remove("b")], false).unwrap();
        log.flush().unwrap();
        let spare = segment_path(&dir, 1).with_extension("spare");
        let old = std::fs::read(&spare).unwrap();
        assert_eq!(files(&dir), vec![2]);
        // Segment 3 starts in segment 1's file: a new put of a the same
        // size ends where the old removal of a began.
        let new_value = "n".repeat(50);
        log.write(&[put("a", &new_value)], false).unwrap();
        assert!(!spare.exists(), "the spare was recycled");
        assert_eq!(log.state().head_number, 3);
        assert_eq!(data_end(&log), removal_at);
        drop(log);
        // A power cut loses the end mark's bytes: the old removal's header
        // is back after the new put.
        let path = segment_path(&dir, 3);
        let mut bytes = std::fs::read(&path).unwrap();
        let at = removal_at as usize;
        bytes[at..at + BATCH_HEADER].copy_from_slice(&old[at..at + BATCH_HEADER]);
        std::fs::write(&path, bytes).unwrap();
        let log = MessageLog::open_sized(&dir, OnDamage::Refuse, Bookkeeping::Adopted, 90).unwrap();
        assert_eq!(pairs(&log), vec![("a".into(), new_value)]);
        drop(log);
        let _ = std::fs::remove_dir_all(&dir);
    }
}
