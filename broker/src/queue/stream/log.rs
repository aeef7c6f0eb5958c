//! A stream's on-disk log: records with monotonically increasing offsets,
//! appended to segment files in one directory, each record checksummed.
//! It owns the files and a sparse index (one entry per segment: its first
//! and next offset, its oldest and newest timestamps, its size), never the
//! records themselves, so memory does not grow with the stream's length.
//!
//! On disk: `<dir>/<first offset as 20 digits>.seg`. A segment starts
//! with [`MAGIC`] and its first offset (`u64` LE); then records: payload
//! length and CRC-32 (`u32` LE each), offset (`u64` LE), timestamp in
//! milliseconds (`i64` LE), flags (`u8`; [`CHUNK_START`]) and the payload.
//! The CRC covers everything after itself, so a record is taken whole or
//! not at all. A segment holds at most `max_segment_bytes` (one record more
//! if a single record is larger). Retention removes whole segments, oldest
//! first, never the newest ([`StreamLog::retain`]), as RabbitMQ does.
//!
//! Appends go to the page cache ([`StreamLog::append`]); the caller makes
//! them durable by handing [`StreamLog::sync_handles`] to the persister,
//! whose group commit syncs them before the publish is confirmed. Once the
//! sync succeeded, and before any confirm it covers is sent, the persister
//! writes [`StreamLog::synced_mark`] to `<dir>/synced` ([`SYNCED`], two
//! checksummed slots by turn, never synced by itself): the offset one past
//! the last synced record. After a kill -9 the page cache keeps it
//! exactly; after a power cut the disk holds it or an earlier one (a torn
//! slot falls back to the other): a lower bound of what was confirmed.
//!
//! A segment that is closed (the log rolled past it) is sealed: beside it,
//! `NAME.seg.seal` holds its first and next offset, its oldest and newest
//! timestamps and its length, with a CRC-32 of those. Opening trusts a
//! sealed segment whose seal checks, whose length is the seal's and whose
//! header is sound, without reading its records: start-up reads the
//! seals, the headers and the newest segment, not the whole log. A record
//! in a sealed segment is checked when it is read (its CRC, its offset,
//! its length within the segment): damage there stops the reader before
//! it, with an error log, and is never served. A closed segment without a
//! seal that checks (sealing lost, or a length that differs) is read whole
//! as the newest is, and sealed if sound.
//!
//! Opening reads every unsealed segment and checks every record. Damage refuses
//! the open with an error naming the file, the position and what is
//! wrong (an `InvalidData` error, [`damage`]): a bad checksum, an offset out of sequence, a bad
//! segment header, a torn record in any segment but the newest, missing
//! segments or a missing directory, a missing or unreadable `synced`
//! file, and a log that ends below its synced offset (the newest segment
//! cut short or removed, every segment removed). The one thing taken as
//! sound is damage at or past the synced offset: appends a crash cut short
//! or scrambled before any confirm covered them. The segment is cut there
//! with a warning; when that is not the newest (a power cut as the log
//! rolled), the segments begun after it are removed and it is the head
//! again, its seal removed. Without a synced offset (recovering) only a
//! torn append at the end of the newest segment is taken for a crash's.
//! With `recover` the open goes on instead: each damaged file is
//! copied aside (`NAME.seg.damaged-SECONDS`), what is lost is logged, and
//! the segment is cut at its last sound record; the records after it are
//! never served as if sound. Synced offsets that are gone are never handed
//! out again: the log goes on at the synced offset, the gap recorded
//! beside the new segment (`NAME.seg.lost`).

use crate::store::slots::{SlotFile, SlotRecord};
use crate::store::AfterSync;
use std::fs::{File, OpenOptions};
use std::io::{self, Read};
use std::os::unix::fs::FileExt;
use std::path::{Path, PathBuf};
use std::sync::Arc;

/// A segment file's first bytes.
const MAGIC: &[u8; 8] = b"LVRTSTM1";
/// A seal file's first bytes.
const SEAL_MAGIC: &[u8; 8] = b"LVRTSEAL";
/// Magic, first, next, oldest, newest, length, CRC-32.
const SEAL_LEN: usize = 8 + 5 * 8 + 4;
/// Magic and first offset.
const SEGMENT_HEADER: u64 = 16;
/// Length, CRC, offset, timestamp, flags.
pub const RECORD_HEADER: usize = 25;
/// Flag: the record starts a chunk (a run of records appended while the
/// previous run was being made durable; `x-stream-offset: last` starts at
/// the newest chunk, as RabbitMQ's does).
pub const CHUNK_START: u8 = 1;
/// Largest payload accepted (the broker's frame limits keep messages far
/// below it); a length above it in a file is damage.
const MAX_PAYLOAD: u32 = 512 * 1024 * 1024;

/// One record read back.
#[derive(Debug, Clone, PartialEq)]
pub struct Record {
    /// Its offset.
    pub offset: u64,
    /// When it was appended, ms since the epoch.
    pub timestamp_ms: i64,
    /// Its flags: [`CHUNK_START`] and the appender's own (kept as given).
    pub flags: u8,
    /// The payload as appended (shared, not copied, by every reader it is
    /// handed to).
    pub payload: bytes::Bytes,
}

/// What the index keeps of one segment.
#[derive(Debug, Clone)]
struct Segment {
    first: u64,
    /// One past its last record (== first when empty).
    next: u64,
    /// Oldest and newest record timestamps (ms), when it has records.
    oldest_ms: i64,
    newest_ms: i64,
    bytes: u64,
    path: PathBuf,
    file: Arc<File>,
}

/// Where a reader stands: the next offset and, when known, the file
/// position of that record in the segment starting at `segment`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Cursor {
    /// The next offset to read.
    pub offset: u64,
    /// `(segment first offset, byte position)` of `offset`, if known.
    at: Option<(u64, u64)>,
    /// Records older than this (ms) are passed over, once: a reader
    /// starting at a time begins at the first record that recent.
    not_before: Option<i64>,
    /// Bytes (header and payload) of the last record read through it, 0
    /// if none yet: sizes the next read's window.
    record_len: usize,
}

impl Cursor {
    /// A cursor at `offset`, position to be found.
    pub fn at(offset: u64) -> Self {
        Cursor {
            offset,
            at: None,
            not_before: None,
            record_len: 0,
        }
    }

    /// A cursor at the first record at or after `timestamp_ms`, searched
    /// from `offset` (the first of the oldest segment that recent, from
    /// [`StreamLog::offset_for_timestamp`]).
    pub fn at_time(offset: u64, timestamp_ms: i64) -> Self {
        Cursor {
            not_before: Some(timestamp_ms),
            ..Cursor::at(offset)
        }
    }
}

/// What a read task needs, taken under the stream's lock and used without
/// it: the segments' files from the cursor's on.
#[derive(Debug, Clone)]
pub struct ReadPlan {
    /// First and next offset, length and file of each.
    segments: Vec<(u64, u64, u64, Arc<File>)>,
}

/// The log (see the module docs).
#[derive(Debug)]
pub struct StreamLog {
    dir: PathBuf,
    dir_handle: Arc<File>,
    max_segment_bytes: u64,
    segments: Vec<Segment>,
    /// First offset of the newest chunk.
    last_chunk: u64,
    /// The synced-offset file ([`SYNCED`]), open for the persister.
    synced_file: Arc<File>,
}

/// How far the stream was synced: the record's sequence is the offset one
/// past the last synced record, its words the head segment's first offset
/// and synced length then. Written by the persister after each sync that
/// covers appends, before their confirms ([`StreamLog::synced_mark`]).
const SYNCED: SlotFile = SlotFile {
    name: "synced",
    magic: b"LVSS",
    what: "synced offset",
};

fn segment_path(dir: &Path, first: u64) -> PathBuf {
    dir.join(format!("{first:020}.seg"))
}

fn checksum(rest: &[u8]) -> u32 {
    crc32fast::hash(rest)
}

