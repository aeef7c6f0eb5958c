//! Opening the log: which segments to read, read each, and open the head.
//!
//! Crashes and damage: a new segment is started only after the previous
//! one is synced and sealed, so only the newest segment can end in a batch
//! that was cut short, and only at or past its recorded flushed length:
//! opening truncates it there, which loses nothing that was confirmed, and
//! says so. Everything else is damage, and opening fails naming the file
//! and the offset: a bad batch, zeros or a file end below the flushed
//! length or before a segment's seal, a damaged header, a segment the list
//! names that is missing, a missing or unreadable list or flushed record
//! ([`Bookkeeping::Required`]: a log opened before it kept them, or a new
//! one, [`Bookkeeping::Adopted`], gets them written from what is found).
//! Salvaging is `damage`'s.
//! An end mark ends a segment's data wherever it lies past what the
//! segment must reach. In the newest, bytes beyond the end are a
//! recycled file's earlier life, or batches written after the last flush
//! that a power cut kept while losing one before them (page caches and
//! disks write back out of order); opening truncates the segment at its
//! end, so a later batch whose end mark a second power cut loses never
//! uncovers them.
//!
//! Uses `state`, `damage`, `index`, `bookkeeping`, `files`, `format` and
//! `retention`'s limit on spares.

use super::bookkeeping::{
    open_kept, read_flushed, read_segment_list, write_segment_list, Bookkeeping, FlushedRecord,
    Listed, FLUSHED, SEGMENT_LIST,
};
use super::damage::{Losses, LostRange, OnDamage, Reach};
use super::files::{
    create_segment, io_error, segment_numbers, segment_path, spare_paths, truncate_segment,
};
use super::format::{Format, HEADER};
use super::index::{Index, Segment};
use super::retention::SPARES;
use super::state::State;
use crate::store::slots::SlotRecord;
use crate::store::StoreError;
use std::fs::OpenOptions;
use std::path::Path;

