//! The publish side of the in-process fast path: an in-process
//! connection's loop, which its task runs, may also be run by the client's
//! own thread for a publish ([`DirectLoop`]), so that the message is
//! routed, queued and (with inline deliveries) handed to its consumer on
//! the publishing thread, with no task hop and no wake of a broker thread.
//!
//! The loop is one future behind a lock that is only ever tried, never
//! waited for: whoever takes it (the connection's task, or a client
//! thread through [`DirectLoop::claim`]) polls the loop until it waits;
//! a task that finds it taken is woken once the thread that holds it lets
//! go. A client thread hands its publish to the loop in a slot of one
//! item ([`Handed`]), read before the link's channel, and only when
//! nothing it sent before waits in that channel, so the loop takes the
//! connection's items in the order the client sent them. The loop is
//! polled with the task's waker, in the broker's runtime's context, and
//! does what it would do on the task: the same channel code, checks,
//! routing, queues, confirms and statistics. A thread already running a
//! connection's loop (an inline delivery on its way) never claims one.

use leveret_protocol::Outgoing;
use std::cell::Cell;
use std::future::Future;
use std::pin::Pin;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex, TryLockError};
use std::task::{Context, Poll, Waker};
use tokio::sync::mpsc;

type LoopFuture = Pin<Box<dyn Future<Output = ()> + Send>>;

thread_local! {
    /// Whether this thread is running a connection's loop now.
    static RUNNING: Cell<bool> = const { Cell::new(false) };
}

/// The item a client thread hands its connection's loop.
#[derive(Default)]
pub(super) struct Handed {
    item: Mutex<Option<Outgoing>>,
    full: AtomicBool,
}

impl Handed {
    /// Whether an item waits.
    pub(super) fn is_full(&self) -> bool {
        self.full.load(Ordering::Acquire)
    }

    /// The item, if one waits.
    pub(super) fn take(&self) -> Option<Outgoing> {
        if !self.is_full() {
            return None;
        }
        let item = lock(&self.item).take();
        self.full.store(false, Ordering::Release);
        item
    }

    fn put(&self, item: Outgoing) {
        debug_assert!(!self.is_full(), "one handed item at a time");
        *lock(&self.item) = Some(item);
        self.full.store(true, Ordering::Release);
    }
}

/// What the connection's task and its client share.
struct Shared {
    /// The loop, until it ends.
    future: Mutex<Option<LoopFuture>>,
    /// The task's waker, from its latest poll.
    task: Mutex<Option<Waker>>,
    /// The task found the loop taken: wake it when the holder lets go.
    missed: AtomicBool,
    handed: Arc<Handed>,
    /// The client's link, to tell whether anything it sent waits in it
    /// (weak: the client's senders going away ends the connection).
    to_broker: mpsc::WeakSender<Outgoing>,
    runtime: tokio::runtime::Handle,
}

/// The client's way into its in-process connection's loop (see the module
/// docs).
#[derive(Clone)]
pub struct DirectLoop {
    shared: Arc<Shared>,
}

impl std::fmt::Debug for DirectLoop {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("DirectLoop").finish_non_exhaustive()
    }
}

/// The connection's loop, taken by a client thread: hand it an item, then
/// run it. Dropping it lets go of the loop.
pub struct LoopClaim<'a> {
    shared: &'a Shared,
    future: Option<std::sync::MutexGuard<'a, Option<LoopFuture>>>,
    waker: Waker,
}

impl DirectLoop {
    /// Takes the connection's loop for this thread, if no other thread or
    /// task runs it now, it has not ended, and this thread is not already
    /// running one.
    pub fn claim(&self) -> Option<LoopClaim<'_>> {
        if RUNNING.with(Cell::get) {
            return None;
        }
        let waker = lock(&self.shared.task).clone()?;
        let future = match self.shared.future.try_lock() {
            Ok(future) => future,
            Err(TryLockError::WouldBlock | TryLockError::Poisoned(_)) => return None,
        };
        let claim = LoopClaim {
            shared: &self.shared,
            future: Some(future),
            waker,
        };
        // An ended loop (dropping the claim wakes a task that missed it).
        if claim.future.as_ref().is_some_and(|future| future.is_none()) {
            return None;
        }
        Some(claim)
    }
}

