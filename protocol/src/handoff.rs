//! A bounded queue that carries items from their senders to one receiver
//! and holds no room while it is empty: what a client's [`Outgoing`]
//! items cross on their way to its writer task or to an in-process
//! broker's connection, and a broker connection's outbox items on their
//! way to its writer or its in-process client (one of each per
//! connection, so an idle one must cost little: a tokio mpsc channel
//! reserves a block of 32 slots when created, 4.6 KiB of `Outgoing`
//! items, 1.8 KiB of the outbox's, for every connection).
//!
//! The interface and the semantics are tokio's bounded mpsc channel's:
//! at most `capacity` items wait or are reserved ([`Permit`]); a sender
//! with no room waits for it ([`Sender::reserve`], [`Sender::send`]) or
//! is told so ([`Sender::try_send`]); the receiver sees the end once
//! every sender is gone and the items are taken; senders see it closed
//! once the receiver is gone (and an item sent through a permit then is
//! dropped). Senders that wait for room are served in the order they
//! began to wait, as tokio's are: each room that comes free is reserved
//! for the sender that has waited longest and only that one is woken, so
//! one busy sender (a channel publishing as fast as it can) never keeps
//! another waiting for ever, and no sender arriving later takes a room
//! before them. A wait given up ([`Sender::reserve`]'s future dropped)
//! leaves its place in the line, or passes the room it was given on to
//! the next in line. Waiters are kept in a `VecDeque` in ticket order:
//! serving the first is O(1); a waiter finds its own place by binary
//! search, and one giving up from the middle shifts the shorter side.
//!
//! The items live in a `VecDeque` behind a mutex, grown as items wait and
//! kept for reuse, so sending on a warm queue allocates nothing; a burst
//! past `ROOM_KEPT` (64) items gives its room back once it has drained, and
//! a receiver that goes idle may give back the rest
//! ([`Receiver::release_room`]: an in-process connection's loop does, as
//! a socket reader gives back its buffer).
//!
//! It uses nothing but a mutex and an atomic, so the `leveret-loom` crate
//! compiles this very file against loom's and explores every interleaving
//! of its senders, permits and receiver (`loom/tests/handoff.rs`).
//!
//! [`Outgoing`]: crate::Outgoing

#[cfg(loom)]
use loom::sync::atomic::{AtomicUsize, Ordering};
#[cfg(loom)]
use loom::sync::{Arc, Mutex, MutexGuard};
use std::collections::VecDeque;
use std::future::{poll_fn, Future};
use std::pin::Pin;
#[cfg(not(loom))]
use std::sync::atomic::{AtomicUsize, Ordering};
#[cfg(not(loom))]
use std::sync::{Arc, Mutex, MutexGuard};
use std::task::{Context, Poll, Waker};

/// The room, in items, a queue keeps once a burst that outgrew it has
/// drained: a burst up to the capacity (hundreds of items) is not held
/// for as long as its connection stays busy.
const ROOM_KEPT: usize = 64;

/// A queue of at most `capacity` items (at least one): its first sender
/// and its receiver.
pub fn channel<T>(capacity: usize) -> (Sender<T>, Receiver<T>) {
    let shared = Arc::new(Shared {
        capacity: capacity.max(1),
        senders: AtomicUsize::new(1),
        free: AtomicUsize::new(capacity.max(1)),
        state: Mutex::new(State {
            items: VecDeque::new(),
            reserved: 0,
            receiving: true,
            receiver: None,
            waiting: VecDeque::new(),
            next_ticket: 0,
            closed_waiters: Vec::new(),
        }),
    });
    (
        Sender {
            shared: Arc::clone(&shared),
        },
        Receiver {
            shared,
            keeps_room: false,
        },
    )
}

/// A send refused: the queue's receiver is gone (the item comes back).
#[derive(Debug, PartialEq, Eq)]
pub struct SendError<T>(pub T);

/// A send without waiting refused (the item comes back).
#[derive(Debug, PartialEq, Eq)]
pub enum TrySendError<T> {
    /// Every room is taken.
    Full(T),
    /// The queue's receiver is gone.
    Closed(T),
}

