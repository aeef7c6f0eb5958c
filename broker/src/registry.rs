//! Which connections and channels are open, for listing them and closing
//! one from outside (the management API's DELETE of a connection). A
//! connection registers when it is accepted and fills in who it is once
//! the handshake is done; each registration is a guard whose drop
//! unregisters it and counts the close. The registry's lock is a
//! `std::sync::Mutex` held for one map operation, never across an await;
//! nothing on the per-message path takes it.
//!
//! Each connection watches its own close signal instead of the broker's
//! shutdown signal: shutting down sets every one of them.

use crate::queue::ChannelLink;
use crate::stats::BrokerCounters;
use crate::stats::ConnectionTraffic;
use leveret_protocol::FieldTable;
use std::collections::{BTreeMap, HashMap};
use std::sync::atomic::{AtomicBool, AtomicU32, AtomicU64, AtomicU8, Ordering};
use std::sync::{Arc, Mutex, MutexGuard, OnceLock};
use std::time::SystemTime;
use tokio::sync::watch;

/// The close text when the broker itself shuts down.
const SHUTDOWN_REASON: &str = "broker is shutting down";

/// Open connections by id.
#[derive(Debug)]
pub(crate) struct Registry {
    state: Mutex<RegistryState>,
    counters: Arc<BrokerCounters>,
}

#[derive(Debug, Default)]
struct RegistryState {
    /// Set once the broker shuts down: later registrations start closed.
    closing_all: bool,
    connections: HashMap<u64, Arc<ConnectionEntry>>,
}

/// What the handshake established.
#[derive(Debug, Clone)]
pub(crate) struct Opened {
    pub user: String,
    pub vhost: String,
    pub client_properties: FieldTable,
    pub frame_max: u32,
    pub channel_max: u16,
    pub heartbeat_secs: u16,
}

/// One connection.
#[derive(Debug)]
pub(crate) struct ConnectionEntry {
    pub id: u64,
    pub peer: String,
    /// What the client speaks (`AMQP 0-9-1`, `MQTT 5.0`…).
    pub protocol: &'static str,
    pub connected_at: SystemTime,
    /// Its byte stream's traffic (`None` for frames exchanged in-process).
    pub traffic: Option<Arc<ConnectionTraffic>>,
    pub opened: OnceLock<Opened>,
    close: watch::Sender<bool>,
    /// Whether the connection has cleaned up ([`Registry::cleaned_up`]),
    /// for an MQTT takeover's [`Registry::close_and_wait`].
    #[cfg(feature = "mqtt")]
    cleaned: Cleaned,
    close_reason: Mutex<Option<String>>,
    channels: Mutex<BTreeMap<u16, Arc<ChannelEntry>>>,
}

impl ConnectionEntry {
    /// Its open channels, by number.
    pub fn channels(&self) -> Vec<Arc<ChannelEntry>> {
        lock(&self.channels).values().cloned().collect()
    }

    /// How many channels it has open.
    pub fn channel_count(&self) -> usize {
        lock(&self.channels).len()
    }
}

/// Whether a connection has cleaned up, and what wakes those waiting for
/// it: a flag and a notify kept in the connection's entry, so that no
/// connection allocates for what only an MQTT takeover asks.
#[cfg(feature = "mqtt")]
#[derive(Debug, Default)]
struct Cleaned {
    done: AtomicBool,
    notify: tokio::sync::Notify,
}

#[cfg(feature = "mqtt")]
impl Cleaned {
    fn set(&self) {
        self.done.store(true, Ordering::SeqCst);
        self.notify.notify_waiters();
    }

    async fn wait(&self) {
        loop {
            // Made before the flag is read: a set after the read wakes it.
            let notified = self.notify.notified();
            if self.done.load(Ordering::SeqCst) {
                return;
            }
            notified.await;
        }
    }
}

/// A channel's mode, for listings.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum ChannelMode {
    Plain = 0,
    Confirm = 1,
    Transactional = 2,
}

/// One channel.
#[derive(Debug)]
pub(crate) struct ChannelEntry {
    pub number: u16,
    pub link: Arc<ChannelLink>,
    mode: AtomicU8,
    prefetch: AtomicU32,
    publisher: AtomicBool,
    /// Publishes awaiting their confirm.
    unconfirmed: AtomicU64,
    /// Publishes held by the open transaction.
    uncommitted_messages: AtomicU64,
    /// Acks, nacks and rejects held by the open transaction.
    uncommitted_acks: AtomicU64,
}

