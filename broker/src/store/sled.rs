//! sled as a [`Store`]: one tree in the data directory's `store/`, holding
//! definitions (see [`DiskStore`](super::DiskStore)). Plain writes
//! are single inserts and removes; atomic writes go through `apply_batch`;
//! `flush` blocks until everything written is stable on disk. The page cache is kept
//! small: the broker holds queued messages in memory itself. sled refuses
//! all work after one I/O error (a full disk), so `reopen` drops the
//! database and opens it again from what is on disk.

use super::{KvOp, KvPair, Store, StoreError, WriteMode};
use std::path::{Path, PathBuf};
use std::sync::RwLock;

/// sled's page cache: small, because recovery reads everything once and
/// the broker keeps what it needs in memory.
const CACHE_BYTES: u64 = 64 * 1024 * 1024;

/// How long opening waits for the database's file lock. sled's I/O
/// threads can hold it for a moment after the previous `Db` of this
/// process is dropped (a restart in the same process); another process
/// holding it is still refused, after this wait.
const LOCK_WAIT: std::time::Duration = std::time::Duration::from_secs(1);

/// A store in a sled database.
#[derive(Debug)]
pub struct SledStore {
    dir: PathBuf,
    /// `None` between dropping a failed database and opening it again
    /// (and after a reopen that failed: the next one tries again). Read
    /// for every call, written only by `reopen`.
    db: RwLock<Option<sled::Db>>,
}

impl SledStore {
    /// Opens (or creates) the store in `dir`.
    pub fn open(dir: &Path) -> Result<Self, StoreError> {
        Ok(SledStore {
            dir: dir.to_owned(),
            db: RwLock::new(Some(open_db(dir)?)),
        })
    }

    /// Runs `call` on the open database.
    fn with_db<T>(
        &self,
        call: impl FnOnce(&sled::Db) -> Result<T, StoreError>,
    ) -> Result<T, StoreError> {
        let db = self.db.read().unwrap_or_else(|e| e.into_inner());
        match &*db {
            Some(db) => call(db),
            None => Err(StoreError::Engine(
                format!(
                    "the store in {} is closed after a failure and could not be reopened yet",
                    self.dir.display()
                )
                .into(),
            )),
        }
    }
}

/// Opens (or creates) the sled database in `dir`.
fn open_db(dir: &Path) -> Result<sled::Db, StoreError> {
    let started = std::time::Instant::now();
    loop {
        let opened = super::guarded("open", || {
            sled::Config::new()
                .path(dir.join("store"))
                .mode(sled::Mode::HighThroughput)
                .cache_capacity(CACHE_BYTES)
                .flush_every_ms(None)
                .open()
                .map_err(StoreError::from)
        });
        match opened {
            Err(e) if is_lock_held(&e) && started.elapsed() < LOCK_WAIT => {
                std::thread::sleep(std::time::Duration::from_millis(10));
            }
            opened => return opened,
        }
    }
}

/// Whether `error` is sled refusing to open because the file lock is held.
fn is_lock_held(error: &StoreError) -> bool {
    error.to_string().contains("could not acquire lock")
}

impl SledStore {
    /// Every key starting with `prefix` and its value, in key order.
    pub fn scan_prefix(&self, prefix: &[u8]) -> Result<Vec<KvPair>, StoreError> {
        self.with_db(|db| {
            db.scan_prefix(prefix)
                .map(|entry| {
                    entry
                        .map(|(k, v)| (k.to_vec(), v.to_vec()))
                        .map_err(StoreError::from)
                })
                .collect()
        })
    }
}

impl Store for SledStore {
    fn write(&self, ops: Vec<KvOp>, mode: WriteMode) -> Result<(), StoreError> {
        self.with_db(|db| write(db, ops, mode))
    }

    fn flush(&self) -> Result<(), StoreError> {
        self.with_db(|db| db.flush().map(drop).map_err(StoreError::from))
    }

    fn scan(&self) -> Result<Vec<KvPair>, StoreError> {
        self.with_db(|db| {
            db.iter()
                .map(|entry| {
                    entry
                        .map(|(k, v)| (k.to_vec(), v.to_vec()))
                        .map_err(StoreError::from)
                })
                .collect()
        })
    }

    fn reopen(&self) -> Result<(), StoreError> {
        let mut db = self.db.write().unwrap_or_else(|e| e.into_inner());
        // The old database must be gone (its file lock released) first.
        drop(db.take());
        *db = Some(open_db(&self.dir)?);
        Ok(())
    }
}

/// Applies `ops` to `db` as `mode` says.
fn write(db: &sled::Db, ops: Vec<KvOp>, mode: WriteMode) -> Result<(), StoreError> {
    if mode == WriteMode::Atomic {
        let mut batch = sled::Batch::default();
        for (key, value) in ops {
            match value {
                Some(value) => batch.insert(key, value),
                None => batch.remove(key),
            }
        }
        return db.apply_batch(batch).map_err(StoreError::from);
    }
    for (key, value) in ops {
        match value {
            Some(value) => db.insert(key, value).map(drop),
            None => db.remove(key).map(drop),
        }
        .map_err(StoreError::from)?;
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn opening_waits_briefly_for_a_lock_being_released() {
        let dir = std::env::temp_dir().join(format!("leveret-sled-lock-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        let first = SledStore::open(&dir).unwrap();
        let release = std::thread::spawn(move || {
            std::thread::sleep(std::time::Duration::from_millis(100));
            drop(first);
        });
        let second = SledStore::open(&dir);
        release.join().unwrap();
        assert!(second.is_ok(), "{:?}", second.err());
        drop(second);
        let _ = std::fs::remove_dir_all(&dir);
    }

    #[test]
    fn batches_survive_reopening() {
        let dir = std::env::temp_dir().join(format!("leveret-sled-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        {
            let store = SledStore::open(&dir).unwrap();
            store
                .write(
                    vec![
                        (b"a".to_vec(), Some(b"1".to_vec())),
                        (b"b".to_vec(), Some(b"2".to_vec())),
                    ],
                    WriteMode::Atomic,
                )
                .unwrap();
            store
                .write(vec![(b"a".to_vec(), None)], WriteMode::Plain)
                .unwrap();
            store.flush().unwrap();
        }
        let store = SledStore::open(&dir).unwrap();
        assert_eq!(store.scan().unwrap(), vec![(b"b".to_vec(), b"2".to_vec())]);
        drop(store);
        let _ = std::fs::remove_dir_all(&dir);
    }
}
