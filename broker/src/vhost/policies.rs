//! A vhost's policies: the set in force, what applies to a queue or an
//! exchange being declared, and a change carried to every existing queue
//! and exchange at once (dead letters a shorter `max-length` makes are
//! routed here). A change replaces the whole set behind one pointer;
//! declares compare the pointer after they insert, so an object declared
//! while a change is carried out ends with the new set either way.

use super::{read, write, Vhost};
use crate::exchange::Exchange;
use crate::policy::{Applied, ObjectKind, PolicyKind, VhostPolicies};
use crate::queue::Queue;
use crate::slice::Progress;
use std::sync::Arc;

impl Vhost {
    /// The policies in force.
    pub fn policies(&self) -> Arc<VhostPolicies> {
        Arc::clone(&read(&self.policies))
    }

    /// The policies in force and what they apply to the object `name`.
    pub(super) fn policies_for(
        &self,
        object: ObjectKind,
        name: &[u8],
    ) -> (Arc<VhostPolicies>, Applied) {
        let policies = self.policies();
        let applied = policies.applied(object, name);
        (policies, applied)
    }

    /// After a queue made with `seen` is registered: if the set changed
    /// meanwhile, the queue takes the new one (the change's own pass may
    /// have run before the queue was registered).
    pub(super) fn catch_up_queue(self: &Vhost, queue: &Arc<Queue>, seen: &Arc<VhostPolicies>) {
        let mut seen = Arc::clone(seen);
        loop {
            let now = self.policies();
            if Arc::ptr_eq(&now, &seen) {
                return;
            }
            self.give_new_queue(
                queue,
                now.applied(queue.policy_object(), queue.name.as_bytes()),
            );
            seen = now;
        }
    }

    /// Gives a queue just declared (so far empty: no length limit pushes
    /// anything out, and a message that came since waits for the sweep)
    /// the policies `applied`.
    pub(super) fn give_new_queue(&self, queue: &Queue, applied: Applied) {
        let (dead, _done_in_one_step) = queue.apply_policies(applied);
        queue.defer(dead);
    }

    /// Gives `queue` the policies `applied`, routing what a lower length
    /// limit pushes out, a step at a time.
    fn apply_queue_policies(self: &Arc<Self>, queue: &Queue, applied: Applied) {
        let (mut dead, mut progress) = queue.apply_policies(applied);
        loop {
            self.dead_letter(dead);
            if progress == Progress::Done {
                return;
            }
            (dead, progress) = queue.shorten_step();
        }
    }

    /// Gives a registered exchange the policy that applies to it, until
    /// the set it read is still the set in force.
    pub(super) fn apply_exchange_policies(&self, exchange: &Exchange) {
        loop {
            let policies = self.policies();
            exchange
                .apply_policies(policies.applied(ObjectKind::Exchange, exchange.name.as_bytes()));
            if Arc::ptr_eq(&policies, &self.policies()) {
                return;
            }
        }
    }

    /// Puts `next` in force and applies it to every queue and exchange:
    /// work that grows with them, so callers run it off the broker's
    /// threads (`Admin` does, on a blocking thread). When `next` differs
    /// from the set in force by one policy (`changed`: its kind and name)
    /// each object costs one match of that policy, and a full look-up only
    /// where it was the one applied ([`VhostPolicies::after_change`]);
    /// otherwise (a batch, [`VhostPolicies::with_all`]) one full look-up,
    /// which the prefix index keeps to a handful of matches.
    pub fn set_policies(
        self: &Arc<Self>,
        next: VhostPolicies,
        changed: Option<(PolicyKind, &str)>,
    ) {
        let next = Arc::new(next);
        *write(&self.policies) = Arc::clone(&next);
        let applied = |current: &Applied, object: ObjectKind, name: &[u8]| match changed {
            Some((kind, policy)) => next.after_change(current, kind, policy, object, name),
            None => next.applied(object, name),
        };
        for exchange in self.exchanges() {
            exchange.apply_policies(applied(
                &exchange.policies(),
                ObjectKind::Exchange,
                exchange.name.as_bytes(),
            ));
        }
        for queue in self.queues() {
            let policies = applied(
                &queue.policies(),
                queue.policy_object(),
                queue.name.as_bytes(),
            );
            self.apply_queue_policies(&queue, policies);
        }
    }
}