impl ChannelEntry {
    /// Plain, confirm or transactional.
    pub fn mode(&self) -> ChannelMode {
        match self.mode.load(Ordering::Relaxed) {
            1 => ChannelMode::Confirm,
            2 => ChannelMode::Transactional,
            _ => ChannelMode::Plain,
        }
    }

    /// The per-consumer prefetch count new consumers get (basic.qos, not global).
    pub fn prefetch(&self) -> u32 {
        self.prefetch.load(Ordering::Relaxed)
    }

    /// Publishes awaiting their confirm, publishes and acks held by the
    /// open transaction.
    pub fn pending(&self) -> (u64, u64, u64) {
        (
            self.unconfirmed.load(Ordering::Relaxed),
            self.uncommitted_messages.load(Ordering::Relaxed),
            self.uncommitted_acks.load(Ordering::Relaxed),
        )
    }
}

fn lock<T>(mutex: &Mutex<T>) -> MutexGuard<'_, T> {
    mutex.lock().unwrap_or_else(|e| e.into_inner())
}

impl Registry {
    /// An empty registry counting into `counters`.
    pub fn new(counters: Arc<BrokerCounters>) -> Self {
        Registry {
            state: Mutex::new(RegistryState::default()),
            counters,
        }
    }

    /// Registers an accepted connection; it stays listed (once opened)
    /// until the guard drops.
    pub fn connection(
        self: &Arc<Self>,
        id: u64,
        peer: &str,
        protocol: &'static str,
        traffic: Option<Arc<ConnectionTraffic>>,
    ) -> ConnectionRegistration {
        let mut state = lock(&self.state);
        let entry = Arc::new(ConnectionEntry {
            id,
            peer: peer.to_owned(),
            protocol,
            connected_at: SystemTime::now(),
            traffic,
            opened: OnceLock::new(),
            close: watch::channel(state.closing_all).0,
            #[cfg(feature = "mqtt")]
            cleaned: Cleaned::default(),
            close_reason: Mutex::new(None),
            channels: Mutex::new(BTreeMap::new()),
        });
        state.connections.insert(id, Arc::clone(&entry));
        ConnectionRegistration {
            registry: Arc::clone(self),
            entry,
        }
    }

    fn entry(&self, id: u64) -> Option<Arc<ConnectionEntry>> {
        lock(&self.state).connections.get(&id).cloned()
    }

    /// The handshake of connection `id` is done.
    pub fn opened(&self, id: u64, mut opened: Opened) {
        if let Some(entry) = self.entry(id) {
            // Kept for the connection's life: only the room it fills.
            opened.client_properties.shrink_to_fit();
            if entry.opened.set(opened).is_ok() {
                self.counters.connections_opened.inc();
            }
        }
    }

    /// The signal connection `id` closes on (with 320 CONNECTION_FORCED).
    pub fn close_signal(&self, id: u64) -> Option<watch::Receiver<bool>> {
        self.entry(id).map(|entry| entry.close.subscribe())
    }

    /// Why connection `id` was told to close.
    pub fn close_reason(&self, id: u64) -> String {
        self.entry(id)
            .and_then(|entry| lock(&entry.close_reason).clone())
            .unwrap_or_else(|| SHUTDOWN_REASON.to_owned())
    }

    /// Tells connection `id` to close, giving `reason`; false if there is
    /// no such open connection.
    pub fn close(&self, id: u64, reason: &str) -> bool {
        let Some(entry) = self.entry(id) else {
            return false;
        };
        lock(&entry.close_reason).get_or_insert_with(|| reason.to_owned());
        entry.close.send_replace(true);
        true
    }

    /// Connection `id` has cleaned up: its channels are closed (their
    /// consumers cancelled, unacknowledged deliveries requeued), its
    /// exclusive queues deleted, and it handles nothing it is sent later.
    #[cfg(feature = "mqtt")]
    pub fn cleaned_up(&self, id: u64) {
        if let Some(entry) = self.entry(id) {
            entry.cleaned.set();
        }
    }