struct Shared<T> {
    capacity: usize,
    /// Live senders (permits that own one count as one): outside the
    /// lock, so a clone costs what an `Arc`'s does.
    senders: AtomicUsize,
    /// Rooms free, stored under the lock whenever they change, so that
    /// [`Sender::capacity`] (a check on every in-process publish) reads it
    /// without taking the lock.
    free: AtomicUsize,
    state: Mutex<State<T>>,
}

struct State<T> {
    items: VecDeque<T>,
    /// Rooms held by permits not yet used.
    reserved: usize,
    /// Whether the receiver is still there.
    receiving: bool,
    /// The receiver's waker, while it waits for an item.
    receiver: Option<Waker>,
    /// Senders waiting for room, in the order they began to wait (their
    /// tickets rise), none of them given a room yet: a sender whose ticket
    /// has left the line without it giving up was given one (reserved for
    /// it). Wakers are taken when the receiver goes (the tickets stay,
    /// for their senders to find).
    waiting: VecDeque<(u64, Option<Waker>)>,
    /// The ticket of the next sender to wait.
    next_ticket: u64,
    /// The tasks waiting for the receiver to go ([`Sender::closed`]), one
    /// waker a task.
    closed_waiters: Vec<Waker>,
}

impl<T> State<T> {
    /// Where the sender holding `ticket` waits, if it still does.
    fn place(&self, ticket: u64) -> Option<usize> {
        self.waiting
            .binary_search_by_key(&ticket, |&(ticket, _)| ticket)
            .ok()
    }
}

impl<T> Shared<T> {
    fn lock(&self) -> MutexGuard<'_, State<T>> {
        self.state.lock().unwrap_or_else(|e| e.into_inner())
    }

    fn room(&self, state: &State<T>) -> usize {
        self.capacity - state.items.len() - state.reserved
    }

    /// Takes a room for a permit; `Full` and `Closed` carry nothing.
    fn try_reserve(&self) -> Result<(), TrySendError<()>> {
        let mut state = self.lock();
        if !state.receiving {
            Err(TrySendError::Closed(()))
        } else if self.room(&state) == 0 {
            Err(TrySendError::Full(()))
        } else {
            state.reserved += 1;
            self.show_free(&state);
            Ok(())
        }
    }

    /// Stores the rooms free for [`Sender::capacity`]; called under the
    /// lock after every change of them.
    fn show_free(&self, state: &State<T>) {
        self.free.store(self.room(state), Ordering::Release);
    }

    /// Reserves a room that has just come free for the sender that has
    /// waited longest: its waker, to wake once the lock is let go.
    fn serve_next(&self, state: &mut State<T>) -> Option<Waker> {
        if !state.receiving || self.room(state) == 0 {
            return None;
        }
        let (_, waker) = state.waiting.pop_front()?;
        state.reserved += 1;
        waker
    }

    /// Takes the next item, if one is there, under `state`'s lock: the
    /// room it leaves goes to the sender that has waited longest, whose
    /// waker comes with it, to wake once the lock is let go. The last item
    /// of a burst past [`ROOM_KEPT`] items takes the burst's room with it.
    fn take(&self, state: &mut State<T>) -> Option<(T, Option<Waker>)> {
        let item = state.items.pop_front()?;
        if state.items.is_empty() && state.items.capacity() > ROOM_KEPT {
            state.items.shrink_to(ROOM_KEPT);
        }
        let next = self.serve_next(state);
        self.show_free(state);
        Some((item, next))
    }

    /// Takes a room for a permit once one is reserved for this sender:
    /// at once if there is room (then nobody waits), else it joins the
    /// line (`ticket` is its place in it).
    fn poll_reserve(
        &self,
        ticket: &mut Option<u64>,
        cx: &mut Context<'_>,
    ) -> Poll<Result<(), SendError<()>>> {
        let mut state = self.lock();
        let Some(mine) = *ticket else {
            if !state.receiving {
                return Poll::Ready(Err(SendError(())));
            }
            if self.room(&state) > 0 {
                state.reserved += 1;
                self.show_free(&state);
                return Poll::Ready(Ok(()));
            }
            let mine = state.next_ticket;
            state.next_ticket += 1;
            state.waiting.push_back((mine, Some(cx.waker().clone())));
            *ticket = Some(mine);
            return Poll::Pending;
        };
        if let Some(place) = state.place(mine) {
            if !state.receiving {
                state.waiting.remove(place);
                *ticket = None;
                return Poll::Ready(Err(SendError(())));
            }
            match &mut state.waiting[place].1 {
                Some(waker) if waker.will_wake(cx.waker()) => {}
                waker => *waker = Some(cx.waker().clone()),
            }
            return Poll::Pending;
        }
        // Served: a room is reserved for it (given back if the receiver
        // has gone since).
        *ticket = None;
        if state.receiving {
            return Poll::Ready(Ok(()));
        }
        state.reserved -= 1;
        self.show_free(&state);
        Poll::Ready(Err(SendError(())))
    }

    /// A sender gives up waiting: it leaves the line, or passes the room
    /// it was given on to the next in line.
    fn leave_line(&self, ticket: u64) {
        let mut state = self.lock();
        let next = match state.place(ticket) {
            Some(place) => {
                state.waiting.remove(place);
                None
            }
            None => {
                state.reserved -= 1;
                let next = self.serve_next(&mut state);
                self.show_free(&state);
                next
            }
        };
        drop(state);
        if let Some(next) = next {
            next.wake();
        }
    }

    /// Puts an item in a room a permit held (dropped if the receiver is
    /// gone).
    fn put(&self, item: T) {
        let mut state = self.lock();
        state.reserved -= 1;
        if !state.receiving {
            self.show_free(&state);
            drop(state);
            drop(item);
            return;
        }
        state.items.push_back(item);
        let receiver = state.receiver.take();
        drop(state);
        if let Some(receiver) = receiver {
            receiver.wake();
        }
    }

    /// Gives back a room a permit held unused.
    fn unreserve(&self) {
        let mut state = self.lock();
        state.reserved -= 1;
        let next = self.serve_next(&mut state);
        self.show_free(&state);
        drop(state);
        if let Some(next) = next {
            next.wake();
        }
    }

    fn add_sender(&self) {
        self.senders.fetch_add(1, Ordering::Relaxed);
    }

    /// The last sender gone wakes the receiver, which finds the count at
    /// zero under the lock taken here after it fell.
    fn drop_sender(&self) {
        if self.senders.fetch_sub(1, Ordering::AcqRel) != 1 {
            return;
        }
        let receiver = self.lock().receiver.take();
        if let Some(receiver) = receiver {
            receiver.wake();
        }
    }
}

