//! Slowing repeated failed logins per source address: each failure from
//! a source makes its next failure answer later (doubling from
//! [`FIRST_DELAY`] up to [`MAX_DELAY`]), until the source has had no
//! failure for [`FORGET_AFTER`].
//!
//! Only failures wait: the delay is taken before the failure is
//! answered, never before a check, and holds no hashing thread. A
//! password that passes is answered at once, so a stranger failing from
//! the same address (or the same NAT, or 127.0.0.1) cannot lock a
//! legitimate user out; a guesser waits longer for each wrong answer.
//! The table is bounded ([`MAX_SOURCES`]). Uses nothing else of the broker.

use std::collections::HashMap;
use std::sync::Mutex;
use std::time::{Duration, Instant};

/// The delay after a source's first failure.
pub const FIRST_DELAY: Duration = Duration::from_millis(50);
/// The longest delay.
pub const MAX_DELAY: Duration = Duration::from_secs(2);
/// A source without a failure for this long starts over.
pub const FORGET_AFTER: Duration = Duration::from_secs(60);
/// Sources remembered at once; beyond it, stale ones are forgotten, then
/// new sources are not slowed until there is room.
pub const MAX_SOURCES: usize = 4096;

#[derive(Debug, Clone, Copy)]
struct Failures {
    count: u32,
    last: Instant,
}

/// Recent failures per source.
#[derive(Debug, Default)]
pub struct LoginBackoff {
    // Held for one lookup or update, never across an await.
    sources: Mutex<HashMap<String, Failures>>,
}

impl LoginBackoff {
    /// Records a failure from `source`; how long to wait before answering it.
    pub fn failed(&self, source: &str) -> Duration {
        self.failed_at(source, Instant::now())
    }

    fn failed_at(&self, source: &str, now: Instant) -> Duration {
        let mut sources = self.sources.lock().unwrap_or_else(|e| e.into_inner());
        if sources.len() >= MAX_SOURCES && !sources.contains_key(source) {
            sources.retain(|_, f| now.duration_since(f.last) < FORGET_AFTER);
            if sources.len() >= MAX_SOURCES {
                return Duration::ZERO;
            }
        }
        let failures = sources.entry(source.to_owned()).or_insert(Failures {
            count: 0,
            last: now,
        });
        if now.duration_since(failures.last) >= FORGET_AFTER {
            failures.count = 0;
        }
        failures.count = failures.count.saturating_add(1);
        failures.last = now;
        let doublings = (failures.count - 1).min(16);
        FIRST_DELAY.saturating_mul(1 << doublings).min(MAX_DELAY)
    }
}

/// The part of a peer's address failures are counted by: the IP address
/// of an `ip:port`, or the whole text for anything else (`in-process`).
pub fn source_of(peer: &str) -> String {
    match peer.parse::<std::net::SocketAddr>() {
        Ok(addr) => addr.ip().to_canonical().to_string(),
        Err(_) => peer.to_owned(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn each_failure_doubles_the_delay_up_to_the_most_and_is_forgotten() {
        let backoff = LoginBackoff::default();
        let start = Instant::now();
        let delays: Vec<_> = (0..8).map(|_| backoff.failed_at("a", start)).collect();
        let ms: Vec<u128> = delays.iter().map(Duration::as_millis).collect();
        assert_eq!(ms, [50, 100, 200, 400, 800, 1600, 2000, 2000]);
        // Another source starts over.
        assert_eq!(backoff.failed_at("b", start), FIRST_DELAY);
        // So does this one, after a quiet minute.
        assert_eq!(backoff.failed_at("a", start + FORGET_AFTER), FIRST_DELAY);
    }

    #[test]
    fn the_table_stays_bounded() {
        let backoff = LoginBackoff::default();
        let start = Instant::now();
        for i in 0..MAX_SOURCES {
            backoff.failed_at(&format!("s{i}"), start);
        }
        assert_eq!(backoff.failed_at("new", start), Duration::ZERO);
        assert_eq!(backoff.failed_at("s1", start), 2 * FIRST_DELAY);
        // Once the old entries are stale they make room.
        assert_eq!(backoff.failed_at("new", start + FORGET_AFTER), FIRST_DELAY);
        assert_eq!(backoff.sources.lock().unwrap().len(), 1);
    }

    #[test]
    fn sources_are_addresses_without_ports() {
        assert_eq!(source_of("127.0.0.1:5000"), "127.0.0.1");
        assert_eq!(source_of("[::ffff:10.0.0.1]:5000"), "10.0.0.1");
        assert_eq!(source_of("in-process"), "in-process");
    }
}
