//! The `x-consistent-hash` exchange, after RabbitMQ's plugin of that name:
//! a binding's key is its weight (an integer), each message goes to
//! exactly one of the bound destinations, chosen by a hash of its routing
//! key (or, with the exchange argument `hash-header`, of that header's
//! value), so one key always lands on the same destination while the
//! bindings stay the same, and adding or removing a binding moves only
//! the keys of its share of the ring.
//!
//! Each binding puts `weight` × [`POINTS_PER_WEIGHT`] points on a 64-bit
//! ring, each at a hash of the destination's name, the binding key and the
//! point's number (stable across restarts); a message goes to the first
//! point at or after its own hash, wrapping around. Several points per unit
//! of weight keep the shares close to the weights whatever the names (with
//! one point per unit, a weight-1 queue's arc could be a sliver). Weights
//! are capped at [`MAX_WEIGHT`], so a binding holds at most
//! `MAX_WEIGHT × POINTS_PER_WEIGHT` points: adding or removing one costs
//! O(points × log points) (4,096 inserts at most, well under a
//! millisecond), routing one lookup, O(log points).

use super::{Destination, DestinationId};
use leveret_protocol::{FieldTable, FieldValue, ShortStr};
use std::collections::BTreeMap;

/// The exchange type's name.
pub const TYPE_NAME: &str = "x-consistent-hash";

/// The largest weight a binding may have.
pub const MAX_WEIGHT: u32 = 256;

/// Ring points per unit of weight.
pub const POINTS_PER_WEIGHT: u32 = 16;

/// The weight a binding key gives, if it is a valid one (1 to
/// [`MAX_WEIGHT`]).
pub fn weight(binding_key: &ShortStr) -> Option<u32> {
    let text = std::str::from_utf8(binding_key.as_bytes()).ok()?;
    let weight: u32 = text.trim().parse().ok()?;
    (1..=MAX_WEIGHT).contains(&weight).then_some(weight)
}

/// The ring: points ordered by position (ties broken by a second hash
/// that includes the destination's identity), each owned by a destination.
#[derive(Debug, Default)]
pub struct HashRing {
    points: BTreeMap<(u64, u64), Destination>,
    /// The header whose value is hashed instead of the routing key.
    hash_header: Option<ShortStr>,
}

impl HashRing {
    /// A ring for an exchange declared with `arguments`.
    pub fn new(arguments: &FieldTable) -> Self {
        let hash_header = match arguments.get("hash-header") {
            Some(FieldValue::LongStr(name)) => ShortStr::try_from(name.clone()).ok(),
            _ => None,
        };
        HashRing {
            points: BTreeMap::new(),
            hash_header,
        }
    }

    fn binding_points(
        destination: &Destination,
        binding_key: &ShortStr,
    ) -> impl Iterator<Item = (u64, u64)> {
        let name = match destination {
            Destination::Queue(queue) => queue.name.clone(),
            Destination::Exchange(exchange) => exchange.name.clone(),
        };
        let kind: &[u8] = match destination {
            Destination::Queue(_) => b"q",
            Destination::Exchange(_) => b"x",
        };
        let DestinationId(identity) = destination.id();
        let points = weight(binding_key).unwrap_or(0) * POINTS_PER_WEIGHT;
        let key = binding_key.clone();
        (0..points).map(move |point| {
            let position = hash(&[kind, name.as_bytes(), key.as_bytes(), &point.to_le_bytes()]);
            let tie = hash(&[
                &identity.to_le_bytes(),
                key.as_bytes(),
                &point.to_le_bytes(),
            ]);
            (position, tie)
        })
    }

    /// Puts a binding's points on the ring (none for an invalid weight,
    /// which binding refuses beforehand).
    pub fn add(&mut self, destination: &Destination, binding_key: &ShortStr) {
        for point in HashRing::binding_points(destination, binding_key) {
            self.points.insert(point, destination.clone());
        }
    }

    /// Takes a binding's points off the ring.
    pub fn remove(&mut self, destination: &Destination, binding_key: &ShortStr) {
        for point in HashRing::binding_points(destination, binding_key) {
            self.points.remove(&point);
        }
    }

    /// The destination of a message, if any binding is there (and, with
    /// `hash-header`, the message has that header).
    pub fn route(
        &self,
        routing_key: &ShortStr,
        headers: Option<&FieldTable>,
    ) -> Option<&Destination> {
        let position = match &self.hash_header {
            None => hash(&[routing_key.as_bytes()]),
            Some(name) => {
                let value = headers?.get(name.as_str()?)?;
                match (value.as_bytes(), value.as_i64()) {
                    (Some(bytes), _) => hash(&[bytes]),
                    (None, Some(number)) => hash(&[&number.to_le_bytes()]),
                    (None, None) => hash(&[format!("{value:?}").as_bytes()]),
                }
            }
        };
        self.points
            .range((position, 0)..)
            .next()
            .or_else(|| self.points.iter().next())
            .map(|(_, destination)| destination)
    }
}

