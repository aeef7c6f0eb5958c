//! A queue's policies: the pair that applies ([`Applied`]) and the
//! arguments it acts on as a result, changed at once when a policy
//! changes, as RabbitMQ does: a new `max-length` shortens the queue now
//! (dropping or dead-lettering its head under `drop-head`); a new
//! `message-ttl` applies to messages published from then on (each
//! message's expiry is fixed when it arrives, in RabbitMQ too).

use super::{DeadLetters, Queue};
use crate::policy::Applied;

impl Queue {
    /// Makes `applied` the queue's policies; the messages a lower length
    /// limit pushed out come back as dead letters for the caller to route.
    pub fn apply_policies(&self, applied: Applied) -> DeadLetters {
        let mut dead = Vec::new();
        let mut st = self.lock();
        if st.deleted || st.applied == applied {
            // The same policies, found in a newer set.
            st.applied = applied;
            return DeadLetters::default();
        }
        let effective = self.args.with_policies(&self.options.arguments, &applied);
        *self
            .dead_lettering
            .write()
            .unwrap_or_else(|e| e.into_inner()) = (
            effective.dead_letter_exchange.clone(),
            effective.dead_letter_routing_key.clone(),
        );
        st.effective = effective;
        st.applied = applied;
        self.enforce_max_length(&mut st, &mut dead);
        DeadLetters(dead)
    }

    /// The policies that apply to the queue.
    pub fn policies(&self) -> Applied {
        self.lock().applied.clone()
    }
}
