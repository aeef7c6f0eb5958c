//! Which connections and channels the broker serves: RabbitMQ's
//! `connection_max` (TCP connections at once), the vhost limit
//! `max-connections`, and the user limits `max-connections` and
//! `max-channels` (every user's connections and channels are counted, so
//! that limits set at run time count what is already open). Each served
//! connection holds a
//! [`Slot`] whose drop gives its places back, whatever way the connection
//! ends. Uses nothing else of the broker.

use leveret_protocol::ShortStr;
use std::collections::HashMap;
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::sync::{Arc, Mutex};

/// Connection counts, broker-wide and per vhost.
#[derive(Debug)]
pub struct Admission {
    network: AtomicUsize,
    max_network: Option<usize>,
    /// Connections per vhost name. The lock is held for one hash-map
    /// update, never across an await.
    per_vhost: Mutex<HashMap<ShortStr, usize>>,
    /// Connections and channels per user. The lock is held for one
    /// hash-map update, never across an await.
    per_user: Mutex<HashMap<String, UserCount>>,
    /// Set while connections are being refused, so that a flood of them
    /// logs one warning rather than one per connection.
    refusing: AtomicBool,
}

/// What a user has open.
#[derive(Debug, Default)]
struct UserCount {
    connections: usize,
    channels: usize,
}

/// A served connection's places in the counts.
#[derive(Debug)]
pub struct Slot {
    admission: Arc<Admission>,
    network: bool,
    vhost: Option<ShortStr>,
    /// The user, once the connection has one.
    user: Option<String>,
    /// Channels this connection counts for its user.
    channels: usize,
}

impl Admission {
    /// Counts with at most `max_network` TCP connections (`None`: no limit).
    pub fn new(max_network: Option<usize>) -> Arc<Self> {
        Arc::new(Admission {
            network: AtomicUsize::new(0),
            max_network,
            per_vhost: Mutex::new(HashMap::new()),
            per_user: Mutex::new(HashMap::new()),
            refusing: AtomicBool::new(false),
        })
    }

    /// TCP connections served now.
    pub fn network_count(&self) -> usize {
        self.network.load(Ordering::Relaxed)
    }

    /// A slot for a TCP connection, or `Err(limit)` when `max_connections`
    /// connections are already served (logged: a warning when refusing
    /// starts, then one debug line per refused connection).
    pub fn admit_network(self: &Arc<Self>, peer: &str) -> Result<Slot, usize> {
        let admitted =
            self.network
                .fetch_update(Ordering::AcqRel, Ordering::Acquire, |n| {
                    match self.max_network {
                        Some(max) if n >= max => None,
                        _ => Some(n + 1),
                    }
                });
        match (admitted, self.max_network) {
            (Ok(_), _) | (Err(_), None) => {
                self.refusing.store(false, Ordering::Relaxed);
                Ok(Slot {
                    admission: Arc::clone(self),
                    network: true,
                    vhost: None,
                    user: None,
                    channels: 0,
                })
            }
            (Err(_), Some(limit)) => {
                if !self.refusing.swap(true, Ordering::Relaxed) {
                    tracing::warn!(
                        %peer,
                        limit,
                        "connection refused: node connection limit ({limit}) is reached; refusing connections until one closes"
                    );
                } else {
                    tracing::debug!(%peer, limit, "connection refused: node connection limit is reached");
                }
                Err(limit)
            }
        }
    }

    /// A slot for an in-process connection (not counted against
    /// `max_connections`).
    pub fn admit_local(self: &Arc<Self>) -> Slot {
        Slot {
            admission: Arc::clone(self),
            network: false,
            vhost: None,
            user: None,
            channels: 0,
        }
    }

    fn per_vhost(&self) -> std::sync::MutexGuard<'_, HashMap<ShortStr, usize>> {
        self.per_vhost.lock().unwrap_or_else(|e| e.into_inner())
    }

    fn per_user(&self) -> std::sync::MutexGuard<'_, HashMap<String, UserCount>> {
        self.per_user.lock().unwrap_or_else(|e| e.into_inner())
    }
}

impl Slot {
    /// Counts the connection in `vhost`, unless `limit` connections are
    /// already open there (`Err(limit)`).
    pub fn enter_vhost(&mut self, vhost: &ShortStr, limit: Option<usize>) -> Result<(), usize> {
        debug_assert!(self.vhost.is_none(), "a connection opens one vhost");
        let mut counts = self.admission.per_vhost();
        let count = counts.entry(vhost.clone()).or_insert(0);
        if let Some(limit) = limit {
            if *count >= limit {
                if *count == 0 {
                    counts.remove(vhost);
                }
                return Err(limit);
            }
        }
        *count += 1;
        self.vhost = Some(vhost.clone());
        Ok(())
    }
}

/// Which user limit refused.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct OverLimit(pub usize);

