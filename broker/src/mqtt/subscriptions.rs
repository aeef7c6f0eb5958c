//! A session's subscriptions with their 5.0 options, and what those
//! options decide for each delivery.
//!
//! A session's own subscriptions are bindings of its per-QoS queues; their
//! options (No Local, Retain As Published, the Subscription Identifier)
//! are kept in the binding's arguments ([`Options::binding_arguments`],
//! RabbitMQ 3.13 keeps them there too), so a resumed persistent session
//! reads them back with the binding keys. One queue gets one copy of a
//! message however many of its bindings match, so a delivery's options
//! are found by matching its topic against the filters of the queue's QoS
//! ([`Subscriptions::for_delivery`]): only for a queue one of whose
//! subscriptions has an option set, at most [`super::session`]'s 4,096
//! filters per delivery.
//!
//! A shared subscription (`$share/GROUP/FILTER`) is a queue of its own,
//! `mqtt-shared-GROUP/FILTER` ([`super::mapping::shared_queue_name`]),
//! bound to `amq.topic` with the filter's key and consumed by every
//! session of the group (the core hands its messages round-robin to its
//! consumers): non-durable and auto-delete for a group of clean sessions,
//! so it lives while a member does; durable and kept for its persistent
//! members' sessions otherwise (`super::shares`). Each member consumes it
//! with a consumer tag of its own ([`shared_consumer_tag`]).

use super::link::{PUBLISHER_HEADER, RETAIN_HEADER};
use leveret_mqtt::{MqttString, QoS, TopicFilter};
use leveret_protocol::{BasicProperties, FieldTable, FieldValue, ShortStr};
use std::collections::HashMap;
use std::num::NonZeroU32;

/// Binding arguments that carry a subscription's options.
const NO_LOCAL_ARGUMENT: &str = "x-mqtt-no-local";
const RETAIN_AS_PUBLISHED_ARGUMENT: &str = "x-mqtt-retain-as-published";
const SUBSCRIPTION_ID_ARGUMENT: &str = "x-mqtt-subscription-id";

/// A subscription's options.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) struct Options {
    /// The QoS granted: the queue it is bound to.
    pub qos: QoS,
    /// Messages the session published itself are not sent to it.
    pub no_local: bool,
    /// Deliveries keep the RETAIN flag they were published with.
    pub retain_as_published: bool,
    /// Sent with every message the subscription matches.
    pub id: Option<NonZeroU32>,
}

impl Options {
    /// Whether a delivery has to look at this subscription.
    fn per_delivery(&self) -> bool {
        self.no_local || self.retain_as_published || self.id.is_some()
    }

    /// The binding arguments that keep the options with the binding
    /// (empty for a subscription without any, as 3.1.1 ones are).
    pub(super) fn binding_arguments(&self) -> FieldTable {
        let mut arguments = FieldTable::new();
        if self.no_local {
            arguments.insert(
                ShortStr::from_static(NO_LOCAL_ARGUMENT),
                FieldValue::Bool(true),
            );
        }
        if self.retain_as_published {
            arguments.insert(
                ShortStr::from_static(RETAIN_AS_PUBLISHED_ARGUMENT),
                FieldValue::Bool(true),
            );
        }
        if let Some(id) = self.id {
            arguments.insert(
                ShortStr::from_static(SUBSCRIPTION_ID_ARGUMENT),
                FieldValue::I64(i64::from(id.get())),
            );
        }
        arguments
    }

    /// The options of a binding of the session's queue for `qos`.
    pub(super) fn from_binding(qos: QoS, arguments: &FieldTable) -> Options {
        let flag = |name| matches!(arguments.get(name), Some(FieldValue::Bool(true)));
        let id = match arguments.get(SUBSCRIPTION_ID_ARGUMENT) {
            Some(FieldValue::I64(id)) => u32::try_from(*id).ok().and_then(NonZeroU32::new),
            _ => None,
        };
        Options {
            qos,
            no_local: flag(NO_LOCAL_ARGUMENT),
            retain_as_published: flag(RETAIN_AS_PUBLISHED_ARGUMENT),
            id,
        }
    }
}

