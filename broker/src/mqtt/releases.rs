//! The QoS 2 publishes a persistent session had routed and PUBREC'd but
//! the client had not yet released (PUBREL): kept for the session's next
//! connection, so that a resend is not routed twice and the PUBREL is
//! answered. They are held in memory from the publish's routing on, and
//! with a store they are durable ([`MetaRecord::Unreleased`],
//! one record per packet identifier, written before the PUBREC and
//! deleted before the PUBCOMP), so this holds across a restart too.
//!
//! They expire with the session, as its queues (`x-expires`) and shared
//! subscriptions (`shares`) do: each record carries the session's Session
//! Expiry Interval (rewritten when the connection ends if it changed: a
//! resuming CONNECT's, a DISCONNECT's; a crash before that leaves the
//! previous interval); once the connection has ended the interval runs (from the
//! restart after one), and when it has passed the state is deleted, from
//! the store too: by [`Releases::sweep`] (the MQTT sweeper, every
//! second), or first by the session's next connection, which then finds
//! none. A clean start, or a session that ends with its connection,
//! deletes it at once.
//!
//! Records written by a Leveret that did not keep the interval have none:
//! they are given [`OLDER_RECORDS_EXPIRY`] (a day) at start, and their
//! session's own interval when it is next seen (its connection's end
//! rewrites them), so a session that never comes back does not hold its
//! place for ever. It is also given to records of never-expiring sessions
//! (an older Leveret stored those without an interval too). At start every
//! session's interval is at most the broker's cap
//! (`mqtt-max-session-expiry-interval-seconds`, as the session's queues
//! are: [`super::expiry::restored`]). What a session is given at start is
//! written back to its records ([`Releases::settle_yielding`], in bounded
//! batches), so that a later start under a raised cap finds what this one
//! gave, as its queues and shared subscriptions do; from then on a
//! session's records are rewritten whenever its interval differs from the
//! one they carry.
//!
//! Bounded: at most [`MAX_PER_SESSION`] identifiers per session (the
//! receive maximum) and [`MAX_SESSIONS`] sessions, in memory and in the
//! store; past that a publish's state is not kept (logged) and a resend of
//! it after the connection ends would be routed again.

use crate::store::{MetaKey, MetaRecord, Persistence, StoreOp};
use leveret_mqtt::PacketId;
use std::collections::{BTreeSet, HashMap};
use std::sync::{Arc, Mutex};
use std::time::Instant;

/// Identifiers kept per session.
const MAX_PER_SESSION: usize = 256;
/// Sessions with identifiers kept.
const MAX_SESSIONS: usize = 10_000;
/// At most this many records (or one session's) are rewritten under one
/// hold of the lock at start ([`Releases::settle_yielding`]).
const SETTLE_RECORDS: usize = 256;
/// The stored Session Expiry Interval of a session that never expires.
const NEVER: u32 = u32::MAX;
/// The Session Expiry Interval, in seconds, of records that carry none
/// (written before it was kept): a day, RabbitMQ's default
/// `mqtt.max_session_expiry_interval_seconds`.
const OLDER_RECORDS_EXPIRY: u32 = 86_400;

/// A session: vhost and client identifier.
type Key = (String, String);

/// By vhost and client identifier.
#[derive(Debug)]
pub(super) struct Releases {
    sessions: Mutex<HashMap<Key, Held>>,
    /// Sessions restored whose records carry another interval than they
    /// were given, for [`Releases::settle_yielding`] (locked after
    /// `sessions`).
    unsettled: Mutex<Vec<Key>>,
    persistence: Option<Arc<Persistence>>,
    max_sessions: usize,
}