/// What scanning one segment found.
struct Scanned {
    next: u64,
    oldest_ms: i64,
    newest_ms: i64,
    /// Byte length of its sound part.
    sound: u64,
    last_chunk: Option<u64>,
    /// Why it ends before the file does, if it does.
    damage: Option<String>,
    /// The part after `sound` is what a crash leaves at the end of the
    /// newest segment: a torn record or zeros.
    torn_tail: bool,
}

fn scan(file: &File, first: u64, len: u64) -> io::Result<Scanned> {
    let mut reader = io::BufReader::with_capacity(256 * 1024, file);
    let mut header = [0u8; SEGMENT_HEADER as usize];
    let mut found = Scanned {
        next: first,
        oldest_ms: i64::MAX,
        newest_ms: i64::MIN,
        sound: SEGMENT_HEADER,
        last_chunk: None,
        damage: None,
        torn_tail: false,
    };
    if len < SEGMENT_HEADER || reader.read_exact(&mut header).is_err() {
        found.sound = 0;
        found.damage = Some("no segment header".into());
        return Ok(found);
    }
    if &header[..8] != MAGIC || u64::from_le_bytes(header[8..].try_into().expect("8")) != first {
        found.sound = 0;
        found.damage = Some("segment header does not match its name".into());
        return Ok(found);
    }
    let mut record = vec![0u8; RECORD_HEADER];
    while found.sound < len {
        if len - found.sound < RECORD_HEADER as u64 {
            found.damage = Some("torn record header".into());
            found.torn_tail = true;
            break;
        }
        reader.read_exact(&mut record[..RECORD_HEADER])?;
        let payload_len = u32::from_le_bytes(record[..4].try_into().expect("4"));
        if payload_len > MAX_PAYLOAD {
            found.damage = Some("impossible record length".into());
            break;
        }
        if len - found.sound - (RECORD_HEADER as u64) < u64::from(payload_len) {
            found.damage = Some("torn record".into());
            found.torn_tail = true;
            break;
        }
        record.resize(RECORD_HEADER + payload_len as usize, 0);
        reader.read_exact(&mut record[RECORD_HEADER..])?;
        let crc = u32::from_le_bytes(record[4..8].try_into().expect("4"));
        if checksum(&record[8..]) != crc {
            found.damage = Some("bad checksum".into());
            found.torn_tail =
                record.iter().all(|b| *b == 0) && zeros_to_end(file, found.sound, len)?;
            break;
        }
        let offset = u64::from_le_bytes(record[8..16].try_into().expect("8"));
        if offset != found.next {
            found.damage = Some(format!("offset {offset} where {} was due", found.next));
            break;
        }
        let ts = i64::from_le_bytes(record[16..24].try_into().expect("8"));
        if record[24] & CHUNK_START != 0 || found.next == first {
            found.last_chunk = Some(offset);
        }
        found.oldest_ms = found.oldest_ms.min(ts);
        found.newest_ms = found.newest_ms.max(ts);
        found.next += 1;
        found.sound += (RECORD_HEADER + payload_len as usize) as u64;
        record.truncate(RECORD_HEADER);
    }
    Ok(found)
}

/// Whether `file` holds only zeros from `from` to `len`.
fn zeros_to_end(file: &File, from: u64, len: u64) -> io::Result<bool> {
    let mut buf = vec![0u8; 64 * 1024];
    let mut at = from;
    while at < len {
        let n = buf.len().min((len - at) as usize);
        file.read_exact_at(&mut buf[..n], at)?;
        if buf[..n].iter().any(|b| *b != 0) {
            return Ok(false);
        }
        at += n as u64;
    }
    Ok(true)
}

/// Damage found opening a stream's log without `recover`: what is wrong,
/// naming the file (an [`io::ErrorKind::InvalidData`] error's text).
fn damage(text: String) -> io::Error {
    io::Error::new(io::ErrorKind::InvalidData, text)
}

/// The file beside a segment that says the offsets before it (after the
/// previous segment's last) were lost in a recovery: that gap is then no
/// longer damage.
fn loss_marker(segment: &Path) -> PathBuf {
    let mut name = segment.as_os_str().to_owned();
    name.push(".lost");
    PathBuf::from(name)
}

/// A segment's seal file (module docs).
fn seal_path(segment: &Path) -> PathBuf {
    let mut name = segment.as_os_str().to_owned();
    name.push(".seal");
    PathBuf::from(name)
}

/// Seals a closed segment (module docs). Not synced: a seal lost or cut
/// short by a crash fails its check, and the segment is read whole.
fn write_seal(segment: &Segment) -> io::Result<()> {
    let mut seal = Vec::with_capacity(SEAL_LEN);
    seal.extend_from_slice(SEAL_MAGIC);
    for value in [segment.first, segment.next] {
        seal.extend_from_slice(&value.to_le_bytes());
    }
    for value in [segment.oldest_ms, segment.newest_ms] {
        seal.extend_from_slice(&value.to_le_bytes());
    }
    seal.extend_from_slice(&segment.bytes.to_le_bytes());
    let crc = checksum(&seal);
    seal.extend_from_slice(&crc.to_le_bytes());
    std::fs::write(seal_path(&segment.path), seal)
}

/// What a segment's seal says, if it checks against the segment: its
/// CRC, first offset, the file's length `len` and header.
fn read_seal(path: &Path, file: &File, first: u64, len: u64) -> Option<Scanned> {
    let seal = std::fs::read(seal_path(path)).ok()?;
    if seal.len() != SEAL_LEN || &seal[..8] != SEAL_MAGIC {
        return None;
    }
    let field = |i: usize| u64::from_le_bytes(seal[8 + 8 * i..16 + 8 * i].try_into().expect("8"));
    let crc = u32::from_le_bytes(seal[SEAL_LEN - 4..].try_into().expect("4"));
    if checksum(&seal[..SEAL_LEN - 4]) != crc || field(0) != first || field(4) != len {
        return None;
    }
    let mut header = [0u8; SEGMENT_HEADER as usize];
    file.read_exact_at(&mut header, 0).ok()?;
    if &header[..8] != MAGIC || header[8..] != first.to_le_bytes() || field(1) <= first {
        return None;
    }
    Some(Scanned {
        next: field(1),
        oldest_ms: field(2) as i64,
        newest_ms: field(3) as i64,
        sound: len,
        last_chunk: None,
        damage: None,
        torn_tail: false,
    })
}

/// Copies a damaged segment aside before it is cut.
fn copy_aside(path: &Path) -> io::Result<PathBuf> {
    let stamp = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| d.as_secs());
    let mut name = path.as_os_str().to_owned();
    name.push(format!(".damaged-{stamp}"));
    let copy = PathBuf::from(name);
    std::fs::copy(path, &copy)?;
    Ok(copy)
}

impl StreamLog {
    /// A new, empty log in `dir`: whatever the directory held (the files
    /// of a deleted stream whose removal a crash cut short) goes first.
    pub fn create(dir: &Path, max_segment_bytes: u64) -> io::Result<StreamLog> {
        match std::fs::remove_dir_all(dir) {
            Err(e) if e.kind() != io::ErrorKind::NotFound => return Err(e),
            _ => {}
        }
        std::fs::create_dir_all(dir)?;
        StreamLog::open_as(dir, max_segment_bytes, false, true)
    }

    /// Opens the log in `dir`, checking every record: damage is an error
    /// ([`io::ErrorKind::InvalidData`], naming the file and what is wrong)
    /// unless `recover`, when the damaged file is copied aside, the loss
    /// logged and the segment cut at its last sound record (module docs).
    pub fn open(dir: &Path, max_segment_bytes: u64, recover: bool) -> io::Result<StreamLog> {
        StreamLog::open_as(dir, max_segment_bytes, recover, false)
    }

