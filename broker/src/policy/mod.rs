//! Policies and operator policies as RabbitMQ 3.10 applies them: a name,
//! a pattern (a regular expression on the queue's or exchange's name
//! bytes,
//! matched by the `regex` crate in time linear in the name), what it
//! applies to, a priority and a definition. This module owns reading and
//! checking a definition (a key Leveret does not act on is refused, never
//! kept and ignored), choosing the one policy of each kind that applies to
//! a name, and RabbitMQ's rules for combining a policy, an operator policy
//! and the object's own arguments (`combine`).
//!
//! The queue and vhost layers keep the result: a vhost holds its
//! [`VhostPolicies`], a queue the [`Applied`] pair it was given and the
//! effective arguments computed from it, so a publish costs nothing more.
//!
//! Uses `permissions` (the pattern size cap).

mod combine;
mod definition;
mod ranked;
#[cfg(test)]
mod tests;

/// Counts of the work policy look-ups do, for tests that bound it
/// (counts, not time): per thread, so tests running at once do not mix.
#[cfg(test)]
pub(crate) mod work {
    use std::cell::Cell;
    use std::thread::LocalKey;

    thread_local! {
        /// Patterns tried against a name.
        pub(crate) static MATCHES: Cell<u64> = const { Cell::new(0) };
        /// Policies put in a ranking.
        pub(crate) static RANKED: Cell<u64> = const { Cell::new(0) };
    }

    pub(crate) fn count(counter: &'static LocalKey<Cell<u64>>, n: u64) {
        counter.with(|c| c.set(c.get() + n));
    }

    /// The counter's value, which it is then reset from.
    pub(crate) fn take(counter: &'static LocalKey<Cell<u64>>) -> u64 {
        counter.with(|c| c.replace(0))
    }
}

pub use combine::{argument_wins, stricter, Applied};
pub use definition::{Definition, KeySupport, Overflow, PolicyKey, PolicyValue, POLICY_KEYS};

#[cfg(feature = "regex")]
use crate::access::permissions::PATTERN_SIZE_LIMIT;
use ranked::Ranked;
use std::collections::{HashMap, HashSet};
use std::sync::Arc;

/// Why a policy was not set.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum PolicyError {
    /// The vhost does not exist.
    #[error("no vhost '{0}'")]
    NoVhost(String),
    /// The policy does not read, or holds a key Leveret refuses.
    #[error("{0}")]
    Invalid(String),
}

/// Which objects a policy applies to (`apply-to`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ApplyTo {
    /// `queues`.
    Queues,
    /// `exchanges`.
    Exchanges,
    /// `all` (RabbitMQ's default).
    All,
}

impl ApplyTo {
    /// RabbitMQ's word for it.
    pub fn as_str(self) -> &'static str {
        match self {
            ApplyTo::Queues => "queues",
            ApplyTo::Exchanges => "exchanges",
            ApplyTo::All => "all",
        }
    }

    /// Reads RabbitMQ's word.
    pub fn parse(word: &str) -> Result<ApplyTo, String> {
        match word {
            "queues" => Ok(ApplyTo::Queues),
            "exchanges" => Ok(ApplyTo::Exchanges),
            "all" => Ok(ApplyTo::All),
            other => Err(format!(
                "apply-to '{other}': one of queues, exchanges and all"
            )),
        }
    }
}

/// A user policy (`set_policy`) or an operator policy
/// (`set_operator_policy`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum PolicyKind {
    /// RabbitMQ's policies.
    User,
    /// RabbitMQ's operator policies: a few limits an operator imposes,
    /// combined with the user policy by the stricter value.
    Operator,
}

/// A policy as given: what `set_policy` takes.
#[derive(Debug, Clone, PartialEq)]
pub struct PolicySpec {
    /// The regular expression on object names.
    pub pattern: String,
    /// Which objects it applies to.
    pub apply_to: ApplyTo,
    /// Higher wins when several match.
    pub priority: i64,
    /// The keys and values, in the order given.
    pub definition: Vec<(String, PolicyValue)>,
}