    /// Tells connection `id` to close (as [`Registry::close`]); the future
    /// resolves once it has cleaned up ([`Registry::cleaned_up`]) or is
    /// gone, so that nothing it was sent takes effect afterwards.
    #[cfg(feature = "mqtt")]
    pub fn close_and_wait(
        &self,
        id: u64,
        reason: &str,
    ) -> impl std::future::Future<Output = ()> + Send + 'static {
        let entry = self.entry(id);
        self.close(id, reason);
        async move {
            if let Some(entry) = entry {
                entry.cleaned.wait().await;
            }
        }
    }

    /// Tells every connection, and any that registers later, to close.
    pub fn close_all(&self) {
        let mut state = lock(&self.state);
        state.closing_all = true;
        for entry in state.connections.values() {
            entry.close.send_replace(true);
        }
    }

    /// Every connection whose handshake is done, by id.
    pub fn connections(&self) -> Vec<Arc<ConnectionEntry>> {
        let mut open: Vec<Arc<ConnectionEntry>> = lock(&self.state)
            .connections
            .values()
            .filter(|entry| entry.opened.get().is_some())
            .cloned()
            .collect();
        open.sort_by_key(|entry| entry.id);
        open
    }

    /// Connection `id`, if its handshake is done.
    pub fn connection_entry(&self, id: u64) -> Option<Arc<ConnectionEntry>> {
        self.entry(id).filter(|entry| entry.opened.get().is_some())
    }

    /// How many connections and channels are open.
    pub fn counts(&self) -> (usize, usize) {
        let state = lock(&self.state);
        let open = state
            .connections
            .values()
            .filter(|entry| entry.opened.get().is_some());
        open.fold((0, 0), |(connections, channels), entry| {
            (connections + 1, channels + entry.channel_count())
        })
    }

    /// Registers channel `number` of connection `connection`.
    pub fn channel(
        self: &Arc<Self>,
        connection: u64,
        number: u16,
        link: &Arc<ChannelLink>,
    ) -> ChannelRegistration {
        let entry = Arc::new(ChannelEntry {
            number,
            link: Arc::clone(link),
            mode: AtomicU8::new(ChannelMode::Plain as u8),
            prefetch: AtomicU32::new(0),
            unconfirmed: AtomicU64::new(0),
            uncommitted_messages: AtomicU64::new(0),
            uncommitted_acks: AtomicU64::new(0),
            publisher: AtomicBool::new(false),
        });
        let owner = self.entry(connection);
        if let Some(owner) = &owner {
            lock(&owner.channels).insert(number, Arc::clone(&entry));
        }
        self.counters.channels_opened.inc();
        ChannelRegistration {
            registry: Arc::clone(self),
            owner,
            entry,
            publisher: false,
        }
    }
}

/// Keeps a connection listed; dropping it unregisters the connection.
#[derive(Debug)]
pub(crate) struct ConnectionRegistration {
    registry: Arc<Registry>,
    entry: Arc<ConnectionEntry>,
}

impl Drop for ConnectionRegistration {
    fn drop(&mut self) {
        lock(&self.registry.state)
            .connections
            .remove(&self.entry.id);
        // Gone: it handles nothing more, cleaned up or not.
        #[cfg(feature = "mqtt")]
        self.entry.cleaned.set();
        if self.entry.opened.get().is_some() {
            self.registry.counters.connections_closed.inc();
        }
    }
}

/// Keeps a channel listed; dropping it unregisters the channel.
#[derive(Debug)]
pub(crate) struct ChannelRegistration {
    registry: Arc<Registry>,
    owner: Option<Arc<ConnectionEntry>>,
    entry: Arc<ChannelEntry>,
    /// Mirrors `entry.publisher` without an atomic load per publish.
    publisher: bool,
}

impl ChannelRegistration {
    /// The channel published: the first time, it becomes a publisher.
    #[inline]
    pub fn publishing(&mut self) {
        if !self.publisher {
            self.publisher = true;
            self.entry.publisher.store(true, Ordering::Relaxed);
            self.registry.counters.publisher_added();
        }
    }

    /// The channel switched to confirm or transactional mode.
    pub fn set_mode(&self, mode: ChannelMode) {
        self.entry.mode.store(mode as u8, Ordering::Relaxed);
    }

    /// basic.qos set the per-consumer prefetch count.
    pub fn set_prefetch(&self, count: u32) {
        self.entry.prefetch.store(count, Ordering::Relaxed);
    }

