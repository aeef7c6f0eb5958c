//! The hashing pool: where slow password checks (argon2id: tens of
//! milliseconds and ~19 MiB each) run, as bounded work that a flood of
//! logins cannot grow.
//!
//! - [`HASH_THREADS`] threads of the pool's own (not tokio's blocking
//!   pool, which grows to 512 threads), started at the first check and
//!   ended when the pool is dropped: at most that many checks run at once,
//!   and a thread is busy exactly as long as its check runs. A caller that
//!   goes away does not end a running check, and does not free its thread
//!   either: nothing can start beside it.
//! - Checks wait in one queue per key (the broker uses the source address
//!   and the user name), and the threads take the keys in turn
//!   (round-robin), so a flood from one source for one user delays
//!   another key's check by at most one round, whatever its size.
//! - A waiting check whose caller went away (its connection closed) is
//!   dropped before it starts.
//! - At most [`QUEUE_CAPACITY`] checks wait. When full, checks whose
//!   caller went away are dropped first; then the newest check of the
//!   longest queue makes room for a check of a shorter one, so a flood
//!   cannot keep another key out; otherwise the new check is refused.
//!   A refused check fails, as a wrong password would.
//!
//! - A thread keeps the check's memory ([`HashMemory`]) while checks keep
//!   coming, and gives it back when none waits.
//!
//! Uses `password`'s [`HashMemory`], nothing else of the broker: a check
//! is any closure returning whether it passed.

use crate::access::password::HashMemory;
use std::collections::VecDeque;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::{Arc, Condvar, Mutex, MutexGuard};
use tokio::sync::oneshot;

/// Threads hashing at once, broker-wide.
pub const HASH_THREADS: usize = 2;
/// Checks that may wait for a thread, all keys together.
pub const QUEUE_CAPACITY: usize = 1024;
/// The name of the pool's threads (as `/proc/*/task/*/comm` shows them).
pub const THREAD_NAME: &str = "leveret-hash";

/// A check for the pool: true if the password passed.
type Check = Box<dyn FnOnce(&mut HashMemory) -> bool + Send>;

struct Job {
    check: Check,
    reply: oneshot::Sender<bool>,
}

impl Job {
    fn abandoned(&self) -> bool {
        self.reply.is_closed()
    }
}

/// Why the pool did not take a check.
#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error)]
pub enum Refused {
    /// [`QUEUE_CAPACITY`] checks were waiting, none of a longer queue.
    #[error("{QUEUE_CAPACITY} password checks are waiting already")]
    Full,
    /// The pool's threads could not be started, or it is shutting down.
    #[error("the password hashing threads are not running")]
    Stopped,
}

/// What the pool has done, for tests and metrics.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct HashPoolStats {
    /// Threads started (at most [`HASH_THREADS`]).
    pub threads: usize,
    /// Checks running now.
    pub running: usize,
    /// The most checks that ever ran at once.
    pub peak_running: usize,
    /// Checks queued now (those whose caller has gone are counted until
    /// a thread reaches them, or room is needed).
    pub waiting: usize,
    /// Checks that ran to the end.
    pub finished: usize,
    /// Waiting checks dropped because their caller had gone.
    pub abandoned: usize,
    /// Checks refused or pushed out for room.
    pub refused: usize,
}

#[derive(Default)]
struct State {
    /// One queue per key with checks waiting, in the order the threads
    /// serve them; a key is at the back again after each check taken.
    queues: VecDeque<(String, VecDeque<Job>)>,
    stats: HashPoolStats,
    closed: bool,
}

impl State {
    /// The next check to run, round-robin over keys; abandoned ones are
    /// dropped on the way.
    fn next_job(&mut self) -> Option<Job> {
        while let Some((key, mut queue)) = self.queues.pop_front() {
            let job = queue.pop_front();
            if !queue.is_empty() {
                self.queues.push_back((key, queue));
            }
            let Some(job) = job else { continue };
            self.stats.waiting -= 1;
            if job.abandoned() {
                self.stats.abandoned += 1;
                continue;
            }
            return Some(job);
        }
        None
    }

