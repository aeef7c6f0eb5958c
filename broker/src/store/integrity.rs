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
//! expect: the message log's segment list and recorded flushed length
//! (see `log`) still make every segment whole or the start refused, but
//! for a tail no confirm covered. A missing manifest beside a store, a
//! missing database file, a database with no record of an earlier start
//! while the log holds messages (`!starts`, written and flushed at every
//! start before serving), and after a clean stop messages of a queue the
//! database does not hold are damage too: each means the definitions
//! were lost, and starting would silently drop their queues' messages.
//! The manifest says `log=listed` once the log keeps its list and flushed
//! length (a store raised from an older format gets them at its first
//! open, and only then are they required).
//!
//! Uses the store's engine (`DiskStore`), its codec (`Recovered`) and
//! nothing else of the broker.

use super::codec::queue_position;
use super::disk::log_dir;
use super::{guarded, Bookkeeping, DiskStore, Losses, OnDamage, Recovered, Store, StoreError};
use std::io::Write;
use std::path::{Path, PathBuf};

/// The manifest's file name in the data directory.
pub const MANIFEST: &str = "leveret-store.manifest";

/// The store's format; a manifest with a higher one was written by a newer
/// Leveret. 2: messages in the message log (1 kept them in sled; such a
/// store is moved over when opened). 3: the message log may hold format 2
/// segments (see `log`), which Leveret before format 3 cannot read. 4:
/// the message log keeps a list of its segments and its flushed length
/// (see `log`), which Leveret before format 4 would not keep up to date.
const FORMAT: u32 = 4;

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
    /// Whether the message log keeps its segment list and flushed length
    /// (written once it has: a manifest raised from an older format
    /// before the log adopted them says `false`).
    log_listed: bool,
}

impl Manifest {
    fn parse(text: &str) -> Option<Manifest> {
        let mut format = None;
        let mut state = None;
        let mut generation = None;
        let mut log_listed = false;
        for line in text.lines() {
            match line.split_once('=')? {
                ("format", v) => format = v.trim().parse().ok(),
                ("state", "running") => state = Some(State::Running),
                ("state", "clean") => state = Some(State::Clean),
                ("generation", v) => generation = v.trim().parse().ok(),
                ("log", "listed") => log_listed = true,
                _ => return None,
            }
        }
        Some(Manifest {
            format: format?,
            state: state?,
            generation: generation?,
            log_listed,
        })
    }

    fn render(&self) -> String {
        let state = match self.state {
            State::Running => "running",
            State::Clean => "clean",
        };
        let log = if self.log_listed { "log=listed\n" } else { "" };
        format!(
            "format={}\nstate={state}\ngeneration={}\n{log}",
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
    let manifest = read_manifest(dir).and_then(|manifest| match manifest {
        None if store_dir(dir).exists() || log_dir(dir).exists() => Err(format!(
            "its manifest {} is missing, but a store is there",
            dir.join(MANIFEST).display()
        )),
        manifest => Ok(manifest),
    });
    let bookkeeping = match &manifest {
        Ok(Some(Manifest {
            log_listed: true, ..
        })) => Bookkeeping::Required,
        _ => Bookkeeping::Adopted,
    };
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
        Ok(manifest) => check(dir, *manifest, bookkeeping),
        Err(problem) => Err(problem.clone()),
    };
    let generation = manifest.ok().flatten().map_or(0, |m| m.generation);
    let (store, recovered) = match checked {
        Ok(opened) => opened,
        Err(problem) if recover => salvage(dir, &problem, bookkeeping)?,
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
            log_listed: true,
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
            log_listed: true,
        },
    )
}

fn store_dir(dir: &Path) -> PathBuf {
    dir.join("store")
}

