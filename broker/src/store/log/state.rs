//! The [`MessageLog`] and what its one lock guards: the index, the head
//! open for appending, the spares, where compaction has got, and the
//! bookkeeping files with their last records.
//!
//! Uses `format`, `bookkeeping`, `index` and `damage`'s `Losses`.

use super::bookkeeping::{FlushedRecord, Listed};
use super::damage::Losses;
use super::format::Format;
use super::index::Index;
use std::fs::File;
use std::path::PathBuf;
use std::sync::Mutex;

/// The log's state: the index and the head open for appending.
#[derive(Debug)]
pub(super) struct State {
    pub(super) index: Index,
    /// The newest segment, open for appending.
    pub(super) head: File,
    pub(super) head_number: u64,
    pub(super) head_format: Format,
    /// The head file's length: its data, then zeros or a recycled file's
    /// old bytes.
    pub(super) head_len: u64,
    /// Dead segments' files waiting to be recycled, at most [`SPARES`](super::retention::SPARES).
    pub(super) spares: Vec<PathBuf>,
    /// Where compaction of the oldest segment has got (segment, offset).
    pub(super) compacting: Option<(u64, u64)>,
    /// Whether the head has writes not yet synced.
    pub(super) dirty: bool,
    /// The segment list's file, its last record's sequence number and
    /// what it says.
    pub(super) list_file: File,
    pub(super) list_sequence: u64,
    pub(super) listed: Listed,
    /// The flushed-length file, and the last record written to it.
    pub(super) flushed_file: File,
    pub(super) flushed: FlushedRecord,
}

/// An append-only key-value log in segment files (see `store::log`'s docs).
#[derive(Debug)]
pub struct MessageLog {
    pub(super) dir: PathBuf,
    pub(super) segment_bytes: u64,
    pub(super) state: Mutex<State>,
    /// What opening it with [`OnDamage::Salvage`](super::OnDamage::Salvage)
    /// could not keep.
    pub(super) losses: Losses,
}

impl MessageLog {
    pub(super) fn state(&self) -> std::sync::MutexGuard<'_, State> {
        self.state.lock().unwrap_or_else(|e| e.into_inner())
    }
}
