//! Client-identifier takeover: at most one session per client identifier
//! and vhost. A CONNECT with an identifier in use asks the session holding
//! it to close and waits until it has ended (its AMQP link cleaned up, so
//! its exclusive subscription queues are gone) before going on, at most
//! the handshake timeout. The map lock is held for one insert or remove,
//! never across an await. If it has not ended in time the new session
//! goes on and the old one's claim is abandoned: the old one's end then
//! only closes its socket and its link ([`Claim::abandoned`]); every
//! other effect of its end (the state a session keeps, its queues' expiry
//! or deletion, its will: [`Claim::unless_abandoned`]) is skipped, as the
//! new session owns the session now.

use std::collections::HashMap;
use std::sync::{Arc, Mutex};
use std::time::Duration;
use tokio::sync::{watch, Notify};

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
    /// Set when a session taking over has stopped waiting for this one.
    abandoned: Mutex<bool>,
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
    /// and waiting for it to end, at most `wait`.
    pub(super) async fn claim(
        self: &Arc<Self>,
        vhost: &str,
        client_id: &str,
        wait: Duration,
    ) -> Claim {
        let key = (vhost.to_owned(), client_id.to_owned());
        let holder = Arc::new(Holder {
            kick: Notify::new(),
            ended: watch::channel(false).0,
            abandoned: Mutex::new(false),
        });
        let previous = self.lock().insert(key.clone(), Arc::clone(&holder));
        if let Some(previous) = previous {
            let mut ended = previous.ended.subscribe();
            previous.kick.notify_one();
            let waited = tokio::time::timeout(wait, ended.wait_for(|e| *e)).await;
            if waited.is_err() {
                tracing::warn!(client_id, vhost, "session taken over did not end in time");
                // Waits for an `unless_abandoned` under way.
                *lock(&previous.abandoned) = true;
            }
        }
        Claim {
            ids: Arc::clone(self),
            key,
            holder,
        }
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, HashMap<(String, String), Arc<Holder>>> {
        lock(&self.open)
    }
}

fn lock<T>(mutex: &Mutex<T>) -> std::sync::MutexGuard<'_, T> {
    mutex.lock().unwrap_or_else(|e| e.into_inner())
}

impl Claim {
    /// Resolves when another session has taken the identifier over.
    pub(super) async fn taken_over(&self) {
        self.holder.kick.notified().await;
    }

    /// Whether a session taking the identifier over has stopped waiting
    /// for this one: its end then closes its socket and link and does
    /// nothing else.
    pub(super) fn abandoned(&self) -> bool {
        *lock(&self.holder.abandoned)
    }

    /// Runs `keep` (the session's end: the state it keeps stored or
    /// forgotten, its queues' expiry, its will taken) unless a session taking the identifier over has stopped
    /// waiting for this one (then that one has resumed the state already:
    /// `None`); a takeover's timeout waits until `keep` has returned.
    pub(super) fn unless_abandoned<T>(&self, keep: impl FnOnce() -> T) -> Option<T> {
        let abandoned = lock(&self.holder.abandoned);
        (!*abandoned).then(keep)
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

#[cfg(test)]
mod tests {
    use super::*;

    #[tokio::test]
    async fn a_session_taken_over_after_the_wait_keeps_nothing_at_its_end() {
        let ids = Arc::new(ClientIds::default());
        let wait = Duration::from_millis(20);
        // Ended within the wait: its end keeps its state.
        let first = ids.claim("/", "c", wait).await;
        let taking = tokio::spawn({
            let ids = Arc::clone(&ids);
            async move { ids.claim("/", "c", wait).await }
        });
        tokio::task::yield_now().await;
        assert_eq!(first.unless_abandoned(|| 1), Some(1));
        assert!(!first.abandoned());
        drop(first);
        let second = taking.await.expect("claimed");
        // Not ended within the wait: the new session goes on, and the old
        // one's end keeps nothing.
        let third = ids.claim("/", "c", wait).await;
        assert!(second.abandoned());
        assert_eq!(second.unless_abandoned(|| 2), None);
        assert_eq!(third.unless_abandoned(|| 3), Some(3));
    }
}
