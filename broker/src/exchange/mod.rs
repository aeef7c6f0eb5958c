//! Exchanges and their bindings: the five kinds (direct, fanout, topic,
//! headers, and RabbitMQ's plugin type x-consistent-hash), each exchange's bindings and routing index, and the
//! [`BindingRegistry`] through which every binding is added or removed.
//!
//! Every operation costs what its inputs' sizes say: adding or removing a
//! binding updates the kind's index in place (a direct key's destinations,
//! a topic trie path, the fanout's destination set) in O(log n) at worst;
//! routing is one lookup (direct), one pass over the destinations
//! (fanout), an automaton walk linear in words × pattern segments
//! (`topic`), or one lookup per binding argument against headers indexed
//! once (`headers`).
//!
//! Bindings sit behind a `std::sync::RwLock` per exchange: routing takes
//! the read lock for one lookup, binding changes the write lock for one
//! update; neither awaits. This module uses the queue type only as a
//! destination handle.

pub mod consistent_hash;
mod destination_set;
mod headers;
mod registry;
mod topic;

use crate::policy::Applied;
use crate::queue::Queue;
use bytes::{Bytes, BytesMut};
use consistent_hash::HashRing;
use destination_set::DestinationSet;
use headers::{HeaderHasher, HeadersPattern, MessageHeaders};
use leveret_protocol::{FieldTable, FieldValue, ShortStr};
use std::collections::{btree_map, BTreeMap};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, RwLock, RwLockReadGuard, RwLockWriteGuard};
use topic::TopicTrie;

pub use headers::valid_x_match;
pub use registry::BindingRegistry;

/// Where a binding sends messages.
#[derive(Debug, Clone)]
pub enum Destination {
    /// A queue.
    Queue(Arc<Queue>),
    /// Another exchange (RabbitMQ's exchange-to-exchange bindings).
    Exchange(Arc<Exchange>),
}

impl PartialEq for Destination {
    fn eq(&self, other: &Self) -> bool {
        self.id() == other.id()
    }
}

/// The identity of a queue or exchange object (not of its name: a queue
/// deleted and declared again is another destination): the address of its
/// shared allocation, stable while a [`Destination`] holds it.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct DestinationId(usize);

impl DestinationId {
    /// The identity of a shared queue or exchange.
    pub fn of<T>(object: &Arc<T>) -> Self {
        DestinationId(Arc::as_ptr(object).cast::<()>() as usize)
    }
}

impl Destination {
    /// Its identity, for hashing.
    pub fn id(&self) -> DestinationId {
        match self {
            Destination::Queue(queue) => DestinationId::of(queue),
            Destination::Exchange(exchange) => DestinationId::of(exchange),
        }
    }
}

/// The kinds of exchange.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ExchangeKind {
    /// Routing key equals binding key.
    Direct,
    /// Every binding.
    Fanout,
    /// Dotted patterns with `*` and `#`.
    Topic,
    /// Header values, x-match all or any.
    Headers,
    /// One destination per message by a hash of its routing key, binding
    /// keys being weights (RabbitMQ's `x-consistent-hash` plugin).
    ConsistentHash,
}

impl ExchangeKind {
    /// The kind named in exchange.declare, if known.
    pub fn parse(name: &[u8]) -> Option<Self> {
        match name {
            b"direct" => Some(ExchangeKind::Direct),
            b"fanout" => Some(ExchangeKind::Fanout),
            b"topic" => Some(ExchangeKind::Topic),
            b"headers" => Some(ExchangeKind::Headers),
            b"x-consistent-hash" => Some(ExchangeKind::ConsistentHash),
            _ => None,
        }
    }

    /// The name used in exchange.declare.
    pub fn name(self) -> &'static str {
        match self {
            ExchangeKind::Direct => "direct",
            ExchangeKind::Fanout => "fanout",
            ExchangeKind::Topic => "topic",
            ExchangeKind::Headers => "headers",
            ExchangeKind::ConsistentHash => consistent_hash::TYPE_NAME,
        }
    }
}

