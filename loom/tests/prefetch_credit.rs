//! Loom model of the prefetch credit (the broker's own code, compiled
//! against loom's atomics): each thread is a queue dispatching to a consumer
//! of the same channel, or a channel settling a delivery.
#![cfg(loom)]

#[path = "../../broker/src/consumer/credit.rs"]
mod credit;

use loom::sync::atomic::{AtomicU32, Ordering};
use loom::sync::Arc;
use loom::thread;

/// Two queues, one unit of the channel's global prefetch left: exactly one
/// of them gets it, whatever the interleaving.
#[test]
fn two_queues_never_share_the_last_unit_of_global_prefetch() {
    loom::model(|| {
        let channel = Arc::new(AtomicU32::new(0));
        let queues: Vec<_> = (0..2)
            .map(|_| {
                let channel = Arc::clone(&channel);
                thread::spawn(move || {
                    let own = AtomicU32::new(0);
                    let taken = credit::try_take_both(&own, 0, &channel, 1);
                    assert_eq!(own.load(Ordering::Relaxed), u32::from(taken));
                    taken
                })
            })
            .collect();
        let taken = queues
            .into_iter()
            .map(|q| q.join().expect("no panic"))
            .filter(|&taken| taken)
            .count();
        assert_eq!(taken, 1);
        assert_eq!(channel.load(Ordering::Relaxed), 1);
    });
}

/// Consumer `a` holds the channel's only unit (limit 1); `a`'s delivery is
/// settled while `a`'s queue and `b`'s queue both try to deliver. The
/// channel's count always equals the units the consumers hold, never goes
/// past the limit, and never below zero (a give-back without a take would
/// wrap it).
#[test]
fn a_settle_racing_two_takes_keeps_every_count_exact() {
    loom::model(|| {
        let channel = Arc::new(AtomicU32::new(1));
        let own_a = Arc::new(AtomicU32::new(1));
        let own_b = Arc::new(AtomicU32::new(0));

        let settle = {
            let (channel, own_a) = (Arc::clone(&channel), Arc::clone(&own_a));
            thread::spawn(move || {
                credit::give_back(&own_a);
                credit::give_back(&channel);
            })
        };
        let queue_a = {
            let (channel, own_a) = (Arc::clone(&channel), Arc::clone(&own_a));
            thread::spawn(move || credit::try_take_both(&own_a, 1, &channel, 1))
        };
        let took_b = credit::try_take_both(&own_b, 1, &channel, 1);
        settle.join().expect("no panic");
        let took_a = queue_a.join().expect("no panic");

        let (a, b, total) = (
            own_a.load(Ordering::Relaxed),
            own_b.load(Ordering::Relaxed),
            channel.load(Ordering::Relaxed),
        );
        assert_eq!((a, b), (u32::from(took_a), u32::from(took_b)));
        assert_eq!(total, a + b);
        assert!(total <= 1, "{total} units out, limit 1");
    });
}
