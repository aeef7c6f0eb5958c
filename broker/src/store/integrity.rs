//! Damage detection for a store kept in a data directory, and salvage.
//!
//! Beside the store (sled's `store/` and the message log's `messages/`)
//! lies a manifest (`leveret-store.manifest`):
//! the format version, whether the broker is running or shut down cleanly,
//! and the generation of the last clean shutdown. A clean shutdown's last
//! write to the store is a marker holding that generation (written and
//! flushed after everything else), and only then is the manifest set to
//! `clean` with it. At start, a manifest that says `clean` must find its
//! marker (in both engines: see `disk`): a store deleted, truncated,
//! replaced by an older copy or cut short by a damaged log (sled drops
//! everything after a bad checksum) lacks it. The message log checks its
//! own batches and segments (see `log`). A store that cannot be opened or read (sled's errors, and its
//! panics, caught at the boundary by `guarded`), or holds a record that
//! cannot be decoded, is damaged too. Damage refuses the start with an
//! error naming the directory and what is wrong, unless told to recover:
//! then the damaged files are copied aside, every readable record is kept,
//! and each dropped one is logged.
//!
//! After a crash (the manifest still says `running`) there is no marker to
//! expect: sled's own per-entry checksums and the flush-before-confirm
//! rule are what hold then.
//!
//! Uses the store's engine (`DiskStore`), its codec (`Recovered`) and
//! nothing else of the broker.

use super::disk::log_dir;
use super::{guarded, DiskStore, OnDamage, Recovered, Store, StoreError};
use std::io::Write;
use std::path::{Path, PathBuf};

/// The manifest's file name in the data directory.
pub const MANIFEST: &str = "leveret-store.manifest";

/// The store's format; a manifest with a higher one was written by a newer
/// Leveret. 2: messages in the message log (1 kept them in sled; such a
/// store is moved over when opened). 3: the message log may hold format 2
/// segments (see `log`), which Leveret before format 3 cannot read.
const FORMAT: u32 = 3;

/// At most this many dropped records are logged one by one when salvaging.
const LOGGED_DROPS: usize = 100;

/// Whether the broker owning the store stopped cleanly.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum State {
    Running,
    Clean,
}

/// What the manifest says.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
struct Manifest {
    format: u32,
    state: State,
    generation: u64,
}

impl Manifest {
    fn parse(text: &str) -> Option<Manifest> {
        let mut format = None;
        let mut state = None;
        let mut generation = None;
        for line in text.lines() {
            match line.split_once('=')? {
                ("format", v) => format = v.trim().parse().ok(),
                ("state", "running") => state = Some(State::Running),
                ("state", "clean") => state = Some(State::Clean),
                ("generation", v) => generation = v.trim().parse().ok(),
                _ => return None,
            }
        }
        Some(Manifest {
            format: format?,
            state: state?,
            generation: generation?,
        })
    }

    fn render(&self) -> String {
        let state = match self.state {
            State::Running => "running",
            State::Clean => "clean",
        };
        format!(
            "format={}\nstate={state}\ngeneration={}\n",
            self.format, self.generation
        )
    }
}

/// A store opened from a data directory, checked, with what it holds.
#[derive(Debug)]
pub struct OpenedStore {
    /// The store.
    pub store: std::sync::Arc<dyn Store>,
    /// Its records.
    pub recovered: Recovered,
    /// The generation the next clean shutdown writes.
    pub next_generation: u64,
}

