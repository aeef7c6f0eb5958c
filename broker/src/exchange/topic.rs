//! The topic exchange's trie: binding keys split into dot-separated words,
//! `*` matching exactly one word and `#` zero or more, as RabbitMQ routes.
//!
//! Cost is bounded whatever the patterns: runs of `#` are collapsed when a
//! pattern is added (`#.#` routes as `#`), and a routing key is matched by
//! walking the trie as an automaton over a deduplicated set of nodes, one
//! step per word, never backtracking. A routing key of `w` words costs
//! O(w × the trie nodes it can be at at once), which for one pattern of
//! `s` segments is O(w × s). Adding or removing a pattern costs O(its
//! segments × log of the fan-out); a node's words are a B-tree, so no
//! change ever rebuilds a whole table. Nodes are pruned when their last
//! pattern goes.

use super::destination_set::DestinationSet;
use super::Destination;
use std::collections::BTreeMap;

/// Words of a routing or binding key: the empty key has none, otherwise
/// every dot separates two (possibly empty) words.
fn words(key: &[u8]) -> impl Iterator<Item = &[u8]> {
    let empty = key.is_empty();
    key.split(|&b| b == b'.').filter(move |_| !empty)
}

/// One segment of a binding key.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Segment<'a> {
    Word(&'a [u8]),
    /// `*`: exactly one word.
    Star,
    /// `#`: zero or more words.
    Hash,
}

/// The segments of a binding key with each run of `#` collapsed to one.
fn segments(pattern: &[u8]) -> impl Iterator<Item = Segment<'_>> {
    let mut previous = None;
    words(pattern)
        .map(|word| match word {
            b"*" => Segment::Star,
            b"#" => Segment::Hash,
            word => Segment::Word(word),
        })
        .filter(move |segment| {
            let repeat = *segment == Segment::Hash && previous == Some(Segment::Hash);
            previous = Some(*segment);
            !repeat
        })
}

#[derive(Debug, Default)]
struct Node {
    words: BTreeMap<Box<[u8]>, Box<Node>>,
    star: Option<Box<Node>>,
    hash: Option<Box<Node>>,
    /// Reached through a `#` edge: the node stays matched on any word.
    loops: bool,
    destinations: DestinationSet,
}

impl Node {
    fn is_unused(&self) -> bool {
        self.words.is_empty()
            && self.star.is_none()
            && self.hash.is_none()
            && self.destinations.is_empty()
    }

    fn child_mut(&mut self, segment: Segment<'_>) -> Option<&mut Node> {
        match segment {
            Segment::Word(word) => self.words.get_mut(word),
            Segment::Star => self.star.as_mut(),
            Segment::Hash => self.hash.as_mut(),
        }
        .map(|child| &mut **child)
    }

    fn child_or_new(&mut self, segment: Segment<'_>) -> &mut Node {
        match segment {
            Segment::Word(word) => self.words.entry(word.into()).or_default(),
            Segment::Star => self.star.get_or_insert_with(Box::default),
            Segment::Hash => self.hash.get_or_insert_with(|| {
                Box::new(Node {
                    loops: true,
                    ..Node::default()
                })
            }),
        }
    }

    fn detach(&mut self, segment: Segment<'_>) {
        match segment {
            Segment::Word(word) => {
                self.words.remove(word);
            }
            Segment::Star => self.star = None,
            Segment::Hash => self.hash = None,
        }
    }

    /// Removes one binding to `destination` at the end of `path`, pruning
    /// the nodes it leaves unused; false if there was none.
    fn remove(&mut self, path: &[Segment<'_>], destination: &Destination) -> bool {
        let Some((&first, rest)) = path.split_first() else {
            return self.destinations.remove(destination);
        };
        let Some(child) = self.child_mut(first) else {
            return false;
        };
        let removed = child.remove(rest, destination);
        if removed && child.is_unused() {
            self.detach(first);
        }
        removed
    }
}

/// The bindings of one topic exchange.
#[derive(Debug, Default)]
pub(super) struct TopicTrie {
    root: Node,
}

impl TopicTrie {
    /// Counts a binding with key `pattern` to `destination`.
    pub(super) fn add(&mut self, pattern: &[u8], destination: &Destination) {
        let mut at = &mut self.root;
        for segment in segments(pattern) {
            at = at.child_or_new(segment);
        }
        at.destinations.add(destination);
    }

    /// Removes one binding with key `pattern` to `destination`, pruning
    /// the nodes it leaves unused; false if there was none.
    pub(super) fn remove(&mut self, pattern: &[u8], destination: &Destination) -> bool {
        let path: Vec<Segment<'_>> = segments(pattern).collect();
        self.root.remove(&path, destination)
    }