/// One session's state.
#[derive(Debug, Default)]
struct Held {
    /// What the session's last connection left, for its next one (empty
    /// while it is connected).
    kept: Vec<PacketId>,
    /// The identifiers in the store.
    stored: BTreeSet<u16>,
    /// The session's expiry interval in seconds (`None`: never), stored
    /// with each record.
    expiry: Option<u32>,
    /// The interval its records carry in the store ([`NEVER`]: never;
    /// `None`: none, as an older Leveret wrote them, or not all the same):
    /// they are rewritten whenever it is not `expiry`'s.
    in_store: Option<u32>,
    /// When it goes unless a connection resumes the session first
    /// (`None` while it is connected, or if it never expires).
    expires_at: Option<Instant>,
}

impl Held {
    fn expired(&self, now: Instant) -> bool {
        super::expiry::has_passed(self.expires_at, now)
    }
}

impl Releases {
    /// The unreleased publishes among `recovered` (the store's metadata),
    /// kept for their sessions' next connections, their sessions' expiry
    /// (at most the broker's cap `max`, s) running from now.
    pub(super) fn new(
        recovered: &[MetaRecord],
        persistence: Option<Arc<Persistence>>,
        max: Option<u32>,
    ) -> Self {
        let mut sessions: HashMap<Key, Held> = HashMap::new();
        for record in recovered {
            if let MetaRecord::Unreleased {
                vhost,
                client_id,
                packet_id,
                session_expiry,
            } = record
            {
                let Some(id) = PacketId::new(*packet_id) else {
                    continue;
                };
                let held = (sessions.entry((vhost.clone(), client_id.clone()))).or_default();
                let first = held.stored.is_empty();
                held.stored.insert(id.get());
                held.kept.push(id);
                let expiry =
                    super::expiry::restored(session_expiry.unwrap_or(OLDER_RECORDS_EXPIRY), max);
                // Mixed intervals (a crash between rewrites): the longest,
                // whatever order the store reads them in.
                (held.expiry, held.in_store) = match first {
                    true => (expiry, *session_expiry),
                    false => (
                        super::expiry::longest(held.expiry, expiry),
                        held.in_store.filter(|&s| Some(s) == *session_expiry),
                    ),
                };
                held.expires_at = super::expiry::ends_at(held.expiry);
            }
        }
        let unsettled = (sessions.iter())
            .filter(|(_, held)| held.in_store != Some(held.expiry.unwrap_or(NEVER)))
            .map(|(key, _)| key.clone());
        Releases {
            unsettled: Mutex::new(unsettled.collect()),
            sessions: Mutex::new(sessions),
            persistence,
            max_sessions: MAX_SESSIONS,
        }
    }

    /// Whether session `client_id` of `vhost` holds QoS 2 state.
    pub(super) fn holds(&self, vhost: &str, client_id: &str) -> bool {
        let key = (vhost.to_owned(), client_id.to_owned());
        self.lock().contains_key(&key)
    }

    /// Writes back, at start, the interval each session restored from the
    /// store was given ([`Releases::new`]) to its records where they carry
    /// another (the cap lowered it; an older Leveret wrote none; a crash
    /// left them mixed): the records of at most [`SETTLE_RECORDS`] (or
    /// one session's) under one hold of the lock, yielding between.
    pub(super) async fn settle_yielding(&self) {
        while self.settle_batch() {
            tokio::task::yield_now().await;
        }
    }

