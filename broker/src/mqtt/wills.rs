//! Last wills: published when a connection ends without DISCONNECT (or
//! with reason 0x04), as the user the session logged in as (with the
//! core's permission checks, as a publish of theirs), to `amq.topic`;
//! a retained will sets its topic's retained message.
//!
//! A 5.0 will's Will Delay Interval holds it back: it is published when
//! the delay or the session's expiry passes, whichever comes first,
//! unless a new connection resumes the session meanwhile (then it is
//! dropped); a new connection that starts clean has it published at
//! once. Bounded: at most [`MAX_DELAYED`] wills wait at a time, each one
//! sleeping task; past that a will is published at once (logged). Waiting
//! wills are in memory only: a broker shutting down drops them.

use super::link::{self, Marks};
use super::mapping::{self, EXCHANGE};
use super::Shared;
use crate::admin::Admin;
use crate::core::Core;
use bytes::Bytes;
use bytes::BytesMut;
use leveret_mqtt::QoS;
use leveret_protocol::BasicProperties;
use std::collections::HashMap;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, SystemTime};
use tokio::sync::oneshot;

/// Wills waiting for their delay at most.
const MAX_DELAYED: usize = 10_000;

/// A will to publish.
#[derive(Debug)]
pub(super) struct LastWill {
    vhost: String,
    user: String,
    topic: String,
    qos: QoS,
    retain: bool,
    /// Mapped from the CONNECT's will, in memory of their own (never
    /// slices of the connection's read buffer, which a waiting will would
    /// keep alive).
    properties: BasicProperties,
    payload: Bytes,
}

impl LastWill {
    /// The will of a CONNECT, for a session of `user` in `vhost`, its
    /// 5.0 properties mapped as a PUBLISH's.
    pub(super) fn new(will: leveret_mqtt::Will, vhost: &str, user: &str, v5: bool) -> LastWill {
        let marks = Marks {
            qos: will.qos,
            retain: will.retain,
            publisher: None,
        };
        let mapped = link::properties(marks, v5.then_some(&will.properties), SystemTime::now());
        let mut encoded = BytesMut::new();
        mapped.encode(&mut encoded);
        let properties = BasicProperties::decode(&encoded.freeze()).unwrap_or(mapped);
        LastWill {
            vhost: vhost.to_owned(),
            user: user.to_owned(),
            topic: will.topic.as_str().to_owned(),
            qos: will.qos,
            retain: will.retain,
            properties,
            // Kept past the connection: never a slice of a read chunk.
            payload: Bytes::copy_from_slice(&will.payload),
        }
    }
}

/// What a new connection makes of a will waiting for its delay.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Fate {
    /// The session was resumed: the will is dropped.
    Drop,
    /// The session started clean: the previous one ended, the will goes.
    PublishNow,
}

/// The wills waiting for their delay, by vhost and client identifier.
#[derive(Debug)]
pub(super) struct Wills {
    waiting: Mutex<HashMap<(String, String), Waiting>>,
    /// Hands each waiting will a number, so that one that fires removes
    /// its own entry and not a later one's.
    next: AtomicU64,
    max: usize,
}

#[derive(Debug)]
struct Waiting {
    number: u64,
    fate: oneshot::Sender<Fate>,
}

impl Default for Wills {
    fn default() -> Self {
        Wills::with_capacity(MAX_DELAYED)
    }
}

