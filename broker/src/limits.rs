//! Vhost and user limits in effect (RabbitMQ's `set_vhost_limits` and
//! `set_user_limits`): the configured ones at start, changed at run time
//! by operators (`admin::limits`). They are kept in the store as runtime
//! parameters, as RabbitMQ keeps vhost limits: component `vhost-limits`,
//! name `limits` in the vhost; user limits under the Leveret component
//! `user-limits`, named by the user, in no vhost. Both values are a JSON
//! object of RabbitMQ's limit names and non-negative integers, written and
//! read here. Admission (`admission`) counts against them; this module only
//! holds them. Uses `parameters`.

use crate::parameters::Parameters;
use std::collections::{BTreeMap, HashMap};
use std::sync::RwLock;

/// The parameter component vhost limits are stored under (RabbitMQ's).
pub const VHOST_LIMITS_COMPONENT: &str = "vhost-limits";
/// The parameter name of a vhost's limits (RabbitMQ's).
pub const VHOST_LIMITS_NAME: &str = "limits";
/// The parameter component user limits are stored under (Leveret's).
pub const USER_LIMITS_COMPONENT: &str = "user-limits";

/// The limits of one user, RabbitMQ's `rabbitmqctl set_user_limits`.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct UserLimits {
    /// Most connections the user has open at once, in any vhost
    /// (`max-connections`); connection.open beyond it is refused with 530
    /// NOT_ALLOWED.
    pub max_connections: Option<usize>,
    /// Most channels the user has open at once across all their
    /// connections (`max-channels`); channel.open beyond it closes the
    /// connection with 530 NOT_ALLOWED, as RabbitMQ does.
    pub max_channels: Option<usize>,
}

/// The limits of one vhost, RabbitMQ's `rabbitmqctl set_vhost_limits`.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct VhostLimits {
    /// Most connections open to the vhost at once (`max-connections`);
    /// connection.open beyond it is refused with 530 NOT_ALLOWED.
    pub max_connections: Option<usize>,
    /// Most queues in the vhost (`max-queues`); queue.declare of a new
    /// queue beyond it is refused with 406 PRECONDITION_FAILED.
    pub max_queues: Option<usize>,
}

