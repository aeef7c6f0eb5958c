//! [`Admin`]'s user, vhost and permission operations, at run time: each
//! change is checked, written to the store as one atomic batch and flushed
//! before it takes effect and before the caller hears it is done, all under
//! [`Core::access_changes`](crate::core::Core::access_changes), so the
//! store and memory see the changes in one order. A write that fails
//! changes nothing and is reported.
//!
//! Uses `access::lasting` (its errors and the records it restores at start),
//! `auth`, `permissions`, `limits`, `store` and the core's users.

use super::Admin;
use crate::access::auth::User;
use crate::access::lasting::{permission_record, user_record, AccessError};
use crate::access::permissions::{Permission, TopicPermission};
use crate::store::{MetaKey, MetaRecord, StoreOp};
use leveret_protocol::ShortStr;

impl Admin {
    /// Writes `ops` as one atomic batch and waits for the flush; a broker
    /// without a store has nothing to wait for. Callers hold
    /// `Core::access_changes`.
    pub(crate) async fn write_meta(&self, ops: Vec<StoreOp>) -> Result<(), AccessError> {
        let Some(persistence) = &self.core.persistence else {
            return Ok(());
        };
        let number = persistence.submit_atomic(ops);
        if persistence.wait(number).await {
            Ok(())
        } else {
            tracing::error!(
                "a change to users, vhosts or permissions could not be written; it is refused"
            );
            Err(AccessError::Storage)
        }
    }

    fn require_user(&self, user: &str) -> Result<(), AccessError> {
        if self.core.users.contains(user) {
            Ok(())
        } else {
            Err(AccessError::NoSuchUser(user.to_owned()))
        }
    }

    /// Adds or replaces a user (RabbitMQ's `add_user`, `change_password`,
    /// `set_user_tags`, `PUT /api/users/NAME`); true if they are new.
    /// Open connections of a replaced user stay open.
    pub async fn put_user(&self, name: &str, user: User) -> Result<bool, AccessError> {
        if name.is_empty() {
            return Err(AccessError::BadName("a user needs a name".to_owned()));
        }
        let _turn = self.core.access_changes.lock().await;
        self.write_meta(vec![StoreOp::PutMeta(user_record(name, &user))])
            .await?;
        Ok(self.core.users.put(name, user))
    }

    /// Deletes a user and their permissions, topic permissions and limits
    /// (RabbitMQ's `delete_user`): they cannot log in again, and their open
    /// channels are refused from their next operation. False if there was
    /// no such user.
    pub async fn delete_user(&self, name: &str) -> Result<bool, AccessError> {
        let _turn = self.core.access_changes.lock().await;
        if !self.core.users.contains(name) {
            return Ok(false);
        }
        let permissions = &self.core.permissions;
        let vhosts: Vec<String> = permissions
            .list()
            .into_iter()
            .filter(|(user, ..)| user == name)
            .map(|(_, vhost, _)| vhost)
            .collect();
        let topics: Vec<(String, String)> = permissions
            .list_topics()
            .into_iter()
            .filter(|(user, ..)| user == name)
            .map(|(_, vhost, exchange, _)| (vhost, exchange))
            .collect();
        let mut ops = vec![
            StoreOp::DeleteMeta(MetaKey::User(name.to_owned())),
            // Their limits, if any (see `limits`).
            StoreOp::DeleteMeta(MetaKey::Parameter {
                component: crate::limits::USER_LIMITS_COMPONENT.to_owned(),
                vhost: String::new(),
                name: name.to_owned(),
            }),
        ];
        ops.extend(vhosts.iter().map(|vhost| {
            StoreOp::DeleteMeta(MetaKey::Permission {
                user: name.to_owned(),
                vhost: vhost.clone(),
            })
        }));
        ops.extend(topics.iter().map(|(vhost, exchange)| {
            StoreOp::DeleteMeta(MetaKey::TopicPermission {
                user: name.to_owned(),
                vhost: vhost.clone(),
                exchange: exchange.clone(),
            })
        }));
        self.write_meta(ops).await?;
        self.core.users.remove(name);
        self.core.limit_tables.set_user(name, None);
        self.core.parameters.write().remove(&(
            crate::limits::USER_LIMITS_COMPONENT.to_owned(),
            String::new(),
            name.to_owned(),
        ));
        for vhost in &vhosts {
            permissions.clear(name, vhost);
        }
        for (vhost, exchange) in &topics {
            permissions.clear_topic(name, vhost, exchange);
        }
        Ok(true)
    }