    /// Adds to `states` the nodes reachable from them through `#` edges
    /// (a `#` matching no word), then sorts and deduplicates them.
    fn close(states: &mut Vec<&Node>) {
        let mut i = 0;
        while i < states.len() {
            if let Some(hash) = &states[i].hash {
                states.push(hash);
            }
            i += 1;
        }
        states.sort_unstable_by_key(|node| std::ptr::from_ref::<Node>(node) as usize);
        states.dedup_by(|a, b| std::ptr::eq(*a, *b));
    }

    /// Calls `found` for each destination whose binding key matches
    /// `routing_key` (a destination bound by several matching patterns
    /// comes once per pattern).
    pub(super) fn route(&self, routing_key: &[u8], mut found: impl FnMut(&Destination)) {
        let mut states = vec![&self.root];
        Self::close(&mut states);
        let mut next = Vec::new();
        for word in words(routing_key) {
            next.clear();
            for node in &states {
                next.extend(node.words.get(word).map(|child| &**child));
                next.extend(node.star.as_deref());
                if node.loops {
                    next.push(*node);
                }
            }
            Self::close(&mut next);
            std::mem::swap(&mut states, &mut next);
            if states.is_empty() {
                return;
            }
        }
        for node in states {
            node.destinations.iter().for_each(&mut found);
        }
    }

