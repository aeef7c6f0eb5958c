//! Vhost and user limits set and cleared by operators (RabbitMQ's
//! `set_vhost_limits`, `clear_vhost_limits`, `set_user_limits`,
//! `clear_user_limits`): each change is written to the store as a runtime
//! parameter (see `limits`) and flushed under the core's access-change
//! lock before it takes effect. A new limit applies to what opens next:
//! connections and channels already open stay, as in RabbitMQ, but count.
//!
//! Uses the core's [`LimitTables`](crate::limits::LimitTables), `store`
//! and `access::lasting`.

use super::Admin;
use crate::access::lasting::AccessError;
use crate::limits::{
    to_json, UserLimits, VhostLimits, USER_LIMITS_COMPONENT, VHOST_LIMITS_COMPONENT,
    VHOST_LIMITS_NAME,
};
use crate::store::{MetaKey, MetaRecord, StoreOp};
use std::collections::BTreeMap;

/// A parameter key: (component, vhost, name).
type Key = (String, String, String);

fn vhost_key(vhost: &str) -> Key {
    (
        VHOST_LIMITS_COMPONENT.to_owned(),
        vhost.to_owned(),
        VHOST_LIMITS_NAME.to_owned(),
    )
}

fn user_key(user: &str) -> Key {
    (
        USER_LIMITS_COMPONENT.to_owned(),
        String::new(),
        user.to_owned(),
    )
}

impl Admin {
    /// Writes (or with no limits set, deletes) a limits parameter, then
    /// keeps it among the core's parameters. Callers hold the
    /// access-change lock.
    async fn write_limits(&self, key: Key, named: &[(&str, usize)]) -> Result<(), AccessError> {
        let (component, vhost, name) = key.clone();
        if named.is_empty() {
            self.write_meta(vec![StoreOp::DeleteMeta(MetaKey::Parameter {
                component,
                vhost,
                name,
            })])
            .await?;
            self.core.parameters.write().remove(&key);
        } else {
            let value = to_json(named);
            self.write_meta(vec![StoreOp::PutMeta(MetaRecord::Parameter {
                component,
                vhost,
                name,
                value: value.clone(),
            })])
            .await?;
            self.core.parameters.write().insert(key, value);
        }
        Ok(())
    }

    /// Replaces the limits of `vhost` (RabbitMQ's `set_vhost_limits`,
    /// whose definition replaces the previous one); on disk before it
    /// returns. Limits without any set clear them.
    pub async fn set_vhost_limits(
        &self,
        vhost: &str,
        limits: VhostLimits,
    ) -> Result<(), AccessError> {
        let _turn = self.core.access_changes.lock().await;
        if !self.vhosts().iter().any(|name| name == vhost) {
            return Err(AccessError::BadName(format!("no vhost '{vhost}'")));
        }
        self.write_limits(vhost_key(vhost), &limits.named()).await?;
        let limits = Some(limits).filter(|l| *l != VhostLimits::default());
        self.core.limit_tables.set_vhost(vhost, limits);
        tracing::info!(%vhost, ?limits, "vhost limits set");
        Ok(())
    }

    /// Clears every limit of `vhost` (`clear_vhost_limits`).
    pub async fn clear_vhost_limits(&self, vhost: &str) -> Result<(), AccessError> {
        let _turn = self.core.access_changes.lock().await;
        self.write_limits(vhost_key(vhost), &[]).await?;
        self.core.limit_tables.set_vhost(vhost, None);
        tracing::info!(%vhost, "vhost limits cleared");
        Ok(())
    }

    /// The limits of `vhost` (none set: the default, no limits).
    pub fn vhost_limits(&self, vhost: &str) -> VhostLimits {
        self.core.limit_tables.vhost(vhost)
    }

    /// Every vhost with limits, by name (`list_vhost_limits --global`).
    pub fn all_vhost_limits(&self) -> BTreeMap<String, VhostLimits> {
        self.core.limit_tables.vhosts()
    }

    /// Replaces the limits of `user` (the caller merges, as RabbitMQ's
    /// `set_user_limits` adds to what the user has); on disk before it
    /// returns. Limits without any set clear them.
    pub async fn set_user_limits(&self, user: &str, limits: UserLimits) -> Result<(), AccessError> {
        let _turn = self.core.access_changes.lock().await;
        if !self.core.users.contains(user) {
            return Err(AccessError::NoSuchUser(user.to_owned()));
        }
        self.write_limits(user_key(user), &limits.named()).await?;
        let limits = Some(limits).filter(|l| *l != UserLimits::default());
        self.core.limit_tables.set_user(user, limits);
        tracing::info!(%user, ?limits, "user limits set");
        Ok(())
    }

    /// Clears every limit of `user` (`clear_user_limits USER all`).
    pub async fn clear_user_limits(&self, user: &str) -> Result<(), AccessError> {
        let _turn = self.core.access_changes.lock().await;
        self.write_limits(user_key(user), &[]).await?;
        self.core.limit_tables.set_user(user, None);
        tracing::info!(%user, "user limits cleared");
        Ok(())
    }

    /// A user's limits, if they have any.
    pub fn user_limits(&self, user: &str) -> Option<UserLimits> {
        self.core.limit_tables.user(user)
    }

    /// Every user with limits, by name (`list_user_limits`).
    pub fn all_user_limits(&self) -> BTreeMap<String, UserLimits> {
        self.core.limit_tables.users()
    }
}
