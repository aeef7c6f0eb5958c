//! The persister: one thread that takes submissions of [`StoreOp`]s from
//! every connection, writes them in groups (plain writes in order, a
//! transaction's commit as one atomic batch, delivery marks merged to one
//! write per queue) and flushes once per group; and [`Persistence`], the
//! broker's handle on it, which numbers submissions and reports how far
//! the disk has got, so a confirm or a commit-ok waits for exactly the
//! flush that covers it.

use super::{KvOp, Recovered, Store, StoreError, StoreOp};
use std::collections::VecDeque;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use tokio::sync::{mpsc, watch};

/// The most ops one group commit writes before its flush (more wait for
/// the next group), so one flush stays short.
const GROUP_OPS: usize = 50_000;

/// A request to the persister: ops to write, all or nothing if `atomic`;
/// or, with `close`, the last request: flush, release the store, answer.
struct Submission {
    ops: Vec<StoreOp>,
    atomic: bool,
    close: Option<tokio::sync::oneshot::Sender<()>>,
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

/// The most recent failed batches remembered, as submission ranges. A
/// waiting publish checks its number against them within moments of the
/// failure, so a short history is enough.
const FAILED_HISTORY: usize = 4096;

/// The broker's handle on durable storage: submit ops, learn when they are
/// on disk. Submissions are numbered; [`Persistence::durable`] reports the
/// highest number flushed.
#[derive(Debug)]
pub struct Persistence {
    submit: mpsc::UnboundedSender<Submission>,
    submitted: AtomicU64,
    durable: watch::Receiver<Durable>,
    failed: Arc<Mutex<VecDeque<(u64, u64)>>>,
    next_message_id: AtomicU64,
    next_queue_id: AtomicU64,
}

/// One group commit being assembled by the persister: plain writes in
/// order, atomic submissions applied as batches in their place, delivery
/// marks merged to one write per queue, then one flush.
#[derive(Default)]
struct Group {
    pending: Vec<KvOp>,
    marks: Vec<(u64, u64)>,
    submissions: u64,
    len: usize,
    error: Option<StoreError>,
}

impl Group {
    /// Adds a submission; returns its close request, if it is one.
    fn add(
        &mut self,
        store: &dyn Store,
        submission: Submission,
    ) -> Option<tokio::sync::oneshot::Sender<()>> {
        self.submissions += 1;
        self.len += submission.ops.len();
        if submission.atomic {
            self.write_pending(store);
            let ops = submission.ops.iter().map(StoreOp::to_kv).collect();
            let result = store.write(ops, true);
            self.record(result);
            return submission.close;
        }
        for op in &submission.ops {
            match op {
                StoreOp::Delivered { queue, seq } => {
                    match self.marks.iter_mut().find(|(q, _)| q == queue) {
                        Some((_, mark)) => *mark = (*mark).max(*seq),
                        None => self.marks.push((*queue, *seq)),
                    }
                }
                op => self.pending.push(op.to_kv()),
            }
        }
        submission.close
    }

    fn write_pending(&mut self, store: &dyn Store) {
        if !self.pending.is_empty() {
            let ops = std::mem::take(&mut self.pending);
            let result = store.write(ops, false);
            self.record(result);
        }
    }

    fn record(&mut self, result: Result<(), StoreError>) {
        if let (Err(e), None) = (result, &self.error) {
            self.error = Some(e);
        }
    }

    fn finish(mut self, store: &dyn Store) -> Result<(), StoreError> {
        let marks = std::mem::take(&mut self.marks);
        self.pending.extend(
            marks
                .into_iter()
                .map(|(queue, seq)| StoreOp::Delivered { queue, seq }.to_kv()),
        );
        self.write_pending(store);
        let flushed = store.flush();
        self.record(flushed);
        match self.error {
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
        // bounded channel here would block a queue's lock holder.
        let (submit, inbox) = mpsc::unbounded_channel::<Submission>();
        let (durable_tx, durable) = watch::channel(Durable { flushed: 0 });
        let failed = Arc::new(Mutex::new(VecDeque::new()));
        let failed_log = Arc::clone(&failed);
        std::thread::Builder::new()
            .name("leveret-persister".into())
            .spawn(move || persist(store, inbox, durable_tx, failed_log))
            .map_err(StoreError::Persister)?;
        Ok(Arc::new(Persistence {
            submit,
            submitted: AtomicU64::new(0),
            durable,
            failed,
            next_message_id: AtomicU64::new(recovered.max_message_id() + 1),
            next_queue_id: AtomicU64::new(recovered.max_queue_id() + 1),
        }))
    }

    /// Queues ops for the next group; returns their submission number.
    pub fn submit(&self, ops: Vec<StoreOp>) -> u64 {
        self.send(Submission {
            ops,
            atomic: false,
            close: None,
        })
    }

    /// Queues ops that must reach the disk all together or not at all (a
    /// transaction's commit).
    pub fn submit_atomic(&self, ops: Vec<StoreOp>) -> u64 {
        self.send(Submission {
            ops,
            atomic: true,
            close: None,
        })
    }

    /// Writes and flushes everything submitted so far, then releases the
    /// store; later submissions are dropped. For shutdown.
    pub async fn close(&self) {
        let (done, closed) = tokio::sync::oneshot::channel();
        self.send(Submission {
            ops: Vec::new(),
            atomic: false,
            close: Some(done),
        });
        let _ = closed.await;
    }

    fn send(&self, submission: Submission) -> u64 {
        let number = self.submitted.fetch_add(1, Ordering::AcqRel) + 1;
        // The persister thread lives as long as the process; a send error
        // only happens at exit.
        let _ = self.submit.send(submission);
        number
    }

    /// Watches what is on disk.
    pub fn durable(&self) -> watch::Receiver<Durable> {
        self.durable.clone()
    }

    /// Highest submission number the persister has attempted.
    pub fn flushed(&self) -> u64 {
        self.durable.borrow().flushed
    }

    /// Whether submission `number` (already attempted) reached the disk.
    pub fn succeeded(&self, number: u64) -> bool {
        let log = self.failed.lock().unwrap_or_else(|e| e.into_inner());
        !log.iter().any(|&(from, to)| (from..=to).contains(&number))
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
        self.wait(self.submitted.load(Ordering::Acquire)).await
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

/// The persister thread: takes every submission already waiting into one
/// group (up to [`GROUP_OPS`] ops), writes and flushes it, then reports
/// the group's submissions done (and records them as failed if the store
/// refused them), until a close request or until every handle is gone.
fn persist(
    store: Arc<dyn Store>,
    mut inbox: mpsc::UnboundedReceiver<Submission>,
    durable: watch::Sender<Durable>,
    failed: Arc<Mutex<VecDeque<(u64, u64)>>>,
) {
    let mut flushed = 0u64;
    while let Some(first) = inbox.blocking_recv() {
        let mut group = Group::default();
        let mut closing = group.add(&*store, first);
        while closing.is_none() && group.len < GROUP_OPS {
            match inbox.try_recv() {
                Ok(next) => closing = group.add(&*store, next),
                Err(_) => break,
            }
        }
        let first_number = flushed + 1;
        flushed += group.submissions;
        if let Err(e) = group.finish(&*store) {
            tracing::error!(error = %e, "persisting failed; affected publishes are nacked");
            // Held only to push or search, never across an await.
            let mut log = failed.lock().unwrap_or_else(|e| e.into_inner());
            if log.len() == FAILED_HISTORY {
                log.pop_front();
            }
            log.push_back((first_number, flushed));
        }
        durable.send_replace(Durable { flushed });
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
}
