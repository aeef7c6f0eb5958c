//! The headers exchange's match, as RabbitMQ 3.10 does it, in time linear
//! in the sizes of the binding and the message.
//!
//! A binding's arguments are compiled once, when it is added, into a
//! [`HeadersPattern`]: the `x-match` mode (`all`, the default, `any`,
//! `all-with-x`, `any-with-x`) and the arguments to compare. `x-match`
//! itself is never compared, and other arguments starting with `x-` are
//! compared only in the `-with-x` modes. A message's headers are indexed
//! once per routing into [`MessageHeaders`], a hash map, so each binding
//! costs one lookup per argument: O(headers + binding arguments) instead of
//! their product. Keys are hashed with the exchange's [`HeaderHasher`]: an
//! argument once, when bound, a header once per routing; a lookup then
//! compares hashes, then keys. The hash is keyed with a secret, so no peer
//! can pick keys that collide.
//!
//! Values compare as RabbitMQ compares the decoded values (Erlang's `==`):
//! numbers by value whatever their type (an `I` 1, an `l` 1, a `T` 1 and a
//! `d` 1.0 are equal), long strings and byte arrays by their bytes, other
//! values (booleans, decimals, arrays, tables) exactly, types included. A
//! void argument matches any value of that header. When a table repeats a
//! key, RabbitMQ's sorted merge pairs the n-th argument of that key with
//! the n-th header of that key; so does this.

use leveret_protocol::{FieldTable, FieldValue, ShortStr};
use std::collections::hash_map::RandomState;
use std::collections::HashMap;
use std::hash::{BuildHasher, BuildHasherDefault, Hasher};

/// The keyed hash of a headers exchange's keys (a secret drawn per
/// exchange).
#[derive(Debug, Default)]
pub(super) struct HeaderHasher(RandomState);

impl HeaderHasher {
    fn hash(&self, key: &[u8]) -> u64 {
        self.0.hash_one(key)
    }
}

/// A hasher for keys that are already [`HeaderHasher`] hashes.
#[derive(Debug, Default)]
struct Prehashed(u64);

impl Hasher for Prehashed {
    fn finish(&self) -> u64 {
        self.0
    }

    fn write(&mut self, bytes: &[u8]) {
        for &byte in bytes {
            self.0 = self.0.rotate_left(8) ^ u64::from(byte);
        }
    }

    fn write_u64(&mut self, hash: u64) {
        self.0 = hash;
    }
}

/// A map keyed by [`HeaderHasher`] hashes.
type ByHash<V> = HashMap<u64, V, BuildHasherDefault<Prehashed>>;

/// Whether `x-match` holds a value RabbitMQ accepts (a long string `all`,
/// `any`, `all-with-x` or `any-with-x`; absent means `all`).
pub fn valid_x_match(arguments: &FieldTable) -> bool {
    match arguments.get("x-match") {
        None => true,
        Some(FieldValue::LongStr(mode)) => {
            matches!(&mode[..], b"all" | b"any" | b"all-with-x" | b"any-with-x")
        }
        Some(_) => false,
    }
}

/// One argument a message's headers are compared with.
#[derive(Debug)]
struct Wanted {
    key: ShortStr,
    /// `key` hashed by the exchange's [`HeaderHasher`].
    hash: u64,
    /// How many earlier arguments have the same key.
    occurrence: usize,
    /// `None` for a void argument: the header need only be present.
    value: Option<FieldValue>,
}

/// A binding's arguments, ready to match messages against.
#[derive(Debug)]
pub(super) struct HeadersPattern {
    /// `any` (or `any-with-x`) rather than `all`.
    any: bool,
    wanted: Vec<Wanted>,
}

