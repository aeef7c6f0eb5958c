//! Prefetch credit as one atomic step: a counter of unacked deliveries is
//! checked against its limit and incremented in a single compare-exchange,
//! so two queues dispatching on two threads can never both take the last
//! unit of a channel's shared (`global`) prefetch.
//!
//! This module owns only the counting; it uses nothing but atomics, so the
//! `leveret-loom` crate compiles this very file against loom's atomics and
//! explores every interleaving of it (see that crate's tests).

#[cfg(loom)]
use loom::sync::atomic::{AtomicU32, Ordering};
#[cfg(not(loom))]
use std::sync::atomic::{AtomicU32, Ordering};

/// Counts one more unacked delivery in `in_flight` if that keeps it within
/// `limit` (0 means unlimited, as in basic.qos); false, and nothing
/// counted, if the limit is reached. The check and the increment are one
/// atomic step.
pub fn try_take(in_flight: &AtomicU32, limit: u32) -> bool {
    // Relaxed is enough: the counter publishes no other data, and the
    // read-modify-write alone makes check and increment indivisible.
    in_flight
        .fetch_update(Ordering::Relaxed, Ordering::Relaxed, |n| {
            (limit == 0 || n < limit).then_some(n + 1)
        })
        .is_ok()
}

/// Gives back one unit counted by [`try_take`] or [`try_take_both`].
pub fn give_back(in_flight: &AtomicU32) {
    in_flight.fetch_sub(1, Ordering::Relaxed);
}

/// Takes one unit of a consumer's own credit and one of its channel's
/// shared credit, or of neither: RabbitMQ's basic.qos with `global=false`
/// limits each consumer, with `global=true` the channel as a whole, and a
/// delivery must fit both.
///
/// The consumer's own counter is only ever incremented by its queue's
/// dispatch, which holds the queue's lock; the channel's counter is shared
/// by every queue the channel consumes from, so it is taken second and the
/// own unit is given back if it is refused.
pub fn try_take_both(
    own: &AtomicU32,
    own_limit: u32,
    channel: &AtomicU32,
    channel_limit: u32,
) -> bool {
    if !try_take(own, own_limit) {
        return false;
    }
    if try_take(channel, channel_limit) {
        return true;
    }
    give_back(own);
    false
}

#[cfg(all(test, not(loom)))]
mod tests {
    use super::*;
    use std::sync::{Arc, Barrier};

    #[test]
    fn zero_is_unlimited_and_a_limit_is_a_ceiling() {
        let unlimited = AtomicU32::new(0);
        assert!((0..1000).all(|_| try_take(&unlimited, 0)));
        let limited = AtomicU32::new(0);
        assert!(try_take(&limited, 2) && try_take(&limited, 2));
        assert!(!try_take(&limited, 2));
        give_back(&limited);
        assert!(try_take(&limited, 2));
        // A limit lowered below what is in flight (basic.qos again) gives
        // nothing until enough is settled.
        assert!(!try_take(&limited, 1));
    }

    #[test]
    fn a_refused_channel_unit_leaves_the_own_count_unchanged() {
        let own = AtomicU32::new(0);
        let channel = AtomicU32::new(3);
        assert!(!try_take_both(&own, 10, &channel, 3));
        assert_eq!(own.load(Ordering::Relaxed), 0);
        assert!(!try_take_both(&own, 0, &channel, 3));
        assert_eq!(own.load(Ordering::Relaxed), 0);
        assert!(try_take_both(&own, 1, &channel, 0));
        assert!(!try_take_both(&own, 1, &channel, 0));
        assert_eq!(
            (own.load(Ordering::Relaxed), channel.load(Ordering::Relaxed)),
            (1, 4)
        );
    }

    /// Many threads (queues) race for a channel's shared credit, each with
    /// its own consumer counter: no more than the limit is ever handed out
    /// at once. (The loom model in `leveret-loom` checks every interleaving
    /// of the same code; this is its plain-thread counterpart.)
    #[test]
    fn racing_threads_never_take_more_than_the_channel_limit() {
        const THREADS: usize = 8;
        const LIMIT: u32 = 3;
        const ROUNDS: usize = 2000;
        let channel = Arc::new(AtomicU32::new(0));
        let holders = Arc::new(AtomicU32::new(0));
        let start = Arc::new(Barrier::new(THREADS));
        let threads: Vec<_> = (0..THREADS)
            .map(|_| {
                let (channel, holders, start) = (
                    Arc::clone(&channel),
                    Arc::clone(&holders),
                    Arc::clone(&start),
                );
                std::thread::spawn(move || {
                    let own = AtomicU32::new(0);
                    start.wait();
                    let mut most = 0;
                    for _ in 0..ROUNDS {
                        if try_take_both(&own, 2, &channel, LIMIT) {
                            most = most.max(holders.fetch_add(1, Ordering::SeqCst) + 1);
                            holders.fetch_sub(1, Ordering::SeqCst);
                            give_back(&own);
                            give_back(&channel);
                        }
                    }
                    most
                })
            })
            .collect();
        for thread in threads {
            let most = thread.join().expect("no panic");
            assert!(most <= LIMIT, "{most} deliveries in flight, limit {LIMIT}");
        }
        assert_eq!(channel.load(Ordering::Relaxed), 0);
    }
}