/// A sending end; clones send into the same queue.
pub struct Sender<T> {
    shared: Arc<Shared<T>>,
}

impl<T> Sender<T> {
    /// Sends `item`, waiting for room; the item comes back if the
    /// receiver is gone.
    pub async fn send(&self, item: T) -> Result<(), SendError<T>> {
        match self.reserve().await {
            Ok(permit) => {
                permit.send(item);
                Ok(())
            }
            Err(SendError(())) => Err(SendError(item)),
        }
    }

    /// Sends `item` if there is room now.
    pub fn try_send(&self, item: T) -> Result<(), TrySendError<T>> {
        let mut state = self.shared.lock();
        if !state.receiving {
            return Err(TrySendError::Closed(item));
        }
        if self.shared.room(&state) == 0 {
            return Err(TrySendError::Full(item));
        }
        state.items.push_back(item);
        self.shared.show_free(&state);
        let receiver = state.receiver.take();
        drop(state);
        if let Some(receiver) = receiver {
            receiver.wake();
        }
        Ok(())
    }

    /// Waits for room and reserves it, after the senders that began
    /// waiting before (cancel-safe: dropped before it is ready, it holds
    /// nothing, and a room it was given goes to the next in line).
    pub fn reserve(&self) -> impl Future<Output = Result<Permit<'_, T>, SendError<()>>> + '_ {
        Reserve {
            shared: &self.shared,
            ticket: None,
        }
    }