/// A shared subscription of the session.
#[derive(Debug, Clone)]
pub(super) struct SharedSubscription {
    /// The session's consumer on it.
    pub consumer_tag: ShortStr,
    pub options: Options,
}

/// What a delivery's subscriptions decide.
#[derive(Debug, Default, PartialEq, Eq)]
pub(super) struct Verdict {
    /// False: every matching subscription has No Local and the session
    /// published the message itself; it is settled, not sent.
    pub send: bool,
    /// The RETAIN flag to send.
    pub retain: bool,
    /// The Subscription Identifiers to send.
    pub ids: Vec<NonZeroU32>,
}

/// A session's subscriptions.
#[derive(Debug, Default)]
pub(super) struct Subscriptions {
    /// Topic filter → options, for the session's own queues.
    own: HashMap<String, (TopicFilter, Options)>,
    /// Own subscriptions with an option a delivery must look at, per QoS.
    per_delivery: [usize; 3],
    /// Own subscriptions with No Local: while there is one, the session's
    /// publishes carry [`PUBLISHER_HEADER`].
    no_local: usize,
    /// `$share/GROUP/FILTER` → the shared subscription.
    shared: HashMap<String, SharedSubscription>,
    /// A shared subscription's consumer tag → its filter.
    shared_by_tag: HashMap<ShortStr, String>,
    /// Consumer tags handed out for shared subscriptions.
    next_tag: u64,
}

impl Subscriptions {
    /// Subscriptions held, own and shared.
    pub(super) fn len(&self) -> usize {
        self.own.len() + self.shared.len()
    }

    /// Whether one of the session's filters matches `topic` as MQTT
    /// matches (a shared one by the filter after `$share/GROUP/`).
    pub(super) fn any_matches(&self, topic: &str) -> bool {
        self.own.values().any(|(filter, _)| filter.matches(topic))
            || self.shared.keys().any(|shared| {
                MqttString::try_from(shared.as_str())
                    .ok()
                    .and_then(|f| TopicFilter::new(f).ok())
                    .is_some_and(|f| f.matches(topic))
            })
    }

    pub(super) fn contains(&self, filter: &str) -> bool {
        self.own.contains_key(filter) || self.shared.contains_key(filter)
    }

    /// Whether the session's publishes must say who published them.
    pub(super) fn marks_publisher(&self) -> bool {
        self.no_local > 0
    }

    /// Adds or replaces an own subscription; the options it replaces.
    /// The filter is copied: a slice of the read buffer would keep it alive.
    pub(super) fn insert_own(&mut self, filter: &TopicFilter, options: Options) -> Option<Options> {
        let text = filter.as_str().to_owned();
        // (The copy of a valid filter is valid.)
        let owned = own_filter(text.clone()).unwrap_or_else(|| filter.clone());
        let old = self.own.insert(text, (owned, options));
        if let Some(old) = old.as_ref().map(|(_, o)| *o) {
            self.count(&old, false);
        }
        self.count(&options, true);
        old.map(|(_, o)| o)
    }

    pub(super) fn remove_own(&mut self, filter: &str) -> Option<Options> {
        let (_, old) = self.own.remove(filter)?;
        self.count(&old, false);
        Some(old)
    }

    fn count(&mut self, options: &Options, added: bool) {
        let slot = &mut self.per_delivery[usize::from(options.qos.level())];
        let per_delivery = options.per_delivery();
        let no_local = options.no_local;
        for (counter, applies) in [(slot, per_delivery), (&mut self.no_local, no_local)] {
            if applies {
                *counter = if added {
                    *counter + 1
                } else {
                    counter.saturating_sub(1)
                };
            }
        }
    }

    pub(super) fn shared(&self, filter: &str) -> Option<&SharedSubscription> {
        self.shared.get(filter)
    }

