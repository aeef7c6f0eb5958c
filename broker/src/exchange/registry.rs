//! The bindings of a vhost seen from both ends. Each exchange holds its
//! own bindings (source side, with its routing index); the registry adds
//! the reverse index, for each destination the exchanges bound to it and
//! how many bindings each has, so that deleting a queue or an exchange
//! visits only its own bindings, never every exchange of the vhost.
//!
//! Every binding is added and removed through the registry, which keeps
//! both sides in step; each change costs O(log n) at worst (plus the
//! binding's own size, to compare its arguments and index its key): the
//! reverse index is a B-tree, which never rebuilds itself whole as a
//! growing hash map does. Removing all the bindings of a deleted queue or
//! exchange goes in steps of a bounded number of bindings, so that the
//! caller can yield between steps.
//!
//! The vhost holds the registry behind a mutex, taken before any
//! exchange's routing lock; it uses exchanges and destinations only.

use super::{Binding, Destination, DestinationId, Exchange};
use std::collections::BTreeMap;
use std::sync::Arc;

/// An exchange with bindings to a destination, and how many.
#[derive(Debug)]
struct Source {
    exchange: Arc<Exchange>,
    bindings: usize,
}

/// Every binding of a vhost, indexed from both ends.
///
/// A (destination, source) pair has an entry only while the source holds
/// a binding to the destination, and so holds the destination itself: its
/// id cannot be reused by another object while indexed.
#[derive(Debug, Default)]
pub struct BindingRegistry {
    /// By (destination, source exchange).
    sources: BTreeMap<(DestinationId, DestinationId), Source>,
}

impl BindingRegistry {
    /// Adds a binding from `source`; false if an identical one is there.
    pub fn bind(&mut self, source: &Arc<Exchange>, binding: Binding) -> bool {
        let destination = binding.destination.id();
        if !source.insert(binding) {
            return false;
        }
        self.sources
            .entry((destination, DestinationId::of(source)))
            .or_insert_with(|| Source {
                exchange: Arc::clone(source),
                bindings: 0,
            })
            .bindings += 1;
        true
    }

    /// Removes a binding from `source`; false if there was none.
    pub fn unbind(&mut self, source: &Arc<Exchange>, binding: &Binding) -> bool {
        if !source.remove(binding) {
            return false;
        }
        self.forget(binding.destination.id(), source, 1);
        true
    }

    /// Takes `removed` bindings from `source` off `destination`'s count.
    fn forget(&mut self, destination: DestinationId, source: &Arc<Exchange>, removed: usize) {
        let key = (destination, DestinationId::of(source));
        if let Some(entry) = self.sources.get_mut(&key) {
            entry.bindings = entry.bindings.saturating_sub(removed);
            if entry.bindings == 0 {
                self.sources.remove(&key);
            }
        }
    }

    /// The sources of bindings to `destination`.
    fn sources_of(
        &self,
        destination: DestinationId,
    ) -> impl Iterator<Item = (&(DestinationId, DestinationId), &Source)> {
        self.sources
            .range((destination, DestinationId(0))..)
            .take_while(move |((to, _), _)| *to == destination)
    }

    /// Whether any binding leads to `destination`.
    pub fn is_destination(&self, destination: &Destination) -> bool {
        self.sources_of(destination.id()).next().is_some()
    }

    /// Calls `found` with each binding to `destination` and its source.
    pub fn for_each_binding_to(
        &self,
        destination: &Destination,
        mut found: impl FnMut(&Exchange, &Binding),
    ) {
        for (_, source) in self.sources_of(destination.id()) {
            let exchange = &source.exchange;
            exchange.for_each_binding_to(destination, |binding| found(exchange, binding));
        }
    }

    /// Removes bindings to `destination`, at most `budget` of them (the
    /// budget is spent by as many), and pushes the exchanges that lost one
    /// onto `touched`; true once none is left.
    pub fn unbind_destination(
        &mut self,
        destination: &Destination,
        budget: &mut usize,
        touched: &mut Vec<Arc<Exchange>>,
    ) -> bool {
        while *budget > 0 {
            let Some((&key, source)) = self.sources_of(destination.id()).next() else {
                return true;
            };
            let exchange = Arc::clone(&source.exchange);
            let removed = exchange.remove_bindings_to(destination, *budget);
            *budget -= removed;
            let entry = self.sources.get_mut(&key).expect("found above");
            entry.bindings = entry.bindings.saturating_sub(removed);
            // A count ahead of the exchange (nothing removed) is dropped too.
            if entry.bindings == 0 || removed == 0 {
                self.sources.remove(&key);
            }
            touched.push(exchange);
        }
        !self.is_destination(destination)
    }

