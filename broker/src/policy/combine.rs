//! RabbitMQ 3.10's rules for combining what applies to a queue or an
//! exchange: the user policy and the operator policy first (for the keys
//! both may hold, `expires`, `message-ttl`, `max-length` and
//! `max-length-bytes`, the smaller value: `rabbit_policy:get/2`), then
//! that with the object's own arguments (`expires`, `message-ttl`,
//! `max-length`, `max-length-bytes`: the smaller; `dead-letter-exchange`,
//! `dead-letter-routing-key`, `overflow` and `alternate-exchange`: the
//! argument wins: `rabbit_amqqueue_process:process_args_policy/1`,
//! `rabbit_policy:get_arg/3`).

use super::{Overflow, Policy, PolicyValue};
use leveret_protocol::ShortStr;
use std::collections::BTreeMap;
use std::sync::Arc;

/// The smaller of the values given (RabbitMQ's `res_min`): neither side
/// can loosen what the other sets.
pub fn stricter(a: Option<u64>, b: Option<u64>) -> Option<u64> {
    match (a, b) {
        (Some(a), Some(b)) => Some(a.min(b)),
        (a, b) => a.or(b),
    }
}

/// The argument if the object has one, else the policy's (RabbitMQ's
/// `res_arg`).
pub fn argument_wins<T>(policy: Option<T>, argument: Option<T>) -> Option<T> {
    argument.or(policy)
}

/// The policies that apply to one object: at most one of each kind.
#[derive(Debug, Clone, Default)]
pub struct Applied {
    /// The user policy.
    pub policy: Option<Arc<Policy>>,
    /// The operator policy.
    pub operator: Option<Arc<Policy>>,
    /// The vhost's policy set these were found in (`VhostPolicies`).
    pub(super) generation: u64,
}

impl PartialEq for Applied {
    fn eq(&self, other: &Self) -> bool {
        let same = |a: &Option<Arc<Policy>>, b: &Option<Arc<Policy>>| match (a, b) {
            (Some(a), Some(b)) => Arc::ptr_eq(a, b),
            (None, None) => true,
            _ => false,
        };
        same(&self.policy, &other.policy) && same(&self.operator, &other.operator)
    }
}

impl Applied {
    fn both(&self, key: impl Fn(&Policy) -> Option<u64>) -> Option<u64> {
        stricter(
            self.policy.as_deref().and_then(&key),
            self.operator.as_deref().and_then(&key),
        )
    }

    fn user<T>(&self, key: impl Fn(&Policy) -> Option<T>) -> Option<T> {
        self.policy.as_deref().and_then(key)
    }

    /// `message-ttl` of the two policies.
    pub fn message_ttl(&self) -> Option<u64> {
        self.both(|p| p.definition.message_ttl)
    }

    /// `expires` of the two policies.
    pub fn expires(&self) -> Option<u64> {
        self.both(|p| p.definition.expires)
    }

    /// `max-length` of the two policies.
    pub fn max_length(&self) -> Option<u64> {
        self.both(|p| p.definition.max_length)
    }

    /// `max-length-bytes` of the two policies.
    pub fn max_length_bytes(&self) -> Option<u64> {
        self.both(|p| p.definition.max_length_bytes)
    }

    /// The user policy's `max-age`, ms.
    pub fn max_age_ms(&self) -> Option<u64> {
        self.user(|p| p.definition.max_age_ms)
    }

    /// The user policy's `stream-max-segment-size-bytes`.
    pub fn stream_max_segment_size_bytes(&self) -> Option<u64> {
        self.user(|p| p.definition.stream_max_segment_size_bytes)
    }

    /// The user policy's `overflow`.
    pub fn overflow(&self) -> Option<Overflow> {
        self.user(|p| p.definition.overflow)
    }

    /// The user policy's `dead-letter-exchange`.
    pub fn dead_letter_exchange(&self) -> Option<ShortStr> {
        self.user(|p| p.definition.dead_letter_exchange.clone())
    }

    /// The user policy's `dead-letter-routing-key`.
    pub fn dead_letter_routing_key(&self) -> Option<ShortStr> {
        self.user(|p| p.definition.dead_letter_routing_key.clone())
    }

    /// The user policy's `alternate-exchange`.
    pub fn alternate_exchange(&self) -> Option<ShortStr> {
        self.user(|p| p.definition.alternate_exchange.clone())
    }

    /// The user policy's name.
    pub fn policy_name(&self) -> Option<&str> {
        self.policy.as_deref().map(|p| p.name.as_str())
    }

    /// The operator policy's name.
    pub fn operator_policy_name(&self) -> Option<&str> {
        self.operator.as_deref().map(|p| p.name.as_str())
    }

    /// RabbitMQ's `effective_policy_definition`: the user policy's keys,
    /// with the operator policy's merged in (the smaller value where both
    /// set one), by key.
    pub fn effective_definition(&self) -> BTreeMap<String, PolicyValue> {
        let mut merged: BTreeMap<String, PolicyValue> = self
            .policy
            .iter()
            .flat_map(|p| p.spec.definition.iter().cloned())
            .collect();
        for (key, value) in self.operator.iter().flat_map(|p| p.spec.definition.iter()) {
            let combined = match (merged.get(key), value) {
                (Some(PolicyValue::Integer(mine)), PolicyValue::Integer(theirs)) => {
                    PolicyValue::Integer(*mine.min(theirs))
                }
                _ => value.clone(),
            };
            merged.insert(key.clone(), combined);
        }
        merged
    }
}