    /// A consumer tag for a new shared subscription at `qos`.
    pub(super) fn new_shared_tag(&mut self, qos: QoS) -> ShortStr {
        self.next_tag += 1;
        shared_consumer_tag(self.next_tag, qos)
    }

    /// Adds or replaces a shared subscription; the one it replaces.
    pub(super) fn insert_shared(
        &mut self,
        filter: &str,
        subscription: SharedSubscription,
    ) -> Option<SharedSubscription> {
        self.shared_by_tag
            .insert(subscription.consumer_tag.clone(), filter.to_owned());
        let tag = subscription.consumer_tag.clone();
        let old = self.shared.insert(filter.to_owned(), subscription)?;
        if old.consumer_tag != tag {
            self.shared_by_tag.remove(&old.consumer_tag);
        }
        Some(old)
    }

    pub(super) fn remove_shared(&mut self, filter: &str) -> Option<SharedSubscription> {
        let old = self.shared.remove(filter)?;
        self.shared_by_tag.remove(&old.consumer_tag);
        Some(old)
    }

    /// What the session's subscriptions decide for a delivery to `topic`
    /// from the consumer `consumer_tag` (an own queue at `queue_qos`, or a
    /// shared subscription's).
    pub(super) fn for_delivery(
        &self,
        consumer_tag: &ShortStr,
        queue_qos: QoS,
        topic: &str,
        message: &Marks,
    ) -> Verdict {
        let shared = (!self.shared.is_empty())
            .then(|| self.shared_by_tag.get(consumer_tag))
            .flatten()
            .and_then(|filter| self.shared.get(filter));
        if let Some(shared) = shared {
            let options = shared.options;
            return Verdict {
                send: true,
                retain: options.retain_as_published && message.retained,
                ids: options.id.into_iter().collect(),
            };
        }
        let mut verdict = Verdict {
            send: true,
            ..Verdict::default()
        };
        if self.per_delivery[usize::from(queue_qos.level())] == 0 {
            return verdict;
        }
        let mut matched = false;
        let mut wanted = false;
        for (filter, options) in self.own.values() {
            if options.qos != queue_qos || !filter.matches(topic) {
                continue;
            }
            matched = true;
            if options.no_local && message.own {
                continue;
            }
            wanted = true;
            verdict.retain |= options.retain_as_published && message.retained;
            verdict.ids.extend(options.id);
        }
        // No filter matched (a binding made outside MQTT): sent as it is.
        verdict.send = wanted || !matched;
        verdict.ids.sort_unstable();
        verdict
    }
}

/// What a message says of its publish.
#[derive(Debug, Default)]
pub(super) struct Marks {
    /// Published by this session's client identifier.
    pub own: bool,
    /// Published with RETAIN set.
    pub retained: bool,
}

impl Marks {
    pub(super) fn of(properties: &BasicProperties, client_id: &str) -> Marks {
        let Some(headers) = properties.headers.as_ref() else {
            return Marks::default();
        };
        Marks {
            own: matches!(
                headers.get(PUBLISHER_HEADER),
                Some(FieldValue::LongStr(id)) if id.as_ref() == client_id.as_bytes()
            ),
            retained: matches!(headers.get(RETAIN_HEADER), Some(FieldValue::Bool(true))),
        }
    }
}

/// The consumer tag of the session's own queue for `qos`.
pub(super) fn own_consumer_tag(qos: QoS) -> ShortStr {
    match qos {
        QoS::AtMostOnce => ShortStr::from_static("mqtt-qos0"),
        QoS::AtLeastOnce => ShortStr::from_static("mqtt-qos1"),
        QoS::ExactlyOnce => ShortStr::from_static("mqtt-qos2"),
    }
}

/// The consumer tag of a shared subscription: numbered, ending like an
/// own queue's in the QoS, so a delivery's QoS is known from its tag even
/// after the subscription is gone.
fn shared_consumer_tag(number: u64, qos: QoS) -> ShortStr {
    ShortStr::try_from(format!("mqtt-shared-{number}-qos{}", qos.level()))
        .expect("a short consumer tag")
}