impl Slot {
    /// Counts the connection for `user`, unless they have
    /// `max_connections` open already.
    pub fn enter_user(
        &mut self,
        user: &str,
        max_connections: Option<usize>,
    ) -> Result<(), OverLimit> {
        debug_assert!(self.user.is_none(), "a connection has one user");
        let mut counts = self.admission.per_user();
        let count = counts.entry(user.to_owned()).or_default();
        if let Some(limit) = max_connections {
            if count.connections >= limit {
                if count.connections == 0 && count.channels == 0 {
                    counts.remove(user);
                }
                return Err(OverLimit(limit));
            }
        }
        count.connections += 1;
        self.user = Some(user.to_owned());
        Ok(())
    }

    /// Counts one more channel for the user, unless they have `limit`
    /// (their `max-channels`) open already.
    pub fn open_channel(&mut self, limit: Option<usize>) -> Result<(), OverLimit> {
        let Some(user) = &self.user else {
            return Ok(());
        };
        let mut counts = self.admission.per_user();
        let count = counts.entry(user.clone()).or_default();
        if let Some(limit) = limit {
            if count.channels >= limit {
                return Err(OverLimit(limit));
            }
        }
        count.channels += 1;
        drop(counts);
        self.channels += 1;
        Ok(())
    }

    /// Gives back `closed` channels.
    pub fn close_channels(&mut self, closed: usize) {
        let Some(user) = &self.user else {
            return;
        };
        let closed = closed.min(self.channels);
        self.channels -= closed;
        if let Some(count) = self.admission.per_user().get_mut(user) {
            count.channels = count.channels.saturating_sub(closed);
        }
    }
}

impl Drop for Slot {
    fn drop(&mut self) {
        if let Some(user) = self.user.take() {
            let mut counts = self.admission.per_user();
            if let Some(count) = counts.get_mut(&user) {
                count.connections = count.connections.saturating_sub(1);
                count.channels = count.channels.saturating_sub(self.channels);
                if count.connections == 0 && count.channels == 0 {
                    counts.remove(&user);
                }
            }
        }
        if self.network {
            self.admission.network.fetch_sub(1, Ordering::AcqRel);
        }
        if let Some(vhost) = self.vhost.take() {
            let mut counts = self.admission.per_vhost();
            if let Some(count) = counts.get_mut(&vhost) {
                *count -= 1;
                if *count == 0 {
                    counts.remove(&vhost);
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn user_limits_count_connections_and_channels_across_connections() {
        let admission = Admission::new(None);
        let mut a = admission.admit_network("a").expect("a");
        let mut b = admission.admit_network("b").expect("b");
        let mut c = admission.admit_network("c").expect("c");
        let max = Some(3);
        a.enter_user("robot", Some(2)).expect("first");
        b.enter_user("robot", Some(2)).expect("second");
        assert_eq!(c.enter_user("robot", Some(2)), Err(OverLimit(2)));
        a.open_channel(max).expect("1");
        a.open_channel(max).expect("2");
        b.open_channel(max).expect("3");
        assert_eq!(b.open_channel(max), Err(OverLimit(3)), "across connections");
        a.close_channels(1);
        b.open_channel(max).expect("a place was given back");
        drop(a);
        c.enter_user("robot", Some(2)).expect("a connection closed");
        c.open_channel(max).expect("its channel went with it");
        assert_eq!(c.open_channel(max), Err(OverLimit(3)));
        drop((b, c));
        assert!(admission.per_user().is_empty(), "nothing left behind");
        // A user without limits is counted, so that a limit set later
        // counts what they already have open.
        let mut free = admission.admit_network("d").expect("d");
        free.enter_user("free", None).expect("no limit");
        for _ in 0..10 {
            free.open_channel(None).expect("no limit");
        }
        assert_eq!(free.open_channel(Some(10)), Err(OverLimit(10)));
        drop(free);
        assert!(admission.per_user().is_empty());
    }

    #[test]
    fn network_connections_are_limited_and_slots_give_their_place_back() {
        let admission = Admission::new(Some(2));
        let a = admission.admit_network("a").expect("first");
        let b = admission.admit_network("b").expect("second");
        assert_eq!(admission.admit_network("c").unwrap_err(), 2);
        let local = admission.admit_local();
        assert_eq!(
            admission.network.load(Ordering::Acquire),
            2,
            "in-process ones are not counted"
        );
        drop(a);
        let _c = admission.admit_network("c").expect("a place was freed");
        drop((b, local));
        assert_eq!(admission.network.load(Ordering::Acquire), 1);
    }

    #[test]
    fn vhost_connections_are_limited_per_vhost() {
        let admission = Admission::new(None);
        let (slash, other) = (ShortStr::from_static("/"), ShortStr::from_static("other"));
        let mut a = admission.admit_local();
        a.enter_vhost(&slash, Some(1)).expect("first in /");
        let mut b = admission.admit_local();
        assert_eq!(b.enter_vhost(&slash, Some(1)), Err(1));
        b.enter_vhost(&other, Some(1))
            .expect("another vhost has its own count");
        let mut zero = admission.admit_local();
        assert_eq!(
            zero.enter_vhost(&ShortStr::from_static("closed"), Some(0)),
            Err(0)
        );
        drop(a);
        let mut c = admission.admit_local();
        c.enter_vhost(&slash, Some(1))
            .expect("the place was given back");
        drop((b, c, zero));
        assert!(admission.per_vhost().is_empty(), "no counts left behind");
    }
}
