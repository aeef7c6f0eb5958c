//! The bytes of a segment. A segment starts with a header (its format's
//! magic, then its number, big-endian) and holds batches: the payload's
//! length and its CRC-32 (both `u32` little-endian), then the payload, a
//! run of records: `PUT` key-length (`u16` LE) key value-length (`u32`
//! LE) value, or `REMOVE` key-length key. One
//! [`MessageLog::write`](super::MessageLog::write) is one batch, so each
//! write is atomic: a batch is applied whole or, when its checksum fails,
//! not at all. Each batch is written with an end mark after it (a batch
//! header of zeros) that the next batch overwrites, so reading stops at
//! the data's end whatever the file holds beyond it; opening cuts off
//! whatever the newest segment holds beyond it that is not zeros (see
//! `load`). A segment that is complete ends in a seal (see `append`'s
//! rotation).
//!
//! Format 2 (`LVRTLOG2`) checksums the segment's number with each payload;
//! format 1 (`LVRTLOG1`, read and appended to, never started) does not.
//! That lets a dead segment's file be recycled as a later segment: its
//! blocks are already allocated, so appending to it changes no file size
//! and a sync writes back data only (a fresh segment is extended with
//! zeros ahead of its data for the same reason, which costs writing those
//! zeros back as well), and a batch left from the file's earlier life
//! never passes as the new segment's own, even when a power cut lost the
//! end mark that hid it.
//!
//! Uses `crc32fast` and the store's `KvOp` and `StoreError`; nothing else
//! of the log.

use crate::store::{KvOp, StoreError};

/// A segment file's first bytes, per format.
pub(super) const MAGIC_V1: &[u8; 8] = b"LVRTLOG1";
pub(super) const MAGIC_V2: &[u8; 8] = b"LVRTLOG2";
/// A segment's header: the magic and its number.
pub(super) const HEADER: u64 = 16;
/// A batch's header: payload length and checksum.
pub(super) const BATCH_HEADER: usize = 8;
/// The end mark written after each batch: a batch header of zeros.
pub(super) const END_MARK: [u8; BATCH_HEADER] = [0; BATCH_HEADER];
/// Record tags.
const PUT: u8 = 1;
const REMOVE: u8 = 2;
/// The last record of a segment that is complete (see `append`'s `rotate`).
const SEAL: u8 = 3;

/// How a segment's batches are checksummed (see the module docs).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) enum Format {
    /// The payload only.
    V1,
    /// The segment's number, then the payload.
    V2,
}

impl Format {
    pub(super) fn of_magic(magic: &[u8]) -> Option<Format> {
        match magic {
            m if m == MAGIC_V1 => Some(Format::V1),
            m if m == MAGIC_V2 => Some(Format::V2),
            _ => None,
        }
    }

    pub(super) fn checksum(self, segment: u64, payload: &[u8]) -> u32 {
        let mut hasher = crc32fast::Hasher::new();
        if self == Format::V2 {
            hasher.update(&segment.to_be_bytes());
        }
        hasher.update(payload);
        hasher.finalize()
    }
}

/// One record of a batch, borrowed from the payload.
pub(super) enum Record<'a> {
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
pub(super) fn parse_records(payload: &[u8]) -> Option<Vec<Record<'_>>> {
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
pub(super) fn encode_batch(
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
pub(super) fn seal_batch(format: Format, segment: u64) -> Vec<u8> {
    let mut batch = Vec::with_capacity(2 * BATCH_HEADER + 1);
    batch.extend_from_slice(&1u32.to_le_bytes());
    batch.extend_from_slice(&format.checksum(segment, &[SEAL]).to_le_bytes());
    batch.push(SEAL);
    batch.extend_from_slice(&END_MARK);
    batch
}

/// A batch at the start of `rest` of segment `segment` in `format`: its
/// payload's length and records, or what is wrong with it.
pub(super) fn check_batch(
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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::store::log::files::segment_path;
    use crate::store::log::testing::*;
    use crate::store::log::{Bookkeeping, MessageLog, OnDamage};

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
}