    /// Reserves room if there is some now.
    pub fn try_reserve(&self) -> Result<Permit<'_, T>, TrySendError<()>> {
        self.shared.try_reserve().map(|()| Permit {
            shared: &self.shared,
        })
    }

    /// Reserves room if there is some now, the permit owning this sender
    /// (which comes back if there is none).
    pub fn try_reserve_owned(self) -> Result<OwnedPermit<T>, TrySendError<Self>> {
        match self.shared.try_reserve() {
            Ok(()) => Ok(OwnedPermit { sender: Some(self) }),
            Err(TrySendError::Full(())) => Err(TrySendError::Full(self)),
            Err(TrySendError::Closed(())) => Err(TrySendError::Closed(self)),
        }
    }

    /// Rooms free now (read without taking the lock: as of the last
    /// send, reserve or take).
    pub fn capacity(&self) -> usize {
        self.shared.free.load(Ordering::Acquire)
    }

    /// Rooms in all.
    pub fn max_capacity(&self) -> usize {
        self.shared.capacity
    }

    /// Whether the receiver is gone.
    pub fn is_closed(&self) -> bool {
        !self.shared.lock().receiving
    }

    /// Resolves once the receiver is gone. Meant for a few tasks that
    /// wait with their own waker (a broker connection's task): a task
    /// that waits again (its wait dropped, then made anew) is remembered
    /// once, and a dropped wait's waker stays until the receiver goes.
    pub fn closed(&self) -> impl Future<Output = ()> + '_ {
        poll_fn(move |cx| {
            let mut state = self.shared.lock();
            if !state.receiving {
                return Poll::Ready(());
            }
            if !state.closed_waiters.iter().any(|w| w.will_wake(cx.waker())) {
                state.closed_waiters.push(cx.waker().clone());
            }
            Poll::Pending
        })
    }

    /// A handle that does not keep the queue open.
    pub fn downgrade(&self) -> WeakSender<T> {
        WeakSender {
            shared: Arc::clone(&self.shared),
        }
    }
}

impl<T> Clone for Sender<T> {
    fn clone(&self) -> Self {
        self.shared.add_sender();
        Sender {
            shared: Arc::clone(&self.shared),
        }
    }
}

impl<T> Drop for Sender<T> {
    fn drop(&mut self) {
        self.shared.drop_sender();
    }
}

impl<T> std::fmt::Debug for Sender<T> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Sender")
            .field("capacity", &self.shared.capacity)
            .finish_non_exhaustive()
    }
}

/// [`Sender::reserve`]'s wait: its place in the line once it has one.
struct Reserve<'a, T> {
    shared: &'a Shared<T>,
    ticket: Option<u64>,
}

impl<'a, T> Future for Reserve<'a, T> {
    type Output = Result<Permit<'a, T>, SendError<()>>;

    fn poll(self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<Self::Output> {
        let this = self.get_mut();
        let shared = this.shared;
        shared
            .poll_reserve(&mut this.ticket, cx)
            .map_ok(|()| Permit { shared })
    }
}

impl<T> Drop for Reserve<'_, T> {
    fn drop(&mut self) {
        if let Some(ticket) = self.ticket.take() {
            self.shared.leave_line(ticket);
        }
    }
}

/// A sender that does not keep the queue open: upgraded while another
/// sender lives.
pub struct WeakSender<T> {
    shared: Arc<Shared<T>>,
}

impl<T> WeakSender<T> {
    /// A sender, unless every sender is gone.
    pub fn upgrade(&self) -> Option<Sender<T>> {
        self.shared
            .senders
            .fetch_update(Ordering::AcqRel, Ordering::Acquire, |n| {
                (n > 0).then_some(n + 1)
            })
            .ok()?;
        Some(Sender {
            shared: Arc::clone(&self.shared),
        })
    }
}

/// Room reserved for one item; dropping it unused gives the room back.
pub struct Permit<'a, T> {
    shared: &'a Shared<T>,
}

impl<T> Permit<'_, T> {
    /// Sends `item` into the room reserved (dropped if the receiver is
    /// gone).
    pub fn send(self, item: T) {
        let shared = self.shared;
        std::mem::forget(self);
        shared.put(item);
    }
}

impl<T> Drop for Permit<'_, T> {
    fn drop(&mut self) {
        self.shared.unreserve();
    }
}

