//! Reading one segment at open, and what its damage costs. A segment
//! must reach through its seal, or, the newest, through its recorded
//! flushed length; what is wrong below that is damage, what is wrong past
//! it a torn tail (never confirmed), where reading stops.
//!
//! Salvaging ([`OnDamage::Salvage`]) keeps every readable batch: after a
//! bad stretch it goes on at the next offset where a whole batch passes
//! its checksum (format 2 checksums hold the segment's number, so a
//! stretch of another segment's or a recycled file's batches never
//! passes), notes each lost stretch and the keys the batches there held
//! when they still parse without their checksums ([`Losses`]), then
//! writes every readable record into a new log that takes the damaged
//! one's place (the caller has copied it aside; see `open`).
//!
//! Uses `format`, `files` and `index`.

use super::files::{io_error, segment_path};
use super::format::{check_batch, parse_records, Format, Record, BATCH_HEADER, HEADER};
use super::index::Index;
use crate::store::StoreError;
use std::path::{Path, PathBuf};

/// How the message log treats damage when it is opened.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum OnDamage {
    /// Fail, naming the file and what is wrong.
    Refuse,
    /// Keep every readable batch: go on after a bad one at the next valid
    /// one, note what was lost (the log's `losses`) and rebuild the
    /// log from what was read.
    Salvage,
}

/// How far a segment's data must reach when it is read.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) enum Reach {
    /// Through its seal: any segment but the newest.
    Seal,
    /// At least this far: the newest, whose recorded flushed length it is
    /// (every confirm was sent for data below it; see `bookkeeping`'s docs).
    Flushed(u64),
}

/// What reading a segment found.
pub(super) struct Read {
    /// Its format, if its header is whole.
    pub(super) format: Option<Format>,
    /// End of the last good batch.
    pub(super) good_end: u64,
    /// Whether that batch is a seal.
    pub(super) sealed: bool,
    /// Whether bytes other than zeros lie beyond the data's end.
    pub(super) leftover: bool,
    /// Damage below what the segment must reach (when refusing).
    pub(super) damage: Option<String>,
    /// A torn tail: what is wrong at or past the flushed length of the
    /// newest segment (never confirmed), where reading stopped.
    pub(super) torn: Option<String>,
}

/// Bytes of the message log a salvage could not read.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct LostRange {
    /// The segment file.
    pub segment: PathBuf,
    /// The byte range lost, or `None` when the whole segment is missing.
    pub bytes: Option<(u64, u64)>,
    /// What was wrong there.
    pub problem: String,
}

/// What a salvage of the message log could not keep (as the log's
/// `losses` returns it).
#[derive(Debug, Default, Clone)]
pub struct Losses {
    /// Every range that could not be read, in log order.
    pub ranges: Vec<LostRange>,
    /// Keys whose latest put lay in an unreadable batch (read without its
    /// checksum) and no later readable write replaced: their values are
    /// gone. Sorted.
    pub puts: Vec<Vec<u8>>,
    /// Keys whose latest removal lay there: an older value comes back.
    /// Sorted.
    pub removals: Vec<Vec<u8>>,
    /// How many ranges did not parse even without their checksums (zeros,
    /// a cut file, a missing segment): what they held is unknown.
    pub unknown_ranges: usize,
    /// What was wrong with the segment list or the flushed length (no
    /// record is lost with them; the rebuilt log has new ones).
    pub bookkeeping: Vec<String>,
}

impl Losses {
    /// Whether nothing was damaged (the log is then not rebuilt).
    pub fn is_empty(&self) -> bool {
        self.ranges.is_empty() && self.bookkeeping.is_empty()
    }
}

/// The first offset in `from..until` of `bytes` where a whole, valid batch
/// starts, for a salvage to go on after damage (format 2 batches checksum
/// their segment's number, so a recycled file's old batches never match).
fn resync(bytes: &[u8], from: usize, until: usize, format: Format, segment: u64) -> Option<usize> {
    (from..until.min(bytes.len())).find(|&at| check_batch(format, segment, &bytes[at..]).is_ok())
}