/// sled's main file in the database directory.
fn database_file(dir: &Path) -> PathBuf {
    store_dir(dir).join("db")
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
fn check(
    dir: &Path,
    manifest: Option<Manifest>,
    bookkeeping: Bookkeeping,
) -> Result<(DiskStore, Recovered), String> {
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
        if !database_file(dir).exists() {
            return Err(format!(
                "its database file {} is missing",
                database_file(dir).display()
            ));
        }
        if manifest.format >= 2 && !log_dir(dir).exists() {
            return Err(format!(
                "its message log directory {} is missing",
                log_dir(dir).display()
            ));
        }
    }
    let (store, pairs) = open_and_scan(dir, OnDamage::Refuse, bookkeeping)?;
    let recovered = Recovered::from_scan(pairs).map_err(|bad| format!("{bad}"))?;
    let messages: usize = recovered.entries.values().map(Vec::len).sum();
    if bookkeeping == Bookkeeping::Required && recovered.starts == 0 && messages > 0 {
        // Every start records itself in the database, flushed, before it
        // serves: a database without that record is not this store's.
        return Err(format!(
            "its database {} holds no record of an earlier start, but the message log holds \
             {messages} queued messages: the database was deleted, emptied or replaced",
            store_dir(dir).display()
        ));
    }
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
        // A clean shutdown leaves no message of a deleted queue behind: a
        // message whose queue the database lacks lost its queue to damage.
        let orphans: Vec<(u64, usize)> = recovered
            .entries
            .iter()
            .filter(|(queue, entries)| {
                !entries.is_empty() && !recovered.queues.iter().any(|q| q.id == **queue)
            })
            .map(|(queue, entries)| (*queue, entries.len()))
            .collect();
        if let Some(&(queue, count)) = orphans.first() {
            return Err(format!(
                "the message log holds {count} messages of queue id {queue} (and {} more queues' \
                 messages), a queue its database {} does not hold: the database lost definitions",
                orphans.len() - 1,
                store_dir(dir).display()
            ));
        }
    }
    Ok((store, recovered))
}

