//! What the log's tests share: a fresh directory, ops, reading a log's
//! pairs and files, damaging its newest segment, and a log filled with
//! flushed batches.

use super::files::{segment_numbers, segment_path, truncate_segment};
use super::format::BATCH_HEADER;
use super::{Bookkeeping, MessageLog, OnDamage};
use crate::store::KvOp;
use std::fs::OpenOptions;
use std::os::unix::fs::FileExt;
use std::path::{Path, PathBuf};

pub(super) fn temp_dir(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("leveret-log-{}-{name}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    dir
}

pub(super) fn put(key: &str, value: &str) -> KvOp {
    (key.as_bytes().to_vec(), Some(value.as_bytes().to_vec()))
}

pub(super) fn remove(key: &str) -> KvOp {
    (key.as_bytes().to_vec(), None)
}

pub(super) fn pairs(log: &MessageLog) -> Vec<(String, String)> {
    log.scan()
        .unwrap()
        .into_iter()
        .map(|(k, v)| (String::from_utf8(k).unwrap(), String::from_utf8(v).unwrap()))
        .collect()
}

pub(super) fn files(dir: &Path) -> Vec<u64> {
    segment_numbers(dir).unwrap()
}

/// Where the head's data ends.
pub(super) fn data_end(log: &MessageLog) -> u64 {
    let state = log.state();
    state.index.segments[&state.head_number].size
}

/// The newest segment loses its bytes from `from` to `to`, as a page
/// cache that never wrote them back would: cut off, or zeros (the
/// zeros the head was extended with).
pub(super) fn lose_tail(dir: &Path, from: u64, to: u64, zeroed: bool) {
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

/// The size of each batch [`filled`] writes while keys have 2 bytes:
/// its header, a put's tag, key length, key, value length and value.
pub(super) const FILLED_BATCH: u64 = BATCH_HEADER as u64 + 1 + 2 + 2 + 4 + 40;

/// Writes `n` batches of one put each (`k0`, `k1`…), flushed, into a
/// log of `segment_bytes` segments; returns the log's directory.
pub(super) fn filled(name: &str, n: usize, segment_bytes: u64) -> PathBuf {
    let dir = temp_dir(name);
    let log = MessageLog::open_sized(&dir, OnDamage::Refuse, Bookkeeping::Adopted, segment_bytes)
        .unwrap();
    for i in 0..n {
        log.write(&[put(&format!("k{i}"), &"v".repeat(40))], false)
            .unwrap();
        log.flush().unwrap();
    }
    dir
}

pub(super) fn refused(dir: &Path) -> String {
    MessageLog::open(dir, OnDamage::Refuse, Bookkeeping::Required)
        .unwrap_err()
        .to_string()
}
