//! The message log: an append-only key-value log in numbered segment files,
//! for the keys written once or twice per message (which keys those are is
//! the codec's business; [`DiskStore`](super::DiskStore) routes them here).
//! A key-value engine built for that pattern: every write is an append,
//! a flush is one `fdatasync`, and nothing is rewritten in place.
//!
//! On disk: `<dir>/<number as 16 hex digits>.seg`. A segment starts with
//! a header (its format's magic, then its number, big-endian) and holds
//! batches: the payload's length and its CRC-32 (both `u32`
//! little-endian), then the payload, a run of records: `PUT` key-length
//! (`u16` LE) key value-length (`u32` LE) value, or `REMOVE` key-length
//! key. One [`MessageLog::write`] is one batch, so each write is atomic: a
//! batch is applied whole or, when its checksum fails, not at all. Each
//! batch is written with an end mark after it (a batch header of zeros)
//! that the next batch overwrites, so reading stops at the data's end
//! whatever the file holds beyond it; opening cuts off whatever the newest
//! segment holds beyond it that is not zeros (see below).
//!
//! Format 2 (`LVRTLOG2`) checksums the segment's number with each payload;
//! format 1 (`LVRTLOG1`, read and appended to, never started) does not.
//! That lets a dead segment's file be recycled as a later segment: its
//! blocks are already allocated, so appending to it changes no file size
//! and a sync writes back data only (a fresh segment is extended with
//! zeros ahead of its data for the same reason, which costs writing those
//! zeros back as well), and a batch left from the file's earlier life
//! never passes as the new segment's own, even when a power cut lost the
//! end mark that hid it. Spare files wait as `<dir>/<old number>.spare`.
//!
//! In memory: where each live key's current value lies (segment, offset,
//! length), and per segment how many bytes are still live. Values are read
//! back only by [`MessageLog::scan`] and by compaction.
//!
//! Space: once every record of the oldest segments is dead (removed or
//! overwritten later) they are deleted, oldest first, so a removal always
//! lies in the same or a later segment than what it removes. A segment at
//! most half live that is the oldest is compacted: its live records are
//! appended again at the head, a bounded amount per flush, and the segment
//! is deleted after a later flush has made the copies durable. A message
//! held for a long time therefore pins at most its own bytes, never the
//! log behind it.
//!
//! Bookkeeping: two small files, each two checksummed 32-byte slots in
//! different sectors, written by turn (a write torn by a power cut spoils
//! only its own slot; the other holds the record before it).
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
//! Crashes and damage: a new segment is started only after the previous
//! one is synced and sealed, so only the newest segment can end in a batch
//! that was cut short, and only at or past its recorded flushed length:
//! opening truncates it there, which loses nothing that was confirmed, and
//! says so. Everything else is damage, and opening fails naming the file
//! and the offset: a bad batch, zeros or a file end below the flushed
//! length or before a segment's seal, a damaged header, a segment the list
//! names that is missing, a missing or unreadable list or flushed record
//! ([`Bookkeeping::Required`]: a log opened before it kept them, or a new
//! one, [`Bookkeeping::Adopted`], gets them written from what is found).
//! Salvaging ([`OnDamage::Salvage`]) keeps every readable batch: after a
//! bad stretch it goes on at the next offset where a whole batch passes
//! its checksum (format 2 checksums hold the segment's number, so a
//! stretch of another segment's or a recycled file's batches never
//! passes), notes each lost stretch and the keys the batches there held
//! when they still parse without their checksums ([`Losses`]), then
//! writes every readable record into a new log that takes the damaged
//! one's place (the caller has copied it aside).
//! An end mark ends a segment's data wherever it lies past what the
//! segment must reach. In the newest, bytes beyond the end are a
//! recycled file's earlier life, or batches written after the last flush
//! that a power cut kept while losing one before them (page caches and
//! disks write back out of order); opening truncates the segment at its
//! end, so a later batch whose end mark a second power cut loses never
//! uncovers them.
//!
//! Uses the standard library, `crc32fast` and the broker's `word_hash`;
//! called from the persister thread (every call takes the log's one lock).

use super::log_key::LogKey;
use super::slots::{SlotFile, SlotRecord};
use super::{KvOp, KvPair, StoreError};
use crate::word_hash::WordHashMap;
use std::collections::{BTreeMap, HashMap, HashSet};
use std::fs::{File, OpenOptions};
use std::os::unix::fs::FileExt;
use std::path::{Path, PathBuf};
use std::sync::Mutex;

/// A segment file's first bytes, per format.
const MAGIC_V1: &[u8; 8] = b"LVRTLOG1";
const MAGIC_V2: &[u8; 8] = b"LVRTLOG2";
/// A segment's header: the magic and its number.
const HEADER: u64 = 16;
/// A batch's header: payload length and checksum.
const BATCH_HEADER: usize = 8;
/// The end mark written after each batch: a batch header of zeros.
const END_MARK: [u8; BATCH_HEADER] = [0; BATCH_HEADER];
/// Dead segments' files kept for recycling at most (more are deleted).
const SPARES: usize = 2;
/// Record tags.
const PUT: u8 = 1;
const REMOVE: u8 = 2;
/// The last record of a segment that is complete (see `rotate`).
const SEAL: u8 = 3;
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
/// The index is given back room once it holds under a quarter of it (and
/// has room for more than this many keys): a hash map never shrinks by
/// itself, so a drained backlog would keep its size until a restart.
const INDEX_ROOM_KEPT: usize = 4096;
/// Live bytes compaction copies per flush at most (the persister thread
/// stays responsive: a flush's extra work is bounded).
const COMPACT_BYTES: u64 = 1024 * 1024;

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
const SEGMENT_LIST: SlotFile = SlotFile {
    name: "segments",
    magic: b"LVSL",
    what: "segment list",
};
const FLUSHED: SlotFile = SlotFile {
    name: "flushed",
    magic: b"LVFL",
    what: "flushed length",
};

/// Opens a bookkeeping file for writing; when it is new, `first` is
/// written to it and synced, with the directory.
fn open_kept(dir: &Path, kept: SlotFile, first: SlotRecord) -> Result<File, StoreError> {
    kept.open(dir, first)
        .map_err(|e| io_error(&kept.path(dir), e))
}

/// The oldest and the newest segment the log holds, as its list says.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
struct Listed {
    first: u64,
    last: u64,
}

/// The segment list in `dir`, or what is wrong with it (a list whose
/// oldest lies past its newest is wrong).
fn read_segment_list(dir: &Path) -> Result<Option<(u64, Listed)>, String> {
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
/// once per [`SEGMENT_BYTES`] written).
fn write_segment_list(
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
struct FlushedRecord {
    sequence: u64,
    segment: u64,
    length: u64,
}

impl FlushedRecord {
    fn as_record(self) -> SlotRecord {
        SlotRecord {
            sequence: self.sequence,
            words: [self.segment, self.length],
        }
    }

    /// Writes it to its slot (one `pwrite`, no sync: see the module docs).
    fn write(self, file: &File) -> std::io::Result<()> {
        FLUSHED.write(file, self.as_record())
    }
}

/// The flushed-length file in `dir`: `None` if there is none, or what is
/// wrong with it.
fn read_flushed(dir: &Path) -> Result<Option<FlushedRecord>, String> {
    Ok(FLUSHED.read(dir)?.map(|record| FlushedRecord {
        sequence: record.sequence,
        segment: record.words[0],
        length: record.words[1],
    }))
}

/// How a segment's batches are checksummed (see the module docs).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Format {
    /// The payload only.
    V1,
    /// The segment's number, then the payload.
    V2,
}

impl Format {
    fn of_magic(magic: &[u8]) -> Option<Format> {
        match magic {
            m if m == MAGIC_V1 => Some(Format::V1),
            m if m == MAGIC_V2 => Some(Format::V2),
            _ => None,
        }
    }

    fn checksum(self, segment: u64, payload: &[u8]) -> u32 {
        let mut hasher = crc32fast::Hasher::new();
        if self == Format::V2 {
            hasher.update(&segment.to_be_bytes());
        }
        hasher.update(payload);
        hasher.finalize()
    }
}

/// Where a live key's current value lies.
#[derive(Debug, Clone, Copy)]
struct Location {
    segment: u64,
    /// The value's offset in the segment file.
    offset: u64,
    len: u32,
}

/// What the log knows of one segment.
#[derive(Debug, Clone, Copy, Default)]
struct Segment {
    /// Where its data ends (the end of its last good batch; the head's
    /// end mark lies there).
    size: u64,
    /// Bytes of live values and keys in it.
    live_bytes: u64,
    /// Live records in it.
    live: u64,
}

/// Where every live key's value lies, and what is live in each segment.
#[derive(Debug, Default)]
struct Index {
    segments: BTreeMap<u64, Segment>,
    /// Hashed, not ordered: updated per message, sorted only by a scan.
    keys: WordHashMap<LogKey, Location>,
    /// While salvaging: keys whose latest put, or removal, lay in an
    /// unreadable batch (see [`Losses`]).
    unread_puts: HashSet<Vec<u8>>,
    unread_removals: HashSet<Vec<u8>>,
}

/// The log's state: the index and the head open for appending.
#[derive(Debug)]
struct State {
    index: Index,
    /// The newest segment, open for appending.
    head: File,
    head_number: u64,
    head_format: Format,
    /// The head file's length: its data, then zeros or a recycled file's
    /// old bytes.
    head_len: u64,
    /// Dead segments' files waiting to be recycled, at most [`SPARES`].
    spares: Vec<PathBuf>,
    /// Where compaction of the oldest segment has got (segment, offset).
    compacting: Option<(u64, u64)>,
    /// Whether the head has writes not yet synced.
    dirty: bool,
    /// The segment list's file, its last record's sequence number and
    /// what it says.
    list_file: File,
    list_sequence: u64,
    listed: Listed,
    /// The flushed-length file, and the last record written to it.
    flushed_file: File,
    flushed: FlushedRecord,
}

/// How the message log treats damage when it is opened.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum OnDamage {
    /// Fail, naming the file and what is wrong.
    Refuse,
    /// Keep every readable batch: go on after a bad one at the next valid
    /// one, note what was lost ([`MessageLog::losses`]) and rebuild the
    /// log from what was read.
    Salvage,
}

