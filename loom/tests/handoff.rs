//! Loom models of the handoff queue (the protocol crate's own
//! `protocol/src/handoff.rs`, compiled against loom's mutex and atomics):
//! each thread is a sender, a permit's holder or the receiver of one
//! connection's queue. A lost wake-up shows as a deadlock (every thread
//! parked), which loom reports; a permit counted wrong shows as an item
//! lost, duplicated or let in past the capacity.
#![cfg(loom)]

#[path = "../../protocol/src/handoff.rs"]
#[allow(dead_code)]
mod handoff;

use handoff::{channel, SendError, TrySendError};
use loom::future::block_on;
use loom::sync::atomic::{AtomicUsize, Ordering};
use loom::sync::Arc;
use loom::thread;
use std::future::{poll_fn, Future};
use std::pin::pin;
use std::task::Poll;

/// Explores every interleaving with at most `preemptions` forced switches
/// a run (loom's bound: the state space of three threads taking a lock
/// several times each is too large to walk whole).
/// Prints how many interleavings it explored.
fn model(preemptions: usize, f: impl Fn() + Sync + Send + 'static) {
    let runs = std::sync::Arc::new(std::sync::atomic::AtomicUsize::new(0));
    let mut builder = loom::model::Builder::new();
    builder.preemption_bound = Some(preemptions);
    let counted = std::sync::Arc::clone(&runs);
    builder.check(move || {
        counted.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
        f();
    });
    let runs = runs.load(std::sync::atomic::Ordering::Relaxed);
    eprintln!("{runs} interleavings (at most {preemptions} preemptions each)");
}

/// An item that counts its drops, to tell an item lost in the queue from
/// one dropped with it.
struct Counted(Arc<AtomicUsize>);

impl Drop for Counted {
    fn drop(&mut self) {
        self.0.fetch_add(1, Ordering::Relaxed);
    }
}

/// Two senders send through a queue of one room, the first two items, the
/// second one, while the receiver takes them: every item arrives exactly
/// once, each sender's in its order, and the receiver sees the end after
/// the last one. (Two items each, or three preemptions, take hours.)
#[test]
fn two_senders_through_one_room_deliver_every_item_once_in_order() {
    const SENT: [usize; 2] = [2, 1];
    model(2, || {
        let (tx, mut rx) = channel::<(usize, usize)>(1);
        let senders: Vec<_> = (0..2)
            .map(|who| {
                let tx = tx.clone();
                thread::spawn(move || {
                    block_on(async {
                        for seq in 0..SENT[who] {
                            tx.send((who, seq)).await.expect("the receiver is there");
                        }
                    })
                })
            })
            .collect();
        drop(tx);
        let mut next = [0; 2];
        while let Some((who, seq)) = block_on(rx.recv()) {
            assert_eq!(seq, next[who], "sender {who}'s items in order, once");
            next[who] += 1;
        }
        assert_eq!(next, SENT, "every item received");
        for sender in senders {
            sender.join().expect("no panic");
        }
    });
}

/// The one room is held by a permit; a sender waits for it while the
/// permit is dropped unused and a third task's reserve is cancelled
/// (after one poll, which may have taken the room: its permit is then
/// dropped unused too). The waiting sender always gets the room.
#[test]
fn a_room_given_back_or_a_cancelled_reserve_never_strands_a_waiting_sender() {
    model(3, || {
        let (tx, mut rx) = channel::<u32>(1);
        let permit = tx.clone().try_reserve_owned().expect("the one room");
        assert!(matches!(tx.try_send(0), Err(TrySendError::Full(0))));
        let holder = thread::spawn(move || drop(permit));
        let canceller = {
            let tx = tx.clone();
            thread::spawn(move || {
                block_on(async {
                    let mut reserve = pin!(tx.reserve());
                    poll_fn(|cx| {
                        // Ready or not, the reserve is dropped after this
                        // one poll (a permit it gave, unused).
                        let _ = reserve.as_mut().poll(cx);
                        Poll::Ready(())
                    })
                    .await;
                })
            })
        };
        let waiter = {
            let tx = tx.clone();
            thread::spawn(move || block_on(tx.send(7)).expect("the receiver is there"))
        };
        for thread in [holder, canceller, waiter] {
            thread.join().expect("no panic");
        }
        assert_eq!(rx.try_recv(), Some(7));
        assert_eq!(rx.try_recv(), None);
        assert_eq!(tx.capacity(), 1, "every room given back");
    });
}

