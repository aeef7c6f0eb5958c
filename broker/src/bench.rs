//! What the contention bench (`broker/benches/contention.rs`) drives, with
//! the feature `bench-internals` only; not an API. It owns nothing: it
//! wraps the unit tests' harness (`testkit`: a vhost driven by direct
//! calls, a channel without a client) in types that keep the broker's
//! internal types out of sight.

use crate::testkit::{message, s, FakeChannel, Harness};
use leveret_protocol::BasicProperties;
use std::sync::Arc;

/// A vhost without storage, its queues reached by name.
pub struct Queues {
    harness: Harness,
}

impl Default for Queues {
    fn default() -> Self {
        Queues {
            harness: Harness::new(),
        }
    }
}

impl Queues {
    /// Declares a transient queue `name`.
    pub fn declare(&self, name: &str) {
        self.harness.queue(name, &[]);
    }

    /// Looks `name` up in the vhost's registry, as a publish to a name the
    /// channel has not remembered does; whether it exists.
    pub fn lookup(&self, name: &str) -> bool {
        self.harness.vhost.queue(&s(name)).is_some()
    }

    /// A channel on a connection of its own, for [`Queues::publish_and_get`].
    pub fn channel(&self) -> Getter {
        Getter(self.harness.channel())
    }

    /// Publishes a 16-byte message to queue `name` and takes one back with
    /// basic.get (no-ack) on `getter`, `times` times: two turns of the
    /// queue's lock each. On a queue other threads use too, another may
    /// have taken it first. The message is one per call, so its count is
    /// this thread's line, not a line every thread writes.
    pub fn publish_and_get(&self, name: &str, getter: &mut Getter, times: u64) {
        let queue = self.harness.vhost.queue(&s(name)).expect("declared");
        let body = message(
            &s(""),
            name,
            "16 bytes of body",
            &BasicProperties::default(),
        );
        for _ in 0..times {
            let (_, dead) = queue.publish(Arc::clone(&body));
            self.harness.vhost.dead_letter(dead);
            if getter.0.get(&queue, true) {
                getter.0.discard();
            }
        }
    }

    /// Empties every queue.
    pub fn purge(&self) {
        for queue in self.harness.vhost.queues() {
            queue.purge();
        }
    }
}

/// A channel that takes messages with basic.get.
pub struct Getter(FakeChannel);
