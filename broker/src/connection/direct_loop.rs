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
//! routing, queues, confirms and statistics. A client thread's run takes
//! at most [`CLAIM_ITEMS`] items, then hands the rest (others' traffic
//! queued behind its own) to the task. A thread running an in-process
//! connection's loop never claims another (an inline delivery on its
//! way; a sink that runs inline must not call into the broker at all, as
//! the client's `DeliverySink::runs_inline` requires). A single-tag ack
//! such a run has a client send to an in-process connection (an inline
//! delivery's ack, in room reserved for it) it defers instead
//! ([`DirectLoop::defer`]): once the run has let go of its loop, the
//! thread hands each deferred item to its connection's loop and runs that
//! loop too when it is free (else sends it through the link), all these
//! runs together taking at most [`CLAIM_ITEMS`] items, so no broker
//! thread is woken for it.

use leveret_protocol::handoff;
use leveret_protocol::Outgoing;
use std::cell::{Cell, RefCell};
use std::collections::VecDeque;
use std::future::Future;
use std::pin::Pin;
use std::sync::atomic::{fence, AtomicBool, Ordering};
use std::sync::{Arc, Mutex, TryLockError};
use std::task::{Context, Poll, Waker};

type LoopFuture = Pin<Box<dyn Future<Output = ()> + Send>>;

thread_local! {
    /// Whether this thread is running a connection's loop now.
    static RUNNING: Cell<bool> = const { Cell::new(false) };
    /// Items a client thread's claimed run may still take (`None`: this
    /// thread is not on a claimed run).
    static CLAIM_BUDGET: Cell<Option<u32>> = const { Cell::new(None) };
    /// Items a claimed run deferred, to send once it has let go.
    static DEFERRED: RefCell<VecDeque<Deferred>> = const { RefCell::new(VecDeque::new()) };
    /// Whether this thread is sending its deferred items now.
    static SENDING_DEFERRED: Cell<bool> = const { Cell::new(false) };
}

/// An item a client thread's claimed run deferred, with the room reserved
/// for it in its connection's link.
struct Deferred {
    here: DirectLoop,
    item: Outgoing,
    room: handoff::OwnedPermit<Outgoing>,
}

/// Whether `item` is a `basic.ack` of one delivery: the only item
/// [`DirectLoop::defer`] defers.
fn is_single_ack(item: &Outgoing) -> bool {
    matches!(
        item,
        Outgoing::Method {
            method: leveret_protocol::Method::BasicAck(leveret_protocol::BasicAck {
                multiple: false,
                ..
            }),
            ..
        }
    )
}

/// Items a client thread takes on its claimed run before it hands the
/// rest back to the connection's task: its own publish runs at once,
/// other threads' traffic queued behind it does not hold it.
const CLAIM_ITEMS: u32 = 64;

/// One unit of work of a connection's loop, taken per item: on the task,
/// a unit of tokio's cooperative budget; on a client thread's claimed
/// run, a unit of the claim's own budget, whose end hands the loop back
/// to the task (a yield, which wakes it) so the publishing thread returns.
pub(super) async fn consume_budget() {
    let claim_spent = CLAIM_BUDGET.with(|budget| match budget.get() {
        Some(0) => true,
        Some(left) => {
            budget.set(Some(left - 1));
            false
        }
        None => false,
    });
    if claim_spent {
        tokio::task::yield_now().await;
    } else {
        tokio::task::consume_budget().await;
    }
}

/// Marks this thread as running a connection's loop (with a claim's
/// budget, on a client thread) until dropped, unwinding included.
struct Running;

impl Running {
    fn enter(claim_budget: Option<u32>) -> Self {
        RUNNING.with(|running| running.set(true));
        CLAIM_BUDGET.with(|budget| budget.set(claim_budget));
        Running
    }

    /// What is left of the claim's budget (0 without one).
    fn budget_left(&self) -> u32 {
        CLAIM_BUDGET.with(Cell::get).unwrap_or(0)
    }
}

impl Drop for Running {
    fn drop(&mut self) {
        RUNNING.with(|running| running.set(false));
        CLAIM_BUDGET.with(|budget| budget.set(None));
    }
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
    to_broker: handoff::WeakSender<Outgoing>,
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
    /// Whether this thread is on a client thread's claimed run of a
    /// connection's loop, where an item for a connection may be deferred
    /// ([`DirectLoop::defer`]).
    pub fn may_defer() -> bool {
        CLAIM_BUDGET.with(Cell::get).is_some()
    }