/// Opens the store in `dir`, checks it against its manifest and marks it
/// running. Damage is an error ([`StoreError::Damaged`]) unless `recover`
/// is set: then the damaged files are copied aside and what is readable is
/// kept.
pub fn open_checked(dir: &Path, recover: bool) -> Result<OpenedStore, StoreError> {
    std::fs::create_dir_all(dir).map_err(|source| StoreError::DataDir {
        path: dir.to_owned(),
        source,
    })?;
    let manifest = read_manifest(dir);
    if let Ok(Some(older)) = &manifest {
        if (2..FORMAT).contains(&older.format) {
            // Opening may write what only this format reads (message log
            // segments of format 2): say so first, so that a Leveret too
            // old for it refuses the directory even after a crash here.
            write_manifest(
                dir,
                Manifest {
                    format: FORMAT,
                    ..*older
                },
            )?;
        }
    }
    let checked = match &manifest {
        Ok(manifest) => check(dir, *manifest),
        Err(problem) => Err(problem.clone()),
    };
    let generation = manifest.ok().flatten().map_or(0, |m| m.generation);
    let (store, recovered) = match checked {
        Ok(opened) => opened,
        Err(problem) if recover => salvage(dir, &problem)?,
        Err(problem) => {
            return Err(StoreError::Damaged {
                path: dir.to_owned(),
                problem,
            })
        }
    };
    write_manifest(
        dir,
        Manifest {
            format: FORMAT,
            state: State::Running,
            generation,
        },
    )?;
    Ok(OpenedStore {
        store: std::sync::Arc::new(store),
        recovered,
        next_generation: generation + 1,
    })
}

/// Records a clean shutdown of generation `generation`, whose marker the
/// store now ends with.
pub fn mark_clean(dir: &Path, generation: u64) -> Result<(), StoreError> {
    write_manifest(
        dir,
        Manifest {
            format: FORMAT,
            state: State::Clean,
            generation,
        },
    )
}

fn store_dir(dir: &Path) -> PathBuf {
    dir.join("store")
}

/// The manifest, `None` if there is none (a new data directory, or one
/// from before manifests), or what is wrong with it.
fn read_manifest(dir: &Path) -> Result<Option<Manifest>, String> {
    let path = dir.join(MANIFEST);
    match std::fs::read_to_string(&path) {
        Ok(text) => Manifest::parse(&text)
            .map(Some)
            .ok_or_else(|| format!("its manifest {} is unreadable", path.display())),
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(None),
        Err(e) => Err(format!("cannot read its manifest {}: {e}", path.display())),
    }
}

/// Writes the manifest durably: a temporary file, flushed, renamed over
/// the old one, and the directory flushed.
fn write_manifest(dir: &Path, manifest: Manifest) -> Result<(), StoreError> {
    let failed = |source| StoreError::DataDir {
        path: dir.join(MANIFEST),
        source,
    };
    let temporary = dir.join(format!("{MANIFEST}.new"));
    let mut file = std::fs::File::create(&temporary).map_err(failed)?;
    file.write_all(manifest.render().as_bytes())
        .and_then(|()| file.sync_all())
        .map_err(failed)?;
    std::fs::rename(&temporary, dir.join(MANIFEST)).map_err(failed)?;
    std::fs::File::open(dir)
        .and_then(|d| d.sync_all())
        .map_err(failed)
}

/// Opens and reads the store, and checks it against `manifest`; the
/// problem, if it is damaged.
fn check(dir: &Path, manifest: Option<Manifest>) -> Result<(DiskStore, Recovered), String> {
    if let Some(manifest) = manifest {
        if manifest.format > FORMAT {
            return Err(format!(
                "it was written in format {} by a newer Leveret (this one reads {FORMAT})",
                manifest.format
            ));
        }
        if !store_dir(dir).exists() {
            return Err(format!(
                "its database directory {} is missing",
                store_dir(dir).display()
            ));
        }
        if manifest.format >= 2 && !log_dir(dir).exists() {
            return Err(format!(
                "its message log directory {} is missing",
                log_dir(dir).display()
            ));
        }
    }
    let (store, pairs) = open_and_scan(dir, OnDamage::Refuse)?;
    let recovered = Recovered::from_scan(pairs).map_err(|bad| format!("{bad}"))?;
    if let Some(Manifest {
        state: State::Clean,
        generation,
        ..
    }) = manifest
    {
        if recovered.clean_generation != Some(generation) {
            let found = recovered
                .clean_generation
                .map_or("none".to_owned(), |g| g.to_string());
            return Err(format!(
                "it was shut down cleanly at generation {generation}, but the database does \
                 not end with that shutdown's marker (found: {found}): its files were \
                 truncated, replaced by an older copy or partly lost"
            ));
        }
    }
    Ok((store, recovered))
}