/// An append-only key-value log in segment files (see the module docs).
#[derive(Debug)]
pub struct MessageLog {
    dir: PathBuf,
    segment_bytes: u64,
    state: Mutex<State>,
    /// What opening it with [`OnDamage::Salvage`] could not keep.
    losses: Losses,
}

fn io_error(path: &Path, e: std::io::Error) -> StoreError {
    StoreError::Engine(format!("message log {}: {e}", path.display()).into())
}

fn segment_path(dir: &Path, number: u64) -> PathBuf {
    dir.join(format!("{number:016x}.seg"))
}

/// The segment numbers in `dir`, ascending; other files are ignored.
fn segment_numbers(dir: &Path) -> Result<Vec<u64>, StoreError> {
    let mut numbers = Vec::new();
    for entry in std::fs::read_dir(dir).map_err(|e| io_error(dir, e))? {
        let name = entry.map_err(|e| io_error(dir, e))?.file_name();
        let name = name.to_string_lossy();
        if let Some(hex) = name.strip_suffix(".seg") {
            if let Ok(number) = u64::from_str_radix(hex, 16) {
                numbers.push(number);
            }
        }
    }
    numbers.sort_unstable();
    Ok(numbers)
}

fn sync_dir(dir: &Path) -> Result<(), StoreError> {
    File::open(dir)
        .and_then(|d| d.sync_all())
        .map_err(|e| io_error(dir, e))
}

/// One record of a batch, borrowed from the payload.
enum Record<'a> {
    Put {
        key: &'a [u8],
        value: &'a [u8],
        at: usize,
    },
    Remove {
        key: &'a [u8],
    },
    Seal,
}

/// Parses a batch payload's records; `None` if it is malformed.
fn parse_records(payload: &[u8]) -> Option<Vec<Record<'_>>> {
    let mut records = Vec::new();
    let mut at = 0;
    let take = |at: &mut usize, n: usize| -> Option<&[u8]> {
        let slice = payload.get(*at..at.checked_add(n)?)?;
        *at += n;
        Some(slice)
    };
    while at < payload.len() {
        let tag = take(&mut at, 1)?[0];
        if tag == SEAL {
            records.push(Record::Seal);
            continue;
        }
        let key_len = u16::from_le_bytes(take(&mut at, 2)?.try_into().ok()?);
        let key = take(&mut at, usize::from(key_len))?;
        match tag {
            PUT => {
                let len = u32::from_le_bytes(take(&mut at, 4)?.try_into().ok()?);
                let value_at = at;
                let value = take(&mut at, len as usize)?;
                records.push(Record::Put {
                    key,
                    value,
                    at: value_at,
                });
            }
            REMOVE => records.push(Record::Remove { key }),
            _ => return None,
        }
    }
    Some(records)
}

/// `ops` as one framed batch for segment `segment` of `format`, built in
/// place (the records after room for the header, then the header filled
/// in, then the end mark), and where each put's value lies from the
/// batch's start (`None` for a remove).
fn encode_batch(
    ops: &[KvOp],
    format: Format,
    segment: u64,
) -> Result<(Vec<u8>, Vec<Option<u64>>), StoreError> {
    // An empty format 1 batch would read as an end mark.
    debug_assert!(!ops.is_empty(), "a batch holds at least one op");
    let size: usize = ops
        .iter()
        .map(|(key, value)| 7 + key.len() + value.as_ref().map_or(0, Vec::len))
        .sum();
    let mut batch = Vec::with_capacity(2 * BATCH_HEADER + size);
    batch.resize(BATCH_HEADER, 0);
    let mut values = Vec::with_capacity(ops.len());
    for (key, value) in ops {
        let key_len = u16::try_from(key.len())
            .map_err(|_| StoreError::Engine("a message log key over 64 KB".into()))?;
        match value {
            Some(value) => {
                let len = u32::try_from(value.len())
                    .map_err(|_| StoreError::Engine("a message log value over 4 GB".into()))?;
                batch.push(PUT);
                batch.extend_from_slice(&key_len.to_le_bytes());
                batch.extend_from_slice(key);
                batch.extend_from_slice(&len.to_le_bytes());
                values.push(Some(batch.len() as u64));
                batch.extend_from_slice(value);
            }
            None => {
                batch.push(REMOVE);
                batch.extend_from_slice(&key_len.to_le_bytes());
                batch.extend_from_slice(key);
                values.push(None);
            }
        }
    }
    let payload_len = u32::try_from(batch.len() - BATCH_HEADER)
        .map_err(|_| StoreError::Engine("a message log batch over 4 GB".into()))?;
    let crc = format.checksum(segment, &batch[BATCH_HEADER..]);
    batch[..4].copy_from_slice(&payload_len.to_le_bytes());
    batch[4..8].copy_from_slice(&crc.to_le_bytes());
    batch.extend_from_slice(&END_MARK);
    Ok((batch, values))
}

/// A seal batch for segment `segment` of `format`, with its end mark.
fn seal_batch(format: Format, segment: u64) -> Vec<u8> {
    let mut batch = Vec::with_capacity(2 * BATCH_HEADER + 1);
    batch.extend_from_slice(&1u32.to_le_bytes());
    batch.extend_from_slice(&format.checksum(segment, &[SEAL]).to_le_bytes());
    batch.push(SEAL);
    batch.extend_from_slice(&END_MARK);
    batch
}

/// How far a segment's data must reach when it is read.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Reach {
    /// Through its seal: any segment but the newest.
    Seal,
    /// At least this far: the newest, whose recorded flushed length it is
    /// (every confirm was sent for data below it; see the module docs).
    Flushed(u64),
}

/// What reading a segment found.
struct Read {
    /// Its format, if its header is whole.
    format: Option<Format>,
    /// End of the last good batch.
    good_end: u64,
    /// Whether that batch is a seal.
    sealed: bool,
    /// Whether bytes other than zeros lie beyond the data's end.
    leftover: bool,
    /// Damage below what the segment must reach (when refusing).
    damage: Option<String>,
    /// A torn tail: what is wrong at or past the flushed length of the
    /// newest segment (never confirmed), where reading stopped.
    torn: Option<String>,
}

/// Bytes of the message log a salvage could not read.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct LostRange {
    /// The segment file.
    pub segment: PathBuf,
    /// The byte range lost, or `None` when the whole segment is missing.
    pub bytes: Option<(u64, u64)>,
    /// What was wrong there.
    pub problem: String,
}

/// What a salvage of the message log could not keep (see
/// [`MessageLog::losses`]).
#[derive(Debug, Default, Clone)]
pub struct Losses {
    /// Every range that could not be read, in log order.
    pub ranges: Vec<LostRange>,
    /// Keys whose latest put lay in an unreadable batch (read without its
    /// checksum) and no later readable write replaced: their values are
    /// gone. Sorted.
    pub puts: Vec<Vec<u8>>,
    /// Keys whose latest removal lay there: an older value comes back.
    /// Sorted.
    pub removals: Vec<Vec<u8>>,
    /// How many ranges did not parse even without their checksums (zeros,
    /// a cut file, a missing segment): what they held is unknown.
    pub unknown_ranges: usize,
    /// What was wrong with the segment list or the flushed length (no
    /// record is lost with them; the rebuilt log has new ones).
    pub bookkeeping: Vec<String>,
}

impl Losses {
    /// Whether nothing was damaged (the log is then not rebuilt).
    pub fn is_empty(&self) -> bool {
        self.ranges.is_empty() && self.bookkeeping.is_empty()
    }
}