/// Reads every segment in `dir` into a fresh state (see the module docs
/// for damage), with the newest open for appending; when salvaging, also
/// what could not be read (the caller then rebuilds the log: nothing here
/// changes a damaged segment).
pub(super) fn load(
    dir: &Path,
    on_damage: OnDamage,
    bookkeeping: Bookkeeping,
) -> Result<(State, Losses), StoreError> {
    let mut losses = Losses::default();
    let mut problems: Vec<String> = Vec::new();
    // Refusing, the first problem is the answer; salvaging, each is noted
    // and reading goes on.
    let mut damage = |problem: String, losses: &mut Losses, lost: Option<LostRange>| {
        if on_damage == OnDamage::Refuse {
            return Err(StoreError::Damaged {
                path: dir.to_owned(),
                problem,
            });
        }
        match lost {
            Some(lost) => losses.ranges.push(lost),
            None => losses.bookkeeping.push(problem.clone()),
        }
        problems.push(problem);
        Ok(())
    };
    let present = segment_numbers(dir)?;
    let listed = match (read_segment_list(dir), bookkeeping) {
        (Ok(Some(found)), _) => Some(found),
        (Ok(None), Bookkeeping::Adopted) => None,
        (Ok(None), Bookkeeping::Required) => {
            let path = dir.join(SEGMENT_LIST.name);
            damage(
                format!("its segment list {} is missing", path.display()),
                &mut losses,
                None,
            )?;
            None
        }
        (Err(problem), _) => {
            damage(problem, &mut losses, None)?;
            None
        }
    };
    let flushed = match (read_flushed(dir), bookkeeping) {
        (Ok(found), Bookkeeping::Adopted) => found,
        (Ok(Some(found)), Bookkeeping::Required) => Some(found),
        (Ok(None), Bookkeeping::Required) => {
            let path = dir.join(FLUSHED.name);
            damage(
                format!("its flushed length {} is missing", path.display()),
                &mut losses,
                None,
            )?;
            None
        }
        (Err(problem), _) => {
            damage(problem, &mut losses, None)?;
            None
        }
    };
    let list_sequence = listed.map_or(0, |(sequence, _)| sequence);
    let listed = listed.map(|(_, listed)| listed);
    // The segments to read: those the list names, every one present
    // (and one past its newest: started by a rotation cut short before
    // the list named it, so holding nothing); without a list, those
    // found, without gaps.
    let mut numbers = Vec::new();
    match listed {
        Some(listed) => {
            for &number in &present {
                if number < listed.first && on_damage == OnDamage::Refuse {
                    // Retired, its deletion cut short: nothing in it lives.
                    let path = segment_path(dir, number);
                    std::fs::remove_file(&path).map_err(|e| io_error(&path, e))?;
                } else if number > listed.last + 1 {
                    damage(
                        format!(
                            "message log segment {} lies past the newest its list names ({})",
                            segment_path(dir, number).display(),
                            listed.last
                        ),
                        &mut losses,
                        None,
                    )?;
                } else if number >= listed.first {
                    numbers.push(number);
                }
            }
            for number in listed.first..=listed.last {
                if present.binary_search(&number).is_err() {
                    let path = segment_path(dir, number);
                    let problem = format!(
                        "message log segment {} is missing (its list says the log holds \
                         segments {} to {})",
                        path.display(),
                        listed.first,
                        listed.last
                    );
                    let lost = LostRange {
                        segment: path,
                        bytes: None,
                        problem: problem.clone(),
                    };
                    damage(problem, &mut losses, Some(lost))?;
                    losses.unknown_ranges += 1;
                }
            }
        }
        None => {
            if let Some(pair) = present.windows(2).find(|pair| pair[1] != pair[0] + 1) {
                let path = segment_path(dir, pair[0] + 1);
                let problem = format!("message log segment {} is missing", path.display());
                let lost = LostRange {
                    segment: path,
                    bytes: None,
                    problem: problem.clone(),
                };
                damage(problem, &mut losses, Some(lost))?;
                losses.unknown_ranges += 1;
            }
            numbers = present.clone();
        }
    }
    // A segment started by a rotation cut short (past the list's newest,
    // or without a list the newest) may hold no whole header: it never
    // held a batch, and goes.
    let unlisted = match listed {
        Some(listed) => numbers.last().filter(|&&n| n == listed.last + 1),
        None => numbers.last(),
    };
    if let Some(&number) = unlisted {
        let path = segment_path(dir, number);
        let bytes = std::fs::read(&path).map_err(|e| io_error(&path, e))?;
        let whole_header = bytes.get(..8).and_then(Format::of_magic).is_some()
            && bytes.get(8..16) == Some(&number.to_be_bytes());
        if !whole_header {
            tracing::warn!(segment = %path.display(), "removing a message log segment whose start was cut short");
            std::fs::remove_file(&path).map_err(|e| io_error(&path, e))?;
            numbers.pop();
        }
    }
    let newest = numbers.last().copied();
    // How far the newest segment must reach: its recorded flushed length;
    // nothing of a segment the record does not name yet was flushed.
    let newest_reach = match (flushed, newest) {
        (Some(record), Some(newest)) if record.segment == newest => record.length,
        (Some(record), Some(newest)) if record.segment > newest => {
            let problem = format!(
                "its flushed length names segment {}, past the newest present ({newest})",
                segment_path(dir, record.segment).display()
            );
            damage(problem, &mut losses, None)?;
            HEADER
        }
        _ => HEADER,
    };
    let mut index = Index::default();
    let mut head_format = Format::V2;
    for &number in &numbers {
        let path = segment_path(dir, number);
        let is_newest = Some(number) == newest;
        let reach = if is_newest {
            Reach::Flushed(newest_reach)
        } else {
            Reach::Seal
        };
        let read = index.read_segment(dir, number, reach, on_damage, &mut losses)?;
        if let Some(problem) = read.damage {
            return Err(StoreError::Damaged {
                path: dir.to_owned(),
                problem: format!("message log segment {}: {problem}", path.display()),
            });
        }
        if let Some(problem) = &read.torn {
            tracing::warn!(
                segment = %path.display(),
                problem,
                flushed = newest_reach,
                "the message log ends in a batch written after its last recorded flush (a crash \
                 or power cut while writing); it is dropped: no confirm was sent for it"
            );
        }
        if read.good_end < HEADER {
            // Refusing, a bad header is damage (returned above); salvaging,
            // the segment is read on as format 2 and rebuilt.
            continue;
        }
        if is_newest && (read.torn.is_some() || read.leftover) && losses.is_empty() {
            // See the module docs: nothing beyond the end may be uncovered.
            truncate_segment(dir, number, read.good_end)?;
        }
        head_format = read.format.unwrap_or(Format::V2);
        index.segments.entry(number).or_default().size = read.good_end;
    }
    losses.puts = std::mem::take(&mut index.unread_puts).into_iter().collect();
    losses.puts.sort_unstable();
    losses.removals = std::mem::take(&mut index.unread_removals)
        .into_iter()
        .collect();
    losses.removals.sort_unstable();
    for problem in &problems {
        tracing::warn!(log = %dir.display(), problem, "message log damage found while salvaging");
    }
    let mut spares = spare_paths(dir)?;
    while spares.len() > SPARES {
        let extra = spares.pop().expect("more than SPARES");
        std::fs::remove_file(&extra).map_err(|e| io_error(&extra, e))?;
    }
    let (head_number, head, head_len) = match index.segments.last_key_value() {
        Some((&number, _)) => {
            let path = segment_path(dir, number);
            let head = OpenOptions::new()
                .read(true)
                .write(true)
                .open(&path)
                .map_err(|e| io_error(&path, e))?;
            let len = head.metadata().map_err(|e| io_error(&path, e))?.len();
            (number, head, len)
        }
        None => {
            let number = newest.or(listed.map(|l| l.last)).map_or(1, |n| n + 1);
            index.segments.insert(
                number,
                Segment {
                    size: HEADER,
                    ..Segment::default()
                },
            );
            head_format = Format::V2;
            let (head, len) = create_segment(dir, number, &mut spares)?;
            (number, head, len)
        }
    };
    let first = *index.segments.first_key_value().expect("the head").0;
    let now_listed = Listed {
        first,
        last: head_number,
    };
    let list_record = SlotRecord {
        sequence: list_sequence,
        words: [now_listed.first, now_listed.last],
    };
    let list_file = open_kept(dir, SEGMENT_LIST, list_record)?;
    let mut list_sequence = list_sequence;
    if losses.is_empty() && listed.is_some_and(|listed| listed != now_listed) {
        list_sequence += 1;
        write_segment_list(dir, &list_file, list_sequence, now_listed)?;
    }
    let flushed = flushed.unwrap_or(FlushedRecord {
        sequence: 0,
        segment: head_number,
        length: HEADER,
    });
    let flushed_file = open_kept(dir, FLUSHED, flushed.as_record())?;
    Ok((
        State {
            index,
            head,
            head_number,
            head_format,
            head_len,
            spares,
            compacting: None,
            dirty: false,
            list_file,
            list_sequence,
            listed: now_listed,
            flushed_file,
            flushed,
        },
        losses,
    ))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::store::log::format::{seal_batch, BATCH_HEADER, MAGIC_V2};
    use crate::store::log::testing::*;
    use crate::store::log::MessageLog;
    use crate::store::{KvOp, KvPair};
    use proptest::prelude::*;
    use std::collections::{BTreeMap, HashMap};
    use std::os::unix::fs::FileExt;

    /// Page caches and disks write back out of order: a power cut may
    /// keep a batch while losing the one before it. The kept one must not
    /// come back when a second power cut loses the end mark of the batch
    /// later written over the lost one.
    #[test]
    fn a_batch_kept_past_a_lost_one_never_returns_after_a_second_power_cut() {
        let dir = temp_dir("second-cut");
        let log = MessageLog::open(&dir, OnDamage::Refuse, Bookkeeping::Adopted).unwrap();
        log.write(&[put("a", "1")], false).unwrap();
        log.flush().unwrap();
        let synced_end = data_end(&log) as usize;
        log.write(&[put("b", "2")], false).unwrap();
        let b_end = data_end(&log) as usize;
        log.write(&[remove("a")], false).unwrap();
        drop(log);
        // The first cut loses b (its bytes go back to the synced end mark
        // and zeros) and keeps the removal of a after it.
        let path = segment_path(&dir, *files(&dir).last().unwrap());
        let mut bytes = std::fs::read(&path).unwrap();
        bytes[synced_end..b_end].fill(0);
        std::fs::write(&path, &bytes).unwrap();
        let log = MessageLog::open(&dir, OnDamage::Refuse, Bookkeeping::Adopted).unwrap();
        assert_eq!(pairs(&log), vec![("a".into(), "1".into())]);
        let on_disk = std::fs::read(&path).unwrap();
        // b again, the same size: its end mark lies where the removal's
        // header was. The second cut loses that end mark: those bytes go
        // back to what the disk held.
        log.write(&[put("b", "3")], false).unwrap();
        assert_eq!(data_end(&log) as usize, b_end);
        drop(log);
        let mut bytes = std::fs::read(&path).unwrap();
        for (at, byte) in bytes.iter_mut().enumerate().skip(b_end).take(BATCH_HEADER) {
            *byte = on_disk.get(at).copied().unwrap_or(0);
        }
        std::fs::write(&path, &bytes).unwrap();
        let log = MessageLog::open(&dir, OnDamage::Refuse, Bookkeeping::Adopted).unwrap();
        assert_eq!(
            pairs(&log),
            vec![("a".into(), "1".into()), ("b".into(), "3".into())]
        );
        drop(log);
        let _ = std::fs::remove_dir_all(&dir);
    }

    #[test]
    fn a_missing_segment_is_damage() {
        let dir = temp_dir("missing");
        {
            let log =
                MessageLog::open_sized(&dir, OnDamage::Refuse, Bookkeeping::Adopted, 64).unwrap();
            for i in 0..6 {
                log.write(&[put(&format!("k{i}"), &"v".repeat(40))], false)
                    .unwrap();
            }
            log.flush().unwrap();
        }
        let numbers = files(&dir);
        std::fs::remove_file(segment_path(&dir, numbers[1])).unwrap();
        let message = MessageLog::open(&dir, OnDamage::Refuse, Bookkeeping::Adopted)
            .unwrap_err()
            .to_string();
        assert!(message.contains("missing"), "{message}");
        let _ = std::fs::remove_dir_all(&dir);
    }

    #[test]
    fn a_missing_newest_segment_every_segment_or_bookkeeping_file_refuses() {
        type Damage = fn(&Path);
        let cases: [(&str, Damage); 4] = [
            ("newest", |dir| {
                std::fs::remove_file(segment_path(dir, *files(dir).last().unwrap())).unwrap()
            }),
            ("all", |dir| {
                for number in files(dir) {
                    std::fs::remove_file(segment_path(dir, number)).unwrap();
                }
            }),
            ("list", |dir| {
                std::fs::remove_file(dir.join(SEGMENT_LIST.name)).unwrap()
            }),
            ("flushed", |dir| {
                std::fs::remove_file(dir.join(FLUSHED.name)).unwrap()
            }),
        ];
        for (name, damage) in cases {
            let dir = filled(&format!("missing-{name}"), 6, 64);
            assert!(files(&dir).len() >= 3);
            damage(&dir);
            let message = refused(&dir);
            assert!(message.contains("missing"), "{name}: {message}");
            let _ = std::fs::remove_dir_all(&dir);
        }
    }

    /// A rotation cut short between starting the next segment and listing
    /// it leaves one file past the list's newest, holding no batch (or
    /// not even a whole header): it is taken in, or removed. A segment
    /// further on is damage.
    #[test]
    fn a_segment_past_the_list_is_a_cut_short_rotation_or_damage() {
        let dir = filled("past-list", 6, 64);
        let newest = *files(&dir).last().unwrap();
        // The rotation sealed the head before starting the next segment.
        let end = MessageLog::open_sized(&dir, OnDamage::Refuse, Bookkeeping::Required, 64)
            .map(|log| data_end(&log))
            .unwrap();
        let file = OpenOptions::new()
            .write(true)
            .open(segment_path(&dir, newest))
            .unwrap();
        file.write_all_at(&seal_batch(Format::V2, newest), end)
            .unwrap();
        let mut header = MAGIC_V2.to_vec();
        header.extend_from_slice(&(newest + 1).to_be_bytes());
        std::fs::write(segment_path(&dir, newest + 1), &header).unwrap();
        let log =
            MessageLog::open_sized(&dir, OnDamage::Refuse, Bookkeeping::Required, 64).unwrap();
        assert_eq!(pairs(&log).len(), 6);
        assert_eq!(log.state().head_number, newest + 1);
        drop(log);
        let newest = newest + 1;
        std::fs::write(segment_path(&dir, newest + 1), &header[..5]).unwrap();
        let log =
            MessageLog::open_sized(&dir, OnDamage::Refuse, Bookkeeping::Required, 64).unwrap();
        assert_eq!(pairs(&log).len(), 6);
        assert!(!segment_path(&dir, newest + 1).exists());
        drop(log);
        std::fs::write(segment_path(&dir, newest + 2), &header).unwrap();
        let message = refused(&dir);
        assert!(message.contains("past the newest"), "{message}");
        let _ = std::fs::remove_dir_all(&dir);
    }

    /// Each segment or spare file's bytes as last seen, per file (inode)
    /// and per life (the segment number in its header), to model what a
    /// recycled file held before.
    #[derive(Default)]
    struct FileLives(HashMap<(u64, u64), Vec<u8>>);

    impl FileLives {
        fn observe(&mut self, dir: &Path) {
            use std::os::unix::fs::MetadataExt;
            for entry in std::fs::read_dir(dir).unwrap() {
                let path = entry.unwrap().path();
                if !path.extension().is_some_and(|e| e == "seg" || e == "spare") {
                    continue;
                }
                let bytes = std::fs::read(&path).unwrap();
                let number = u64::from_be_bytes(bytes[8..16].try_into().unwrap());
                let inode = std::fs::metadata(&path).unwrap().ino();
                self.0.insert((inode, number), bytes);
            }
        }

        /// What the file at `path` held in its life before segment
        /// `number` (nothing if it is new).
        fn earlier_life(&self, path: &Path, number: u64) -> Vec<u8> {
            use std::os::unix::fs::MetadataExt;
            let inode = std::fs::metadata(path).unwrap().ino();
            self.0
                .iter()
                .filter(|((i, n), _)| *i == inode && *n < number)
                .max_by_key(|((_, n), _)| *n)
                .map(|(_, bytes)| bytes.clone())
                .unwrap_or_default()
        }
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(64))]

        /// A power cut: the newest segment keeps what was synced plus any
        /// prefix of what was written after (as a page cache might); past
        /// that its file holds what it held at the last sync (for a
        /// recycled file, its earlier life's batches), then nothing or
        /// zeros, and the prefix's last byte is possibly garbage. The log
        /// opens on exactly the state after the last flush or after some
        /// later batch: nothing flushed is lost, no batch is applied in
        /// part or out of order, and no batch from a recycled file's
        /// earlier life comes back.
        #[test]
        fn a_power_cut_keeps_every_flushed_batch_and_a_prefix_of_the_rest(
            batches in proptest::collection::vec(
                (proptest::collection::vec((0u8..12, proptest::option::of(0usize..120)), 1..4), any::<bool>()),
                1..60,
            ),
            kept in any::<proptest::sample::Index>(),
            garbage in any::<bool>(),
            zeroed in any::<bool>(),
        ) {
            let dir = temp_dir("power-cut");
            let log = MessageLog::open_sized(&dir, OnDamage::Refuse, Bookkeeping::Adopted, 400).unwrap();
            let mut model: BTreeMap<Vec<u8>, Vec<u8>> = BTreeMap::new();
            let mut states = vec![Vec::new()];
            let mut flushed_states = 0;
            let mut files = FileLives::default();
            // The head's number, data end and bytes at the last flush.
            let mut synced: Option<(u64, u64, Vec<u8>)> = None;
            for (n, (ops, flush)) in batches.iter().enumerate() {
                let ops: Vec<KvOp> = ops
                    .iter()
                    .map(|(k, len)| (vec![*k], len.map(|len| vec![n as u8; len])))
                    .collect();
                log.write(&ops, false).unwrap();
                for (key, value) in ops {
                    match value {
                        Some(value) => model.insert(key, value),
                        None => model.remove(&key),
                    };
                }
                states.push(model.clone().into_iter().collect::<Vec<KvPair>>());
                if *flush {
                    log.flush().unwrap();
                    flushed_states = states.len() - 1;
                    let head = log.state().head_number;
                    let bytes = std::fs::read(segment_path(&dir, head)).unwrap();
                    synced = Some((head, data_end(&log), bytes));
                }
                files.observe(&dir);
            }
            let newest = log.state().head_number;
            let written = data_end(&log) + BATCH_HEADER as u64;
            drop(log);
            let path = segment_path(&dir, newest);
            let now = std::fs::read(&path).unwrap();
            let (synced_len, before) = match synced {
                Some((head, end, bytes)) if head == newest => (end, bytes),
                // Started since: its header and end mark were synced,
                // after them lie its earlier life's bytes, if it had one.
                _ => {
                    let marked = HEADER as usize + BATCH_HEADER;
                    let mut bytes = files.earlier_life(&path, newest);
                    bytes.resize(bytes.len().max(marked), 0);
                    bytes[..marked].copy_from_slice(&now[..marked]);
                    (HEADER, bytes)
                }
            };
            let cut = synced_len + kept.index((written - synced_len + 1) as usize) as u64;
            let mut after = now[..cut as usize].to_vec();
            if before.len() > after.len() {
                after.extend_from_slice(&before[after.len()..]);
            }
            if zeroed && now.len() > after.len() {
                after.resize(now.len(), 0);
            }
            if garbage && cut > synced_len {
                after[cut as usize - 1] ^= 0x5a;
            }
            std::fs::write(&path, &after).unwrap();
            // The bookkeeping files are as the page cache left them.
            let log = MessageLog::open_sized(&dir, OnDamage::Refuse, Bookkeeping::Required, 400).unwrap();
            let found = log.scan().unwrap();
            prop_assert!(
                states[flushed_states..].contains(&found),
                "found {:?}, flushed {:?}", found, states[flushed_states]
            );
            drop(log);
            let _ = std::fs::remove_dir_all(&dir);
        }
    }
}