fn open_and_scan(
    dir: &Path,
    on_damage: OnDamage,
) -> Result<(DiskStore, Vec<super::KvPair>), String> {
    let store = DiskStore::open(dir, on_damage).map_err(|e| match e {
        StoreError::Damaged { problem, .. } => problem,
        e => format!("the database cannot be opened: {e}"),
    })?;
    let pairs = guarded("scan", || store.scan())
        .map_err(|e| format!("the database cannot be read: {e}"))?;
    Ok((store, pairs))
}

/// `--recover`: copies the damaged database and message log aside (the
/// log inside the copy, as `messages/`), then keeps every record that can
/// be read; if the store cannot be opened at all, starts from an empty one
/// (everything is in the copy).
fn salvage(dir: &Path, problem: &str) -> Result<(DiskStore, Recovered), StoreError> {
    tracing::error!(dir = %dir.display(), problem, "the store is damaged; recovering as asked");
    let database = store_dir(dir);
    let log = log_dir(dir);
    if database.exists() || log.exists() {
        let stamp = std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map_or(0, |d| d.as_secs());
        let copy = dir.join(format!("store.damaged-{stamp}"));
        let copied = |source| StoreError::DataDir {
            path: copy.clone(),
            source,
        };
        if database.exists() {
            copy_dir(&database, &copy).map_err(copied)?;
        }
        if log.exists() {
            copy_dir(&log, &copy.join("messages")).map_err(copied)?;
        }
        tracing::warn!(copy = %copy.display(), "kept a copy of the damaged store");
    }
    let (store, pairs) = match open_and_scan(dir, OnDamage::Salvage) {
        Ok(opened) => opened,
        Err(unreadable) => {
            tracing::error!(
                problem = unreadable,
                "nothing can be salvaged from the database; starting with an empty one \
                 (the copy holds what there was)"
            );
            for part in [&database, &log] {
                if part.exists() {
                    std::fs::remove_dir_all(part).map_err(|source| StoreError::DataDir {
                        path: part.to_path_buf(),
                        source,
                    })?;
                }
            }
            let store = DiskStore::open(dir, OnDamage::Refuse)?;
            return Ok((store, Recovered::default()));
        }
    };
    let kept = pairs.len();
    let (recovered, dropped) = Recovered::salvage(pairs);
    for bad in dropped.iter().take(LOGGED_DROPS) {
        tracing::warn!(%bad, "dropped an unreadable record");
    }
    tracing::warn!(
        read = kept,
        dropped = dropped.len(),
        "salvaged the store: every readable record is kept"
    );
    Ok((store, recovered))
}

fn copy_dir(from: &Path, to: &Path) -> std::io::Result<()> {
    std::fs::create_dir_all(to)?;
    for entry in std::fs::read_dir(from)? {
        let entry = entry?;
        let target = to.join(entry.file_name());
        if entry.file_type()?.is_dir() {
            copy_dir(&entry.path(), &target)?;
        } else {
            std::fs::copy(entry.path(), target)?;
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_manifest_round_trips_and_refuses_garbage() {
        let manifest = Manifest {
            format: FORMAT,
            state: State::Clean,
            generation: 42,
        };
        assert_eq!(Manifest::parse(&manifest.render()), Some(manifest));
        for bad in ["", "format=1\n", "format=1\nstate=odd\ngeneration=1\n", "x"] {
            assert_eq!(Manifest::parse(bad), None, "{bad:?}");
        }
    }

    /// The manifest names this format before the store is opened (opening
    /// may write what older Leverets cannot read), even when opening then
    /// fails.
    #[test]
    fn an_older_format_is_raised_before_the_store_is_opened() {
        let dir = std::env::temp_dir().join(format!("leveret-manifest-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir).unwrap();
        let older = Manifest {
            format: 2,
            state: State::Clean,
            generation: 7,
        };
        write_manifest(&dir, older).unwrap();
        // No database directory: the open fails after the manifest check.
        assert!(open_checked(&dir, false).is_err());
        let raised = read_manifest(&dir).unwrap().unwrap();
        assert_eq!(
            raised,
            Manifest {
                format: FORMAT,
                ..older
            }
        );
        let _ = std::fs::remove_dir_all(&dir);
    }
}