    /// Drops every waiting check whose caller has gone.
    fn drop_abandoned(&mut self) {
        let mut dropped = 0;
        for (_, queue) in &mut self.queues {
            let before = queue.len();
            queue.retain(|job| !job.abandoned());
            dropped += before - queue.len();
        }
        self.queues.retain(|(_, queue)| !queue.is_empty());
        self.stats.waiting -= dropped;
        self.stats.abandoned += dropped;
    }

    /// Makes room for one more check of `key`, if the rules allow.
    fn make_room(&mut self, key: &str) -> Result<(), Refused> {
        if self.stats.waiting < QUEUE_CAPACITY {
            return Ok(());
        }
        self.drop_abandoned();
        if self.stats.waiting < QUEUE_CAPACITY {
            return Ok(());
        }
        let own = self
            .queues
            .iter()
            .find(|(k, _)| k == key)
            .map_or(0, |(_, queue)| queue.len());
        let longest = self
            .queues
            .iter_mut()
            .max_by_key(|(_, queue)| queue.len())
            .filter(|(_, queue)| queue.len() > own + 1);
        let Some((_, queue)) = longest else {
            self.stats.refused += 1;
            return Err(Refused::Full);
        };
        // Dropping its reply tells that caller it was refused.
        queue.pop_back();
        self.stats.waiting -= 1;
        self.stats.refused += 1;
        Ok(())
    }
}

struct Shared {
    state: Mutex<State>,
    work: Condvar,
    /// Threads that have not ended yet (they outlive the pool by the
    /// check they are running, if any).
    alive: AtomicUsize,
}

impl Shared {
    fn lock(&self) -> MutexGuard<'_, State> {
        self.state.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// A pool thread: runs checks until the pool is dropped.
    fn serve(&self) {
        let mut memory = HashMemory::default();
        loop {
            let job = {
                let mut state = self.lock();
                loop {
                    if state.closed {
                        return;
                    }
                    if let Some(job) = state.next_job() {
                        state.stats.running += 1;
                        state.stats.peak_running =
                            state.stats.peak_running.max(state.stats.running);
                        break job;
                    }
                    memory.release();
                    state = self.work.wait(state).unwrap_or_else(|e| e.into_inner());
                }
            };
            // A check that panics fails, and its thread lives on.
            let check = std::panic::AssertUnwindSafe(|| (job.check)(&mut memory));
            let passed = std::panic::catch_unwind(check).unwrap_or(false);
            {
                let mut state = self.lock();
                state.stats.running -= 1;
                state.stats.finished += 1;
            }
            let _ = job.reply.send(passed);
        }
    }
}

/// The pool. Dropping it ends its threads once their current checks end;
/// checks still waiting then fail.
pub struct HashPool {
    shared: Arc<Shared>,
}

impl std::fmt::Debug for HashPool {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_tuple("HashPool").field(&self.stats()).finish()
    }
}

impl Default for HashPool {
    fn default() -> Self {
        HashPool {
            shared: Arc::new(Shared {
                state: Mutex::new(State::default()),
                work: Condvar::new(),
                alive: AtomicUsize::new(0),
            }),
        }
    }
}

impl HashPool {
    /// Queues `check` under `key`; the receiver gets its result, or is
    /// closed if the check was dropped for room or the pool stopped.
    /// Dropping the receiver before the check starts withdraws it.
    pub fn submit(
        &self,
        key: &str,
        check: impl FnOnce(&mut HashMemory) -> bool + Send + 'static,
    ) -> Result<oneshot::Receiver<bool>, Refused> {
        let (reply, answer) = oneshot::channel();
        let job = Job {
            check: Box::new(check),
            reply,
        };
        let mut state = self.shared.lock();
        if state.closed {
            return Err(Refused::Stopped);
        }
        state.make_room(key)?;
        match state.queues.iter_mut().find(|(k, _)| k == key) {
            Some((_, queue)) => queue.push_back(job),
            None => state
                .queues
                .push_back((key.to_owned(), VecDeque::from([job]))),
        }
        state.stats.waiting += 1;
        if state.stats.threads < HASH_THREADS {
            self.start_thread(&mut state)?;
        }
        drop(state);
        self.shared.work.notify_one();
        Ok(answer)
    }