/// One binding from an exchange.
#[derive(Debug, Clone)]
pub struct Binding {
    /// Where it routes to.
    pub destination: Destination,
    /// Binding key.
    pub routing_key: ShortStr,
    /// Binding arguments (headers exchange match, or ignored).
    pub arguments: FieldTable,
}

/// What tells apart two bindings between the same two ends: the binding
/// key and the arguments (compared in their wire form, so that comparing
/// them costs their size once).
#[derive(Debug, Clone, PartialEq, Eq, PartialOrd, Ord)]
struct BindingKey {
    routing_key: ShortStr,
    arguments: Bytes,
}

impl BindingKey {
    fn of(binding: &Binding) -> Self {
        let arguments = if binding.arguments.is_empty() {
            Bytes::new()
        } else {
            let mut wire = BytesMut::new();
            binding.arguments.encode(&mut wire);
            wire.freeze()
        };
        BindingKey {
            routing_key: binding.routing_key.clone(),
            arguments,
        }
    }

    /// The key that sorts before every other.
    fn lowest() -> Self {
        BindingKey {
            routing_key: ShortStr::default(),
            arguments: Bytes::new(),
        }
    }
}

/// Where a chunked listing of an exchange's bindings goes on from
/// ([`Exchange::bindings_chunk`]).
#[derive(Debug, Clone)]
pub struct BindingCursor(BindingId);

/// A binding's place among its exchange's bindings: by destination first,
/// so that the bindings to one destination are one range.
#[derive(Debug, Clone, PartialEq, Eq, PartialOrd, Ord)]
struct BindingId {
    destination: DestinationId,
    key: BindingKey,
}

impl BindingId {
    fn of(binding: &Binding) -> Self {
        BindingId {
            destination: binding.destination.id(),
            key: BindingKey::of(binding),
        }
    }

    /// Where the bindings to `destination` start.
    fn first_to(destination: DestinationId) -> Self {
        BindingId {
            destination,
            key: BindingKey::lowest(),
        }
    }
}

/// A binding and, on a headers exchange, its compiled arguments.
#[derive(Debug)]
struct Bound {
    binding: Binding,
    pattern: Option<HeadersPattern>,
}

/// The index a kind routes with.
#[derive(Debug)]
enum RouteIndex {
    /// Destinations by binding key.
    Direct(BTreeMap<ShortStr, DestinationSet>),
    /// Every destination.
    Fanout(DestinationSet),
    /// Binding keys as a trie.
    Topic(TopicTrie),
    /// Headers bindings are matched one by one with their compiled
    /// patterns, keys hashed with the exchange's hasher.
    Headers(HeaderHasher),
    /// Weighted points on a hash ring.
    ConsistentHash(HashRing),
}

impl RouteIndex {
    fn add(&mut self, binding: &Binding) {
        match self {
            RouteIndex::Direct(keys) => keys
                .entry(binding.routing_key.clone())
                .or_default()
                .add(&binding.destination),
            RouteIndex::Fanout(all) => all.add(&binding.destination),
            RouteIndex::Topic(trie) => {
                trie.add(binding.routing_key.as_bytes(), &binding.destination)
            }
            RouteIndex::Headers(_) => {}
            RouteIndex::ConsistentHash(ring) => {
                ring.add(&binding.destination, &binding.routing_key)
            }
        }
    }

    fn remove(&mut self, binding: &Binding) {
        match self {
            RouteIndex::Direct(keys) => {
                if let Some(set) = keys.get_mut(&binding.routing_key) {
                    set.remove(&binding.destination);
                    if set.is_empty() {
                        keys.remove(&binding.routing_key);
                    }
                }
            }
            RouteIndex::Fanout(all) => {
                all.remove(&binding.destination);
            }
            RouteIndex::Topic(trie) => {
                trie.remove(binding.routing_key.as_bytes(), &binding.destination);
            }
            RouteIndex::Headers(_) => {}
            RouteIndex::ConsistentHash(ring) => {
                ring.remove(&binding.destination, &binding.routing_key)
            }
        }
    }
}

