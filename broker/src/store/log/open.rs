//! The log's life: opening it (`load`, then a rebuild if a salvage lost
//! something), the losses a salvage reports, and reading it again after a
//! failed write or flush.
//!
//! Uses `load`, `scan`, `append`, `flush`, `state` and `files`.

use super::append::SEGMENT_BYTES;
use super::bookkeeping::Bookkeeping;
use super::damage::{Losses, OnDamage};
use super::files::{io_error, sync_dir};
use super::load::load;
use super::state::MessageLog;
use crate::store::{KvOp, StoreError};
use std::path::Path;
use std::sync::Mutex;

impl MessageLog {
    /// Opens the log in `dir` (created if missing), reading every
    /// segment; see `load`'s docs for what counts as damage.
    pub fn open(
        dir: &Path,
        on_damage: OnDamage,
        bookkeeping: Bookkeeping,
    ) -> Result<MessageLog, StoreError> {
        MessageLog::open_sized(dir, on_damage, bookkeeping, SEGMENT_BYTES)
    }

    /// [`MessageLog::open`] with segments of `segment_bytes` (small ones
    /// exercise rotation and compaction in tests).
    pub fn open_sized(
        dir: &Path,
        on_damage: OnDamage,
        bookkeeping: Bookkeeping,
        segment_bytes: u64,
    ) -> Result<MessageLog, StoreError> {
        let rebuilt = dir.with_extension("rebuilt");
        if !dir.exists() && rebuilt.exists() {
            // A rebuild stopped between its two renames: the rebuilt log
            // was whole and synced before the first.
            std::fs::rename(&rebuilt, dir).map_err(|e| io_error(dir, e))?;
        }
        std::fs::create_dir_all(dir).map_err(|e| io_error(dir, e))?;
        let (state, losses) = load(dir, on_damage, bookkeeping)?;
        let log = MessageLog {
            dir: dir.to_owned(),
            segment_bytes,
            state: Mutex::new(state),
            losses,
        };
        if log.losses.is_empty() {
            return Ok(log);
        }
        log.rebuild()
    }

    /// What opening with [`OnDamage::Salvage`] could not keep (empty
    /// otherwise).
    pub fn losses(&self) -> &Losses {
        &self.losses
    }

    /// After a salvage that lost something: writes every readable record
    /// into a new log beside this one, synced, and puts it in this one's
    /// place, so the next start finds a whole log (the caller has copied
    /// the damaged one aside).
    fn rebuild(self) -> Result<MessageLog, StoreError> {
        let pairs = self.scan()?;
        let rebuilt = self.dir.with_extension("rebuilt");
        let replaced = self.dir.with_extension("replaced");
        for stale in [&rebuilt, &replaced] {
            if stale.exists() {
                std::fs::remove_dir_all(stale).map_err(|e| io_error(stale, e))?;
            }
        }
        {
            let fresh = MessageLog::open_sized(
                &rebuilt,
                OnDamage::Refuse,
                Bookkeeping::Adopted,
                self.segment_bytes,
            )?;
            let puts: Vec<KvOp> = pairs
                .into_iter()
                .map(|(key, value)| (key, Some(value)))
                .collect();
            if !puts.is_empty() {
                fresh.write(&puts, false)?;
            }
            fresh.flush()?;
        }
        let MessageLog {
            dir,
            segment_bytes,
            state,
            losses,
        } = self;
        drop(state);
        let parent = dir.parent().unwrap_or(Path::new("."));
        std::fs::rename(&dir, &replaced)
            .and_then(|()| std::fs::rename(&rebuilt, &dir))
            .map_err(|e| io_error(&dir, e))?;
        sync_dir(parent)?;
        std::fs::remove_dir_all(&replaced).map_err(|e| io_error(&replaced, e))?;
        let (state, _) = load(&dir, OnDamage::Refuse, Bookkeeping::Required)?;
        Ok(MessageLog {
            dir,
            segment_bytes,
            state: Mutex::new(state),
            losses,
        })
    }

    /// Reads the log again from disk (after a failed write or flush):
    /// what is durable, and a cut-short last batch truncated.
    pub fn reopen(&self) -> Result<(), StoreError> {
        let mut state = self.state();
        *state = load(&self.dir, OnDamage::Refuse, Bookkeeping::Required)?.0;
        Ok(())
    }
}