/// Room reserved for one item, owning its sender; dropping it unused
/// gives the room back.
pub struct OwnedPermit<T> {
    /// Always there until sent or dropped.
    sender: Option<Sender<T>>,
}

impl<T> OwnedPermit<T> {
    /// Sends `item` into the room reserved (dropped if the receiver is
    /// gone); the sender comes back.
    pub fn send(mut self, item: T) -> Sender<T> {
        let sender = self.sender.take().expect("a permit holds its sender");
        sender.shared.put(item);
        sender
    }
}

impl<T> Drop for OwnedPermit<T> {
    fn drop(&mut self) {
        if let Some(sender) = &self.sender {
            sender.shared.unreserve();
        }
    }
}

impl<T> std::fmt::Debug for OwnedPermit<T> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("OwnedPermit").finish_non_exhaustive()
    }
}

/// The receiving end.
pub struct Receiver<T> {
    shared: Arc<Shared<T>>,
    /// Whether an item has been taken since the room was last given back
    /// (so the queue has grown room): known without taking the lock.
    keeps_room: bool,
}

impl<T> Receiver<T> {
    /// The next item, waiting for one; `None` once every sender is gone
    /// and every item taken.
    pub async fn recv(&mut self) -> Option<T> {
        poll_fn(|cx| self.poll_recv(cx)).await
    }

    /// The next item if one is there, else registers `cx` to be woken.
    pub fn poll_recv(&mut self, cx: &mut Context<'_>) -> Poll<Option<T>> {
        let mut state = self.shared.lock();
        if let Some((item, next)) = self.shared.take(&mut state) {
            drop(state);
            return Poll::Ready(Some(self.taken(item, next)));
        }
        if self.shared.senders.load(Ordering::Acquire) == 0 {
            return Poll::Ready(None);
        }
        match &mut state.receiver {
            Some(waker) if waker.will_wake(cx.waker()) => {}
            receiver => *receiver = Some(cx.waker().clone()),
        }
        Poll::Pending
    }

    /// The next item if one is there now.
    pub fn try_recv(&mut self) -> Option<T> {
        let mut state = self.shared.lock();
        let (item, next) = self.shared.take(&mut state)?;
        drop(state);
        Some(self.taken(item, next))
    }

    /// An item taken ([`Shared::take`]), the lock let go: the receiver
    /// keeps its room from now, and the sender served next is woken.
    fn taken(&mut self, item: T, next: Option<Waker>) -> T {
        self.keeps_room = true;
        if let Some(next) = next {
            next.wake();
        }
        item
    }

    /// Whether the queue may keep room for items: one has been taken
    /// since [`Receiver::release_room`] (told without taking the lock).
    pub fn holds_room(&self) -> bool {
        self.keeps_room
    }

    /// Gives back the room kept for items, if none waits: for an idle
    /// receiver (the next item grows it again).
    pub fn release_room(&mut self) {
        let mut state = self.shared.lock();
        if !state.items.is_empty() {
            return;
        }
        // Freed once the lock is let go: senders do not wait for it.
        let items = std::mem::take(&mut state.items);
        let waiting = if state.waiting.is_empty() {
            std::mem::take(&mut state.waiting)
        } else {
            VecDeque::new()
        };
        self.keeps_room = false;
        drop(state);
        drop((items, waiting));
    }
}

impl<T> Drop for Receiver<T> {
    fn drop(&mut self) {
        let mut state = self.shared.lock();
        state.receiving = false;
        let items = std::mem::take(&mut state.items);
        self.shared.show_free(&state);
        // The waiting senders' tickets stay in line, to be told it closed.
        let waiting: Vec<Waker> = state
            .waiting
            .iter_mut()
            .filter_map(|(_, waker)| waker.take())
            .collect();
        // Its own waker too: the task it names is not kept alive, nor
        // woken by the last sender, once nothing can be received.
        let receiver = state.receiver.take();
        let closed_waiters = std::mem::take(&mut state.closed_waiters);
        drop(state);
        drop((items, receiver));
        for waker in waiting.into_iter().chain(closed_waiters) {
            waker.wake();
        }
    }
}

