//! The shared subscriptions (`$share/GROUP/FILTER`) of persistent
//! sessions: part of the session's state (MQTT 5.0, 4.1), kept for its
//! next connection, which joins its groups again without subscribing. With
//! a store they are durable ([`MetaRecord::SharedSubscription`], one record
//! per filter, written when the session subscribes and deleted when it
//! unsubscribes, starts clean or ends with its connection), so this holds
//! across a restart too. Like the unreleased QoS 2 publishes of
//! `releases`, they do not expire with a 5.0 Session Expiry Interval (only
//! queues do).
//!
//! Bounded: per session by the session's subscription cap, and at most
//! [`MAX_SESSIONS`] sessions hold some; past that a session's shared
//! subscriptions end with its connection (logged).

use super::subscriptions::Options;
use crate::store::{MetaKey, MetaRecord, Persistence, StoreOp};
use leveret_mqtt::QoS;
use std::collections::{BTreeMap, HashMap};
use std::num::NonZeroU32;
use std::sync::{Arc, Mutex};

/// Sessions with shared subscriptions kept.
const MAX_SESSIONS: usize = 10_000;

/// A session: vhost and client identifier.
type Key = (String, String);

/// By vhost and client identifier: filter → options.
#[derive(Debug)]
pub(super) struct Shares {
    kept: Mutex<HashMap<Key, BTreeMap<String, Options>>>,
    persistence: Option<Arc<Persistence>>,
    max_sessions: usize,
}

impl Shares {
    /// The shared subscriptions among `recovered` (the store's metadata).
    pub(super) fn new(recovered: &[MetaRecord], persistence: Option<Arc<Persistence>>) -> Self {
        let mut kept: HashMap<Key, BTreeMap<String, Options>> = HashMap::new();
        for record in recovered {
            if let MetaRecord::SharedSubscription {
                vhost,
                client_id,
                filter,
                qos,
                retain_as_published,
                subscription_id,
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
                kept.entry(key).or_default().insert(filter.clone(), options);
            }
        }
        Shares {
            kept: Mutex::new(kept),
            persistence,
            max_sessions: MAX_SESSIONS,
        }
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, HashMap<Key, BTreeMap<String, Options>>> {
        self.kept.lock().unwrap_or_else(|e| e.into_inner())
    }

    fn submit(&self, op: StoreOp) {
        if let Some(persistence) = &self.persistence {
            persistence.submit(vec![op]);
        }
    }

    /// The shared subscriptions a session holds.
    pub(super) fn held(&self, vhost: &str, client_id: &str) -> Vec<(String, Options)> {
        let key = (vhost.to_owned(), client_id.to_owned());
        let kept = self.lock();
        let held = kept.get(&key).into_iter().flatten();
        held.map(|(filter, options)| (filter.clone(), *options))
            .collect()
    }

    /// Keeps (or replaces) a persistent session's shared subscription
    /// `filter`; false if it is not kept (too many sessions hold some).
    pub(super) fn keep(
        &self,
        vhost: &str,
        client_id: &str,
        filter: &str,
        options: Options,
    ) -> bool {
        let key = (vhost.to_owned(), client_id.to_owned());
        let mut kept = self.lock();
        let sessions = kept.len();
        let filters = match kept.get_mut(&key) {
            Some(filters) => filters,
            None if sessions < self.max_sessions => kept.entry(key).or_default(),
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
        if filters.get(filter) == Some(&options) {
            return true;
        }
        filters.insert(filter.to_owned(), options);
        // Submitted under the lock: the store sees a session's changes in
        // the order memory does.
        self.submit(StoreOp::PutMeta(MetaRecord::SharedSubscription {
            vhost: vhost.to_owned(),
            client_id: client_id.to_owned(),
            filter: filter.to_owned(),
            qos: options.qos.level(),
            retain_as_published: options.retain_as_published,
            subscription_id: options.id.map_or(0, NonZeroU32::get),
        }));
        true
    }

    /// Drops a session's shared subscription `filter` (UNSUBSCRIBE).
    pub(super) fn remove(&self, vhost: &str, client_id: &str, filter: &str) {
        let key = (vhost.to_owned(), client_id.to_owned());
        let mut kept = self.lock();
        let Some(filters) = kept.get_mut(&key) else {
            return;
        };
        if filters.remove(filter).is_none() {
            return;
        }
        if filters.is_empty() {
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
        for filter in kept.remove(&key).unwrap_or_default().into_keys() {
            self.submit(StoreOp::DeleteMeta(MetaKey::SharedSubscription {
                vhost: vhost.to_owned(),
                client_id: client_id.to_owned(),
                filter,
            }));
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
        assert!(shares.keep("/", "a", "$share/g/x", options(QoS::AtLeastOnce)));
        assert!(shares.keep("/", "b", "$share/g/x", options(QoS::AtMostOnce)));
        assert!(!shares.keep("/", "c", "$share/g/x", options(QoS::AtMostOnce)));
        // A session already holding some may hold more.
        assert!(shares.keep("/", "a", "$share/h/y", options(QoS::ExactlyOnce)));
        assert_eq!(shares.held("/", "a").len(), 2);
        assert!(shares.held("/", "c").is_empty());
        shares.forget("/", "b");
        assert!(shares.held("/", "b").is_empty());
        assert!(shares.keep("/", "c", "$share/g/x", options(QoS::AtMostOnce)));
        shares.remove("/", "a", "$share/g/x");
        assert_eq!(
            shares.held("/", "a"),
            [("$share/h/y".to_owned(), options(QoS::ExactlyOnce))]
        );
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
        };
        let shares = Shares::new(&[record], None);
        let expected = Options {
            retain_as_published: true,
            id: NonZeroU32::new(7),
            ..options(QoS::AtLeastOnce)
        };
        assert_eq!(
            shares.held("v", "c"),
            [("$share/g/t/#".to_owned(), expected)]
        );
    }
}
