//! The persister: one thread that takes submissions of [`StoreOp`]s from
//! every connection, writes them in groups (plain writes in order, a
//! transaction's commit as one atomic batch, delivery marks merged to one
//! write per queue) and flushes once per group; and [`Persistence`], the
//! broker's handle on it, which numbers submissions and reports how far
//! the disk has got, so a confirm or a commit-ok waits for exactly the
//! flush that covers it.
//!
//! Submissions wait in an [`Inbox`] under a mutex: a submission is
//! numbered and queued in one step, so the persister always takes a
//! contiguous run of numbers, and the only cross-thread signal is a wake
//! when the persister sleeps (a channel costs every send atomics shared
//! with the draining thread).

use super::slots::{SlotFile, SlotRecord};
use super::{guarded, KvOp, Recovered, Store, StoreError, StoreOp, WriteMode};
use crate::stats::{Histogram, HistogramFigures};
use crate::word_hash::WordHashMap;
use std::collections::VecDeque;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Condvar, Mutex, MutexGuard};
use tokio::sync::watch;

/// The most ops one group commit writes before its flush (more wait for
/// the next group), so one flush stays short.
const GROUP_OPS: usize = 50_000;

/// A request to the persister: ops to write as `mode` says;
/// or, with `close`, the last request: flush, release the store, answer.
struct Submission {
    /// Its number: one more than the submission queued before it.
    number: u64,
    ops: Vec<StoreOp>,
    mode: WriteMode,
    close: Option<tokio::sync::oneshot::Sender<()>>,
    /// Files written outside the store (a stream's segments) that this
    /// group's flush must sync too.
    syncs: Vec<Arc<std::fs::File>>,
    /// What to record once they are synced.
    then: Option<AfterSync>,
}

/// A bookkeeping record to write once a group's syncs have succeeded (a
/// stream's synced offset): one `pwrite`, not synced itself, so what
/// survives a power cut is this record or an earlier one, a lower bound of
/// what was synced (see `super::slots`).
#[derive(Debug)]
pub(crate) struct AfterSync {
    /// The bookkeeping file, open for writing.
    pub file: Arc<std::fs::File>,
    /// Its kind.
    pub kind: SlotFile,
    /// The record; of two for the same file in one group, the one with
    /// the higher sequence is written.
    pub record: SlotRecord,
}

impl std::fmt::Debug for Submission {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "Submission({} ops)", self.ops.len())
    }
}

/// How far the persister has got: every submission numbered up to
/// `flushed` has been attempted, and is on disk unless its batch failed
/// (see [`Persistence::succeeded`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Durable {
    /// Highest submission number attempted.
    pub flushed: u64,
}

/// The submissions one piece of work made (a publish: its shared record
/// and its queues' index entries), as the span of their numbers. It is on
/// disk once the persister has attempted the last and no group in the
/// span failed ([`Persistence::written`]): a failed group between two of
/// its submissions counts against it even if it held none of them, so the
/// answer errs towards "not written", never the other way.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct Written {
    first: u64,
    last: u64,
}

impl Written {
    /// Adds submission `number` (0, "nothing submitted", adds nothing).
    pub fn add(&mut self, number: u64) {
        if number == 0 {
            return;
        }
        self.first = if self.first == 0 {
            number
        } else {
            self.first.min(number)
        };
        self.last = self.last.max(number);
    }

    /// The highest submission number in it (0 if it is empty): the
    /// persister's progress to wait for.
    pub fn last(&self) -> u64 {
        self.last
    }
}

/// Submissions not yet taken by the persister, in number order.
#[derive(Debug, Default)]
struct Inbox {
    waiting: Vec<Submission>,
    /// The number the latest submission got.
    numbered: u64,
    /// The persister sleeps until a submission wakes it.
    sleeping: bool,
    /// The broker's handle is gone (the persister writes what waits, then
    /// stops), or the persister has stopped (later submissions are
    /// dropped, never answered).
    closed: bool,
}

/// The inbox and the persister's wake-up call.
#[derive(Debug, Default)]
struct Mailbox {
    inbox: Mutex<Inbox>,
    arrived: Condvar,
}

impl Mailbox {
    fn lock(&self) -> MutexGuard<'_, Inbox> {
        // Held only to push, take or flag, never across a call that can
        // panic midway through a change.
        self.inbox.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// Waits for submissions; takes them, in order, up to [`GROUP_OPS`]
    /// ops (at least one submission) into `taken`. False once the inbox is
    /// closed and empty.
    fn take(&self, taken: &mut Vec<Submission>) -> bool {
        let mut inbox = self.lock();
        while inbox.waiting.is_empty() {
            if inbox.closed {
                return false;
            }
            inbox.sleeping = true;
            inbox = self.arrived.wait(inbox).unwrap_or_else(|e| e.into_inner());
        }
        inbox.sleeping = false;
        let mut ops = 0;
        let fit = inbox
            .waiting
            .iter()
            .enumerate()
            .take_while(|(at, submission)| {
                ops += submission.ops.len();
                *at == 0 || ops <= GROUP_OPS
            })
            .count();
        if fit == inbox.waiting.len() {
            std::mem::swap(&mut inbox.waiting, taken);
        } else {
            taken.extend(inbox.waiting.drain(..fit));
        }
        true
    }
}

