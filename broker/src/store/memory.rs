//! An in-memory [`Store`]: the same keys and values as on disk, kept in a
//! `BTreeMap`. For tests, and for an embedded broker that restarts within
//! one process.

use super::{KvOp, KvPair, Store, StoreError, WriteMode};
use std::collections::BTreeMap;
use std::sync::Mutex;

/// A store held in memory.
#[derive(Debug, Default)]
pub struct MemoryStore {
    // Held for one batch or one scan, never across an await.
    map: Mutex<BTreeMap<Vec<u8>, Vec<u8>>>,
}

impl Store for MemoryStore {
    fn write(&self, ops: Vec<KvOp>, _mode: WriteMode) -> Result<(), StoreError> {
        // One lock for the whole batch: plain writes are atomic too.
        let mut map = self.map.lock().unwrap_or_else(|e| e.into_inner());
        for (key, value) in ops {
            match value {
                Some(value) => map.insert(key, value),
                None => map.remove(&key),
            };
        }
        Ok(())
    }

    fn flush(&self) -> Result<(), StoreError> {
        Ok(())
    }

    fn scan(&self) -> Result<Vec<KvPair>, StoreError> {
        let map = self.map.lock().unwrap_or_else(|e| e.into_inner());
        Ok(map.iter().map(|(k, v)| (k.clone(), v.clone())).collect())
    }
}