    /// One batch of [`Releases::settle_yielding`]; whether any are left.
    fn settle_batch(&self) -> bool {
        let mut sessions = self.lock();
        let mut unsettled = (self.unsettled.lock()).unwrap_or_else(|e| e.into_inner());
        let mut records = 0;
        while records < SETTLE_RECORDS {
            let Some(key) = unsettled.pop() else {
                break;
            };
            if let Some(held) = sessions.get_mut(&key) {
                records += held.stored.len();
                let expiry = held.expiry;
                self.set_expiry(&key, held, expiry);
            }
        }
        !unsettled.is_empty()
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, HashMap<Key, Held>> {
        self.sessions.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// The expiry interval a session's state is kept for, if any is kept.
    #[cfg(test)]
    fn expiry_of(&self, vhost: &str, client_id: &str) -> Option<Option<u32>> {
        let key = (vhost.to_owned(), client_id.to_owned());
        self.lock().get(&key).map(|held| held.expiry)
    }

    fn submit(&self, op: StoreOp) -> u64 {
        self.persistence
            .as_ref()
            .map_or(0, |persistence| persistence.submit(vec![op]))
    }

    fn put(&self, (vhost, client_id): &Key, packet_id: u16, expiry: Option<u32>) -> u64 {
        self.submit(StoreOp::PutMeta(MetaRecord::Unreleased {
            vhost: vhost.clone(),
            client_id: client_id.clone(),
            packet_id,
            session_expiry: Some(expiry.unwrap_or(NEVER)),
        }))
    }

    fn delete(&self, (vhost, client_id): &Key, packet_id: u16) -> u64 {
        self.submit(StoreOp::DeleteMeta(MetaKey::Unreleased {
            vhost: vhost.clone(),
            client_id: client_id.clone(),
            packet_id,
        }))
    }

    /// Gives a session's records its expiry interval `expiry` (rewritten
    /// if they carry another).
    fn set_expiry(&self, key: &Key, held: &mut Held, expiry: Option<u32>) {
        held.expiry = expiry;
        let carried = Some(expiry.unwrap_or(NEVER));
        if held.in_store == carried {
            return;
        }
        held.in_store = carried;
        for &packet_id in &held.stored {
            self.put(key, packet_id, expiry);
        }
    }

    /// The place of session `key`, made if there is room (expired sessions
    /// swept first when there is none).
    fn place<'a>(&self, sessions: &'a mut HashMap<Key, Held>, key: &Key) -> Option<&'a mut Held> {
        if sessions.len() >= self.max_sessions && !sessions.contains_key(key) {
            self.sweep_locked(sessions);
        }
        if sessions.len() >= self.max_sessions && !sessions.contains_key(key) {
            return None;
        }
        Some(sessions.entry(key.clone()).or_default())
    }

    /// A persistent session's connection has ended: keeps its unreleased
    /// identifiers for its next connection, for `expiry` seconds from now
    /// (`None`: never), its interval then.
    pub(super) fn keep(
        &self,
        vhost: &str,
        client_id: &str,
        mut ids: Vec<PacketId>,
        expiry: Option<u32>,
    ) {
        let key = (vhost.to_owned(), client_id.to_owned());
        let mut sessions = self.lock();
        if ids.is_empty() && sessions.get(&key).is_none_or(|h| h.stored.is_empty()) {
            sessions.remove(&key);
            return;
        }
        let Some(held) = self.place(&mut sessions, &key) else {
            tracing::warn!(
                vhost,
                client_id,
                "QoS 2 state of a persistent MQTT session not kept: too many sessions hold some"
            );
            return;
        };
        ids.truncate(MAX_PER_SESSION);
        held.kept = ids;
        held.expires_at = super::expiry::ends_at(expiry);
        self.set_expiry(&key, held, expiry);
    }

    /// Takes what a session's previous connection (or the broker's
    /// previous run) left: for the session to hold if it `resumes` and
    /// has not expired, otherwise forgotten (and deleted from the store).
    /// A resuming session takes every identifier held, also those of a
    /// connection whose end kept nothing (abandoned by a takeover): each
    /// is a routed publish the client has not released.
    pub(super) fn take(&self, vhost: &str, client_id: &str, resumes: bool) -> Vec<PacketId> {
        let key = (vhost.to_owned(), client_id.to_owned());
        let mut sessions = self.lock();
        let Some(held) = sessions.get_mut(&key) else {
            return Vec::new();
        };
        if resumes && !held.expired(Instant::now()) {
            held.expires_at = None;
            let mut ids: BTreeSet<u16> = held.kept.drain(..).map(PacketId::get).collect();
            ids.extend(&held.stored);
            return ids.into_iter().filter_map(PacketId::new).collect();
        }
        if let Some(held) = sessions.remove(&key) {
            for packet_id in held.stored {
                self.delete(&key, packet_id);
            }
        }
        Vec::new()
    }