/// The most recent failed batches remembered, as submission ranges. A
/// waiting publish checks its number against them within moments of the
/// failure, so a short history is enough; one that checks later, after its
/// range was evicted, reads as failed ([`FailureLog::forgotten`]).
const FAILED_HISTORY: usize = 4096;

/// The failed groups' submission ranges, the newest [`FAILED_HISTORY`] of
/// them, and how far the evicted ones reached.
#[derive(Debug, Default)]
struct FailureLog {
    ranges: VecDeque<(u64, u64)>,
    /// Highest submission number of an evicted range: a span that starts
    /// at or below it may have held an evicted failure, so it counts as
    /// failed (the safe direction: a nack, never a false ack).
    forgotten: u64,
}

impl FailureLog {
    fn record(&mut self, from: u64, to: u64) {
        if self.ranges.len() == FAILED_HISTORY {
            if let Some((_, evicted)) = self.ranges.pop_front() {
                self.forgotten = self.forgotten.max(evicted);
            }
        }
        self.ranges.push_back((from, to));
    }

    /// Whether a failed group (remembered or forgotten) overlaps
    /// submissions `first..=last`.
    fn overlaps(&self, first: u64, last: u64) -> bool {
        first <= self.forgotten
            || self
                .ranges
                .iter()
                .any(|&(from, to)| from <= last && to >= first)
    }
}

/// The broker's handle on durable storage: submit ops, learn when they are
/// on disk. Submissions are numbered; [`Persistence::durable`] reports the
/// highest number flushed.
#[derive(Debug)]
pub struct Persistence {
    mailbox: Arc<Mailbox>,
    durable: watch::Receiver<Durable>,
    failed: Arc<Mutex<FailureLog>>,
    /// How many groups have failed so far (the disk alarm probes free
    /// space when it changes).
    failures: watch::Receiver<u64>,
    next_message_id: AtomicU64,
    next_queue_id: AtomicU64,
    /// This start's number on the store (one more than the last).
    start: u64,
    figures: Arc<GroupFigures>,
    /// Where streams keep their segment files (`<data dir>/streams`), set
    /// once by the broker that opened the store in a data directory, and
    /// whether a damaged stream is recovered (`--recover`) or refused.
    stream_root: std::sync::OnceLock<(std::path::PathBuf, bool)>,
}

/// Ops per group commit: Prometheus-style bucket bounds.
static BATCH_BOUNDS: [f64; 12] = [
    1.0, 2.0, 5.0, 10.0, 20.0, 50.0, 100.0, 200.0, 500.0, 1000.0, 5000.0, 50000.0,
];
/// Seconds per group's writes and flush.
static FLUSH_BOUNDS: [f64; 13] = [
    0.0001, 0.00025, 0.0005, 0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0,
];

/// What the persister thread records of each group commit.
#[derive(Debug)]
struct GroupFigures {
    batch_ops: Histogram,
    flush_seconds: Histogram,
}

/// The persister's histograms, read at one moment.
#[derive(Debug, Clone, PartialEq)]
pub struct PersisterFigures {
    /// Ops written per group commit.
    pub batch_ops: HistogramFigures,
    /// Seconds each group took to write and flush.
    pub flush_seconds: HistogramFigures,
}

/// Bits of a queue position below the start number: each start's
/// positions begin at its number shifted by this, above every earlier
/// start's (2^40 positions per queue per start; 2^24 starts).
pub const START_SHIFT: u32 = 40;

/// One group commit being assembled by the persister: plain writes in
/// order, atomic submissions applied as batches in their place, delivery
/// marks merged to one write per queue, then one flush.
///
/// A message whose index entry (or shared record) is removed in the same
/// group that inserts it (a consumer acknowledged it while its enqueue was
/// waiting for the disk, the usual case when consumers keep up) is written
/// not at all: insert and remove are both dropped. The publisher's confirm
/// still waits for the group's flush; the message is by then fully handled,
/// which is when RabbitMQ confirms such a message too. Only keys that are
/// never rewritten qualify (index entries and shared records, whose
/// positions and ids are fresh), so no older stored value can show
/// through.
#[derive(Default)]
struct Group {
    /// Plain writes not yet applied (encoded only when written); `None`
    /// where an insert was dropped.
    pending: Vec<Option<StoreOp>>,
    /// Where in `pending` each fresh key's insert waits.
    /// Hashed by a multiply per word: its words are positions and ids the
    /// broker hands out, never a peer's choice (SipHash showed in the
    /// broker's profile under persistent load).
    fresh: WordHashMap<Fresh, usize>,
    /// Inserts dropped with their removes.
    elided: usize,
    marks: Vec<(u64, u64)>,
    /// The first and last submission numbers in the group.
    numbers: Option<(u64, u64)>,
    len: usize,
    error: Option<StoreError>,
    /// Files outside the store to sync with this group's flush.
    syncs: Vec<Arc<std::fs::File>>,
    /// Records to write once those are synced, one per file.
    then: Vec<AfterSync>,
    /// The files in `syncs`, and where each file's record is in `then`,
    /// by the file's address: a group can hold many streams' appends, so
    /// each submission finds its files at once, not by a scan.
    synced_files: WordHashMap<u64, ()>,
    records_at: WordHashMap<u64, usize>,
}

/// A shared file's address, its key in a group.
fn address(file: &Arc<std::fs::File>) -> u64 {
    Arc::as_ptr(file) as usize as u64
}