impl LoopClaim<'_> {
    /// Hands the loop `item`, to be taken before anything sent later
    /// through the link, if nothing sent before still waits there (nor
    /// another handed item) and `permit` is the only room reserved in it;
    /// otherwise sends `item` through `permit`, as it would have gone
    /// without the claim. Whether it was handed.
    pub fn hand_or_send(&mut self, item: Outgoing, permit: mpsc::Permit<'_, Outgoing>) -> bool {
        let idle = self
            .shared
            .to_broker
            .upgrade()
            .is_some_and(|link| link.capacity() + 1 == link.max_capacity());
        if !idle || self.shared.handed.is_full() {
            permit.send(item);
            return false;
        }
        drop(permit);
        self.shared.handed.put(item);
        true
    }

    /// Runs the loop on this thread until it waits (it handles what it
    /// has been handed and whatever else the link holds), then lets go.
    pub fn run(mut self) {
        let Some(future) = self.future.as_mut() else {
            return;
        };
        let _runtime = self.shared.runtime.enter();
        RUNNING.with(|running| running.set(true));
        if let Some(running) = future.as_mut() {
            if running
                .as_mut()
                .poll(&mut Context::from_waker(&self.waker))
                .is_ready()
            {
                **future = None;
                // The task ends once it sees the loop gone.
                self.waker.wake_by_ref();
            }
        }
        RUNNING.with(|running| running.set(false));
    }
}

impl Drop for LoopClaim<'_> {
    fn drop(&mut self) {
        drop(self.future.take());
        if self.shared.missed.swap(false, Ordering::AcqRel) {
            self.waker.wake_by_ref();
        }
    }
}

/// The connection's task: runs the loop when no client thread does.
struct LoopTask {
    shared: Arc<Shared>,
}

impl Future for LoopTask {
    type Output = ();

    fn poll(self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<()> {
        let shared = &self.shared;
        {
            let mut task = lock(&shared.task);
            if !task.as_ref().is_some_and(|w| w.will_wake(cx.waker())) {
                *task = Some(cx.waker().clone());
            }
        }
        let mut future = match shared.future.try_lock() {
            Ok(future) => future,
            Err(TryLockError::WouldBlock) => {
                shared.missed.store(true, Ordering::SeqCst);
                // The holder may have let go before it could see `missed`.
                match shared.future.try_lock() {
                    Ok(future) => future,
                    Err(TryLockError::WouldBlock) => return Poll::Pending,
                    Err(TryLockError::Poisoned(_)) => return Poll::Ready(()),
                }
            }
            // The loop panicked on a client's thread: it cannot go on.
            Err(TryLockError::Poisoned(_)) => return Poll::Ready(()),
        };
        let Some(running) = future.as_mut() else {
            return Poll::Ready(());
        };
        RUNNING.with(|r| r.set(true));
        let polled = running.as_mut().poll(cx);
        RUNNING.with(|r| r.set(false));
        if polled.is_ready() {
            *future = None;
        }
        polled
    }
}

impl Drop for LoopTask {
    /// A task dropped unfinished (its runtime shut down) takes the loop
    /// with it: no client thread may run it without its runtime.
    fn drop(&mut self) {
        lock(&self.shared.future).take();
    }
}

/// Spawns `connection` (an in-process connection's loop) on the current
/// runtime as a task that its client may also run (see [`DirectLoop`]).
pub(super) fn spawn(
    connection: impl Future<Output = ()> + Send + 'static,
    handed: Arc<Handed>,
    to_broker: &mpsc::Sender<Outgoing>,
) -> DirectLoop {
    let shared = Arc::new(Shared {
        future: Mutex::new(Some(Box::pin(connection))),
        task: Mutex::new(None),
        missed: AtomicBool::new(false),
        handed,
        to_broker: to_broker.downgrade(),
        runtime: tokio::runtime::Handle::current(),
    });
    tokio::spawn(LoopTask {
        shared: Arc::clone(&shared),
    });
    DirectLoop { shared }
}

fn lock<T>(mutex: &Mutex<T>) -> std::sync::MutexGuard<'_, T> {
    mutex.lock().unwrap_or_else(|e| e.into_inner())
}
