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
//! does.
//!
//! Bounded: per session by the session's subscription cap, and at most
//! [`MAX_SESSIONS`] sessions hold some (expired ones are swept when the
//! cap is reached); past that a session's shared subscriptions end with
//! its connection (logged).

use super::subscriptions::Options;
use crate::store::{MetaKey, MetaRecord, Persistence, StoreOp};
use leveret_mqtt::QoS;
use std::collections::{BTreeMap, HashMap};
use std::num::NonZeroU32;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

/// Sessions with shared subscriptions kept.
const MAX_SESSIONS: usize = 10_000;

/// A session: vhost and client identifier.
type Key = (String, String);

/// By vhost and client identifier.
#[derive(Debug)]
pub(super) struct Shares {
    kept: Mutex<HashMap<Key, Held>>,
    persistence: Option<Arc<Persistence>>,
    max_sessions: usize,
}

/// One session's shared subscriptions.
#[derive(Debug, Default)]
struct Held {
    /// Filter → options.
    filters: BTreeMap<String, Options>,
    /// The session's expiry interval in seconds (`None`: never), stored
    /// with each record.
    expiry: Option<u32>,
    /// When they go unless a connection resumes the session first
    /// (`None` while it is connected, or if it never expires).
    expires_at: Option<Instant>,
}

impl Held {
    fn expired(&self, now: Instant) -> bool {
        self.expires_at.is_some_and(|at| at <= now)
    }
}

/// When a session that ended now expires.
fn expires_at(expiry: Option<u32>) -> Option<Instant> {
    expiry.map(|seconds| Instant::now() + Duration::from_secs(seconds.into()))
}