/// A limit name that is not one of RabbitMQ's for its kind.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("unknown limit '{0}' (known: {1})")]
pub struct UnknownLimit(pub String, pub &'static str);

/// A limit's value as RabbitMQ takes it: negative is no limit.
fn limit(value: i64) -> Option<usize> {
    usize::try_from(value).ok()
}

impl VhostLimits {
    /// The limit names, as RabbitMQ spells them.
    pub const NAMES: &'static str = "max-connections, max-queues";

    /// These limits with `name` set to `value` (negative: no limit).
    pub fn with(mut self, name: &str, value: i64) -> Result<Self, UnknownLimit> {
        match name {
            "max-connections" => self.max_connections = limit(value),
            "max-queues" => self.max_queues = limit(value),
            _ => return Err(UnknownLimit(name.to_owned(), Self::NAMES)),
        }
        Ok(self)
    }

    /// Each limit set, by RabbitMQ's name.
    pub fn named(&self) -> Vec<(&'static str, usize)> {
        [
            ("max-connections", self.max_connections),
            ("max-queues", self.max_queues),
        ]
        .into_iter()
        .filter_map(|(name, value)| Some((name, value?)))
        .collect()
    }
}

impl UserLimits {
    /// The limit names, as RabbitMQ spells them.
    pub const NAMES: &'static str = "max-connections, max-channels";

    /// These limits with `name` set to `value` (negative: no limit).
    pub fn with(mut self, name: &str, value: i64) -> Result<Self, UnknownLimit> {
        match name {
            "max-connections" => self.max_connections = limit(value),
            "max-channels" => self.max_channels = limit(value),
            _ => return Err(UnknownLimit(name.to_owned(), Self::NAMES)),
        }
        Ok(self)
    }

    /// Each limit set, by RabbitMQ's name.
    pub fn named(&self) -> Vec<(&'static str, usize)> {
        [
            ("max-connections", self.max_connections),
            ("max-channels", self.max_channels),
        ]
        .into_iter()
        .filter_map(|(name, value)| Some((name, value?)))
        .collect()
    }
}

/// `{"max-connections":10}`: the stored form.
pub fn to_json(named: &[(&str, usize)]) -> String {
    let fields: Vec<String> = named
        .iter()
        .map(|(name, value)| format!("\"{name}\":{value}"))
        .collect();
    format!("{{{}}}", fields.join(","))
}

/// Reads the stored form back: a flat JSON object of limit names (no
/// quotes, commas or colons in them) and integers; `None` if it is not
/// one.
fn from_json(text: &str) -> Option<Vec<(String, i64)>> {
    let inner = text.trim().strip_prefix('{')?.strip_suffix('}')?.trim();
    if inner.is_empty() {
        return Some(Vec::new());
    }
    inner
        .split(',')
        .map(|field| {
            let (name, value) = field.split_once(':')?;
            let name = name.trim().strip_prefix('"')?.strip_suffix('"')?;
            Some((name.to_owned(), value.trim().parse().ok()?))
        })
        .collect()
}

fn parsed<L: Default>(
    text: &str,
    with: impl Fn(L, &str, i64) -> Result<L, UnknownLimit>,
) -> Option<L> {
    from_json(text)?
        .into_iter()
        .try_fold(L::default(), |limits, (name, value)| {
            with(limits, &name, value).ok()
        })
}

/// The limits in effect, by vhost and by user. Each lock is held for one
/// lookup or change, never across an await.
#[derive(Debug, Default)]
pub struct LimitTables {
    vhosts: RwLock<HashMap<String, VhostLimits>>,
    users: RwLock<HashMap<String, UserLimits>>,
}

impl LimitTables {
    /// The stored limits, then the configured ones over them (a
    /// configuration names its limits afresh at each start, as it does its
    /// users). A stored value that cannot be read is logged and skipped.
    pub fn at_start(
        parameters: &Parameters,
        configured_vhosts: &HashMap<String, VhostLimits>,
        configured_users: &HashMap<String, UserLimits>,
    ) -> Self {
        let mut vhosts = HashMap::new();
        let mut users = HashMap::new();
        for ((component, vhost, name), value) in parameters.read().iter() {
            let restored = match component.as_str() {
                VHOST_LIMITS_COMPONENT => parsed(value, VhostLimits::with)
                    .map(|limits| vhosts.insert(vhost.clone(), limits))
                    .is_some(),
                USER_LIMITS_COMPONENT => parsed(value, UserLimits::with)
                    .map(|limits| users.insert(name.clone(), limits))
                    .is_some(),
                _ => true,
            };
            if !restored {
                tracing::error!(%component, %vhost, %name, %value, "stored limits cannot be read; not restored");
            }
        }
        vhosts.extend(configured_vhosts.iter().map(|(k, v)| (k.clone(), *v)));
        users.extend(configured_users.iter().map(|(k, v)| (k.clone(), *v)));
        LimitTables {
            vhosts: RwLock::new(vhosts),
            users: RwLock::new(users),
        }
    }

    /// The limits of the vhost called `name` (none set: no limits).
    pub fn vhost(&self, name: &str) -> VhostLimits {
        let vhosts = self.vhosts.read().unwrap_or_else(|e| e.into_inner());
        vhosts.get(name).copied().unwrap_or_default()
    }

    /// The limits of the user called `name`, if they have any.
    pub fn user(&self, name: &str) -> Option<UserLimits> {
        let users = self.users.read().unwrap_or_else(|e| e.into_inner());
        users.get(name).copied()
    }

    /// Sets (or with `None` clears) a vhost's limits.
    pub fn set_vhost(&self, name: &str, limits: Option<VhostLimits>) {
        let mut vhosts = self.vhosts.write().unwrap_or_else(|e| e.into_inner());
        match limits {
            Some(limits) => vhosts.insert(name.to_owned(), limits),
            None => vhosts.remove(name),
        };
    }

    /// Sets (or with `None` clears) a user's limits.
    pub fn set_user(&self, name: &str, limits: Option<UserLimits>) {
        let mut users = self.users.write().unwrap_or_else(|e| e.into_inner());
        match limits {
            Some(limits) => users.insert(name.to_owned(), limits),
            None => users.remove(name),
        };
    }

    /// Every vhost with limits, by name.
    pub fn vhosts(&self) -> BTreeMap<String, VhostLimits> {
        let vhosts = self.vhosts.read().unwrap_or_else(|e| e.into_inner());
        vhosts.iter().map(|(k, v)| (k.clone(), *v)).collect()
    }

    /// Every user with limits, by name.
    pub fn users(&self) -> BTreeMap<String, UserLimits> {
        let users = self.users.read().unwrap_or_else(|e| e.into_inner());
        users.iter().map(|(k, v)| (k.clone(), *v)).collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_stored_form_reads_back_and_negative_values_are_no_limit() {
        let limits = VhostLimits::default()
            .with("max-connections", 10)
            .unwrap()
            .with("max-queues", 0)
            .unwrap();
        let text = to_json(&limits.named());
        assert_eq!(text, r#"{"max-connections":10,"max-queues":0}"#);
        assert_eq!(parsed(&text, VhostLimits::with), Some(limits));
        assert_eq!(
            parsed(r#"{ "max-channels" : -1 }"#, UserLimits::with),
            Some(UserLimits::default())
        );
        assert_eq!(parsed("{}", UserLimits::with), Some(UserLimits::default()));
        for bad in [r#"{"max-queues":1}"#, "[1]", r#"{"max-channels":x}"#, ""] {
            assert_eq!(parsed(bad, UserLimits::with), None, "{bad}");
        }
        assert_eq!(
            UserLimits::default().with("memory", 1),
            Err(UnknownLimit("memory".into(), UserLimits::NAMES))
        );
    }
}