/// An exchange's bindings and its routing index, kept in step. Both are
/// B-trees (or a trie of them): every change costs O(log n) at worst, as
/// no change ever rebuilds a whole table the way a growing hash map does.
#[derive(Debug)]
struct Routes {
    bindings: BTreeMap<BindingId, Bound>,
    index: RouteIndex,
}

impl Routes {
    fn new(kind: ExchangeKind, arguments: &FieldTable) -> Self {
        let index = match kind {
            ExchangeKind::Direct => RouteIndex::Direct(BTreeMap::new()),
            ExchangeKind::Fanout => RouteIndex::Fanout(DestinationSet::default()),
            ExchangeKind::Topic => RouteIndex::Topic(TopicTrie::default()),
            ExchangeKind::Headers => RouteIndex::Headers(HeaderHasher::default()),
            ExchangeKind::ConsistentHash => RouteIndex::ConsistentHash(HashRing::new(arguments)),
        };
        Routes {
            bindings: BTreeMap::new(),
            index,
        }
    }

    fn insert(&mut self, binding: Binding) -> bool {
        let btree_map::Entry::Vacant(slot) = self.bindings.entry(BindingId::of(&binding)) else {
            return false;
        };
        self.index.add(&binding);
        let pattern = match &self.index {
            RouteIndex::Headers(hasher) => Some(HeadersPattern::new(&binding.arguments, hasher)),
            _ => None,
        };
        slot.insert(Bound { binding, pattern });
        true
    }

    fn remove(&mut self, binding: &Binding) -> bool {
        match self.bindings.remove(&BindingId::of(binding)) {
            Some(removed) => {
                self.index.remove(&removed.binding);
                true
            }
            None => false,
        }
    }

    /// The bindings to `destination`, in order.
    fn to(&self, destination: DestinationId) -> impl Iterator<Item = (&BindingId, &Bound)> {
        self.bindings
            .range(BindingId::first_to(destination)..)
            .take_while(move |(id, _)| id.destination == destination)
    }

    /// Removes up to `limit` bindings to `destination`; returns how many.
    fn remove_to(&mut self, destination: &Destination, limit: usize) -> usize {
        let ids: Vec<BindingId> = self
            .to(destination.id())
            .take(limit)
            .map(|(id, _)| id.clone())
            .collect();
        self.remove_ids(&ids).len()
    }

    /// Removes up to `limit` bindings, whatever their destination.
    fn remove_some(&mut self, limit: usize) -> Vec<Binding> {
        let ids: Vec<BindingId> = self.bindings.keys().take(limit).cloned().collect();
        self.remove_ids(&ids)
    }

    fn remove_ids(&mut self, ids: &[BindingId]) -> Vec<Binding> {
        let mut removed = Vec::with_capacity(ids.len());
        for id in ids {
            if let Some(bound) = self.bindings.remove(id) {
                self.index.remove(&bound.binding);
                removed.push(bound.binding);
            }
        }
        removed
    }
}

/// Declared properties of an exchange.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct ExchangeOptions {
    /// Survives a restart.
    pub durable: bool,
    /// Deleted when its last binding goes.
    pub auto_delete: bool,
    /// Not published to directly, only through bindings.
    pub internal: bool,
    /// Arguments as declared.
    pub arguments: FieldTable,
}

/// One exchange.
#[derive(Debug)]
pub struct Exchange {
    /// Its name.
    pub name: ShortStr,
    /// Its kind.
    pub kind: ExchangeKind,
    /// Declared properties.
    pub options: ExchangeOptions,
    /// Set when the exchange is deleted: it routes nothing from then on,
    /// while its bindings are removed.
    deleted: AtomicBool,
    routes: RwLock<Routes>,
    /// The policies that apply (the vhost sets them).
    policies: RwLock<Applied>,
}