    /// Opens the log in `dir`; `fresh` when [`StreamLog::create`] just made
    /// the directory (no synced-offset file yet).
    fn open_as(
        dir: &Path,
        max_segment_bytes: u64,
        recover: bool,
        fresh: bool,
    ) -> io::Result<StreamLog> {
        if !dir.exists() {
            if !recover {
                return Err(damage(format!(
                    "the stream directory {} is missing",
                    dir.display()
                )));
            }
            tracing::error!(stream = %dir.display(), "a stored stream's directory is missing: its records are lost; it starts empty");
        }
        std::fs::create_dir_all(dir)?;
        let synced = match SYNCED.read(dir) {
            Ok(Some(record)) => Some(record.sequence),
            Ok(None) if fresh => None,
            Ok(None) | Err(_) if recover => {
                tracing::error!(stream = %dir.display(), "a stored stream's synced-offset file is missing or unreadable: recovering without knowing how far it was synced");
                None
            }
            Ok(None) => {
                return Err(damage(format!(
                    "its synced-offset file {} is missing",
                    SYNCED.path(dir).display()
                )))
            }
            Err(problem) => return Err(damage(format!("stream {}: {problem}", dir.display()))),
        };
        let mut firsts: Vec<u64> = std::fs::read_dir(dir)?
            .filter_map(|e| e.ok())
            .filter_map(|e| {
                let name = e.file_name().into_string().ok()?;
                name.strip_suffix(".seg")?.parse::<u64>().ok()
            })
            .collect();
        firsts.sort_unstable();
        let dir_handle = Arc::new(File::open(dir)?);
        let mut log = StreamLog {
            dir: dir.to_path_buf(),
            dir_handle: Arc::clone(&dir_handle),
            max_segment_bytes: max_segment_bytes.max(1),
            segments: Vec::new(),
            last_chunk: 0,
            // Replaced below, once the segments are known.
            synced_file: dir_handle,
        };
        let newest = firsts.last().copied();
        let mut expected = firsts.first().copied().unwrap_or(0);
        // Where a crash's unsynced tail was cut in a segment before the
        // newest (a power cut as the log rolled): what follows was never
        // synced, so never confirmed.
        let mut crash_cut = false;
        for first in firsts {
            let path = segment_path(dir, first);
            if crash_cut {
                std::fs::remove_file(&path)?;
                let _ = std::fs::remove_file(seal_path(&path));
                tracing::warn!(stream = %dir.display(), segment = %path.display(), "a stream segment begun after the last synced record, before a crash: removed (nothing in it was confirmed)");
                continue;
            }
            let file = OpenOptions::new().read(true).write(true).open(&path)?;
            let len = file.metadata()?.len();
            let mut closed = Some(first) != newest;
            let sealed = if closed {
                read_seal(&path, &file, first, len)
            } else {
                None
            };
            let trusted = sealed.is_some();
            let found = match sealed {
                Some(found) => found,
                None => scan(&file, first, len)?,
            };
            if first < expected {
                if !recover {
                    return Err(damage(format!(
                        "stream segment {} overlaps the one before it (offsets from {first}, {expected} expected)",
                        path.display()
                    )));
                }
                tracing::error!(stream = %dir.display(), segment = %path.display(), "stream segment overlaps the one before it; left out (its file is kept)");
                continue;
            }
            if first > expected && loss_marker(&path).exists() {
                tracing::info!(stream = %dir.display(), segment = %path.display(), missing_from = expected, missing_to = first - 1, "stream offsets lost in an earlier recovery");
            } else if first > expected {
                if !recover {
                    return Err(damage(format!(
                        "stream segments are missing before {}: offsets {expected} to {} are lost",
                        path.display(),
                        first - 1
                    )));
                }
                tracing::error!(stream = %dir.display(), segment = %path.display(), missing_from = expected, missing_to = first - 1, "recovering a stream with missing offsets: these are lost");
                File::create(loss_marker(&path))?.sync_all()?;
            }
            if let Some(why) = &found.damage {
                // What a crash leaves lies past what was synced: damage
                // there held nothing confirmed; below it, it is damage.
                // Without the synced offset (recovering), only a torn
                // append at the very end is taken for a crash's.
                let crash_tail = found.sound > 0
                    && match synced {
                        Some(synced) => found.next >= synced,
                        None => found.torn_tail && Some(first) == newest,
                    };
                if crash_tail {
                    tracing::warn!(stream = %dir.display(), segment = %path.display(), position = found.sound, bytes = len - found.sound, reason = %why, "a stream segment ends in an append never synced (a crash before it was confirmed): cut there");
                    if closed {
                        // The log goes on from here: no longer sealed.
                        let _ = std::fs::remove_file(seal_path(&path));
                        closed = false;
                        crash_cut = true;
                    }
                } else if !recover {
                    return Err(damage(format!(
                        "stream segment {} is damaged at byte {} of {len} ({why}): offsets from {} on would be lost",
                        path.display(),
                        found.sound,
                        found.next
                    )));
                } else {
                    let copy = copy_aside(&path)?;
                    tracing::error!(stream = %dir.display(), segment = %path.display(), copy = %copy.display(), position = found.sound, sound_records = found.next - first, lost_from_offset = found.next, bytes_lost = len - found.sound, reason = %why, "recovering a damaged stream segment: copied aside; the records from here to its end are lost and the file is cut there");
                }
                if found.sound == 0 {
                    // Not even its header is sound: nothing to keep.
                    continue;
                }
                file.set_len(found.sound)?;
            }
            if let Some(chunk) = found.last_chunk {
                log.last_chunk = chunk;
            }
            expected = found.next;
            let segment = Segment {
                first,
                next: found.next,
                oldest_ms: found.oldest_ms,
                newest_ms: found.newest_ms,
                bytes: found.sound,
                path,
                file: Arc::new(file),
            };
            if closed && !trusted && found.next > first {
                if let Err(e) = write_seal(&segment) {
                    tracing::warn!(segment = %segment.path.display(), error = %e, "cannot seal a stream segment: it is read whole at each start");
                }
            }
            log.segments.push(segment);
        }
        if let Some(synced) = synced.filter(|&synced| synced > expected) {
            // The newest records were synced (so maybe confirmed) and are
            // gone: the newest segment was cut short or removed.
            if !recover {
                return Err(damage(format!(
                    "stream {} ends at offset {expected}, but offsets up to {} were synced before their confirms: the newest segment was cut short or removed",
                    dir.display(),
                    synced - 1
                )));
            }
            tracing::error!(stream = %dir.display(), lost_from_offset = expected, lost_to_offset = synced - 1, "recovering a stream whose newest synced records are missing: these are lost; later records keep their offsets");
            log.start_segment(synced)?;
            File::create(loss_marker(&log.head().path))?.sync_all()?;
            log.last_chunk = synced;
            expected = synced;
        }
        if log.segments.is_empty() {
            log.start_segment(expected)?;
            log.last_chunk = expected;
        }
        let head = log.head();
        // A seal beside the head is stale (a crash as the log rolled).
        let _ = std::fs::remove_file(seal_path(&head.path));
        let first_record = SlotRecord {
            sequence: head.next,
            words: [head.first, head.bytes],
        };
        log.synced_file = Arc::new(SYNCED.open(dir, first_record)?);
        Ok(log)
    }

    fn start_segment(&mut self, first: u64) -> io::Result<()> {
        let path = segment_path(&self.dir, first);
        let file = OpenOptions::new()
            .read(true)
            .write(true)
            .create(true)
            .truncate(true)
            .open(&path)?;
        let mut header = [0u8; SEGMENT_HEADER as usize];
        header[..8].copy_from_slice(MAGIC);
        header[8..].copy_from_slice(&first.to_le_bytes());
        file.write_all_at(&header, 0)?;
        self.segments.push(Segment {
            first,
            next: first,
            oldest_ms: i64::MAX,
            newest_ms: i64::MIN,
            bytes: SEGMENT_HEADER,
            path,
            file: Arc::new(file),
        });
        Ok(())
    }

    fn head(&self) -> &Segment {
        self.segments.last().expect("a log always has a segment")
    }

    /// The offset the next append gets.
    pub fn next_offset(&self) -> u64 {
        self.head().next
    }