    /// Starts one more thread (called with the state locked, so the count
    /// and the threads agree).
    fn start_thread(&self, state: &mut State) -> Result<(), Refused> {
        let shared = Arc::clone(&self.shared);
        shared.alive.fetch_add(1, Ordering::SeqCst);
        let started = std::thread::Builder::new()
            .name(THREAD_NAME.to_owned())
            .spawn(move || {
                shared.serve();
                shared.alive.fetch_sub(1, Ordering::SeqCst);
            });
        match started {
            Ok(_) => {
                state.stats.threads += 1;
                Ok(())
            }
            Err(e) => {
                self.shared.alive.fetch_sub(1, Ordering::SeqCst);
                tracing::error!(error = %e, "cannot start a password hashing thread");
                if state.stats.threads > 0 {
                    return Ok(());
                }
                // No thread to run what waits: fail it all now.
                state.queues.clear();
                state.stats.waiting = 0;
                Err(Refused::Stopped)
            }
        }
    }

    /// What the pool has done so far.
    pub fn stats(&self) -> HashPoolStats {
        self.shared.lock().stats
    }
}

impl Drop for HashPool {
    fn drop(&mut self) {
        let mut state = self.shared.lock();
        state.closed = true;
        state.stats.waiting = 0;
        state.queues.clear();
        drop(state);
        self.shared.work.notify_all();
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::sync::mpsc;
    use std::time::Duration;

    const HANG: Duration = Duration::from_secs(20);

    /// A check that records its name when it runs and, if `gate` is
    /// given, waits for a word on it first.
    fn check(
        name: &'static str,
        ran: &mpsc::Sender<&'static str>,
        gate: Option<mpsc::Receiver<()>>,
    ) -> impl FnOnce(&mut HashMemory) -> bool + Send + 'static {
        let ran = ran.clone();
        move |_memory| {
            ran.send(name).unwrap();
            if let Some(gate) = gate {
                gate.recv_timeout(HANG).expect("released");
            }
            true
        }
    }

    /// Fills every thread with a check that holds it until released.
    fn occupy(pool: &HashPool) -> Vec<mpsc::Sender<()>> {
        let (started_tx, started) = mpsc::channel();
        let mut gates = Vec::new();
        let mut answers = Vec::new();
        for _ in 0..HASH_THREADS {
            let (open, gate) = mpsc::channel();
            gates.push(open);
            let check = check("occupier", &started_tx, Some(gate));
            answers.push(pool.submit("occupier", check).unwrap());
        }
        for _ in 0..HASH_THREADS {
            started.recv_timeout(HANG).expect("every thread busy");
        }
        // Not awaited: dropping an answer once its check runs withdraws
        // nothing.
        drop(answers);
        gates
    }

    fn release(gates: Vec<mpsc::Sender<()>>) {
        for gate in gates {
            gate.send(()).unwrap();
        }
    }

    async fn answer(rx: oneshot::Receiver<bool>) -> Option<bool> {
        tokio::time::timeout(HANG, rx)
            .await
            .expect("answered in time")
            .ok()
    }

