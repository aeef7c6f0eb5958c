//! A queue's consumers and the choice of the next one to deliver to:
//! every consumer in registration order, the same consumers grouped by
//! `x-priority` (highest group first, each with its round-robin cursor),
//! and, on a queue with `x-single-active-consumer`, the one that is active.
//!
//! RabbitMQ's semantics: a higher-priority consumer gets messages while it
//! has credit (prefetch room); lower ones get them only when every higher
//! one is blocked; equal ones take turns. With a single active consumer
//! only that one gets messages; when it goes, the waiting consumer with
//! the highest priority, registered earliest, takes over, and gets its
//! first message once the one before holds none unacked (acked, or
//! requeued when its channel closes: those then come first, in order), so
//! that two consumers never work on the queue at once.
//!
//! Cost: choosing looks at groups from the highest down and stops at the
//! first consumer with credit. Groups found wholly blocked are skipped
//! until credit may have come back ([`Consumers::reopen`], called by every
//! dispatch except the one a publish makes: a publish frees no credit), so
//! many consumers with distinct priorities, all blocked, cost one look
//! each per burst of credit, not one per message. (Consumers on channels
//! with a `global` prefetch, shared with other queues, are looked at every
//! time, as before.)

use super::Consumer;
use std::sync::atomic::Ordering;
use std::sync::Arc;

/// One priority's consumers.
#[derive(Debug)]
struct Group {
    priority: i64,
    members: Vec<Arc<Consumer>>,
    /// The member to try first (round-robin among equals).
    cursor: usize,
}

/// Where the consumer [`Consumers::pick`] chose sits.
#[derive(Debug, Clone, Copy)]
pub(super) struct Slot {
    group: usize,
    member: usize,
    /// Its index among all consumers, for marking it out of room.
    pub flat: usize,
}

/// A queue's consumers.
#[derive(Debug, Default)]
pub(super) struct Consumers {
    /// Every consumer, in registration order.
    registered: Vec<Arc<Consumer>>,
    /// By priority, highest first.
    groups: Vec<Group>,
    /// Each group's first consumer's index among all (`Slot::flat`).
    offsets: Vec<usize>,
    /// Groups before this one were found blocked since credit last came
    /// back.
    first_open: usize,
    /// `x-single-active-consumer`.
    single_active: bool,
    /// The active consumer of a single-active-consumer queue.
    active: Option<Arc<Consumer>>,
    /// The active consumer before it, gone (cancelled, its channel closed)
    /// while it held unacked messages: the active one waits until it holds
    /// none.
    previous: Option<Arc<Consumer>>,
    /// Consumers looked at by [`Consumers::pick`], for the tests that
    /// bound its cost.
    #[cfg(test)]
    pub examined: u64,
}

impl Consumers {
    /// No consumers yet; `single_active` for `x-single-active-consumer`.
    pub fn new(single_active: bool) -> Self {
        Consumers {
            single_active,
            ..Consumers::default()
        }
    }

    /// How many.
    pub fn len(&self) -> usize {
        self.registered.len()
    }

    /// Whether there are none.
    pub fn is_empty(&self) -> bool {
        self.registered.is_empty()
    }

    /// Adds one (the last registered); on a single-active-consumer queue
    /// with none active, it becomes the active one.
    pub fn add(&mut self, consumer: Arc<Consumer>) {
        if self.single_active && self.active.is_none() {
            self.active = Some(Arc::clone(&consumer));
        }
        let at = self
            .groups
            .partition_point(|g| g.priority > consumer.priority);
        match self.groups.get_mut(at) {
            Some(group) if group.priority == consumer.priority => {
                group.members.push(Arc::clone(&consumer))
            }
            _ => self.groups.insert(
                at,
                Group {
                    priority: consumer.priority,
                    members: vec![Arc::clone(&consumer)],
                    cursor: 0,
                },
            ),
        }
        self.registered.push(consumer);
        self.regrouped();
    }

    /// Removes one; None if it was not there, else whether another
    /// consumer became the active one (it was the active consumer of a
    /// single-active-consumer queue and others wait).
    pub fn remove(&mut self, consumer: &Arc<Consumer>) -> Option<bool> {
        let index = self
            .registered
            .iter()
            .position(|c| Arc::ptr_eq(c, consumer))?;
        self.registered.remove(index);
        if let Some(g) = self
            .groups
            .iter()
            .position(|g| g.priority == consumer.priority)
        {
            let group = &mut self.groups[g];
            if let Some(m) = group.members.iter().position(|c| Arc::ptr_eq(c, consumer)) {
                group.members.remove(m);
                if m < group.cursor {
                    group.cursor -= 1;
                }
            }
            if group.members.is_empty() {
                self.groups.remove(g);
            } else if group.cursor >= group.members.len() {
                group.cursor = 0;
            }
        }
        self.regrouped();
        let was_active = self
            .active
            .as_ref()
            .is_some_and(|active| Arc::ptr_eq(active, consumer));
        if !was_active {
            return Some(false);
        }
        if consumer.in_flight.load(Ordering::Relaxed) > 0 {
            self.previous = Some(Arc::clone(consumer));
        }
        // The highest priority waiting, registered earliest.
        self.active = self
            .groups
            .first()
            .and_then(|top| self.registered.iter().find(|c| c.priority == top.priority))
            .cloned();
        Some(self.active.is_some())
    }

