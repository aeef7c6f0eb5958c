//! Loom model of the delivery-tag handover, isolated from the broker: two
//! queues deliver to one channel at once. Each takes the channel's next
//! delivery tag (under the channel's delivery lock) and puts the delivery in
//! the connection's outbox (a FIFO the writer drains in order). The client
//! must read the tags in increasing order: a multiple-ack of a tag it has
//! seen would otherwise settle one it has not.
#![cfg(loom)]

use loom::sync::{Arc, Mutex};
use loom::thread;
use std::collections::VecDeque;

/// The channel's delivery bookkeeping and its connection's outbox.
#[derive(Default)]
struct Channel {
    last_tag: Mutex<u64>,
    outbox: Mutex<VecDeque<u64>>,
}

impl Channel {
    /// The handover the broker uses: the tag is taken and the delivery
    /// queued while the delivery lock is held.
    fn deliver_under_one_lock(&self) {
        let mut last_tag = self.last_tag.lock().expect("not poisoned");
        *last_tag += 1;
        self.outbox
            .lock()
            .expect("not poisoned")
            .push_back(*last_tag);
    }

    /// The handover the broker had: the tag taken under the lock, the
    /// delivery queued after releasing it.
    fn deliver_after_the_lock(&self) {
        let tag = {
            let mut last_tag = self.last_tag.lock().expect("not poisoned");
            *last_tag += 1;
            *last_tag
        };
        self.outbox.lock().expect("not poisoned").push_back(tag);
    }
}

/// Two queues deliver at once with `deliver`; the writer then sends the
/// outbox in order. Panics if the client would read a tag out of order.
fn two_queues_deliver(deliver: fn(&Channel)) {
    loom::model(move || {
        let channel = Arc::new(Channel::default());
        let other_queue = {
            let channel = Arc::clone(&channel);
            thread::spawn(move || deliver(&channel))
        };
        deliver(&channel);
        other_queue.join().expect("no panic");
        let sent: Vec<u64> = channel
            .outbox
            .lock()
            .expect("not poisoned")
            .iter()
            .copied()
            .collect();
        assert_eq!(sent, [1, 2], "tags reach the client in order");
    });
}

#[test]
fn tags_taken_and_queued_under_one_lock_reach_the_client_in_order() {
    two_queues_deliver(Channel::deliver_under_one_lock);
}

/// The model is sensitive: with the queueing outside the lock, loom finds
/// the interleaving where tag 2 overtakes tag 1.
#[test]
#[should_panic(expected = "tags reach the client in order")]
fn tags_queued_after_the_lock_can_overtake_each_other() {
    two_queues_deliver(Channel::deliver_after_the_lock);
}
