//! The topic exchange's trie: binding keys split into dot-separated words,
//! `*` matching exactly one word and `#` zero or more, with each routing
//! key's result cached until the bindings change.

use super::Destination;
use leveret_protocol::ShortStr;
use std::collections::HashMap;
use std::sync::{Arc, Mutex};

/// Words of a routing or binding key: the empty key has none, otherwise
/// every dot separates two (possibly empty) words.
fn words(key: &[u8]) -> impl Iterator<Item = &[u8]> {
    let empty = key.is_empty();
    key.split(|&b| b == b'.').filter(move |_| !empty)
}

#[derive(Debug, Default)]
struct Node {
    children: HashMap<Box<[u8]>, Node>,
    star: Option<Box<Node>>,
    hash: Option<Box<Node>>,
    destinations: Vec<Destination>,
}

impl Node {
    fn insert<'a>(&mut self, mut key: impl Iterator<Item = &'a [u8]>, destination: Destination) {
        match key.next() {
            None => {
                if !self.destinations.contains(&destination) {
                    self.destinations.push(destination);
                }
            }
            Some(b"*") => self
                .star
                .get_or_insert_with(Default::default)
                .insert(key, destination),
            Some(b"#") => self
                .hash
                .get_or_insert_with(Default::default)
                .insert(key, destination),
            Some(word) => self
                .children
                .entry(word.into())
                .or_default()
                .insert(key, destination),
        }
    }

    fn collect(&self, words: &[&[u8]], out: &mut Vec<Destination>) {
        if let Some(hash) = &self.hash {
            // `#` swallows zero, one, or more of the remaining words.
            for skip in 0..=words.len() {
                hash.collect(&words[skip..], out);
            }
        }
        let Some((first, rest)) = words.split_first() else {
            out.extend(self.destinations.iter().cloned());
            return;
        };
        if let Some(child) = self.children.get(*first) {
            child.collect(rest, out);
        }
        if let Some(star) = &self.star {
            star.collect(rest, out);
        }
    }
}

/// Most routing keys remembered; past this the cache starts over.
const CACHE_LIMIT: usize = 4096;

/// The bindings of one topic exchange.
#[derive(Debug, Default)]
pub struct TopicTrie {
    root: Node,
    cache: Mutex<HashMap<ShortStr, Arc<[Destination]>>>,
}

impl TopicTrie {
    /// Builds the trie for a set of (binding key, destination) pairs.
    pub fn build<'a>(bindings: impl Iterator<Item = (&'a ShortStr, &'a Destination)>) -> Self {
        let mut root = Node::default();
        for (key, destination) in bindings {
            root.insert(words(key.as_bytes()), destination.clone());
        }
        TopicTrie {
            root,
            cache: Mutex::new(HashMap::new()),
        }
    }

    /// The destinations whose binding key matches `routing_key`, each once.
    pub fn route(&self, routing_key: &ShortStr) -> Arc<[Destination]> {
        // Lock held only for a lookup or an insert, never across an await.
        let mut cache = self.cache.lock().unwrap_or_else(|e| e.into_inner());
        if let Some(hit) = cache.get(routing_key) {
            return Arc::clone(hit);
        }
        let words: Vec<&[u8]> = words(routing_key.as_bytes()).collect();
        let mut found = Vec::new();
        self.root.collect(&words, &mut found);
        let mut unique: Vec<Destination> = Vec::with_capacity(found.len());
        for d in found {
            if !unique.contains(&d) {
                unique.push(d);
            }
        }
        let result: Arc<[Destination]> = unique.into();
        if cache.len() >= CACHE_LIMIT {
            cache.clear();
        }
        cache.insert(routing_key.clone(), Arc::clone(&result));
        result
    }
}
