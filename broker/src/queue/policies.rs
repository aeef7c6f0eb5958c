//! A queue's policies: the pair that applies ([`Applied`]) and the
//! arguments it acts on as a result, changed at once when a policy
//! changes, as RabbitMQ does: a new `max-length` shortens the queue now
//! (dropping or dead-lettering its head under `drop-head`, in steps of
//! [`DEAD_LETTERS_PER_STEP`] so that neither the queue's lock nor the dead
//! letters waiting to be routed grow with the queue); a new `message-ttl`
//! applies to messages published from then on (each message's expiry is
//! fixed when it arrives, in RabbitMQ too).

use super::{DeadLetters, Queue, DEAD_LETTERS_PER_STEP};
use crate::policy::{stricter, Applied, ObjectKind};
use crate::slice::Progress;
use leveret_protocol::FieldTable;

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
        let mut effective = self.args.with_policies(&self.options.arguments, &applied);
        effective.expires = stricter(applied.expires(), st.own_expires);
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

    /// The queue's arguments as they stand: as declared, or with the
    /// `x-expires` set since ([`Queue::set_expires`]).
    pub fn arguments(&self) -> FieldTable {
        match &self.lock().changed_arguments {
            Some(changed) => changed.clone(),
            None => self.options.arguments.clone(),
        }
    }

    /// Gives the queue its own expiry `expires` (`x-expires` in ms; `None`
    /// for none) in place of the declared one, as if it had been declared
    /// so: acted on at once (the stricter of it and a policy's), listed in
    /// its arguments, and for a durable queue stored (its record
    /// rewritten), so a restart keeps it. The idle time already counted
    /// stays. The MQTT front end's: a session's expiry changes with a
    /// DISCONNECT or a later CONNECT. False for a stream (no expiry) or a
    /// deleted queue; the caller makes sure a deletion is not under way
    /// (`Vhost::set_queue_expires`). With `mark`, that argument is set to
    /// `true` too (the MQTT mark of a session's queue, which it adopts).
    #[cfg(feature = "mqtt")]
    pub fn set_expires(&self, expires: Option<u64>, mark: Option<&'static str>) -> bool {
        use crate::store::{QueueRecord, StoreOp};
        use leveret_protocol::{FieldValue, ShortStr};
        if self.stream.is_some() {
            return false;
        }
        let mut st = self.lock();
        if st.deleted {
            return false;
        }
        let mut arguments = match st.changed_arguments.take() {
            Some(changed) => changed,
            None => self.options.arguments.clone(),
        };
        match expires {
            Some(ms) => {
                let ms = i64::try_from(ms).unwrap_or(i64::MAX);
                arguments.insert(ShortStr::from_static("x-expires"), FieldValue::I64(ms));
            }
            None => {
                arguments.remove("x-expires");
            }
        }
        if let Some(mark) = mark {
            arguments.insert(ShortStr::from_static(mark), FieldValue::Bool(true));
        }
        st.own_expires = expires;
        st.effective.expires = stricter(st.applied.expires(), expires);
        if let Some((persistence, id)) = &self.durable_store {
            // Under the queue's lock: two changes reach the store in order.
            persistence.submit(vec![StoreOp::PutQueue(QueueRecord {
                vhost: self.vhost.clone(),
                name: self.name.clone(),
                id: *id,
                auto_delete: self.options.auto_delete,
                arguments: arguments.clone(),
            })]);
        }
        st.changed_arguments = Some(arguments);
        true
    }
}
