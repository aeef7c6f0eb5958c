//! One kind of a vhost's policies in the order a match is looked for
//! (highest priority first, ties by name), with an index that keeps a
//! look-up from trying every policy: a pattern that plainly requires a
//! literal prefix (`^orders\.eu`, no `|`) is filed under it, and a name is
//! tried only against the policies filed under one of its own prefixes
//! and those with no such prefix. A vhost with thousands of policies of
//! the usual `^prefix` shape so costs a declare a handful of matches.

use super::{ObjectKind, Policy};
use std::collections::HashMap;
use std::sync::Arc;

/// Policies, ranked, with their prefix index.
#[derive(Debug, Default)]
pub(super) struct Ranked {
    /// Every policy, highest rank first.
    list: Vec<Arc<Policy>>,
    /// Rank (index in `list`) of the policies with a required prefix, by
    /// that prefix.
    by_prefix: HashMap<Vec<u8>, Vec<usize>>,
    /// Ranks of the policies without one.
    unfiled: Vec<usize>,
    /// The longest prefix filed.
    longest: usize,
}

/// The literal prefix every name `pattern` matches starts with, when the
/// pattern says so plainly: `^`, then ASCII letters, digits, `-`, `_`,
/// `/`, `:`, `@` or escaped ASCII punctuation, up to (not with) the
/// first literal a quantifier follows; `None` for a
/// pattern with a `|` anywhere (an alternative need not share it).
pub(super) fn required_prefix(pattern: &str) -> Option<Vec<u8>> {
    let rest = pattern.strip_prefix('^')?;
    if pattern.contains('|') {
        return None;
    }
    let mut prefix = Vec::new();
    let mut chars = rest.chars().peekable();
    while let Some(c) = chars.next() {
        let literal = match c {
            '\\' => match chars.next() {
                Some(escaped) if escaped.is_ascii_punctuation() => escaped,
                _ => break,
            },
            c if c.is_ascii_alphanumeric() || "-_/:@".contains(c) => c,
            _ => break,
        };
        // Quantified (even by `+`, which a further quantifier may make
        // optional), it is not required as written: the prefix stops.
        if matches!(chars.peek(), Some('?' | '*' | '{' | '+')) {
            break;
        }
        prefix.push(literal as u8);
    }
    Some(prefix)
}

impl Ranked {
    /// `policies` ranked and filed.
    pub(super) fn new(mut list: Vec<Arc<Policy>>) -> Ranked {
        #[cfg(test)]
        super::work::count(&super::work::RANKED, list.len() as u64);
        list.sort_by(|a, b| {
            b.spec
                .priority
                .cmp(&a.spec.priority)
                .then_with(|| a.name.cmp(&b.name))
        });
        let mut ranked = Ranked::default();
        for (rank, policy) in list.iter().enumerate() {
            match &policy.prefix {
                Some(prefix) => {
                    ranked.longest = ranked.longest.max(prefix.len());
                    ranked
                        .by_prefix
                        .entry(prefix.clone())
                        .or_default()
                        .push(rank);
                }
                None => ranked.unfiled.push(rank),
            }
        }
        ranked.list = list;
        ranked
    }

    /// Every policy, highest rank first.
    pub(super) fn list(&self) -> &[Arc<Policy>] {
        &self.list
    }

    /// The highest-ranked policy that matches the object: tried are only
    /// those filed under a prefix of `name` and those not filed.
    pub(super) fn first_match(&self, object: ObjectKind, name: &[u8]) -> Option<Arc<Policy>> {
        let filed = (1..=name.len().min(self.longest))
            .filter_map(|len| self.by_prefix.get(&name[..len]))
            .flatten();
        let mut candidates: Vec<usize> = filed.chain(&self.unfiled).copied().collect();
        candidates.sort_unstable();
        candidates
            .into_iter()
            .map(|rank| &self.list[rank])
            .find(|policy| policy.matches(object, name))
            .cloned()
    }
}
