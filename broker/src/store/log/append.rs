//! The write path: each write appended to the head as batches (cut into
//! several when not atomic), indexed; a full head sealed, synced and
//! followed by a new segment, listed before any batch goes to it. Nothing
//! here is durable until `flush`.
//!
//! Uses `state`, `format`, `files`, `bookkeeping` and `index`.

use super::bookkeeping::{write_segment_list, Listed};
use super::files::{create_segment, io_error, segment_path};
use super::format::{encode_batch, seal_batch, Format, BATCH_HEADER, HEADER};
use super::index::{Location, Segment};
use super::state::{MessageLog, State};
use crate::store::{KvOp, StoreError};
use std::os::unix::fs::FileExt;

/// A new segment is started before a batch once the current one holds
/// this much (a segment is larger only by its last batch).
pub const SEGMENT_BYTES: u64 = 16 * 1024 * 1024;
/// Plain writes are cut into batches of about this many payload bytes, so
/// a batch's length always fits its `u32`.
const BATCH_BYTES: usize = 64 * 1024 * 1024;
/// The head is extended with zeros this far ahead of its data (at most a
/// segment), so most syncs change no file size and cost one device flush
/// instead of a journal commit as well.
const PREFILL_BYTES: u64 = 2 * 1024 * 1024;

impl MessageLog {
    /// Appends `ops` (as one batch when `atomic`; plain writes may be cut
    /// into several). Not durable until [`MessageLog::flush`].
    pub fn write(&self, ops: &[KvOp], atomic: bool) -> Result<(), StoreError> {
        let mut state = self.state();
        let mut start = 0;
        while start < ops.len() {
            let mut end = start;
            let mut bytes = 0;
            while end < ops.len() && (atomic || bytes < BATCH_BYTES) {
                let (key, value) = &ops[end];
                bytes += 7 + key.len() + value.as_ref().map_or(0, Vec::len);
                end += 1;
            }
            self.append(&mut state, &ops[start..end])?;
            start = end;
        }
        Ok(())
    }

    /// Appends `ops` as one batch to the head (starting a new segment first
    /// if the head is full), then indexes them. A failed append is cut off
    /// again, so the next one follows good data.
    pub(super) fn append(&self, state: &mut State, ops: &[KvOp]) -> Result<(), StoreError> {
        let size = state
            .index
            .segments
            .get(&state.head_number)
            .map_or(0, |s| s.size);
        if size >= self.segment_bytes {
            self.rotate(state)?;
        }
        let number = state.head_number;
        let (batch, values) = encode_batch(ops, state.head_format, number)?;
        let offset = self.write_batch(state, &batch)?;
        for ((key, value), at) in ops.iter().zip(values) {
            match (value, at) {
                (Some(value), Some(at)) => state.index.put(
                    key,
                    Location {
                        segment: number,
                        offset: offset + at,
                        len: value.len() as u32,
                    },
                ),
                _ => state.index.remove(key),
            }
        }
        Ok(())
    }

    /// Writes a framed batch (with its end mark) at the end of the head's
    /// data, extending the file with zeros when the batch reaches its end;
    /// returns its offset. A failed write is cut off again (with the
    /// zeros), so the next one follows good data.
    fn write_batch(&self, state: &mut State, batch: &[u8]) -> Result<u64, StoreError> {
        let number = state.head_number;
        let offset = state.index.segments.get(&number).map_or(HEADER, |s| s.size);
        let marked_end = offset + batch.len() as u64;
        let mut written = state.head.write_all_at(batch, offset);
        if written.is_ok() && marked_end > state.head_len {
            let zeros_to = marked_end + PREFILL_BYTES.min(self.segment_bytes);
            let zeros = vec![0; (zeros_to - marked_end) as usize];
            written = state.head.write_all_at(&zeros, marked_end);
            if written.is_ok() {
                state.head_len = zeros_to;
            }
        }
        if let Err(e) = written {
            let _ = state.head.set_len(offset);
            state.head_len = offset;
            return Err(io_error(&segment_path(&self.dir, number), e));
        }
        state.dirty = true;
        // The data ends where its end mark starts.
        state.index.segments.entry(number).or_default().size = marked_end - BATCH_HEADER as u64;
        Ok(offset)
    }

    /// Seals the full head, syncs it and starts the next segment. Only the
    /// newest segment may lack its seal.
    pub(super) fn rotate(&self, state: &mut State) -> Result<(), StoreError> {
        let number = state.head_number;
        self.write_batch(state, &seal_batch(state.head_format, number))?;
        state
            .head
            .sync_data()
            .map_err(|e| io_error(&segment_path(&self.dir, number), e))?;
        state.dirty = false;
        let next = number + 1;
        let (head, head_len) = create_segment(&self.dir, next, &mut state.spares)?;
        // Listed before any batch is written to it: a segment past the
        // list's newest holds nothing (see `load`).
        let listed = Listed {
            last: next,
            ..state.listed
        };
        self.record_list(state, listed)?;
        state.head = head;
        state.head_number = next;
        state.head_format = Format::V2;
        state.head_len = head_len;
        state.index.segments.insert(
            next,
            Segment {
                size: HEADER,
                ..Segment::default()
            },
        );
        Ok(())
    }

    /// Records `listed` in the segment list, synced.
    pub(super) fn record_list(&self, state: &mut State, listed: Listed) -> Result<(), StoreError> {
        let sequence = state.list_sequence + 1;
        write_segment_list(&self.dir, &state.list_file, sequence, listed)?;
        state.list_sequence = sequence;
        state.listed = listed;
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use crate::store::log::testing::*;
    use crate::store::log::{Bookkeeping, MessageLog, OnDamage};

    #[test]
    fn writes_survive_reopening_with_overwrites_and_removes_applied() {
        let dir = temp_dir("reopen");
        {
            let log = MessageLog::open(&dir, OnDamage::Refuse, Bookkeeping::Adopted).unwrap();
            log.write(&[put("a", "1"), put("b", "2"), put("c", "3")], false)
                .unwrap();
            log.write(&[remove("a"), put("b", "22"), remove("zz")], true)
                .unwrap();
            log.flush().unwrap();
        }
        let log = MessageLog::open(&dir, OnDamage::Refuse, Bookkeeping::Adopted).unwrap();
        assert_eq!(
            pairs(&log),
            vec![("b".into(), "22".into()), ("c".into(), "3".into())]
        );
        drop(log);
        let _ = std::fs::remove_dir_all(&dir);
    }
}
