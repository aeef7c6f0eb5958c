//! Retained messages: at most one per topic and vhost, held in memory for
//! the SUBSCRIBEs that match it and kept in the store
//! ([`MetaRecord::Retained`]) so they survive a restart, as RabbitMQ's
//! plugin keeps them per vhost. An empty payload deletes a topic's. A
//! 5.0 publish's properties are kept with it (as the AMQP properties they
//! map to, encoded: [`super::properties`]), so a later subscriber gets
//! them, and its Message Expiry Interval ends it (MQTT-3.3.2-5).
//!
//! Bounded: at most [`RetainedLimits::messages`] messages and
//! [`RetainedLimits::bytes`] bytes (topic, properties and payload) in the broker;
//! their bytes count in the memory gauge. A message that would pass a cap
//! is still published but not retained, and the first refusal of a run of
//! them is logged. Looking up a filter visits only the topics that share
//! its literal prefix.

use crate::alarm::memory::MemoryGauge;
use crate::store::{Durable, MetaKey, MetaRecord, Persistence, StoreOp};
use bytes::Bytes;
use leveret_mqtt::{QoS, TopicFilter};
use std::collections::{BTreeMap, HashMap};
use std::sync::{Arc, Mutex};

/// Bytes counted per retained message beyond its topic and payload.
const OVERHEAD: usize = 64;

/// How many retained messages a broker holds.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct RetainedLimits {
    /// Messages, over every vhost.
    pub messages: usize,
    /// Bytes (topics and payloads), over every vhost.
    pub bytes: usize,
}

impl Default for RetainedLimits {
    fn default() -> Self {
        RetainedLimits {
            messages: 10_000,
            bytes: 64 << 20,
        }
    }
}

/// A retained message.
#[derive(Debug, Clone, PartialEq, Eq)]
pub(super) struct Message {
    pub topic: String,
    pub qos: QoS,
    /// Its 5.0 properties as encoded AMQP basic properties (empty: none).
    pub properties: Bytes,
    pub payload: Bytes,
}

/// What is kept of a topic's retained message.
#[derive(Debug)]
struct Kept {
    qos: QoS,
    properties: Bytes,
    payload: Bytes,
}

/// Why a message was not retained.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) struct Full;

/// The broker's retained messages.
#[derive(Debug)]
pub(crate) struct Retained {
    state: Mutex<State>,
    gauge: Arc<MemoryGauge>,
    persistence: Option<Arc<Persistence>>,
    limits: RetainedLimits,
}

#[derive(Debug, Default)]
struct State {
    /// vhost → topic → its message.
    by_vhost: HashMap<String, BTreeMap<String, Kept>>,
    messages: usize,
    bytes: usize,
    /// Whether the current run of refusals has been logged.
    refusal_logged: bool,
}

fn cost(topic: &str, kept: &Kept) -> usize {
    topic.len() + kept.properties.len() + kept.payload.len() + OVERHEAD
}

