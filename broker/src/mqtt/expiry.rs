//! A persistent session's expiry, kept on its queues: each carries the
//! session's Session Expiry Interval as `x-expires` (the core deletes a
//! queue unused that long, and so the session), set when the queue is
//! declared and changed in place (`Queue::set_expires`, stored with a
//! durable queue) when the session's expiry changes: by a 5.0
//! DISCONNECT's Session Expiry Interval (MQTT-3.14.2-2), or by the
//! CONNECT that resumes the session with another (the latest
//! connection's interval is the session's).

use crate::core::Core;
use leveret_protocol::{FieldValue, ShortStr};
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
pub(super) fn queue_expires(seconds: Option<u32>) -> Option<u64> {
    seconds.map(|s| u64::from(s.min(MAX_FINITE_SECONDS)) * 1000)
}

/// Makes the session queues `names` of `vhost` that outlive their
/// connection expire after `expires` ms unused (`None`: never), those
/// that do not already; how many changed.
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
        let current = (queue.arguments().get("x-expires"))
            .and_then(FieldValue::as_i64)
            .and_then(|ms| u64::try_from(ms).ok());
        if current != expires && vhost.set_queue_expires(&queue, expires) {
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
    }
}