/// A checked policy.
#[derive(Debug, Clone)]
pub struct Policy {
    /// Its name.
    pub name: String,
    /// User or operator policy.
    pub kind: PolicyKind,
    /// As given.
    pub spec: PolicySpec,
    /// The definition read.
    pub definition: Definition,
    /// Whether it may apply to classic queues and to streams (its keys
    /// decide: [`definition::applicable`]).
    applicable: (bool, bool),
    #[cfg(feature = "regex")]
    matcher: regex::bytes::Regex,
    /// Without the regex engine: `.*` and literal names and prefixes only.
    #[cfg(not(feature = "regex"))]
    matcher: crate::access::permissions::Matcher,
    /// The literal prefix every name it matches starts with, if its
    /// pattern plainly has one (`ranked`).
    prefix: Option<Vec<u8>>,
}

impl Policy {
    /// Checks `spec` as RabbitMQ does for a policy of `kind`: the pattern
    /// compiles (within the size cap), every key is one Leveret acts on
    /// for that kind and its value has the right type and range.
    pub fn new(kind: PolicyKind, name: &str, spec: PolicySpec) -> Result<Policy, String> {
        if name.is_empty() {
            return Err("a policy needs a name".into());
        }
        #[cfg(feature = "regex")]
        let matcher = regex::bytes::RegexBuilder::new(&spec.pattern)
            .size_limit(PATTERN_SIZE_LIMIT)
            .build()
            .map_err(|e| format!("pattern '{}': {e}", spec.pattern))?;
        // An empty regular expression matches every name (in a permission,
        // the empty pattern means none: hence the rewrite).
        #[cfg(not(feature = "regex"))]
        let matcher = crate::access::permissions::Matcher::compile(
            if spec.pattern.is_empty() {
                ".*"
            } else {
                &spec.pattern
            },
            None,
        )
        .map_err(|e| format!("pattern '{}': {}", spec.pattern, e.reason))?;
        let definition = Definition::read(kind, &spec.definition)?;
        let prefix = ranked::required_prefix(&spec.pattern).filter(|p| !p.is_empty());
        Ok(Policy {
            prefix,
            name: name.to_owned(),
            kind,
            applicable: definition::applicable(&spec.definition),
            spec,
            definition,
            matcher,
        })
    }

    fn matches(&self, object: ObjectKind, name: &[u8]) -> bool {
        let (classic, stream) = self.applicable;
        let kind_fits = match (self.spec.apply_to, object) {
            (ApplyTo::Exchanges | ApplyTo::All, ObjectKind::Exchange) => true,
            (ApplyTo::Queues | ApplyTo::All, ObjectKind::Queue) => classic,
            (ApplyTo::Queues | ApplyTo::All, ObjectKind::Stream) => stream,
            _ => false,
        };
        #[cfg(test)]
        work::count(&work::MATCHES, 1);
        #[cfg(feature = "regex")]
        let matched = self.matcher.is_match(name);
        #[cfg(not(feature = "regex"))]
        let matched = std::str::from_utf8(name).is_ok_and(|name| self.matcher.matches(name));
        kind_fits && matched
    }
}

/// What a policy is matched against. A policy is passed over (the next
/// that matches applies) for a kind of queue its keys do not fit, as in
/// RabbitMQ 3.10: one with a stream-only key for a classic queue, one
/// with a key other than a stream's for a stream.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ObjectKind {
    /// A classic queue.
    Queue,
    /// A stream queue.
    Stream,
    /// An exchange.
    Exchange,
}

/// One vhost's policies of both kinds, each list in the order a match is
/// looked for: highest priority first, ties by name (RabbitMQ 3.10 leaves
/// a tie to its table's order; Leveret makes it the name's byte order, so
/// the outcome never depends on history). Replaced whole on each change.
#[derive(Debug, Default)]
pub struct VhostPolicies {
    user: Ranked,
    operator: Ranked,
    /// Counts the changes: an [`Applied`] computed from the set just
    /// before this one can be brought up to date by one match.
    generation: u64,
}

impl VhostPolicies {
    fn list(&self, kind: PolicyKind) -> &[Arc<Policy>] {
        match kind {
            PolicyKind::User => self.user.list(),
            PolicyKind::Operator => self.operator.list(),
        }
    }

