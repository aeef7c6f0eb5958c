//! The on-disk [`Store`] of a data directory: definitions in sled
//! ([`SledStore`], in `store/`), the keys written for every message in the
//! [`MessageLog`] (in `messages/`), each key where the codec's [`home`]
//! says. sled's cost per key (its allocations, its own I/O threads) made
//! it the ceiling of the persistent path; the log appends and syncs once
//! per group.
//!
//! A write goes to each engine in order; an atomic write must stay within
//! one engine (a transaction's messages, or a set of definitions), which is
//! all the broker asks, and a write that mixes them is refused rather than
//! made atomic only in part. A flush syncs the log, then sled if it was
//! written since its last flush. The clean-shutdown marker goes to both,
//! and a scan reports it only when both hold it (the older of the two if
//! they differ), so a damaged or older copy of either engine's files fails
//! the manifest check.
//!
//! A data directory from before the log keeps its message keys in sled:
//! opening moves them into the log (written and synced before they are
//! removed from sled, so a crash in between only repeats the move).

use super::codec::{home, Home, CLEAN_MARKER_KEY, LOG_PREFIXES};
use super::log::{Bookkeeping, Losses, MessageLog, OnDamage};
use super::{KvOp, KvPair, SledStore, Store, StoreError, WriteMode};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};

/// The directory of the message log inside a data directory.
pub fn log_dir(data_dir: &Path) -> PathBuf {
    data_dir.join("messages")
}

/// A data directory's store: sled for definitions, the log for messages.
#[derive(Debug)]
pub struct DiskStore {
    definitions: SledStore,
    log: MessageLog,
    /// Whether sled was written since its last flush.
    definitions_dirty: AtomicBool,
}

impl DiskStore {
    /// Opens (or creates) the store in `data_dir`; see `MessageLog` for
    /// what `on_damage` does with a damaged log and what `bookkeeping`
    /// means.
    pub fn open(
        data_dir: &Path,
        on_damage: OnDamage,
        bookkeeping: Bookkeeping,
    ) -> Result<DiskStore, StoreError> {
        let definitions = SledStore::open(data_dir)?;
        let log = MessageLog::open(&log_dir(data_dir), on_damage, bookkeeping)?;
        let store = DiskStore {
            definitions,
            log,
            definitions_dirty: AtomicBool::new(false),
        };
        store.move_message_keys_to_log()?;
        Ok(store)
    }

    /// What opening the message log with [`OnDamage::Salvage`] could not
    /// keep.
    pub fn log_losses(&self) -> &Losses {
        self.log.losses()
    }

    /// Moves message keys found in sled (a store from before the log, or
    /// a move cut short by a crash) into the log, with the clean marker if
    /// the log has none yet.
    fn move_message_keys_to_log(&self) -> Result<(), StoreError> {
        let mut found = Vec::new();
        for prefix in LOG_PREFIXES {
            found.extend(self.definitions.scan_prefix(prefix)?);
        }
        if found.is_empty() {
            return Ok(());
        }
        tracing::info!(
            keys = found.len(),
            "moving stored messages from sled into the message log"
        );
        let log_has_marker = self
            .log
            .scan()?
            .iter()
            .any(|(key, _)| key == CLEAN_MARKER_KEY);
        let mut moved: Vec<KvOp> = found
            .iter()
            .map(|(key, value)| (key.clone(), Some(value.clone())))
            .collect();
        if !log_has_marker {
            if let Some((key, value)) = self.definitions.scan_prefix(CLEAN_MARKER_KEY)?.pop() {
                moved.push((key, Some(value)));
            }
        }
        self.log.write(&moved, false)?;
        self.log.flush()?;
        let removed = found.into_iter().map(|(key, _)| (key, None)).collect();
        self.definitions.write(removed, WriteMode::Plain)?;
        self.definitions.flush()
    }
}

