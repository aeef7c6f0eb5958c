//! The on-disk [`Store`]: one sled tree in the data directory. A batch is
//! applied with `apply_batch` (atomic) and then `flush` (fsync), so a batch
//! is either wholly on disk or not at all after a crash.

use super::{KvOp, KvPair, Store, StoreError};
use std::path::Path;

/// A store in a sled database.
#[derive(Debug)]
pub struct SledStore {
    db: sled::Db,
}

fn err(e: sled::Error) -> StoreError {
    StoreError(e.to_string())
}

impl SledStore {
    /// Opens (or creates) the store in `dir`.
    pub fn open(dir: &Path) -> Result<Self, StoreError> {
        let db = sled::Config::new()
            .path(dir.join("store"))
            .mode(sled::Mode::HighThroughput)
            .flush_every_ms(None)
            .open()
            .map_err(err)?;
        Ok(SledStore { db })
    }
}

impl Store for SledStore {
    fn apply(&self, ops: Vec<KvOp>) -> Result<(), StoreError> {
        let mut batch = sled::Batch::default();
        for (key, value) in ops {
            match value {
                Some(value) => batch.insert(key, value),
                None => batch.remove(key),
            }
        }
        self.db.apply_batch(batch).map_err(err)?;
        self.db.flush().map_err(err)?;
        Ok(())
    }

    fn scan(&self) -> Result<Vec<KvPair>, StoreError> {
        self.db
            .iter()
            .map(|entry| entry.map(|(k, v)| (k.to_vec(), v.to_vec())).map_err(err))
            .collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn batches_survive_reopening() {
        let dir = std::env::temp_dir().join(format!("leveret-sled-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        {
            let store = SledStore::open(&dir).unwrap();
            store
                .apply(vec![
                    (b"a".to_vec(), Some(b"1".to_vec())),
                    (b"b".to_vec(), Some(b"2".to_vec())),
                ])
                .unwrap();
            store.apply(vec![(b"a".to_vec(), None)]).unwrap();
        }
        let store = SledStore::open(&dir).unwrap();
        assert_eq!(store.scan().unwrap(), vec![(b"b".to_vec(), b"2".to_vec())]);
        drop(store);
        let _ = std::fs::remove_dir_all(&dir);
    }
}
