//! Client-identifier takeover: at most one session per client identifier
//! and vhost. A CONNECT with an identifier in use asks the session holding
//! it to close and waits until it has ended (its AMQP link cleaned up, so
//! its exclusive subscription queues are gone) before going on, at most
//! the handshake timeout. The map lock is held for one insert or remove,
//! never across an await.
//!
//! Whether the old session still acts is a state it commits to under its
//! holder's lock ([`State`]), not a check at one moment: it handles
//! packets and the core's replies only while [`State::Running`]
//! ([`Claim::running`]), and its end first moves it to [`State::Ending`]
//! ([`Claim::end`]), after which the end (flush, deletes, the state it
//! keeps, its will) is its own and a takeover waits for it, however long
//! its write timeouts let it take. A takeover that times out on a running
//! session abandons it ([`State::Abandoned`]) and force-closes its AMQP
//! link, waiting until the core has cleaned that up (its consumers
//! cancelled, its exclusive queues deleted, nothing sent on it handled
//! later), before the new session reads the session's queues: the old
//! one can then change nothing the new one owns, and at its end only
//! closes its socket. Its will is the new session's to publish then
//! ([`Claim::inherited_will`]), as the old one's end would have (MQTT
//! 5.0 3.1.4, 3.1.1 3.1.2.5: a connection the server closes without
//! DISCONNECT leaves its will; Mosquitto 2.0 publishes it on a takeover).

use super::wills::LastWill;
use crate::registry::Registry;
use std::collections::HashMap;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Duration;
use tokio::sync::Notify;

/// The sessions open on a broker's MQTT listeners, by vhost and client id.
#[derive(Debug, Default)]
pub(crate) struct ClientIds {
    open: Mutex<HashMap<(String, String), Arc<Holder>>>,
}

/// Where a holding session is, as a takeover sees it.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum State {
    /// Handling packets: a takeover that stops waiting abandons it.
    Running,
    /// Its end has begun and owns the session: a takeover waits for it.
    Ending,
    /// A takeover stopped waiting and closed its link: it acts no more.
    Abandoned,
}

/// A session's hold on its client identifier.
#[derive(Debug)]
struct Holder {
    /// Told when another session takes the identifier over.
    kick: Notify,
    /// Set when the holding session has ended ([`Holder::ended`]).
    has_ended: AtomicBool,
    /// Wakes those waiting for `has_ended`.
    ended_told: Notify,
    state: Mutex<State>,
    /// The holding session's AMQP connection, closed by a takeover that
    /// abandons it.
    link: u64,
    /// The holding session's will and its delay as its CONNECT set them:
    /// taken by its own end, or by a takeover that abandons it.
    will: Mutex<Option<(Box<LastWill>, Duration)>>,
}

/// A session's claim; dropping it when the session has ended releases the
/// identifier and lets a session taking it over go on.
#[derive(Debug)]
pub(super) struct Claim {
    ids: Arc<ClientIds>,
    key: (String, String),
    holder: Arc<Holder>,
    /// The will of a session this claim's takeover abandoned.
    inherited: Option<(Box<LastWill>, Duration)>,
}

