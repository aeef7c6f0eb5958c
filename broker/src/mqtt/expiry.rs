//! A persistent session's expiry, kept on its queues: each carries the
//! session's Session Expiry Interval as `x-expires` (the core deletes a
//! queue unused that long, and so the session), set when the queue is
//! declared and changed in place (`Queue::set_expires`, stored with a
//! durable queue) when the session's expiry changes: by a 5.0
//! DISCONNECT's Session Expiry Interval (MQTT-3.14.2-2), or by the
//! CONNECT that resumes the session with another (the latest
//! connection's interval is the session's). Sessions restored from the
//! store are given the broker's cap at start ([`cap_restored_queues`],
//! [`restored`]), every part of a session alike and written back (its
//! queues here, its QoS 2 and shared subscription records by `releases`
//! and `shares`, before its queues: `super::write_back_restored`), so
//! that whatever caps later starts have, its parts keep expiring
//! together.

use super::mapping;
use crate::core::Core;
use crate::vhost::Vhost;
use leveret_protocol::{FieldValue, ShortStr};
use std::sync::Arc;
use std::time::{Duration, Instant};

/// The longest finite Session Expiry Interval a session is given (s):
/// its queues' `x-expires` (ms) is then at most the largest a queue takes
/// (2^32 - 1 ms, RabbitMQ's limit), about 49.7 days.
pub(super) const MAX_FINITE_SECONDS: u32 = 4_294_967;

/// RabbitMQ's default `mqtt.max_session_expiry_interval_seconds` (3.13):
/// a day.
pub(crate) const DEFAULT_MAX_SECONDS: u32 = 86_400;

/// The Session Expiry Interval a session is given for the one a 5.0
/// client asks for (CONNECT or DISCONNECT), under the broker's cap `max`
/// (`None`: RabbitMQ's `infinity`, and then 0xFFFFFFFF still means
/// never): at most `max`, and at most [`MAX_FINITE_SECONDS`] unless never.
pub(super) fn capped(requested: u32, max: Option<u32>) -> u32 {
    match max {
        None if requested == u32::MAX => u32::MAX,
        None => requested.min(MAX_FINITE_SECONDS),
        Some(max) => requested.min(max).min(MAX_FINITE_SECONDS),
    }
}

/// When a session whose connection ends now expires, `seconds` from now
/// (`None`: never); the state it keeps beside its queues (unreleased QoS 2
/// publishes, shared subscriptions) goes then.
pub(super) fn ends_at(seconds: Option<u32>) -> Option<Instant> {
    seconds.map(|s| Instant::now() + Duration::from_secs(s.into()))
}

/// Whether a session that expires at `at` (`None`: never) has by `now`.
pub(super) fn has_passed(at: Option<Instant>, now: Instant) -> bool {
    at.is_some_and(|at| at <= now)
}

/// The `x-expires` (ms) of the queues of a session that expires
/// `seconds` after its connection ends (`None`: never); never above the
/// largest a queue takes (an interval an older Leveret stored uncapped).
/// 0 (a session restored under a cap of 0: it ended with its connection,
/// before the restart) is 1 ms, the least a queue takes: they go once
/// unused.
pub(super) fn queue_expires(seconds: Option<u32>) -> Option<u64> {
    seconds.map(|s| (u64::from(s.min(MAX_FINITE_SECONDS)) * 1000).max(1))
}

/// The expiry interval (s; `None`: never) a session restored from the
/// store is given under the broker's cap `max`, for the one it was stored
/// with (`u32::MAX`: never, as a 3.1.1 persistent session was before the
/// cap applied to it): the lower of the two.
pub(super) fn restored(stored: u32, max: Option<u32>) -> Option<u32> {
    match capped(stored, max) {
        u32::MAX => None,
        seconds => Some(seconds),
    }
}

/// The mark of a session's own queue.
const SESSION_MARK: &str = crate::arguments::MQTT_SESSION;

/// Queues [`cap_restored_queues`] looks at between yields.
const CAP_CHUNK: usize = 256;

