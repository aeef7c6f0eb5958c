//! Reading the log back: every live key and its value, in key order (at
//! start-up, and for a rebuild after a salvage).
//!
//! Uses `state`, `files` and `key`.

use super::files::{io_error, segment_path};
use super::index::Location;
use super::key::LogKey;
use super::state::MessageLog;
use crate::store::{KvPair, StoreError};
use std::collections::HashMap;

impl MessageLog {
    /// Every live key and value, in key order.
    pub fn scan(&self) -> Result<Vec<KvPair>, StoreError> {
        let state = self.state();
        let mut files: HashMap<u64, Vec<u8>> = HashMap::new();
        // Sorted as copies side by side: sorting references into the hash
        // table would chase a pointer per comparison (with many keys, that
        // alone was most of a start-up's scan).
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
}