/// A key that is written once and removed once, never rewritten: a
/// queue's index entry, or a shared message record.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
enum Fresh {
    Index { queue: u64, seq: u64 },
    Message(u64),
}

impl Fresh {
    /// The fresh key `op` inserts (true) or removes (false), if any.
    fn of(op: &StoreOp) -> Option<(Fresh, bool)> {
        match *op {
            StoreOp::Enqueue { queue, seq, .. } => Some((Fresh::Index { queue, seq }, true)),
            StoreOp::Dequeue { queue, seq } => Some((Fresh::Index { queue, seq }, false)),
            StoreOp::PutMessage { id, .. } => Some((Fresh::Message(id), true)),
            StoreOp::DeleteMessage { id } => Some((Fresh::Message(id), false)),
            _ => None,
        }
    }
}

impl Group {
    /// Adds a submission; returns its close request, if it is one.
    fn add(
        &mut self,
        store: &dyn Store,
        submission: Submission,
    ) -> Option<tokio::sync::oneshot::Sender<()>> {
        let number = submission.number;
        self.numbers = Some(
            self.numbers
                .map_or((number, number), |(first, _)| (first, number)),
        );
        self.len += submission.ops.len();
        for file in submission.syncs {
            if self.synced_files.insert(address(&file), ()).is_none() {
                self.syncs.push(file);
            }
        }
        if let Some(after) = submission.then {
            match self.records_at.get(&address(&after.file)) {
                Some(&at) if self.then[at].record.sequence < after.record.sequence => {
                    self.then[at] = after;
                }
                Some(_) => {}
                None => {
                    self.records_at
                        .insert(address(&after.file), self.then.len());
                    self.then.push(after);
                }
            }
        }
        if submission.mode == WriteMode::Atomic {
            self.write_pending(store);
            let ops = submission.ops.iter().map(StoreOp::to_kv).collect();
            let result = guarded("write", || store.write(ops, WriteMode::Atomic));
            self.record(result);
            return submission.close;
        }
        for op in submission.ops {
            match op {
                StoreOp::Delivered { queue, seq } => {
                    match self.marks.iter_mut().find(|(q, _)| *q == queue) {
                        Some((_, mark)) => *mark = (*mark).max(seq),
                        None => self.marks.push((queue, seq)),
                    }
                }
                op => self.push_plain(op),
            }
        }
        submission.close
    }

    /// Queues a plain write, dropping an insert of a fresh key together
    /// with its remove.
    fn push_plain(&mut self, op: StoreOp) {
        match Fresh::of(&op) {
            Some((key, true)) => {
                self.fresh.insert(key, self.pending.len());
            }
            Some((key, false)) => {
                if let Some(at) = self.fresh.remove(&key) {
                    self.pending[at] = None;
                    self.elided += 1;
                    return;
                }
            }
            None => {}
        }
        self.pending.push(Some(op));
    }

    fn write_pending(&mut self, store: &dyn Store) {
        self.fresh.clear();
        let ops: Vec<KvOp> = self
            .pending
            .drain(..)
            .flatten()
            .map(|op| op.to_kv())
            .collect();
        if !ops.is_empty() {
            let result = guarded("write", || store.write(ops, WriteMode::Plain));
            self.record(result);
        }
    }

    fn record(&mut self, result: Result<(), StoreError>) {
        if let (Err(e), None) = (result, &self.error) {
            self.error = Some(e);
        }
    }

    /// Writes what is pending and flushes; the group is then empty again,
    /// its buffers kept for the next one (grown afresh per group, they were
    /// copied over and over as they doubled).
    fn finish(&mut self, store: &dyn Store) -> Result<(), StoreError> {
        let marks = self
            .marks
            .drain(..)
            .map(|(queue, seq)| Some(StoreOp::Delivered { queue, seq }));
        self.pending.extend(marks);
        self.write_pending(store);
        let flushed = guarded("flush", || store.flush());
        self.record(flushed);
        let mut syncs = std::mem::take(&mut self.syncs);
        for file in syncs.drain(..) {
            let synced = file.sync_data().map_err(StoreError::StreamSync);
            self.record(synced);
        }
        self.syncs = syncs;
        self.synced_files.clear();
        self.records_at.clear();
        for after in self.then.drain(..) {
            if self.error.is_some() {
                // Not synced: nothing new to record.
                continue;
            }
            if let Err(e) = after.kind.write(&after.file, after.record) {
                // The record stays at an earlier value: a lower bound, so
                // a later start checks less, never refuses wrongly.
                tracing::warn!(error = %e, what = after.kind.what, "cannot record what was synced");
            }
        }
        self.numbers = None;
        self.len = 0;
        self.elided = 0;
        match self.error.take() {
            Some(e) => Err(e),
            None => Ok(()),
        }
    }
}

