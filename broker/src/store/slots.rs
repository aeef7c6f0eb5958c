//! Bookkeeping files of two checksummed slots written by turn: how the
//! message log keeps its segment list and flushed length, and how a
//! stream keeps how far it was synced. A record is a sequence number and
//! two words; it goes to slot `sequence % 2` with one `pwrite`, so the
//! other slot holds the record before it. The slots lie in different
//! sectors: a write torn by a power cut spoils at most the slot it was
//! writing, and reading takes the valid record with the highest sequence.
//! Whether a record is synced is the caller's choice (see the users'
//! module docs for why each is safe).
//!
//! Uses the standard library and `crc32fast`; no broker types.

use std::fs::{File, OpenOptions};
use std::io;
use std::os::unix::fs::FileExt;
use std::path::{Path, PathBuf};

/// A slot: magic, CRC-32 of the rest, then the record's sequence number
/// and its two words (`u64` LE each).
const SLOT: usize = 32;
/// Where the two slots lie (different sectors).
pub const SLOT_AT: [u64; 2] = [0, 512];

/// One kind of bookkeeping file: its name in its directory, its magic and
/// what it is called in messages.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct SlotFile {
    /// The file's name in its directory.
    pub name: &'static str,
    /// The first bytes of each slot.
    pub magic: &'static [u8; 4],
    /// What it is, for messages ("flushed length").
    pub what: &'static str,
}

/// One record of a bookkeeping file.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct SlotRecord {
    /// Increases with every record written; picks the slot.
    pub sequence: u64,
    /// What the record says (its file's kind defines them).
    pub words: [u64; 2],
}

impl SlotFile {
    /// Its path in `dir`.
    pub fn path(self, dir: &Path) -> PathBuf {
        dir.join(self.name)
    }

    fn encode(self, record: SlotRecord) -> [u8; SLOT] {
        let mut slot = [0; SLOT];
        slot[..4].copy_from_slice(self.magic);
        slot[8..16].copy_from_slice(&record.sequence.to_le_bytes());
        slot[16..24].copy_from_slice(&record.words[0].to_le_bytes());
        slot[24..32].copy_from_slice(&record.words[1].to_le_bytes());
        let crc = crc32fast::hash(&slot[8..]);
        slot[4..8].copy_from_slice(&crc.to_le_bytes());
        slot
    }

    fn decode(self, slot: &[u8]) -> Option<SlotRecord> {
        let slot: &[u8; SLOT] = slot.try_into().ok()?;
        let word = |at: usize| u64::from_le_bytes(slot[at..at + 8].try_into().expect("8 bytes"));
        let crc = u32::from_le_bytes(slot[4..8].try_into().expect("4 bytes"));
        (&slot[..4] == self.magic && crc32fast::hash(&slot[8..]) == crc).then(|| SlotRecord {
            sequence: word(8),
            words: [word(16), word(24)],
        })
    }

    /// Writes `record` to its slot of `file`: one `pwrite`, not synced.
    pub fn write(self, file: &File, record: SlotRecord) -> io::Result<()> {
        let at = SLOT_AT[(record.sequence % 2) as usize];
        file.write_all_at(&self.encode(record), at)
    }

    /// The newest valid record of this file in `dir`: `None` if there is
    /// no such file, or what is wrong with it.
    pub fn read(self, dir: &Path) -> Result<Option<SlotRecord>, String> {
        let path = self.path(dir);
        let bytes = match std::fs::read(&path) {
            Ok(bytes) => bytes,
            Err(e) if e.kind() == io::ErrorKind::NotFound => return Ok(None),
            Err(e) => {
                return Err(format!(
                    "cannot read its {} {}: {e}",
                    self.what,
                    path.display()
                ))
            }
        };
        SLOT_AT
            .iter()
            .filter_map(|&at| bytes.get(at as usize..at as usize + SLOT))
            .filter_map(|slot| self.decode(slot))
            .max_by_key(|record| record.sequence)
            .map(Some)
            .ok_or_else(|| format!("its {} {} is unreadable", self.what, path.display()))
    }

    /// Opens this file in `dir` for writing; when it is new, `first` is
    /// written to it and synced, with the directory.
    pub fn open(self, dir: &Path, first: SlotRecord) -> io::Result<File> {
        let path = self.path(dir);
        let existing = path.exists();
        let file = OpenOptions::new()
            .create(true)
            .truncate(false)
            .write(true)
            .open(&path)?;
        if !existing {
            self.write(&file, first)?;
            file.sync_all()?;
            File::open(dir)?.sync_all()?;
        }
        Ok(file)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const TEST: SlotFile = SlotFile {
        name: "test-slots",
        magic: b"LVTS",
        what: "test record",
    };

    fn dir(name: &str) -> PathBuf {
        let dir = std::env::temp_dir().join(format!("leveret-slots-{name}-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir).unwrap();
        dir
    }

    #[test]
    fn the_newest_record_is_read_and_a_torn_slot_falls_back_to_the_other() {
        let dir = dir("torn");
        assert_eq!(TEST.read(&dir), Ok(None));
        let first = SlotRecord {
            sequence: 1,
            words: [1, 2],
        };
        let file = TEST.open(&dir, first).unwrap();
        assert_eq!(TEST.read(&dir), Ok(Some(first)));
        let second = SlotRecord {
            sequence: 2,
            words: [3, 4],
        };
        TEST.write(&file, second).unwrap();
        assert_eq!(TEST.read(&dir), Ok(Some(second)));
        // A power cut tears the slot being written: the other is read.
        file.write_all_at(&[0xFF; 8], SLOT_AT[0] + 16).unwrap();
        assert_eq!(TEST.read(&dir), Ok(Some(first)));
        // Both torn: the file is unreadable, never taken as absent.
        file.write_all_at(&[0xFF; 8], SLOT_AT[1] + 16).unwrap();
        assert!(TEST.read(&dir).unwrap_err().contains("unreadable"));
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn opening_an_existing_file_keeps_what_it_holds() {
        let dir = dir("reopen");
        let first = SlotRecord {
            sequence: 7,
            words: [8, 9],
        };
        drop(TEST.open(&dir, first).unwrap());
        let other = SlotRecord {
            sequence: 1,
            words: [0, 0],
        };
        drop(TEST.open(&dir, other).unwrap());
        assert_eq!(TEST.read(&dir), Ok(Some(first)));
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