impl<T> std::fmt::Debug for Receiver<T> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Receiver")
            .field("capacity", &self.shared.capacity)
            .finish_non_exhaustive()
    }
}

#[cfg(all(test, not(loom)))]
mod tests {
    use super::*;
    use std::sync::atomic::{AtomicUsize, Ordering};
    use std::task::Wake;

    /// Counts its wakes.
    #[derive(Default)]
    struct Wakes(AtomicUsize);

    impl Wake for Wakes {
        fn wake(self: Arc<Self>) {
            self.0.fetch_add(1, Ordering::Relaxed);
        }
    }

    fn poll<F: Future>(future: std::pin::Pin<&mut F>, waker: &Waker) -> Poll<F::Output> {
        future.poll(&mut Context::from_waker(waker))
    }

    #[test]
    fn items_arrive_in_order_up_to_the_capacity_and_room_comes_back() {
        let (tx, mut rx) = channel(2);
        assert_eq!(rx.try_recv(), None);
        tx.try_send(1).unwrap();
        let permit = tx.try_reserve().unwrap();
        assert_eq!(tx.capacity(), 0);
        assert_eq!(tx.try_send(3), Err(TrySendError::Full(3)));
        drop(permit);
        assert_eq!(tx.capacity(), 1, "an unused permit gives its room back");
        tx.try_send(2).unwrap();
        assert_eq!(rx.try_recv(), Some(1));
        tx.try_send(3).unwrap();
        assert_eq!(
            (rx.try_recv(), rx.try_recv(), rx.try_recv()),
            (Some(2), Some(3), None)
        );
        assert_eq!(tx.capacity(), tx.max_capacity());
    }

    #[test]
    fn a_sender_without_room_waits_and_is_woken_when_an_item_is_taken() {
        let (tx, mut rx) = channel(1);
        tx.try_send(1).unwrap();
        let wakes = Arc::new(Wakes::default());
        let waker = Waker::from(Arc::clone(&wakes));
        let mut reserve = std::pin::pin!(tx.reserve());
        assert!(poll(reserve.as_mut(), &waker).is_pending());
        assert_eq!(wakes.0.load(Ordering::Relaxed), 0);
        assert_eq!(rx.try_recv(), Some(1));
        assert_eq!(wakes.0.load(Ordering::Relaxed), 1);
        let Poll::Ready(Ok(permit)) = poll(reserve.as_mut(), &waker) else {
            panic!("room after the take");
        };
        permit.send(2);
        assert_eq!(rx.try_recv(), Some(2));
    }

    /// A waker that counts its wakes, and the count.
    fn counted_waker() -> (Waker, Arc<Wakes>) {
        let wakes = Arc::new(Wakes::default());
        (Waker::from(Arc::clone(&wakes)), wakes)
    }

    fn woken(wakes: &[&Arc<Wakes>]) -> Vec<usize> {
        wakes.iter().map(|w| w.0.load(Ordering::Relaxed)).collect()
    }

    #[test]
    fn waiting_senders_are_served_in_the_order_they_began_to_wait() {
        let (tx, mut rx) = channel(1);
        tx.try_send(0).unwrap();
        let [(wa, a), (wb, b), (wc, c)] = [(); 3].map(|()| counted_waker());
        let mut first = std::pin::pin!(tx.send(1));
        let mut second = std::pin::pin!(tx.send(2));
        let mut third = std::pin::pin!(tx.send(3));
        assert!(poll(first.as_mut(), &wa).is_pending());
        assert!(poll(second.as_mut(), &wb).is_pending());
        assert!(poll(third.as_mut(), &wc).is_pending());
        assert_eq!(rx.try_recv(), Some(0));
        assert_eq!(woken(&[&a, &b, &c]), [1, 0, 0], "only the first woken");
        assert_eq!(
            tx.try_send(9),
            Err(TrySendError::Full(9)),
            "the room is the first waiter's"
        );
        // The later ones, polled first, still wait their turn.
        assert!(poll(third.as_mut(), &wc).is_pending());
        assert!(poll(second.as_mut(), &wb).is_pending());
        assert_eq!(poll(first.as_mut(), &wa), Poll::Ready(Ok(())));
        assert_eq!(rx.try_recv(), Some(1));
        assert_eq!(woken(&[&a, &b, &c]), [1, 1, 0]);
        assert!(poll(third.as_mut(), &wc).is_pending());
        assert_eq!(poll(second.as_mut(), &wb), Poll::Ready(Ok(())));
        assert_eq!(rx.try_recv(), Some(2));
        assert_eq!(woken(&[&a, &b, &c]), [1, 1, 1]);
        assert_eq!(poll(third.as_mut(), &wc), Poll::Ready(Ok(())));
        assert_eq!(rx.try_recv(), Some(3));
        assert_eq!(tx.capacity(), 1);
    }

