//! The QoS 2 publishes a persistent session had routed and PUBREC'd but
//! the client had not yet released (PUBREL): kept for the session's next
//! connection, so that a resend is not routed twice and the PUBREL is
//! answered. With a store they are durable ([`MetaRecord::Unreleased`],
//! one record per packet identifier, written before the PUBREC and
//! deleted before the PUBCOMP), so this holds across a restart too.
//!
//! Bounded: at most [`MAX_PER_SESSION`] identifiers per session (the
//! receive maximum) and [`MAX_SESSIONS`] sessions, in memory and in the
//! store; past that a publish's state is not kept (logged) and a resend of
//! it after the connection ends would be routed again.

use crate::store::{MetaKey, MetaRecord, Persistence, StoreOp};
use leveret_mqtt::PacketId;
use std::collections::{BTreeSet, HashMap};
use std::sync::{Arc, Mutex};

/// Identifiers kept per session.
const MAX_PER_SESSION: usize = 256;
/// Sessions with identifiers kept.
const MAX_SESSIONS: usize = 10_000;

/// A session: vhost and client identifier.
type Key = (String, String);

/// By vhost and client identifier.
#[derive(Debug, Default)]
pub(super) struct Releases {
    state: Mutex<State>,
    persistence: Option<Arc<Persistence>>,
}

#[derive(Debug, Default)]
struct State {
    /// What sessions not connected left, for their next connection.
    kept: HashMap<Key, Vec<PacketId>>,
    /// The identifiers in the store, per session (connected or not).
    stored: HashMap<Key, BTreeSet<u16>>,
}

impl Releases {
    /// The unreleased publishes among `recovered` (the store's metadata),
    /// kept for their sessions' next connections.
    pub(super) fn new(recovered: &[MetaRecord], persistence: Option<Arc<Persistence>>) -> Self {
        let mut state = State::default();
        for record in recovered {
            if let MetaRecord::Unreleased {
                vhost,
                client_id,
                packet_id,
            } = record
            {
                let Some(id) = PacketId::new(*packet_id) else {
                    continue;
                };
                let key = (vhost.clone(), client_id.clone());
                state
                    .stored
                    .entry(key.clone())
                    .or_default()
                    .insert(id.get());
                state.kept.entry(key).or_default().push(id);
            }
        }
        Releases {
            state: Mutex::new(state),
            persistence,
        }
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, State> {
        self.state.lock().unwrap_or_else(|e| e.into_inner())
    }

    fn submit(&self, op: StoreOp) -> u64 {
        self.persistence
            .as_ref()
            .map_or(0, |persistence| persistence.submit(vec![op]))
    }

    /// Keeps a session's unreleased identifiers for its next connection.
    pub(super) fn keep(&self, vhost: &str, client_id: &str, mut ids: Vec<PacketId>) {
        let key = (vhost.to_owned(), client_id.to_owned());
        let mut state = self.lock();
        state.kept.remove(&key);
        if ids.is_empty() {
            return;
        }
        if state.kept.len() >= MAX_SESSIONS {
            tracing::warn!(
                vhost,
                client_id,
                "QoS 2 state of a persistent MQTT session not kept: too many sessions hold some"
            );
            return;
        }
        ids.truncate(MAX_PER_SESSION);
        state.kept.insert(key, ids);
    }

    /// Takes what a session's previous connection (or the broker's
    /// previous run) left: for the session to hold if it `resumes`,
    /// otherwise forgotten (and deleted from the store).
    pub(super) fn take(&self, vhost: &str, client_id: &str, resumes: bool) -> Vec<PacketId> {
        let key = (vhost.to_owned(), client_id.to_owned());
        let mut state = self.lock();
        let ids = state.kept.remove(&key).unwrap_or_default();
        if resumes {
            return ids;
        }
        let stored = state.stored.remove(&key).unwrap_or_default();
        drop(state);
        for packet_id in stored {
            self.submit(StoreOp::DeleteMeta(MetaKey::Unreleased {
                vhost: vhost.to_owned(),
                client_id: client_id.to_owned(),
                packet_id,
            }));
        }
        Vec::new()
    }

    /// Forgets what a session left (it ends with its connection).
    pub(super) fn forget(&self, vhost: &str, client_id: &str) {
        self.take(vhost, client_id, false);
    }

    /// Stores that a persistent session's QoS 2 publish `id` is routed and
    /// awaits PUBREL; the store submission to wait for before the PUBREC
    /// (0: none, or not stored, past the bounds).
    pub(super) fn routed(&self, vhost: &str, client_id: &str, id: PacketId) -> u64 {
        if self.persistence.is_none() {
            return 0;
        }
        let key = (vhost.to_owned(), client_id.to_owned());
        let mut state = self.lock();
        let sessions = state.stored.len();
        let ids = match state.stored.get_mut(&key) {
            Some(ids) => ids,
            None if sessions < MAX_SESSIONS => state.stored.entry(key).or_default(),
            None => {
                tracing::warn!(
                    vhost,
                    client_id,
                    "QoS 2 publish state not stored: too many MQTT sessions hold some"
                );
                return 0;
            }
        };
        if ids.len() >= MAX_PER_SESSION && !ids.contains(&id.get()) {
            tracing::warn!(
                vhost,
                client_id,
                "QoS 2 publish state not stored: the session holds {MAX_PER_SESSION} already"
            );
            return 0;
        }
        ids.insert(id.get());
        // Submitted under the lock: the store sees a session's changes in
        // the order memory does.
        self.submit(StoreOp::PutMeta(MetaRecord::Unreleased {
            vhost: vhost.to_owned(),
            client_id: client_id.to_owned(),
            packet_id: id.get(),
        }))
    }

    /// Deletes a released publish's state; the store submission to wait
    /// for before the PUBCOMP (0: none stored).
    pub(super) fn released(&self, vhost: &str, client_id: &str, id: PacketId) -> u64 {
        let key = (vhost.to_owned(), client_id.to_owned());
        let mut state = self.lock();
        let Some(ids) = state.stored.get_mut(&key) else {
            return 0;
        };
        if !ids.remove(&id.get()) {
            return 0;
        }
        if ids.is_empty() {
            state.stored.remove(&key);
        }
        self.submit(StoreOp::DeleteMeta(MetaKey::Unreleased {
            vhost: vhost.to_owned(),
            client_id: client_id.to_owned(),
            packet_id: id.get(),
        }))
    }
}