/// A batch at the start of `rest` of segment `segment` in `format`: its
/// payload's length and records, or what is wrong with it.
fn check_batch(
    format: Format,
    segment: u64,
    rest: &[u8],
) -> Result<(usize, Vec<Record<'_>>), String> {
    if rest.len() < BATCH_HEADER {
        return Err(format!("{} bytes of a batch header", rest.len()));
    }
    let len = u32::from_le_bytes(rest[..4].try_into().expect("4 bytes")) as usize;
    let crc = u32::from_le_bytes(rest[4..8].try_into().expect("4 bytes"));
    match rest.get(BATCH_HEADER..BATCH_HEADER + len) {
        // A zero length with a checksum: never written by the log.
        Some([]) => Err("an empty batch".into()),
        None => Err(format!(
            "a batch of {len} bytes with only {} present",
            rest.len() - BATCH_HEADER
        )),
        // Cheap before the checksum, for a salvage trying every offset.
        Some([tag, ..]) if ![PUT, REMOVE, SEAL].contains(tag) => {
            Err("a batch whose records are malformed".into())
        }
        Some(payload) if format.checksum(segment, payload) != crc => {
            Err("a batch whose checksum fails".into())
        }
        Some(payload) => parse_records(payload)
            .map(|records| (len, records))
            .ok_or_else(|| "a batch whose records are malformed".into()),
    }
}

/// The first offset in `from..until` of `bytes` where a whole, valid batch
/// starts, for a salvage to go on after damage (format 2 batches checksum
/// their segment's number, so a recycled file's old batches never match).
fn resync(bytes: &[u8], from: usize, until: usize, format: Format, segment: u64) -> Option<usize> {
    (from..until.min(bytes.len())).find(|&at| check_batch(format, segment, &bytes[at..]).is_ok())
}

impl Index {
    /// Records a put of `key` at `location`, retiring its older value.
    fn put(&mut self, key: &[u8], location: Location) {
        self.supersede(key);
        let weight = location.len as u64 + key.len() as u64;
        if let Some(old) = self.keys.insert(LogKey::new(key), location) {
            self.retire(key.len(), old);
        }
        let segment = self.segments.entry(location.segment).or_default();
        segment.live += 1;
        segment.live_bytes += weight;
    }

