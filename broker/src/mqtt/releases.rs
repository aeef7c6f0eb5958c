//! The QoS 2 publishes a persistent session had routed and PUBREC'd but
//! the client had not yet released (PUBREL) when its connection ended,
//! kept for the session's next connection so that a resend is not routed
//! twice and the PUBREL is answered. In memory: they do not survive a
//! restart. Bounded: at most [`MAX_PER_SESSION`] identifiers per session
//! (the receive maximum) and [`MAX_SESSIONS`] sessions; past that a
//! session's are not kept (logged).

use leveret_mqtt::PacketId;
use std::collections::HashMap;
use std::sync::Mutex;

/// Identifiers kept per session.
const MAX_PER_SESSION: usize = 256;
/// Sessions with identifiers kept.
const MAX_SESSIONS: usize = 10_000;

/// By vhost and client identifier.
#[derive(Debug, Default)]
pub(super) struct Releases {
    kept: Mutex<HashMap<(String, String), Vec<PacketId>>>,
}

impl Releases {
    fn lock(&self) -> std::sync::MutexGuard<'_, HashMap<(String, String), Vec<PacketId>>> {
        self.kept.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// Keeps a session's unreleased identifiers for its next connection.
    pub(super) fn keep(&self, vhost: &str, client_id: &str, mut ids: Vec<PacketId>) {
        let key = (vhost.to_owned(), client_id.to_owned());
        let mut kept = self.lock();
        kept.remove(&key);
        if ids.is_empty() {
            return;
        }
        if kept.len() >= MAX_SESSIONS {
            tracing::warn!(
                vhost,
                client_id,
                "QoS 2 state of a persistent MQTT session not kept: too many sessions hold some"
            );
            return;
        }
        ids.truncate(MAX_PER_SESSION);
        kept.insert(key, ids);
    }

    /// Takes what a session's previous connection left.
    pub(super) fn take(&self, vhost: &str, client_id: &str) -> Vec<PacketId> {
        let key = (vhost.to_owned(), client_id.to_owned());
        self.lock().remove(&key).unwrap_or_default()
    }
}