impl Index {
    /// Notes what the unreadable `bytes` held, read as batches without
    /// their checksums (the puts and removals a salvage reports lost);
    /// whether they all parsed.
    fn note_unreadable(&mut self, bytes: &[u8]) -> bool {
        let mut at = 0;
        while at < bytes.len() {
            let Some(header) = bytes.get(at..at + BATCH_HEADER) else {
                return false;
            };
            let len = u32::from_le_bytes(header[..4].try_into().expect("4 bytes")) as usize;
            let Some(records) = bytes
                .get(at + BATCH_HEADER..at + BATCH_HEADER + len)
                .filter(|payload| !payload.is_empty())
                .and_then(parse_records)
            else {
                return false;
            };
            for record in records {
                match record {
                    Record::Put { key, .. } => {
                        self.unread_removals.remove(key);
                        self.unread_puts.insert(key.to_vec());
                    }
                    Record::Remove { key } => {
                        self.unread_puts.remove(key);
                        self.unread_removals.insert(key.to_vec());
                    }
                    Record::Seal => {}
                }
            }
            at += BATCH_HEADER + len;
        }
        true
    }

    /// Reads segment `number`'s batches into the index. Damage below
    /// `reach` is reported as such when refusing; when salvaging, each bad
    /// stretch is noted in `losses` and reading goes on at the next valid
    /// batch. Whatever is wrong at or past a newest segment's flushed
    /// length is a torn tail: reading stops there.
    pub(super) fn read_segment(
        &mut self,
        dir: &Path,
        number: u64,
        reach: Reach,
        on_damage: OnDamage,
        losses: &mut Losses,
    ) -> Result<Read, StoreError> {
        let path = segment_path(dir, number);
        let bytes = std::fs::read(&path).map_err(|e| io_error(&path, e))?;
        self.segments.entry(number).or_default();
        let header_format = bytes.get(..8).and_then(Format::of_magic);
        let header_format =
            header_format.filter(|_| bytes.get(8..16) == Some(&number.to_be_bytes()));
        let mut read = Read {
            format: header_format,
            good_end: HEADER,
            sealed: false,
            leftover: false,
            damage: None,
            torn: None,
        };
        let mut lose = |index: &mut Index, from: usize, to: usize, problem: String| {
            if !index.note_unreadable(&bytes[from..to]) {
                losses.unknown_ranges += 1;
            }
            losses.ranges.push(LostRange {
                segment: path.clone(),
                bytes: Some((from as u64, to as u64)),
                problem,
            });
        };
        let format = match (header_format, on_damage) {
            (Some(format), _) => format,
            (None, OnDamage::Refuse) => {
                read.good_end = 0;
                read.damage = Some("its header is missing or wrong".into());
                return Ok(read);
            }
            // Read on as the format every segment is started in.
            (None, OnDamage::Salvage) => {
                let end = bytes.len().min(HEADER as usize);
                lose(self, 0, end, "its header is missing or wrong".into());
                Format::V2
            }
        };
        let until = match reach {
            Reach::Seal => bytes.len(),
            Reach::Flushed(flushed) => (flushed as usize).min(bytes.len()),
        };
        let mut at = HEADER as usize;
        let mut sealed = false;
        loop {
            let must_go_on = match reach {
                Reach::Seal => !sealed,
                Reach::Flushed(flushed) => (at as u64) < flushed,
            };
            let rest = &bytes[at.min(bytes.len())..];
            let ended = rest[..rest.len().min(BATCH_HEADER)].iter().all(|&b| b == 0);
            let issue = if ended {
                // The end mark, the zeros a head was extended with, or the
                // end of the file.
                if !must_go_on {
                    break;
                }
                let what = if rest.is_empty() {
                    format!("the file ends at offset {at}")
                } else {
                    format!("zeros at offset {at}")
                };
                match reach {
                    Reach::Seal => format!("{what}, before its seal (truncated or zeroed)"),
                    Reach::Flushed(flushed) => format!(
                        "{what}, below the {flushed} bytes recorded as flushed (truncated or \
                         zeroed)"
                    ),
                }
            } else {
                match check_batch(format, number, rest) {
                    Ok((len, records)) => {
                        sealed = matches!(records[..], [Record::Seal]);
                        self.apply(number, (at + BATCH_HEADER) as u64, records);
                        at += BATCH_HEADER + len;
                        continue;
                    }
                    Err(problem) => format!("at offset {at}: {problem}"),
                }
            };
            if matches!(reach, Reach::Flushed(flushed) if at as u64 >= flushed) {
                read.torn = Some(issue);
                break;
            }
            match on_damage {
                OnDamage::Refuse => {
                    read.damage = Some(issue);
                    break;
                }
                OnDamage::Salvage => {
                    let next = resync(&bytes, at + 1, until, format, number);
                    let from = at.min(bytes.len());
                    lose(self, from, next.unwrap_or(bytes.len()).max(from), issue);
                    match next {
                        Some(next) => at = next,
                        None => {
                            // Nothing readable follows: what the segment
                            // held after the damage is gone.
                            at = bytes.len();
                            break;
                        }
                    }
                }
            }
        }
        read.good_end = at as u64;
        read.sealed = sealed;
        read.leftover = bytes
            .get(at..)
            .is_some_and(|rest| rest.iter().any(|&b| b != 0));
        Ok(read)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::store::log::append::SEGMENT_BYTES;
    use crate::store::log::bookkeeping::{
        open_kept, read_flushed, Bookkeeping, FlushedRecord, FLUSHED, SEGMENT_LIST,
    };
    use crate::store::log::files::segment_path;
    use crate::store::log::format::{MAGIC_V1, MAGIC_V2};
    use crate::store::log::testing::*;
    use crate::store::log::MessageLog;
    use crate::store::slots::SlotRecord;
    use proptest::prelude::*;
    use std::fs::OpenOptions;
    use std::os::unix::fs::FileExt;

    #[test]
    fn a_batch_cut_short_at_the_end_is_dropped_and_writing_goes_on_after_the_good_data() {
        let dir = temp_dir("torn");
        let mut log = MessageLog::open(&dir, OnDamage::Refuse, Bookkeeping::Adopted).unwrap();
        log.write(&[put("a", "1")], false).unwrap();
        log.flush().unwrap();
        // Each time the last batch (not flushed) loses its last `cut`
        // bytes, cut off or left as the zeros after the data.
        for cut in 1..=8 {
            for zeroed in [false, true] {
                log.write(&[put("b", "2")], false).unwrap();
                let end = data_end(&log);
                drop(log);
                lose_tail(&dir, end - cut, end, zeroed);
                log = MessageLog::open(&dir, OnDamage::Refuse, Bookkeeping::Adopted).unwrap();
                assert_eq!(pairs(&log), vec![("a".into(), "1".into())], "cut {cut}");
                log.write(&[put("c", "3")], false).unwrap();
                log.flush().unwrap();
                drop(log);
                log = MessageLog::open(&dir, OnDamage::Refuse, Bookkeeping::Adopted).unwrap();
                assert_eq!(
                    pairs(&log),
                    vec![("a".into(), "1".into()), ("c".into(), "3".into())]
                );
                log.write(&[remove("c")], false).unwrap();
                log.flush().unwrap();
            }
        }
        drop(log);
        let _ = std::fs::remove_dir_all(&dir);
    }

    #[test]
    fn damage_before_the_last_segment_refuses_and_salvage_keeps_every_other_batch() {
        let dir = temp_dir("damage");
        let sizes: Vec<u64> = {
            let log =
                MessageLog::open_sized(&dir, OnDamage::Refuse, Bookkeeping::Adopted, 64).unwrap();
            for i in 0..6 {
                log.write(&[put(&format!("k{i}"), &"v".repeat(40))], false)
                    .unwrap();
            }
            log.flush().unwrap();
            let state = log.state();
            state.index.segments.values().map(|s| s.size).collect()
        };
        let numbers = files(&dir);
        assert!(numbers.len() >= 3, "{numbers:?}");
        let second = segment_path(&dir, numbers[1]);
        let mut bytes = std::fs::read(&second).unwrap();
        // The last byte of its value, before its seal batch.
        let in_value = (sizes[1] - BATCH_HEADER as u64 - 2) as usize;
        bytes[in_value] ^= 0xff;
        std::fs::write(&second, bytes).unwrap();
        let refused = MessageLog::open(&dir, OnDamage::Refuse, Bookkeeping::Adopted).unwrap_err();
        let message = refused.to_string();
        assert!(message.contains(&second.display().to_string()), "{message}");
        assert!(message.contains("checksum"), "{message}");
        let log = MessageLog::open(&dir, OnDamage::Salvage, Bookkeeping::Adopted).unwrap();
        let kept = pairs(&log);
        assert_eq!(kept.len(), 5, "only the damaged batch is lost: {kept:?}");
        drop(log);
        // Salvaged, it opens normally again.
        MessageLog::open(&dir, OnDamage::Refuse, Bookkeeping::Adopted).unwrap();
        let _ = std::fs::remove_dir_all(&dir);
    }

    /// The newest segment's data below its recorded flushed length was
    /// confirmed: a flipped byte, a cut or zeros there refuse the start,
    /// naming the segment (a torn tail is only ever past that length).
    #[test]
    fn damage_below_the_flushed_length_of_the_newest_segment_refuses() {
        for damage in ["flip", "truncate", "zero"] {
            let dir = filled(&format!("below-flushed-{damage}"), 5, SEGMENT_BYTES);
            let newest = segment_path(&dir, *files(&dir).last().unwrap());
            let flushed = read_flushed(&dir).unwrap().unwrap();
            assert_eq!(flushed.length, HEADER + 5 * FILLED_BATCH);
            let at = HEADER + 60;
            let file = OpenOptions::new().write(true).open(&newest).unwrap();
            match damage {
                "flip" => file.write_all_at(&[0x5a], at).unwrap(),
                "truncate" => file.set_len(at).unwrap(),
                _ => file.write_all_at(&[0; 64], at).unwrap(),
            }
            let message = refused(&dir);
            assert!(
                message.contains(&newest.display().to_string()),
                "{damage}: {message}"
            );
            let _ = std::fs::remove_dir_all(&dir);
        }
    }

    /// Salvage goes on after a bad batch at the next valid one, reports
    /// exactly the put it lost, and leaves a whole log.
    #[test]
    fn salvage_resynchronises_after_a_bad_batch_and_reports_its_puts() {
        let dir = filled("resync", 10, SEGMENT_BYTES);
        let newest = segment_path(&dir, *files(&dir).last().unwrap());
        // Inside k3's value.
        let at = HEADER + 3 * FILLED_BATCH + 30;
        let file = OpenOptions::new().write(true).open(&newest).unwrap();
        file.write_all_at(&[0x5a], at).unwrap();
        assert!(refused(&dir).contains("checksum"));
        let log = MessageLog::open(&dir, OnDamage::Salvage, Bookkeeping::Required).unwrap();
        let kept: Vec<String> = pairs(&log).into_iter().map(|(k, _)| k).collect();
        assert_eq!(kept.len(), 9);
        assert!(!kept.contains(&"k3".to_owned()) && kept.contains(&"k9".to_owned()));
        let losses = log.losses();
        assert_eq!(losses.ranges.len(), 1);
        assert_eq!(losses.puts, vec![b"k3".to_vec()]);
        assert_eq!(losses.unknown_ranges, 0);
        drop(log);
        let log = MessageLog::open(&dir, OnDamage::Refuse, Bookkeeping::Required).unwrap();
        assert_eq!(pairs(&log).len(), 9);
        drop(log);
        let _ = std::fs::remove_dir_all(&dir);
    }

    /// A lost removal brings its key back, and is reported; a lost put
    /// whose key a later readable batch removed is no loss.
    #[test]
    fn salvage_reports_lost_removals_and_forgets_superseded_puts() {
        let dir = temp_dir("lost-removal");
        let log = MessageLog::open(&dir, OnDamage::Refuse, Bookkeeping::Adopted).unwrap();
        log.write(&[put("a", "1")], false).unwrap();
        let damaged = data_end(&log);
        log.write(&[remove("a"), put("b", "2")], false).unwrap();
        log.write(&[remove("b")], false).unwrap();
        log.flush().unwrap();
        drop(log);
        let path = segment_path(&dir, *files(&dir).last().unwrap());
        let file = OpenOptions::new().write(true).open(&path).unwrap();
        file.write_all_at(&[0xff], damaged + 4).unwrap();
        let log = MessageLog::open(&dir, OnDamage::Salvage, Bookkeeping::Required).unwrap();
        assert_eq!(pairs(&log), vec![("a".into(), "1".into())]);
        assert_eq!(log.losses().removals, vec![b"a".to_vec()]);
        assert!(log.losses().puts.is_empty());
        drop(log);
        let _ = std::fs::remove_dir_all(&dir);
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(64))]