    fn regrouped(&mut self) {
        self.offsets.clear();
        let mut offset = 0;
        for group in &self.groups {
            self.offsets.push(offset);
            offset += group.members.len();
        }
        self.first_open = 0;
    }

    /// Takes every consumer (the queue is deleted).
    pub fn take_all(&mut self) -> Vec<Arc<Consumer>> {
        self.groups.clear();
        self.offsets.clear();
        self.active = None;
        self.previous = None;
        self.first_open = 0;
        std::mem::take(&mut self.registered)
    }

    /// Every consumer in registration order, with whether it is active
    /// (RabbitMQ's `active`: every consumer of a queue without a single
    /// active consumer is).
    pub fn snapshot(&self) -> Vec<(Arc<Consumer>, bool)> {
        self.registered
            .iter()
            .map(|c| (Arc::clone(c), self.is_active(c)))
            .collect()
    }

    /// Whether `consumer` may get messages now as far as the queue is
    /// concerned (its credit aside).
    pub fn is_active(&self, consumer: &Arc<Consumer>) -> bool {
        !self.single_active
            || self
                .active
                .as_ref()
                .is_some_and(|active| Arc::ptr_eq(active, consumer))
    }

    /// Credit may have come back (an ack, a qos, a new or activated
    /// consumer, room in a writer): look at every group again.
    pub fn reopen(&mut self) {
        self.first_open = 0;
    }

    /// The consumer to deliver to next: the active one of a
    /// single-active-consumer queue if it has credit (and the one before
    /// it holds nothing unacked); otherwise the first
    /// with credit in the highest group that has one, from that group's
    /// cursor. `full` marks consumers (by [`Slot::flat`]) whose writer had
    /// no room in this dispatch.
    pub fn pick(&mut self, full: &[bool]) -> Option<(Slot, Arc<Consumer>)> {
        let is_full = |flat: usize| full.get(flat).copied().unwrap_or(false);
        if self.single_active {
            self.active.as_ref()?;
            self.count_examined();
            if let Some(previous) = &self.previous {
                if previous.in_flight.load(Ordering::Relaxed) > 0 {
                    return None;
                }
                self.previous = None;
            }
            let active = self.active.as_ref()?;
            let slot = Slot {
                group: usize::MAX,
                member: 0,
                flat: 0,
            };
            return (!is_full(0) && active.has_credit()).then(|| (slot, Arc::clone(active)));
        }
        // Groups found blocked extend the skipped prefix only while each of
        // their consumers is blocked by what only a dispatch of this queue
        // lifts (its own prefetch, its activation). A channel's `global`
        // prefetch is shared with other queues, whose dispatch may take a
        // unit and give it back, or whose ack may free one, without
        // dispatching this one: those groups are looked at every time.
        let mut prefix = true;
        for g in self.first_open..self.groups.len() {
            let count = self.groups[g].members.len();
            let mut memoable = true;
            for k in 0..count {
                let member = (self.groups[g].cursor + k) % count;
                let flat = self.offsets[g] + member;
                self.count_examined();
                let consumer = &self.groups[g].members[member];
                if !is_full(flat) && consumer.has_credit() {
                    return Some((
                        Slot {
                            group: g,
                            member,
                            flat,
                        },
                        Arc::clone(consumer),
                    ));
                }
                memoable &= consumer.channel.global_prefetch.load(Ordering::Relaxed) == 0;
            }
            prefix &= memoable;
            if prefix {
                self.first_open = g + 1;
            }
        }
        None
    }

    /// A delivery went to the consumer at `slot`: the next one of its
    /// group goes first next time.
    pub fn delivered(&mut self, slot: Slot) {
        if let Some(group) = self.groups.get_mut(slot.group) {
            group.cursor = (slot.member + 1) % group.members.len();
        }
    }

    #[cfg(test)]
    fn count_examined(&mut self) {
        self.examined += 1;
    }

    #[cfg(not(test))]
    fn count_examined(&mut self) {}
}