impl ClientIds {
    /// Claims `client_id` in `vhost` for the session on AMQP connection
    /// `link`, closing the session that held it and waiting for it to
    /// end, at most `wait` unless its end is under way; one that has not
    /// begun to end by then is abandoned and its link closed (waited for,
    /// at most `wait` again). `will`: the session's will and its delay as
    /// its CONNECT set them, held from the start so that a takeover
    /// abandoning it even before its loop inherits it.
    pub(super) async fn claim(
        self: &Arc<Self>,
        (vhost, client_id): (&str, &str),
        link: u64,
        will: Option<(Box<LastWill>, Duration)>,
        registry: &Registry,
        wait: Duration,
    ) -> Claim {
        let key = (vhost.to_owned(), client_id.to_owned());
        let holder = Arc::new(Holder {
            kick: Notify::new(),
            has_ended: AtomicBool::new(false),
            ended_told: Notify::new(),
            state: Mutex::new(State::Running),
            link,
            will: Mutex::new(will),
        });
        let mut inherited = None;
        let previous = self.lock().insert(key.clone(), Arc::clone(&holder));
        if let Some(previous) = previous {
            previous.kick.notify_one();
            let waited = tokio::time::timeout(wait, previous.ended()).await;
            if waited.map(drop).is_err() {
                let abandoned = {
                    let mut state = lock(&previous.state);
                    let running = *state == State::Running;
                    if running {
                        *state = State::Abandoned;
                    }
                    running
                };
                if abandoned {
                    tracing::warn!(client_id, vhost, "session taken over did not end in time");
                    inherited = lock(&previous.will).take();
                    let closed = registry.close_and_wait(previous.link, "MQTT session taken over");
                    if tokio::time::timeout(wait, closed).await.is_err() {
                        tracing::warn!(
                            client_id,
                            vhost,
                            "link of a session taken over not closed in time"
                        );
                    }
                } else {
                    // Its end is under way, bounded by its write timeouts.
                    previous.ended().await;
                }
            }
        }
        Claim {
            ids: Arc::clone(self),
            key,
            holder,
            inherited,
        }
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, HashMap<(String, String), Arc<Holder>>> {
        lock(&self.open)
    }
}

impl Holder {
    /// Resolves once the holding session has ended (its claim dropped).
    async fn ended(&self) {
        loop {
            let told = self.ended_told.notified();
            tokio::pin!(told);
            // Registered before the flag is read, so a drop between the
            // read and the await still wakes it.
            told.as_mut().enable();
            if self.has_ended.load(Ordering::Acquire) {
                return;
            }
            told.await;
        }
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

    /// Runs `act` (handling packets or the core's replies) while the
    /// session has not been abandoned, under the lock a takeover abandons
    /// it with; `None` once abandoned.
    pub(super) fn running<T>(&self, act: impl FnOnce() -> T) -> Option<T> {
        let state = lock(&self.holder.state);
        (*state == State::Running).then(act)
    }

    /// The session's will, for its own end ([`Claim::end`] true).
    pub(super) fn take_will(&self) -> Option<Box<LastWill>> {
        lock(&self.holder.will).take().map(|(will, _)| will)
    }

    /// The will of the session this claim's takeover abandoned, with its
    /// delay: the new session publishes or schedules it before it begins.
    pub(super) fn inherited_will(&mut self) -> Option<(Box<LastWill>, Duration)> {
        self.inherited.take()
    }

    /// Begins the session's end: whether the end is its own (flush,
    /// deletes, the state it keeps, its will), then waited for by a
    /// takeover; false if a takeover has abandoned it.
    pub(super) fn end(&self) -> bool {
        let mut state = lock(&self.holder.state);
        if *state == State::Running {
            *state = State::Ending;
        }
        *state == State::Ending
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
        self.holder.has_ended.store(true, Ordering::Release);
        self.holder.ended_told.notify_waiters();
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[tokio::test]
    async fn a_takeover_waits_for_an_end_under_way_and_closes_the_link_of_one_abandoned() {
        let registry = Arc::new(Registry::new(Arc::default()));
        let _links: Vec<_> = (1..=3)
            .map(|id| registry.connection(id, "peer", "MQTT 5.0", None))
            .collect();
        let ids = Arc::new(ClientIds::default());
        let wait = Duration::from_millis(20);
        let claim = |link: u64| {
            let ids = Arc::clone(&ids);
            let registry = Arc::clone(&registry);
            async move { ids.claim(("/", "c"), link, None, &registry, wait).await }
        };
        // An end under way is waited for past the timeout.
        let first = claim(1).await;
        let taking = tokio::spawn(claim(2));
        tokio::task::yield_now().await;
        assert!(first.end(), "its end is its own");
        tokio::time::sleep(wait * 5).await;
        assert!(!taking.is_finished(), "waits for an end under way");
        assert_eq!(first.running(|| 1), None, "an ending session acts no more");
        drop(first);
        let second = taking.await.expect("claimed");
        // A running session is abandoned at the timeout: its link is told
        // to close, and the takeover goes on once it has cleaned up.
        let taking = tokio::spawn(claim(3));
        let mut closing = registry.close_signal(2).expect("link 2");
        closing
            .wait_for(|c| *c)
            .await
            .expect("link 2 told to close");
        assert_eq!(second.running(|| 2), None, "abandoned");
        assert!(!second.end(), "an abandoned session's end is not its own");
        tokio::time::sleep(wait / 2).await;
        assert!(!taking.is_finished(), "waits for the link's clean-up");
        registry.cleaned_up(2);
        let third = taking.await.expect("claimed");
        assert_eq!(third.running(|| 3), Some(3));
        assert!(third.end());
    }

    #[tokio::test]
    async fn a_session_abandoned_while_claiming_acts_no_more_and_its_will_is_inherited() {
        let registry = Arc::new(Registry::new(Arc::default()));
        let _links: Vec<_> = (1..=3)
            .map(|id| registry.connection(id, "peer", "MQTT 3.1.1", None))
            .collect();
        let ids = Arc::new(ClientIds::default());
        // Hang limits: B waits for the stuck A until the test ends A.
        let long = Duration::from_secs(60);
        let stuck = ids.claim(("/", "c"), 1, None, &registry, long).await;
        let will = leveret_mqtt::Will {
            topic: leveret_mqtt::TopicName::from_static("b/will"),
            payload: bytes::Bytes::from_static(b"b"),
            qos: leveret_mqtt::QoS::AtMostOnce,
            retain: false,
            properties: Default::default(),
        };
        let will = Box::new(LastWill::new(will, "/", "u", false));
        let delay = Duration::from_secs(7);
        let claiming = {
            let (ids, registry) = (Arc::clone(&ids), Arc::clone(&registry));
            let will = Some((will, delay));
            tokio::spawn(async move { ids.claim(("/", "c"), 2, will, &registry, long).await })
        };
        tokio::task::yield_now().await;
        // C gives up on B, still inside its claim, and inherits its will.
        let short = Duration::from_millis(20);
        let mut third = ids.claim(("/", "c"), 3, None, &registry, short).await;
        let inherited = third.inherited_will().map(|(_, delay)| delay);
        assert_eq!(inherited, Some(delay), "B's will, held from its claim");
        let told = registry.close_signal(2).expect("link 2");
        assert!(*told.borrow(), "B's link told to close");
        // B's claim returns once A ends: abandoned, it may act no more.
        drop(stuck);
        let second = claiming.await.expect("claimed");
        assert_eq!(second.running(|| 2), None, "abandoned before its loop");
        assert!(!second.end(), "an abandoned session's end is not its own");
        assert!(
            second.take_will().is_none(),
            "its will went to the takeover"
        );
        assert_eq!(third.running(|| 3), Some(3));
    }
}