        /// A byte flipped anywhere in data a flush covered (any segment
        /// the list names, the newest up to its recorded flushed length)
        /// refuses the start: only a tail no confirm covered is dropped.
        #[test]
        fn a_flipped_byte_below_what_was_flushed_always_refuses(
            batches in proptest::collection::vec((0u8..12, 1usize..120, any::<bool>()), 1..40),
            which in any::<proptest::sample::Index>(),
            at in any::<proptest::sample::Index>(),
        ) {
            let dir = temp_dir("flip-flushed");
            let log = MessageLog::open_sized(&dir, OnDamage::Refuse, Bookkeeping::Adopted, 400).unwrap();
            for (key, len, removed) in &batches {
                let value = (!removed).then(|| vec![1; *len]);
                log.write(&[(vec![*key], value)], false).unwrap();
            }
            log.flush().unwrap();
            let spans: Vec<(u64, u64)> = {
                let state = log.state();
                state
                    .index
                    .segments
                    .iter()
                    .map(|(&number, segment)| {
                        let end = if number != state.head_number {
                            segment.size
                        } else if state.flushed.segment == number {
                            state.flushed.length
                        } else {
                            HEADER
                        };
                        (number, end)
                    })
                    .filter(|&(_, end)| end > HEADER)
                    .collect()
            };
            drop(log);
            prop_assume!(!spans.is_empty());
            let (number, end) = spans[which.index(spans.len())];
            let offset = HEADER + at.index((end - HEADER) as usize) as u64;
            let path = segment_path(&dir, number);
            let mut bytes = std::fs::read(&path).unwrap();
            bytes[offset as usize] ^= 0x5a;
            std::fs::write(&path, bytes).unwrap();
            let opened = MessageLog::open_sized(&dir, OnDamage::Refuse, Bookkeeping::Required, 400);
            prop_assert!(opened.is_err(), "segment {} offset {} of {}", number, offset, end);
            let _ = std::fs::remove_dir_all(&dir);
        }