    /// Forgets what a session left (it ends with its connection).
    pub(super) fn forget(&self, vhost: &str, client_id: &str) {
        self.take(vhost, client_id, false);
    }

    /// Deletes the state of at most [`super::SWEEP_BATCH`] sessions that
    /// have expired (so one call's work under the lock is bounded); how
    /// many.
    pub(super) fn sweep(&self) -> usize {
        self.sweep_locked(&mut self.lock())
    }

    fn sweep_locked(&self, sessions: &mut HashMap<Key, Held>) -> usize {
        let now = Instant::now();
        let expired: Vec<Key> = (sessions.iter())
            .filter(|(_, held)| held.expired(now))
            .map(|(key, _)| key.clone())
            .take(super::SWEEP_BATCH)
            .collect();
        for key in &expired {
            if let Some(held) = sessions.remove(key) {
                for packet_id in held.stored {
                    self.delete(key, packet_id);
                }
            }
        }
        expired.len()
    }

    /// Stores that a persistent session (expiry interval `expiry`
    /// seconds, `None`: never) has its QoS 2 publish `id` routed and
    /// awaiting PUBREL; the store submission to wait for before the
    /// PUBREC (0: none, or not stored, past the bounds).
    pub(super) fn routed(
        &self,
        vhost: &str,
        client_id: &str,
        id: PacketId,
        expiry: Option<u32>,
    ) -> u64 {
        let key = (vhost.to_owned(), client_id.to_owned());
        let mut sessions = self.lock();
        let Some(held) = self.place(&mut sessions, &key) else {
            tracing::warn!(
                vhost,
                client_id,
                "QoS 2 publish state not stored: too many MQTT sessions hold some"
            );
            return 0;
        };
        if held.stored.len() >= MAX_PER_SESSION && !held.stored.contains(&id.get()) {
            tracing::warn!(
                vhost,
                client_id,
                "QoS 2 publish state not stored: the session holds {MAX_PER_SESSION} already"
            );
            return 0;
        }
        // A resuming CONNECT's interval is the session's now.
        self.set_expiry(&key, held, expiry);
        held.stored.insert(id.get());
        // Submitted under the lock: the store sees a session's changes in
        // the order memory does.
        self.put(&key, id.get(), expiry)
    }