/// Gives the persistent sessions' queues restored from the store (durable
/// `mqtt-subscription-<client id>qos<N>` queues in `vhosts`) the broker's
/// cap `max` (s; `None`: none) where their `x-expires` is longer or
/// absent: once at start, before anything sweeps the vhosts, so that a
/// session stored as never expiring (a 3.1.1 one, by a Leveret before the
/// cap applied to those) or with a longer interval expires `max` seconds
/// after the start unless its client comes back, as its QoS 2 and shared
/// subscription records do (both written back). Only queues a session
/// declared or resumed (marked [`crate::arguments::MQTT_SESSION`]) are
/// capped, and unmarked ones (an older Leveret's, or an AMQP client's of
/// that name) only where `holds(vhost, client id)` (the session has
/// restored QoS 2 or shared subscription state: it is an MQTT session's;
/// then marked), under `0` too: that session's records are restored as
/// ended, so its queue is given 1 ms and goes with them, never left as a
/// session present without them. An unmarked queue without such a
/// session is never changed. Yields every [`CAP_CHUNK`] queues. How many
/// changed.
pub(super) async fn cap_restored_queues(
    vhosts: &[Arc<Vhost>],
    max: Option<u32>,
    holds: impl Fn(&str, &str) -> bool,
) -> usize {
    let Some(cap) = queue_expires(max) else {
        return 0;
    };
    let mut changed = 0;
    for vhost in vhosts {
        let vhost_name = vhost.name.to_string_lossy();
        for chunk in vhost.queues().chunks(CAP_CHUNK) {
            for queue in chunk {
                let Some(client_id) = queue.name.as_str().and_then(mapping::session_of_queue)
                else {
                    continue;
                };
                if !queue.options.durable || queue.options.exclusive_owner.is_some() {
                    continue;
                }
                let arguments = queue.arguments();
                let ours = crate::arguments::marks_an_mqtt_session_queue(&arguments)
                    || holds(&vhost_name, client_id);
                let current = (arguments.get("x-expires"))
                    .and_then(FieldValue::as_i64)
                    .and_then(|ms| u64::try_from(ms).ok());
                // An unmarked one of a session with records is its
                // session's: marked as such.
                if ours
                    && current.is_none_or(|ms| ms > cap)
                    && vhost.set_queue_expires(queue, Some(cap), Some(SESSION_MARK))
                {
                    changed += 1;
                }
            }
            tokio::task::yield_now().await;
        }
    }
    changed
}

/// The longer of two Session Expiry Intervals (`None`: never).
pub(super) fn longest(a: Option<u32>, b: Option<u32>) -> Option<u32> {
    a.zip(b).map(|(a, b)| a.max(b))
}

