//! The shared subscriptions (`$share/GROUP/FILTER`) of persistent
//! sessions: part of the session's state (MQTT 5.0, 4.1), kept for its
//! next connection, which joins its groups again without subscribing. With
//! a store they are durable ([`MetaRecord::SharedSubscription`], one record
//! per filter, written when the session subscribes and deleted when it
//! unsubscribes, starts clean, ends with its connection or expires), so
//! this holds across a restart too. They expire with the session: once
//! its connection has ended, its Session Expiry Interval (the latest
//! connection's, a DISCONNECT's included) runs, and a connection after
//! that finds none (as a session's queues expire by `x-expires`); after a
//! restart the interval runs from the restart, as a queue's `x-expires`
//! does, and it is at most the broker's session expiry cap then, written
//! back to the records as it is to the session's queues.
//!
//! A group with a persistent member keeps its queue while no member is
//! connected (MQTT 5.0 4.8.2, as Mosquitto): the queue a persistent member
//! creates is durable, not auto-delete, and its `x-expires` is the
//! longest Session Expiry Interval among the group's persistent members
//! ([`GroupKeep`], none if one never expires), so the core deletes it
//! once the last member's session has expired, across a restart too. When
//! the group loses its last persistent member (UNSUBSCRIBE, clean start, a
//! session that ends with its connection) its `x-expires` becomes 1 ms:
//! it goes as soon as no member consumes it. Every change is applied to
//! the queue in place ([`Shares::apply`], under the lock, from the group's
//! state then); members create the group queue from the group's state
//! under the same lock and join an existing one as it is
//! ([`Shares::declare_queue`]), so one a clean member created is
//! non-durable and auto-delete and stays so until it goes. A joining
//! member holds the queue until its consume arrives ([`QueueJoin`]); only
//! queues members declared (marked [`GROUP_QUEUE_ARGUMENT`]) are given a
//! group's expiry, at start too ([`Shares::reconcile`]).
//!
//! A session's new expiry interval reaches its subscriptions (records,
//! group memberships) in batches ([`Shares::settle_yielding`]), never all
//! under one hold of the lock.
//!
//! Bounded: per session by the session's subscription cap, at most
//! [`MAX_SESSIONS`] sessions hold some (expired ones are swept every
//! second by `super::sweeper`, and when the cap is reached) and at most [`MAX_GROUPS`] groups are kept; past either
//! a session's new shared subscription ends with its connection (logged)
//! and its group is not kept for it.

use super::mapping;
use super::subscriptions::Options;
use crate::core::Core;
use crate::error::{AmqpError, AmqpResult};
use crate::queue::QueueOptions;
use crate::store::{MetaKey, MetaRecord, Persistence, StoreOp};
use crate::vhost::{JoinAttempt, QueueDeclaration, QueueJoin, Vhost};
use leveret_mqtt::QoS;
use leveret_protocol::{FieldTable, FieldValue, ShortStr};
use std::collections::{BTreeMap, HashMap, HashSet};
use std::num::NonZeroU32;
use std::sync::{Arc, Mutex};
use std::time::Instant;

/// Sessions with shared subscriptions kept.
const MAX_SESSIONS: usize = 10_000;
/// Groups kept for persistent members, per broker.
const MAX_GROUPS: usize = 10_000;

/// At most this many expired shared subscriptions are deleted under one
/// hold of the lock (or one session's, up to its subscription cap).
const SWEEP_RECORDS: usize = 256;

/// The argument that marks a queue as a group's, declared by a member
/// ([`Shares::declare_queue`]) with `true`: only such a queue is given
/// its group's expiry ([`Shares::apply`]), never one declared under that
/// name without it (an AMQP client's, unless it copied the mark).
const GROUP_QUEUE_ARGUMENT: &str = crate::arguments::MQTT_SHARED_GROUP;

/// At most this many shared subscriptions of sessions whose expiry
/// changed are moved to it (group and record) under one hold of the lock
/// ([`Shares::settle_batch`]), from at most [`super::SWEEP_BATCH`] sessions.
const SETTLE_RECORDS: usize = 256;

/// At most this many groups' queues are given their expiry under one hold
/// of the lock.
const APPLY_BATCH: usize = 256;

/// The stored Session Expiry Interval of a session that never expires.
const NEVER: u32 = u32::MAX;

/// A session: vhost and client identifier.
type Key = (String, String);

/// A group in a vhost: vhost and `$share/GROUP/FILTER`.
type Group = (String, String);

/// Groups whose persistent members changed (vhost and filter), for
/// [`Shares::apply`] to give their queues what they are kept for now.
pub(super) type Groups = Vec<Group>;

/// How long a group's queue outlives its last consumer.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) enum GroupKeep {
    /// No persistent member: it goes once unused.
    Unkept,
    /// For the longest Session Expiry Interval of its persistent members,
    /// in seconds (`None`: forever).
    Kept(Option<u32>),
}

impl GroupKeep {
    /// The `x-expires` (ms) of the group's durable queue.
    pub(super) fn queue_expires(self) -> Option<u64> {
        match self {
            GroupKeep::Unkept => Some(1),
            GroupKeep::Kept(seconds) => super::expiry::queue_expires(seconds),
        }
    }
}

/// By vhost and client identifier.
#[derive(Debug)]
pub(super) struct Shares {
    state: Mutex<State>,
    persistence: Option<Arc<Persistence>>,
    max_sessions: usize,
    max_groups: usize,
}

#[derive(Debug, Default)]
struct State {
    sessions: HashMap<Key, Held>,
    /// Per group, its persistent members' expiry intervals in seconds
    /// ([`NEVER`] for none) with how many members have each.
    groups: HashMap<Group, BTreeMap<u32, usize>>,
    /// Sessions whose expiry changed with some subscriptions not yet
    /// moved to it ([`Shares::settle_batch`]).
    moving: HashSet<Key>,
}

impl State {
    fn join(&mut self, vhost: &str, filter: &str, expiry: Option<u32>) {
        let group = (vhost.to_owned(), filter.to_owned());
        let members = self.groups.entry(group).or_default();
        *members.entry(expiry.unwrap_or(NEVER)).or_default() += 1;
    }

    fn leave(&mut self, vhost: &str, filter: &str, expiry: Option<u32>) {
        let group = (vhost.to_owned(), filter.to_owned());
        let Some(members) = self.groups.get_mut(&group) else {
            return;
        };
        let seconds = expiry.unwrap_or(NEVER);
        if let Some(count) = members.get_mut(&seconds) {
            *count -= 1;
            if *count == 0 {
                members.remove(&seconds);
            }
        }
        if members.is_empty() {
            self.groups.remove(&group);
        }
    }

    fn group(&self, vhost: &str, filter: &str) -> GroupKeep {
        let group = (vhost.to_owned(), filter.to_owned());
        match self.groups.get(&group).and_then(|m| m.keys().next_back()) {
            None => GroupKeep::Unkept,
            Some(&longest) => GroupKeep::Kept((longest != NEVER).then_some(longest)),
        }
    }

    /// A session's filters leave their groups; the groups changed.
    fn leave_all(&mut self, vhost: &str, held: &Held) -> Groups {
        let filters = held.filters.iter();
        filters.for_each(|(filter, (_, expiry))| self.leave(vhost, filter, *expiry));
        self.groups_of(vhost, held)
    }

    fn groups_of(&self, vhost: &str, held: &Held) -> Groups {
        (held.filters.keys())
            .map(|filter| (vhost.to_owned(), filter.clone()))
            .collect()
    }
}

