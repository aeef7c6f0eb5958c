//! Policies and operator policies set and cleared by operators
//! (RabbitMQ's `set_policy`, `set_operator_policy` and their `clear_`
//! and `list_` siblings). A change is checked, put in force in its vhost
//! and carried to the vhost's queues and exchanges before it returns, on
//! a blocking thread (the work grows with the queues). Changes take the
//! core's access-change lock one at a time.
//!
//! The broker keeps policies in memory: the `leveret` binary keeps them
//! as runtime parameters (components `policy` and `operator_policy`, as
//! RabbitMQ does) and sets them again at start.

use super::Admin;
use crate::policy::{Applied, Policy, PolicyError, PolicyKind, PolicySpec, VhostPolicies};
use crate::vhost::Vhost;
use leveret_protocol::ShortStr;
use std::collections::BTreeMap;
use std::sync::Arc;

impl Admin {
    fn policy_vhost(&self, vhost: &str) -> Result<Arc<Vhost>, PolicyError> {
        ShortStr::try_from(vhost)
            .ok()
            .and_then(|name| self.core.vhost(&name))
            .ok_or_else(|| PolicyError::NoVhost(vhost.to_owned()))
    }

    /// Computes the vhost's next set from the one in force with `change`
    /// and puts it in force, on a blocking thread: ranking the set and
    /// carrying it to every queue grow with them. `changed` names the one
    /// policy `change` set or cleared, if it was one.
    async fn change_policies(
        &self,
        vhost: Arc<Vhost>,
        changed: Option<(PolicyKind, String)>,
        change: impl FnOnce(&VhostPolicies) -> VhostPolicies + Send + 'static,
    ) {
        let _turn = self.core.access_changes.lock().await;
        // Only a panic fails the task; the vhost keeps what it had then.
        let _ = tokio::task::spawn_blocking(move || {
            let next = change(&vhost.policies());
            let changed = changed.as_ref().map(|(kind, name)| (*kind, name.as_str()));
            vhost.set_policies(next, changed);
        })
        .await;
    }

    /// Sets the policy `name` of `kind` in `vhost` (replacing one of that
    /// name): checked as RabbitMQ checks it, in force for every queue and
    /// exchange it matches when this returns.
    pub async fn set_policy(
        &self,
        kind: PolicyKind,
        vhost: &str,
        name: &str,
        spec: PolicySpec,
    ) -> Result<(), PolicyError> {
        let policy = Policy::new(kind, name, spec).map_err(PolicyError::Invalid)?;
        let target = self.policy_vhost(vhost)?;
        self.change_policies(target, Some((kind, name.to_owned())), |now| {
            now.with(policy)
        })
        .await;
        Ok(())
    }

    /// Sets many checked policies at once, each in the vhost it is paired
    /// with (an import, a start): each vhost's set is ranked once and
    /// carried to its queues and exchanges once, so the cost grows with
    /// policies plus objects, not with their product as one change at a
    /// time would. Nothing is set if a vhost does not exist.
    pub async fn set_policies(&self, policies: Vec<(String, Policy)>) -> Result<(), PolicyError> {
        let mut by_vhost: BTreeMap<String, Vec<Policy>> = BTreeMap::new();
        for (vhost, policy) in policies {
            by_vhost.entry(vhost).or_default().push(policy);
        }
        let mut targets = Vec::with_capacity(by_vhost.len());
        for (vhost, policies) in by_vhost {
            targets.push((self.policy_vhost(&vhost)?, policies));
        }
        for (target, policies) in targets {
            self.change_policies(target, None, |now| now.with_all(policies))
                .await;
        }
        Ok(())
    }

    /// Clears the policy `name` of `kind` in `vhost`; false if there was
    /// none.
    pub async fn clear_policy(&self, kind: PolicyKind, vhost: &str, name: &str) -> bool {
        let Ok(target) = self.policy_vhost(vhost) else {
            return false;
        };
        if target.policies().get(kind, name).is_none() {
            return false;
        }
        let owned = name.to_owned();
        self.change_policies(target, Some((kind, owned.clone())), move |now| {
            now.without(kind, &owned)
        })
        .await;
        true
    }

    /// The policies of `kind` as (vhost, policy), by vhost and name; of
    /// one vhost if `vhost` is given.
    pub fn policies(&self, kind: PolicyKind, vhost: Option<&str>) -> Vec<(String, Arc<Policy>)> {
        let mut vhosts = self.core.vhosts();
        vhosts.sort_by(|a, b| a.name.cmp(&b.name));
        vhosts
            .into_iter()
            .filter(|v| vhost.is_none_or(|wanted| v.name.as_bytes() == wanted.as_bytes()))
            .flat_map(|v| {
                let name = v.name.to_string();
                v.policies()
                    .all(kind)
                    .into_iter()
                    .map(move |p| (name.clone(), p))
            })
            .collect()
    }

    /// The policies that apply to the exchange `exchange` of `vhost`
    /// (the binary's federation reads its keys from them).
    pub fn exchange_policies(&self, vhost: &str, exchange: &str) -> Applied {
        let found = ShortStr::try_from(vhost)
            .ok()
            .and_then(|v| self.core.vhost(&v))
            .zip(ShortStr::try_from(exchange).ok())
            .and_then(|(v, name)| v.exchange(&name));
        found.map(|e| e.policies()).unwrap_or_default()
    }
}