impl Shares {
    /// The shared subscriptions among `recovered` (the store's metadata),
    /// their sessions' expiry running from now.
    pub(super) fn new(recovered: &[MetaRecord], persistence: Option<Arc<Persistence>>) -> Self {
        let mut kept: HashMap<Key, Held> = HashMap::new();
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
                let held = kept.entry((vhost.clone(), client_id.clone())).or_default();
                held.filters.insert(filter.clone(), options);
                held.expiry = (*session_expiry != u32::MAX).then_some(*session_expiry);
                held.expires_at = expires_at(held.expiry);
            }
        }
        Shares {
            kept: Mutex::new(kept),
            persistence,
            max_sessions: MAX_SESSIONS,
        }
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, HashMap<Key, Held>> {
        self.kept.lock().unwrap_or_else(|e| e.into_inner())
    }

    fn submit(&self, op: StoreOp) {
        if let Some(persistence) = &self.persistence {
            persistence.submit(vec![op]);
        }
    }

    /// Stores a session's shared subscription (replacing its record).
    fn store(&self, key: &Key, filter: &str, options: Options, expiry: Option<u32>) {
        self.submit(StoreOp::PutMeta(MetaRecord::SharedSubscription {
            vhost: key.0.clone(),
            client_id: key.1.clone(),
            filter: filter.to_owned(),
            qos: options.qos.level(),
            retain_as_published: options.retain_as_published,
            subscription_id: options.id.map_or(0, NonZeroU32::get),
            session_expiry: expiry.unwrap_or(u32::MAX),
        }));
    }

    /// Deletes a session's records.
    fn delete(&self, key: &Key, held: Held) {
        for filter in held.filters.into_keys() {
            self.submit(StoreOp::DeleteMeta(MetaKey::SharedSubscription {
                vhost: key.0.clone(),
                client_id: key.1.clone(),
                filter,
            }));
        }
    }

    /// The shared subscriptions of a session a connection resumes (none
    /// once it has expired: then forgotten); they do not expire while it
    /// is connected.
    pub(super) fn resume(&self, vhost: &str, client_id: &str) -> Vec<(String, Options)> {
        let key = (vhost.to_owned(), client_id.to_owned());
        let mut kept = self.lock();
        if kept
            .get(&key)
            .is_some_and(|held| held.expired(Instant::now()))
        {
            if let Some(expired) = kept.remove(&key) {
                self.delete(&key, expired);
            }
            return Vec::new();
        }
        let Some(held) = kept.get_mut(&key) else {
            return Vec::new();
        };
        held.expires_at = None;
        let filters = held.filters.iter();
        filters
            .map(|(filter, options)| (filter.clone(), *options))
            .collect()
    }

    /// A persistent session's connection has ended: its shared
    /// subscriptions expire `expiry` seconds from now (`None`: never), its
    /// interval then (a DISCONNECT may have changed it: stored again).
    pub(super) fn ended(&self, vhost: &str, client_id: &str, expiry: Option<u32>) {
        let key = (vhost.to_owned(), client_id.to_owned());
        let mut kept = self.lock();
        let Some(held) = kept.get_mut(&key) else {
            return;
        };
        held.expires_at = expires_at(expiry);
        if held.expiry != expiry {
            held.expiry = expiry;
            for (filter, options) in &held.filters {
                self.store(&key, filter, *options, expiry);
            }
        }
    }

    /// Keeps (or replaces) shared subscription `filter` of a connected
    /// persistent session whose expiry interval is `expiry` seconds
    /// (`None`: never); false if it is not kept (too many sessions hold
    /// some).
    pub(super) fn keep(
        &self,
        (vhost, client_id): (&str, &str),
        filter: &str,
        options: Options,
        expiry: Option<u32>,
    ) -> bool {
        let key = (vhost.to_owned(), client_id.to_owned());
        let mut kept = self.lock();
        if kept.len() >= self.max_sessions && !kept.contains_key(&key) {
            self.sweep(&mut kept);
        }
        let sessions = kept.len();
        let held = match kept.get_mut(&key) {
            Some(held) => held,
            None if sessions < self.max_sessions => kept.entry(key.clone()).or_default(),
            None => {
                tracing::warn!(
                    vhost,
                    client_id,
                    filter,
                    "shared subscription not kept by the persistent MQTT session: too many sessions hold some"
                );
                return false;
            }
        };
        held.expires_at = None;
        if held.filters.get(filter) == Some(&options) && held.expiry == expiry {
            return true;
        }
        held.filters.insert(filter.to_owned(), options);
        held.expiry = expiry;
        // Submitted under the lock: the store sees a session's changes in
        // the order memory does.
        self.store(&key, filter, options, expiry);
        true
    }

    /// Forgets the sessions whose shared subscriptions have expired.
    fn sweep(&self, kept: &mut HashMap<Key, Held>) {
        let now = Instant::now();
        let expired: Vec<Key> = (kept.iter())
            .filter(|(_, held)| held.expired(now))
            .map(|(key, _)| key.clone())
            .collect();
        for key in expired {
            if let Some(held) = kept.remove(&key) {
                self.delete(&key, held);
            }
        }
    }

    /// Drops a session's shared subscription `filter` (UNSUBSCRIBE).
    pub(super) fn remove(&self, vhost: &str, client_id: &str, filter: &str) {
        let key = (vhost.to_owned(), client_id.to_owned());
        let mut kept = self.lock();
        let Some(held) = kept.get_mut(&key) else {
            return;
        };
        if held.filters.remove(filter).is_none() {
            return;
        }
        if held.filters.is_empty() {
            kept.remove(&key);
        }
        self.submit(StoreOp::DeleteMeta(MetaKey::SharedSubscription {
            vhost: vhost.to_owned(),
            client_id: client_id.to_owned(),
            filter: filter.to_owned(),
        }));
    }

    /// Forgets every shared subscription of a session (it starts clean
    /// or ends with its connection).
    pub(super) fn forget(&self, vhost: &str, client_id: &str) {
        let key = (vhost.to_owned(), client_id.to_owned());
        let mut kept = self.lock();
        if let Some(held) = kept.remove(&key) {
            self.delete(&key, held);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

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
        let mut shares = Shares::new(&[], None);
        shares.max_sessions = 2;
        let keep =
            |shares: &Shares, id, filter, qos| shares.keep(("/", id), filter, options(qos), None);
        assert!(keep(&shares, "a", "$share/g/x", QoS::AtLeastOnce));
        assert!(keep(&shares, "b", "$share/g/x", QoS::AtMostOnce));
        assert!(!keep(&shares, "c", "$share/g/x", QoS::AtMostOnce));
        // A session already holding some may hold more.
        assert!(keep(&shares, "a", "$share/h/y", QoS::ExactlyOnce));
        assert_eq!(shares.resume("/", "a").len(), 2);
        assert!(shares.resume("/", "c").is_empty());
        shares.forget("/", "b");
        assert!(shares.resume("/", "b").is_empty());
        assert!(keep(&shares, "c", "$share/g/x", QoS::AtMostOnce));
        shares.remove("/", "a", "$share/g/x");
        assert_eq!(
            shares.resume("/", "a"),
            [("$share/h/y".to_owned(), options(QoS::ExactlyOnce))]
        );
    }

    #[test]
    fn expired_sessions_hold_none_and_make_room_at_the_cap() {
        let mut shares = Shares::new(&[], None);
        shares.max_sessions = 1;
        let zero = options(QoS::AtMostOnce);
        assert!(shares.keep(("/", "a"), "$share/g/x", zero, Some(0)));
        // Connected: no expiry runs.
        assert_eq!(shares.resume("/", "a").len(), 1);
        shares.ended("/", "a", Some(0));
        // Expired, so a new session takes its place at the cap.
        assert!(shares.keep(("/", "b"), "$share/g/x", zero, None));
        assert!(shares.resume("/", "a").is_empty());
        shares.ended("/", "b", Some(3600));
        assert_eq!(shares.resume("/", "b").len(), 1, "an hour has not passed");
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
        let shares = Shares::new(&[record], None);
        let expected = Options {
            retain_as_published: true,
            id: NonZeroU32::new(7),
            ..options(QoS::AtLeastOnce)
        };
        assert_eq!(
            shares.resume("v", "c"),
            [("$share/g/t/#".to_owned(), expected)]
        );
    }
}