    #[test]
    fn a_sender_giving_up_leaves_the_line_or_passes_its_room_on() {
        let (tx, mut rx) = channel(1);
        tx.try_send(0).unwrap();
        let [(wa, a), (wb, b), (wc, c)] = [(); 3].map(|()| counted_waker());
        let mut first = Box::pin(tx.reserve());
        let mut second = Box::pin(tx.reserve());
        let mut third = Box::pin(tx.reserve());
        assert!(poll(first.as_mut(), &wa).is_pending());
        assert!(poll(second.as_mut(), &wb).is_pending());
        assert!(poll(third.as_mut(), &wc).is_pending());
        drop(second);
        assert_eq!(rx.try_recv(), Some(0));
        assert_eq!(woken(&[&a, &b, &c]), [1, 0, 0], "the second left the line");
        drop(first);
        assert_eq!(
            woken(&[&a, &b, &c]),
            [1, 0, 1],
            "the room the first was given goes to the next in line"
        );
        let Poll::Ready(Ok(permit)) = poll(third.as_mut(), &wc) else {
            panic!("the third is given the room");
        };
        permit.send(3);
        assert_eq!(rx.try_recv(), Some(3));
        assert_eq!(tx.capacity(), 1, "no room lost");
    }

    #[test]
    fn a_sender_served_as_the_receiver_goes_gives_its_room_back() {
        let (tx, mut rx) = channel(1);
        tx.try_send(0).unwrap();
        let (waker, wakes) = counted_waker();
        let mut reserve = std::pin::pin!(tx.reserve());
        assert!(poll(reserve.as_mut(), &waker).is_pending());
        assert_eq!(rx.try_recv(), Some(0));
        drop(rx);
        assert_eq!(woken(&[&wakes]), [1]);
        assert!(matches!(
            poll(reserve.as_mut(), &waker),
            Poll::Ready(Err(SendError(())))
        ));
        assert_eq!(tx.capacity(), 1);
    }

    #[test]
    fn the_rooms_free_are_told_without_taking_the_lock() {
        let (tx, mut rx) = channel(2);
        let permit = tx.try_reserve().unwrap();
        tx.try_send(1).unwrap();
        let held = tx.shared.lock();
        let (report, told) = std::sync::mpsc::channel();
        std::thread::scope(|scope| {
            scope.spawn(|| report.send(tx.capacity()).unwrap());
            let free = told.recv_timeout(std::time::Duration::from_secs(10));
            drop(held);
            assert_eq!(free, Ok(0), "told while another holds the lock");
        });
        drop(permit);
        assert_eq!(tx.capacity(), 1);
        assert_eq!(rx.try_recv(), Some(1));
        assert_eq!(tx.capacity(), 2);
    }

    #[test]
    fn the_receiver_is_woken_by_an_item_and_sees_the_end_after_the_items() {
        let (tx, mut rx) = channel(4);
        let wakes = Arc::new(Wakes::default());
        let waker = Waker::from(Arc::clone(&wakes));
        let mut cx = Context::from_waker(&waker);
        assert!(rx.poll_recv(&mut cx).is_pending());
        let owned = tx.clone().try_reserve_owned().unwrap();
        let weak = tx.downgrade();
        tx.try_send(1).unwrap();
        assert_eq!(wakes.0.load(Ordering::Relaxed), 1);
        drop(tx);
        assert!(
            weak.upgrade().is_some(),
            "the permit's sender keeps it open"
        );
        drop(owned.send(2));
        assert!(weak.upgrade().is_none());
        assert_eq!(rx.poll_recv(&mut cx), Poll::Ready(Some(1)));
        assert_eq!(rx.poll_recv(&mut cx), Poll::Ready(Some(2)));
        assert_eq!(rx.poll_recv(&mut cx), Poll::Ready(None));
    }

