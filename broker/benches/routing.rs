//! Routing and binding with adversarial inputs, through the same code the
//! broker runs (`Exchange::route`, the `BindingRegistry` that every bind,
//! unbind and deletion goes through):
//!
//! - one routing on a topic exchange bound with ten `#` (and with ten
//!   `#.*`, which no collapsing helps), for a 255-word routing key;
//! - one routing on a headers exchange with a 30,000-argument binding, for
//!   a message with the same 30,000 headers (the worst case: all compared);
//! - 100,000 bindings created, then deleted with their queue (the registry
//!   steps of a deletion) or one by one (unbind).
//!
//! Targets: each routing under 1 ms; 100,000 bindings created and deleted
//! under 1 s.
//!
//! Run: `cargo bench -p leveret-broker --features bench-internals --bench routing`

use criterion::{black_box, criterion_group, criterion_main, BatchSize, Criterion};
use leveret_broker::exchange::{
    Binding, BindingRegistry, Destination, Exchange, ExchangeKind, ExchangeOptions,
};
use leveret_protocol::{FieldTable, FieldValue, ShortStr};
use std::sync::Arc;
use std::time::Duration;

fn short(text: &str) -> ShortStr {
    ShortStr::try_from(text).expect("at most 255 bytes")
}

fn exchange(name: &str, kind: ExchangeKind) -> Arc<Exchange> {
    Arc::new(Exchange::new(short(name), kind, ExchangeOptions::default()))
}

/// A destination that needs no queue: a fanout exchange.
fn destination(name: &str) -> Destination {
    Destination::Exchange(exchange(name, ExchangeKind::Fanout))
}

fn binding(destination: &Destination, key: &str, arguments: FieldTable) -> Binding {
    Binding {
        destination: destination.clone(),
        routing_key: short(key),
        arguments,
    }
}

/// Counts the destinations `exchange` routes a message to.
fn route(exchange: &Exchange, key: &ShortStr, headers: Option<&FieldTable>) -> usize {
    let mut found = 0;
    exchange.route(key, headers, |_| found += 1);
    found
}

fn topic(c: &mut Criterion) {
    let mut group = c.benchmark_group("topic");
    // 255 words fit a short string only as empty words (254 dots); 128
    // one-letter words are the longest key with non-empty words.
    let empty_words = short(&".".repeat(254));
    let letters = short(&["a"; 128].join("."));
    for pattern in [["#"; 10].join("."), ["#.*"; 10].join(".")] {
        let x = exchange("topic", ExchangeKind::Topic);
        let mut registry = BindingRegistry::default();
        registry.bind(&x, binding(&destination("q"), &pattern, FieldTable::new()));
        // A near miss beside it, so the walk keeps several states alive.
        let near = format!("{pattern}.b");
        registry.bind(&x, binding(&destination("near"), &near, FieldTable::new()));
        for (what, key) in [("255 empty words", &empty_words), ("128 words", &letters)] {
            assert_eq!(route(&x, key, None), 1, "{pattern} matches {what}");
            group.bench_function(format!("{pattern} / {what}"), |b| {
                b.iter(|| route(&x, black_box(key), None))
            });
        }
    }
    group.finish();
}

fn headers(c: &mut Criterion) {
    let n = 30_000;
    let headers = wire_table(n, None);
    let arguments = wire_table(n, Some(("x-match", FieldValue::string("all"))));
    let x = exchange("headers", ExchangeKind::Headers);
    let mut registry = BindingRegistry::default();
    registry.bind(&x, binding(&destination("q"), "", arguments));
    let key = short("");
    assert_eq!(route(&x, &key, Some(&headers)), 1);
    let mut group = c.benchmark_group("headers");
    group.bench_function("30k-argument binding / 30k headers", |b| {
        b.iter(|| route(&x, &key, Some(black_box(&headers))))
    });
    let few = wire_table(3, None);
    group.bench_function("30k-argument binding / 3 headers", |b| {
        b.iter(|| route(&x, &key, Some(black_box(&few))))
    });
    group.finish();
}

/// A field table of `n` distinct entries `k0` … with integer values (after
/// `first`), encoded once and decoded, which is linear in its size.
fn wire_table(n: usize, first: Option<(&str, FieldValue)>) -> FieldTable {
    let mut body = bytes::BytesMut::new();
    let entries = first
        .map(|(k, v)| (k.to_owned(), v))
        .into_iter()
        .chain((0..n).map(|i| (format!("k{i}"), FieldValue::I64(i as i64))));
    for (key, value) in entries {
        let mut one = FieldTable::new();
        one.insert(short(&key), value);
        let mut wire = bytes::BytesMut::new();
        one.encode(&mut wire);
        body.extend_from_slice(&wire[4..]);
    }
    let mut whole = bytes::BytesMut::with_capacity(body.len() + 4);
    whole.extend_from_slice(&(body.len() as u32).to_be_bytes());
    whole.extend_from_slice(&body);
    FieldTable::decode(&whole.freeze()).expect("decodes")
}

const BINDINGS: usize = 100_000;

/// An exchange, a destination and `BINDINGS` binding keys, not yet bound.
fn unbound() -> (Arc<Exchange>, Destination, Vec<ShortStr>) {
    let keys = (0..BINDINGS).map(|i| short(&format!("key.{i}"))).collect();
    (
        exchange("direct", ExchangeKind::Direct),
        destination("q"),
        keys,
    )
}

fn bind_all(registry: &mut BindingRegistry, x: &Arc<Exchange>, d: &Destination, keys: &[ShortStr]) {
    for key in keys {
        registry.bind(
            x,
            Binding {
                destination: d.clone(),
                routing_key: key.clone(),
                arguments: FieldTable::new(),
            },
        );
    }
}

fn bindings(c: &mut Criterion) {
    let mut group = c.benchmark_group("bindings");
    group.sample_size(10);
    group.measurement_time(Duration::from_secs(10));
    group.bench_function("100k created, deleted with their queue", |b| {
        b.iter_batched(
            unbound,
            |(x, d, keys)| {
                let mut registry = BindingRegistry::default();
                bind_all(&mut registry, &x, &d, &keys);
                // The steps of a queue deletion (1024 bindings each).
                loop {
                    let mut budget = 1024;
                    let mut touched = Vec::new();
                    if registry.unbind_destination(&d, &mut budget, &mut touched) {
                        break;
                    }
                }
                assert!(!x.has_bindings());
            },
            BatchSize::PerIteration,
        )
    });
    group.bench_function("100k created, unbound one by one", |b| {
        b.iter_batched(
            unbound,
            |(x, d, keys)| {
                let mut registry = BindingRegistry::default();
                bind_all(&mut registry, &x, &d, &keys);
                for key in &keys {
                    let unbound = registry.unbind(
                        &x,
                        &Binding {
                            destination: d.clone(),
                            routing_key: key.clone(),
                            arguments: FieldTable::new(),
                        },
                    );
                    assert!(unbound);
                }
                assert!(!x.has_bindings());
            },
            BatchSize::PerIteration,
        )
    });
    group.finish();
}

criterion_group!(benches, topic, headers, bindings);
criterion_main!(benches);