impl Retained {
    /// The retained messages among `recovered` (the store's metadata),
    /// counted in `gauge`; those past the limits are dropped with a log
    /// line (the limits may have been lowered).
    pub(crate) fn new(
        recovered: &[MetaRecord],
        gauge: Arc<MemoryGauge>,
        persistence: Option<Arc<Persistence>>,
        limits: RetainedLimits,
    ) -> Self {
        let retained = Retained {
            state: Mutex::default(),
            gauge,
            persistence,
            limits,
        };
        let mut dropped = 0usize;
        for record in recovered {
            if let MetaRecord::Retained {
                vhost,
                topic,
                qos,
                properties,
                payload,
            } = record
            {
                let kept = Kept {
                    qos: QoS::from_level(*qos).unwrap_or(QoS::AtMostOnce),
                    properties: properties.clone(),
                    payload: payload.clone(),
                };
                if retained.lock_put(vhost, topic, kept).is_err() {
                    dropped += 1;
                }
            }
        }
        if dropped > 0 {
            tracing::warn!(
                dropped,
                "stored MQTT retained messages past the retained-message limits were not restored"
            );
        }
        retained
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, State> {
        self.state.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// Sets (or, with an empty payload, deletes) `topic`'s retained
    /// message in `vhost`, in memory and in the store; the store
    /// submission to wait for before acknowledging the publish (0 if
    /// none), or [`Full`]. `properties` are its 5.0 properties as encoded
    /// AMQP basic properties (empty: none).
    pub(super) fn retain(
        &self,
        vhost: &str,
        topic: &str,
        qos: QoS,
        properties: Bytes,
        payload: Bytes,
    ) -> Result<u64, Full> {
        let op = if payload.is_empty() {
            StoreOp::DeleteMeta(MetaKey::Retained {
                vhost: vhost.to_owned(),
                topic: topic.to_owned(),
            })
        } else {
            StoreOp::PutMeta(MetaRecord::Retained {
                vhost: vhost.to_owned(),
                topic: topic.to_owned(),
                qos: qos.level(),
                properties: properties.clone(),
                payload: payload.clone(),
            })
        };
        let kept = Kept {
            qos,
            properties,
            payload,
        };
        let mut state = self.lock_put(vhost, topic, kept)?;
        // Submitted under the lock: the store sees a topic's changes in
        // the order memory does.
        let number = self
            .persistence
            .as_ref()
            .map_or(0, |persistence| persistence.submit(vec![op]));
        state.refusal_logged = false;
        Ok(number)
    }

    /// Applies a change in memory; the lock, still held, on success.
    fn lock_put(
        &self,
        vhost: &str,
        topic: &str,
        kept: Kept,
    ) -> Result<std::sync::MutexGuard<'_, State>, Full> {
        let mut guard = self.lock();
        let state = &mut *guard;
        let old = state
            .by_vhost
            .get(vhost)
            .and_then(|topics| topics.get(topic))
            .map(|old| cost(topic, old));
        if kept.payload.is_empty() {
            if let Some(old) = old {
                if let Some(topics) = state.by_vhost.get_mut(vhost) {
                    topics.remove(topic);
                    if topics.is_empty() {
                        state.by_vhost.remove(vhost);
                    }
                }
                state.messages -= 1;
                state.bytes -= old;
                self.gauge.sub(old);
            }
            return Ok(guard);
        }
        let new = cost(topic, &kept);
        let messages = state.messages + usize::from(old.is_none());
        let bytes = state.bytes - old.unwrap_or(0) + new;
        if messages > self.limits.messages || bytes > self.limits.bytes {
            if !state.refusal_logged {
                state.refusal_logged = true;
                tracing::warn!(
                    vhost,
                    messages = state.messages,
                    bytes = state.bytes,
                    limit_messages = self.limits.messages,
                    limit_bytes = self.limits.bytes,
                    "MQTT retained message not retained: the retained-message limit is reached \
                     (later refusals are not logged until one is retained)"
                );
            }
            return Err(Full);
        }
        state
            .by_vhost
            .entry(vhost.to_owned())
            .or_default()
            .insert(topic.to_owned(), kept);
        state.messages = messages;
        state.bytes = bytes;
        self.gauge.add(new);
        if let Some(old) = old {
            self.gauge.sub(old);
        }
        Ok(guard)
    }

    /// The retained messages in `vhost` whose topics `filter` matches.
    pub(super) fn matching(&self, vhost: &str, filter: &TopicFilter) -> Vec<Message> {
        let inner = filter.shared().map_or(filter.as_str(), |s| s.filter);
        // Every matching topic starts with the filter's text before its
        // first wildcard, less a trailing `/` (`a/#` matches `a`).
        let literal = inner.find(['+', '#']).map_or(inner, |at| &inner[..at]);
        let prefix = literal.strip_suffix('/').unwrap_or(literal);
        let state = self.lock();
        let Some(topics) = state.by_vhost.get(vhost) else {
            return Vec::new();
        };
        topics
            .range(prefix.to_owned()..)
            .take_while(|(topic, _)| topic.starts_with(prefix))
            .filter(|(topic, _)| filter.matches(topic))
            .map(|(topic, kept)| Message {
                topic: topic.clone(),
                qos: kept.qos,
                properties: kept.properties.clone(),
                payload: kept.payload.clone(),
            })
            .collect()
    }

    /// The highest store submission attempted (all of them without a
    /// store).
    pub(super) fn flushed(&self) -> u64 {
        self.persistence.as_ref().map_or(u64::MAX, |p| p.flushed())
    }

    /// Whether store submission `number` (attempted) reached the disk.
    pub(super) fn written(&self, number: u64) -> bool {
        number == 0
            || self
                .persistence
                .as_ref()
                .is_none_or(|p| p.succeeded(number))
    }

    /// What tells that the store has attempted more submissions.
    pub(super) fn durable(&self) -> Option<tokio::sync::watch::Receiver<Durable>> {
        self.persistence.as_ref().map(|p| p.durable())
    }

    /// How many messages are retained, and their counted bytes.
    #[cfg(test)]
    fn figures(&self) -> (usize, usize) {
        let state = self.lock();
        (state.messages, state.bytes)
    }
}

impl Drop for Retained {
    fn drop(&mut self) {
        self.gauge.sub(self.lock().bytes);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn retained(messages: usize, bytes: usize) -> (Retained, Arc<MemoryGauge>) {
        let gauge = Arc::new(MemoryGauge::new(usize::MAX));
        let limits = RetainedLimits { messages, bytes };
        (Retained::new(&[], Arc::clone(&gauge), None, limits), gauge)
    }

    fn topics(retained: &Retained, filter: &'static str) -> Vec<String> {
        retained
            .matching("/", &TopicFilter::from_static(filter))
            .into_iter()
            .map(|m| m.topic)
            .collect()
    }

    #[test]
    fn one_message_per_topic_an_empty_payload_deletes_and_the_gauge_follows() {
        let (retained, gauge) = retained(10, 10_000);
        let one = Bytes::from_static(b"1");
        retained
            .retain("/", "a/b", QoS::AtLeastOnce, Bytes::new(), one.clone())
            .unwrap();
        retained
            .retain(
                "/",
                "a/b",
                QoS::AtMostOnce,
                Bytes::new(),
                Bytes::from_static(b"22"),
            )
            .unwrap();
        retained
            .retain("/", "a", QoS::AtMostOnce, Bytes::new(), one.clone())
            .unwrap();
        retained
            .retain("/", "ab", QoS::AtMostOnce, Bytes::new(), one.clone())
            .unwrap();
        retained
            .retain("other", "a/b", QoS::AtMostOnce, Bytes::new(), one)
            .unwrap();
        assert_eq!(retained.figures().0, 4);
        assert_eq!(gauge.used(), retained.figures().1);
        let found = retained.matching("/", &TopicFilter::from_static("a/b"));
        assert_eq!(found.len(), 1);
        assert_eq!(&found[0].payload[..], b"22");
        assert_eq!(found[0].qos, QoS::AtMostOnce);
        assert_eq!(topics(&retained, "a/#"), ["a", "a/b"]);
        assert_eq!(topics(&retained, "+"), ["a", "ab"]);
        assert_eq!(topics(&retained, "#"), ["a", "a/b", "ab"]);
        retained
            .retain("/", "a/b", QoS::AtMostOnce, Bytes::new(), Bytes::new())
            .unwrap();
        retained
            .retain("/", "never", QoS::AtMostOnce, Bytes::new(), Bytes::new())
            .unwrap();
        assert_eq!(topics(&retained, "#"), ["a", "ab"]);
        assert_eq!(retained.figures().0, 3);
        assert_eq!(gauge.used(), retained.figures().1);
        drop(retained);
        assert_eq!(gauge.used(), 0);
    }

    #[test]
    fn properties_are_kept_and_counted() {
        let (retained, gauge) = retained(10, 10_000);
        let properties = Bytes::from_static(b"encoded properties");
        retained
            .retain(
                "/",
                "p",
                QoS::AtLeastOnce,
                properties.clone(),
                Bytes::from_static(b"v"),
            )
            .unwrap();
        let found = retained.matching("/", &TopicFilter::from_static("p"));
        assert_eq!(found[0].properties, properties);
        assert_eq!(gauge.used(), "p".len() + properties.len() + 1 + OVERHEAD);
    }

    #[test]
    fn the_caps_refuse_new_topics_but_let_existing_ones_change() {
        let (retained, gauge) = retained(2, 1_000);
        let small = Bytes::from_static(b"x");
        retained
            .retain("/", "a", QoS::AtMostOnce, Bytes::new(), small.clone())
            .unwrap();
        retained
            .retain("/", "b", QoS::AtMostOnce, Bytes::new(), small.clone())
            .unwrap();
        assert_eq!(
            retained.retain("/", "c", QoS::AtMostOnce, Bytes::new(), small.clone()),
            Err(Full)
        );
        retained
            .retain(
                "/",
                "b",
                QoS::AtMostOnce,
                Bytes::new(),
                Bytes::from_static(b"yy"),
            )
            .unwrap();
        let big = Bytes::from(vec![0u8; 1_000]);
        assert_eq!(
            retained.retain("/", "a", QoS::AtMostOnce, Bytes::new(), big),
            Err(Full)
        );
        assert_eq!(topics(&retained, "#"), ["a", "b"]);
        assert_eq!(gauge.used(), retained.figures().1);
        assert!(retained.figures().1 <= 1_000);
    }
}