    /// These policies without those `drop` picks, with `added`.
    fn rebuilt(&self, drop: impl Fn(&Policy) -> bool, added: Vec<Policy>) -> VhostPolicies {
        let (added_user, added_operator): (Vec<Policy>, Vec<Policy>) =
            added.into_iter().partition(|p| p.kind == PolicyKind::User);
        let next = |of: PolicyKind, added: Vec<Policy>| {
            let mut list: Vec<Arc<Policy>> =
                self.list(of).iter().filter(|p| !drop(p)).cloned().collect();
            list.extend(added.into_iter().map(Arc::new));
            Ranked::new(list)
        };
        VhostPolicies {
            user: next(PolicyKind::User, added_user),
            operator: next(PolicyKind::Operator, added_operator),
            generation: self.generation + 1,
        }
    }

    /// These policies with `policy` set (replacing one of its kind and
    /// name).
    pub fn with(&self, policy: Policy) -> VhostPolicies {
        self.with_all(vec![policy])
    }

    /// These policies with every one of `policies` set, each replacing
    /// the one of its kind and name (of two with the same kind and name
    /// in `policies`, the later): ranked once for the whole batch, so
    /// putting N policies in costs N log N, not N² as N changes would.
    pub fn with_all(&self, policies: Vec<Policy>) -> VhostPolicies {
        let mut last: HashMap<(PolicyKind, String), Policy> = HashMap::new();
        for policy in policies {
            last.insert((policy.kind, policy.name.clone()), policy);
        }
        let mut replaced: HashMap<PolicyKind, HashSet<String>> = HashMap::new();
        for (kind, name) in last.keys() {
            replaced.entry(*kind).or_default().insert(name.clone());
        }
        let is_replaced = |p: &Policy| {
            replaced
                .get(&p.kind)
                .is_some_and(|names| names.contains(&p.name))
        };
        self.rebuilt(is_replaced, last.into_values().collect())
    }

    /// These policies without the policy `name` of `kind`.
    pub fn without(&self, kind: PolicyKind, name: &str) -> VhostPolicies {
        self.rebuilt(|p| p.kind == kind && p.name == name, Vec::new())
    }

    /// The policy `name` of `kind`.
    pub fn get(&self, kind: PolicyKind, name: &str) -> Option<&Arc<Policy>> {
        self.list(kind).iter().find(|p| p.name == name)
    }

    /// Every policy of `kind`, by name.
    pub fn all(&self, kind: PolicyKind) -> Vec<Arc<Policy>> {
        let mut all = self.list(kind).to_vec();
        all.sort_by(|a, b| a.name.cmp(&b.name));
        all
    }

    /// The policy of each kind that applies to the object: the first
    /// match in each ranking. Costs a match per policy filed under a
    /// prefix of the name or under none (`ranked`).
    pub fn applied(&self, object: ObjectKind, name: &[u8]) -> Applied {
        Applied {
            policy: self.user.first_match(object, name),
            operator: self.operator.first_match(object, name),
            generation: self.generation,
        }
    }

    /// What applies to the object after the policy `name` of `kind` was
    /// set or cleared, given what applied before (`current`): one match of
    /// the changed policy, and a full look-up only when the changed policy
    /// was the one that applied or `current` was not computed from the set
    /// just before this one. A change so costs one match per object, not
    /// one per object and policy.
    pub fn after_change(
        &self,
        current: &Applied,
        kind: PolicyKind,
        name: &str,
        object: ObjectKind,
        object_name: &[u8],
    ) -> Applied {
        let slot = match kind {
            PolicyKind::User => &current.policy,
            PolicyKind::Operator => &current.operator,
        };
        if current.generation + 1 != self.generation
            || slot.as_ref().is_some_and(|p| p.name == name)
        {
            return self.applied(object, object_name);
        }
        let mut next = current.clone();
        next.generation = self.generation;
        let Some(changed) = self.get(kind, name) else {
            return next;
        };
        let beats = |held: &Option<Arc<Policy>>| match held {
            None => true,
            Some(held) => {
                changed.spec.priority > held.spec.priority
                    || (changed.spec.priority == held.spec.priority && changed.name < held.name)
            }
        };
        if !(beats(slot) && changed.matches(object, object_name)) {
            return next;
        }
        match kind {
            PolicyKind::User => next.policy = Some(Arc::clone(changed)),
            PolicyKind::Operator => next.operator = Some(Arc::clone(changed)),
        }
        next
    }
}
