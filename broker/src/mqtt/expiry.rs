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
/// `seconds` after its connection ends (`None`: never).
pub(super) fn queue_expires(seconds: Option<u32>) -> Option<u64> {
    seconds.map(|s| u64::from(s) * 1000)
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