    /// Deletes a released publish's state; the store submission to wait
    /// for before the PUBCOMP (0: none stored).
    pub(super) fn released(&self, vhost: &str, client_id: &str, id: PacketId) -> u64 {
        let key = (vhost.to_owned(), client_id.to_owned());
        let mut sessions = self.lock();
        let Some(held) = sessions.get_mut(&key) else {
            return 0;
        };
        if !held.stored.remove(&id.get()) {
            return 0;
        }
        if held.stored.is_empty() && held.kept.is_empty() {
            sessions.remove(&key);
        }
        self.delete(&key, id.get())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::store::{MemoryStore, Recovered, Store};

    fn id(n: u16) -> PacketId {
        PacketId::new(n).expect("not 0")
    }

    /// The unreleased records in `store`, once what was submitted is on it.
    async fn stored(store: &Arc<MemoryStore>, persistence: &Persistence) -> Vec<MetaRecord> {
        assert!(persistence.sync().await, "the store took the writes");
        let recovered = Recovered::from_scan(store.scan().expect("scan")).expect("decodes");
        let unreleased = recovered.meta.into_iter();
        unreleased
            .filter(|r| matches!(r, MetaRecord::Unreleased { .. }))
            .collect()
    }

    fn open(store: &Arc<MemoryStore>) -> (Releases, Arc<Persistence>) {
        let as_store: Arc<dyn Store> = Arc::clone(store) as Arc<dyn Store>;
        let recovered = Recovered::from_scan(store.scan().expect("scan")).expect("decodes");
        let persistence = Persistence::start(as_store, &recovered).expect("persister");
        let releases = Releases::new(&recovered.meta, Some(Arc::clone(&persistence)), None);
        (releases, persistence)
    }

    #[tokio::test]
    async fn an_expired_sessions_state_is_deleted_from_the_store_after_a_restart() {
        let store = Arc::new(MemoryStore::default());
        let (releases, persistence) = open(&store);
        // "gone" expires at once when its connection ends; "kept" never.
        releases.routed("/", "gone", id(1), Some(3600));
        releases.routed("/", "gone", id(2), Some(3600));
        releases.routed("/", "kept", id(7), None);
        // The DISCONNECT's interval rewrites the records.
        releases.keep("/", "gone", vec![id(1), id(2)], Some(0));
        releases.keep("/", "kept", vec![id(7)], None);
        let records = stored(&store, &persistence).await;
        assert_eq!(records.len(), 3);
        assert!(records.iter().any(|r| matches!(
            r,
            MetaRecord::Unreleased { client_id, session_expiry: Some(0), .. } if client_id == "gone"
        )));
        drop(releases);
        drop(persistence);
        // A restart: the interval runs from it (here 0 s, so it has passed).
        let (releases, persistence) = open(&store);
        assert_eq!(releases.sweep(), 1, "one session expired");
        let records = stored(&store, &persistence).await;
        let left: Vec<_> = records
            .iter()
            .map(|r| match r {
                MetaRecord::Unreleased {
                    client_id,
                    packet_id,
                    ..
                } => (client_id.as_str(), *packet_id),
                _ => unreachable!(),
            })
            .collect();
        assert_eq!(left, [("kept", 7)], "nothing of the expired session stays");
        assert!(releases.take("/", "gone", true).is_empty());
        assert_eq!(releases.take("/", "kept", true), [id(7)]);
        assert_eq!(releases.sweep(), 0);
    }

    #[tokio::test]
    async fn records_without_an_expiry_expire_after_a_day_or_with_their_session() {
        let store = Arc::new(MemoryStore::default());
        let (releases, persistence) = open(&store);
        // Written by a Leveret that did not keep the interval.
        let older = |client_id: &str, packet_id| {
            StoreOp::PutMeta(MetaRecord::Unreleased {
                vhost: "/".into(),
                client_id: client_id.into(),
                packet_id,
                session_expiry: None,
            })
        };
        persistence.submit(vec![older("gone", 1), older("back", 2)]);
        releases.routed("/", "forever", id(3), None);
        releases.keep("/", "forever", vec![id(3)], None);
        assert_eq!(stored(&store, &persistence).await.len(), 3);
        drop(releases);
        drop(persistence);
        let (releases, persistence) = open(&store);
        let day = Some(OLDER_RECORDS_EXPIRY);
        assert_eq!(releases.expiry_of("/", "gone"), Some(day));
        assert_eq!(releases.expiry_of("/", "forever"), Some(None), "never");
        // Seen again, ended with a minute: its record says so.
        assert_eq!(releases.take("/", "back", true), [id(2)]);
        releases.keep("/", "back", vec![id(2)], Some(60));
        let records = stored(&store, &persistence).await;
        assert!(records.iter().any(|r| matches!(
            r,
            MetaRecord::Unreleased { client_id, session_expiry: Some(60), .. } if client_id == "back"
        )));
    }

    #[tokio::test]
    async fn records_are_given_the_cap_at_start_if_they_outlive_it() {
        let store = Arc::new(MemoryStore::default());
        let (releases, persistence) = open(&store);
        // A 3.1.1 session stored as never expiring, one of a minute, and
        // one written before the interval was kept.
        releases.routed("/", "never", id(1), None);
        releases.routed("/", "minute", id(2), Some(60));
        persistence.submit(vec![StoreOp::PutMeta(MetaRecord::Unreleased {
            vhost: "/".into(),
            client_id: "older".into(),
            packet_id: 3,
            session_expiry: None,
        })]);
        let recovered = stored(&store, &persistence).await;
        let capped = Releases::new(&recovered, None, Some(30));
        for client_id in ["never", "minute", "older"] {
            assert_eq!(capped.expiry_of("/", client_id), Some(Some(30)));
        }
        let hour = Releases::new(&recovered, None, Some(3600));
        assert_eq!(hour.expiry_of("/", "never"), Some(Some(3600)));
        assert_eq!(hour.expiry_of("/", "minute"), Some(Some(60)));
        assert_eq!(hour.expiry_of("/", "older"), Some(Some(3600)));
        // A cap of 0: they ended with their connections, before the start.
        assert_eq!(Releases::new(&recovered, None, Some(0)).sweep(), 3);
    }

    /// The interval the unreleased records of `client_id` carry in `records`.
    fn carried(records: &[MetaRecord], client_id: &str) -> Vec<Option<u32>> {
        let carried = records.iter().filter_map(|r| match r {
            MetaRecord::Unreleased {
                client_id: c,
                session_expiry,
                ..
            } if c == client_id => Some(*session_expiry),
            _ => None,
        });
        carried.collect()
    }

    #[tokio::test]
    async fn what_a_start_gives_is_written_back_and_a_session_seen_again_rewrites_it() {
        let store = Arc::new(MemoryStore::default());
        let (releases, persistence) = open(&store);
        // A 3.1.1 session stored as never expiring, one of two hours, and
        // one written before the interval was kept.
        releases.routed("/", "never", id(1), None);
        releases.routed("/", "never", id(2), None);
        releases.routed("/", "hours", id(3), Some(7200));
        persistence.submit(vec![StoreOp::PutMeta(MetaRecord::Unreleased {
            vhost: "/".into(),
            client_id: "older".into(),
            packet_id: 4,
            session_expiry: None,
        })]);
        let recovered = stored(&store, &persistence).await;
        drop(releases);
        // A start under the default day, then one under an hour: each
        // writes back what it gave.
        for (max, want) in [(86_400, 86_400), (3600, 3600)] {
            let recovered = stored(&store, &persistence).await;
            let capped = Releases::new(&recovered, Some(Arc::clone(&persistence)), Some(max));
            capped.settle_yielding().await;
            let records = stored(&store, &persistence).await;
            assert_eq!(carried(&records, "never"), [Some(want), Some(want)]);
            assert_eq!(carried(&records, "hours"), [Some(want.min(7200))]);
            assert_eq!(carried(&records, "older"), [Some(want)]);
        }
        // A start under infinity keeps what the lower caps gave, as the
        // sessions' queues do.
        let records = stored(&store, &persistence).await;
        let unlimited = Releases::new(&records, Some(Arc::clone(&persistence)), None);
        unlimited.settle_yielding().await;
        assert_eq!(unlimited.expiry_of("/", "never"), Some(Some(3600)));
        assert_eq!(
            stored(&store, &persistence).await,
            records,
            "nothing to write"
        );
        // Seen again with the interval its records were restored with
        // (not written back here): its end rewrites them.
        let unwritten = Releases::new(&recovered, Some(Arc::clone(&persistence)), Some(60));
        assert_eq!(unwritten.take("/", "never", true), [id(1), id(2)]);
        unwritten.keep("/", "never", vec![id(1), id(2)], Some(60));
        let records = stored(&store, &persistence).await;
        assert_eq!(carried(&records, "never"), [Some(60), Some(60)]);
    }

    #[tokio::test]
    async fn start_up_write_back_is_bounded_per_hold_of_the_lock() {
        let store = Arc::new(MemoryStore::default());
        let (releases, persistence) = open(&store);
        let sessions = SETTLE_RECORDS + 3;
        for n in 0..sessions {
            releases.routed("/", &format!("c{n}"), id(1), None);
        }
        let recovered = stored(&store, &persistence).await;
        let capped = Releases::new(&recovered, Some(Arc::clone(&persistence)), Some(60));
        assert!(capped.settle_batch(), "more than one batch");
        assert!(!capped.settle_batch(), "the rest");
        let records = stored(&store, &persistence).await;
        assert!(records.iter().all(|r| matches!(
            r,
            MetaRecord::Unreleased {
                session_expiry: Some(60),
                ..
            }
        )));
    }

    #[tokio::test]
    async fn a_sweep_deletes_a_bounded_batch_of_expired_sessions_at_a_time() {
        let store = Arc::new(MemoryStore::default());
        let (releases, persistence) = open(&store);
        let sessions = super::super::SWEEP_BATCH * 2 + 3;
        for n in 0..sessions {
            let client_id = format!("c{n}");
            releases.routed("/", &client_id, id(1), Some(0));
            releases.keep("/", &client_id, vec![id(1)], Some(0));
        }
        let batch = super::super::SWEEP_BATCH;
        assert_eq!(releases.sweep(), batch);
        assert_eq!(releases.sweep(), batch);
        assert_eq!(releases.sweep(), 3, "the rest");
        assert_eq!(releases.sweep(), 0);
        assert!(stored(&store, &persistence).await.is_empty());
    }

    #[tokio::test]
    async fn a_clean_start_deletes_the_state_and_a_resumed_session_takes_it_unless_expired() {
        let store = Arc::new(MemoryStore::default());
        let (releases, persistence) = open(&store);
        releases.routed("/", "a", id(1), Some(3600));
        releases.keep("/", "a", vec![id(1)], Some(3600));
        assert_eq!(releases.sweep(), 0, "an hour has not passed");
        assert!(releases.take("/", "a", false).is_empty(), "a clean start");
        assert!(stored(&store, &persistence).await.is_empty());
        // Expired before its next connection: that finds none, and the
        // store holds none.
        releases.routed("/", "b", id(3), Some(1));
        releases.keep("/", "b", vec![id(3)], Some(0));
        assert!(releases.take("/", "b", true).is_empty());
        assert!(stored(&store, &persistence).await.is_empty());
    }

    #[test]
    fn a_resuming_session_takes_the_ids_a_connection_abandoned_at_its_end_held() {
        let store = Arc::new(MemoryStore::default());
        let durable = open(&store).0;
        let in_memory = Releases::new(&[], None, None);
        for releases in [&durable, &in_memory] {
            // The first connection's end kept 1; the next routed 2 and 3,
            // released 3, and its end kept nothing (a takeover abandoned it).
            releases.routed("/", "a", id(1), Some(3600));
            releases.keep("/", "a", vec![id(1)], Some(3600));
            assert_eq!(releases.take("/", "a", true), vec![id(1)]);
            releases.routed("/", "a", id(2), Some(3600));
            releases.routed("/", "a", id(3), Some(3600));
            releases.released("/", "a", id(3));
            assert_eq!(releases.take("/", "a", true), vec![id(1), id(2)]);
        }
    }

    #[test]
    fn sessions_past_the_cap_keep_nothing_until_expired_ones_make_room() {
        let mut releases = Releases::new(&[], None, None);
        releases.max_sessions = 2;
        releases.keep("/", "a", vec![id(1)], Some(0));
        releases.keep("/", "b", vec![id(1)], None);
        // "a" has expired: swept to make room for "c".
        releases.keep("/", "c", vec![id(1)], None);
        releases.keep("/", "d", vec![id(1)], None);
        assert!(releases.take("/", "d", true).is_empty(), "past the cap");
        assert_eq!(releases.take("/", "c", true), [id(1)]);
        assert!(releases.take("/", "a", true).is_empty());
        let many: Vec<_> = (1..=1000).map(id).collect();
        releases.keep("/", "b", many, None);
        assert_eq!(releases.take("/", "b", true).len(), MAX_PER_SESSION);
    }
}