impl Persistence {
    /// Starts the persister thread for `store`, after `recovered` told the
    /// ids in use.
    pub fn start(
        store: Arc<dyn Store>,
        recovered: &Recovered,
    ) -> Result<Arc<Persistence>, StoreError> {
        // Unbounded on purpose: submissions are bounded upstream (publishers
        // wait for confirms and are blocked by the memory alarm), and a
        // bounded inbox would block a queue's lock holder.
        let mailbox = Arc::new(Mailbox::default());
        let inbox = Arc::clone(&mailbox);
        let (durable_tx, durable) = watch::channel(Durable { flushed: 0 });
        let failed = Arc::new(Mutex::new(FailureLog::default()));
        let failed_log = Arc::clone(&failed);
        let (failures_tx, failures) = watch::channel(0);
        let figures = Arc::new(GroupFigures {
            batch_ops: Histogram::new(&BATCH_BOUNDS, 1.0),
            flush_seconds: Histogram::new(&FLUSH_BOUNDS, 1e9),
        });
        let recorded = Arc::clone(&figures);
        std::thread::Builder::new()
            .name("leveret-persister".into())
            .spawn(move || {
                persist(
                    store,
                    inbox,
                    Reports {
                        durable: durable_tx,
                        failed: failed_log,
                        failures: failures_tx,
                        figures: recorded,
                    },
                )
            })
            .map_err(StoreError::Persister)?;
        Ok(Arc::new(Persistence {
            mailbox,
            durable,
            failed,
            failures,
            next_message_id: AtomicU64::new(recovered.max_message_id() + 1),
            next_queue_id: AtomicU64::new(recovered.max_queue_id() + 1),
            start: recovered.starts + 1,
            figures,
            stream_root: std::sync::OnceLock::new(),
        }))
    }

    /// The group commits' batch sizes and write-and-flush times.
    pub fn figures(&self) -> PersisterFigures {
        PersisterFigures {
            batch_ops: self.figures.batch_ops.figures(),
            flush_seconds: self.figures.flush_seconds.figures(),
        }
    }

    /// The op recording this start; the broker writes it, flushed, before
    /// it serves, so [`Persistence::seq_floor`] is never used twice.
    pub fn start_record(&self) -> StoreOp {
        StoreOp::Starts { count: self.start }
    }

    /// Where durable queues' positions start in this run: above every
    /// position any earlier run handed out (messages recovered from disk
    /// keep theirs, which are lower), so a position names one message for
    /// the store's whole life, as a consumer that deduplicates by it
    /// (a shovel's downstream) needs.
    pub fn seq_floor(&self) -> u64 {
        self.start << START_SHIFT
    }

    /// Sets where streams keep their files and whether a damaged one is
    /// recovered (once; later calls are ignored).
    pub fn set_stream_root(&self, dir: std::path::PathBuf, recover: bool) {
        let _ = self.stream_root.set((dir, recover));
    }

    /// Where stream `id` keeps its segment files, if the store lives in a
    /// data directory.
    pub fn stream_dir(&self, id: u64) -> Option<std::path::PathBuf> {
        Some(self.stream_root.get()?.0.join(id.to_string()))
    }

    /// Whether a damaged stream is recovered at start (`--recover`)
    /// rather than refused.
    pub fn recover_streams(&self) -> bool {
        self.stream_root.get().is_some_and(|(_, recover)| *recover)
    }

    /// Queues ops for the next group; returns their submission number.
    pub fn submit(&self, ops: Vec<StoreOp>) -> u64 {
        self.send(ops, WriteMode::Plain, None, Vec::new(), None)
    }

    /// Asks the next group to sync `files` (written by their owner, a
    /// stream, before this call) with its flush; returns the submission
    /// number, durable once [`Persistence::durable`] reaches it.
    pub(crate) fn submit_sync(&self, files: Vec<Arc<std::fs::File>>, then: AfterSync) -> u64 {
        self.send(Vec::new(), WriteMode::Plain, None, files, Some(then))
    }

    /// Queues ops that must reach the disk all together or not at all (a
    /// transaction's commit).
    pub fn submit_atomic(&self, ops: Vec<StoreOp>) -> u64 {
        self.send(ops, WriteMode::Atomic, None, Vec::new(), None)
    }

    /// Writes and flushes everything submitted so far, then `last` (the
    /// clean-shutdown marker), then releases the store; later submissions
    /// are dropped. For shutdown. Whether `last` reached the disk.
    pub async fn close(&self, last: Vec<StoreOp>) -> bool {
        let (done, closed) = tokio::sync::oneshot::channel();
        let number = self.send(last, WriteMode::Plain, Some(done), Vec::new(), None);
        closed.await.is_ok() && self.succeeded(number)
    }

    /// Numbers and queues a submission, waking the persister if it sleeps.
    fn send(
        &self,
        ops: Vec<StoreOp>,
        mode: WriteMode,
        close: Option<tokio::sync::oneshot::Sender<()>>,
        syncs: Vec<Arc<std::fs::File>>,
        then: Option<AfterSync>,
    ) -> u64 {
        let mut inbox = self.mailbox.lock();
        inbox.numbered += 1;
        let number = inbox.numbered;
        if inbox.closed {
            // The persister has stopped: nothing will answer this one (a
            // close request's sender is dropped, so its waiter learns).
            return number;
        }
        inbox.waiting.push(Submission {
            number,
            ops,
            mode,
            close,
            syncs,
            then,
        });
        let wake = std::mem::take(&mut inbox.sleeping);
        drop(inbox);
        if wake {
            self.mailbox.arrived.notify_one();
        }
        number
    }

    /// Watches what is on disk.
    pub fn durable(&self) -> watch::Receiver<Durable> {
        self.durable.clone()
    }

    /// Counts failed groups: changes each time a write or flush fails.
    pub fn write_failures(&self) -> watch::Receiver<u64> {
        self.failures.clone()
    }