fn open_and_scan(
    dir: &Path,
    on_damage: OnDamage,
    bookkeeping: Bookkeeping,
) -> Result<(DiskStore, Vec<super::KvPair>), String> {
    let store = DiskStore::open(dir, on_damage, bookkeeping).map_err(|e| match e {
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
fn salvage(
    dir: &Path,
    problem: &str,
    bookkeeping: Bookkeeping,
) -> Result<(DiskStore, Recovered), StoreError> {
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
    let (store, pairs) = match open_and_scan(dir, OnDamage::Salvage, bookkeeping) {
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
            let store = DiskStore::open(dir, OnDamage::Refuse, Bookkeeping::Adopted)?;
            return Ok((store, Recovered::default()));
        }
    };
    let kept = pairs.len();
    let (recovered, dropped) = Recovered::salvage(pairs);
    report_losses(store.log_losses(), &recovered);
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

/// Logs what a salvage of the message log lost: each unreadable stretch
/// (segment, byte range), then per queue the positions of the messages
/// that were in it, and how many removals were lost (those messages come
/// back).
fn report_losses(losses: &Losses, recovered: &Recovered) {
    if losses.is_empty() {
        return;
    }
    for range in &losses.ranges {
        match range.bytes {
            Some((from, to)) => tracing::warn!(
                segment = %range.segment.display(),
                from,
                to,
                bytes = to - from,
                problem = range.problem,
                "salvage: lost an unreadable stretch of the message log"
            ),
            None => tracing::warn!(
                segment = %range.segment.display(),
                problem = range.problem,
                "salvage: lost a whole message log segment"
            ),
        }
    }
    for problem in &losses.bookkeeping {
        tracing::warn!(
            problem,
            "salvage: the message log's bookkeeping was damaged; the rebuilt log has new"
        );
    }
    let mut lost: std::collections::BTreeMap<u64, Vec<u64>> = Default::default();
    for (queue, seq) in losses.puts.iter().filter_map(|key| queue_position(key)) {
        lost.entry(queue).or_default().push(seq);
    }
    for (queue, seqs) in &lost {
        let name = recovered
            .queues
            .iter()
            .find(|q| q.id == *queue)
            .map_or("(no longer declared)".to_owned(), |q| {
                format!("{} in vhost {}", q.name, q.vhost)
            });
        tracing::warn!(
            queue = name,
            queue_id = queue,
            count = seqs.len(),
            positions = positions(seqs),
            "salvage: messages lost from a queue"
        );
    }
    let come_back = losses
        .removals
        .iter()
        .filter(|key| queue_position(key).is_some())
        .count();
    tracing::warn!(
        stretches = losses.ranges.len(),
        messages_lost = lost.values().map(Vec::len).sum::<usize>(),
        acked_messages_back = come_back,
        unknown_stretches = losses.unknown_ranges,
        "salvaged the message log: every readable batch is kept; the counts cover the stretches \
         whose batches still parse (an unknown stretch held what no one can tell)"
    );
}

/// Sorted positions as runs, `3-7,9`, at most [`LOGGED_DROPS`] runs.
fn positions(seqs: &[u64]) -> String {
    let mut runs: Vec<(u64, u64)> = Vec::new();
    for &seq in seqs {
        match runs.last_mut() {
            Some((_, last)) if *last + 1 == seq => *last = seq,
            _ => runs.push((seq, seq)),
        }
    }
    let mut text: Vec<String> = runs
        .iter()
        .take(LOGGED_DROPS)
        .map(|&(a, b)| {
            if a == b {
                a.to_string()
            } else {
                format!("{a}-{b}")
            }
        })
        .collect();
    if runs.len() > LOGGED_DROPS {
        text.push(format!("and {} more runs", runs.len() - LOGGED_DROPS));
    }
    text.join(",")
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
            log_listed: true,
        };
        assert_eq!(Manifest::parse(&manifest.render()), Some(manifest));
        for bad in ["", "format=1\n", "format=1\nstate=odd\ngeneration=1\n", "x"] {
            assert_eq!(Manifest::parse(bad), None, "{bad:?}");
        }
    }

    /// A store from format 3 has no segment list or flushed length: its
    /// first open writes them, and from then on they are required; a
    /// manifest missing beside a store refuses the start.
    #[test]
    fn an_older_store_adopts_the_log_bookkeeping_which_is_then_required() {
        let dir = std::env::temp_dir().join(format!("leveret-adopt-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        let opened = open_checked(&dir, false).unwrap();
        drop(opened);
        for file in ["segments", "flushed"] {
            std::fs::remove_file(log_dir(&dir).join(file)).unwrap();
        }
        let older = Manifest {
            format: 3,
            state: State::Running,
            generation: 0,
            log_listed: false,
        };
        write_manifest(&dir, older).unwrap();
        drop(open_checked(&dir, false).unwrap());
        assert!(read_manifest(&dir).unwrap().unwrap().log_listed);
        std::fs::remove_file(log_dir(&dir).join("segments")).unwrap();
        let refused = open_checked(&dir, false).unwrap_err().to_string();
        assert!(refused.contains("segment list"), "{refused}");
        std::fs::remove_file(dir.join(MANIFEST)).unwrap();
        let refused = open_checked(&dir, false).unwrap_err().to_string();
        assert!(refused.contains("manifest"), "{refused}");
        let _ = std::fs::remove_dir_all(&dir);
    }

    /// After a clean stop no message is left of a deleted queue: messages
    /// of a queue the database lacks mean it lost definitions, and the
    /// start is refused instead of dropping them.
    #[test]
    fn after_a_clean_stop_messages_of_an_unknown_queue_refuse_the_start() {
        use crate::store::{EntryBody, MessageRecord, QueueRecord, StoreOp, WriteMode};
        use leveret_protocol::ShortStr;
        let dir = std::env::temp_dir().join(format!("leveret-orphans-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        let opened = open_checked(&dir, false).unwrap();
        let queue = QueueRecord {
            vhost: ShortStr::from_static("/"),
            name: ShortStr::from_static("q"),
            id: 1,
            auto_delete: false,
            arguments: Default::default(),
        };
        let entry = StoreOp::Enqueue {
            queue: 1,
            seq: 1,
            body: EntryBody::Inline(MessageRecord {
                exchange: ShortStr::from_static(""),
                routing_key: ShortStr::from_static("q"),
                properties: Default::default(),
                body: bytes::Bytes::from_static(b"m"),
            }),
        };
        let ops = [
            StoreOp::Starts { count: 1 },
            StoreOp::PutQueue(queue),
            entry,
        ];
        let write = |ops: &[StoreOp]| {
            let kv = ops.iter().map(StoreOp::to_kv).collect();
            opened.store.write(kv, WriteMode::Plain).unwrap();
            opened.store.flush().unwrap();
        };
        write(&ops);
        // The database loses the queue; the message stays in the log.
        let generation = opened.next_generation;
        write(&[
            StoreOp::DeleteQueue {
                vhost: ShortStr::from_static("/"),
                name: ShortStr::from_static("q"),
            },
            StoreOp::CleanShutdown { generation },
        ]);
        drop(opened);
        mark_clean(&dir, generation).unwrap();
        let refused = open_checked(&dir, false).unwrap_err().to_string();
        assert!(
            refused.contains("1 messages of queue id 1") && refused.contains("does not hold"),
            "{refused}"
        );
        let _ = std::fs::remove_dir_all(&dir);
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
            log_listed: false,
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