    /// Removes bindings from `source`, at most `budget` of them (the
    /// budget is spent by as many); true once none is left.
    pub fn unbind_source(&mut self, source: &Arc<Exchange>, budget: &mut usize) -> bool {
        if *budget > 0 {
            let removed = source.remove_some_bindings(*budget);
            *budget -= removed.len();
            for binding in &removed {
                self.forget(binding.destination.id(), source, 1);
            }
        }
        !source.has_bindings()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::exchange::tests::{binding, destinations, exchange};
    use crate::exchange::ExchangeKind;
    use leveret_protocol::FieldTable;

    fn count_to(registry: &BindingRegistry, destination: &Destination) -> usize {
        let mut n = 0;
        registry.for_each_binding_to(destination, |_, _| n += 1);
        n
    }

    #[test]
    fn bind_and_unbind_keep_both_ends_in_step() {
        let d = destinations(2);
        let x = exchange(ExchangeKind::Direct);
        let y = exchange(ExchangeKind::Topic);
        let mut registry = BindingRegistry::default();
        assert!(registry.bind(&x, binding(&d[0], "a", FieldTable::new())));
        assert!(!registry.bind(&x, binding(&d[0], "a", FieldTable::new())));
        assert!(registry.bind(&x, binding(&d[0], "b", FieldTable::new())));
        assert!(registry.bind(&y, binding(&d[0], "a.#", FieldTable::new())));
        assert_eq!(count_to(&registry, &d[0]), 3);
        assert!(!registry.is_destination(&d[1]));
        assert!(registry.unbind(&x, &binding(&d[0], "a", FieldTable::new())));
        assert!(!registry.unbind(&x, &binding(&d[0], "a", FieldTable::new())));
        assert!(registry.unbind(&x, &binding(&d[0], "b", FieldTable::new())));
        assert!(!x.has_bindings());
        assert!(registry.is_destination(&d[0]), "still bound from y");
        assert!(registry.unbind(&y, &binding(&d[0], "a.#", FieldTable::new())));
        assert!(!registry.is_destination(&d[0]));
        assert!(registry.sources.is_empty());
    }

    #[test]
    fn a_destination_is_unbound_in_steps_from_every_source() {
        let d = destinations(2);
        let sources: Vec<Arc<Exchange>> = (0..3).map(|_| exchange(ExchangeKind::Direct)).collect();
        let mut registry = BindingRegistry::default();
        for (n, x) in sources.iter().enumerate() {
            for i in 0..100 {
                registry.bind(x, binding(&d[0], &format!("{n}.{i}"), FieldTable::new()));
            }
            registry.bind(x, binding(&d[1], "other", FieldTable::new()));
        }
        let mut steps = 0;
        let mut touched = Vec::new();
        loop {
            steps += 1;
            let mut budget = 64;
            let done = registry.unbind_destination(&d[0], &mut budget, &mut touched);
            if done {
                break;
            }
            assert_eq!(budget, 0, "an unfinished step spends its budget");
        }
        assert_eq!(steps, 5, "300 bindings in steps of 64");
        assert!(!registry.is_destination(&d[0]));
        assert_eq!(count_to(&registry, &d[1]), 3, "other destination untouched");
        for x in &sources {
            assert!(touched.iter().any(|t| Arc::ptr_eq(t, x)));
            assert!(x.has_bindings());
        }
    }

    #[test]
    fn a_source_is_unbound_in_steps() {
        let d = destinations(3);
        let x = exchange(ExchangeKind::Fanout);
        let y = exchange(ExchangeKind::Fanout);
        let mut registry = BindingRegistry::default();
        for i in 0..50 {
            for dest in &d {
                registry.bind(&x, binding(dest, &i.to_string(), FieldTable::new()));
            }
        }
        registry.bind(&y, binding(&d[0], "", FieldTable::new()));
        let mut steps = 0;
        loop {
            steps += 1;
            let mut budget = 40;
            if registry.unbind_source(&x, &mut budget) {
                break;
            }
        }
        assert_eq!(steps, 4, "150 bindings in steps of 40");
        assert!(!registry.is_destination(&d[1]));
        assert!(!registry.is_destination(&d[2]));
        assert_eq!(count_to(&registry, &d[0]), 1, "y's binding stays");
    }

    #[test]
    fn twenty_thousand_bindings_come_and_go_one_by_one() {
        let d = destinations(1);
        let x = exchange(ExchangeKind::Direct);
        let mut registry = BindingRegistry::default();
        let n = 20_000;
        for i in 0..n {
            assert!(registry.bind(&x, binding(&d[0], &i.to_string(), FieldTable::new())));
        }
        assert_eq!(x.read().bindings.len(), n);
        for i in 0..n {
            assert!(registry.unbind(&x, &binding(&d[0], &i.to_string(), FieldTable::new())));
        }
        assert!(!x.has_bindings());
        assert!(!registry.is_destination(&d[0]));
    }
}