    /// Highest submission number the persister has attempted.
    pub fn flushed(&self) -> u64 {
        self.durable.borrow().flushed
    }

    /// Whether submission `number` (already attempted) reached the disk.
    pub fn succeeded(&self, number: u64) -> bool {
        let log = self.failed.lock().unwrap_or_else(|e| e.into_inner());
        !log.overlaps(number, number)
    }

    /// Whether everything in `written` is on disk: `None` while the
    /// persister has not yet attempted all of it, `Some(false)` if a group
    /// in its span failed or the persister stopped before attempting it
    /// (it never will). Nothing written is written.
    pub fn written(&self, written: Written) -> Option<bool> {
        if written.last == 0 {
            return Some(true);
        }
        if self.flushed() < written.last {
            // The sender is gone once the persister thread has ended.
            return self.durable.has_changed().is_err().then_some(false);
        }
        let log = self.failed.lock().unwrap_or_else(|e| e.into_inner());
        Some(!log.overlaps(written.first, written.last))
    }

    /// Waits until everything in `written` is on disk; false if a group in
    /// its span failed or the persister stopped first.
    pub async fn wait_written(&self, written: Written) -> bool {
        let mut durable = self.durable.clone();
        if durable
            .wait_for(|d| d.flushed >= written.last)
            .await
            .is_err()
        {
            return false;
        }
        self.written(written) == Some(true)
    }

    /// Waits until submission `number` is on disk; false if its batch failed.
    pub async fn wait(&self, number: u64) -> bool {
        let mut durable = self.durable.clone();
        if durable.wait_for(|d| d.flushed >= number).await.is_err() {
            return false;
        }
        self.succeeded(number)
    }

    /// Waits until everything submitted so far is on disk.
    pub async fn sync(&self) -> bool {
        let submitted = self.mailbox.lock().numbered;
        self.wait(submitted).await
    }

    /// A fresh message id.
    pub fn next_message_id(&self) -> u64 {
        self.next_message_id.fetch_add(1, Ordering::Relaxed)
    }

    /// A fresh queue id.
    pub fn next_queue_id(&self) -> u64 {
        self.next_queue_id.fetch_add(1, Ordering::Relaxed)
    }
}

impl Drop for Persistence {
    /// The persister writes what waits, then stops.
    fn drop(&mut self) {
        self.mailbox.lock().closed = true;
        self.mailbox.arrived.notify_one();
    }
}

/// Closes the inbox when the persister thread ends, however it ends:
/// what still waits is dropped, and so is whatever comes later.
struct Stopped<'a>(&'a Mailbox);

impl Drop for Stopped<'_> {
    fn drop(&mut self) {
        let mut inbox = self.0.lock();
        inbox.closed = true;
        inbox.waiting.clear();
    }
}

/// What the persister thread reports to [`Persistence`].
struct Reports {
    /// The highest attempted submission number.
    durable: watch::Sender<Durable>,
    /// Submission ranges whose group failed.
    failed: Arc<Mutex<FailureLog>>,
    /// How many groups failed.
    failures: watch::Sender<u64>,
    /// Each group's size and time.
    figures: Arc<GroupFigures>,
}