/// One session's shared subscriptions.
#[derive(Debug, Default)]
struct Held {
    /// Filter → options, and the expiry interval its record and group
    /// membership have: the session's, or an older one until moved
    /// ([`Shares::settle_batch`]).
    filters: BTreeMap<String, (Options, Option<u32>)>,
    /// The session's expiry interval in seconds (`None`: never).
    expiry: Option<u32>,
    /// When they go unless a connection resumes the session first
    /// (`None` while it is connected, or if it never expires).
    expires_at: Option<Instant>,
}

impl Held {
    fn expired(&self, now: Instant) -> bool {
        super::expiry::has_passed(self.expires_at, now)
    }
}

impl Shares {
    /// The shared subscriptions among `recovered` (the store's metadata),
    /// their sessions' expiry (at most the broker's cap `max`, s: as the
    /// sessions' own queues, [`super::expiry::restored`]) running from
    /// now. A session given a lower interval than its records carry is
    /// moved to it by [`Shares::reconcile`] (records rewritten, group
    /// memberships moved), so that a later start under a raised cap finds
    /// what this one gave, as its queues do.
    pub(super) fn new(
        recovered: &[MetaRecord],
        persistence: Option<Arc<Persistence>>,
        max: Option<u32>,
    ) -> Self {
        let mut state = State::default();
        for record in recovered {
            if let MetaRecord::SharedSubscription {
                vhost,
                client_id,
                filter,
                qos,
                retain_as_published,
                subscription_id,
                session_expiry,
            } = record
            {
                let qos = match qos {
                    0 => QoS::AtMostOnce,
                    1 => QoS::AtLeastOnce,
                    _ => QoS::ExactlyOnce,
                };
                let options = Options {
                    qos,
                    no_local: false,
                    retain_as_published: *retain_as_published,
                    id: NonZeroU32::new(*subscription_id),
                };
                let key = (vhost.clone(), client_id.clone());
                let held = state.sessions.entry(key).or_default();
                // The record's interval as stored, and the session's under
                // the cap.
                let stored = super::expiry::restored(*session_expiry, None);
                let expiry = super::expiry::restored(*session_expiry, max);
                // Mixed intervals (a crash between a move's batches): the
                // longest, whatever order the store reads them in.
                held.expiry = match held.filters.is_empty() {
                    true => expiry,
                    false => super::expiry::longest(held.expiry, expiry),
                };
                held.filters.insert(filter.clone(), (options, stored));
                held.expires_at = super::expiry::ends_at(held.expiry);
            }
        }
        let members: Vec<(String, String, Option<u32>)> = (state.sessions.iter())
            .flat_map(|((vhost, _), held)| {
                (held.filters.iter())
                    .map(|(filter, (_, expiry))| (vhost.clone(), filter.clone(), *expiry))
            })
            .collect();
        for (vhost, filter, expiry) in members {
            state.join(&vhost, &filter, expiry);
        }
        // A crash while a session's records were being moved to a new
        // interval leaves them mixed: they are made one again (the longest
        // of them: it never drops a subscription early, and may keep one
        // longer than a shortened interval asked), by `reconcile` at start;
        // so are those the cap lowered.
        let moving = (state.sessions.iter())
            .filter(|(_, held)| held.filters.values().any(|(_, e)| *e != held.expiry))
            .map(|(key, _)| key.clone());
        state.moving = moving.collect();
        Shares {
            state: Mutex::new(state),
            persistence,
            max_sessions: MAX_SESSIONS,
            max_groups: MAX_GROUPS,
        }
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, State> {
        self.state.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// One submit per lock hold, under the lock: the store sees the
    /// changes in the order memory does.
    fn submit(&self, ops: Vec<StoreOp>) {
        match &self.persistence {
            Some(persistence) if !ops.is_empty() => {
                persistence.submit(ops);
            }
            _ => {}
        }
    }

    /// A session leaves its groups, its records' deletions added to
    /// `ops`; the groups its leaving changed.
    fn delete(state: &mut State, key: &Key, held: Held, ops: &mut Vec<StoreOp>) -> Groups {
        let groups = state.leave_all(&key.0, &held);
        ops.extend(held.filters.into_keys().map(|filter| unput(key, filter)));
        groups
    }

    /// Whether session `client_id` of `vhost` holds shared subscriptions.
    pub(super) fn holds(&self, vhost: &str, client_id: &str) -> bool {
        let key = (vhost.to_owned(), client_id.to_owned());
        self.lock().sessions.contains_key(&key)
    }

    /// What group `filter` of `vhost` keeps its queue for.
    #[cfg(test)]
    fn group(&self, vhost: &str, filter: &str) -> GroupKeep {
        self.lock().group(vhost, filter)
    }

    /// The shared subscriptions of a session a connection resumes (none
    /// once it has expired: then forgotten, and the groups that changed
    /// returned); they do not expire while it is connected.
    pub(super) fn resume(&self, vhost: &str, client_id: &str) -> (Vec<(String, Options)>, Groups) {
        let key = (vhost.to_owned(), client_id.to_owned());
        let mut state = self.lock();
        let state = &mut *state;
        if (state.sessions.get(&key)).is_some_and(|held| held.expired(Instant::now())) {
            let mut ops = Vec::new();
            let groups = match state.sessions.remove(&key) {
                Some(expired) => Self::delete(state, &key, expired, &mut ops),
                None => Vec::new(),
            };
            self.submit(ops);
            return (Vec::new(), groups);
        }
        let Some(held) = state.sessions.get_mut(&key) else {
            return (Vec::new(), Vec::new());
        };
        held.expires_at = None;
        let filters = held.filters.iter();
        let filters = filters
            .map(|(filter, (options, _))| (filter.clone(), *options))
            .collect();
        (filters, Vec::new())
    }

    /// A persistent session's connection has ended: its shared
    /// subscriptions expire `expiry` seconds from now (`None`: never), its
    /// interval then (a DISCONNECT may have changed it: its subscriptions
    /// are then moved to it by [`Shares::settle_yielding`], which the
    /// caller runs). All the session's groups are returned, changed or
    /// not, so that each disconnect gives their queues their current value
    /// again.
    pub(super) fn ended(&self, vhost: &str, client_id: &str, expiry: Option<u32>) -> Groups {
        let key = (vhost.to_owned(), client_id.to_owned());
        let mut state = self.lock();
        let state = &mut *state;
        let Some(held) = state.sessions.get_mut(&key) else {
            return Vec::new();
        };
        held.expires_at = super::expiry::ends_at(expiry);
        if held.expiry != expiry {
            held.expiry = expiry;
            state.moving.insert(key.clone());
        }
        let held = &state.sessions[&key];
        state.groups_of(vhost, held)
    }

    /// Moves at most [`SETTLE_RECORDS`] shared subscriptions of sessions
    /// whose expiry interval changed to it: out of their groups' members
    /// at the old interval into the new, their records rewritten in one
    /// submit; the groups changed and whether any are left to move.
    fn settle_batch(&self) -> (Groups, bool) {
        let mut state = self.lock();
        let state = &mut *state;
        let (mut groups, mut ops) = (Vec::new(), Vec::new());
        let sessions: Vec<Key> = state
            .moving
            .iter()
            .take(super::SWEEP_BATCH)
            .cloned()
            .collect();
        for key in sessions {
            let budget = SETTLE_RECORDS - ops.len();
            if budget == 0 {
                break;
            }
            let (mut moved, mut done) = (Vec::new(), true);
            if let Some(held) = state.sessions.get_mut(&key) {
                let target = held.expiry;
                for (filter, (options, expiry)) in &mut held.filters {
                    if *expiry == target {
                        continue;
                    }
                    if moved.len() == budget {
                        done = false;
                        break;
                    }
                    moved.push((filter.clone(), *expiry, target));
                    *expiry = target;
                    ops.push(put(&key, filter, *options, target));
                }
            }
            for (filter, from, to) in moved {
                state.leave(&key.0, &filter, from);
                state.join(&key.0, &filter, to);
                groups.push((key.0.clone(), filter));
            }
            if done {
                state.moving.remove(&key);
            }
        }
        self.submit(ops);
        (groups, !state.moving.is_empty())
    }

    /// Moves every session whose expiry interval changed to it
    /// ([`Shares::settle_batch`]) and gives the groups changed their
    /// queues' expiry, yielding between holds of the lock.
    pub(super) async fn settle_yielding(&self, core: &Core) {
        self.settle_yielding_in(&|name: &str| vhost_named(core, name))
            .await;
    }

    async fn settle_yielding_in(&self, vhost_of: &impl Fn(&str) -> VhostOf) {
        loop {
            let (groups, more) = self.settle_batch();
            self.apply_yielding_in(vhost_of, groups).await;
            if !more {
                return;
            }
            tokio::task::yield_now().await;
        }
    }

    /// Keeps (or replaces) shared subscription `filter` of a connected
    /// persistent session whose expiry interval is `expiry` seconds
    /// (`None`: never); the groups changed (this one's included, and any a
    /// room-making sweep changed, kept or not), and whether it is kept (not
    /// when too many sessions or groups hold some).
    pub(super) fn keep(
        &self,
        (vhost, client_id): (&str, &str),
        filter: &str,
        options: Options,
        expiry: Option<u32>,
    ) -> (Groups, bool) {
        let key = (vhost.to_owned(), client_id.to_owned());
        let mut state = self.lock();
        let state = &mut *state;
        let mut groups = Vec::new();
        if state.sessions.len() >= self.max_sessions && !state.sessions.contains_key(&key) {
            self.sweep_locked(state, &mut groups);
        }
        if state.sessions.len() >= self.max_sessions && !state.sessions.contains_key(&key) {
            tracing::warn!(
                vhost,
                client_id,
                filter,
                "shared subscription not kept by the persistent MQTT session: too many sessions hold some"
            );
            // (A sweep that freed a place would have made room.)
            return (groups, false);
        }
        let group = (vhost.to_owned(), filter.to_owned());
        if state.groups.len() >= self.max_groups && !state.groups.contains_key(&group) {
            tracing::warn!(
                vhost,
                client_id,
                filter,
                "shared subscription not kept by the persistent MQTT session: too many groups are kept"
            );
            return (groups, false);
        }
        let mut held = state.sessions.remove(&key).unwrap_or_default();
        held.expires_at = None;
        let same = held.filters.get(filter).map(|(same, _)| same) == Some(&options);
        if same && held.expiry == expiry {
            // (Moved to the session's interval by `settle_yielding` if
            // it has not been yet.)
            state.sessions.insert(key, held);
            groups.push((vhost.to_owned(), filter.to_owned()));
            return (groups, true);
        }
        if held.expiry != expiry && !held.filters.is_empty() {
            // The session resumed with another interval (once a
            // connection): its other filters are moved over by
            // `settle_yielding`, which the session runs.
            state.moving.insert(key.clone());
        }
        held.expiry = expiry;
        match held.filters.insert(filter.to_owned(), (options, expiry)) {
            None => state.join(vhost, filter, expiry),
            Some((_, old)) if old != expiry => {
                state.leave(vhost, filter, old);
                state.join(vhost, filter, expiry);
            }
            Some(_) => {}
        }
        groups.push((vhost.to_owned(), filter.to_owned()));
        state.sessions.insert(key.clone(), held);
        self.submit(vec![put(&key, filter, options, expiry)]);
        (groups, true)
    }

    /// Forgets sessions whose shared subscriptions have expired (deleting
    /// their records), at most [`super::SWEEP_BATCH`] sessions holding at
    /// most [`SWEEP_RECORDS`] subscriptions (or one session: one call's
    /// work under the lock is bounded); how many, the groups changed, and
    /// whether expired ones are left.
    pub(super) fn sweep(&self) -> (usize, Groups, bool) {
        let mut state = self.lock();
        let mut groups = Vec::new();
        let (swept, more) = self.sweep_locked(&mut state, &mut groups);
        (swept, groups, more)
    }

    fn sweep_locked(&self, state: &mut State, groups: &mut Groups) -> (usize, bool) {
        let now = Instant::now();
        let mut records = 0;
        let mut expired = Vec::new();
        let mut more = false;
        for (key, held) in &state.sessions {
            if !held.expired(now) {
                continue;
            }
            let over = records + held.filters.len() > SWEEP_RECORDS;
            if !expired.is_empty() && (expired.len() == super::SWEEP_BATCH || over) {
                more = true;
                break;
            }
            records += held.filters.len();
            expired.push(key.clone());
        }
        let mut ops = Vec::with_capacity(records);
        let swept = expired.len();
        for key in expired {
            if let Some(held) = state.sessions.remove(&key) {
                groups.extend(Self::delete(state, &key, held, &mut ops));
            }
        }
        self.submit(ops);
        (swept, more)
    }

    /// Drops a session's shared subscription `filter` (UNSUBSCRIBE); the
    /// groups changed.
    pub(super) fn remove(&self, vhost: &str, client_id: &str, filter: &str) -> Groups {
        let key = (vhost.to_owned(), client_id.to_owned());
        let mut state = self.lock();
        let state = &mut *state;
        let Some(held) = state.sessions.get_mut(&key) else {
            return Vec::new();
        };
        let Some((_, expiry)) = held.filters.remove(filter) else {
            return Vec::new();
        };
        if held.filters.is_empty() {
            state.sessions.remove(&key);
        }
        state.leave(vhost, filter, expiry);
        self.submit(vec![unput(&key, filter.to_owned())]);
        vec![(vhost.to_owned(), filter.to_owned())]
    }

    /// Gives every group queue a member declared durable in `vhosts`
    /// (kept or not) its group's expiry, once at start, before
    /// anything sweeps the vhosts: a group's records and its queue's are
    /// written by separate submits, so a crash between them can leave the
    /// queue with a stale `x-expires` (a short one would expire it before
    /// its members' expiry is given back; one of a group that has lost
    /// its last persistent member would keep it too long, or for ever).
    /// Sessions recovered half-moved to a new interval are moved on
    /// first ([`Shares::new`]), so no group is given an expiry from a
    /// mixed state.
    pub(super) async fn reconcile(&self, vhosts: &[Arc<Vhost>]) {
        let vhost_of = |name: &str| (vhosts.iter()).find(|v| v.name.to_string_lossy() == name);
        let vhost_of = |name: &str| vhost_of(name).cloned();
        self.settle_yielding_in(&vhost_of).await;
        (self.apply_yielding_in(&vhost_of, declared_groups(vhosts))).await;
    }

    /// Gives the durable queues of `groups` the `x-expires` their
    /// persistent members keep them for now ([`GroupKeep::queue_expires`]);
    /// a non-durable group queue (a clean member's) is left as it is, and
    /// so is a queue of that name a member did not declare (no
    /// [`GROUP_QUEUE_ARGUMENT`]: an AMQP client's).
    /// Read from the groups' current state and written under the lock, so
    /// that a value computed before another change can never be written
    /// after it.
    pub(super) fn apply(&self, core: &Core, groups: Groups) {
        self.apply_in(|name| vhost_named(core, name), groups);
    }

    /// [`Shares::apply`] for a task: yields between holds of the lock.
    pub(super) async fn apply_yielding(&self, core: &Core, groups: Groups) {
        let vhost_of = |name: &str| vhost_named(core, name);
        self.apply_yielding_in(&vhost_of, groups).await;
    }

    async fn apply_yielding_in(&self, vhost_of: &impl Fn(&str) -> VhostOf, groups: Groups) {
        for batch in groups.chunks(APPLY_BATCH) {
            self.apply_batch(vhost_of, batch);
            tokio::task::yield_now().await;
        }
    }

    fn apply_in(&self, vhost_of: impl Fn(&str) -> Option<Arc<Vhost>>, groups: Groups) {
        for batch in groups.chunks(APPLY_BATCH) {
            self.apply_batch(&vhost_of, batch);
        }
    }

    fn apply_batch(&self, vhost_of: &impl Fn(&str) -> Option<Arc<Vhost>>, groups: &[Group]) {
        // Lock order: shares, then the vhost's queues, then the queue.
        let state = self.lock();
        for (vhost_name, filter) in groups {
            let Some(vhost) = vhost_of(vhost_name) else {
                continue;
            };
            let Some(queue) = queue_name(filter).and_then(|name| vhost.queue(&name)) else {
                continue;
            };
            let arguments = queue.arguments();
            let declared_by_a_member = crate::arguments::marks_an_mqtt_group_queue(&arguments);
            let exclusive = queue.options.exclusive_owner.is_some();
            if !declared_by_a_member || !queue.options.durable || exclusive {
                continue;
            }
            let current = (arguments.get("x-expires"))
                .and_then(FieldValue::as_i64)
                .and_then(|ms| u64::try_from(ms).ok());
            let expires = state.group(vhost_name, filter).queue_expires();
            if current != expires && vhost.set_queue_expires(&queue, expires, None) {
                tracing::debug!(queue = %queue.name, ?expires, "MQTT shared subscription group's queue given its members' expiry");
            }
        }
    }

    /// Declares the queue of group `filter` in `vhost` (named `queue`) for
    /// a member about to bind and consume it: one that exists is joined as
    /// it is; a new one is marked as the group's ([`GROUP_QUEUE_ARGUMENT`]),
    /// durable, not auto-delete, with the group's `x-expires` if the group
    /// has a persistent member now, else non-durable and auto-delete. Under
    /// the lock, so that no member's change to the group comes between the
    /// value read and the queue created, and members never refuse each
    /// other's queue. The member holds the queue until it drops the
    /// [`QueueJoin`] (its consume has arrived, or it has gone), so it
    /// cannot expire or be auto-deleted in between. The join and whether
    /// the queue was created.
    pub(super) fn declare_queue(
        &self,
        vhost: &Arc<Vhost>,
        filter: &str,
        queue: ShortStr,
        max_queues: Option<usize>,
    ) -> AmqpResult<(QueueJoin, bool)> {
        // Twice at most: a queue declared anew can only be going again if
        // its own last consumer has come and gone meanwhile.
        for _ in 0..2 {
            match self.join_or_declare_queue(vhost, filter, queue.clone(), max_queues)? {
                JoinAttempt::Joined(join, created) => return Ok((join, created)),
                // Its deletion is under way: finished here, without the
                // lock (a queue's deletion costs what its bindings do).
                JoinAttempt::Going(going) => {
                    vhost.delete_queue(&going).notify();
                }
            }
        }
        Err(AmqpError::resource_locked(format_args!(
            "queue '{queue}' in vhost '{}' is being deleted",
            vhost.name
        )))
    }

    /// One attempt of [`Shares::declare_queue`], under the lock.
    fn join_or_declare_queue(
        &self,
        vhost: &Arc<Vhost>,
        filter: &str,
        queue: ShortStr,
        max_queues: Option<usize>,
    ) -> AmqpResult<JoinAttempt> {
        let state = self.lock();
        let vhost_name = vhost.name.to_string_lossy();
        let keep = state.group(&vhost_name, filter);
        let mut arguments = FieldTable::new();
        arguments.insert(
            ShortStr::from_static(GROUP_QUEUE_ARGUMENT),
            FieldValue::Bool(true),
        );
        let kept = keep != GroupKeep::Unkept;
        if let Some(ms) = keep.queue_expires().filter(|_| kept) {
            arguments.insert(
                ShortStr::from_static("x-expires"),
                FieldValue::I64(i64::try_from(ms).unwrap_or(i64::MAX)),
            );
        }
        let declaration = QueueDeclaration {
            name: queue,
            passive: false,
            server_named: false,
            options: QueueOptions {
                durable: kept,
                exclusive_owner: None,
                auto_delete: !kept,
                arguments,
            },
            max_queues,
        };
        vhost.join_or_declare_queue(declaration)
    }

    /// Forgets every shared subscription of a session (it starts clean
    /// or ends with its connection); the groups changed.
    pub(super) fn forget(&self, vhost: &str, client_id: &str) -> Groups {
        let key = (vhost.to_owned(), client_id.to_owned());
        let mut state = self.lock();
        let state = &mut *state;
        let mut ops = Vec::new();
        let groups = match state.sessions.remove(&key) {
            Some(held) => Self::delete(state, &key, held, &mut ops),
            None => Vec::new(),
        };
        self.submit(ops);
        groups
    }
}

/// The record of a session's shared subscription (replacing any).
fn put(key: &Key, filter: &str, options: Options, expiry: Option<u32>) -> StoreOp {
    StoreOp::PutMeta(MetaRecord::SharedSubscription {
        vhost: key.0.clone(),
        client_id: key.1.clone(),
        filter: filter.to_owned(),
        qos: options.qos.level(),
        retain_as_published: options.retain_as_published,
        subscription_id: options.id.map_or(0, NonZeroU32::get),
        session_expiry: expiry.unwrap_or(NEVER),
    })
}

/// The deletion of a session's shared subscription's record.
fn unput(key: &Key, filter: String) -> StoreOp {
    StoreOp::DeleteMeta(MetaKey::SharedSubscription {
        vhost: key.0.clone(),
        client_id: key.1.clone(),
        filter,
    })
}

/// The groups whose queues in `vhosts` a member declared durable.
fn declared_groups(vhosts: &[Arc<Vhost>]) -> Groups {
    let mut groups = Vec::new();
    for vhost in vhosts {
        for queue in vhost.queues() {
            let name = queue.name.to_string_lossy();
            let Some(group) = name.strip_prefix(mapping::SHARED_QUEUE_PREFIX) else {
                continue;
            };
            let marked = crate::arguments::marks_an_mqtt_group_queue(&queue.arguments());
            if marked && queue.options.durable {
                let vhost_name = vhost.name.to_string_lossy().into_owned();
                groups.push((vhost_name, format!("$share/{group}")));
            }
        }
    }
    groups
}

/// A vhost looked up by name.
type VhostOf = Option<Arc<Vhost>>;

fn vhost_named(core: &Core, name: &str) -> Option<Arc<Vhost>> {
    ShortStr::try_from(name)
        .ok()
        .and_then(|name| core.vhost(&name))
}

/// The queue of shared subscription `filter` (`$share/GROUP/FILTER`).
pub(super) fn queue_name(filter: &str) -> Option<ShortStr> {
    let (group, inner) = filter.strip_prefix("$share/")?.split_once('/')?;
    mapping::shared_queue_name(group, inner)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::testkit::Harness;
    use std::time::Duration;

    /// The stored record of `client_id`'s QoS 1 shared subscription
    /// `filter` in vhost `/` (no other option), its session's expiry
    /// `session_expiry`.
    fn member(client_id: &str, filter: &str, session_expiry: u32) -> MetaRecord {
        MetaRecord::SharedSubscription {
            vhost: "/".into(),
            client_id: client_id.into(),
            filter: filter.into(),
            qos: 1,
            retain_as_published: false,
            subscription_id: 0,
            session_expiry,
        }
    }

    fn options(qos: QoS) -> Options {
        Options {
            qos,
            no_local: false,
            retain_as_published: false,
            id: None,
        }
    }

    #[test]
    fn sessions_past_the_cap_keep_none_and_forgetting_frees_a_place() {
        let mut shares = Shares::new(&[], None, None);
        shares.max_sessions = 2;
        let keep = |shares: &Shares, id, filter, qos| {
            (shares.keep(("/", id), filter, options(qos), None)).1
        };
        assert!(keep(&shares, "a", "$share/g/x", QoS::AtLeastOnce));
        assert!(keep(&shares, "b", "$share/g/x", QoS::AtMostOnce));
        assert!(!keep(&shares, "c", "$share/g/x", QoS::AtMostOnce));
        // A session already holding some may hold more.
        assert!(keep(&shares, "a", "$share/h/y", QoS::ExactlyOnce));
        assert_eq!(shares.resume("/", "a").0.len(), 2);
        assert!(shares.resume("/", "c").0.is_empty());
        shares.forget("/", "b");
        assert!(shares.resume("/", "b").0.is_empty());
        assert!(keep(&shares, "c", "$share/g/x", QoS::AtMostOnce));
        shares.remove("/", "a", "$share/g/x");
        assert_eq!(
            shares.resume("/", "a").0,
            [("$share/h/y".to_owned(), options(QoS::ExactlyOnce))]
        );
    }

    #[test]
    fn expired_sessions_hold_none_and_make_room_at_the_cap() {
        let mut shares = Shares::new(&[], None, None);
        shares.max_sessions = 1;
        let zero = options(QoS::AtMostOnce);
        assert!(shares.keep(("/", "a"), "$share/g/x", zero, Some(0)).1);
        // Connected: no expiry runs.
        assert_eq!(shares.resume("/", "a").0.len(), 1);
        shares.ended("/", "a", Some(0));
        // Expired, so a new session takes its place at the cap.
        assert!(shares.keep(("/", "b"), "$share/g/x", zero, None).1);
        assert!(shares.resume("/", "a").0.is_empty());
        shares.ended("/", "b", Some(3600));
        assert_eq!(shares.resume("/", "b").0.len(), 1, "an hour has not passed");
    }

    #[test]
    fn recovered_records_are_held_with_their_options() {
        let record = MetaRecord::SharedSubscription {
            vhost: "v".into(),
            client_id: "c".into(),
            filter: "$share/g/t/#".into(),
            qos: 1,
            retain_as_published: true,
            subscription_id: 7,
            session_expiry: 3600,
        };
        let shares = Shares::new(&[record], None, None);
        let expected = Options {
            retain_as_published: true,
            id: NonZeroU32::new(7),
            ..options(QoS::AtLeastOnce)
        };
        assert_eq!(
            shares.resume("v", "c").0,
            [("$share/g/t/#".to_owned(), expected)]
        );
    }

    #[tokio::test]
    async fn recovered_records_are_given_the_cap_if_they_outlive_it() {
        let record =
            |client_id: &str, session_expiry| member(client_id, "$share/g/capped", session_expiry);
        // A 3.1.1 session stored as never expiring, one of an hour.
        let records = [record("never", NEVER), record("hour", 3600)];
        // Moved to it at start (`reconcile`), written back.
        let records = &records;
        let started = |max| async move {
            let shares = Shares::new(records, None, max);
            shares.settle_yielding_in(&|_: &str| None).await;
            shares
        };
        let shares = started(Some(60)).await;
        assert_eq!(
            shares.group("/", "$share/g/capped"),
            GroupKeep::Kept(Some(60))
        );
        let shares = started(Some(7200)).await;
        let kept = shares.group("/", "$share/g/capped");
        assert_eq!(kept, GroupKeep::Kept(Some(7200)), "never is the cap");
        let shares = Shares::new(records, None, None);
        assert_eq!(shares.group("/", "$share/g/capped"), GroupKeep::Kept(None));
    }

    #[test]
    fn a_groups_queue_is_kept_for_its_longest_lived_persistent_member() {
        let shares = Shares::new(&[], None, None);
        let group = |shares: &Shares| shares.group("/", "$share/g/x");
        let one = options(QoS::AtLeastOnce);
        assert_eq!(group(&shares), GroupKeep::Unkept, "no persistent member");
        let g = || ("/".to_owned(), "$share/g/x".to_owned());
        let joined = shares.keep(("/", "a"), "$share/g/x", one, Some(60));
        let kept = GroupKeep::Kept(Some(60));
        assert_eq!(joined, (vec![g()], true));
        assert_eq!(group(&shares), kept);
        assert_eq!(kept.queue_expires(), Some(60_000));
        assert!(shares.keep(("/", "b"), "$share/g/x", one, Some(10)).1);
        assert_eq!(group(&shares), GroupKeep::Kept(Some(60)));
        // Another vhost's group of the same name is another group.
        assert_eq!(shares.group("v", "$share/g/x"), GroupKeep::Unkept);
        // A DISCONNECT makes "b" never expire.
        assert_eq!(shares.ended("/", "b", None), [g()]);
        assert_eq!(shares.settle_batch(), (vec![g()], false));
        assert_eq!(group(&shares), GroupKeep::Kept(None));
        assert_eq!(GroupKeep::Kept(None).queue_expires(), None);
        // "b" starts clean, "a" unsubscribes: no persistent member left.
        assert_eq!(shares.forget("/", "b"), [g()]);
        assert_eq!(group(&shares), kept);
        assert_eq!(shares.remove("/", "a", "$share/g/x"), [g()]);
        let unkept = GroupKeep::Unkept;
        assert_eq!(group(&shares), unkept);
        assert_eq!(unkept.queue_expires(), Some(1), "goes once unused");
        // A member whose session expired leaves its groups when swept.
        assert!(shares.keep(("/", "c"), "$share/g/x", one, Some(0)).1);
        assert!(shares.sweep().1.is_empty(), "connected: no expiry runs");
        shares.ended("/", "c", Some(0));
        assert_eq!(shares.sweep(), (1, vec![g()], false));
        assert_eq!(group(&shares), GroupKeep::Unkept);
    }

    #[test]
    fn a_group_filter_names_the_groups_queue() {
        let name = queue_name("$share/g/a/+/#").expect("a shared filter");
        assert_eq!(name.as_bytes(), b"mqtt-shared-g/a/+/#");
        assert!(queue_name("a/b").is_none());
    }

    #[test]
    fn groups_past_the_cap_are_not_kept_until_one_goes() {
        let mut shares = Shares::new(&[], None, None);
        shares.max_groups = 2;
        let one = options(QoS::AtLeastOnce);
        let keep = |shares: &Shares, id, filter| shares.keep(("/", id), filter, one, None).1;
        assert!(keep(&shares, "a", "$share/g/1"));
        assert!(keep(&shares, "b", "$share/g/2"));
        // A third group is not kept, for a new or an existing session.
        assert!(!keep(&shares, "c", "$share/g/3"));
        assert!(!keep(&shares, "a", "$share/g/3"));
        assert_eq!(shares.group("/", "$share/g/3"), GroupKeep::Unkept);
        // A kept group takes more members.
        assert!(keep(&shares, "c", "$share/g/1"));
        shares.forget("/", "b");
        assert!(keep(&shares, "c", "$share/g/3"));
        assert_eq!(shares.resume("/", "c").0.len(), 2);
    }

    #[test]
    fn a_session_resumed_with_another_interval_moves_all_its_groups() {
        let shares = Shares::new(&[], None, None);
        let one = options(QoS::AtLeastOnce);
        let keep = |filter, expiry| shares.keep(("/", "a"), filter, one, expiry);
        assert!(keep("$share/g/1", Some(60)).1);
        // A second filter at the same interval changes its group only.
        let (changed, kept) = keep("$share/g/2", Some(60));
        assert!(kept);
        assert_eq!(changed, [("/".into(), "$share/g/2".into())]);
        assert_eq!(shares.group("/", "$share/g/2"), GroupKeep::Kept(Some(60)));
        shares.ended("/", "a", Some(60));
        assert_eq!(shares.resume("/", "a").0.len(), 2);
        // Rejoined with ten seconds: its group follows, and the other
        // once settled (rejoining it moves nothing by itself).
        let (changed, _) = keep("$share/g/1", Some(10));
        assert_eq!(changed, [("/".into(), "$share/g/1".into())]);
        let (changed, _) = keep("$share/g/2", Some(10));
        assert_eq!(changed, [("/".into(), "$share/g/2".into())]);
        assert_eq!(shares.group("/", "$share/g/2"), GroupKeep::Kept(Some(60)));
        let (moved, more) = shares.settle_batch();
        assert_eq!(
            (moved, more),
            (vec![("/".into(), "$share/g/2".into())], false)
        );
        let ten = GroupKeep::Kept(Some(10));
        assert_eq!(shares.group("/", "$share/g/1"), ten);
        assert_eq!(shares.group("/", "$share/g/2"), ten);
    }

    /// The argument a member's declaration marks a group's queue with.
    fn marked() -> (&'static str, FieldValue) {
        (GROUP_QUEUE_ARGUMENT, FieldValue::Bool(true))
    }

    /// The `x-expires` of `queue` now.
    fn expires_of(queue: &crate::queue::Queue) -> Option<i64> {
        queue
            .arguments()
            .get("x-expires")
            .and_then(FieldValue::as_i64)
    }

    #[test]
    fn a_stale_change_never_overwrites_a_groups_newer_expiry() {
        let h = Harness::durable();
        let vhost_of = |_: &str| Some(Arc::clone(&h.vhost));
        let shares = Shares::new(&[], None, None);
        let one = options(QoS::AtLeastOnce);
        let queue = h.declare_queue("mqtt-shared-g/x", true, &[marked()]);
        assert!(shares.keep(("/", "p2"), "$share/g/x", one, Some(0)).1);
        shares.ended("/", "p2", Some(0));
        // The sweeper removes p2's expired membership: no persistent
        // member left (then the value was 1 ms) ...
        let (swept, stale, _) = shares.sweep();
        assert_eq!(swept, 1);
        // ... and before it writes, p3 joins for an hour and writes.
        let (joined, kept) = shares.keep(("/", "p3"), "$share/g/x", one, Some(3600));
        assert!(kept);
        shares.apply_in(vhost_of, joined);
        assert_eq!(expires_of(&queue), Some(3_600_000));
        // The sweeper's write comes last: the group's value now stays.
        shares.apply_in(vhost_of, stale);
        assert_eq!(expires_of(&queue), Some(3_600_000));
        // A disconnect with an unchanged interval gives its groups their
        // value again (whatever wrote the queue meanwhile).
        assert!(h.vhost.set_queue_expires(&queue, Some(1), None));
        let ended = shares.ended("/", "p3", Some(3600));
        assert_eq!(ended, [("/".to_owned(), "$share/g/x".to_owned())]);
        shares.apply_in(vhost_of, ended);
        assert_eq!(expires_of(&queue), Some(3_600_000));
    }

    #[test]
    fn members_join_a_group_queue_as_it_is_and_create_it_from_the_groups_state() {
        let h = Harness::durable();
        let vhost_of = |_: &str| Some(Arc::clone(&h.vhost));
        let shares = Shares::new(&[], None, None);
        let one = options(QoS::AtLeastOnce);
        let name = |filter| queue_name(filter).expect("a shared filter");
        // The members' joins, held as their consumes would be pending.
        let joins = std::cell::RefCell::new(Vec::new());
        let declare = |filter| {
            let (join, created) = shares
                .declare_queue(&h.vhost, filter, name(filter), None)
                .ok()?;
            joins.borrow_mut().push(join);
            Some(created)
        };
        // A clean member creates a group's queue: non-durable, auto-delete.
        assert_eq!(declare("$share/c/x"), Some(true));
        let clean = h.vhost.queue(&name("$share/c/x")).expect("created");
        assert!(!clean.options.durable && clean.options.auto_delete);
        // A persistent member joins it as it is.
        assert!(shares.keep(("/", "p"), "$share/c/x", one, Some(60)).1);
        assert_eq!(declare("$share/c/x"), Some(false));
        // A kept group's new queue: durable, with the group's expiry.
        assert!(shares.keep(("/", "p1"), "$share/k/x", one, Some(60)).1);
        assert_eq!(declare("$share/k/x"), Some(true));
        let kept = h.vhost.queue(&name("$share/k/x")).expect("created");
        assert!(kept.options.durable && !kept.options.auto_delete);
        assert_eq!(expires_of(&kept), Some(60_000));
        // Another member joins for an hour and applies it; a member that
        // read the minute before still joins (an AMQP redeclaration is
        // compared, but for x-expires, which is MQTT's: one with the
        // minute and a flag of its own is refused as inequivalent).
        let (joined, _) = shares.keep(("/", "p2"), "$share/k/x", one, Some(3600));
        shares.apply_in(vhost_of, joined);
        assert_eq!(expires_of(&kept), Some(3_600_000));
        assert_eq!(declare("$share/k/x"), Some(false));
        let minute = [("x-expires", FieldValue::I64(60_000))];
        let redeclared = |auto_delete| QueueDeclaration {
            name: name("$share/k/x"),
            passive: false,
            server_named: false,
            options: QueueOptions {
                durable: true,
                exclusive_owner: None,
                auto_delete,
                arguments: crate::testkit::table(&minute),
            },
            max_queues: None,
        };
        assert!(h.vhost.declare_queue(redeclared(true), 0).is_err());
        assert!(h.vhost.declare_queue(redeclared(false), 0).is_ok());
        assert_eq!(expires_of(&kept), Some(3_600_000));
        // A clean member joins the durable queue as it is too.
        assert_eq!(declare("$share/k/x"), Some(false));
    }

    #[test]
    fn a_sweep_to_make_room_is_applied_even_if_the_subscription_is_not_kept() {
        let mut shares = Shares::new(&[], None, None);
        shares.max_sessions = 2;
        shares.max_groups = 1;
        let one = options(QoS::AtLeastOnce);
        assert!(shares.keep(("/", "a"), "$share/g/1", one, Some(0)).1);
        assert!(shares.keep(("/", "b"), "$share/g/1", one, Some(10)).1);
        shares.ended("/", "a", Some(0));
        // "c" needs room: "a" is swept, but a second group is not kept.
        let (changed, kept) = shares.keep(("/", "c"), "$share/g/2", one, None);
        assert!(!kept);
        assert_eq!(changed, [("/".to_owned(), "$share/g/1".to_owned())]);
        assert!(shares.resume("/", "a").0.is_empty());
    }

    #[test]
    fn declared_group_queues_are_given_their_groups_expiry_kept_or_not() {
        // A crash after the member's record, before its queue's.
        let record = member("c", "$share/g/x", 3600);
        let h = Harness::durable();
        let old = [("x-expires", FieldValue::I64(60_000)), marked()];
        let queue = h.declare_queue("mqtt-shared-g/x", true, &old);
        // And one after its group's last persistent member's records
        // were deleted, before its queue's: left for ever.
        let never = [marked()];
        let unkept = h.declare_queue("mqtt-shared-h/y", true, &never);
        // A durable queue not declared by a member is left alone.
        let amqp = h.declare_queue("mqtt-shared-a/z", true, &[]);
        let shares = Shares::new(&[record], None, None);
        let declared = declared_groups(&[Arc::clone(&h.vhost)]);
        assert_eq!(declared.len(), 2);
        assert!(declared.contains(&("/".to_owned(), "$share/g/x".to_owned())));
        assert!(declared.contains(&("/".to_owned(), "$share/h/y".to_owned())));
        shares.apply_in(|_| Some(Arc::clone(&h.vhost)), declared);
        assert_eq!(expires_of(&queue), Some(3_600_000));
        assert_eq!(expires_of(&unkept), Some(1), "goes once unused");
        assert_eq!(expires_of(&amqp), None);
    }

    #[test]
    fn a_sweep_deletes_a_bounded_number_of_subscriptions_under_one_hold() {
        let shares = Shares::new(&[], None, None);
        let one = options(QoS::AtLeastOnce);
        let each = SWEEP_RECORDS / 2 + 1;
        for id in ["a", "b", "c"] {
            for n in 0..each {
                let filter = format!("$share/g{n}/x");
                assert!(shares.keep(("/", id), &filter, one, Some(0)).1);
            }
            shares.ended("/", id, Some(0));
        }
        // Two sessions would pass the budget: one per hold.
        let swept: Vec<(usize, bool)> = (0..4)
            .map(|_| shares.sweep())
            .map(|(swept, _, more)| (swept, more))
            .collect();
        assert_eq!(swept, [(1, true), (1, true), (1, false), (0, false)]);
    }

    #[test]
    fn an_expiry_change_moves_a_bounded_number_of_subscriptions_under_one_hold() {
        let shares = Shares::new(&[], None, None);
        let one = options(QoS::AtLeastOnce);
        let filter = |n: usize| format!("$share/g{n}/x");
        let count = 2 * SETTLE_RECORDS + 10;
        for n in 0..count {
            assert!(shares.keep(("/", "a"), &filter(n), one, Some(60)).1);
        }
        // A DISCONNECT's new interval: the end itself moves none.
        assert_eq!(shares.ended("/", "a", Some(3600)).len(), count);
        let last = filter(count - 1);
        assert_eq!(shares.group("/", &last), GroupKeep::Kept(Some(60)));
        let batches: Vec<(usize, bool)> = (0..4)
            .map(|_| shares.settle_batch())
            .map(|(moved, more)| (moved.len(), more))
            .collect();
        let full = SETTLE_RECORDS;
        assert_eq!(
            batches,
            [(full, true), (full, true), (10, false), (0, false)]
        );
        assert_eq!(shares.group("/", &last), GroupKeep::Kept(Some(3600)));
        // Resumed with another interval: the same, from the first keep.
        shares.resume("/", "a");
        let (changed, _) = shares.keep(("/", "a"), &filter(0), one, Some(10));
        assert_eq!(changed.len(), 1);
        assert_eq!(shares.settle_batch().0.len(), full);
        assert_eq!(shares.group("/", &last), GroupKeep::Kept(Some(3600)));
        while shares.settle_batch().1 {}
        assert_eq!(shares.group("/", &last), GroupKeep::Kept(Some(10)));
        // Each left its old group: forgetting the session unkeeps them all.
        assert_eq!(shares.forget("/", "a").len(), count);
        assert!(shares.lock().groups.is_empty());
    }

    #[tokio::test]
    async fn a_session_recovered_half_moved_is_moved_on_at_start_to_its_longest_interval() {
        // A crash between two batches of a move from 60 s to an hour; the
        // store may read the records in either order.
        let record = |filter: &str, session_expiry| member("c", filter, session_expiry);
        let (unmoved, moved) = (record("$share/g/1", 60), record("$share/g/2", 3600));
        for records in [[unmoved.clone(), moved.clone()], [moved, unmoved]] {
            let h = Harness::durable();
            let name = queue_name("$share/g/1").expect("a shared filter");
            let minute = [("x-expires", FieldValue::I64(60_000)), marked()];
            let queue = h.declare_queue(&name.to_string_lossy(), true, &minute);
            let shares = Shares::new(&records, None, None);
            // Start-up, no session connecting.
            shares.reconcile(std::slice::from_ref(&h.vhost)).await;
            assert_eq!(shares.group("/", "$share/g/1"), GroupKeep::Kept(Some(3600)));
            assert_eq!(expires_of(&queue), Some(3_600_000));
            assert_eq!(shares.settle_batch(), (Vec::new(), false), "all moved");
        }
    }

    #[tokio::test]
    async fn what_a_start_gives_a_session_is_written_back_and_kept_under_a_raised_cap() {
        let h = Harness::durable();
        let persistence = h.persistence.clone().expect("durable");
        // A 3.1.1 session stored as never expiring, and its group's queue.
        let record = member("c", "$share/g/x", NEVER);
        persistence.submit(vec![StoreOp::PutMeta(record)]);
        let queue = h.declare_queue("mqtt-shared-g/x", true, &[marked()]);
        let carried = || async {
            assert!(persistence.sync().await, "the store took the writes");
            let records = h.stored().meta.into_iter();
            let carried = records.filter_map(|r| match r {
                MetaRecord::SharedSubscription { session_expiry, .. } => Some(session_expiry),
                _ => None,
            });
            carried.collect::<Vec<u32>>()
        };
        assert_eq!(carried().await, [NEVER]);
        // A start under a minute: the record says so, as the queue.
        let shares = Shares::new(&h.stored().meta, Some(Arc::clone(&persistence)), Some(60));
        shares.reconcile(std::slice::from_ref(&h.vhost)).await;
        assert_eq!(carried().await, [60]);
        assert_eq!(expires_of(&queue), Some(60_000));
        // The next under infinity finds what it gave, as the session's own
        // queues keep theirs.
        let later = Shares::new(&h.stored().meta, Some(Arc::clone(&persistence)), None);
        later.reconcile(std::slice::from_ref(&h.vhost)).await;
        assert_eq!(later.group("/", "$share/g/x"), GroupKeep::Kept(Some(60)));
        assert_eq!(expires_of(&queue), Some(60_000));
        assert_eq!(carried().await, [60]);
        assert!(later.holds("/", "c") && !later.holds("/", "d"));
    }

    #[test]
    fn a_joined_unkept_group_queue_outlives_its_x_expires_until_the_consume() {
        let h = Harness::durable();
        let shares = Shares::new(&[], None, None);
        let filter = "$share/u/x";
        let name = queue_name(filter).expect("a shared filter");
        // A durable queue whose group lost its last persistent member.
        let unkept = [("x-expires", FieldValue::I64(1)), marked()];
        h.declare_queue("mqtt-shared-u/x", true, &unkept);
        let (join, created) =
            (shares.declare_queue(&h.vhost, filter, name.clone(), None)).expect("joined");
        assert!(!created);
        // However late the consume comes (no timer runs out).
        let late = Instant::now() + Duration::from_secs(3600);
        h.vhost.sweep_at(late);
        assert!(h.vhost.queue(&name).is_some(), "kept for the consume");
        // Even if another member's consumer comes and goes meanwhile.
        let queue = h.vhost.queue(&name).expect("listed");
        let member = h.channel();
        let consume = crate::testkit::Consume {
            no_ack: true,
            prefetch: 0,
        };
        let consumer = member.consume(&queue, "other", consume);
        queue.remove_consumer(&consumer);
        h.vhost.sweep_at(late);
        assert!(h.vhost.queue(&name).is_some(), "still kept for the consume");
        // The member's consume arrives, then its hold is released.
        let consumer = member.consume(&queue, "joined", consume);
        drop(join);
        h.vhost.sweep_at(late);
        assert!(h.vhost.queue(&name).is_some(), "consumed");
        queue.remove_consumer(&consumer);
        h.vhost.sweep_at(Instant::now() + Duration::from_millis(50));
        assert!(h.vhost.queue(&name).is_none(), "gone once unused");
    }

    /// What a channel does when a consumer is cancelled: an auto-delete
    /// queue it leaves without consumers is deleted.
    fn cancel(
        h: &Harness,
        queue: &Arc<crate::queue::Queue>,
        consumer: &Arc<crate::queue::Consumer>,
    ) {
        if queue.remove_consumer(consumer) {
            h.vhost.delete_queue(queue).notify();
        }
    }

    #[test]
    fn a_clean_groups_queue_whose_last_consumer_leaves_waits_for_the_joiners_consume() {
        let h = Harness::new();
        let shares = Shares::new(&[], None, None);
        let filter = "$share/c/x";
        let name = queue_name(filter).expect("a shared filter");
        let declare = || shares.declare_queue(&h.vhost, filter, name.clone(), None);
        let consume = crate::testkit::Consume {
            no_ack: true,
            prefetch: 0,
        };
        let channel = h.channel();
        // A clean member creates the queue and consumes it.
        let (first, created) = declare().expect("declared");
        assert!(created);
        let queue = Arc::clone(first.queue());
        let consumer = channel.consume(&queue, "first", consume);
        drop(first);
        // A second member joins; the first leaves before its consume.
        let (second, created) = declare().expect("joined");
        assert!(!created);
        cancel(&h, &queue, &consumer);
        assert!(h.vhost.queue(&name).is_some(), "kept for the joiner");
        // Its consume arrives: the queue lives on with it.
        let consumer = channel.consume(&queue, "second", consume);
        drop(second);
        assert!(h.vhost.queue(&name).is_some(), "consumed");
        // Its last member gone, the queue goes.
        cancel(&h, &queue, &consumer);
        assert!(h.vhost.queue(&name).is_none(), "auto-deleted");
        // A joiner that goes without consuming takes the queue with it
        // when the last consumer has left meanwhile, or none ever came.
        let (third, _) = declare().expect("declared");
        let queue = Arc::clone(third.queue());
        let consumer = channel.consume(&queue, "third", consume);
        let (fourth, _) = declare().expect("joined");
        cancel(&h, &queue, &consumer);
        drop(third);
        assert!(h.vhost.queue(&name).is_some(), "the fourth's join pending");
        drop(fourth);
        assert!(h.vhost.queue(&name).is_none(), "auto-deleted");
        let (fifth, _) = declare().expect("declared");
        drop(fifth);
        assert!(h.vhost.queue(&name).is_none(), "never consumed: gone");
    }

    #[test]
    fn a_member_joining_a_queue_whose_auto_deletion_is_under_way_gets_a_new_one() {
        let h = Harness::new();
        let shares = Shares::new(&[], None, None);
        let filter = "$share/c/x";
        let name = queue_name(filter).expect("a shared filter");
        let (first, _) =
            (shares.declare_queue(&h.vhost, filter, name.clone(), None)).expect("declared");
        let old = Arc::clone(first.queue());
        let consume = crate::testkit::Consume {
            no_ack: true,
            prefetch: 0,
        };
        let consumer = h.channel().consume(&old, "first", consume);
        drop(first);
        // The last consumer leaves: the queue is to go, but the channel
        // has not deleted it yet when a member joins.
        assert!(old.remove_consumer(&consumer));
        let (joined, created) =
            (shares.declare_queue(&h.vhost, filter, name.clone(), None)).expect("declared anew");
        assert!(created);
        assert!(!Arc::ptr_eq(joined.queue(), &old));
        // The channel's deletion then finds the old queue gone.
        h.vhost.delete_queue(&old).notify();
        let listed = h.vhost.queue(&name).expect("the new queue stays");
        assert!(Arc::ptr_eq(&listed, joined.queue()));
    }

    #[test]
    fn a_member_joining_a_queue_the_sweeper_found_expired_gets_a_new_one() {
        let h = Harness::durable();
        let shares = Shares::new(&[], None, None);
        let filter = "$share/u/x";
        let name = queue_name(filter).expect("a shared filter");
        let unkept = [("x-expires", FieldValue::I64(1)), marked()];
        let old = h.declare_queue("mqtt-shared-u/x", true, &unkept);
        // The sweeper finds it expired; before it deletes it, a member
        // joins: it must not join the queue about to go.
        let late = Instant::now() + Duration::from_secs(3600);
        assert!(old.take_expired(late));
        let (joined, created) =
            (shares.declare_queue(&h.vhost, filter, name.clone(), None)).expect("declared anew");
        assert!(created);
        assert!(!Arc::ptr_eq(joined.queue(), &old));
        // The sweeper's deletion then finds the old queue gone, and its
        // next sweep leaves the joined one.
        h.vhost.delete_queue(&old).notify();
        h.vhost.sweep_at(late);
        let listed = h.vhost.queue(&name).expect("the new queue stays");
        assert!(Arc::ptr_eq(&listed, joined.queue()));
    }

    #[test]
    fn a_queue_an_amqp_client_declared_under_a_groups_name_keeps_its_arguments() {
        let h = Harness::durable();
        let shares = Shares::new(&[], None, None);
        let minute = [("x-expires", FieldValue::I64(60_000))];
        let queue = h.declare_queue("mqtt-shared-g/x", true, &minute);
        let one = options(QoS::AtLeastOnce);
        let (joined, kept) = shares.keep(("/", "p"), "$share/g/x", one, Some(3600));
        assert!(kept);
        shares.apply_in(|_| Some(Arc::clone(&h.vhost)), joined);
        assert_eq!(expires_of(&queue), Some(60_000), "not the group's queue");
        assert!(queue.arguments().get(GROUP_QUEUE_ARGUMENT).is_none());
        // Only `true` marks: `false` is no mark, at start either.
        let unmarked = [
            ("x-expires", FieldValue::I64(60_000)),
            (GROUP_QUEUE_ARGUMENT, FieldValue::Bool(false)),
        ];
        let other = h.declare_queue("mqtt-shared-g/y", true, &unmarked);
        let (joined, _) = shares.keep(("/", "p"), "$share/g/y", one, Some(3600));
        shares.apply_in(|_| Some(Arc::clone(&h.vhost)), joined);
        assert_eq!(expires_of(&other), Some(60_000), "false marks nothing");
        assert!(declared_groups(std::slice::from_ref(&h.vhost)).is_empty());
    }
}
