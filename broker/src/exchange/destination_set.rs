//! A set of destinations with a count per destination: the slot of an
//! exchange's index (a direct key, a topic trie node, a fanout's bindings)
//! where several bindings may lead to the same destination. Adding and
//! removing cost O(log n) at worst: small sets are a vector scanned in
//! place, and once a set outgrows [`SCAN_LIMIT`] it keeps a B-tree of
//! positions beside the vector (a B-tree rather than a hash map, which
//! would rehash everything when it grows). Routing walks the vector.

use super::{Destination, DestinationId};
use std::collections::BTreeMap;

/// Entries scanned linearly before a set builds its position index.
const SCAN_LIMIT: usize = 16;

/// One destination and how many bindings of the slot lead to it.
#[derive(Debug)]
struct Entry {
    destination: Destination,
    bindings: usize,
}

/// Destinations of one index slot, each once, with their binding counts.
#[derive(Debug, Default)]
pub(super) struct DestinationSet {
    entries: Vec<Entry>,
    /// Position in `entries` by destination, once the set is large.
    positions: Option<BTreeMap<DestinationId, usize>>,
}

impl DestinationSet {
    fn position(&self, id: DestinationId) -> Option<usize> {
        match &self.positions {
            Some(positions) => positions.get(&id).copied(),
            None => self.entries.iter().position(|e| e.destination.id() == id),
        }
    }

    /// Counts one more binding to `destination`.
    pub(super) fn add(&mut self, destination: &Destination) {
        if let Some(at) = self.position(destination.id()) {
            self.entries[at].bindings += 1;
            return;
        }
        self.entries.push(Entry {
            destination: destination.clone(),
            bindings: 1,
        });
        let last = self.entries.len() - 1;
        match &mut self.positions {
            Some(positions) => {
                positions.insert(destination.id(), last);
            }
            None if self.entries.len() > SCAN_LIMIT => {
                let positions = self
                    .entries
                    .iter()
                    .enumerate()
                    .map(|(at, e)| (e.destination.id(), at))
                    .collect();
                self.positions = Some(positions);
            }
            None => {}
        }
    }

    /// Counts one binding to `destination` less, dropping the destination
    /// with its last binding; false if it was not in the set.
    pub(super) fn remove(&mut self, destination: &Destination) -> bool {
        let id = destination.id();
        let Some(at) = self.position(id) else {
            return false;
        };
        self.entries[at].bindings -= 1;
        if self.entries[at].bindings == 0 {
            self.entries.swap_remove(at);
            if let Some(positions) = &mut self.positions {
                positions.remove(&id);
                if let Some(moved) = self.entries.get(at) {
                    positions.insert(moved.destination.id(), at);
                }
            }
        }
        true
    }

    /// Whether no binding is left.
    pub(super) fn is_empty(&self) -> bool {
        self.entries.is_empty()
    }

    /// Each destination once.
    pub(super) fn iter(&self) -> impl Iterator<Item = &Destination> {
        self.entries.iter().map(|e| &e.destination)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::exchange::tests::destinations;

    #[test]
    fn counts_bindings_per_destination_small_and_large() {
        for size in [3, SCAN_LIMIT * 4] {
            let all = destinations(size);
            let mut set = DestinationSet::default();
            for d in &all {
                set.add(d);
                set.add(d);
            }
            assert_eq!(set.iter().count(), size, "each destination once");
            for d in &all {
                assert!(set.remove(d), "first of two bindings");
            }
            assert_eq!(set.iter().count(), size, "one binding left each");
            for d in all.iter().step_by(2) {
                assert!(set.remove(d));
                assert!(!set.remove(d), "already gone");
            }
            let left: Vec<DestinationId> = set.iter().map(Destination::id).collect();
            let want: Vec<DestinationId> =
                all.iter().skip(1).step_by(2).map(Destination::id).collect();
            let mut sorted = left.clone();
            sorted.sort_unstable();
            let mut want_sorted = want.clone();
            want_sorted.sort_unstable();
            assert_eq!(sorted, want_sorted);
            for d in all.iter().skip(1).step_by(2) {
                assert!(set.remove(d));
            }
            assert!(set.is_empty());
        }
    }
}