impl Exchange {
    /// A new exchange with no bindings.
    pub fn new(name: ShortStr, kind: ExchangeKind, options: ExchangeOptions) -> Self {
        let routes = RwLock::new(Routes::new(kind, &options.arguments));
        Exchange {
            name,
            kind,
            options,
            deleted: AtomicBool::new(false),
            routes,
            policies: RwLock::default(),
        }
    }

    fn read(&self) -> RwLockReadGuard<'_, Routes> {
        self.routes.read().unwrap_or_else(|e| e.into_inner())
    }

    fn write(&self) -> RwLockWriteGuard<'_, Routes> {
        self.routes.write().unwrap_or_else(|e| e.into_inner())
    }

    /// The `alternate-exchange` argument, or else the policy's (the
    /// argument wins, as in RabbitMQ).
    pub fn alternate(&self) -> Option<ShortStr> {
        match self.options.arguments.get("alternate-exchange") {
            Some(FieldValue::LongStr(name)) => ShortStr::try_from(name.clone()).ok(),
            Some(_) => None,
            None => self
                .policies
                .read()
                .unwrap_or_else(|e| e.into_inner())
                .alternate_exchange(),
        }
    }

    /// Makes `applied` the exchange's policies.
    pub fn apply_policies(&self, applied: Applied) {
        *self.policies.write().unwrap_or_else(|e| e.into_inner()) = applied;
    }

    /// The policies that apply to the exchange.
    pub fn policies(&self) -> Applied {
        self.policies
            .read()
            .unwrap_or_else(|e| e.into_inner())
            .clone()
    }

    /// Whether any binding has this exchange as its source.
    pub fn has_bindings(&self) -> bool {
        !self.read().bindings.is_empty()
    }

    /// Whether the exchange was deleted.
    pub fn is_deleted(&self) -> bool {
        self.deleted.load(Ordering::Acquire)
    }

    /// Marks the exchange deleted: from now on it routes nothing.
    pub fn mark_deleted(&self) {
        self.deleted.store(true, Ordering::Release);
    }

    /// Drops every binding at once (the vhost is going away: bindings
    /// between exchanges may form cycles of `Arc`s that nothing else
    /// would break).
    pub(crate) fn forget_routes(&self) {
        *self.write() = Routes::new(self.kind, &self.options.arguments);
    }

    /// Adds a binding; false if an identical one is there.
    fn insert(&self, binding: Binding) -> bool {
        self.write().insert(binding)
    }

    /// Removes a binding; false if there was no such binding.
    fn remove(&self, binding: &Binding) -> bool {
        self.write().remove(binding)
    }

    /// Removes up to `limit` bindings to `destination`; returns how many.
    fn remove_bindings_to(&self, destination: &Destination, limit: usize) -> usize {
        self.write().remove_to(destination, limit)
    }

    /// Removes up to `limit` of its bindings, whatever their destination.
    fn remove_some_bindings(&self, limit: usize) -> Vec<Binding> {
        self.write().remove_some(limit)
    }

    /// Calls `found` for each of its bindings to `destination`.
    fn for_each_binding_to(&self, destination: &Destination, mut found: impl FnMut(&Binding)) {
        self.read()
            .to(destination.id())
            .for_each(|(_, bound)| found(&bound.binding));
    }

    /// Up to `limit` of its bindings after `after` (from the first when
    /// `None`), in its order, and where the next chunk starts (`None` once
    /// there are no more): a listing copies the bindings out a chunk at a
    /// time, so it never holds the exchange for long. Bindings added or
    /// removed between chunks may be missed; none is listed twice.
    pub fn bindings_chunk(
        &self,
        after: Option<&BindingCursor>,
        limit: usize,
    ) -> (Vec<Binding>, Option<BindingCursor>) {
        use std::ops::Bound;
        let routes = self.read();
        let start = match after {
            Some(cursor) => Bound::Excluded(&cursor.0),
            None => Bound::Unbounded,
        };
        let mut chunk = Vec::with_capacity(limit.min(routes.bindings.len()));
        let mut last = None;
        for (id, bound) in routes.bindings.range((start, Bound::Unbounded)).take(limit) {
            chunk.push(bound.binding.clone());
            last = Some(id);
        }
        let next = (chunk.len() == limit)
            .then(|| last.cloned().map(BindingCursor))
            .flatten();
        (chunk, next)
    }

    /// Calls `found` for each of its bindings.
    pub fn for_each_binding(&self, mut found: impl FnMut(&Binding)) {
        self.read()
            .bindings
            .values()
            .for_each(|bound| found(&bound.binding));
    }

    /// Calls `found` for each destination a message with this routing key
    /// and headers goes to (possibly the same one more than once).
    pub fn route(
        &self,
        routing_key: &ShortStr,
        headers: Option<&FieldTable>,
        mut found: impl FnMut(&Destination),
    ) {
        if self.deleted.load(Ordering::Acquire) {
            return;
        }
        let routes = self.read();
        match &routes.index {
            RouteIndex::Direct(keys) => {
                if let Some(set) = keys.get(routing_key) {
                    set.iter().for_each(found);
                }
            }
            RouteIndex::Fanout(all) => all.iter().for_each(found),
            RouteIndex::Topic(trie) => trie.route(routing_key.as_bytes(), found),
            RouteIndex::ConsistentHash(ring) => {
                if let Some(destination) = ring.route(routing_key, headers) {
                    found(destination);
                }
            }
            RouteIndex::Headers(hasher) => {
                if routes.bindings.is_empty() {
                    return;
                }
                let headers = MessageHeaders::new(headers, hasher);
                // Bindings come grouped by destination: once one of a
                // destination's matches, the rest of its group is skipped.
                let mut matched: Option<DestinationId> = None;
                for (id, bound) in &routes.bindings {
                    if matched == Some(id.destination) {
                        continue;
                    }
                    let pattern = bound.pattern.as_ref();
                    if pattern.is_some_and(|pattern| pattern.matches(&headers)) {
                        matched = Some(id.destination);
                        found(&bound.binding.destination);
                    }
                }
            }
        }
    }
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;

    fn s(text: &str) -> ShortStr {
        ShortStr::try_from(text).expect("short")
    }

    /// `n` distinct destinations (fanout exchanges, which need no queue).
    pub(crate) fn destinations(n: usize) -> Vec<Destination> {
        (0..n)
            .map(|i| {
                let name = s(&format!("d{i}"));
                let x = Exchange::new(name, ExchangeKind::Fanout, ExchangeOptions::default());
                Destination::Exchange(Arc::new(x))
            })
            .collect()
    }

    pub(crate) fn exchange(kind: ExchangeKind) -> Arc<Exchange> {
        Arc::new(Exchange::new(s("x"), kind, ExchangeOptions::default()))
    }

    pub(crate) fn binding(destination: &Destination, key: &str, arguments: FieldTable) -> Binding {
        Binding {
            destination: destination.clone(),
            routing_key: s(key),
            arguments,
        }
    }

    fn sorted(mut ids: Vec<DestinationId>) -> Vec<DestinationId> {
        ids.sort_unstable();
        ids
    }

    fn routed(x: &Exchange, key: &str, headers: Option<&FieldTable>) -> Vec<DestinationId> {
        let mut found = Vec::new();
        x.route(&s(key), headers, |d| found.push(d.id()));
        sorted(found)
    }

    #[test]
    fn direct_routes_each_destination_once_per_key_and_forgets_removed_keys() {
        let d = destinations(2);
        let x = exchange(ExchangeKind::Direct);
        let mut args = FieldTable::new();
        args.insert(s("k"), FieldValue::I32(1));
        assert!(x.insert(binding(&d[0], "a", FieldTable::new())));
        assert!(
            !x.insert(binding(&d[0], "a", FieldTable::new())),
            "identical"
        );
        assert!(
            x.insert(binding(&d[0], "a", args.clone())),
            "other arguments"
        );
        assert!(x.insert(binding(&d[1], "a", FieldTable::new())));
        assert_eq!(routed(&x, "a", None), sorted(vec![d[0].id(), d[1].id()]));
        assert!(x.remove(&binding(&d[0], "a", FieldTable::new())));
        assert_eq!(routed(&x, "a", None).len(), 2, "d0 still bound with args");
        assert!(x.remove(&binding(&d[0], "a", args)));
        assert_eq!(routed(&x, "a", None), vec![d[1].id()]);
        assert_eq!(x.remove_bindings_to(&d[1], 10), 1);
        assert!(!x.has_bindings());
        let RouteIndex::Direct(keys) = &x.read().index else {
            panic!("direct index");
        };
        assert!(keys.is_empty(), "no key left behind");
    }

    #[test]
    fn fanout_topic_and_headers_route_through_their_indexes() {
        let d = destinations(3);
        let fanout = exchange(ExchangeKind::Fanout);
        for (i, dest) in d.iter().enumerate() {
            fanout.insert(binding(dest, &i.to_string(), FieldTable::new()));
        }
        assert_eq!(routed(&fanout, "any", None).len(), 3);

        let topic = exchange(ExchangeKind::Topic);
        topic.insert(binding(&d[0], "a.#.#", FieldTable::new()));
        topic.insert(binding(&d[1], "a.*", FieldTable::new()));
        assert_eq!(
            routed(&topic, "a.b", None),
            sorted(vec![d[0].id(), d[1].id()])
        );
        assert!(topic.remove(&binding(&d[0], "a.#.#", FieldTable::new())));
        assert_eq!(routed(&topic, "a.b", None), vec![d[1].id()]);

        let headers = exchange(ExchangeKind::Headers);
        let mut args = FieldTable::new();
        args.insert(s("x-match"), FieldValue::string("any"));
        args.insert(s("f"), FieldValue::string("pdf"));
        args.insert(s("t"), FieldValue::string("log"));
        headers.insert(binding(&d[2], "", args));
        let mut message = FieldTable::new();
        message.insert(s("t"), FieldValue::string("log"));
        assert_eq!(routed(&headers, "", Some(&message)), vec![d[2].id()]);
        assert!(routed(&headers, "", None).is_empty());
    }

    #[test]
    fn a_deleted_exchange_routes_nothing() {
        let d = destinations(1);
        let x = exchange(ExchangeKind::Fanout);
        x.insert(binding(&d[0], "", FieldTable::new()));
        x.mark_deleted();
        assert!(routed(&x, "", None).is_empty());
    }

    #[test]
    fn removing_in_chunks_empties_the_index() {
        let d = destinations(2);
        let x = exchange(ExchangeKind::Topic);
        for i in 0..100 {
            x.insert(binding(&d[i % 2], &format!("k.{i}.#"), FieldTable::new()));
        }
        assert_eq!(x.remove_bindings_to(&d[0], 30), 30);
        assert_eq!(x.remove_bindings_to(&d[0], 30), 20);
        assert_eq!(x.remove_bindings_to(&d[0], 30), 0);
        assert_eq!(x.remove_some_bindings(40).len(), 40);
        assert_eq!(x.remove_some_bindings(40).len(), 10);
        assert!(!x.has_bindings());
        let RouteIndex::Topic(trie) = &x.read().index else {
            panic!("topic index");
        };
        let mut any = false;
        trie.route(b"k.1.z", |_| any = true);
        assert!(!any);
    }
}