/// The queue is full; one sender waits to send, another holds a permit
/// and sends through it, while the receiver takes one item and goes.
/// Nothing hangs, the senders then see it closed, and every item is
/// dropped by then: taken, given back in the error, or dropped with the
/// receiver (none kept by the queue).
#[test]
fn a_receiver_gone_closes_the_queue_for_waiting_senders_and_drops_its_items() {
    model(3, || {
        let drops = Arc::new(AtomicUsize::new(0));
        let item = || Counted(Arc::clone(&drops));
        let (tx, mut rx) = channel::<Counted>(1);
        tx.try_send(item()).ok().expect("the one room");
        let waiter = {
            let (tx, item) = (tx.clone(), item());
            thread::spawn(move || {
                if let Err(SendError(item)) = block_on(tx.send(item)) {
                    drop(item);
                }
            })
        };
        let reserver = {
            let (tx, item) = (tx.clone(), item());
            thread::spawn(move || {
                if let Ok(permit) = block_on(tx.reserve()) {
                    permit.send(item);
                }
            })
        };
        let receiver = thread::spawn(move || {
            drop(rx.try_recv());
            drop(rx);
        });
        for thread in [waiter, reserver, receiver] {
            thread.join().expect("no panic");
        }
        assert!(tx.is_closed());
        assert!(matches!(tx.try_send(item()), Err(TrySendError::Closed(_))));
        assert!(block_on(tx.reserve()).is_err());
        assert_eq!(drops.load(Ordering::Relaxed), 4, "no item kept");
        assert_eq!(tx.capacity(), 1, "no room kept by a permit");
    });
}

/// The receiver waits while the last senders go: one sends and goes, and
/// a weak sender upgraded (if a sender is still there) sends and goes.
/// The receiver gets the items sent, then the end.
#[test]
fn the_last_sender_gone_wakes_the_receiver_after_the_items() {
    model(3, || {
        let (tx, mut rx) = channel::<u32>(2);
        let weak = tx.downgrade();
        let sender = thread::spawn(move || tx.try_send(1).expect("room"));
        let upgrader = thread::spawn(move || match weak.upgrade() {
            Some(tx) => {
                tx.try_send(2).expect("room");
                1
            }
            None => 0,
        });
        let mut received = Vec::new();
        while let Some(item) = block_on(rx.recv()) {
            received.push(item);
        }
        let upgraded = upgrader.join().expect("no panic");
        sender.join().expect("no panic");
        received.sort_unstable();
        assert_eq!(received, [[1].as_slice(), &[1, 2]][upgraded]);
    });
}

/// The receiver gives its room back while a sender sends: the item is not
/// lost, and the receiver gets it, then the end.
#[test]
fn giving_the_room_back_racing_a_send_keeps_the_item() {
    model(3, || {
        let (tx, mut rx) = channel::<u32>(1);
        tx.try_send(0).expect("room");
        assert_eq!(rx.try_recv(), Some(0));
        let sender = thread::spawn(move || tx.try_send(1).expect("room"));
        rx.release_room();
        assert_eq!(block_on(rx.recv()), Some(1));
        assert_eq!(block_on(rx.recv()), None);
        sender.join().expect("no panic");
    });
}

/// The queue is full and two senders wait for its one room, the first in
/// line to send 1, the second (which begins waiting after it) 2, while
/// the receiver takes the item that filled it and then the two: the first
/// in line always sends first, whatever order they are woken and run in.
#[test]
fn waiting_senders_send_in_the_order_they_began_to_wait() {
    model(2, || {
        let (tx, mut rx) = channel::<u32>(1);
        tx.try_send(0).expect("the one room");
        let mut first = Box::pin(tx.send(1));
        // Polled once here, before the second sender exists: it is first
        // in line (the waker is replaced when it is polled again below).
        let mut cx = std::task::Context::from_waker(std::task::Waker::noop());
        assert!(first.as_mut().poll(&mut cx).is_pending());
        let second = {
            let tx = tx.clone();
            thread::spawn(move || block_on(tx.send(2)).expect("the receiver is there"))
        };
        let receiver = thread::spawn(move || {
            let mut received = Vec::new();
            for _ in 0..3 {
                received.push(block_on(rx.recv()).expect("an item"));
            }
            received
        });
        block_on(first).expect("the receiver is there");
        second.join().expect("no panic");
        assert_eq!(receiver.join().expect("no panic"), [0, 1, 2]);
    });
}

/// The queue is full and two senders wait for its one room: one gives up
/// after its first poll (it may have been first in line, and given the
/// room by then), the other waits to send, while the receiver takes the
/// item that filled it. The room always reaches the sender that stays: a
/// wait given up passes on the room it was given.
#[test]
fn a_sender_giving_up_passes_the_room_it_was_given_to_the_next_in_line() {
    model(3, || {
        let (tx, mut rx) = channel::<u32>(1);
        tx.try_send(0).expect("the one room");
        let canceller = {
            let tx = tx.clone();
            thread::spawn(move || {
                block_on(async {
                    let mut reserve = pin!(tx.reserve());
                    poll_fn(|cx| {
                        // Ready or not, the reserve is dropped after this
                        // one poll (a permit it gave, unused).
                        let _ = reserve.as_mut().poll(cx);
                        Poll::Ready(())
                    })
                    .await;
                })
            })
        };
        let waiter = {
            let tx = tx.clone();
            thread::spawn(move || block_on(tx.send(7)).expect("the receiver is there"))
        };
        assert_eq!(rx.try_recv(), Some(0));
        assert_eq!(block_on(rx.recv()), Some(7));
        for thread in [canceller, waiter] {
            thread.join().expect("no panic");
        }
        assert_eq!(rx.try_recv(), None);
        assert_eq!(tx.capacity(), 1, "every room given back");
    });
}
