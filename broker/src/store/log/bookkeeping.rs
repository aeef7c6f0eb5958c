//! The log's bookkeeping: two small files, each two checksummed 32-byte
//! slots in different sectors, written by turn (a write torn by a power
//! cut spoils only its own slot; the other holds the record before it).
//! `<dir>/segments` lists the oldest and the newest segment the log holds;
//! it is written and synced (one `pwrite`, one `fdatasync`) when a segment
//! is started, after the new file is synced and before any batch goes to
//! it, and when segments are retired, before their files go. So a segment
//! past the list's newest never held a batch, one before its oldest holds
//! nothing live, and a torn write falls back to the list before it, which
//! was still true: nothing that relied on the new one had happened. Both
//! are rare (once per [`SEGMENT_BYTES`] written): no sync per message.
//! `<dir>/flushed` records how far the newest segment was synced: after
//! each group's `fdatasync` of the head, one `pwrite` of (sequence,
//! segment, length), never synced by itself.
//!
//! Why that proves what was confirmed: a confirm is sent only after
//! [`MessageLog::flush`] returns, and flush writes the record after the
//! sync. So every confirmed batch lies below the last record written.
//! After a kill -9 the page cache keeps that record exactly. After a power
//! cut the disk holds some earlier record, or this one (a torn slot fails
//! its checksum and the other slot, an earlier record, is read): each
//! was written after its length had been synced, so whatever record is
//! read is a length that was durable then, a lower bound of what was
//! confirmed: never more than what is on disk, the safe direction.
//! A record naming a segment older than the newest says nothing of the
//! newest was flushed yet (a rotation syncs the segment it seals, and the
//! next flush records the new head).
//!
//! Uses `files` and the store's `slots` and `StoreError`.
//!
//! [`SEGMENT_BYTES`]: super::append::SEGMENT_BYTES
//! [`MessageLog::flush`]: super::MessageLog::flush

use super::files::io_error;
use crate::store::slots::{SlotFile, SlotRecord};
use crate::store::StoreError;
use std::fs::File;
use std::path::Path;

/// How the log treats its bookkeeping files (the segment list and the
/// flushed length) when it is opened.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Bookkeeping {
    /// The log keeps them (its data directory's manifest says so): one
    /// missing is damage.
    Required,
    /// A new log, or one from before them: they are written from what is
    /// found.
    Adopted,
}

/// The log's two bookkeeping files (see the module docs), each two
/// checksummed slots written by turn (`super::slots`): the segment list
/// (the oldest and the newest segment the log holds; each write synced)
/// and the flushed length (the head's number and how much of it was last
/// synced; never synced by itself).
pub(super) const SEGMENT_LIST: SlotFile = SlotFile {
    name: "segments",
    magic: b"LVSL",
    what: "segment list",
};
pub(super) const FLUSHED: SlotFile = SlotFile {
    name: "flushed",
    magic: b"LVFL",
    what: "flushed length",
};

/// Opens a bookkeeping file for writing; when it is new, `first` is
/// written to it and synced, with the directory.
pub(super) fn open_kept(dir: &Path, kept: SlotFile, first: SlotRecord) -> Result<File, StoreError> {
    kept.open(dir, first)
        .map_err(|e| io_error(&kept.path(dir), e))
}

/// The oldest and the newest segment the log holds, as its list says.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) struct Listed {
    pub(super) first: u64,
    pub(super) last: u64,
}

/// The segment list in `dir`, or what is wrong with it (a list whose
/// oldest lies past its newest is wrong).
pub(super) fn read_segment_list(dir: &Path) -> Result<Option<(u64, Listed)>, String> {
    match SEGMENT_LIST.read(dir)? {
        Some(SlotRecord {
            sequence,
            words: [first, last],
        }) if first <= last => Ok(Some((sequence, Listed { first, last }))),
        Some(_) => Err(format!(
            "its segment list {} is unreadable",
            dir.join(SEGMENT_LIST.name).display()
        )),
        None => Ok(None),
    }
}