impl Store for DiskStore {
    fn write(&self, ops: Vec<KvOp>, mode: WriteMode) -> Result<(), StoreError> {
        let mut to_log = Vec::new();
        let mut to_definitions = Vec::new();
        for (key, value) in ops {
            match home(&key) {
                Home::Log => to_log.push((key, value)),
                Home::Definitions => to_definitions.push((key, value)),
                Home::Both => {
                    to_log.push((key.clone(), value.clone()));
                    to_definitions.push((key, value));
                }
            }
        }
        if mode == WriteMode::Atomic && !to_log.is_empty() && !to_definitions.is_empty() {
            return Err(StoreError::Engine(
                "an atomic write mixes message and definition keys, which no engine can \
                 apply atomically together"
                    .into(),
            ));
        }
        if !to_log.is_empty() {
            self.log.write(&to_log, mode == WriteMode::Atomic)?;
        }
        if !to_definitions.is_empty() {
            self.definitions_dirty.store(true, Ordering::Relaxed);
            self.definitions.write(to_definitions, mode)?;
        }
        Ok(())
    }

    fn flush(&self) -> Result<(), StoreError> {
        self.log.flush()?;
        if self.definitions_dirty.swap(false, Ordering::Relaxed) {
            if let Err(e) = self.definitions.flush() {
                self.definitions_dirty.store(true, Ordering::Relaxed);
                return Err(e);
            }
        }
        Ok(())
    }

    fn scan(&self) -> Result<Vec<KvPair>, StoreError> {
        let mut logged = self.log.scan()?;
        let log_marker = logged
            .iter()
            .position(|(key, _)| key == CLEAN_MARKER_KEY)
            .map(|at| logged.remove(at).1);
        let mut definitions = Vec::new();
        for (key, value) in self.definitions.scan()? {
            match home(&key) {
                // Left by a move cut short; the log's copy is the one.
                Home::Log => {}
                Home::Definitions => definitions.push((key, value)),
                Home::Both => {
                    // Big-endian generations: the smaller bytes are the older.
                    if let Some(log_marker) = &log_marker {
                        let older = value.min(log_marker.clone());
                        definitions.push((key, older));
                    }
                }
            }
        }
        Ok(merge_sorted(definitions, logged))
    }

    fn reopen(&self) -> Result<(), StoreError> {
        self.log.reopen()?;
        self.definitions.reopen()
    }
}