    fn remove(&mut self, key: &[u8]) {
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
    fn apply(&mut self, segment: u64, payload_offset: u64, records: Vec<Record<'_>>) {
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

    /// Notes what the unreadable `bytes` held, read as batches without
    /// their checksums (the puts and removals a salvage reports lost);
    /// whether they all parsed.
    fn note_unreadable(&mut self, bytes: &[u8]) -> bool {
        let mut at = 0;
        while at < bytes.len() {
            let Some(header) = bytes.get(at..at + BATCH_HEADER) else {
                return false;
            };
            let len = u32::from_le_bytes(header[..4].try_into().expect("4 bytes")) as usize;
            let Some(records) = bytes
                .get(at + BATCH_HEADER..at + BATCH_HEADER + len)
                .filter(|payload| !payload.is_empty())
                .and_then(parse_records)
            else {
                return false;
            };
            for record in records {
                match record {
                    Record::Put { key, .. } => {
                        self.unread_removals.remove(key);
                        self.unread_puts.insert(key.to_vec());
                    }
                    Record::Remove { key } => {
                        self.unread_puts.remove(key);
                        self.unread_removals.insert(key.to_vec());
                    }
                    Record::Seal => {}
                }
            }
            at += BATCH_HEADER + len;
        }
        true
    }

    /// Reads segment `number`'s batches into the index. Damage below
    /// `reach` is reported as such when refusing; when salvaging, each bad
    /// stretch is noted in `losses` and reading goes on at the next valid
    /// batch. Whatever is wrong at or past a newest segment's flushed
    /// length is a torn tail: reading stops there.
    fn read_segment(
        &mut self,
        dir: &Path,
        number: u64,
        reach: Reach,
        on_damage: OnDamage,
        losses: &mut Losses,
    ) -> Result<Read, StoreError> {
        let path = segment_path(dir, number);
        let bytes = std::fs::read(&path).map_err(|e| io_error(&path, e))?;
        self.segments.entry(number).or_default();
        let header_format = bytes.get(..8).and_then(Format::of_magic);
        let header_format =
            header_format.filter(|_| bytes.get(8..16) == Some(&number.to_be_bytes()));
        let mut read = Read {
            format: header_format,
            good_end: HEADER,
            sealed: false,
            leftover: false,
            damage: None,
            torn: None,
        };
        let mut lose = |index: &mut Index, from: usize, to: usize, problem: String| {
            if !index.note_unreadable(&bytes[from..to]) {
                losses.unknown_ranges += 1;
            }
            losses.ranges.push(LostRange {
                segment: path.clone(),
                bytes: Some((from as u64, to as u64)),
                problem,
            });
        };
        let format = match (header_format, on_damage) {
            (Some(format), _) => format,
            (None, OnDamage::Refuse) => {
                read.good_end = 0;
                read.damage = Some("its header is missing or wrong".into());
                return Ok(read);
            }
            // Read on as the format every segment is started in.
            (None, OnDamage::Salvage) => {
                let end = bytes.len().min(HEADER as usize);
                lose(self, 0, end, "its header is missing or wrong".into());
                Format::V2
            }
        };
        let until = match reach {
            Reach::Seal => bytes.len(),
            Reach::Flushed(flushed) => (flushed as usize).min(bytes.len()),
        };
        let mut at = HEADER as usize;
        let mut sealed = false;
        loop {
            let must_go_on = match reach {
                Reach::Seal => !sealed,
                Reach::Flushed(flushed) => (at as u64) < flushed,
            };
            let rest = &bytes[at.min(bytes.len())..];
            let ended = rest[..rest.len().min(BATCH_HEADER)].iter().all(|&b| b == 0);
            let issue = if ended {
                // The end mark, the zeros a head was extended with, or the
                // end of the file.
                if !must_go_on {
                    break;
                }
                let what = if rest.is_empty() {
                    format!("the file ends at offset {at}")
                } else {
                    format!("zeros at offset {at}")
                };
                match reach {
                    Reach::Seal => format!("{what}, before its seal (truncated or zeroed)"),
                    Reach::Flushed(flushed) => format!(
                        "{what}, below the {flushed} bytes recorded as flushed (truncated or \
                         zeroed)"
                    ),
                }
            } else {
                match check_batch(format, number, rest) {
                    Ok((len, records)) => {
                        sealed = matches!(records[..], [Record::Seal]);
                        self.apply(number, (at + BATCH_HEADER) as u64, records);
                        at += BATCH_HEADER + len;
                        continue;
                    }
                    Err(problem) => format!("at offset {at}: {problem}"),
                }
            };
            if matches!(reach, Reach::Flushed(flushed) if at as u64 >= flushed) {
                read.torn = Some(issue);
                break;
            }
            match on_damage {
                OnDamage::Refuse => {
                    read.damage = Some(issue);
                    break;
                }
                OnDamage::Salvage => {
                    let next = resync(&bytes, at + 1, until, format, number);
                    let from = at.min(bytes.len());
                    lose(self, from, next.unwrap_or(bytes.len()).max(from), issue);
                    match next {
                        Some(next) => at = next,
                        None => {
                            // Nothing readable follows: what the segment
                            // held after the damage is gone.
                            at = bytes.len();
                            break;
                        }
                    }
                }
            }
        }
        read.good_end = at as u64;
        read.sealed = sealed;
        read.leftover = bytes
            .get(at..)
            .is_some_and(|rest| rest.iter().any(|&b| b != 0));
        Ok(read)
    }
}

/// The spare files in `dir` (dead segments' files kept for recycling).
fn spare_paths(dir: &Path) -> Result<Vec<PathBuf>, StoreError> {
    let mut spares = Vec::new();
    for entry in std::fs::read_dir(dir).map_err(|e| io_error(dir, e))? {
        let path = entry.map_err(|e| io_error(dir, e))?.path();
        if path.extension().is_some_and(|e| e == "spare") {
            spares.push(path);
        }
    }
    Ok(spares)
}

/// Starts segment `number` in format 2: in a spare file if there is one
/// (renamed, its old bytes left after the new header's end mark), else in
/// a new file; header synced, and the directory synced so the file is
/// there after a power cut. Returns the file and its length.
fn create_segment(
    dir: &Path,
    number: u64,
    spares: &mut Vec<PathBuf>,
) -> Result<(File, u64), StoreError> {
    let path = segment_path(dir, number);
    let recycled = match spares.pop() {
        Some(spare) => match std::fs::rename(&spare, &path) {
            Ok(()) => true,
            Err(e) => {
                tracing::warn!(spare = %spare.display(), error = %e, "could not recycle a spare message log file");
                spares.push(spare);
                false
            }
        },
        None => false,
    };
    let file = OpenOptions::new()
        .create(true)
        .truncate(!recycled)
        .write(true)
        .read(true)
        .open(&path)
        .map_err(|e| io_error(&path, e))?;
    let mut header = MAGIC_V2.to_vec();
    header.extend_from_slice(&number.to_be_bytes());
    header.extend_from_slice(&END_MARK);
    file.write_all_at(&header, 0)
        .and_then(|()| file.sync_data())
        .map_err(|e| io_error(&path, e))?;
    sync_dir(dir)?;
    let len = file.metadata().map_err(|e| io_error(&path, e))?.len();
    Ok((file, len))
}

/// Truncates segment `number` to `len` bytes, durably.
fn truncate_segment(dir: &Path, number: u64, len: u64) -> Result<(), StoreError> {
    let path = segment_path(dir, number);
    OpenOptions::new()
        .write(true)
        .open(&path)
        .and_then(|f| f.set_len(len).and_then(|()| f.sync_all()))
        .map_err(|e| io_error(&path, e))
}

impl MessageLog {
    /// Opens the log in `dir` (created if missing), reading every
    /// segment; see the module docs for what counts as damage.
    pub fn open(
        dir: &Path,
        on_damage: OnDamage,
        bookkeeping: Bookkeeping,
    ) -> Result<MessageLog, StoreError> {
        MessageLog::open_sized(dir, on_damage, bookkeeping, SEGMENT_BYTES)
    }

    /// [`MessageLog::open`] with segments of `segment_bytes` (small ones
    /// exercise rotation and compaction in tests).
    pub fn open_sized(
        dir: &Path,
        on_damage: OnDamage,
        bookkeeping: Bookkeeping,
        segment_bytes: u64,
    ) -> Result<MessageLog, StoreError> {
        let rebuilt = dir.with_extension("rebuilt");
        if !dir.exists() && rebuilt.exists() {
            // A rebuild stopped between its two renames: the rebuilt log
            // was whole and synced before the first.
            std::fs::rename(&rebuilt, dir).map_err(|e| io_error(dir, e))?;
        }
        std::fs::create_dir_all(dir).map_err(|e| io_error(dir, e))?;
        let (state, losses) = load(dir, on_damage, bookkeeping)?;
        let log = MessageLog {
            dir: dir.to_owned(),
            segment_bytes,
            state: Mutex::new(state),
            losses,
        };
        if log.losses.is_empty() {
            return Ok(log);
        }
        log.rebuild()
    }

    /// What opening with [`OnDamage::Salvage`] could not keep (empty
    /// otherwise).
    pub fn losses(&self) -> &Losses {
        &self.losses
    }

    /// After a salvage that lost something: writes every readable record
    /// into a new log beside this one, synced, and puts it in this one's
    /// place, so the next start finds a whole log (the caller has copied
    /// the damaged one aside).
    fn rebuild(self) -> Result<MessageLog, StoreError> {
        let pairs = self.scan()?;
        let rebuilt = self.dir.with_extension("rebuilt");
        let replaced = self.dir.with_extension("replaced");
        for stale in [&rebuilt, &replaced] {
            if stale.exists() {
                std::fs::remove_dir_all(stale).map_err(|e| io_error(stale, e))?;
            }
        }
        {
            let fresh = MessageLog::open_sized(
                &rebuilt,
                OnDamage::Refuse,
                Bookkeeping::Adopted,
                self.segment_bytes,
            )?;
            let puts: Vec<KvOp> = pairs
                .into_iter()
                .map(|(key, value)| (key, Some(value)))
                .collect();
            if !puts.is_empty() {
                fresh.write(&puts, false)?;
            }
            fresh.flush()?;
        }
        let MessageLog {
            dir,
            segment_bytes,
            state,
            losses,
        } = self;
        drop(state);
        let parent = dir.parent().unwrap_or(Path::new("."));
        std::fs::rename(&dir, &replaced)
            .and_then(|()| std::fs::rename(&rebuilt, &dir))
            .map_err(|e| io_error(&dir, e))?;
        sync_dir(parent)?;
        std::fs::remove_dir_all(&replaced).map_err(|e| io_error(&replaced, e))?;
        let (state, _) = load(&dir, OnDamage::Refuse, Bookkeeping::Required)?;
        Ok(MessageLog {
            dir,
            segment_bytes,
            state: Mutex::new(state),
            losses,
        })
    }

    fn state(&self) -> std::sync::MutexGuard<'_, State> {
        self.state.lock().unwrap_or_else(|e| e.into_inner())
    }

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
    fn append(&self, state: &mut State, ops: &[KvOp]) -> Result<(), StoreError> {
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
    fn rotate(&self, state: &mut State) -> Result<(), StoreError> {
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
            // for what it covers is sent (see the module docs).
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

    /// Records `listed` in the segment list, synced.
    fn record_list(&self, state: &mut State, listed: Listed) -> Result<(), StoreError> {
        let sequence = state.list_sequence + 1;
        write_segment_list(&self.dir, &state.list_file, sequence, listed)?;
        state.list_sequence = sequence;
        state.listed = listed;
        Ok(())
    }

    /// Deletes the oldest segments while they hold nothing live (never the
    /// head), oldest first: the segment list first leaves them out, then
    /// they go, with one sync of the directory. A deleted segment's file
    /// is kept as a spare while there are fewer than [`SPARES`].
    fn delete_dead(&self, state: &mut State) -> Result<(), StoreError> {
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
    fn compact(&self, state: &mut State) -> Result<(), StoreError> {
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

    /// Every live key and value, in key order.
    pub fn scan(&self) -> Result<Vec<KvPair>, StoreError> {
        let state = self.state();
        let mut files: HashMap<u64, Vec<u8>> = HashMap::new();
        // Sorted as copies side by side: sorting references into the hash
        // table would chase a pointer per comparison (with a million keys,
        // that alone took most of a second at start-up).
        let mut live: Vec<(LogKey, Location)> = state
            .index
            .keys
            .iter()
            .map(|(key, location)| (key.clone(), *location))
            .collect();
        live.sort_unstable_by(|a, b| a.0.cmp(&b.0));
        let mut pairs = Vec::with_capacity(live.len());
        for (key, location) in live {
            let path = segment_path(&self.dir, location.segment);
            let bytes = match files.entry(location.segment) {
                std::collections::hash_map::Entry::Occupied(file) => file.into_mut(),
                std::collections::hash_map::Entry::Vacant(slot) => {
                    slot.insert(std::fs::read(&path).map_err(|e| io_error(&path, e))?)
                }
            };
            let start = location.offset as usize;
            let value = bytes
                .get(start..start + location.len as usize)
                .ok_or_else(|| {
                    StoreError::Engine(
                        format!("message log {}: shorter than indexed", path.display()).into(),
                    )
                })?;
            pairs.push((key.to_vec(), value.to_vec()));
        }
        Ok(pairs)
    }

    /// Reads the log again from disk (after a failed write or flush):
    /// what is durable, and a cut-short last batch truncated.
    pub fn reopen(&self) -> Result<(), StoreError> {
        let mut state = self.state();
        *state = load(&self.dir, OnDamage::Refuse, Bookkeeping::Required)?.0;
        Ok(())
    }
}

/// Reads every segment in `dir` into a fresh state (see the module docs
/// for damage), with the newest open for appending; when salvaging, also
/// what could not be read (the caller then rebuilds the log: nothing here
/// changes a damaged segment).
fn load(
    dir: &Path,
    on_damage: OnDamage,
    bookkeeping: Bookkeeping,
) -> Result<(State, Losses), StoreError> {
    let mut losses = Losses::default();
    let mut problems: Vec<String> = Vec::new();
    // Refusing, the first problem is the answer; salvaging, each is noted
    // and reading goes on.
    let mut damage = |problem: String, losses: &mut Losses, lost: Option<LostRange>| {
        if on_damage == OnDamage::Refuse {
            return Err(StoreError::Damaged {
                path: dir.to_owned(),
                problem,
            });
        }
        match lost {
            Some(lost) => losses.ranges.push(lost),
            None => losses.bookkeeping.push(problem.clone()),
        }
        problems.push(problem);
        Ok(())
    };
    let present = segment_numbers(dir)?;
    let listed = match (read_segment_list(dir), bookkeeping) {
        (Ok(Some(found)), _) => Some(found),
        (Ok(None), Bookkeeping::Adopted) => None,
        (Ok(None), Bookkeeping::Required) => {
            let path = dir.join(SEGMENT_LIST.name);
            damage(
                format!("its segment list {} is missing", path.display()),
                &mut losses,
                None,
            )?;
            None
        }
        (Err(problem), _) => {
            damage(problem, &mut losses, None)?;
            None
        }
    };
    let flushed = match (read_flushed(dir), bookkeeping) {
        (Ok(found), Bookkeeping::Adopted) => found,
        (Ok(Some(found)), Bookkeeping::Required) => Some(found),
        (Ok(None), Bookkeeping::Required) => {
            let path = dir.join(FLUSHED.name);
            damage(
                format!("its flushed length {} is missing", path.display()),
                &mut losses,
                None,
            )?;
            None
        }
        (Err(problem), _) => {
            damage(problem, &mut losses, None)?;
            None
        }
    };
    let list_sequence = listed.map_or(0, |(sequence, _)| sequence);
    let listed = listed.map(|(_, listed)| listed);
    // The segments to read: those the list names, every one present
    // (and one past its newest: started by a rotation cut short before
    // the list named it, so holding nothing); without a list, those
    // found, without gaps.
    let mut numbers = Vec::new();
    match listed {
        Some(listed) => {
            for &number in &present {
                if number < listed.first && on_damage == OnDamage::Refuse {
                    // Retired, its deletion cut short: nothing in it lives.
                    let path = segment_path(dir, number);
                    std::fs::remove_file(&path).map_err(|e| io_error(&path, e))?;
                } else if number > listed.last + 1 {
                    damage(
                        format!(
                            "message log segment {} lies past the newest its list names ({})",
                            segment_path(dir, number).display(),
                            listed.last
                        ),
                        &mut losses,
                        None,
                    )?;
                } else if number >= listed.first {
                    numbers.push(number);
                }
            }
            for number in listed.first..=listed.last {
                if present.binary_search(&number).is_err() {
                    let path = segment_path(dir, number);
                    let problem = format!(
                        "message log segment {} is missing (its list says the log holds \
                         segments {} to {})",
                        path.display(),
                        listed.first,
                        listed.last
                    );
                    let lost = LostRange {
                        segment: path,
                        bytes: None,
                        problem: problem.clone(),
                    };
                    damage(problem, &mut losses, Some(lost))?;
                    losses.unknown_ranges += 1;
                }
            }
        }
        None => {
            if let Some(pair) = present.windows(2).find(|pair| pair[1] != pair[0] + 1) {
                let path = segment_path(dir, pair[0] + 1);
                let problem = format!("message log segment {} is missing", path.display());
                let lost = LostRange {
                    segment: path,
                    bytes: None,
                    problem: problem.clone(),
                };
                damage(problem, &mut losses, Some(lost))?;
                losses.unknown_ranges += 1;
            }
            numbers = present.clone();
        }
    }
    // A segment started by a rotation cut short (past the list's newest,
    // or without a list the newest) may hold no whole header: it never
    // held a batch, and goes.
    let unlisted = match listed {
        Some(listed) => numbers.last().filter(|&&n| n == listed.last + 1),
        None => numbers.last(),
    };
    if let Some(&number) = unlisted {
        let path = segment_path(dir, number);
        let bytes = std::fs::read(&path).map_err(|e| io_error(&path, e))?;
        let whole_header = bytes.get(..8).and_then(Format::of_magic).is_some()
            && bytes.get(8..16) == Some(&number.to_be_bytes());
        if !whole_header {
            tracing::warn!(segment = %path.display(), "removing a message log segment whose start was cut short");
            std::fs::remove_file(&path).map_err(|e| io_error(&path, e))?;
            numbers.pop();
        }
    }
    let newest = numbers.last().copied();
    // How far the newest segment must reach: its recorded flushed length;
    // nothing of a segment the record does not name yet was flushed.
    let newest_reach = match (flushed, newest) {
        (Some(record), Some(newest)) if record.segment == newest => record.length,
        (Some(record), Some(newest)) if record.segment > newest => {
            let problem = format!(
                "its flushed length names segment {}, past the newest present ({newest})",
                segment_path(dir, record.segment).display()
            );
            damage(problem, &mut losses, None)?;
            HEADER
        }
        _ => HEADER,
    };
    let mut index = Index::default();
    let mut head_format = Format::V2;
    for &number in &numbers {
        let path = segment_path(dir, number);
        let is_newest = Some(number) == newest;
        let reach = if is_newest {
            Reach::Flushed(newest_reach)
        } else {
            Reach::Seal
        };
        let read = index.read_segment(dir, number, reach, on_damage, &mut losses)?;
        if let Some(problem) = read.damage {
            return Err(StoreError::Damaged {
                path: dir.to_owned(),
                problem: format!("message log segment {}: {problem}", path.display()),
            });
        }
        if let Some(problem) = &read.torn {
            tracing::warn!(
                segment = %path.display(),
                problem,
                flushed = newest_reach,
                "the message log ends in a batch written after its last recorded flush (a crash \
                 or power cut while writing); it is dropped: no confirm was sent for it"
            );
        }
        if read.good_end < HEADER {
            // Refusing, a bad header is damage (returned above); salvaging,
            // the segment is read on as format 2 and rebuilt.
            continue;
        }
        if is_newest && (read.torn.is_some() || read.leftover) && losses.is_empty() {
            // See the module docs: nothing beyond the end may be uncovered.
            truncate_segment(dir, number, read.good_end)?;
        }
        head_format = read.format.unwrap_or(Format::V2);
        index.segments.entry(number).or_default().size = read.good_end;
    }
    losses.puts = std::mem::take(&mut index.unread_puts).into_iter().collect();
    losses.puts.sort_unstable();
    losses.removals = std::mem::take(&mut index.unread_removals)
        .into_iter()
        .collect();
    losses.removals.sort_unstable();
    for problem in &problems {
        tracing::warn!(log = %dir.display(), problem, "message log damage found while salvaging");
    }
    let mut spares = spare_paths(dir)?;
    while spares.len() > SPARES {
        let extra = spares.pop().expect("more than SPARES");
        std::fs::remove_file(&extra).map_err(|e| io_error(&extra, e))?;
    }
    let (head_number, head, head_len) = match index.segments.last_key_value() {
        Some((&number, _)) => {
            let path = segment_path(dir, number);
            let head = OpenOptions::new()
                .read(true)
                .write(true)
                .open(&path)
                .map_err(|e| io_error(&path, e))?;
            let len = head.metadata().map_err(|e| io_error(&path, e))?.len();
            (number, head, len)
        }
        None => {
            let number = newest.or(listed.map(|l| l.last)).map_or(1, |n| n + 1);
            index.segments.insert(
                number,
                Segment {
                    size: HEADER,
                    ..Segment::default()
                },
            );
            head_format = Format::V2;
            let (head, len) = create_segment(dir, number, &mut spares)?;
            (number, head, len)
        }
    };
    let first = *index.segments.first_key_value().expect("the head").0;
    let now_listed = Listed {
        first,
        last: head_number,
    };
    let list_record = SlotRecord {
        sequence: list_sequence,
        words: [now_listed.first, now_listed.last],
    };
    let list_file = open_kept(dir, SEGMENT_LIST, list_record)?;
    let mut list_sequence = list_sequence;
    if losses.is_empty() && listed.is_some_and(|listed| listed != now_listed) {
        list_sequence += 1;
        write_segment_list(dir, &list_file, list_sequence, now_listed)?;
    }
    let flushed = flushed.unwrap_or(FlushedRecord {
        sequence: 0,
        segment: head_number,
        length: HEADER,
    });
    let flushed_file = open_kept(dir, FLUSHED, flushed.as_record())?;
    Ok((
        State {
            index,
            head,
            head_number,
            head_format,
            head_len,
            spares,
            compacting: None,
            dirty: false,
            list_file,
            list_sequence,
            listed: now_listed,
            flushed_file,
            flushed,
        },
        losses,
    ))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::store::slots::SLOT_AT;
    use proptest::prelude::*;

    fn temp_dir(name: &str) -> PathBuf {
        let dir = std::env::temp_dir().join(format!("leveret-log-{}-{name}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        dir
    }

    fn put(key: &str, value: &str) -> KvOp {
        (key.as_bytes().to_vec(), Some(value.as_bytes().to_vec()))
    }

    fn remove(key: &str) -> KvOp {
        (key.as_bytes().to_vec(), None)
    }

    fn pairs(log: &MessageLog) -> Vec<(String, String)> {
        log.scan()
            .unwrap()
            .into_iter()
            .map(|(k, v)| (String::from_utf8(k).unwrap(), String::from_utf8(v).unwrap()))
            .collect()
    }

    fn files(dir: &Path) -> Vec<u64> {
        segment_numbers(dir).unwrap()
    }

    /// Where the head's data ends.
    fn data_end(log: &MessageLog) -> u64 {
        let state = log.state();
        state.index.segments[&state.head_number].size
    }

    /// The newest segment loses its bytes from `from` to `to`, as a page
    /// cache that never wrote them back would: cut off, or zeros (the
    /// zeros the head was extended with).
    fn lose_tail(dir: &Path, from: u64, to: u64, zeroed: bool) {
        let newest = *files(dir).last().unwrap();
        let path = segment_path(dir, newest);
        if zeroed {
            let file = OpenOptions::new().write(true).open(&path).unwrap();
            file.write_all_at(&vec![0; (to - from) as usize], from)
                .unwrap();
        } else {
            truncate_segment(dir, newest, from).unwrap();
        }
    }

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
    fn a_batch_cut_short_at_the_end_is_dropped_and_writing_goes_on_after_the_good_data() {
        let dir = temp_dir("torn");
        let mut log = MessageLog::open(&dir, OnDamage::Refuse, Bookkeeping::Adopted).unwrap();
        log.write(&[put("a", "1")], false).unwrap();
        log.flush().unwrap();
        // Each time the last batch (not flushed) loses its last `cut`
        // bytes, cut off or left as the zeros after the data.
        for cut in 1..=8 {
            for zeroed in [false, true] {
                log.write(&[put("b", "2")], false).unwrap();
                let end = data_end(&log);
                drop(log);
                lose_tail(&dir, end - cut, end, zeroed);
                log = MessageLog::open(&dir, OnDamage::Refuse, Bookkeeping::Adopted).unwrap();
                assert_eq!(pairs(&log), vec![("a".into(), "1".into())], "cut {cut}");
                log.write(&[put("c", "3")], false).unwrap();
                log.flush().unwrap();
                drop(log);
                log = MessageLog::open(&dir, OnDamage::Refuse, Bookkeeping::Adopted).unwrap();
                assert_eq!(
                    pairs(&log),
                    vec![("a".into(), "1".into()), ("c".into(), "3".into())]
                );
                log.write(&[remove("c")], false).unwrap();
                log.flush().unwrap();
            }
        }
        drop(log);
        let _ = std::fs::remove_dir_all(&dir);
    }

    #[test]
    fn damage_before_the_last_segment_refuses_and_salvage_keeps_every_other_batch() {
        let dir = temp_dir("damage");
        let sizes: Vec<u64> = {
            let log =
                MessageLog::open_sized(&dir, OnDamage::Refuse, Bookkeeping::Adopted, 64).unwrap();
            for i in 0..6 {
                log.write(&[put(&format!("k{i}"), &"v".repeat(40))], false)
                    .unwrap();
            }
            log.flush().unwrap();
            let state = log.state();
            state.index.segments.values().map(|s| s.size).collect()
        };
        let numbers = files(&dir);
        assert!(numbers.len() >= 3, "{numbers:?}");
        let second = segment_path(&dir, numbers[1]);
        let mut bytes = std::fs::read(&second).unwrap();
        // The last byte of its value, before its seal batch.
        let in_value = (sizes[1] - BATCH_HEADER as u64 - 2) as usize;
        bytes[in_value] ^= 0xff;
        std::fs::write(&second, bytes).unwrap();
        let refused = MessageLog::open(&dir, OnDamage::Refuse, Bookkeeping::Adopted).unwrap_err();
        let message = refused.to_string();
        assert!(message.contains(&second.display().to_string()), "{message}");
        assert!(message.contains("checksum"), "{message}");
        let log = MessageLog::open(&dir, OnDamage::Salvage, Bookkeeping::Adopted).unwrap();
        let kept = pairs(&log);
        assert_eq!(kept.len(), 5, "only the damaged batch is lost: {kept:?}");
        drop(log);
        // Salvaged, it opens normally again.
        MessageLog::open(&dir, OnDamage::Refuse, Bookkeeping::Adopted).unwrap();
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

    /// Page caches and disks write back out of order: a power cut may
    /// keep a batch while losing the one before it. The kept one must not
    /// come back when a second power cut loses the end mark of the batch
    /// later written over the lost one.
    #[test]
    fn a_batch_kept_past_a_lost_one_never_returns_after_a_second_power_cut() {
        let dir = temp_dir("second-cut");
        let log = MessageLog::open(&dir, OnDamage::Refuse, Bookkeeping::Adopted).unwrap();
        log.write(&[put("a", "1")], false).unwrap();
        log.flush().unwrap();
        let synced_end = data_end(&log) as usize;
        log.write(&[put("b", "2")], false).unwrap();
        let b_end = data_end(&log) as usize;
        log.write(&[remove("a")], false).unwrap();
        drop(log);
        // The first cut loses b (its bytes go back to the synced end mark
        // and zeros) and keeps the removal of a after it.
        let path = segment_path(&dir, *files(&dir).last().unwrap());
        let mut bytes = std::fs::read(&path).unwrap();
        bytes[synced_end..b_end].fill(0);
        std::fs::write(&path, &bytes).unwrap();
        let log = MessageLog::open(&dir, OnDamage::Refuse, Bookkeeping::Adopted).unwrap();
        assert_eq!(pairs(&log), vec![("a".into(), "1".into())]);
        let on_disk = std::fs::read(&path).unwrap();
        // b again, the same size: its end mark lies where the removal's
        // header was. The second cut loses that end mark: those bytes go
        // back to what the disk held.
        log.write(&[put("b", "3")], false).unwrap();
        assert_eq!(data_end(&log) as usize, b_end);
        drop(log);
        let mut bytes = std::fs::read(&path).unwrap();
        for (at, byte) in bytes.iter_mut().enumerate().skip(b_end).take(BATCH_HEADER) {
            *byte = on_disk.get(at).copied().unwrap_or(0);
        }
        std::fs::write(&path, &bytes).unwrap();
        let log = MessageLog::open(&dir, OnDamage::Refuse, Bookkeeping::Adopted).unwrap();
        assert_eq!(
            pairs(&log),
            vec![("a".into(), "1".into()), ("b".into(), "3".into())]
        );
        drop(log);
        let _ = std::fs::remove_dir_all(&dir);
    }

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

    #[test]
    fn a_format_1_segment_is_read_and_appended_to() {
        let dir = temp_dir("format-1");
        std::fs::create_dir_all(&dir).unwrap();
        let mut bytes = MAGIC_V1.to_vec();
        bytes.extend_from_slice(&1u64.to_be_bytes());
        let (batch, _) = encode_batch(&[put("a", "1"), put("b", "2")], Format::V1, 1).unwrap();
        bytes.extend_from_slice(&batch);
        std::fs::write(segment_path(&dir, 1), bytes).unwrap();
        let log = MessageLog::open(&dir, OnDamage::Refuse, Bookkeeping::Adopted).unwrap();
        log.write(&[remove("a"), put("c", "3")], false).unwrap();
        log.flush().unwrap();
        drop(log);
        let log = MessageLog::open(&dir, OnDamage::Refuse, Bookkeeping::Adopted).unwrap();
        assert_eq!(
            pairs(&log),
            vec![("b".into(), "2".into()), ("c".into(), "3".into())]
        );
        assert_eq!(files(&dir), vec![1]);
        drop(log);
        let _ = std::fs::remove_dir_all(&dir);
    }

    #[test]
    fn a_missing_segment_is_damage() {
        let dir = temp_dir("missing");
        {
            let log =
                MessageLog::open_sized(&dir, OnDamage::Refuse, Bookkeeping::Adopted, 64).unwrap();
            for i in 0..6 {
                log.write(&[put(&format!("k{i}"), &"v".repeat(40))], false)
                    .unwrap();
            }
            log.flush().unwrap();
        }
        let numbers = files(&dir);
        std::fs::remove_file(segment_path(&dir, numbers[1])).unwrap();
        let message = MessageLog::open(&dir, OnDamage::Refuse, Bookkeeping::Adopted)
            .unwrap_err()
            .to_string();
        assert!(message.contains("missing"), "{message}");
        let _ = std::fs::remove_dir_all(&dir);
    }

    /// The size of each batch [`filled`] writes while keys have 2 bytes:
    /// its header, a put's tag, key length, key, value length and value.
    const FILLED_BATCH: u64 = BATCH_HEADER as u64 + 1 + 2 + 2 + 4 + 40;

    /// Writes `n` batches of one put each (`k0`, `k1`…), flushed, into a
    /// log of `segment_bytes` segments; returns the log's directory.
    fn filled(name: &str, n: usize, segment_bytes: u64) -> PathBuf {
        let dir = temp_dir(name);
        let log =
            MessageLog::open_sized(&dir, OnDamage::Refuse, Bookkeeping::Adopted, segment_bytes)
                .unwrap();
        for i in 0..n {
            log.write(&[put(&format!("k{i}"), &"v".repeat(40))], false)
                .unwrap();
            log.flush().unwrap();
        }
        dir
    }

    fn refused(dir: &Path) -> String {
        MessageLog::open(dir, OnDamage::Refuse, Bookkeeping::Required)
            .unwrap_err()
            .to_string()
    }

    /// The newest segment's data below its recorded flushed length was
    /// confirmed: a flipped byte, a cut or zeros there refuse the start,
    /// naming the segment (a torn tail is only ever past that length).
    #[test]
    fn damage_below_the_flushed_length_of_the_newest_segment_refuses() {
        for damage in ["flip", "truncate", "zero"] {
            let dir = filled(&format!("below-flushed-{damage}"), 5, SEGMENT_BYTES);
            let newest = segment_path(&dir, *files(&dir).last().unwrap());
            let flushed = read_flushed(&dir).unwrap().unwrap();
            assert_eq!(flushed.length, HEADER + 5 * FILLED_BATCH);
            let at = HEADER + 60;
            let file = OpenOptions::new().write(true).open(&newest).unwrap();
            match damage {
                "flip" => file.write_all_at(&[0x5a], at).unwrap(),
                "truncate" => file.set_len(at).unwrap(),
                _ => file.write_all_at(&[0; 64], at).unwrap(),
            }
            let message = refused(&dir);
            assert!(
                message.contains(&newest.display().to_string()),
                "{damage}: {message}"
            );
            let _ = std::fs::remove_dir_all(&dir);
        }
    }

    #[test]
    fn a_missing_newest_segment_every_segment_or_bookkeeping_file_refuses() {
        type Damage = fn(&Path);
        let cases: [(&str, Damage); 4] = [
            ("newest", |dir| {
                std::fs::remove_file(segment_path(dir, *files(dir).last().unwrap())).unwrap()
            }),
            ("all", |dir| {
                for number in files(dir) {
                    std::fs::remove_file(segment_path(dir, number)).unwrap();
                }
            }),
            ("list", |dir| {
                std::fs::remove_file(dir.join(SEGMENT_LIST.name)).unwrap()
            }),
            ("flushed", |dir| {
                std::fs::remove_file(dir.join(FLUSHED.name)).unwrap()
            }),
        ];
        for (name, damage) in cases {
            let dir = filled(&format!("missing-{name}"), 6, 64);
            assert!(files(&dir).len() >= 3);
            damage(&dir);
            let message = refused(&dir);
            assert!(message.contains("missing"), "{name}: {message}");
            let _ = std::fs::remove_dir_all(&dir);
        }
    }

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

    /// A rotation cut short between starting the next segment and listing
    /// it leaves one file past the list's newest, holding no batch (or
    /// not even a whole header): it is taken in, or removed. A segment
    /// further on is damage.
    #[test]
    fn a_segment_past_the_list_is_a_cut_short_rotation_or_damage() {
        let dir = filled("past-list", 6, 64);
        let newest = *files(&dir).last().unwrap();
        // The rotation sealed the head before starting the next segment.
        let end = MessageLog::open_sized(&dir, OnDamage::Refuse, Bookkeeping::Required, 64)
            .map(|log| data_end(&log))
            .unwrap();
        let file = OpenOptions::new()
            .write(true)
            .open(segment_path(&dir, newest))
            .unwrap();
        file.write_all_at(&seal_batch(Format::V2, newest), end)
            .unwrap();
        let mut header = MAGIC_V2.to_vec();
        header.extend_from_slice(&(newest + 1).to_be_bytes());
        std::fs::write(segment_path(&dir, newest + 1), &header).unwrap();
        let log =
            MessageLog::open_sized(&dir, OnDamage::Refuse, Bookkeeping::Required, 64).unwrap();
        assert_eq!(pairs(&log).len(), 6);
        assert_eq!(log.state().head_number, newest + 1);
        drop(log);
        let newest = newest + 1;
        std::fs::write(segment_path(&dir, newest + 1), &header[..5]).unwrap();
        let log =
            MessageLog::open_sized(&dir, OnDamage::Refuse, Bookkeeping::Required, 64).unwrap();
        assert_eq!(pairs(&log).len(), 6);
        assert!(!segment_path(&dir, newest + 1).exists());
        drop(log);
        std::fs::write(segment_path(&dir, newest + 2), &header).unwrap();
        let message = refused(&dir);
        assert!(message.contains("past the newest"), "{message}");
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

    /// Salvage goes on after a bad batch at the next valid one, reports
    /// exactly the put it lost, and leaves a whole log.
    #[test]
    fn salvage_resynchronises_after_a_bad_batch_and_reports_its_puts() {
        let dir = filled("resync", 10, SEGMENT_BYTES);
        let newest = segment_path(&dir, *files(&dir).last().unwrap());
        // Inside k3's value.
        let at = HEADER + 3 * FILLED_BATCH + 30;
        let file = OpenOptions::new().write(true).open(&newest).unwrap();
        file.write_all_at(&[0x5a], at).unwrap();
        assert!(refused(&dir).contains("checksum"));
        let log = MessageLog::open(&dir, OnDamage::Salvage, Bookkeeping::Required).unwrap();
        let kept: Vec<String> = pairs(&log).into_iter().map(|(k, _)| k).collect();
        assert_eq!(kept.len(), 9);
        assert!(!kept.contains(&"k3".to_owned()) && kept.contains(&"k9".to_owned()));
        let losses = log.losses();
        assert_eq!(losses.ranges.len(), 1);
        assert_eq!(losses.puts, vec![b"k3".to_vec()]);
        assert_eq!(losses.unknown_ranges, 0);
        drop(log);
        let log = MessageLog::open(&dir, OnDamage::Refuse, Bookkeeping::Required).unwrap();
        assert_eq!(pairs(&log).len(), 9);
        drop(log);
        let _ = std::fs::remove_dir_all(&dir);
    }

    /// A lost removal brings its key back, and is reported; a lost put
    /// whose key a later readable batch removed is no loss.
    #[test]
    fn salvage_reports_lost_removals_and_forgets_superseded_puts() {
        let dir = temp_dir("lost-removal");
        let log = MessageLog::open(&dir, OnDamage::Refuse, Bookkeeping::Adopted).unwrap();
        log.write(&[put("a", "1")], false).unwrap();
        let damaged = data_end(&log);
        log.write(&[remove("a"), put("b", "2")], false).unwrap();
        log.write(&[remove("b")], false).unwrap();
        log.flush().unwrap();
        drop(log);
        let path = segment_path(&dir, *files(&dir).last().unwrap());
        let file = OpenOptions::new().write(true).open(&path).unwrap();
        file.write_all_at(&[0xff], damaged + 4).unwrap();
        let log = MessageLog::open(&dir, OnDamage::Salvage, Bookkeeping::Required).unwrap();
        assert_eq!(pairs(&log), vec![("a".into(), "1".into())]);
        assert_eq!(log.losses().removals, vec![b"a".to_vec()]);
        assert!(log.losses().puts.is_empty());
        drop(log);
        let _ = std::fs::remove_dir_all(&dir);
    }

    /// Each segment or spare file's bytes as last seen, per file (inode)
    /// and per life (the segment number in its header), to model what a
    /// recycled file held before.
    #[derive(Default)]
    struct FileLives(HashMap<(u64, u64), Vec<u8>>);

    impl FileLives {
        fn observe(&mut self, dir: &Path) {
            use std::os::unix::fs::MetadataExt;
            for entry in std::fs::read_dir(dir).unwrap() {
                let path = entry.unwrap().path();
                if !path.extension().is_some_and(|e| e == "seg" || e == "spare") {
                    continue;
                }
                let bytes = std::fs::read(&path).unwrap();
                let number = u64::from_be_bytes(bytes[8..16].try_into().unwrap());
                let inode = std::fs::metadata(&path).unwrap().ino();
                self.0.insert((inode, number), bytes);
            }
        }

        /// What the file at `path` held in its life before segment
        /// `number` (nothing if it is new).
        fn earlier_life(&self, path: &Path, number: u64) -> Vec<u8> {
            use std::os::unix::fs::MetadataExt;
            let inode = std::fs::metadata(path).unwrap().ino();
            self.0
                .iter()
                .filter(|((i, n), _)| *i == inode && *n < number)
                .max_by_key(|((_, n), _)| *n)
                .map(|(_, bytes)| bytes.clone())
                .unwrap_or_default()
        }
    }

    #[derive(Debug, Clone)]
    enum Step {
        Put(u8, usize),
        Remove(u8),
        Flush,
        Reopen,
    }

    fn step() -> impl Strategy<Value = Step> {
        prop_oneof![
            4 => (0u8..24, 0usize..200).prop_map(|(k, n)| Step::Put(k, n)),
            3 => (0u8..24).prop_map(Step::Remove),
            2 => Just(Step::Flush),
            1 => Just(Step::Reopen),
        ]
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(64))]

        /// With tiny segments (rotation, deletion and compaction all the
        /// time), the log always holds exactly what a map would, across
        /// reopenings.
        #[test]
        fn the_log_behaves_like_a_map(steps in proptest::collection::vec(step(), 1..120)) {
            let dir = temp_dir("model");
            let mut model: BTreeMap<Vec<u8>, Vec<u8>> = BTreeMap::new();
            let mut log = MessageLog::open_sized(&dir, OnDamage::Refuse, Bookkeeping::Adopted, 300).unwrap();
            for (n, step) in steps.into_iter().enumerate() {
                match step {
                    Step::Put(k, len) => {
                        let value = vec![n as u8; len];
                        log.write(&[(vec![k], Some(value.clone()))], false).unwrap();
                        model.insert(vec![k], value);
                    }
                    Step::Remove(k) => {
                        log.write(&[(vec![k], None)], false).unwrap();
                        model.remove(&vec![k]);
                    }
                    Step::Flush => log.flush().unwrap(),
                    Step::Reopen => {
                        log.flush().unwrap();
                        drop(log);
                        log = MessageLog::open_sized(&dir, OnDamage::Refuse, Bookkeeping::Adopted, 300).unwrap();
                    }
                }
                let expected: Vec<KvPair> = model.clone().into_iter().collect();
                prop_assert_eq!(log.scan().unwrap(), expected);
            }
            drop(log);
            let _ = std::fs::remove_dir_all(&dir);
        }

        /// A power cut: the newest segment keeps what was synced plus any
        /// prefix of what was written after (as a page cache might); past
        /// that its file holds what it held at the last sync (for a
        /// recycled file, its earlier life's batches), then nothing or
        /// zeros, and the prefix's last byte is possibly garbage. The log
        /// opens on exactly the state after the last flush or after some
        /// later batch: nothing flushed is lost, no batch is applied in
        /// part or out of order, and no batch from a recycled file's
        /// earlier life comes back.
        #[test]
        fn a_power_cut_keeps_every_flushed_batch_and_a_prefix_of_the_rest(
            batches in proptest::collection::vec(
                (proptest::collection::vec((0u8..12, proptest::option::of(0usize..120)), 1..4), any::<bool>()),
                1..60,
            ),
            kept in any::<proptest::sample::Index>(),
            garbage in any::<bool>(),
            zeroed in any::<bool>(),
        ) {
            let dir = temp_dir("power-cut");
            let log = MessageLog::open_sized(&dir, OnDamage::Refuse, Bookkeeping::Adopted, 400).unwrap();
            let mut model: BTreeMap<Vec<u8>, Vec<u8>> = BTreeMap::new();
            let mut states = vec![Vec::new()];
            let mut flushed_states = 0;
            let mut files = FileLives::default();
            // The head's number, data end and bytes at the last flush.
            let mut synced: Option<(u64, u64, Vec<u8>)> = None;
            for (n, (ops, flush)) in batches.iter().enumerate() {
                let ops: Vec<KvOp> = ops
                    .iter()
                    .map(|(k, len)| (vec![*k], len.map(|len| vec![n as u8; len])))
                    .collect();
                log.write(&ops, false).unwrap();
                for (key, value) in ops {
                    match value {
                        Some(value) => model.insert(key, value),
                        None => model.remove(&key),
                    };
                }
                states.push(model.clone().into_iter().collect::<Vec<KvPair>>());
                if *flush {
                    log.flush().unwrap();
                    flushed_states = states.len() - 1;
                    let head = log.state().head_number;
                    let bytes = std::fs::read(segment_path(&dir, head)).unwrap();
                    synced = Some((head, data_end(&log), bytes));
                }
                files.observe(&dir);
            }
            let newest = log.state().head_number;
            let written = data_end(&log) + BATCH_HEADER as u64;
            drop(log);
            let path = segment_path(&dir, newest);
            let now = std::fs::read(&path).unwrap();
            let (synced_len, before) = match synced {
                Some((head, end, bytes)) if head == newest => (end, bytes),
                // Started since: its header and end mark were synced,
                // after them lie its earlier life's bytes, if it had one.
                _ => {
                    let marked = HEADER as usize + BATCH_HEADER;
                    let mut bytes = files.earlier_life(&path, newest);
                    bytes.resize(bytes.len().max(marked), 0);
                    bytes[..marked].copy_from_slice(&now[..marked]);
                    (HEADER, bytes)
                }
            };
            let cut = synced_len + kept.index((written - synced_len + 1) as usize) as u64;
            let mut after = now[..cut as usize].to_vec();
            if before.len() > after.len() {
                after.extend_from_slice(&before[after.len()..]);
            }
            if zeroed && now.len() > after.len() {
                after.resize(now.len(), 0);
            }
            if garbage && cut > synced_len {
                after[cut as usize - 1] ^= 0x5a;
            }
            std::fs::write(&path, &after).unwrap();
            // The bookkeeping files are as the page cache left them.
            let log = MessageLog::open_sized(&dir, OnDamage::Refuse, Bookkeeping::Required, 400).unwrap();
            let found = log.scan().unwrap();
            prop_assert!(
                states[flushed_states..].contains(&found),
                "found {:?}, flushed {:?}", found, states[flushed_states]
            );
            drop(log);
            let _ = std::fs::remove_dir_all(&dir);
        }

        /// A byte flipped anywhere in data a flush covered (any segment
        /// the list names, the newest up to its recorded flushed length)
        /// refuses the start: only a tail no confirm covered is dropped.
        #[test]
        fn a_flipped_byte_below_what_was_flushed_always_refuses(
            batches in proptest::collection::vec((0u8..12, 1usize..120, any::<bool>()), 1..40),
            which in any::<proptest::sample::Index>(),
            at in any::<proptest::sample::Index>(),
        ) {
            let dir = temp_dir("flip-flushed");
            let log = MessageLog::open_sized(&dir, OnDamage::Refuse, Bookkeeping::Adopted, 400).unwrap();
            for (key, len, removed) in &batches {
                let value = (!removed).then(|| vec![1; *len]);
                log.write(&[(vec![*key], value)], false).unwrap();
            }
            log.flush().unwrap();
            let spans: Vec<(u64, u64)> = {
                let state = log.state();
                state
                    .index
                    .segments
                    .iter()
                    .map(|(&number, segment)| {
                        let end = if number != state.head_number {
                            segment.size
                        } else if state.flushed.segment == number {
                            state.flushed.length
                        } else {
                            HEADER
                        };
                        (number, end)
                    })
                    .filter(|&(_, end)| end > HEADER)
                    .collect()
            };
            drop(log);
            prop_assume!(!spans.is_empty());
            let (number, end) = spans[which.index(spans.len())];
            let offset = HEADER + at.index((end - HEADER) as usize) as u64;
            let path = segment_path(&dir, number);
            let mut bytes = std::fs::read(&path).unwrap();
            bytes[offset as usize] ^= 0x5a;
            std::fs::write(&path, bytes).unwrap();
            let opened = MessageLog::open_sized(&dir, OnDamage::Refuse, Bookkeeping::Required, 400);
            prop_assert!(opened.is_err(), "segment {} offset {} of {}", number, offset, end);
            let _ = std::fs::remove_dir_all(&dir);
        }

        /// Whatever bytes a segment holds (its header cut or not), with or
        /// without bookkeeping files claiming any flushed length, opening
        /// never panics: it refuses or salvages, and a salvaged log then
        /// opens as a whole one.
        #[test]
        fn any_segment_bytes_open_without_panicking(
            tail in proptest::collection::vec(any::<u8>(), 0..200),
            cut in any::<proptest::sample::Index>(),
            older in any::<bool>(),
            first_format in any::<bool>(),
            claimed in proptest::option::of(0u64..400),
        ) {
            let dir = temp_dir("garbage");
            std::fs::create_dir_all(&dir).unwrap();
            let magic = if first_format { MAGIC_V1 } else { MAGIC_V2 };
            let mut bytes = magic.to_vec();
            bytes.extend_from_slice(&1u64.to_be_bytes());
            bytes.extend_from_slice(&tail);
            bytes.truncate(cut.index(bytes.len() + 1));
            std::fs::write(segment_path(&dir, 1), &bytes).unwrap();
            let newest = if older {
                let mut next = MAGIC_V2.to_vec();
                next.extend_from_slice(&2u64.to_be_bytes());
                std::fs::write(segment_path(&dir, 2), &next).unwrap();
                2
            } else {
                1
            };
            let bookkeeping = match claimed {
                Some(length) => {
                    let list = SlotRecord { sequence: 1, words: [1, newest] };
                    open_kept(&dir, SEGMENT_LIST, list).unwrap();
                    let record = FlushedRecord { sequence: 1, segment: newest, length };
                    open_kept(&dir, FLUSHED, record.as_record()).unwrap();
                    Bookkeeping::Required
                }
                None => Bookkeeping::Adopted,
            };
            let _ = MessageLog::open(&dir, OnDamage::Refuse, bookkeeping);
            let log = MessageLog::open(&dir, OnDamage::Salvage, bookkeeping).unwrap();
            log.write(&[(b"k".to_vec(), Some(b"v".to_vec()))], false).unwrap();
            log.flush().unwrap();
            drop(log);
            let log = MessageLog::open(&dir, OnDamage::Refuse, Bookkeeping::Required).unwrap();
            prop_assert!(log.scan().unwrap().contains(&(b"k".to_vec(), b"v".to_vec())));
            drop(log);
            let _ = std::fs::remove_dir_all(&dir);
        }
    }
}