/// Writes `listed` as record `sequence` of the segment list, synced (one
/// `pwrite` and one `fdatasync`: segments are started and retired rarely,
/// once per [`SEGMENT_BYTES`](super::append::SEGMENT_BYTES) written).
pub(super) fn write_segment_list(
    dir: &Path,
    file: &File,
    sequence: u64,
    listed: Listed,
) -> Result<(), StoreError> {
    let record = SlotRecord {
        sequence,
        words: [listed.first, listed.last],
    };
    SEGMENT_LIST
        .write(file, record)
        .and_then(|()| file.sync_data())
        .map_err(|e| io_error(&dir.join(SEGMENT_LIST.name), e))
}

/// What the flushed-length file says.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) struct FlushedRecord {
    pub(super) sequence: u64,
    pub(super) segment: u64,
    pub(super) length: u64,
}

impl FlushedRecord {
    pub(super) fn as_record(self) -> SlotRecord {
        SlotRecord {
            sequence: self.sequence,
            words: [self.segment, self.length],
        }
    }

    /// Writes it to its slot (one `pwrite`, no sync: see the module docs).
    pub(super) fn write(self, file: &File) -> std::io::Result<()> {
        FLUSHED.write(file, self.as_record())
    }
}

/// The flushed-length file in `dir`: `None` if there is none, or what is
/// wrong with it.
pub(super) fn read_flushed(dir: &Path) -> Result<Option<FlushedRecord>, String> {
    Ok(FLUSHED.read(dir)?.map(|record| FlushedRecord {
        sequence: record.sequence,
        segment: record.words[0],
        length: record.words[1],
    }))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::store::log::append::SEGMENT_BYTES;
    use crate::store::log::testing::*;
    use crate::store::log::{MessageLog, OnDamage};
    use crate::store::slots::SLOT_AT;

    /// The list is rewritten as segments are started and retired, so it
    /// always names exactly the segments there are.
    #[test]
    fn the_segment_list_follows_rotation_and_retirement() {
        let dir = temp_dir("list");
        let log =
            MessageLog::open_sized(&dir, OnDamage::Refuse, Bookkeeping::Adopted, 128).unwrap();
        for round in 0..30 {
            let key = format!("k{round}");
            log.write(&[put(&key, &"x".repeat(60))], false).unwrap();
            log.flush().unwrap();
            if round % 3 != 0 {
                log.write(&[remove(&key)], false).unwrap();
                log.flush().unwrap();
            }
            let numbers = files(&dir);
            let (_, listed) = read_segment_list(&dir).unwrap().unwrap();
            assert_eq!(
                (listed.first, listed.last),
                (numbers[0], *numbers.last().unwrap())
            );
        }
        drop(log);
        MessageLog::open_sized(&dir, OnDamage::Refuse, Bookkeeping::Required, 128).unwrap();
        let _ = std::fs::remove_dir_all(&dir);
    }

    /// A torn slot (a power cut mid-write) falls back to the other one.
    #[test]
    fn a_torn_flushed_slot_falls_back_to_the_other() {
        let dir = filled("torn-slot", 3, SEGMENT_BYTES);
        let newest = read_flushed(&dir).unwrap().unwrap();
        let path = dir.join(FLUSHED.name);
        let mut bytes = std::fs::read(&path).unwrap();
        let at = SLOT_AT[(newest.sequence % 2) as usize] as usize;
        bytes[at + 20] ^= 1;
        std::fs::write(&path, &bytes).unwrap();
        let older = read_flushed(&dir).unwrap().unwrap();
        assert_eq!(older.sequence + 1, newest.sequence);
        assert!(older.length < newest.length);
        MessageLog::open(&dir, OnDamage::Refuse, Bookkeeping::Required).unwrap();
        let _ = std::fs::remove_dir_all(&dir);
    }
}