    #[test]
    fn senders_see_the_receiver_gone_and_waiting_ones_are_woken() {
        let (tx, rx) = channel(1);
        tx.try_send(1).unwrap();
        let wakes = Arc::new(Wakes::default());
        let waker = Waker::from(Arc::clone(&wakes));
        let mut reserve = std::pin::pin!(tx.reserve());
        assert!(poll(reserve.as_mut(), &waker).is_pending());
        drop(rx);
        assert_eq!(wakes.0.load(Ordering::Relaxed), 1);
        assert!(matches!(
            poll(reserve.as_mut(), &waker),
            Poll::Ready(Err(SendError(())))
        ));
        assert!(tx.is_closed());
        assert_eq!(tx.try_send(2), Err(TrySendError::Closed(2)));
    }

    #[test]
    fn a_receiver_gone_keeps_no_waker_of_its_own() {
        let (tx, mut rx) = channel::<u32>(1);
        let wakes = Arc::new(Wakes::default());
        let waker = Waker::from(Arc::clone(&wakes));
        assert!(rx.poll_recv(&mut Context::from_waker(&waker)).is_pending());
        drop((rx, waker));
        assert_eq!(Arc::strong_count(&wakes), 1, "its task not kept alive");
        drop(tx);
        assert_eq!(wakes.0.load(Ordering::Relaxed), 0, "nor woken");
    }

    #[test]
    fn an_idle_receiver_gives_its_room_back() {
        let (tx, mut rx) = channel(8);
        assert!(!rx.holds_room(), "a new queue holds no room");
        tx.try_send(1).unwrap();
        rx.release_room();
        assert_eq!(rx.try_recv(), Some(1), "an item waiting keeps its room");
        assert!(rx.holds_room());
        rx.release_room();
        assert!(!rx.holds_room());
    }

    #[test]
    fn closed_resolves_once_the_receiver_is_gone() {
        let (tx, rx) = channel::<u8>(1);
        let wakes = Arc::new(Wakes::default());
        let waker = Waker::from(Arc::clone(&wakes));
        let mut cx = Context::from_waker(&waker);
        // Waited on twice by the same task (the first wait dropped).
        for _ in 0..2 {
            let mut closed = std::pin::pin!(tx.closed());
            assert!(closed.as_mut().poll(&mut cx).is_pending());
        }
        assert_eq!(tx.shared.lock().closed_waiters.len(), 1, "one waker a task");
        drop(rx);
        assert_eq!(
            wakes.0.load(Ordering::Relaxed),
            1,
            "woken as the receiver went"
        );
        assert!(std::pin::pin!(tx.closed()).poll(&mut cx).is_ready());
    }

    #[test]
    fn a_drained_burst_keeps_only_the_room_kept() {
        let (tx, mut rx) = channel::<u64>(4 * ROOM_KEPT);
        let room = |rx: &Receiver<u64>| rx.shared.lock().items.capacity();
        for round in 0..2 {
            for i in 0..4 * ROOM_KEPT as u64 {
                tx.try_send(i).unwrap();
            }
            assert!(
                room(&rx) >= 4 * ROOM_KEPT,
                "round {round}: the burst's room"
            );
            for i in 0..4 * ROOM_KEPT as u64 {
                assert_eq!(rx.try_recv(), Some(i), "round {round}: in order");
                if i < 4 * ROOM_KEPT as u64 - 1 {
                    assert!(room(&rx) >= 4 * ROOM_KEPT, "kept while items wait");
                }
            }
            assert!(room(&rx) <= ROOM_KEPT, "round {round}: {} kept", room(&rx));
        }
        // A queue that never outgrew the room kept keeps all of it.
        for i in 0..8 {
            tx.try_send(i).unwrap();
        }
        let before = room(&rx);
        while rx.try_recv().is_some() {}
        assert_eq!(room(&rx), before);
    }
}