    /// On a client thread's claimed run (see [`DirectLoop::may_defer`]),
    /// for a single-tag `basic.ack` (an inline delivery's ack): keeps
    /// `item` for this connection, with `room` reserved for it in its
    /// link, until the run has let go of its loop; then this thread hands
    /// it to this connection's loop and runs it if it is free, or else
    /// sends it through `room`. Any other item, or off such a run, gives
    /// both back, to be sent through the link at once; on such a run,
    /// after what this thread deferred for this connection, which goes
    /// into the link first, so this thread's items keep their order.
    ///
    /// The limit: a deferred ack reaches the connection when the run lets
    /// go (before the put that claimed it returns), not when the client's
    /// send returned; an item another thread sends on the connection
    /// meanwhile may go first. Only single-tag acks are deferred, so this
    /// reorders only those against other threads' items: an application
    /// that acknowledges one channel from several threads must not have
    /// another thread's `multiple` ack rely on an ack sent on a putting
    /// thread's inline delivery before that put returned.
    #[allow(clippy::result_large_err)]
    pub fn defer(
        &self,
        item: Outgoing,
        room: handoff::OwnedPermit<Outgoing>,
    ) -> Result<(), (Outgoing, handoff::OwnedPermit<Outgoing>)> {
        if !DirectLoop::may_defer() {
            return Err((item, room));
        }
        if !is_single_ack(&item) {
            self.release_deferred();
            return Err((item, room));
        }
        DEFERRED.with(|deferred| {
            deferred.borrow_mut().push_back(Deferred {
                here: self.clone(),
                item,
                room,
            });
        });
        Ok(())
    }

    /// Sends what this thread deferred for this connection through the
    /// room reserved for it, in order.
    fn release_deferred(&self) {
        let mine = DEFERRED.with(|deferred| {
            let mut deferred = deferred.borrow_mut();
            let (mine, others): (VecDeque<_>, VecDeque<_>) = deferred
                .drain(..)
                .partition(|kept| Arc::ptr_eq(&kept.here.shared, &self.shared));
            *deferred = others;
            mine
        });
        for Deferred { item, room, .. } in mine {
            room.send(item);
        }
    }

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
    pub fn hand_or_send(&mut self, item: Outgoing, permit: handoff::Permit<'_, Outgoing>) -> bool {
        if !self.may_hand() {
            permit.send(item);
            return false;
        }
        drop(permit);
        self.shared.handed.put(item);
        true
    }

    /// Whether an item may be handed: nothing sent before waits in the
    /// link (its one room reserved is the caller's), nor another handed
    /// item.
    fn may_hand(&self) -> bool {
        self.may_hand_besides(0)
    }

    /// [`LoopClaim::may_hand`], with `reserved` more rooms in the link
    /// known to be this thread's, for items it deferred after this one.
    fn may_hand_besides(&self, reserved: usize) -> bool {
        let idle = self
            .shared
            .to_broker
            .upgrade()
            .is_some_and(|link| link.capacity() + 1 + reserved == link.max_capacity());
        idle && !self.shared.handed.is_full()
    }

    /// Runs the loop on this thread until it waits or has taken
    /// `CLAIM_ITEMS` items (it handles what it has been handed first,
    /// then what else the link holds; the task does the rest), then lets
    /// go. Whether the handed item was handled here. A panic in the loop
    /// ends the connection, as on its task, and stays on this side.
    pub fn run(self) -> bool {
        self.run_within(CLAIM_ITEMS).0
    }

    /// [`LoopClaim::run`] taking at most `budget` items: whether the
    /// handed item was handled here, and what is left of `budget`.
    fn run_within(mut self, budget: u32) -> (bool, u32) {
        let Some(future) = self.future.as_mut() else {
            return (false, budget);
        };
        let _runtime = self.shared.runtime.enter();
        let mut left = budget;
        if let Some(running) = future.as_mut() {
            let polled = {
                let running_mark = Running::enter(Some(budget));
                let mut cx = Context::from_waker(&self.waker);
                let polled = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
                    running.as_mut().poll(&mut cx)
                }));
                left = running_mark.budget_left();
                polled
            };
            let ended = match polled {
                Ok(polled) => polled.is_ready(),
                Err(_) => {
                    tracing::error!("an in-process connection's loop panicked on a client thread; the connection ends");
                    true
                }
            };
            if ended {
                **future = None;
                // The task ends once it sees the loop gone.
                self.waker.wake_by_ref();
            }
        }
        (!self.shared.handed.is_full(), left)
    }
}

