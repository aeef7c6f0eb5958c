//! The names the broker makes up, as RabbitMQ does: consumer tags
//! (`amq.ctag-…`), server-named queues (`amq.gen-…`), direct reply-to
//! addresses, and the client identifiers MQTT assigns.
//!
//! Uses nothing of the broker.

use leveret_protocol::ShortStr;
use std::sync::atomic::{AtomicU64, Ordering};

/// `prefix` and a unique suffix: 22 characters of `[A-Za-z0-9_-]` from a
/// counter and a per-call random hash.
pub(crate) fn unique_name(prefix: &str) -> ShortStr {
    use std::hash::{BuildHasher, Hasher};
    static COUNTER: AtomicU64 = AtomicU64::new(0);
    let mut hasher = std::collections::hash_map::RandomState::new().build_hasher();
    hasher.write_u64(COUNTER.fetch_add(1, Ordering::Relaxed));
    let a = hasher.finish();
    hasher.write_u64(a);
    let b = hasher.finish();
    const ALPHABET: &[u8; 64] = b"ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789-_";
    let mut name = String::with_capacity(prefix.len() + 22);
    name.push_str(prefix);
    let mut bits = (u128::from(a) << 64) | u128::from(b);
    for _ in 0..22 {
        name.push(ALPHABET[(bits & 63) as usize] as char);
        bits >>= 6;
    }
    ShortStr::try_from(name).unwrap_or_default()
}