    /// The oldest offset still held (== `next_offset` when empty).
    pub fn first_offset(&self) -> u64 {
        self.segments
            .iter()
            .find(|s| s.next > s.first)
            .map_or(self.next_offset(), |s| s.first)
    }

    /// Records held (offsets a recovery lost between segments are not).
    pub fn len(&self) -> u64 {
        self.segments.iter().map(|s| s.next - s.first).sum()
    }

    /// First offset of the newest chunk (`next_offset` when empty).
    pub fn last_chunk(&self) -> u64 {
        if self.len() == 0 {
            self.next_offset()
        } else {
            self.last_chunk.max(self.first_offset())
        }
    }

    /// Bytes on disk.
    pub fn bytes(&self) -> u64 {
        self.segments.iter().map(|s| s.bytes).sum()
    }

    /// Segment files.
    pub fn segment_count(&self) -> usize {
        self.segments.len()
    }

    /// Appends one record with `flags` ([`CHUNK_START`] if it starts a
    /// chunk, and bits of the appender's own, kept and read back as given);
    /// returns its offset and whether a new segment was started (its file
    /// and the directory then need syncing too; the record then starts a
    /// chunk).
    pub fn append(
        &mut self,
        payload: &[u8],
        timestamp_ms: i64,
        flags: u8,
    ) -> io::Result<(u64, bool)> {
        let size = (RECORD_HEADER + payload.len()) as u64;
        let mut rolled = false;
        let head = self.head();
        if head.next > head.first && head.bytes + size > self.max_segment_bytes {
            let first = head.next;
            if let Err(e) = write_seal(head) {
                tracing::warn!(segment = %head.path.display(), error = %e, "cannot seal a stream segment: it is read whole at each start");
            }
            self.start_segment(first)?;
            rolled = true;
        }
        let flags = if rolled { flags | CHUNK_START } else { flags };
        let chunk_start = flags & CHUNK_START != 0;
        let head = self.segments.last_mut().expect("a segment");
        let offset = head.next;
        let mut record = Vec::with_capacity(size as usize);
        record.extend_from_slice(&(payload.len() as u32).to_le_bytes());
        record.extend_from_slice(&[0; 4]);
        record.extend_from_slice(&offset.to_le_bytes());
        record.extend_from_slice(&timestamp_ms.to_le_bytes());
        record.push(flags);
        record.extend_from_slice(payload);
        let crc = checksum(&record[8..]);
        record[4..8].copy_from_slice(&crc.to_le_bytes());
        head.file.write_all_at(&record, head.bytes)?;
        head.bytes += size;
        head.next += 1;
        head.oldest_ms = head.oldest_ms.min(timestamp_ms);
        head.newest_ms = head.newest_ms.max(timestamp_ms);
        if chunk_start {
            self.last_chunk = offset;
        }
        Ok((offset, rolled))
    }

    /// The files a sync must cover after appends: the newest segment's,
    /// and with `rolled` the directory's (a new file's name) and the
    /// segment before it (its last records).
    pub fn sync_handles(&self, rolled: bool) -> Vec<Arc<File>> {
        let mut files = vec![Arc::clone(&self.head().file)];
        if rolled {
            files.push(Arc::clone(&self.dir_handle));
            if self.segments.len() > 1 {
                files.push(Arc::clone(&self.segments[self.segments.len() - 2].file));
            }
        }
        files
    }

    /// What the persister records once the files [`StreamLog::sync_handles`]
    /// gave it are synced: everything appended so far.
    pub fn synced_mark(&self) -> AfterSync {
        let head = self.head();
        AfterSync {
            file: Arc::clone(&self.synced_file),
            kind: SYNCED,
            record: SlotRecord {
                sequence: head.next,
                words: [head.first, head.bytes],
            },
        }
    }

    /// Lets whole segments go, oldest first and never the newest, while
    /// the log holds more than `max_bytes` or the segment's newest record
    /// is older than `max_age_ms` before `now_ms`. Returns their files, for
    /// [`remove_files`] to delete off the caller's thread (unlinking a
    /// large file can take milliseconds); readers that hold one open read
    /// on undisturbed.
    pub fn retain(
        &mut self,
        max_bytes: Option<u64>,
        max_age_ms: Option<u64>,
        now_ms: i64,
    ) -> Vec<PathBuf> {
        let mut gone = Vec::new();
        while self.segments.len() > 1 {
            let oldest = &self.segments[0];
            let over_size = max_bytes.is_some_and(|max| self.bytes() > max);
            let too_old = max_age_ms.is_some_and(|age| {
                oldest.next > oldest.first && oldest.newest_ms < now_ms.saturating_sub(age as i64)
            });
            if !(over_size || too_old) {
                break;
            }
            gone.push(self.segments.remove(0).path);
        }
        gone
    }

    /// The first offset whose segment holds records at or after
    /// `timestamp_ms`: the first record of the oldest segment whose newest
    /// record is that recent (RabbitMQ also starts a timestamp at a chunk,
    /// not at the exact record); `next_offset` if none is.
    pub fn offset_for_timestamp(&self, timestamp_ms: i64) -> u64 {
        self.segments
            .iter()
            .find(|s| s.next > s.first && s.newest_ms >= timestamp_ms)
            .map_or(self.next_offset(), |s| s.first)
    }

    /// The files a read from `cursor` goes through.
    pub fn plan(&self, cursor: &Cursor) -> ReadPlan {
        ReadPlan {
            segments: self
                .segments
                .iter()
                .filter(|s| s.next > cursor.offset && s.next > s.first)
                .map(|s| (s.first, s.next, s.bytes, Arc::clone(&s.file)))
                .collect(),
        }
    }

    /// Removes every file (the stream was deleted; reads under way keep
    /// their open files until they finish).
    pub fn destroy(&self) {
        if let Err(e) = std::fs::remove_dir_all(&self.dir) {
            tracing::warn!(stream = %self.dir.display(), error = %e, "could not remove a deleted stream's files");
        }
    }
}

/// Deletes segment files retention let go (blocking: call it off the
/// broker's threads). A file left by a crash first comes back at the next
/// start and is let go again.
pub fn remove_files(paths: Vec<PathBuf>) {
    for path in paths {
        if let Err(e) = std::fs::remove_file(&path) {
            tracing::warn!(segment = %path.display(), error = %e, "could not remove a stream segment retention let go");
        }
        let _ = std::fs::remove_file(loss_marker(&path));
        let _ = std::fs::remove_file(seal_path(&path));
    }
}