/// Two key-ordered lists with no key in common, as one.
fn merge_sorted(left: Vec<KvPair>, right: Vec<KvPair>) -> Vec<KvPair> {
    let mut merged = Vec::with_capacity(left.len() + right.len());
    let mut left = left.into_iter().peekable();
    let mut right = right.into_iter().peekable();
    loop {
        let take_left = match (left.peek(), right.peek()) {
            (Some(l), Some(r)) => l.0 <= r.0,
            (Some(_), None) => true,
            (None, Some(_)) => false,
            (None, None) => return merged,
        };
        merged.extend(if take_left { left.next() } else { right.next() });
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn temp_dir(name: &str) -> PathBuf {
        let dir = std::env::temp_dir().join(format!("leveret-disk-{}-{name}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        dir
    }

    fn put(key: &[u8], value: &[u8]) -> KvOp {
        (key.to_vec(), Some(value.to_vec()))
    }

    #[test]
    fn each_key_goes_to_its_engine_and_a_scan_merges_them() {
        let dir = temp_dir("merge");
        {
            let store = DiskStore::open(&dir, OnDamage::Refuse, Bookkeeping::Adopted).unwrap();
            store
                .write(
                    vec![
                        put(b"qvhost\0queue", b"def"),
                        put(b"i0123456789abcdef", b"message"),
                        put(CLEAN_MARKER_KEY, &7u64.to_be_bytes()),
                    ],
                    WriteMode::Plain,
                )
                .unwrap();
            store.flush().unwrap();
            // Only the definition is in sled, only the message in the log
            // (the marker in both).
            let sled = store.definitions.scan().unwrap();
            assert!(sled.iter().all(|(k, _)| home(k) != Home::Log));
            assert_eq!(sled.len(), 2);
            assert_eq!(store.log.scan().unwrap().len(), 2);
        }
        let store = DiskStore::open(&dir, OnDamage::Refuse, Bookkeeping::Adopted).unwrap();
        assert_eq!(
            store.scan().unwrap(),
            vec![
                (CLEAN_MARKER_KEY.to_vec(), 7u64.to_be_bytes().to_vec()),
                (b"i0123456789abcdef".to_vec(), b"message".to_vec()),
                (b"qvhost\0queue".to_vec(), b"def".to_vec()),
            ]
        );
        drop(store);
        let _ = std::fs::remove_dir_all(&dir);
    }

    #[test]
    fn the_clean_marker_counts_only_when_both_engines_hold_it() {
        let dir = temp_dir("marker");
        let store = DiskStore::open(&dir, OnDamage::Refuse, Bookkeeping::Adopted).unwrap();
        let marker = |store: &DiskStore| {
            store
                .scan()
                .unwrap()
                .into_iter()
                .find(|(k, _)| k == CLEAN_MARKER_KEY)
                .map(|(_, v)| v)
        };
        store
            .write(
                vec![put(CLEAN_MARKER_KEY, &5u64.to_be_bytes())],
                WriteMode::Plain,
            )
            .unwrap();
        assert_eq!(marker(&store), Some(5u64.to_be_bytes().to_vec()));
        // An older log (or sled) shows as the older generation.
        store
            .definitions
            .write(
                vec![put(CLEAN_MARKER_KEY, &6u64.to_be_bytes())],
                WriteMode::Plain,
            )
            .unwrap();
        assert_eq!(marker(&store), Some(5u64.to_be_bytes().to_vec()));
        // Missing from one: none.
        store
            .log
            .write(&[(CLEAN_MARKER_KEY.to_vec(), None)], false)
            .unwrap();
        assert_eq!(marker(&store), None);
        drop(store);
        let _ = std::fs::remove_dir_all(&dir);
    }

    #[test]
    fn an_atomic_write_across_both_engines_is_refused() {
        let dir = temp_dir("mixed");
        let store = DiskStore::open(&dir, OnDamage::Refuse, Bookkeeping::Adopted).unwrap();
        let mixed = vec![put(b"i0123456789abcdef", b"m"), put(b"evhost\0x", b"d")];
        assert!(store.write(mixed.clone(), WriteMode::Atomic).is_err());
        store.write(mixed, WriteMode::Plain).unwrap();
        drop(store);
        let _ = std::fs::remove_dir_all(&dir);
    }

    #[test]
    fn messages_kept_in_sled_by_an_older_leveret_move_into_the_log() {
        let dir = temp_dir("move");
        {
            let sled = SledStore::open(&dir).unwrap();
            sled.write(
                vec![
                    put(b"i0123456789abcdef", b"old message"),
                    put(b"d01234567", b"mark"),
                    put(b"qvhost\0queue", b"def"),
                    put(CLEAN_MARKER_KEY, &3u64.to_be_bytes()),
                ],
                WriteMode::Plain,
            )
            .unwrap();
            sled.flush().unwrap();
        }
        let expected = vec![
            (CLEAN_MARKER_KEY.to_vec(), 3u64.to_be_bytes().to_vec()),
            (b"d01234567".to_vec(), b"mark".to_vec()),
            (b"i0123456789abcdef".to_vec(), b"old message".to_vec()),
            (b"qvhost\0queue".to_vec(), b"def".to_vec()),
        ];
        {
            let store = DiskStore::open(&dir, OnDamage::Refuse, Bookkeeping::Adopted).unwrap();
            assert_eq!(store.scan().unwrap(), expected);
            let sled = store.definitions.scan().unwrap();
            assert!(sled.iter().all(|(k, _)| home(k) != Home::Log), "{sled:?}");
        }
        let store = DiskStore::open(&dir, OnDamage::Refuse, Bookkeeping::Adopted).unwrap();
        assert_eq!(store.scan().unwrap(), expected);
        drop(store);
        let _ = std::fs::remove_dir_all(&dir);
    }
}
