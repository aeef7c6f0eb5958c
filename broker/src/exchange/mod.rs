//! Exchanges and their bindings: the four kinds (direct, fanout, topic,
//! headers), binding bookkeeping, and routing a message to destinations.
//! Bindings sit behind a `std::sync::RwLock`: routing takes the read lock
//! for the length of one lookup, binding changes take the write lock and
//! rebuild the kind's index (direct map, topic trie); neither awaits.

mod headers;
mod topic;

use crate::queue::Queue;
use leveret_protocol::{FieldTable, FieldValue, ShortStr};
use std::collections::HashMap;
use std::sync::{Arc, RwLock, RwLockReadGuard, RwLockWriteGuard};
use topic::TopicTrie;

pub use headers::valid_x_match;

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
        match (self, other) {
            (Destination::Queue(a), Destination::Queue(b)) => Arc::ptr_eq(a, b),
            (Destination::Exchange(a), Destination::Exchange(b)) => Arc::ptr_eq(a, b),
            _ => false,
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
}

impl ExchangeKind {
    /// The kind named in exchange.declare, if known.
    pub fn parse(name: &[u8]) -> Option<Self> {
        match name {
            b"direct" => Some(ExchangeKind::Direct),
            b"fanout" => Some(ExchangeKind::Fanout),
            b"topic" => Some(ExchangeKind::Topic),
            b"headers" => Some(ExchangeKind::Headers),
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

impl Binding {
    fn same_as(&self, other: &Binding) -> bool {
        self.destination == other.destination
            && self.routing_key == other.routing_key
            && self.arguments == other.arguments
    }
}

#[derive(Debug, Default)]
struct Routes {
    bindings: Vec<Binding>,
    direct: HashMap<ShortStr, Vec<Destination>>,
    topic: TopicTrie,
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
    routes: RwLock<Routes>,
}

impl Exchange {
    /// A new exchange with no bindings.
    pub fn new(name: ShortStr, kind: ExchangeKind, options: ExchangeOptions) -> Self {
        Exchange {
            name,
            kind,
            options,
            routes: RwLock::new(Routes::default()),
        }
    }

    fn read(&self) -> RwLockReadGuard<'_, Routes> {
        self.routes.read().unwrap_or_else(|e| e.into_inner())
    }

    fn write(&self) -> RwLockWriteGuard<'_, Routes> {
        self.routes.write().unwrap_or_else(|e| e.into_inner())
    }

    /// The `alternate-exchange` argument.
    pub fn alternate(&self) -> Option<ShortStr> {
        match self.options.arguments.get("alternate-exchange")? {
            FieldValue::LongStr(name) => ShortStr::try_from(name.clone()).ok(),
            _ => None,
        }
    }

    /// Adds a binding (an identical one is not added twice).
    pub fn bind(&self, binding: Binding) {
        let mut routes = self.write();
        if routes.bindings.iter().any(|b| b.same_as(&binding)) {
            return;
        }
        routes.bindings.push(binding);
        self.reindex(&mut routes);
    }

    /// Removes a binding; false if there was no such binding.
    pub fn unbind(&self, binding: &Binding) -> bool {
        let mut routes = self.write();
        let before = routes.bindings.len();
        routes.bindings.retain(|b| !b.same_as(binding));
        let removed = routes.bindings.len() != before;
        if removed {
            self.reindex(&mut routes);
        }
        removed
    }

    /// Removes every binding to `destination`; returns the removed ones.
    pub fn unbind_destination(&self, destination: &Destination) -> Vec<Binding> {
        let mut routes = self.write();
        let (removed, kept): (Vec<Binding>, Vec<Binding>) = std::mem::take(&mut routes.bindings)
            .into_iter()
            .partition(|b| b.destination == *destination);
        routes.bindings = kept;
        if !removed.is_empty() {
            self.reindex(&mut routes);
        }
        removed
    }

    /// A copy of every binding from this exchange.
    pub fn bindings(&self) -> Vec<Binding> {
        self.read().bindings.clone()
    }

    /// Calls `found` for every binding's destination.
    pub fn for_each_destination(&self, found: impl FnMut(&Destination)) {
        self.read()
            .bindings
            .iter()
            .map(|b| &b.destination)
            .for_each(found);
    }

    /// Whether any binding has this exchange as its source.
    pub fn has_bindings(&self) -> bool {
        !self.read().bindings.is_empty()
    }

    fn reindex(&self, routes: &mut Routes) {
        match self.kind {
            ExchangeKind::Direct => {
                let mut direct: HashMap<ShortStr, Vec<Destination>> = HashMap::new();
                for b in &routes.bindings {
                    let list = direct.entry(b.routing_key.clone()).or_default();
                    if !list.contains(&b.destination) {
                        list.push(b.destination.clone());
                    }
                }
                routes.direct = direct;
            }
            ExchangeKind::Topic => {
                routes.topic = TopicTrie::build(
                    routes
                        .bindings
                        .iter()
                        .map(|b| (&b.routing_key, &b.destination)),
                );
            }
            ExchangeKind::Fanout | ExchangeKind::Headers => {}
        }
    }

    /// Calls `found` for each destination a message with this routing key
    /// and headers goes to (possibly the same one more than once).
    pub fn route(
        &self,
        routing_key: &ShortStr,
        headers: Option<&FieldTable>,
        mut found: impl FnMut(&Destination),
    ) {
        let routes = self.read();
        match self.kind {
            ExchangeKind::Direct => {
                if let Some(list) = routes.direct.get(routing_key) {
                    list.iter().for_each(found);
                }
            }
            ExchangeKind::Fanout => routes.bindings.iter().for_each(|b| found(&b.destination)),
            ExchangeKind::Topic => routes.topic.route(routing_key).iter().for_each(found),
            ExchangeKind::Headers => routes
                .bindings
                .iter()
                .filter(|b| headers::matches(&b.arguments, headers))
                .for_each(|b| found(&b.destination)),
        }
    }
}