    #[tokio::test]
    async fn keys_are_served_in_turn_however_long_one_queue_is() {
        let pool = HashPool::default();
        let (ran_tx, ran) = mpsc::channel();
        let gates = occupy(&pool);
        let mut answers = Vec::new();
        for _ in 0..50 {
            answers.push(pool.submit("flood", check("flood", &ran_tx, None)).unwrap());
        }
        answers.push(pool.submit("legit", check("legit", &ran_tx, None)).unwrap());
        assert_eq!(pool.stats().waiting, 51);
        release(gates);
        for rx in answers {
            assert_eq!(answer(rx).await, Some(true));
        }
        let order: Vec<_> = ran.try_iter().collect();
        let legit = order.iter().position(|n| *n == "legit").unwrap();
        // The flood's first check, then the legitimate one (each thread
        // takes the next key in turn; two threads may record them in
        // either order).
        assert!(legit <= 1, "served at {legit}: {order:?}");
        // The occupiers' answers are not awaited: on a loaded machine one
        // thread may serve every waiting check before the other has
        // finished its occupier, so wait for that one to be counted.
        let deadline = std::time::Instant::now() + HANG;
        while pool.stats().finished < 51 + HASH_THREADS && std::time::Instant::now() < deadline {
            std::thread::sleep(Duration::from_millis(1));
        }
        let stats = pool.stats();
        assert_eq!(stats.finished, 51 + HASH_THREADS);
        assert_eq!(stats.peak_running, HASH_THREADS);
        assert_eq!(stats.threads, HASH_THREADS);
        assert_eq!((stats.running, stats.waiting), (0, 0));
    }

    #[tokio::test]
    async fn a_check_whose_caller_went_away_never_starts() {
        let pool = HashPool::default();
        let (ran_tx, ran) = mpsc::channel();
        let gates = occupy(&pool);
        let gone = pool.submit("k", check("gone", &ran_tx, None)).unwrap();
        let kept = pool.submit("k", check("kept", &ran_tx, None)).unwrap();
        drop(gone);
        release(gates);
        assert_eq!(answer(kept).await, Some(true));
        let order: Vec<_> = ran.try_iter().collect();
        assert_eq!(order, ["kept"]);
        assert_eq!(pool.stats().abandoned, 1);
    }

    #[tokio::test]
    async fn a_full_queue_refuses_the_flood_and_makes_room_for_others() {
        let pool = HashPool::default();
        let (ran_tx, _ran) = mpsc::channel();
        let gates = occupy(&pool);
        let mut flood = Vec::new();
        for _ in 0..QUEUE_CAPACITY {
            flood.push(pool.submit("flood", check("flood", &ran_tx, None)).unwrap());
        }
        // The flood's own next check is refused…
        assert_eq!(
            pool.submit("flood", check("flood", &ran_tx, None)).err(),
            Some(Refused::Full)
        );
        // …another key's is taken, pushing out the flood's newest.
        let legit = pool.submit("legit", check("legit", &ran_tx, None)).unwrap();
        let stats = pool.stats();
        assert_eq!((stats.waiting, stats.refused), (QUEUE_CAPACITY, 2));
        // An abandoned check makes room before anything is refused.
        drop(flood.remove(0));
        let again = pool.submit("flood", check("flood", &ran_tx, None)).unwrap();
        release(gates);
        assert_eq!(answer(legit).await, Some(true));
        assert_eq!(answer(again).await, Some(true));
        let pushed_out = flood.pop().unwrap();
        assert_eq!(answer(pushed_out).await, None, "pushed out: closed");
        for rx in flood {
            assert_eq!(answer(rx).await, Some(true));
        }
        let stats = pool.stats();
        assert_eq!(stats.peak_running, HASH_THREADS);
        assert_eq!(stats.abandoned, 1);
    }

    #[test]
    fn dropping_the_pool_ends_its_threads_after_their_checks() {
        let pool = HashPool::default();
        let (ran_tx, _ran) = mpsc::channel();
        let gates = occupy(&pool);
        let waiting = pool.submit("k", check("never", &ran_tx, None)).unwrap();
        let shared = Arc::clone(&pool.shared);
        drop(pool);
        assert_eq!(shared.alive.load(Ordering::SeqCst), HASH_THREADS);
        release(gates);
        let deadline = std::time::Instant::now() + HANG;
        while shared.alive.load(Ordering::SeqCst) > 0 {
            assert!(std::time::Instant::now() < deadline, "threads ended");
            std::thread::sleep(Duration::from_millis(5));
        }
        assert!(waiting.blocking_recv().is_err(), "waiting checks fail");
    }
}