impl Drop for LoopClaim<'_> {
    fn drop(&mut self) {
        drop(self.future.take());
        // Against the task's store of `missed` then try of the lock: one
        // of the two sees the other (a fence each side, not ordering of
        // two different locations alone).
        fence(Ordering::SeqCst);
        if self.shared.missed.swap(false, Ordering::AcqRel) {
            self.waker.wake_by_ref();
        }
        send_deferred();
    }
}

/// Sends what this thread's claimed runs deferred, in order, once it runs
/// no loop: each handed to its connection's loop, run here when it is
/// free, else through the room reserved for it in the link. All these
/// runs share one budget of [`CLAIM_ITEMS`] items (a run's own deferred
/// items join the queue): a chain of them (an ack that frees credit, the
/// next queued message delivered inline, its ack deferred, ...) takes at
/// most that many items of other connections' work on this thread; the
/// rest goes through the links, to the connections' tasks.
fn send_deferred() {
    if RUNNING.with(Cell::get) || SENDING_DEFERRED.with(|sending| sending.replace(true)) {
        return;
    }
    struct Sending;
    impl Drop for Sending {
        fn drop(&mut self) {
            SENDING_DEFERRED.with(|sending| sending.set(false));
        }
    }
    let _sending = Sending;
    let mut items = CLAIM_ITEMS;
    while let Some(Deferred { here, item, room }) =
        DEFERRED.with(|deferred| deferred.borrow_mut().pop_front())
    {
        if items > 0 {
            // This thread's rooms for the connection's later deferred
            // items: reserved, but nothing waits in them.
            let later = DEFERRED.with(|deferred| {
                deferred
                    .borrow()
                    .iter()
                    .filter(|later| Arc::ptr_eq(&later.here.shared, &here.shared))
                    .count()
            });
            if let Some(claim) = here.claim() {
                if claim.may_hand_besides(later) {
                    drop(room);
                    claim.shared.handed.put(item);
                    items = claim.run_within(items).1;
                    continue;
                }
            }
        }
        room.send(item);
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
                fence(Ordering::SeqCst);
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
        let polled = {
            let _running = Running::enter(None);
            running.as_mut().poll(cx)
        };
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
    to_broker: &handoff::Sender<Outgoing>,
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

#[cfg(test)]
mod tests {
    use super::*;
    use std::sync::atomic::AtomicUsize;
    use std::task::Wake;

    struct CountWakes(AtomicUsize);

    impl Wake for CountWakes {
        fn wake(self: Arc<Self>) {
            self.0.fetch_add(1, Ordering::SeqCst);
        }
    }

    /// A loop that takes `items` items, counting them into `taken`.
    async fn taking(items: u32, taken: &Cell<u32>) {
        for _ in 0..items {
            consume_budget().await;
            taken.set(taken.get() + 1);
        }
    }

    #[test]
    fn a_claimed_run_takes_its_budget_then_hands_back_with_a_wake() {
        let wakes = Arc::new(CountWakes(AtomicUsize::new(0)));
        let waker = Waker::from(Arc::clone(&wakes));
        let taken = Cell::new(0);
        let mut run = Box::pin(taking(CLAIM_ITEMS + 10, &taken));
        let polled = {
            let _running = Running::enter(Some(CLAIM_ITEMS));
            run.as_mut().poll(&mut Context::from_waker(&waker))
        };
        assert!(polled.is_pending(), "the run stopped at its budget");
        assert_eq!(taken.get(), CLAIM_ITEMS);
        assert_eq!(wakes.0.load(Ordering::SeqCst), 1, "the task is woken");
        assert!(!RUNNING.with(Cell::get), "the mark is gone");
        // The task's poll, without a claim's budget, takes the rest.
        let polled = {
            let _running = Running::enter(None);
            run.as_mut().poll(&mut Context::from_waker(&waker))
        };
        assert!(polled.is_ready());
        assert_eq!(taken.get(), CLAIM_ITEMS + 10);
    }

    fn ack(tag: u64) -> Outgoing {
        Outgoing::Method {
            channel: 1,
            method: leveret_protocol::Method::BasicAck(leveret_protocol::BasicAck {
                delivery_tag: tag,
                multiple: false,
            }),
        }
    }

    fn tag_of(item: &Outgoing) -> u64 {
        match item {
            Outgoing::Method {
                method: leveret_protocol::Method::BasicAck(ack),
                ..
            } => ack.delivery_tag,
            other => panic!("not an ack: {other:?}"),
        }
    }

    /// A connection's loop that records the tags of the items it takes,
    /// the handed one first (looked at on each poll, as the connection's
    /// source does), and waits on its link.
    async fn recording_loop(
        handed: Arc<Handed>,
        mut link: handoff::Receiver<Outgoing>,
        taken: Arc<Mutex<Vec<u64>>>,
    ) {
        loop {
            let next = std::future::poll_fn(|cx| match handed.take() {
                Some(item) => Poll::Ready(Some(item)),
                None => link.poll_recv(cx),
            })
            .await;
            let Some(item) = next else { return };
            lock(&taken).push(tag_of(&item));
        }
    }

    #[test]
    fn an_item_deferred_on_a_claimed_run_is_handled_here_once_the_run_lets_go() {
        let runtime = tokio::runtime::Builder::new_current_thread()
            .build()
            .expect("runtime");
        let (to_broker, link) = handoff::channel(8);
        let handed = Arc::new(Handed::default());
        let taken = Arc::new(Mutex::new(Vec::new()));
        let here = runtime.block_on(async {
            let here = spawn(
                recording_loop(Arc::clone(&handed), link, Arc::clone(&taken)),
                Arc::clone(&handed),
                &to_broker,
            );
            // The task's first poll: the loop waits on its link.
            tokio::task::yield_now().await;
            here
        });
        let room = || to_broker.clone().try_reserve_owned().expect("room");

        // Off a claimed run, nothing is deferred.
        assert!(!DirectLoop::may_defer());
        assert!(here.defer(ack(1), room()).is_err());

        // On one, the item waits for the run's end; then this thread
        // hands it to the loop and runs it: no item in the link, no wake.
        {
            let _running = Running::enter(Some(CLAIM_ITEMS));
            assert!(here.defer(ack(2), room()).is_ok());
            assert!(lock(&taken).is_empty(), "deferred");
        }
        send_deferred();
        assert_eq!(*lock(&taken), [2], "handled on this thread");
        assert_eq!(
            to_broker.capacity(),
            to_broker.max_capacity(),
            "room given back"
        );

        // With the loop held elsewhere, it goes through the link.
        {
            let _running = Running::enter(Some(CLAIM_ITEMS));
            assert!(here.defer(ack(3), room()).is_ok());
        }
        let held = here.shared.future.lock().expect("the loop");
        send_deferred();
        drop(held);
        assert_eq!(
            to_broker.max_capacity() - to_broker.capacity(),
            1,
            "in the link"
        );
        runtime.block_on(tokio::task::yield_now());
        assert_eq!(*lock(&taken), [2, 3], "taken by the task, in order");
    }

    /// A loop that works through a backlog a chain of deferred items
    /// feeds: per item it takes (the handed one first), [`CHAIN_UNITS`]
    /// units of its budget (the item and the backlog's messages its
    /// handling delivers), each counted into `units`, then, on a claimed
    /// run, it defers the next item to itself (the ack of what it
    /// delivered inline), with room reserved in its link.
    async fn chaining_loop(
        handed: Arc<Handed>,
        mut link: handoff::Receiver<Outgoing>,
        to_broker: handoff::Sender<Outgoing>,
        here: Arc<std::sync::OnceLock<DirectLoop>>,
        units: Arc<AtomicUsize>,
    ) {
        loop {
            let next = std::future::poll_fn(|cx| match handed.take() {
                Some(item) => Poll::Ready(Some(item)),
                None => link.poll_recv(cx),
            })
            .await;
            let Some(item) = next else { return };
            for _ in 0..CHAIN_UNITS {
                consume_budget().await;
                units.fetch_add(1, Ordering::SeqCst);
            }
            if DirectLoop::may_defer() {
                let here = here.get().expect("the loop's handle");
                let room = to_broker.clone().try_reserve_owned().expect("room");
                let next = ack(tag_of(&item) + 1);
                assert!(here.defer(next, room).is_ok());
            }
        }
    }

    /// Budget units [`chaining_loop`] takes per item.
    const CHAIN_UNITS: usize = 4;

    #[test]
    fn deferred_runs_share_one_budget_and_the_rest_goes_to_the_task() {
        let runtime = tokio::runtime::Builder::new_current_thread()
            .build()
            .expect("runtime");
        let (to_broker, link) = handoff::channel(8);
        let handed = Arc::new(Handed::default());
        let units = Arc::new(AtomicUsize::new(0));
        let cell = Arc::new(std::sync::OnceLock::new());
        let here = runtime.block_on(async {
            let here = spawn(
                chaining_loop(
                    Arc::clone(&handed),
                    link,
                    to_broker.clone(),
                    Arc::clone(&cell),
                    Arc::clone(&units),
                ),
                Arc::clone(&handed),
                &to_broker,
            );
            tokio::task::yield_now().await;
            here
        });
        cell.set(here.clone()).expect("set once");
        // A put's claimed run deferred the first item of the chain.
        {
            let _running = Running::enter(Some(CLAIM_ITEMS));
            let room = to_broker.clone().try_reserve_owned().expect("room");
            assert!(here.defer(ack(1), room).is_ok());
        }
        send_deferred();
        let handled_here = units.load(Ordering::SeqCst);
        assert_eq!(
            handled_here, CLAIM_ITEMS as usize,
            "this thread took one budget's worth of the chain, no more"
        );
        assert!(DEFERRED.with(|deferred| deferred.borrow().is_empty()));
        // The chain goes on on the connection's task (its loop is not run
        // here again once the budget is spent): the item the last run was
        // stopped in, or the one it deferred, is the task's.
        runtime.block_on(async {
            for _ in 0..4 {
                tokio::task::yield_now().await;
            }
        });
        assert!(
            units.load(Ordering::SeqCst) > handled_here,
            "the task took the rest"
        );
    }

    #[test]
    fn only_single_acks_are_deferred_and_others_keep_this_threads_order() {
        let runtime = tokio::runtime::Builder::new_current_thread()
            .build()
            .expect("runtime");
        let (to_broker, link) = handoff::channel(8);
        let handed = Arc::new(Handed::default());
        let taken = Arc::new(Mutex::new(Vec::new()));
        let here = runtime.block_on(async {
            let here = spawn(
                recording_loop(Arc::clone(&handed), link, Arc::clone(&taken)),
                Arc::clone(&handed),
                &to_broker,
            );
            tokio::task::yield_now().await;
            here
        });
        let room = || to_broker.clone().try_reserve_owned().expect("room");
        let multiple = |tag| Outgoing::Method {
            channel: 1,
            method: leveret_protocol::Method::BasicAck(leveret_protocol::BasicAck {
                delivery_tag: tag,
                multiple: true,
            }),
        };
        {
            let _running = Running::enter(Some(CLAIM_ITEMS));
            assert!(here.defer(ack(1), room()).is_ok(), "a single ack waits");
            let (item, given_back) = here
                .defer(multiple(5), room())
                .expect_err("a multiple ack is not deferred");
            // The client sends it through the link, after ack 1.
            given_back.send(item);
            assert!(DEFERRED.with(|deferred| deferred.borrow().is_empty()));
            assert_eq!(
                to_broker.max_capacity() - to_broker.capacity(),
                2,
                "both in the link"
            );
        }
        send_deferred();
        runtime.block_on(tokio::task::yield_now());
        assert_eq!(*lock(&taken), [1, 5], "in the order this thread sent");
    }

    #[test]
    fn two_acks_deferred_for_one_connection_are_both_handled_here() {
        let runtime = tokio::runtime::Builder::new_current_thread()
            .build()
            .expect("runtime");
        let (to_broker, link) = handoff::channel(8);
        let handed = Arc::new(Handed::default());
        let taken = Arc::new(Mutex::new(Vec::new()));
        let here = runtime.block_on(async {
            let here = spawn(
                recording_loop(Arc::clone(&handed), link, Arc::clone(&taken)),
                Arc::clone(&handed),
                &to_broker,
            );
            tokio::task::yield_now().await;
            here
        });
        let room = || to_broker.clone().try_reserve_owned().expect("room");
        {
            let _running = Running::enter(Some(CLAIM_ITEMS));
            assert!(here.defer(ack(1), room()).is_ok());
            assert!(here.defer(ack(2), room()).is_ok());
        }
        send_deferred();
        // The task has not run: both were handled on this thread.
        assert_eq!(*lock(&taken), [1, 2], "both handled here, in order");
        assert_eq!(to_broker.capacity(), to_broker.max_capacity());
    }

    #[test]
    fn the_running_mark_is_gone_after_a_panic() {
        let unwound = std::panic::catch_unwind(|| {
            let _running = Running::enter(Some(CLAIM_ITEMS));
            panic!("in the loop");
        });
        assert!(unwound.is_err());
        assert!(!RUNNING.with(Cell::get));
        assert_eq!(CLAIM_BUDGET.with(Cell::get), None);
    }
}