/// FNV-1a over the parts, then a 64-bit finaliser (splitmix64) so that
/// nearby inputs land far apart on the ring.
fn hash(parts: &[&[u8]]) -> u64 {
    let mut state: u64 = 0xcbf2_9ce4_8422_2325;
    for part in parts {
        for &byte in *part {
            state ^= u64::from(byte);
            state = state.wrapping_mul(0x0100_0000_01b3);
        }
        // Separate the parts, so ("ab", "c") and ("a", "bc") differ.
        state ^= 0xff;
        state = state.wrapping_mul(0x0100_0000_01b3);
    }
    state ^= state >> 30;
    state = state.wrapping_mul(0xbf58_476d_1ce4_e5b9);
    state ^= state >> 27;
    state = state.wrapping_mul(0x94d0_49bb_1331_11eb);
    state ^ (state >> 31)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::exchange::tests::destinations;

    fn s(text: &str) -> ShortStr {
        ShortStr::try_from(text).unwrap()
    }

    #[test]
    fn weights_are_integers_from_1_to_the_cap() {
        assert_eq!(weight(&s("1")), Some(1));
        assert_eq!(weight(&s("10")), Some(10));
        assert_eq!(weight(&s(&MAX_WEIGHT.to_string())), Some(MAX_WEIGHT));
        for bad in ["", "0", "-1", "x", "1.5", "257", "99999999999"] {
            assert_eq!(weight(&s(bad)), None, "{bad:?}");
        }
    }

    #[test]
    fn each_key_goes_to_one_destination_by_weight_and_stays() {
        let d = destinations(3);
        let mut ring = HashRing::default();
        assert!(ring.route(&s("k"), None).is_none());
        ring.add(&d[0], &s("10"));
        ring.add(&d[1], &s("10"));
        ring.add(&d[2], &s("20"));
        let mut counts = [0usize; 3];
        let mut first = Vec::new();
        for i in 0..4000 {
            let key = s(&format!("robot-{i}"));
            let to = ring.route(&key, None).unwrap().id();
            let index = d.iter().position(|x| x.id() == to).unwrap();
            counts[index] += 1;
            first.push(index);
        }
        // Shares follow the weights (1:1:2), loosely.
        assert!(counts.iter().all(|&c| c > 400), "{counts:?}");
        assert!(counts[2] > counts[0] && counts[2] > counts[1], "{counts:?}");
        // Removing d[1] moves only the keys it had.
        ring.remove(&d[1], &s("10"));
        for (i, before) in first.iter().enumerate() {
            let key = s(&format!("robot-{i}"));
            let to = ring.route(&key, None).unwrap().id();
            if *before != 1 {
                assert_eq!(to, d[*before].id(), "key {i} moved");
            } else {
                assert_ne!(to, d[1].id());
            }
        }
        ring.remove(&d[0], &s("10"));
        ring.remove(&d[2], &s("20"));
        assert!(ring.points.is_empty());
    }

    /// Whatever the destinations are called, small weights get about their
    /// share: 1:1:2 over 100 differently named triples, every weight-1
    /// destination gets more than a tenth of 2,000 keys (a quarter expected).
    #[test]
    fn small_weights_get_their_share_whatever_the_names() {
        let d = destinations(300);
        for triple in d.chunks(3) {
            let mut ring = HashRing::default();
            for (destination, key) in triple.iter().zip(["1", "1", "2"]) {
                ring.add(destination, &s(key));
            }
            let mut counts = [0usize; 3];
            for i in 0..2000 {
                let to = ring.route(&s(&format!("robot-{i}")), None).unwrap().id();
                counts[triple.iter().position(|x| x.id() == to).unwrap()] += 1;
            }
            assert!(counts[0] > 200 && counts[1] > 200, "{counts:?}");
        }
    }

    #[test]
    fn hash_header_routes_by_the_header() {
        let d = destinations(2);
        let mut arguments = FieldTable::new();
        arguments.insert(s("hash-header"), FieldValue::string("robot"));
        let mut ring = HashRing::new(&arguments);
        ring.add(&d[0], &s("5"));
        ring.add(&d[1], &s("5"));
        assert!(ring.route(&s("any"), None).is_none(), "no header");
        let mut seen = std::collections::BTreeSet::new();
        for i in 0..200 {
            let mut headers = FieldTable::new();
            headers.insert(s("robot"), FieldValue::string(&format!("r{i}")));
            let a = ring.route(&s("a"), Some(&headers)).unwrap().id();
            let b = ring.route(&s("b"), Some(&headers)).unwrap().id();
            assert_eq!(a, b, "the routing key does not matter");
            seen.insert(a);
        }
        assert_eq!(seen.len(), 2);
    }
}