/// The persister thread: takes every submission already waiting into one
/// group (up to [`GROUP_OPS`] ops), writes and flushes it, then reports
/// the group's submissions done (and records them as failed if the store
/// refused them), until a close request or until the handle is gone.
///
/// After a failed group the store is reopened ([`Store::reopen`]) before
/// the next one: an engine that poisons itself on an I/O error (sled does,
/// on a full disk) would otherwise refuse every later write. The failed
/// group's submissions were reported failed, so whatever of them the
/// reopened store lacks was never promised.
fn persist(store: Arc<dyn Store>, mailbox: Arc<Mailbox>, reports: Reports) {
    let Reports {
        durable,
        failed,
        failures,
        figures,
    } = reports;
    let _stopped = Stopped(&mailbox);
    let mut must_reopen = false;
    let mut taken = Vec::new();
    let mut group = Group::default();
    while mailbox.take(&mut taken) {
        if must_reopen {
            match guarded("reopen", || store.reopen()) {
                Ok(()) => {
                    tracing::info!("storage reopened after a failure; writing again");
                    must_reopen = false;
                }
                Err(e) => group.record(Err(e)),
            }
        }
        let mut closing = None;
        for submission in taken.drain(..) {
            closing = group.add(&*store, submission);
            if closing.is_some() {
                break;
            }
        }
        let numbers = group.numbers;
        // Ops written: the submitted ones less the dropped pairs.
        let ops = group.len.saturating_sub(2 * group.elided);
        let started = std::time::Instant::now();
        let finished = group.finish(&*store);
        figures.batch_ops.observe(ops as f64);
        figures
            .flush_seconds
            .observe(started.elapsed().as_secs_f64());
        let Some((first, last)) = numbers else {
            continue;
        };
        if let Err(e) = finished {
            tracing::error!(error = %e, "persisting failed; affected publishes are nacked");
            must_reopen = true;
            failures.send_modify(|count| *count += 1);
            // Held only to push or search, never across an await.
            failed
                .lock()
                .unwrap_or_else(|e| e.into_inner())
                .record(first, last);
        }
        durable.send_replace(Durable { flushed: last });
        if let Some(done) = closing {
            // Releases the data directory (sled's lock) before answering,
            // so a new broker can open it at once.
            drop(store);
            let _ = done.send(());
            return;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::store::MemoryStore;

    #[tokio::test]
    async fn persister_numbers_submissions_and_reports_them_flushed() {
        let store: Arc<dyn Store> = Arc::new(MemoryStore::default());
        let persistence = Persistence::start(Arc::clone(&store), &Recovered::default()).unwrap();
        let mut last = 0;
        for i in 0..100 {
            last = persistence.submit(vec![StoreOp::DeleteMessage { id: i }]);
        }
        assert_eq!(last, 100);
        assert!(persistence.wait(last).await);
        assert_eq!(persistence.next_queue_id(), 1);
    }

    /// Once the persister has stopped, a submission is dropped and a second
    /// close answers at once (false) instead of waiting forever.
    #[tokio::test]
    async fn after_a_close_submissions_are_dropped_and_close_answers() {
        let store: Arc<dyn Store> = Arc::new(MemoryStore::default());
        let persistence = Persistence::start(store, &Recovered::default()).unwrap();
        assert!(persistence.close(Vec::new()).await);
        let late = persistence.submit(vec![StoreOp::DeleteMessage { id: 1 }]);
        assert!(!persistence.wait(late).await);
        assert!(!persistence.close(Vec::new()).await);
    }

    /// A store that refuses writes while `failing` is set.
    #[derive(Debug, Default)]
    struct Flaky {
        inner: MemoryStore,
        failing: std::sync::atomic::AtomicBool,
    }

    impl Store for Flaky {
        fn write(&self, ops: Vec<KvOp>, mode: WriteMode) -> Result<(), StoreError> {
            if self.failing.load(Ordering::SeqCst) {
                return Err(StoreError::Engine("simulated failure".into()));
            }
            self.inner.write(ops, mode)
        }
        fn flush(&self) -> Result<(), StoreError> {
            self.inner.flush()
        }
        fn scan(&self) -> Result<Vec<crate::store::KvPair>, StoreError> {
            self.inner.scan()
        }
    }

    /// A store that keeps every op written to it, in order.
    #[derive(Debug, Default)]
    struct Recording(Mutex<Vec<KvOp>>);

    impl Store for Recording {
        fn write(&self, ops: Vec<KvOp>, _mode: WriteMode) -> Result<(), StoreError> {
            self.0.lock().unwrap().extend(ops);
            Ok(())
        }
        fn flush(&self) -> Result<(), StoreError> {
            Ok(())
        }
        fn scan(&self) -> Result<Vec<crate::store::KvPair>, StoreError> {
            Ok(Vec::new())
        }
    }

    /// A group writes each file's newest after-sync record once its syncs
    /// and flush succeeded, and none when the group failed.
    #[test]
    fn after_sync_records_are_written_only_after_a_successful_group() {
        use crate::store::slots::{SlotFile, SlotRecord};
        const MARK: SlotFile = SlotFile {
            name: "mark",
            magic: b"LVTM",
            what: "test mark",
        };
        let dir = std::env::temp_dir().join(format!("leveret-after-sync-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir).unwrap();
        let first = SlotRecord {
            sequence: 1,
            words: [0, 0],
        };
        let file = Arc::new(MARK.open(&dir, first).unwrap());
        let submission = |number, sequence| Submission {
            number,
            ops: Vec::new(),
            mode: WriteMode::Plain,
            close: None,
            syncs: vec![Arc::clone(&file)],
            then: Some(AfterSync {
                file: Arc::clone(&file),
                kind: MARK,
                record: SlotRecord {
                    sequence,
                    words: [sequence, 0],
                },
            }),
        };
        let store = Flaky::default();
        let mut group = Group::default();
        group.add(&store, submission(1, 5));
        group.add(&store, submission(2, 3));
        group.finish(&store).unwrap();
        assert_eq!(
            MARK.read(&dir).unwrap().unwrap().sequence,
            5,
            "the newest of the group"
        );
        store.failing.store(true, Ordering::SeqCst);
        group.add(
            &store,
            Submission {
                ops: vec![StoreOp::DeleteMessage { id: 1 }],
                ..submission(3, 9)
            },
        );
        assert!(group.finish(&store).is_err());
        assert_eq!(
            MARK.read(&dir).unwrap().unwrap().sequence,
            5,
            "a failed group records nothing"
        );
        std::fs::remove_dir_all(&dir).unwrap();
    }

    /// Submissions from several threads at once are numbered without a
    /// gap or a repeat, and waiting for the last covers every one.
    #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
    async fn submissions_from_many_threads_are_numbered_in_one_run() {
        let recording = Arc::new(Recording::default());
        let store: Arc<dyn Store> = Arc::clone(&recording) as Arc<dyn Store>;
        let persistence = Persistence::start(store, &Recovered::default()).unwrap();
        let submitters: Vec<_> = (0..4u64)
            .map(|thread| {
                let persistence = Arc::clone(&persistence);
                std::thread::spawn(move || {
                    (0..500u64)
                        .map(|i| {
                            let id = thread * 1000 + i;
                            persistence.submit(vec![StoreOp::DeleteMessage { id }])
                        })
                        .collect::<Vec<u64>>()
                })
            })
            .collect();
        let mut numbers: Vec<u64> = submitters
            .into_iter()
            .flat_map(|thread| thread.join().unwrap())
            .collect();
        numbers.sort_unstable();
        assert_eq!(numbers, (1..=2000).collect::<Vec<u64>>());
        assert!(persistence.wait(2000).await);
        assert_eq!(recording.0.lock().unwrap().len(), 2000);
    }

    /// A message enqueued and acknowledged within one group is never
    /// written; an exchange declared and deleted in one group is (its
    /// delete must remove an older stored definition); an insert already
    /// written before an atomic batch is removed normally.
    #[test]
    fn an_insert_removed_in_its_own_group_is_not_written() {
        use crate::store::{EntryBody, ExchangeRecord, MessageRecord};
        use leveret_protocol::{FieldTable, ShortStr};
        let store = Recording::default();
        let record = MessageRecord {
            exchange: ShortStr::from_static(""),
            routing_key: ShortStr::from_static("q"),
            properties: bytes::Bytes::new(),
            body: bytes::Bytes::from_static(b"m"),
        };
        let plain = |number, ops| Submission {
            number,
            ops,
            mode: WriteMode::Plain,
            close: None,
            syncs: Vec::new(),
            then: None,
        };
        let exchange = ExchangeRecord {
            vhost: ShortStr::from_static("/"),
            name: ShortStr::from_static("x"),
            kind: ShortStr::from_static("direct"),
            auto_delete: false,
            internal: false,
            arguments: FieldTable::new(),
        };
        let mut group = Group::default();
        group.add(
            &store,
            plain(
                1,
                vec![
                    StoreOp::Enqueue {
                        queue: 1,
                        seq: 7,
                        body: EntryBody::Inline(record.clone()),
                    },
                    StoreOp::Enqueue {
                        queue: 1,
                        seq: 8,
                        body: EntryBody::Inline(record.clone()),
                    },
                    StoreOp::PutExchange(exchange.clone()),
                ],
            ),
        );
        group.add(
            &store,
            plain(
                2,
                vec![
                    StoreOp::Dequeue { queue: 1, seq: 7 },
                    StoreOp::DeleteExchange {
                        vhost: exchange.vhost.clone(),
                        name: exchange.name.clone(),
                    },
                ],
            ),
        );
        group.add(
            &store,
            Submission {
                number: 3,
                ops: vec![StoreOp::PutMessage {
                    id: 5,
                    record: record.clone(),
                }],
                mode: WriteMode::Atomic,
                close: None,
                syncs: Vec::new(),
                then: None,
            },
        );
        group.add(
            &store,
            plain(4, vec![StoreOp::Dequeue { queue: 1, seq: 8 }]),
        );
        assert_eq!(group.elided, 1);
        group.finish(&store).unwrap();
        let written = store.0.lock().unwrap();
        let index = |seq: u64| StoreOp::Dequeue { queue: 1, seq }.to_kv().0;
        assert!(
            !written.iter().any(|(key, _)| *key == index(7)),
            "seq 7 was inserted and removed in one group: never written"
        );
        let eight: Vec<_> = written.iter().filter(|(key, _)| *key == index(8)).collect();
        assert_eq!(
            eight.len(),
            2,
            "written before the atomic batch, then removed"
        );
        assert!(eight[1].1.is_none());
        let exchange_key = StoreOp::PutExchange(exchange).to_kv().0;
        assert_eq!(
            written
                .iter()
                .filter(|(key, _)| *key == exchange_key)
                .count(),
            2,
            "a definition's delete is always written"
        );
        drop(written);
        // Finished, the group is empty again: a remove in the next group
        // is written, never matched with this group's inserts.
        assert_eq!((group.numbers, group.len, group.elided), (None, 0, 0));
        group.add(
            &store,
            plain(5, vec![StoreOp::Dequeue { queue: 1, seq: 7 }]),
        );
        assert_eq!(group.elided, 0);
        group.finish(&store).unwrap();
        let written = store.0.lock().unwrap();
        assert_eq!(written.last(), Some(&(index(7), None)));
    }

    /// A failed range evicted from the history still reads as failed: a
    /// span that reaches below the highest evicted submission is never
    /// reported written.
    #[test]
    fn an_evicted_failure_is_never_read_as_written() {
        let mut log = FailureLog::default();
        log.record(10, 12);
        for n in 0..FAILED_HISTORY as u64 {
            let from = 100 + 2 * n;
            log.record(from, from);
        }
        assert_eq!(log.ranges.len(), FAILED_HISTORY);
        assert!(log.overlaps(11, 11), "the evicted range still failed");
        assert!(log.overlaps(5, 50), "a span over the evicted range failed");
        assert!(log.overlaps(102, 102), "a remembered range failed");
        assert!(!log.overlaps(101, 101), "a good one between failures");
        assert!(!log.overlaps(100_000, 100_001), "a good one after them");
    }

    /// Once the persister has stopped, what it never attempted is not
    /// written (`Some(false)`, so a confirm becomes a nack), never
    /// pending forever.
    #[tokio::test]
    async fn what_a_stopped_persister_never_attempted_is_not_written() {
        let store: Arc<dyn Store> = Arc::new(MemoryStore::default());
        let persistence = Persistence::start(store, &Recovered::default()).unwrap();
        let mut before = Written::default();
        before.add(persistence.submit(vec![StoreOp::DeleteMessage { id: 1 }]));
        assert!(persistence.wait_written(before).await);
        assert!(persistence.close(Vec::new()).await);
        let mut after = Written::default();
        after.add(persistence.submit(vec![StoreOp::DeleteMessage { id: 2 }]));
        assert_eq!(persistence.written(before), Some(true));
        let stopped = tokio::time::timeout(std::time::Duration::from_secs(30), async {
            loop {
                match persistence.written(after) {
                    Some(written) => return written,
                    None => tokio::task::yield_now().await,
                }
            }
        });
        assert_eq!(stopped.await, Ok(false));
        assert!(!persistence.wait_written(after).await);
    }

    #[tokio::test]
    async fn a_failed_group_fails_exactly_its_submissions() {
        let flaky = Arc::new(Flaky::default());
        let store: Arc<dyn Store> = Arc::clone(&flaky) as Arc<dyn Store>;
        let persistence = Persistence::start(store, &Recovered::default()).unwrap();
        let good = persistence.submit(vec![StoreOp::DeleteMessage { id: 1 }]);
        assert!(persistence.wait(good).await);
        flaky.failing.store(true, Ordering::SeqCst);
        let bad = persistence.submit(vec![StoreOp::DeleteMessage { id: 2 }]);
        assert!(!persistence.wait(bad).await);
        flaky.failing.store(false, Ordering::SeqCst);
        let after = persistence.submit(vec![StoreOp::DeleteMessage { id: 3 }]);
        assert!(persistence.wait(after).await);
        assert!(persistence.succeeded(good));
    }

    /// A span of submissions is written only if every group it spans
    /// succeeded: a publish whose shared record went out in a group that
    /// failed is not written, however well its later index entries fared.
    #[tokio::test]
    async fn a_written_span_fails_when_any_group_in_it_failed() {
        let flaky = Arc::new(Flaky::default());
        let store: Arc<dyn Store> = Arc::clone(&flaky) as Arc<dyn Store>;
        let persistence = Persistence::start(store, &Recovered::default()).unwrap();
        let mut nothing = Written::default();
        nothing.add(0);
        assert_eq!(persistence.written(nothing), Some(true));
        assert!(persistence.wait_written(nothing).await);
        let mut good = Written::default();
        good.add(persistence.submit(vec![StoreOp::DeleteMessage { id: 1 }]));
        good.add(persistence.submit(vec![StoreOp::DeleteMessage { id: 2 }]));
        assert!(persistence.wait_written(good).await);
        flaky.failing.store(true, Ordering::SeqCst);
        let record = persistence.submit(vec![StoreOp::DeleteMessage { id: 3 }]);
        assert!(!persistence.wait(record).await);
        flaky.failing.store(false, Ordering::SeqCst);
        let entry = persistence.submit(vec![StoreOp::DeleteMessage { id: 4 }]);
        assert!(persistence.wait(entry).await);
        let mut spanning = Written::default();
        spanning.add(entry);
        spanning.add(record);
        assert_eq!(spanning.last(), entry);
        assert_eq!(persistence.written(spanning), Some(false));
        assert!(!persistence.wait_written(spanning).await);
        let mut later = Written::default();
        later.add(entry);
        assert_eq!(persistence.written(later), Some(true));
        let mut ahead = Written::default();
        ahead.add(entry + 1_000);
        assert_eq!(persistence.written(ahead), None, "not attempted yet");
    }

    /// A store whose writes panic while `panicking` is set.
    #[derive(Debug, Default)]
    struct Panicky {
        inner: MemoryStore,
        panicking: std::sync::atomic::AtomicBool,
    }

    impl Store for Panicky {
        fn write(&self, ops: Vec<KvOp>, mode: WriteMode) -> Result<(), StoreError> {
            assert!(
                !self.panicking.load(Ordering::SeqCst),
                "tried to serialize Uninitialized (simulated)"
            );
            self.inner.write(ops, mode)
        }
        fn flush(&self) -> Result<(), StoreError> {
            self.inner.flush()
        }
        fn scan(&self) -> Result<Vec<crate::store::KvPair>, StoreError> {
            self.inner.scan()
        }
    }

    /// A panic inside the storage engine fails its group like an error
    /// does; the persister thread lives on and later groups succeed.
    #[tokio::test]
    async fn a_panic_in_the_store_fails_its_group_and_the_persister_goes_on() {
        let panicky = Arc::new(Panicky::default());
        let store: Arc<dyn Store> = Arc::clone(&panicky) as Arc<dyn Store>;
        let persistence = Persistence::start(store, &Recovered::default()).unwrap();
        panicky.panicking.store(true, Ordering::SeqCst);
        let bad = persistence.submit_atomic(vec![StoreOp::DeleteMessage { id: 1 }]);
        assert!(!persistence.wait(bad).await);
        let bad = persistence.submit(vec![StoreOp::DeleteMessage { id: 2 }]);
        assert!(!persistence.wait(bad).await);
        panicky.panicking.store(false, Ordering::SeqCst);
        let after = persistence.submit(vec![StoreOp::DeleteMessage { id: 3 }]);
        assert!(persistence.wait(after).await, "the persister survived");
    }

    #[test]
    fn guarded_turns_a_panic_into_an_error_naming_the_call() {
        let err = guarded::<()>("flush", || panic!("boom {}", 7)).unwrap_err();
        assert!(
            matches!(&err, StoreError::Panicked { what: "flush", message } if message == "boom 7"),
            "{err}"
        );
        assert!(guarded("scan", || Ok(5)).is_ok_and(|v| v == 5));
    }
}
