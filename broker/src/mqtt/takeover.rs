//! Client-identifier takeover: at most one session per client identifier
//! and vhost. A CONNECT with an identifier in use asks the session holding
//! it to close and waits until it has ended (its AMQP link cleaned up, so
//! its exclusive subscription queues are gone) before going on. The map
//! lock is held for one insert or remove, never across an await.

use std::collections::HashMap;
use std::sync::{Arc, Mutex};
use std::time::Duration;
use tokio::sync::{watch, Notify};

/// How long a new session waits for the one it takes over to end.
const TAKEOVER_WAIT: Duration = Duration::from_secs(10);

/// The sessions open on a broker's MQTT listeners, by vhost and client id.
#[derive(Debug, Default)]
pub(crate) struct ClientIds {
    open: Mutex<HashMap<(String, String), Arc<Holder>>>,
}

/// A session's hold on its client identifier.
#[derive(Debug)]
struct Holder {
    /// Told when another session takes the identifier over.
    kick: Notify,
    /// Set when the holding session has ended.
    ended: watch::Sender<bool>,
}

/// A session's claim; dropping it when the session has ended releases the
/// identifier and lets a session taking it over go on.
#[derive(Debug)]
pub(super) struct Claim {
    ids: Arc<ClientIds>,
    key: (String, String),
    holder: Arc<Holder>,
}

impl ClientIds {
    /// Claims `client_id` in `vhost`, closing the session that held it
    /// and waiting (bounded) for it to end.
    pub(super) async fn claim(self: &Arc<Self>, vhost: &str, client_id: &str) -> Claim {
        let key = (vhost.to_owned(), client_id.to_owned());
        let holder = Arc::new(Holder {
            kick: Notify::new(),
            ended: watch::channel(false).0,
        });
        let previous = self.lock().insert(key.clone(), Arc::clone(&holder));
        if let Some(previous) = previous {
            let mut ended = previous.ended.subscribe();
            previous.kick.notify_one();
            let waited = tokio::time::timeout(TAKEOVER_WAIT, ended.wait_for(|e| *e)).await;
            if waited.is_err() {
                tracing::warn!(client_id, vhost, "session taken over did not end in time");
            }
        }
        Claim {
            ids: Arc::clone(self),
            key,
            holder,
        }
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, HashMap<(String, String), Arc<Holder>>> {
        self.open.lock().unwrap_or_else(|e| e.into_inner())
    }
}

impl Claim {
    /// Resolves when another session has taken the identifier over.
    pub(super) async fn taken_over(&self) {
        self.holder.kick.notified().await;
    }
}

impl Drop for Claim {
    fn drop(&mut self) {
        let mut open = self.ids.lock();
        if open
            .get(&self.key)
            .is_some_and(|holder| Arc::ptr_eq(holder, &self.holder))
        {
            open.remove(&self.key);
        }
        drop(open);
        self.holder.ended.send_replace(true);
    }
}