impl ReadPlan {
    /// Reads from `cursor` at most `max_records` records and about
    /// `max_bytes` (at least one record), without any lock; moves the
    /// cursor past them. Offsets before the oldest segment (removed by
    /// retention meanwhile) are skipped. Stops at a record that does not
    /// check (damage after opening): reported, never served.
    ///
    /// The file is read a window at a time ([`Window`]: up to
    /// [`READ_WINDOW`] bytes, sized by the records still wanted and the
    /// cursor's record size), so a batch of small records is a few system
    /// calls rather than one a record. Each payload is copied out of the
    /// window into a buffer of its own (a delivery kept unacked holds its
    /// record, never a window); a record larger than a window is read
    /// alone into its own buffer and sliced, not copied.
    pub fn read(&self, cursor: &mut Cursor, max_records: usize, max_bytes: usize) -> Vec<Record> {
        let mut out = Vec::new();
        let mut bytes = 0;
        let mut window = Window::default();
        for (first, next, length, file) in &self.segments {
            if cursor.offset >= *next {
                continue;
            }
            if cursor.offset < *first {
                *cursor = Cursor::at(*first);
            }
            let mut pos = match cursor.at {
                Some((segment, pos)) if segment == *first => pos,
                _ => SEGMENT_HEADER,
            };
            window.clear();
            // Bytes the rest of this read is expected to want: the records
            // still wanted at the cursor's record size (a record when
            // unknown), within the byte budget.
            let wanted = |out: &Vec<Record>, bytes: usize, record: usize| {
                let records = (max_records - out.len()).saturating_mul(record);
                let budget = max_bytes.saturating_sub(bytes).saturating_add(record);
                records.min(budget).clamp(RECORD_HEADER, READ_WINDOW)
            };
            while cursor.offset < *next
                && out.len() < max_records
                && (bytes < max_bytes || out.is_empty())
            {
                let hint = cursor.record_len.max(RECORD_HEADER);
                let size = wanted(&out, bytes, hint);
                let header = match window.get(file, pos, RECORD_HEADER, size, *length) {
                    Ok(header) => header,
                    Err(ends) => {
                        log_cut_short(pos, ends);
                        return out;
                    }
                };
                let header: [u8; RECORD_HEADER] = header.try_into().expect("25");
                let len = u32::from_le_bytes(header[..4].try_into().expect("4")) as usize;
                let offset = u64::from_le_bytes(header[8..16].try_into().expect("8"));
                let timestamp_ms = i64::from_le_bytes(header[16..24].try_into().expect("8"));
                let end = pos + (RECORD_HEADER + len) as u64;
                if end > *length {
                    tracing::error!(
                        position = pos,
                        offset,
                        "stream record damaged (its length runs past its segment): not served"
                    );
                    return out;
                }
                if offset < cursor.offset {
                    pos = end;
                    continue;
                }
                if cursor.not_before.is_some_and(|t| timestamp_ms < t) && offset == cursor.offset {
                    // Before the time asked for: passed over.
                    pos = end;
                    cursor.offset += 1;
                    cursor.at = Some((*first, pos));
                    continue;
                }
                cursor.not_before = None;
                let whole = RECORD_HEADER + len;
                let payload = if whole > READ_WINDOW {
                    // Larger than a window: read alone, sliced.
                    let mut buf = vec![0u8; whole];
                    let read = read_up_to(file, &mut buf, pos);
                    if read < whole {
                        log_cut_short(pos, pos + read as u64);
                        return out;
                    }
                    if !sound(&buf, &header, offset, cursor.offset) {
                        tracing::error!(
                            position = pos,
                            offset,
                            "stream record damaged: not served"
                        );
                        return out;
                    }
                    bytes::Bytes::from(buf).slice(RECORD_HEADER..)
                } else {
                    let size = wanted(&out, bytes, whole).max(whole);
                    let record = match window.get(file, pos, whole, size, *length) {
                        Ok(record) => record,
                        Err(ends) => {
                            log_cut_short(pos, ends);
                            return out;
                        }
                    };
                    if !sound(record, &header, offset, cursor.offset) {
                        tracing::error!(
                            position = pos,
                            offset,
                            "stream record damaged: not served"
                        );
                        return out;
                    }
                    bytes::Bytes::copy_from_slice(&record[RECORD_HEADER..])
                };
                bytes += len;
                pos = end;
                out.push(Record {
                    offset,
                    timestamp_ms,
                    flags: header[24],
                    payload,
                });
                cursor.offset += 1;
                cursor.at = Some((*first, pos));
                cursor.record_len = whole;
            }
            if out.len() >= max_records || bytes >= max_bytes {
                break;
            }
        }
        out
    }
}

/// Whether `record` (header and payload as read) is the record its
/// `header` (read first, perhaps by another read) announced, its CRC
/// checks, and its offset is the one the cursor expects.
fn sound(record: &[u8], header: &[u8; RECORD_HEADER], offset: u64, expected: u64) -> bool {
    let crc = u32::from_le_bytes(record[4..8].try_into().expect("4"));
    record[..RECORD_HEADER] == header[..] && checksum(&record[8..]) == crc && offset == expected
}

/// The most a reader asks of a segment file at once.
const READ_WINDOW: usize = 128 * 1024;

/// The stretch of a segment file last read by one [`ReadPlan::read`]: its
/// buffer is reused for every window of that read.
#[derive(Default)]
struct Window {
    /// File position of `buf[0]`.
    at: u64,
    /// Bytes of `buf` read from the file.
    filled: usize,
    buf: Vec<u8>,
}

impl Window {
    /// Forgets what was read (another segment is next).
    fn clear(&mut self) {
        self.filled = 0;
    }

    /// The `len` bytes of `file` at `pos`, from the window if it holds
    /// them, else from a new window of about `size` bytes (at least `len`,
    /// at most to the segment's `length`) read at `pos`. A window may come
    /// back short (the file ends before the window's end): that is enough
    /// as long as it holds the `len` bytes asked for. `Err` with the
    /// position where the file's data ends if it does not hold them.
    fn get(
        &mut self,
        file: &File,
        pos: u64,
        len: usize,
        size: usize,
        length: u64,
    ) -> Result<&[u8], u64> {
        let end = pos.checked_add(len as u64).ok_or(pos)?;
        let held = self.at..self.at + self.filled as u64;
        if !(held.contains(&pos) && end <= held.end) {
            let left = usize::try_from(length.saturating_sub(pos)).unwrap_or(usize::MAX);
            let size = size.max(len).min(left);
            if size < len {
                return Err(length);
            }
            if self.buf.len() < size {
                self.buf.resize(size, 0);
            }
            self.filled = 0;
            let read = read_up_to(file, &mut self.buf[..size], pos);
            self.at = pos;
            self.filled = read;
            if read < len {
                return Err(pos + read as u64);
            }
        }
        let from = (pos - self.at) as usize;
        Ok(&self.buf[from..from + len])
    }
}

/// Logs a read that found a segment file ending at `file_ends`, before
/// the record at `position` its index says is whole (damage after the
/// file was opened): the records before it are served, none after.
fn log_cut_short(position: u64, file_ends: u64) {
    tracing::error!(
        position,
        file_ends,
        "stream segment shorter than its index says"
    );
}