impl HeadersPattern {
    /// Compiles a binding's arguments (an unknown `x-match`, which only a
    /// stored binding can carry, means `all`, as in RabbitMQ).
    pub(super) fn new(arguments: &FieldTable, hasher: &HeaderHasher) -> Self {
        let mode = match arguments.get("x-match") {
            Some(FieldValue::LongStr(mode)) => &mode[..],
            _ => b"all",
        };
        let any = matches!(mode, b"any" | b"any-with-x");
        let with_x = matches!(mode, b"all-with-x" | b"any-with-x");
        let mut seen: HashMap<&[u8], usize> = HashMap::new();
        let wanted = arguments
            .iter()
            .filter(|(key, _)| {
                let key = key.as_bytes();
                key != b"x-match" && (with_x || !key.starts_with(b"x-"))
            })
            .map(|(key, value)| {
                let count = seen.entry(key.as_bytes()).or_insert(0);
                let occurrence = *count;
                *count += 1;
                Wanted {
                    key: key.clone(),
                    hash: hasher.hash(key.as_bytes()),
                    occurrence,
                    value: (!matches!(value, FieldValue::Void)).then(|| value.clone()),
                }
            })
            .collect();
        HeadersPattern { any, wanted }
    }

    /// Whether a message with these headers matches.
    pub(super) fn matches(&self, headers: &MessageHeaders<'_>) -> bool {
        let mut hits = self.wanted.iter().map(|wanted| {
            match headers.get(wanted.key.as_bytes(), wanted.hash, wanted.occurrence) {
                None => false,
                Some(actual) => wanted
                    .value
                    .as_ref()
                    .is_none_or(|expected| same_value(expected, actual)),
            }
        });
        if self.any {
            hits.any(|hit| hit)
        } else {
            hits.all(|hit| hit)
        }
    }
}

/// The headers of a message under one hash (one key, but for a collision
/// of keyed hashes), in table order.
#[derive(Debug)]
struct Slot<'a> {
    first: (&'a [u8], &'a FieldValue),
    /// Headers after the first (a repeated key; almost always none).
    more: Vec<(&'a [u8], &'a FieldValue)>,
}

/// A message's headers indexed by key, built once per routing.
#[derive(Debug, Default)]
pub(super) struct MessageHeaders<'a> {
    by_hash: ByHash<Slot<'a>>,
}

impl<'a> MessageHeaders<'a> {
    /// Indexes a message's headers (none is an empty table) with the
    /// exchange's hasher.
    pub(super) fn new(headers: Option<&'a FieldTable>, hasher: &HeaderHasher) -> Self {
        let mut by_hash: ByHash<Slot<'a>> = ByHash::with_capacity_and_hasher(
            headers.map_or(0, FieldTable::len),
            Default::default(),
        );
        for (key, value) in headers.into_iter().flat_map(FieldTable::iter) {
            let header = (key.as_bytes(), value);
            by_hash
                .entry(hasher.hash(key.as_bytes()))
                .and_modify(|slot| slot.more.push(header))
                .or_insert(Slot {
                    first: header,
                    more: Vec::new(),
                });
        }
        MessageHeaders { by_hash }
    }

    /// The `occurrence`-th value (from 0) under `key`, whose hash is `hash`.
    fn get(&self, key: &[u8], hash: u64, occurrence: usize) -> Option<&'a FieldValue> {
        let slot = self.by_hash.get(&hash)?;
        std::iter::once(&slot.first)
            .chain(&slot.more)
            .filter(|(header, _)| *header == key)
            .nth(occurrence)
            .map(|(_, value)| *value)
    }
}

/// A number as Erlang holds it: an integer or a float.
#[derive(Debug, Clone, Copy)]
enum Number {
    Integer(i128),
    Float(f64),
}

fn number(value: &FieldValue) -> Option<Number> {
    Some(match *value {
        FieldValue::I8(v) => Number::Integer(v.into()),
        FieldValue::U8(v) => Number::Integer(v.into()),
        FieldValue::I16(v) => Number::Integer(v.into()),
        FieldValue::U16(v) => Number::Integer(v.into()),
        FieldValue::I32(v) => Number::Integer(v.into()),
        FieldValue::U32(v) => Number::Integer(v.into()),
        FieldValue::I64(v) => Number::Integer(v.into()),
        FieldValue::Timestamp(v) => Number::Integer(v.into()),
        FieldValue::F32(v) => Number::Float(v.into()),
        FieldValue::F64(v) => Number::Float(v),
        _ => return None,
    })
}

