//! The message log: an append-only key-value log in numbered segment files,
//! for the keys written once or twice per message (which keys those are is
//! the codec's business; [`DiskStore`](super::DiskStore) routes them here).
//! A key-value engine built for that pattern: every write is an append,
//! a flush is one `fdatasync`, and nothing is rewritten in place.
//!
//! A file a job, each listed with what it may use (besides the standard
//! library and the store's `KvOp`, `KvPair` and `StoreError`); none uses
//! a file listed after it, and none uses this one:
//! - `format`: the bytes of a segment: its header, batches and their
//!   records, the end mark, the seal, and the two formats' checksums
//!   (`crc32fast`). Uses nothing else of the log.
//! - `files`: the segment and spare files in the log's directory: their
//!   names, listing them, starting a segment (in a recycled spare or a new
//!   file) and truncating one. Uses `format`.
//! - `bookkeeping`: the segment list and the flushed length (the store's
//!   `slots`), and why the flushed length proves what was confirmed. Uses
//!   `files`.
//! - `key`: the index's key type. Uses nothing else.
//! - `index`: where each live key's value lies and what is live in each
//!   segment (the broker's `word_hash`). Uses `key`, `format`.
//! - `damage`: reading one segment at open: how far it must reach, what
//!   is damage and what a torn tail, and salvage's losses. Uses `format`,
//!   `files`, `index`.
//! - `state`: the [`MessageLog`] type and what its one lock guards. Uses
//!   `format`, `bookkeeping`, `index`, `damage`.
//! - `append`: the write path: batches appended to the head, rotation to
//!   a new segment. Uses `state` and those below it.
//! - `retention`: dead segments deleted or kept as spares, compaction.
//!   Uses `append` (compaction appends its copies) and those below it.
//! - `flush`: the sync that makes writes durable, its flushed-length
//!   record, then retention. Uses `retention` and those below it.
//! - `scan`: every live value read back. Uses `state`, `files`, `key`.
//! - `load`: opening: which segments to read (by the bookkeeping), each
//!   read (`damage`), the head opened or started. Uses `state` and those
//!   below it.
//! - `open`: the log's life: opening, rebuilding after a salvage that
//!   lost something, reopening after a failed write. Uses `load`, `scan`,
//!   `append`, `flush`.
//!
//! Called from the persister thread (every call takes the log's one lock).

mod append;
mod bookkeeping;
mod damage;
mod files;
mod flush;
mod format;
mod index;
mod key;
mod load;
mod open;
mod retention;
mod scan;
mod state;
#[cfg(test)]
mod testing;

pub use self::bookkeeping::Bookkeeping;
pub use self::damage::{Losses, LostRange, OnDamage};
pub use self::state::MessageLog;

#[cfg(test)]
mod tests {
    use super::testing::temp_dir;
    use super::{Bookkeeping, MessageLog, OnDamage};
    use crate::store::KvPair;
    use proptest::prelude::*;
    use std::collections::BTreeMap;

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
    }
}