/// Reads `file` at `pos` into `buf` until `buf` is full, the file ends or
/// a read fails; the bytes read.
fn read_up_to(file: &File, buf: &mut [u8], pos: u64) -> usize {
    let mut read = 0;
    while read < buf.len() {
        match file.read_at(&mut buf[read..], pos + read as u64) {
            Ok(0) => break,
            Ok(n) => read += n,
            Err(e) if e.kind() == std::io::ErrorKind::Interrupted => {}
            Err(e) => {
                tracing::error!(position = pos + read as u64, error = %e, "stream segment read failed");
                break;
            }
        }
    }
    read
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A directory of this test's own, removed afterwards.
    struct Scratch(PathBuf);

    impl Scratch {
        fn new(name: &str) -> Self {
            let dir =
                std::env::temp_dir().join(format!("leveret-stream-{}-{name}", std::process::id()));
            let _ = std::fs::remove_dir_all(&dir);
            std::fs::create_dir_all(&dir).expect("scratch directory");
            Scratch(dir)
        }

        fn path(&self) -> &Path {
            &self.0
        }
    }

    impl Drop for Scratch {
        fn drop(&mut self) {
            let _ = std::fs::remove_dir_all(&self.0);
        }
    }

    fn read_all(log: &StreamLog, from: u64) -> Vec<Record> {
        let mut cursor = Cursor::at(from);
        let plan = log.plan(&cursor);
        plan.read(&mut cursor, usize::MAX, usize::MAX)
    }

    #[test]
    fn a_segment_cut_short_after_open_serves_the_records_before_the_cut() {
        // Damage after opening: the file loses its tail (offsets 5.. gone,
        // the cut inside record 5's header). A window reaching past the cut
        // comes back short; the records it holds are served.
        let dir = Scratch::new("cut-first");
        let mut log = StreamLog::create(dir.path(), 1 << 20).unwrap();
        for i in 0..10u8 {
            log.append(&[i; 10], 1, 0).unwrap();
        }
        let path = log.segments[0].path.clone();
        cut(&path, SEGMENT_HEADER + 5 * (RECORD_HEADER as u64 + 10) + 3);
        let offsets: Vec<u64> = read_all(&log, 0).iter().map(|r| r.offset).collect();
        assert_eq!(
            offsets,
            [0, 1, 2, 3, 4],
            "records before the cut are served"
        );
        // The same a few records a read, and from a later offset.
        let mut cursor = Cursor::at(2);
        let plan = log.plan(&cursor);
        let mut read = Vec::new();
        loop {
            let got = plan.read(&mut cursor, 2, usize::MAX);
            if got.is_empty() {
                break;
            }
            read.extend(got.iter().map(|r| r.offset));
        }
        assert_eq!(read, [2, 3, 4]);
        assert_eq!(cursor.offset, 5, "the reader stops at the cut");
    }

    #[test]
    fn a_segment_cut_inside_a_record_larger_than_a_window_serves_the_records_before_it() {
        let dir = Scratch::new("cut-big");
        let mut log = StreamLog::create(dir.path(), 1 << 22).unwrap();
        log.append(&[1; 10], 1, 0).unwrap();
        log.append(&[2; 10], 1, 0).unwrap();
        log.append(&vec![3; READ_WINDOW * 2], 1, 0).unwrap();
        log.append(&[4; 10], 1, 0).unwrap();
        let path = log.segments[0].path.clone();
        let big = SEGMENT_HEADER + 2 * (RECORD_HEADER as u64 + 10);
        cut(&path, big + READ_WINDOW as u64);
        let offsets: Vec<u64> = read_all(&log, 0).iter().map(|r| r.offset).collect();
        assert_eq!(offsets, [0, 1]);
    }

    #[test]
    fn a_later_segment_cut_short_serves_every_record_before_the_cut() {
        let dir = Scratch::new("cut-later");
        let record = RECORD_HEADER as u64 + 10;
        let mut log = StreamLog::create(dir.path(), SEGMENT_HEADER + 4 * record).unwrap();
        for i in 0..20u8 {
            log.append(&[i; 10], 1, 0).unwrap();
        }
        assert!(log.segments.len() > 2, "several segments");
        let (first, path) = (log.segments[1].first, log.segments[1].path.clone());
        cut(&path, SEGMENT_HEADER + 2 * record + 7);
        let offsets: Vec<u64> = read_all(&log, 0).iter().map(|r| r.offset).collect();
        assert_eq!(offsets, (0..first + 2).collect::<Vec<_>>());
    }

    #[test]
    fn appends_get_increasing_offsets_and_read_back_from_any_offset() {
        let dir = Scratch::new("offsets");
        let mut log = StreamLog::create(dir.path(), 1 << 20).unwrap();
        for i in 0..100u32 {
            let (offset, _) = log
                .append(
                    &i.to_le_bytes(),
                    1000 + i64::from(i),
                    if i % 10 == 0 { CHUNK_START } else { 0 },
                )
                .unwrap();
            assert_eq!(offset, u64::from(i));
        }
        assert_eq!(
            (log.first_offset(), log.next_offset(), log.len()),
            (0, 100, 100)
        );
        let from_40 = read_all(&log, 40);
        assert_eq!(from_40.len(), 60);
        assert_eq!(from_40[0].payload, &40u32.to_le_bytes()[..]);
        assert_eq!(from_40[0].timestamp_ms, 1040);
        assert_eq!(log.last_chunk(), 90);
        // Bounded reads move the cursor on exactly.
        let mut cursor = Cursor::at(0);
        let plan = log.plan(&cursor);
        let first = plan.read(&mut cursor, 7, usize::MAX);
        let rest = plan.read(&mut cursor, usize::MAX, usize::MAX);
        assert_eq!(first.len() + rest.len(), 100);
        assert_eq!(rest[0].offset, 7);
    }

    /// Reads everything from `from` in reads of at most `batch` records
    /// and about `max_bytes`, until a read brings nothing.
    fn read_in_batches(log: &StreamLog, from: u64, batch: usize, max_bytes: usize) -> Vec<Record> {
        let mut cursor = Cursor::at(from);
        let plan = log.plan(&cursor);
        let mut read = Vec::new();
        loop {
            let records = plan.read(&mut cursor, batch, max_bytes);
            if records.is_empty() {
                return read;
            }
            read.extend(records);
        }
    }

    #[test]
    fn records_of_every_size_read_back_in_batches_of_any_size() {
        // Records larger than a window, and one at either side of a
        // window's size.
        let sizes = |i: usize| match i {
            500 => 600 * 1024,
            700 => 5 * 1024,
            800 => READ_WINDOW - RECORD_HEADER,
            801 => READ_WINDOW - RECORD_HEADER + 1,
            _ => i % 97,
        };
        let payload = |i: usize| vec![(i % 251) as u8; sizes(i)];
        // One segment, and segments of a few records (each record size
        // at a segment's start, middle and end).
        for segment_bytes in [4 << 20, 300] {
            let dir = Scratch::new(&format!("sizes-{segment_bytes}"));
            let mut log = StreamLog::create(dir.path(), segment_bytes).unwrap();
            for i in 0..1000 {
                log.append(&payload(i), i as i64, 0).unwrap();
            }
            for (batch, max_bytes) in [
                (1, usize::MAX),
                (7, usize::MAX),
                (1000, usize::MAX),
                (1000, 150),
            ] {
                let read = read_in_batches(&log, 0, batch, max_bytes);
                assert_eq!(
                    read.len(),
                    1000,
                    "batch {batch}, segments of {segment_bytes}"
                );
                for (i, record) in read.iter().enumerate() {
                    assert_eq!(record.offset, i as u64, "batch {batch}");
                    assert_eq!(record.payload, payload(i), "batch {batch}, record {i}");
                }
            }
            let from_middle = read_in_batches(&log, 333, 10, usize::MAX);
            assert_eq!(from_middle.first().map(|r| r.offset), Some(333));
            assert_eq!(from_middle.len(), 667);
        }
    }

    #[test]
    fn flags_are_kept_as_appended() {
        let dir = Scratch::new("flags");
        let mut log = StreamLog::create(dir.path(), 1 << 20).unwrap();
        for flags in [0, CHUNK_START, 1 << 1, 1 << 2 | CHUNK_START, 0xfe] {
            log.append(b"p", 1, flags).unwrap();
        }
        let read: Vec<u8> = read_all(&log, 0).iter().map(|r| r.flags).collect();
        assert_eq!(read, [0, CHUNK_START, 1 << 1, 1 << 2 | CHUNK_START, 0xfe]);
    }

    #[test]
    fn damage_to_a_header_read_along_with_the_record_before_it_is_found() {
        // Each field of offset 2's header: length, CRC, offset, timestamp,
        // flags; read record by record (its header read alone) and in
        // batches (its header read with record 1).
        for field in [0, 1, 4, 8, 16, 24] {
            let dir = Scratch::new(&format!("header-damage-{field}"));
            let mut log = StreamLog::create(dir.path(), 1 << 20).unwrap();
            for i in 0..5u8 {
                log.append(&[i; 10], 1, 0).unwrap();
            }
            let path = log.segments[0].path.clone();
            flip(
                &path,
                SEGMENT_HEADER as usize + 2 * (RECORD_HEADER + 10) + field,
            );
            for batch in [1, 2, 100] {
                let offsets: Vec<u64> = read_in_batches(&log, 0, batch, usize::MAX)
                    .iter()
                    .map(|r| r.offset)
                    .collect();
                assert_eq!(offsets, [0, 1], "field at {field}, batch {batch}");
            }
            // Read from past it, the rest is served, unless the damage is
            // in what leads past it (its length, or its offset, which
            // then looks due and fails its check): nothing then.
            let offsets: Vec<u64> = read_all(&log, 3).iter().map(|r| r.offset).collect();
            let rest: &[u64] = if [0, 1, 8].contains(&field) {
                &[]
            } else {
                &[3, 4]
            };
            assert_eq!(offsets, rest, "field at {field}");
        }
    }

    #[test]
    fn segments_roll_at_their_size_and_retention_removes_whole_old_segments() {
        let dir = Scratch::new("retention");
        let mut log = StreamLog::create(dir.path(), 1000).unwrap();
        let body = [7u8; 75]; // 100 bytes a record
        for i in 0..50 {
            log.append(&body, i, 0).unwrap();
        }
        assert_eq!(
            log.segments.len(),
            6,
            "9 records of 100 bytes after a 16-byte header per segment"
        );
        assert!(log.segments.iter().all(|s| s.bytes <= 1000));
        let by_size = log.retain(Some(2500), None, 0);
        assert_eq!(by_size.len(), 3);
        remove_files(by_size);
        assert!(log.bytes() <= 2500);
        assert_eq!(log.first_offset(), 27);
        assert_eq!(
            read_all(&log, 0)[0].offset,
            27,
            "a read before the first offset starts at it"
        );
        // By age: segments whose newest record is older than the limit go,
        // the newest never.
        let by_age = log.retain(None, Some(10), 1000);
        assert_eq!(by_age.len(), 2);
        remove_files(by_age);
        assert_eq!(log.segments.len(), 1);
        assert_eq!(log.first_offset(), 45);
        let segment_files = std::fs::read_dir(dir.path())
            .unwrap()
            .filter(|e| {
                e.as_ref()
                    .unwrap()
                    .file_name()
                    .to_string_lossy()
                    .ends_with(".seg")
            })
            .count();
        assert_eq!(segment_files, 1);
    }

    #[test]
    fn offsets_and_contents_survive_reopening() {
        let dir = Scratch::new("reopen");
        {
            let mut log = StreamLog::create(dir.path(), 300).unwrap();
            for i in 0..20u8 {
                log.append(&[i; 30], 5, if i == 12 { CHUNK_START } else { 0 })
                    .unwrap();
            }
            remove_files(log.retain(Some(600), None, 0));
        }
        let mut log = StreamLog::open(dir.path(), 300, false).unwrap();
        let first = log.first_offset();
        assert!(first > 0);
        assert_eq!(log.next_offset(), 20);
        let records = read_all(&log, 0);
        assert_eq!(records.len() as u64, 20 - first);
        assert_eq!(records[0].payload, vec![first as u8; 30]);
        assert_eq!(log.append(b"x", 6, CHUNK_START).unwrap().0, 20);
    }

    /// What the persister does once a sync covering the appends succeeded.
    fn record_synced(log: &StreamLog) {
        let mark = log.synced_mark();
        mark.kind.write(&mark.file, mark.record).unwrap();
    }

    /// Ten records of 10 bytes in segments of three, each synced (and so
    /// maybe confirmed); returns the segments' paths.
    fn ten_records(dir: &Path) -> Vec<PathBuf> {
        let mut log =
            StreamLog::create(dir, 3 * (RECORD_HEADER as u64 + 10) + SEGMENT_HEADER).unwrap();
        for i in 0..10u8 {
            log.append(&[i; 10], 1, 0).unwrap();
            record_synced(&log);
        }
        log.segments.iter().map(|s| s.path.clone()).collect()
    }

    fn reopen(dir: &Path, recover: bool) -> io::Result<StreamLog> {
        StreamLog::open(
            dir,
            3 * (RECORD_HEADER as u64 + 10) + SEGMENT_HEADER,
            recover,
        )
    }

    /// Cuts the file at `path` to `len` bytes.
    fn cut(path: &Path, len: u64) {
        OpenOptions::new()
            .write(true)
            .open(path)
            .unwrap()
            .set_len(len)
            .unwrap();
    }

    fn flip(path: &Path, at: usize) {
        let mut bytes = std::fs::read(path).unwrap();
        bytes[at] ^= 0xff;
        std::fs::write(path, &bytes).unwrap();
    }

    fn copies_aside(dir: &Path) -> usize {
        std::fs::read_dir(dir)
            .unwrap()
            .filter(|e| {
                e.as_ref()
                    .unwrap()
                    .file_name()
                    .to_string_lossy()
                    .contains(".damaged-")
            })
            .count()
    }

    #[test]
    fn damage_refuses_the_open_naming_the_file_unless_recovering() {
        let dir = Scratch::new("damage");
        let segments = ten_records(dir.path());
        assert_eq!(segments.len(), 4, "3, 3, 3 and 1 records");
        // Flip one payload byte of offset 4 (the middle segment's second),
        // in a segment whose seal is lost (so it is read whole at open).
        std::fs::remove_file(seal_path(&segments[1])).unwrap();
        flip(
            &segments[1],
            SEGMENT_HEADER as usize + RECORD_HEADER + 10 + RECORD_HEADER + 3,
        );
        let refused = reopen(dir.path(), false).unwrap_err();
        assert_eq!(refused.kind(), io::ErrorKind::InvalidData);
        let text = refused.to_string();
        assert!(text.contains(&segments[1].display().to_string()), "{text}");
        assert!(
            text.contains("bad checksum") && text.contains("offsets from 4"),
            "{text}"
        );
        assert_eq!(
            copies_aside(dir.path()),
            0,
            "a refused open changes nothing"
        );
        assert!(reopen(dir.path(), false).is_err(), "and refuses again");

        let log = reopen(dir.path(), true).unwrap();
        assert_eq!(copies_aside(dir.path()), 1);
        let offsets: Vec<u64> = read_all(&log, 0).iter().map(|r| r.offset).collect();
        assert_eq!(
            offsets,
            vec![0, 1, 2, 3, 6, 7, 8, 9],
            "every readable record is kept; 4 and 5 are lost"
        );
        drop(log);
        // The recovery's gap is no damage for later opens; a gap nothing
        // accounts for is, named as such.
        let log = reopen(dir.path(), false).unwrap();
        assert_eq!((log.first_offset(), log.next_offset()), (0, 10));
        assert_eq!(log.len(), 8, "offsets 4 and 5 are not held");
        drop(log);
        std::fs::remove_file(&segments[2]).unwrap();
        let text = reopen(dir.path(), false).unwrap_err().to_string();
        assert!(
            text.contains("missing") && text.contains("offsets 4 to 8"),
            "{text}"
        );
    }

    #[test]
    fn closed_segments_are_sealed_trusted_at_open_and_checked_on_read() {
        let dir = Scratch::new("sealed");
        let segments = ten_records(dir.path());
        for closed in &segments[..3] {
            assert!(seal_path(closed).exists(), "{} sealed", closed.display());
        }
        assert!(!seal_path(&segments[3]).exists(), "the newest is not");
        // A flipped byte in a sealed segment: the open trusts the seal (it
        // does not read the records) and the read stops before the damage.
        flip(
            &segments[0],
            SEGMENT_HEADER as usize + RECORD_HEADER + 10 + RECORD_HEADER + 3,
        );
        let log = reopen(dir.path(), false).unwrap();
        assert_eq!((log.first_offset(), log.next_offset()), (0, 10));
        let offsets: Vec<u64> = read_all(&log, 0).iter().map(|r| r.offset).collect();
        assert_eq!(offsets, vec![0], "offset 1 is damaged: nothing from it on");
        let later: Vec<u64> = read_all(&log, 3).iter().map(|r| r.offset).collect();
        assert_eq!(later, (3..10).collect::<Vec<_>>());
        drop(log);
        // A damaged length in a sealed segment is bounded by the segment.
        let mut bytes = std::fs::read(&segments[1]).unwrap();
        bytes[SEGMENT_HEADER as usize..][..4].copy_from_slice(&u32::MAX.to_le_bytes());
        std::fs::write(&segments[1], &bytes).unwrap();
        let log = reopen(dir.path(), false).unwrap();
        assert!(read_all(&log, 3).is_empty());
        drop(log);
        // A sealed segment whose length differs from its seal's is read
        // whole: cut short, it is damage.
        let len = std::fs::metadata(&segments[2]).unwrap().len();
        cut(&segments[2], len - 3);
        let text = reopen(dir.path(), false).unwrap_err().to_string();
        assert!(text.contains("torn record"), "{text}");
        // A seal that does not check is not trusted either.
        let dir = Scratch::new("bad-seal");
        let segments = ten_records(dir.path());
        flip(&seal_path(&segments[0]), 20);
        flip(&segments[0], SEGMENT_HEADER as usize + RECORD_HEADER + 3);
        assert!(reopen(dir.path(), false).is_err());
    }

    #[test]
    fn a_torn_or_zeroed_tail_of_the_newest_segment_is_a_crash_and_is_cut() {
        let dir = Scratch::new("torn");
        let segments = ten_records(dir.path());
        let newest = segments.last().unwrap();
        // Half a record appended (a crash mid-append), then zeros.
        let mut bytes = std::fs::read(newest).unwrap();
        let whole = bytes.len();
        let torn = bytes[SEGMENT_HEADER as usize..][..RECORD_HEADER + 4].to_vec();
        bytes.extend_from_slice(&torn);
        std::fs::write(newest, &bytes).unwrap();
        let log = reopen(dir.path(), false).unwrap();
        assert_eq!(log.next_offset(), 10);
        assert_eq!(std::fs::metadata(newest).unwrap().len() as usize, whole);
        drop(log);
        let mut bytes = std::fs::read(newest).unwrap();
        bytes.extend_from_slice(&[0; 200]);
        std::fs::write(newest, &bytes).unwrap();
        let mut log = reopen(dir.path(), false).unwrap();
        assert_eq!(log.append(b"next", 2, CHUNK_START).unwrap().0, 10);
        drop(log);
        // A torn record in an older segment is damage (its seal no longer
        // matches its length, so it is read whole).
        let older = &segments[0];
        let len = std::fs::metadata(older).unwrap().len();
        cut(older, len - 2);
        let text = reopen(dir.path(), false).unwrap_err().to_string();
        assert!(text.contains("torn record"), "{text}");
        // A damaged newest record that is not zeros is damage too.
        let dir = Scratch::new("newest-flip");
        let segments = ten_records(dir.path());
        flip(
            segments.last().unwrap(),
            SEGMENT_HEADER as usize + RECORD_HEADER + 1,
        );
        assert!(reopen(dir.path(), false).is_err());
    }

    #[test]
    fn synced_records_that_are_gone_refuse_the_open_and_recovery_never_reuses_their_offsets() {
        // The newest segment cut short inside what was synced.
        let dir = Scratch::new("synced-cut");
        let segments = ten_records(dir.path());
        let newest = segments.last().unwrap();
        cut(newest, SEGMENT_HEADER + 10);
        let text = reopen(dir.path(), false).unwrap_err().to_string();
        assert!(text.contains("offsets from 9 on would be lost"), "{text}");
        let mut log = reopen(dir.path(), true).unwrap();
        assert_eq!(
            log.next_offset(),
            10,
            "the lost offset is not handed out again"
        );
        assert_eq!(log.append(b"after", 2, CHUNK_START).unwrap().0, 10);
        record_synced(&log);
        drop(log);
        let log = reopen(dir.path(), false).expect("the recorded loss is accepted later");
        assert_eq!(
            read_all(&log, 0)
                .iter()
                .map(|r| r.offset)
                .collect::<Vec<_>>(),
            [0, 1, 2, 3, 4, 5, 6, 7, 8, 10]
        );
        drop(log);

        // Cut at a record boundary: no torn record, still refused.
        let dir = Scratch::new("synced-boundary");
        let segments = ten_records(dir.path());
        let newest = segments.last().unwrap();
        cut(newest, SEGMENT_HEADER);
        assert!(reopen(dir.path(), false).is_err());

        // The newest segment removed, or every segment.
        let dir = Scratch::new("synced-newest-gone");
        let segments = ten_records(dir.path());
        std::fs::remove_file(segments.last().unwrap()).unwrap();
        let text = reopen(dir.path(), false).unwrap_err().to_string();
        assert!(text.contains("ends at offset 9"), "{text}");
        let dir = Scratch::new("synced-all-gone");
        for segment in ten_records(dir.path()) {
            std::fs::remove_file(&segment).unwrap();
            let _ = std::fs::remove_file(seal_path(&segment));
        }
        let text = reopen(dir.path(), false).unwrap_err().to_string();
        assert!(text.contains("ends at offset 0"), "{text}");

        // The synced-offset file itself removed.
        let dir = Scratch::new("synced-file-gone");
        ten_records(dir.path());
        std::fs::remove_file(SYNCED.path(dir.path())).unwrap();
        let text = reopen(dir.path(), false).unwrap_err().to_string();
        assert!(text.contains("synced-offset file"), "{text}");
        assert_eq!(reopen(dir.path(), true).unwrap().next_offset(), 10);
        assert_eq!(
            reopen(dir.path(), false).unwrap().next_offset(),
            10,
            "recovery wrote it again"
        );
    }

    #[test]
    fn a_torn_append_past_the_synced_offset_is_still_a_crash() {
        let dir = Scratch::new("synced-torn-tail");
        let segments = ten_records(dir.path());
        let mut log = reopen(dir.path(), false).unwrap();
        log.append(&[10; 10], 1, 0).unwrap(); // not synced
        drop(log);
        let newest = segments.last().unwrap();
        let len = std::fs::metadata(newest).unwrap().len();
        cut(newest, len - 4);
        let log = reopen(dir.path(), false).unwrap();
        assert_eq!(
            log.next_offset(),
            10,
            "the torn, never synced record is cut"
        );
    }

    #[test]
    fn a_power_cut_as_the_log_rolled_leaves_a_crash_tail_not_damage() {
        let dir = Scratch::new("roll-cut");
        let segments = ten_records(dir.path()); // [0-2] [3-5] [6-8] [9], all synced
        let mut log = reopen(dir.path(), false).unwrap();
        for i in 10..13u8 {
            log.append(&[i; 10], 1, 0).unwrap(); // 10, 11, then a roll: 12
        }
        assert_eq!(log.segments.len(), 5);
        drop(log);
        // The cut lost the end of record 11 (never synced); the new
        // segment's file and the seal of the one before survived.
        let rolled = segments.last().unwrap();
        assert!(seal_path(rolled).exists());
        let len = std::fs::metadata(rolled).unwrap().len();
        cut(rolled, len - 3);
        let mut log = reopen(dir.path(), false).expect("nothing synced was lost");
        assert_eq!(log.next_offset(), 11, "cut after record 10");
        assert_eq!(
            log.segments.len(),
            4,
            "the segment begun after the cut is gone"
        );
        assert!(
            !seal_path(rolled).exists(),
            "the cut segment is the head again"
        );
        assert_eq!(log.append(&[11; 10], 1, 0).unwrap().0, 11);
        record_synced(&log);
        drop(log);
        let log = reopen(dir.path(), false).unwrap();
        assert_eq!(read_all(&log, 0).len(), 12);
    }

    #[test]
    fn a_missing_directory_is_damage_unless_recovering() {
        let dir = Scratch::new("gone");
        ten_records(dir.path());
        std::fs::remove_dir_all(dir.path()).unwrap();
        let text = reopen(dir.path(), false).unwrap_err().to_string();
        assert!(text.contains("missing"), "{text}");
        assert_eq!(reopen(dir.path(), true).unwrap().len(), 0);
    }

    #[test]
    fn timestamps_find_the_oldest_segment_recent_enough() {
        let dir = Scratch::new("timestamps");
        let mut log = StreamLog::create(dir.path(), 200).unwrap();
        for i in 0..20 {
            log.append(&[0; 35], i * 100, 0).unwrap(); // 60 bytes: 3 a segment
        }
        assert_eq!(log.offset_for_timestamp(0), 0);
        assert_eq!(log.offset_for_timestamp(450), 3);
        assert_eq!(log.offset_for_timestamp(1_000_000), 20);
        // A reader at a time starts at the first record that recent, not
        // at its segment's start.
        let mut cursor = Cursor::at_time(log.offset_for_timestamp(450), 450);
        let records = log.plan(&cursor).read(&mut cursor, 2, usize::MAX);
        let offsets: Vec<u64> = records.iter().map(|r| r.offset).collect();
        assert_eq!(offsets, vec![5, 6]);
    }
}