/// The QoS of the consumer a delivery with `consumer_tag` came from.
pub(super) fn consumer_qos(consumer_tag: &ShortStr) -> QoS {
    match consumer_tag.as_bytes().last() {
        Some(b'1') => QoS::AtLeastOnce,
        Some(b'2') => QoS::ExactlyOnce,
        _ => QoS::AtMostOnce,
    }
}

/// The filter of an own subscription read back from a binding key.
pub(super) fn own_filter(filter: String) -> Option<TopicFilter> {
    TopicFilter::new(MqttString::from_utf8(filter.into()).ok()?).ok()
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

    fn filter(f: &'static str) -> TopicFilter {
        TopicFilter::from_static(f)
    }

    #[test]
    fn options_round_trip_through_binding_arguments() {
        let plain = options(QoS::AtLeastOnce);
        assert!(plain.binding_arguments().is_empty());
        let all = Options {
            no_local: true,
            retain_as_published: true,
            id: NonZeroU32::new(268_435_455),
            ..plain
        };
        let back = Options::from_binding(QoS::AtLeastOnce, &all.binding_arguments());
        assert_eq!(back, all);
    }

    #[test]
    fn overlapping_filters_send_every_matching_identifier() {
        let mut subs = Subscriptions::default();
        for (f, id) in [("a/#", 1), ("a/+", 2), ("b/#", 3)] {
            let o = Options {
                id: NonZeroU32::new(id),
                ..options(QoS::AtLeastOnce)
            };
            subs.insert_own(&filter(f), o);
        }
        let tag = own_consumer_tag(QoS::AtLeastOnce);
        let v = subs.for_delivery(&tag, QoS::AtLeastOnce, "a/x", &Marks::default());
        assert_eq!(
            v.ids,
            [NonZeroU32::new(1).unwrap(), NonZeroU32::new(2).unwrap()]
        );
        assert!(v.send && !v.retain);
    }

    #[test]
    fn no_local_skips_only_when_every_match_has_it() {
        let mut subs = Subscriptions::default();
        let local = Options {
            no_local: true,
            ..options(QoS::AtMostOnce)
        };
        subs.insert_own(&filter("t/#"), local);
        assert!(subs.marks_publisher());
        let tag = own_consumer_tag(QoS::AtMostOnce);
        let own = Marks {
            own: true,
            retained: false,
        };
        assert!(!subs.for_delivery(&tag, QoS::AtMostOnce, "t/1", &own).send);
        assert!(
            subs.for_delivery(&tag, QoS::AtMostOnce, "t/1", &Marks::default())
                .send
        );
        subs.insert_own(&filter("t/+"), options(QoS::AtMostOnce));
        assert!(subs.for_delivery(&tag, QoS::AtMostOnce, "t/1", &own).send);
        subs.remove_own("t/#");
        assert!(!subs.marks_publisher());
        assert_eq!(subs.per_delivery, [0, 0, 0]);
    }

    #[test]
    fn replacing_a_subscription_keeps_the_counts() {
        let mut subs = Subscriptions::default();
        let rap = Options {
            retain_as_published: true,
            ..options(QoS::AtLeastOnce)
        };
        subs.insert_own(&filter("x"), rap);
        subs.insert_own(&filter("x"), rap);
        assert_eq!(subs.per_delivery, [0, 1, 0]);
        subs.insert_own(&filter("x"), options(QoS::ExactlyOnce));
        assert_eq!(subs.per_delivery, [0, 0, 0]);
    }

    #[test]
    fn a_consumer_tag_tells_its_qos() {
        for qos in [QoS::AtMostOnce, QoS::AtLeastOnce, QoS::ExactlyOnce] {
            assert_eq!(consumer_qos(&own_consumer_tag(qos)), qos);
            assert_eq!(consumer_qos(&shared_consumer_tag(u64::MAX, qos)), qos);
        }
    }
}