        /// Whatever bytes a segment holds (its header cut or not), with or
        /// without bookkeeping files claiming any flushed length, opening
        /// never panics: it refuses or salvages, and a salvaged log then
        /// opens as a whole one.
        #[test]
        fn any_segment_bytes_open_without_panicking(
            tail in proptest::collection::vec(any::<u8>(), 0..200),
            cut in any::<proptest::sample::Index>(),
            older in any::<bool>(),
            first_format in any::<bool>(),
            claimed in proptest::option::of(0u64..400),
        ) {
            let dir = temp_dir("garbage");
            std::fs::create_dir_all(&dir).unwrap();
            let magic = if first_format { MAGIC_V1 } else { MAGIC_V2 };
            let mut bytes = magic.to_vec();
            bytes.extend_from_slice(&1u64.to_be_bytes());
            bytes.extend_from_slice(&tail);
            bytes.truncate(cut.index(bytes.len() + 1));
            std::fs::write(segment_path(&dir, 1), &bytes).unwrap();
            let newest = if older {
                let mut next = MAGIC_V2.to_vec();
                next.extend_from_slice(&2u64.to_be_bytes());
                std::fs::write(segment_path(&dir, 2), &next).unwrap();
                2
            } else {
                1
            };
            let bookkeeping = match claimed {
                Some(length) => {
                    let list = SlotRecord { sequence: 1, words: [1, newest] };
                    open_kept(&dir, SEGMENT_LIST, list).unwrap();
                    let record = FlushedRecord { sequence: 1, segment: newest, length };
                    open_kept(&dir, FLUSHED, record.as_record()).unwrap();
                    Bookkeeping::Required
                }
                None => Bookkeeping::Adopted,
            };
            let _ = MessageLog::open(&dir, OnDamage::Refuse, bookkeeping);
            let log = MessageLog::open(&dir, OnDamage::Salvage, bookkeeping).unwrap();
            log.write(&[(b"k".to_vec(), Some(b"v".to_vec()))], false).unwrap();
            log.flush().unwrap();
            drop(log);
            let log = MessageLog::open(&dir, OnDamage::Refuse, Bookkeeping::Required).unwrap();
            prop_assert!(log.scan().unwrap().contains(&(b"k".to_vec(), b"v".to_vec())));
            drop(log);
            let _ = std::fs::remove_dir_all(&dir);
        }
    }
}
