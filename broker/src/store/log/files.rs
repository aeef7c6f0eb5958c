//! The log's files in its directory: segments as
//! `<dir>/<number as 16 hex digits>.seg`, and dead segments' files kept
//! for recycling as `<dir>/<old number>.spare` (why recycling is safe:
//! see `format`'s docs). Names them, lists them, starts a segment (in a
//! spare or a new file, synced with the directory) and truncates one.
//!
//! Uses `format` (a new segment's header) and the store's `StoreError`.

use super::format::{END_MARK, MAGIC_V2};
use crate::store::StoreError;
use std::fs::{File, OpenOptions};
use std::os::unix::fs::FileExt;
use std::path::{Path, PathBuf};

pub(super) fn io_error(path: &Path, e: std::io::Error) -> StoreError {
    StoreError::Engine(format!("message log {}: {e}", path.display()).into())
}

pub(super) fn segment_path(dir: &Path, number: u64) -> PathBuf {
    dir.join(format!("{number:016x}.seg"))
}

/// The segment numbers in `dir`, ascending; other files are ignored.
pub(super) fn segment_numbers(dir: &Path) -> Result<Vec<u64>, StoreError> {
    let mut numbers = Vec::new();
    for entry in std::fs::read_dir(dir).map_err(|e| io_error(dir, e))? {
        let name = entry.map_err(|e| io_error(dir, e))?.file_name();
        let name = name.to_string_lossy();
        if let Some(hex) = name.strip_suffix(".seg") {
            if let Ok(number) = u64::from_str_radix(hex, 16) {
                numbers.push(number);
            }
        }
    }
    numbers.sort_unstable();
    Ok(numbers)
}

pub(super) fn sync_dir(dir: &Path) -> Result<(), StoreError> {
    File::open(dir)
        .and_then(|d| d.sync_all())
        .map_err(|e| io_error(dir, e))
}

/// The spare files in `dir` (dead segments' files kept for recycling).
pub(super) fn spare_paths(dir: &Path) -> Result<Vec<PathBuf>, StoreError> {
    let mut spares = Vec::new();
    for entry in std::fs::read_dir(dir).map_err(|e| io_error(dir, e))? {
        let path = entry.map_err(|e| io_error(dir, e))?.path();
        if path.extension().is_some_and(|e| e == "spare") {
            spares.push(path);
        }
    }
    Ok(spares)
}

/// Starts segment `number` in format 2: in a spare file if there is one
/// (renamed, its old bytes left after the new header's end mark), else in
/// a new file; header synced, and the directory synced so the file is
/// there after a power cut. Returns the file and its length.
pub(super) fn create_segment(
    dir: &Path,
    number: u64,
    spares: &mut Vec<PathBuf>,
) -> Result<(File, u64), StoreError> {
    let path = segment_path(dir, number);
    let recycled = match spares.pop() {
        Some(spare) => match std::fs::rename(&spare, &path) {
            Ok(()) => true,
            Err(e) => {
                tracing::warn!(spare = %spare.display(), error = %e, "could not recycle a spare message log file");
                spares.push(spare);
                false
            }
        },
        None => false,
    };
    let file = OpenOptions::new()
        .create(true)
        .truncate(!recycled)
        .write(true)
        .read(true)
        .open(&path)
        .map_err(|e| io_error(&path, e))?;
    let mut header = MAGIC_V2.to_vec();
    header.extend_from_slice(&number.to_be_bytes());
    header.extend_from_slice(&END_MARK);
    file.write_all_at(&header, 0)
        .and_then(|()| file.sync_data())
        .map_err(|e| io_error(&path, e))?;
    sync_dir(dir)?;
    let len = file.metadata().map_err(|e| io_error(&path, e))?.len();
    Ok((file, len))
}

/// Truncates segment `number` to `len` bytes, durably.
pub(super) fn truncate_segment(dir: &Path, number: u64, len: u64) -> Result<(), StoreError> {
    let path = segment_path(dir, number);
    OpenOptions::new()
        .write(true)
        .open(&path)
        .and_then(|f| f.set_len(len).and_then(|()| f.sync_all()))
        .map_err(|e| io_error(&path, e))
}