    /// What the channel holds now: publishes awaiting their confirm,
    /// publishes and acks held by its transaction.
    pub fn set_pending(&self, unconfirmed: usize, messages: usize, acks: usize) {
        let entry = &self.entry;
        entry
            .unconfirmed
            .store(unconfirmed as u64, Ordering::Relaxed);
        entry
            .uncommitted_messages
            .store(messages as u64, Ordering::Relaxed);
        entry.uncommitted_acks.store(acks as u64, Ordering::Relaxed);
    }
}

impl Drop for ChannelRegistration {
    fn drop(&mut self) {
        if let Some(owner) = &self.owner {
            let mut channels = lock(&owner.channels);
            if channels
                .get(&self.entry.number)
                .is_some_and(|e| Arc::ptr_eq(e, &self.entry))
            {
                channels.remove(&self.entry.number);
            }
        }
        self.registry.counters.channels_closed.inc();
        if self.publisher {
            self.registry.counters.publisher_removed();
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn opened() -> Opened {
        Opened {
            user: "guest".into(),
            vhost: "/".into(),
            client_properties: FieldTable::new(),
            frame_max: 4096,
            channel_max: 10,
            heartbeat_secs: 0,
        }
    }

    #[test]
    fn connections_are_listed_once_opened_and_counted_once_closed() {
        let counters = Arc::new(BrokerCounters::default());
        let registry = Arc::new(Registry::new(Arc::clone(&counters)));
        let a = registry.connection(1, "peer-a", "AMQP 0-9-1", None);
        let b = registry.connection(2, "peer-b", "AMQP 0-9-1", None);
        assert!(registry.connections().is_empty());
        registry.opened(1, opened());
        registry.opened(1, opened());
        assert_eq!(registry.counts(), (1, 0));
        assert_eq!(counters.connections_opened.get(), 1);
        drop(b);
        assert_eq!(counters.connections_closed.get(), 0, "never opened");
        drop(a);
        assert_eq!(counters.connections_closed.get(), 1);
        assert_eq!(registry.counts(), (0, 0));
    }

    /// A close waited for resolves once the connection has cleaned up, or
    /// once it is gone without (its registration dropped), not before.
    #[cfg(feature = "mqtt")]
    #[tokio::test]
    async fn a_close_waited_for_ends_at_the_clean_up_or_the_connections_end() {
        let registry = Arc::new(Registry::new(Arc::default()));
        let _cleaning = registry.connection(1, "a", "MQTT 5.0", None);
        let ending = registry.connection(2, "b", "MQTT 5.0", None);
        let mut cleaned = tokio::spawn(registry.close_and_wait(1, "taken over"));
        let mut gone = tokio::spawn(registry.close_and_wait(2, "taken over"));
        assert!(*registry.close_signal(1).unwrap().borrow(), "told to close");
        tokio::task::yield_now().await;
        assert!(!cleaned.is_finished() && !gone.is_finished());
        registry.cleaned_up(1);
        tokio::time::timeout(std::time::Duration::from_secs(30), &mut cleaned)
            .await
            .expect("resolved at the clean-up")
            .unwrap();
        assert!(!gone.is_finished());
        drop(ending);
        tokio::time::timeout(std::time::Duration::from_secs(30), &mut gone)
            .await
            .expect("resolved at the connection's end")
            .unwrap();
        // Already cleaned up, or never there: at once.
        registry.close_and_wait(1, "again").await;
        registry.close_and_wait(3, "none").await;
    }

    #[test]
    fn closing_one_connection_signals_only_it() {
        let registry = Arc::new(Registry::new(Arc::default()));
        let _a = registry.connection(1, "a", "AMQP 0-9-1", None);
        let _b = registry.connection(2, "b", "AMQP 0-9-1", None);
        let a = registry.close_signal(1).unwrap();
        let b = registry.close_signal(2).unwrap();
        assert!(registry.close(1, "Closed via management plugin"));
        assert!(*a.borrow() && !*b.borrow());
        assert_eq!(registry.close_reason(1), "Closed via management plugin");
        assert_eq!(registry.close_reason(2), SHUTDOWN_REASON);
        assert!(!registry.close(3, "x"));
        registry.close_all();
        assert!(*b.borrow());
        let _late = registry.connection(4, "late", "AMQP 0-9-1", None);
        assert!(*registry.close_signal(4).unwrap().borrow());
    }
}