impl Wills {
    fn with_capacity(max: usize) -> Wills {
        Wills {
            waiting: Mutex::default(),
            next: AtomicU64::new(0),
            max,
        }
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, HashMap<(String, String), Waiting>> {
        self.waiting.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// Wills waiting now.
    #[cfg(test)]
    fn waiting(&self) -> usize {
        self.lock().len()
    }

    /// Registers a will waiting for its delay; its number, or `None` if
    /// [`MAX_DELAYED`] wait already. A will still waiting for the same
    /// identifier is dropped: its session has had a newer connection.
    fn wait(&self, key: (String, String), fate: oneshot::Sender<Fate>) -> Option<u64> {
        let mut waiting = self.lock();
        if waiting.len() >= self.max && !waiting.contains_key(&key) {
            return None;
        }
        let number = self.next.fetch_add(1, Ordering::Relaxed);
        if let Some(old) = waiting.insert(key, Waiting { number, fate }) {
            let _ = old.fate.send(Fate::Drop);
        }
        Some(number)
    }

    /// Forgets waiting will `number` once it has fired.
    fn fired(&self, key: &(String, String), number: u64) {
        let mut waiting = self.lock();
        if waiting.get(key).is_some_and(|w| w.number == number) {
            waiting.remove(key);
        }
    }

    /// A new connection of `client_id` in `vhost`: the will its session's
    /// previous connection left waiting is dropped if the session is
    /// resumed, else published now.
    pub(super) fn reconnected(&self, vhost: &str, client_id: &str, resumed: bool) {
        let key = (vhost.to_owned(), client_id.to_owned());
        if let Some(waiting) = self.lock().remove(&key) {
            let fate = if resumed {
                Fate::Drop
            } else {
                Fate::PublishNow
            };
            let _ = waiting.fate.send(fate);
        }
    }
}

/// Schedules `will`, of the session of `client_id`, to be published after
/// `delay`; the will back if it is to be published now ([`publish`]: the
/// delay is zero or too many wait), which the caller awaits so that the
/// session ends after it, as a broker shutting down waits for its
/// sessions. Never waits, so a session's end can decide it under its claim.
pub(super) fn schedule(
    shared: &Arc<Shared>,
    core: &Arc<Core>,
    client_id: &str,
    will: LastWill,
    delay: Duration,
) -> Option<LastWill> {
    if delay.is_zero() {
        return Some(will);
    }
    let key = (will.vhost.clone(), client_id.to_owned());
    let (fate, decided) = oneshot::channel();
    let Some(number) = shared.wills.wait(key.clone(), fate) else {
        tracing::warn!(
            client_id,
            "more delayed MQTT wills than the broker keeps waiting; published now"
        );
        return Some(will);
    };
    let shared_ = Arc::clone(shared);
    let core_ = Arc::clone(core);
    let mut shutdown = core.shutdown_signal();
    tokio::spawn(async move {
        let publish_it = tokio::select! {
            _ = tokio::time::sleep(delay) => true,
            fate = decided => fate == Ok(Fate::PublishNow),
            _ = shutdown.wait_for(|down| *down) => false,
        };
        shared_.wills.fired(&key, number);
        if publish_it {
            publish(&shared_, &core_, will).await;
        }
    });
    None
}

/// Publishes a will now, as its user (a refusal, such as no write
/// permission on the topic or a resource alarm, is logged).
pub(super) async fn publish(shared: &Shared, core: &Arc<Core>, mut will: LastWill) {
    let topic = will.topic.as_str();
    let Some(key) = mapping::routing_key(topic) else {
        return;
    };
    // The Message Expiry Interval counts from the will's publication.
    if will.properties.expiration.is_some() {
        will.properties.timestamp = Some(super::properties::epoch_seconds(SystemTime::now()));
    }
    if will.retain {
        // Kept with the properties the will is published with (its 5.0
        // properties mapped, and the broker's own delivery mode and
        // x-mqtt- headers, which a delivery does not read back).
        let mut properties = BytesMut::new();
        will.properties.encode(&mut properties);
        // Past the retained caps the will is still published (logged there).
        let _ = shared.retained.retain(
            &will.vhost,
            topic,
            will.qos,
            properties.freeze(),
            will.payload.clone(),
        );
    }
    let admin = Admin {
        core: Arc::clone(core),
    };
    let published = admin
        .as_user(&will.user)
        .publish(
            &will.vhost,
            EXCHANGE,
            &key.to_string_lossy(),
            will.properties,
            will.payload,
        )
        .await;
    if let Err(e) = published {
        tracing::warn!(vhost = %will.vhost, topic, error = %e, "MQTT will not published");
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_resumed_session_drops_the_waiting_will_and_a_clean_one_sends_it() {
        let wills = Wills::with_capacity(2);
        for (id, resumed, expected) in [("a", true, Fate::Drop), ("b", false, Fate::PublishNow)] {
            let (fate, mut decided) = oneshot::channel();
            wills
                .lock()
                .insert(("/".into(), id.into()), Waiting { number: 1, fate });
            wills.reconnected("/", id, resumed);
            assert_eq!(decided.try_recv(), Ok(expected));
        }
        assert_eq!(wills.waiting(), 0);
        // No will waiting: nothing to decide.
        wills.reconnected("/", "c", true);
    }

    #[test]
    fn at_most_the_cap_wait_and_a_fired_will_frees_its_place() {
        let wills = Wills::with_capacity(2);
        let key = |id: &str| ("/".to_owned(), id.to_owned());
        let mut receivers = Vec::new();
        let mut numbers = Vec::new();
        for id in ["a", "b", "c"] {
            let (fate, decided) = oneshot::channel();
            receivers.push(decided);
            numbers.push(wills.wait(key(id), fate));
        }
        assert!(numbers[0].is_some() && numbers[1].is_some());
        assert_eq!(numbers[2], None, "a third will is published at once");
        assert_eq!(wills.waiting(), 2);
        // A newer will of a waiting identifier replaces it (no growth).
        let (fate, _decided) = oneshot::channel();
        let newer = wills.wait(key("a"), fate).unwrap();
        assert_eq!(receivers[0].try_recv(), Ok(Fate::Drop));
        assert_eq!(wills.waiting(), 2);
        // The replaced will firing late does not remove the newer one.
        wills.fired(&key("a"), numbers[0].unwrap());
        assert_eq!(wills.waiting(), 2);
        wills.fired(&key("a"), newer);
        wills.fired(&key("b"), numbers[1].unwrap());
        assert_eq!(wills.waiting(), 0);
    }
}