/// Makes the session queues `names` of `vhost` that outlive their
/// connection expire after `expires` ms unused (`None`: never), those
/// that do not already, and marks them as the session's (one it resumed
/// without the mark, an older Leveret's or an AMQP client's, is its
/// session's from then on, as RabbitMQ 3.13 takes it); how many changed.
pub(super) fn follow(
    core: &Core,
    vhost: &str,
    names: impl IntoIterator<Item = ShortStr>,
    expires: Option<u64>,
) -> usize {
    let Some(vhost) = ShortStr::try_from(vhost)
        .ok()
        .and_then(|name| core.vhost(&name))
    else {
        return 0;
    };
    let mut changed = 0;
    for name in names {
        let Some(queue) = vhost.queue(&name) else {
            continue;
        };
        if queue.options.exclusive_owner.is_some() {
            continue;
        }
        let arguments = queue.arguments();
        let marked = crate::arguments::marks_an_mqtt_session_queue(&arguments);
        let current = (arguments.get("x-expires"))
            .and_then(FieldValue::as_i64)
            .and_then(|ms| u64::try_from(ms).ok());
        let changes = current != expires || !marked;
        if changes && vhost.set_queue_expires(&queue, expires, Some(SESSION_MARK)) {
            changed += 1;
        }
    }
    changed
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn intervals_are_capped_and_queue_expiry_stays_within_amqps_maximum() {
        let day = Some(DEFAULT_MAX_SECONDS);
        assert_eq!(capped(0, day), 0);
        assert_eq!(capped(60, day), 60);
        assert_eq!(capped(5_000_000, day), 86_400);
        assert_eq!(capped(u32::MAX, day), 86_400, "never is capped too");
        assert_eq!(
            capped(60, Some(0)),
            0,
            "every session ends with its connection"
        );
        // infinity: never stays never; a finite interval stays finite.
        assert_eq!(capped(u32::MAX, None), u32::MAX);
        assert_eq!(capped(5_000_000, None), MAX_FINITE_SECONDS);
        assert_eq!(capped(5_000_000, Some(5_000_000)), MAX_FINITE_SECONDS);
        assert_eq!(queue_expires(Some(5_000_000)), Some(4_294_967_000));
        assert!(queue_expires(Some(u32::MAX - 1)).is_some_and(|ms| ms <= 4_294_967_295));
        assert_eq!(queue_expires(Some(0)), Some(1), "the least a queue takes");
    }

    /// The `x-expires` of `queue` now.
    fn expires_of(queue: &crate::queue::Queue) -> Option<i64> {
        (queue.arguments().get("x-expires")).and_then(FieldValue::as_i64)
    }

    #[tokio::test]
    async fn only_queues_of_sessions_declared_or_with_records_are_capped_at_start_under_0_too() {
        use crate::testkit::Harness;
        let marked = (crate::arguments::MQTT_SESSION, FieldValue::Bool(true));
        let unmarked = (crate::arguments::MQTT_SESSION, FieldValue::Bool(false));
        for (max, want) in [(Some(60), Some(60_000)), (Some(0), Some(1))] {
            let h = Harness::durable();
            let session = h.declare_queue(
                "mqtt-subscription-devqos1",
                true,
                std::slice::from_ref(&marked),
            );
            // An AMQP client's of a session queue's name, one that says
            // `false`, and an older Leveret's of a session with records.
            let amqp = h.declare_queue("mqtt-subscription-appqos1", true, &[]);
            let untrue = h.declare_queue(
                "mqtt-subscription-noqos2",
                true,
                std::slice::from_ref(&unmarked),
            );
            let older = h.declare_queue("mqtt-subscription-oldqos0", true, &[]);
            let holds = |vhost: &str, client_id: &str| vhost == "/" && client_id == "old";
            let vhosts = [Arc::clone(&h.vhost)];
            let changed = cap_restored_queues(&vhosts, max, holds).await;
            assert_eq!(expires_of(&session), want);
            assert_eq!(expires_of(&amqp), None, "an AMQP client's is left alone");
            assert_eq!(expires_of(&untrue), None, "false marks nothing");
            // Under 0 too: its records are restored as ended, and it goes
            // with them (1 ms), never kept as a session present without.
            assert_eq!(changed, 2);
            assert_eq!(expires_of(&older), want, "its session's records say so");
            let arguments = older.arguments();
            assert!(crate::arguments::marks_an_mqtt_session_queue(&arguments));
        }
        // Only lowered, never raised.
        let h = Harness::durable();
        let minute = [marked, ("x-expires", FieldValue::I64(60_000))];
        let session = h.declare_queue("mqtt-subscription-devqos1", true, &minute);
        let vhosts = [Arc::clone(&h.vhost)];
        assert_eq!(
            cap_restored_queues(&vhosts, Some(3600), |_, _| false).await,
            0
        );
        assert_eq!(cap_restored_queues(&vhosts, None, |_, _| false).await, 0);
        assert_eq!(expires_of(&session), Some(60_000));
    }

    #[test]
    fn a_marked_session_queues_expiry_is_not_compared_on_redeclaration() {
        use crate::queue::QueueOptions;
        use crate::vhost::QueueDeclaration;
        let h = crate::testkit::Harness::durable();
        let marked = (crate::arguments::MQTT_SESSION, FieldValue::Bool(true));
        let hour = [marked, ("x-expires", FieldValue::I64(3_600_000))];
        let queue = h.declare_queue("mqtt-subscription-devqos1", true, &hour);
        // An old export's, without the mark or with another x-expires.
        let redeclared = |arguments: &[(&str, FieldValue)]| QueueDeclaration {
            name: crate::testkit::s("mqtt-subscription-devqos1"),
            passive: false,
            server_named: false,
            options: QueueOptions {
                durable: true,
                exclusive_owner: None,
                auto_delete: false,
                arguments: crate::testkit::table(arguments),
            },
            max_queues: None,
        };
        let minute = ("x-expires", FieldValue::I64(60_000));
        assert!(h.vhost.declare_queue(redeclared(&[]), 0).is_ok());
        assert!(h.vhost.declare_queue(redeclared(&[minute]), 0).is_ok());
        assert_eq!(expires_of(&queue), Some(3_600_000));
        // The rest is compared.
        let length = ("x-max-length", FieldValue::I64(10));
        assert!(h.vhost.declare_queue(redeclared(&[length]), 0).is_err());
        // An unmarked one's x-expires is.
        let plain = [("x-expires", FieldValue::I64(3_600_000))];
        h.declare_queue("mqtt-subscription-appqos1", true, &plain);
        let mut other = redeclared(&[("x-expires", FieldValue::I64(60_000))]);
        other.name = crate::testkit::s("mqtt-subscription-appqos1");
        assert!(h.vhost.declare_queue(other, 0).is_err());
    }

    #[test]
    fn a_restored_session_is_given_the_cap_if_it_outlives_it() {
        // Stored as never expiring (a 3.1.1 session before the cap applied).
        assert_eq!(restored(u32::MAX, Some(DEFAULT_MAX_SECONDS)), Some(86_400));
        assert_eq!(restored(u32::MAX, None), None, "infinity keeps never");
        assert_eq!(restored(60, Some(DEFAULT_MAX_SECONDS)), Some(60));
        assert_eq!(restored(7200, Some(3600)), Some(3600));
        assert_eq!(restored(7200, Some(0)), Some(0));
        assert_eq!(restored(7200, None), Some(7200));
    }
}