/// Erlang's `==` between an integer and a float: equal when they are the
/// same number exactly.
fn integer_equals_float(integer: i128, float: f64) -> bool {
    // 2^127 as a float: every float in [-2^127, 2^127) converts exactly.
    const LIMIT: f64 = 170_141_183_460_469_231_731_687_303_715_884_105_728.0;
    float.fract() == 0.0 && (-LIMIT..LIMIT).contains(&float) && float as i128 == integer
}

/// Values compare as RabbitMQ compares them (see the module docs).
fn same_value(expected: &FieldValue, actual: &FieldValue) -> bool {
    match (number(expected), number(actual)) {
        (Some(Number::Integer(a)), Some(Number::Integer(b))) => a == b,
        (Some(Number::Float(a)), Some(Number::Float(b))) => a == b,
        (Some(Number::Integer(i)), Some(Number::Float(f)))
        | (Some(Number::Float(f)), Some(Number::Integer(i))) => integer_equals_float(i, f),
        (Some(_), None) | (None, Some(_)) => false,
        (None, None) => match (expected.as_bytes(), actual.as_bytes()) {
            (Some(a), Some(b)) => a == b,
            (None, None) => expected == actual,
            _ => false,
        },
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use bytes::Bytes;
    use leveret_protocol::Decimal;
    use proptest::prelude::*;

    fn s(key: &str) -> ShortStr {
        ShortStr::try_from(key).expect("short")
    }

    fn table(entries: &[(&str, FieldValue)]) -> FieldTable {
        // Built entry by entry so that repeated keys stay repeated, as a
        // decoded table from a peer may have them.
        let mut encoded = bytes::BytesMut::new();
        let mut body = bytes::BytesMut::new();
        for (key, value) in entries {
            let one: FieldTable = std::iter::once((s(key), value.clone())).collect();
            let mut buf = bytes::BytesMut::new();
            one.encode(&mut buf);
            body.extend_from_slice(&buf[4..]);
        }
        bytes::BufMut::put_u32(&mut encoded, body.len() as u32);
        encoded.extend_from_slice(&body);
        FieldTable::decode(&encoded.freeze()).expect("decodes")
    }

    fn matches(arguments: &[(&str, FieldValue)], headers: &[(&str, FieldValue)]) -> bool {
        let arguments = table(arguments);
        let headers = table(headers);
        let hasher = HeaderHasher::default();
        HeadersPattern::new(&arguments, &hasher)
            .matches(&MessageHeaders::new(Some(&headers), &hasher))
    }

    fn text(s: &str) -> FieldValue {
        FieldValue::string(s)
    }

    #[test]
    fn all_any_and_the_default() {
        let args = [("x-match", text("all")), ("a", text("1")), ("b", text("2"))];
        assert!(matches(
            &args,
            &[("b", text("2")), ("a", text("1")), ("c", text("3"))]
        ));
        assert!(!matches(&args, &[("a", text("1"))]));
        assert!(!matches(&args, &[("a", text("1")), ("b", text("3"))]));
        let any = [("x-match", text("any")), ("a", text("1")), ("b", text("2"))];
        assert!(matches(&any, &[("b", text("2"))]));
        assert!(!matches(&any, &[("b", text("1")), ("c", text("2"))]));
        assert!(!matches(&any, &[]), "any with no header matches nothing");
        let default = [("a", text("1"))];
        assert!(matches(&default, &[("a", text("1"))]));
        assert!(!matches(&default, &[]));
        assert!(
            matches(&[("x-match", text("all"))], &[]),
            "nothing to compare"
        );
        assert!(!matches(&[("x-match", text("any"))], &[("a", text("1"))]));
        let none = FieldTable::new();
        let hasher = HeaderHasher::default();
        let pattern = HeadersPattern::new(&none, &hasher);
        assert!(pattern.matches(&MessageHeaders::new(None, &hasher)));
    }

    #[test]
    fn x_arguments_count_only_with_x_and_x_match_never() {
        let args = [
            ("x-match", text("all")),
            ("x-k", text("1")),
            ("a", text("1")),
        ];
        assert!(matches(&args, &[("a", text("1"))]), "x-k ignored");
        let with_x = [
            ("x-match", text("all-with-x")),
            ("x-k", text("1")),
            ("a", text("1")),
        ];
        assert!(!matches(&with_x, &[("a", text("1"))]), "x-k compared");
        assert!(
            matches(&with_x, &[("a", text("1")), ("x-k", text("1"))]),
            "x-match itself is not compared"
        );
        let any_x = [("x-match", text("any-with-x")), ("x-k", text("1"))];
        assert!(matches(&any_x, &[("x-k", text("1"))]));
        let any = [("x-match", text("any")), ("x-k", text("1"))];
        assert!(!matches(&any, &[("x-k", text("1"))]), "nothing to compare");
    }

    #[test]
    fn void_means_present_and_values_compare_as_erlang_does() {
        assert!(matches(
            &[("a", FieldValue::Void)],
            &[("a", FieldValue::Bool(false))]
        ));
        assert!(!matches(
            &[("a", FieldValue::Void)],
            &[("b", FieldValue::Void)]
        ));
        let one = [
            FieldValue::I8(1),
            FieldValue::U8(1),
            FieldValue::I16(1),
            FieldValue::U16(1),
            FieldValue::I32(1),
            FieldValue::U32(1),
            FieldValue::I64(1),
            FieldValue::Timestamp(1),
            FieldValue::F32(1.0),
            FieldValue::F64(1.0),
        ];
        for a in &one {
            for b in &one {
                assert!(
                    matches(&[("n", a.clone())], &[("n", b.clone())]),
                    "{a:?} {b:?}"
                );
            }
        }
        assert!(!matches(
            &[("n", FieldValue::I32(1))],
            &[("n", FieldValue::F64(1.5))]
        ));
        assert!(!matches(&[("n", FieldValue::I32(1))], &[("n", text("1"))]));
        assert!(!matches(
            &[("n", FieldValue::Bool(true))],
            &[("n", FieldValue::I32(1))]
        ));
        let bytes = FieldValue::ByteArray(Bytes::from_static(b"pdf"));
        assert!(matches(&[("f", text("pdf"))], &[("f", bytes)]));
        let big = i64::MAX;
        assert!(!matches(
            &[("n", FieldValue::I64(big))],
            &[("n", FieldValue::F64(big as f64))]
        ));
        assert!(matches(
            &[("n", FieldValue::Timestamp(1 << 62))],
            &[("n", FieldValue::F64((1u64 << 62) as f64))]
        ));
        let d = FieldValue::Decimal(Decimal {
            scale: 1,
            value: 10,
        });
        let e = FieldValue::Decimal(Decimal { scale: 0, value: 1 });
        assert!(matches(&[("d", d.clone())], &[("d", d.clone())]));
        assert!(
            !matches(&[("d", d)], &[("d", e)]),
            "decimals compare exactly"
        );
        let ints = FieldValue::Array(vec![FieldValue::I32(1)]);
        let longs = FieldValue::Array(vec![FieldValue::I64(1)]);
        assert!(matches(&[("a", ints.clone())], &[("a", ints.clone())]));
        assert!(
            !matches(&[("a", ints)], &[("a", longs)]),
            "types count inside arrays"
        );
    }

    #[test]
    fn repeated_keys_pair_in_order() {
        let twice = [("k", text("1")), ("k", text("2"))];
        assert!(matches(&twice, &[("k", text("1")), ("k", text("2"))]));
        assert!(!matches(&twice, &[("k", text("2")), ("k", text("1"))]));
        assert!(!matches(&twice, &[("k", text("1"))]), "second k missing");
        assert!(matches(
            &[("k", text("1"))],
            &[("k", text("1")), ("k", text("9"))]
        ));
        assert!(!matches(
            &[("k", text("9"))],
            &[("k", text("1")), ("k", text("9"))]
        ));
    }

    #[test]
    fn x_match_must_be_a_known_long_string() {
        let valid = |v: FieldValue| valid_x_match(&table(&[("x-match", v)]));
        for mode in ["all", "any", "all-with-x", "any-with-x"] {
            assert!(valid(text(mode)));
        }
        assert!(!valid(text("some")));
        assert!(!valid(FieldValue::ByteArray(Bytes::from_static(b"all"))));
        assert!(!valid(FieldValue::I32(1)));
        assert!(valid_x_match(&FieldTable::new()));
    }

    #[test]
    fn thirty_thousand_arguments_against_thirty_thousand_headers() {
        let n = 30_000;
        let names: Vec<String> = (0..n).map(|i| format!("k{i}")).collect();
        let entries: Vec<(&str, FieldValue)> = names
            .iter()
            .zip(0..)
            .map(|(name, i)| (name.as_str(), FieldValue::I32(i)))
            .collect();
        let headers = table(&entries);
        let mut with_mode = vec![("x-match", text("all"))];
        with_mode.extend(entries.iter().cloned());
        let hasher = HeaderHasher::default();
        let pattern = HeadersPattern::new(&table(&with_mode), &hasher);
        assert!(pattern.matches(&MessageHeaders::new(Some(&headers), &hasher)));
        let last = entries.len() - 1;
        let mut one_off = entries.clone();
        one_off[last].1 = FieldValue::I32(0);
        let one_off = table(&one_off);
        assert!(!pattern.matches(&MessageHeaders::new(Some(&one_off), &hasher)));
    }

    /// RabbitMQ's algorithm as plainly as possible: sort both tables by
    /// key (stably), then walk them together.
    fn reference(arguments: &[(String, u8)], headers: &[(String, u8)], any: bool) -> bool {
        let mut p: Vec<&(String, u8)> = arguments.iter().collect();
        let mut d: Vec<&(String, u8)> = headers.iter().collect();
        p.sort_by(|a, b| a.0.cmp(&b.0));
        d.sort_by(|a, b| a.0.cmp(&b.0));
        let (mut all_match, mut any_match) = (true, false);
        let (mut i, mut j) = (0, 0);
        while i < p.len() {
            if j == d.len() {
                all_match = false;
                break;
            }
            match p[i].0.cmp(&d[j].0) {
                std::cmp::Ordering::Greater => j += 1,
                std::cmp::Ordering::Less => {
                    all_match = false;
                    i += 1;
                }
                std::cmp::Ordering::Equal => {
                    // Value 0 stands for void.
                    if p[i].1 == 0 || p[i].1 == d[j].1 {
                        any_match = true;
                    } else {
                        all_match = false;
                    }
                    i += 1;
                    j += 1;
                }
            }
        }
        if any {
            any_match
        } else {
            all_match
        }
    }

    fn entries() -> impl Strategy<Value = Vec<(String, u8)>> {
        prop::collection::vec((prop::sample::select(vec!["a", "b", "c"]), 0u8..3), 0..6)
            .prop_map(|v| v.into_iter().map(|(k, n)| (k.to_string(), n)).collect())
    }

    fn value(n: u8) -> FieldValue {
        if n == 0 {
            FieldValue::Void
        } else {
            FieldValue::I32(n.into())
        }
    }

    proptest! {
        #[test]
        fn matches_as_rabbitmqs_sorted_merge(
            arguments in entries(),
            headers in entries(),
            any in any::<bool>(),
        ) {
            let mode = if any { "any" } else { "all" };
            let mut args: Vec<(&str, FieldValue)> = vec![("x-match", text(mode))];
            args.extend(arguments.iter().map(|(k, n)| (k.as_str(), value(*n))));
            // A void header is a present header with a value no argument has.
            let data: Vec<(&str, FieldValue)> = headers
                .iter()
                .map(|(k, n)| (k.as_str(), value(*n)))
                .collect();
            let reference_data: Vec<(String, u8)> = headers
                .iter()
                .map(|(k, n)| (k.clone(), if *n == 0 { u8::MAX } else { *n }))
                .collect();
            prop_assert_eq!(
                matches(&args, &data),
                reference(&arguments, &reference_data, any)
            );
        }
    }
}