    /// Whether the trie holds nothing but its root (every pattern removed).
    #[cfg(test)]
    fn is_pruned(&self) -> bool {
        self.root.is_unused()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::exchange::tests::destinations;
    use crate::exchange::DestinationId;
    use proptest::prelude::*;

    /// RabbitMQ's semantics written as plainly as possible (exponential in
    /// the worst case, fine for the small inputs of these tests).
    fn reference_matches(pattern: &[&[u8]], key: &[&[u8]]) -> bool {
        match pattern.split_first() {
            None => key.is_empty(),
            Some((first, rest)) if *first == b"#" => {
                (0..=key.len()).any(|skip| reference_matches(rest, &key[skip..]))
            }
            Some((first, rest)) => match key.split_first() {
                None => false,
                Some((word, key_rest)) => {
                    (*first == b"*" || first == word) && reference_matches(rest, key_rest)
                }
            },
        }
    }

    fn reference(pattern: &str, key: &str) -> bool {
        let pattern: Vec<&[u8]> = words(pattern.as_bytes()).collect();
        let key: Vec<&[u8]> = words(key.as_bytes()).collect();
        reference_matches(&pattern, &key)
    }

    fn matched(trie: &TopicTrie, key: &str) -> Vec<DestinationId> {
        let mut found = Vec::new();
        trie.route(key.as_bytes(), |d| found.push(d.id()));
        found.sort_unstable();
        found.dedup();
        found
    }

    #[test]
    fn rabbitmq_examples_including_empty_words() {
        let keys = ["a.b.c", "a.c", "a", "", "a..c", "a.b.b.c", "b.c", ".", "a."];
        let table: [(&str, &[&str]); 12] = [
            ("a.*.c", &["a.b.c", "a..c"]),
            ("a.#", &["a.b.c", "a.c", "a", "a..c", "a.b.b.c", "a."]),
            ("#", &keys),
            ("*", &["a"]),
            ("#.c", &["a.b.c", "a.c", "a..c", "a.b.b.c", "b.c"]),
            ("a.#.c", &["a.b.c", "a.c", "a..c", "a.b.b.c"]),
            ("a..c", &["a..c"]),
            ("", &[""]),
            ("*.*", &["a.c", "b.c", ".", "a."]),
            ("a.*", &["a.c", "a."]),
            ("#.#", &keys),
            (
                "#.*.#",
                &["a.b.c", "a.c", "a", "a..c", "a.b.b.c", "b.c", ".", "a."],
            ),
        ];
        let dests = destinations(table.len());
        let mut trie = TopicTrie::default();
        for ((pattern, _), d) in table.iter().zip(&dests) {
            trie.add(pattern.as_bytes(), d);
        }
        for key in keys {
            let want: Vec<DestinationId> = {
                let mut v: Vec<DestinationId> = table
                    .iter()
                    .zip(&dests)
                    .filter(|((_, matching), _)| matching.contains(&key))
                    .map(|(_, d)| d.id())
                    .collect();
                v.sort_unstable();
                v
            };
            assert_eq!(matched(&trie, key), want, "routing key {key:?}");
            for (pattern, matching) in &table {
                assert_eq!(reference(pattern, key), matching.contains(&key));
            }
        }
    }

    #[test]
    fn runs_of_hash_share_one_node_and_count_separately() {
        let d = destinations(1).remove(0);
        let mut trie = TopicTrie::default();
        trie.add(b"a.#.#.#", &d);
        trie.add(b"a.#", &d);
        assert_eq!(matched(&trie, "a.x.y"), vec![d.id()]);
        assert!(trie.remove(b"a.#.#", &d), "collapses to the same pattern");
        assert_eq!(matched(&trie, "a"), vec![d.id()], "one binding left");
        assert!(trie.remove(b"a.#", &d));
        assert!(!trie.remove(b"a.#", &d), "nothing left to remove");
        assert!(matched(&trie, "a").is_empty());
        assert!(trie.is_pruned());
    }

    #[test]
    fn many_hashes_and_a_long_key_cost_one_pass() {
        let d = destinations(1).remove(0);
        let mut trie = TopicTrie::default();
        let pattern = vec!["#"; 64].join(".");
        trie.add(pattern.as_bytes(), &d);
        trie.add(b"#.a.#.a.#.a.#.a.#.a.#.a.#.a.#.b", &d);
        let key = vec!["a"; 127].join(".");
        // Exponential search would not finish; the automaton is instant.
        assert_eq!(matched(&trie, &key), vec![d.id()]);
        let mut calls = 0;
        trie.route(key.as_bytes(), |_| calls += 1);
        assert_eq!(calls, 1, "only the all-# pattern matches");
    }

    #[test]
    fn removing_patterns_prunes_every_node() {
        let dests = destinations(3);
        let mut trie = TopicTrie::default();
        for round in 0..3 {
            for (i, d) in dests.iter().enumerate() {
                trie.add(format!("a.*.{i}.#").as_bytes(), d);
                trie.add(b"a.b", d);
            }
            assert_eq!(matched(&trie, "a.b").len(), 3);
            assert_eq!(matched(&trie, "a.x.1.y.z"), vec![dests[1].id()]);
            assert!(!trie.remove(b"a.*.9.#", &dests[0]), "no such pattern");
            assert!(
                !trie.remove(b"a.b", &destinations(1)[0]),
                "no such destination"
            );
            for (i, d) in dests.iter().enumerate() {
                assert!(trie.remove(format!("a.*.{i}.#").as_bytes(), d));
                assert!(trie.remove(b"a.b", d));
            }
            assert!(trie.is_pruned(), "round {round}");
        }
    }

    /// Patterns and keys from a small alphabet with `*`, `#` and empty
    /// words, so that matches and near-misses are frequent.
    fn pattern() -> impl Strategy<Value = String> {
        prop::collection::vec(prop::sample::select(vec!["a", "b", "", "*", "#"]), 0..7)
            .prop_map(|w| w.join("."))
    }

    fn key() -> impl Strategy<Value = String> {
        prop::collection::vec(prop::sample::select(vec!["a", "b", ""]), 0..8)
            .prop_map(|w| w.join("."))
    }

    proptest! {
        #[test]
        fn the_trie_routes_as_the_reference_matcher(
            patterns in prop::collection::vec(pattern(), 1..12),
            keys in prop::collection::vec(key(), 1..12),
            removed in prop::collection::vec(any::<bool>(), 12),
        ) {
            let dests = destinations(patterns.len());
            let mut trie = TopicTrie::default();
            for (p, d) in patterns.iter().zip(&dests) {
                trie.add(p.as_bytes(), d);
            }
            // Remove some again, so pruning is exercised beside matching.
            let kept: Vec<bool> = patterns.iter().enumerate().map(|(i, p)| {
                if removed[i] {
                    prop_assert!(trie.remove(p.as_bytes(), &dests[i]));
                }
                Ok(!removed[i])
            }).collect::<Result<_, _>>()?;
            for key in &keys {
                let mut want: Vec<DestinationId> = patterns
                    .iter()
                    .zip(&dests)
                    .zip(&kept)
                    .filter(|((p, _), keep)| **keep && reference(p, key))
                    .map(|((_, d), _)| d.id())
                    .collect();
                want.sort_unstable();
                prop_assert_eq!(matched(&trie, key), want, "key {:?} patterns {:?}", key, patterns);
            }
            for (i, p) in patterns.iter().enumerate() {
                if kept[i] {
                    prop_assert!(trie.remove(p.as_bytes(), &dests[i]));
                }
            }
            prop_assert!(trie.is_pruned());
        }
    }
}