    /// Adds a vhost (RabbitMQ's `add_vhost`, `PUT /api/vhosts/NAME`); true
    /// if it is new.
    pub async fn add_vhost(&self, name: &str) -> Result<bool, AccessError> {
        let vhost = ShortStr::try_from(name)
            .ok()
            .filter(|vhost| !vhost.is_empty())
            .ok_or_else(|| AccessError::BadName("a vhost's name is 1 to 255 bytes".to_owned()))?;
        let _turn = self.core.access_changes.lock().await;
        if self.core.vhost(&vhost).is_some() {
            return Ok(false);
        }
        self.write_meta(vec![StoreOp::PutMeta(MetaRecord::Vhost {
            name: name.to_owned(),
        })])
        .await?;
        self.core.vhost_or_create(&vhost);
        Ok(true)
    }

    /// Sets `user`'s permission on `vhost` (RabbitMQ's `set_permissions`);
    /// every open channel of theirs checks against it from its next
    /// operation.
    pub async fn set_permission(
        &self,
        user: &str,
        vhost: &str,
        permission: Permission,
    ) -> Result<(), AccessError> {
        permission.check()?;
        let _turn = self.core.access_changes.lock().await;
        self.require_user(user)?;
        self.write_meta(vec![StoreOp::PutMeta(permission_record(
            user,
            vhost,
            &permission,
        ))])
        .await?;
        Ok(self.core.permissions.set(user, vhost, permission)?)
    }

    /// Removes `user`'s permission on `vhost` (`clear_permissions`): their
    /// open channels there are refused from their next operation.
    pub async fn clear_permission(&self, user: &str, vhost: &str) -> Result<(), AccessError> {
        let _turn = self.core.access_changes.lock().await;
        self.write_meta(vec![StoreOp::DeleteMeta(MetaKey::Permission {
            user: user.to_owned(),
            vhost: vhost.to_owned(),
        })])
        .await?;
        self.core.permissions.clear(user, vhost);
        Ok(())
    }

    /// Sets `user`'s topic permission on `exchange` in `vhost`
    /// (`set_topic_permissions`).
    pub async fn set_topic_permission(
        &self,
        user: &str,
        vhost: &str,
        exchange: &str,
        permission: TopicPermission,
    ) -> Result<(), AccessError> {
        permission.check(user, vhost)?;
        let _turn = self.core.access_changes.lock().await;
        self.require_user(user)?;
        self.write_meta(vec![StoreOp::PutMeta(MetaRecord::TopicPermission {
            user: user.to_owned(),
            vhost: vhost.to_owned(),
            exchange: exchange.to_owned(),
            write: permission.write.clone(),
            read: permission.read.clone(),
        })])
        .await?;
        Ok(self
            .core
            .permissions
            .set_topic(user, vhost, exchange, permission)?)
    }

    /// Removes `user`'s topic permission on `exchange` in `vhost`
    /// (`clear_topic_permissions`).
    pub async fn clear_topic_permission(
        &self,
        user: &str,
        vhost: &str,
        exchange: &str,
    ) -> Result<(), AccessError> {
        let _turn = self.core.access_changes.lock().await;
        self.write_meta(vec![StoreOp::DeleteMeta(MetaKey::TopicPermission {
            user: user.to_owned(),
            vhost: vhost.to_owned(),
            exchange: exchange.to_owned(),
        })])
        .await?;
        self.core.permissions.clear_topic(user, vhost, exchange);
        Ok(())
    }

    /// Every (user, vhost, permission), ordered by user then vhost.
    pub fn permissions(&self) -> Vec<(String, String, Permission)> {
        self.core.permissions.list()
    }

    /// Every (user, vhost, exchange, topic permission).
    pub fn topic_permissions(&self) -> Vec<(String, String, String, TopicPermission)> {
        self.core.permissions.list_topics()
    }

    /// Whether `user` may log in from `peer` (RabbitMQ's
    /// `loopback_users`: some users only from this host).
    pub fn may_connect_from(&self, user: &str, peer: std::net::SocketAddr) -> bool {
        self.core.users.may_connect_from(user, &peer.to_string())
    }

    /// The broker's users, sorted by name.
    pub fn users(&self) -> Vec<(String, User)> {
        self.core.users.list()
    }

    /// One user.
    pub fn user(&self, name: &str) -> Option<User> {
        self.core.users.get(name)
    }

    /// Whether `user` with `password` is one of the broker's users;
    /// `source` is where the attempt comes from (an `ip:port`, or text
    /// naming the way in), for the fair queueing and slowing of checks
    /// (see `auth`).
    pub async fn authenticate(&self, user: &str, password: &str, source: &str) -> bool {
        self.core
            .users
            .check_password(user, password.as_bytes(), source)
            .await
    }

    /// What the password hashing pool has done: its threads, and the
    /// most checks it ran at once.
    pub fn hash_pool_stats(&self) -> crate::access::hash_pool::HashPoolStats {
        self.core.users.hash_pool_stats()
    }
}
