//! A queue's policies: the pair that applies ([`Applied`]) and the
//! arguments it acts on as a result, changed at once when a policy
//! changes, as RabbitMQ does: a new `max-length` shortens the queue now
//! (dropping or dead-lettering its head under `drop-head`, in steps of
//! [`DEAD_LETTERS_PER_STEP`] so that neither the queue's lock nor the dead
//! letters waiting to be routed grow with the queue); a new `message-ttl`
//! applies to messages published from then on (each message's expiry is
//! fixed when it arrives, in RabbitMQ too).

use super::{DeadLetters, Queue, DEAD_LETTERS_PER_STEP};
use crate::policy::{Applied, ObjectKind};
use crate::slice::Progress;

impl Queue {
    /// Makes `applied` the queue's policies; the first messages a lower
    /// length limit pushes out come back as dead letters for the caller to
    /// route, with [`Progress::More`] if [`Queue::shorten_step`] has more.
    pub fn apply_policies(&self, applied: Applied) -> (DeadLetters, Progress) {
        if let Some(stream) = &self.stream {
            // A stream acts on its own keys only (the policies that reach
            // it hold no other: `ObjectKind::Stream`).
            stream.apply_policies(&applied);
            self.lock().applied = applied;
            return (DeadLetters::default(), Progress::Done);
        }
        let mut st = self.lock();
        if st.deleted || st.applied == applied {
            // The same policies, found in a newer set.
            st.applied = applied;
            return (DeadLetters::default(), Progress::Done);
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
        drop(st);
        self.shorten_step()
    }

    /// Drops (or dead-letters) at most [`DEAD_LETTERS_PER_STEP`] head
    /// messages of a queue over its length limits: them, and whether more
    /// are over.
    pub fn shorten_step(&self) -> (DeadLetters, Progress) {
        let mut dead = Vec::new();
        let more = self.drop_over_length(&mut self.lock(), &mut dead, DEAD_LETTERS_PER_STEP);
        let progress = if more { Progress::More } else { Progress::Done };
        (DeadLetters(dead), progress)
    }

    /// What policies are matched against for this queue (a stream's and a
    /// classic queue's differ).
    pub fn policy_object(&self) -> ObjectKind {
        if self.stream.is_some() {
            ObjectKind::Stream
        } else {
            ObjectKind::Queue
        }
    }

    /// The policies that apply to the queue.
    pub fn policies(&self) -> Applied {
        self.lock().applied.clone()
    }
}
