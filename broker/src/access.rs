//! Users, vhosts and permissions that last, as RabbitMQ's do.
//!
//! At start ([`at_start`]): first what was changed at run time and kept in
//! the store ([`MetaRecord`]s), then what the embedder configured, over
//! it (a configuration names its users afresh at each start, as RabbitMQ's
//! definitions file does at boot). The default `guest` is created only
//! when nothing names a user and the store has never been started before,
//! and is then written to the store: deleting it lasts, as in RabbitMQ.
//!
//! At run time ([`Admin`]'s user, vhost and permission operations): each
//! change is checked, written to the store as one atomic batch and flushed
//! before it takes effect and before the caller hears it is done, all under
//! [`Core::access_changes`](crate::core::Core::access_changes), so the store and memory see the changes in
//! one order. A write that fails changes nothing and is reported.
//!
//! Uses `auth`, `password`, `permissions`, `limits`, `parameters`, `store` and `core`.

use crate::admin::Admin;
use crate::auth::{User, Users, GUEST};
use crate::password::PasswordHash;
use crate::permissions::{PatternError, Permission, Permissions, TopicPermission};
use crate::store::{MetaKey, MetaRecord, Recovered, StoreOp};
use leveret_protocol::ShortStr;

/// What the embedder configured (the builder, the server's config file,
/// `--definitions`).
#[derive(Debug, Default)]
pub struct Configured {
    /// Vhosts.
    pub vhosts: Vec<String>,
    /// Users.
    pub users: Vec<(String, User)>,
    /// (user, vhost, permission).
    pub permissions: Vec<(String, String, Permission)>,
    /// (user, vhost, exchange, topic permission).
    pub topic_permissions: Vec<(String, String, String, TopicPermission)>,
}

/// The users, vhosts and permissions a broker starts with.
#[derive(Debug)]
pub struct AtStart {
    /// Users.
    pub users: Users,
    /// Permissions.
    pub permissions: Permissions,
    /// Vhosts.
    pub vhosts: Vec<String>,
    /// What to write to the store before serving (the default user, the
    /// marker that it was considered), if anything.
    pub seed: Vec<StoreOp>,
}

/// Builds the start's users, vhosts and permissions from the store's
/// records and the configuration (see the module docs); `durable` says
/// whether the broker has a store to seed. A configured pattern the regex
/// engine cannot run is the error; a stored record that no longer applies
/// is logged and skipped.
pub fn at_start(
    configured: Configured,
    recovered: &Recovered,
    durable: bool,
) -> Result<AtStart, PatternError> {
    let users = Users::default();
    let permissions = Permissions::default();
    let mut vhosts = configured.vhosts;
    if vhosts.is_empty() {
        vhosts.push("/".to_owned());
    }
    for record in &recovered.meta {
        restore(record, &users, &permissions, &mut vhosts);
    }
    let mut seed = Vec::new();
    if !recovered.seeded {
        if configured.users.is_empty() {
            // RabbitMQ's default user: an administrator with everything
            // on every vhost.
            let guest = User {
                password_hash: PasswordHash::new("guest"),
                tags: vec!["administrator".to_owned()],
            };
            seed.push(StoreOp::PutMeta(user_record(GUEST, &guest)));
            users.put(GUEST, guest);
            for vhost in &vhosts {
                permissions.set(GUEST, vhost, Permission::full())?;
                seed.push(StoreOp::PutMeta(permission_record(
                    GUEST,
                    vhost,
                    &Permission::full(),
                )));
            }
        }
        seed.push(StoreOp::Seeded);
    }
    if !durable {
        seed.clear();
    }
    for (name, user) in configured.users {
        if users.get(&name).is_some_and(|stored| stored != user) {
            tracing::info!(user = %name, "the configuration's user replaces the one changed at run time");
        }
        users.put(name, user);
    }
    for (user, vhost, permission) in configured.permissions {
        permissions.set(&user, &vhost, permission)?;
    }
    for (user, vhost, exchange, permission) in configured.topic_permissions {
        permissions.set_topic(&user, &vhost, &exchange, permission)?;
    }
    let granted: std::collections::HashSet<String> = permissions
        .list()
        .into_iter()
        .map(|(user, ..)| user)
        .collect();
    for (name, _) in users.list() {
        if !granted.contains(&name) {
            tracing::warn!(user = %name, "user has no permissions: it can log in but open no vhost (RabbitMQ's rule); grant some");
        }
    }
    Ok(AtStart {
        users,
        permissions,
        vhosts,
        seed,
    })
}

/// Applies one stored record; one that no longer applies is logged.
fn restore(
    record: &MetaRecord,
    users: &Users,
    permissions: &Permissions,
    vhosts: &mut Vec<String>,
) {
    let outcome = match record {
        MetaRecord::User {
            name,
            password_hash,
            hashing_algorithm,
            tags,
        } => match PasswordHash::from_rabbitmq(password_hash, hashing_algorithm) {
            Some(hash) => {
                users.put(
                    name.clone(),
                    User {
                        password_hash: hash,
                        tags: tags.clone(),
                    },
                );
                Ok(())
            }
            None => Err(format!(
                "its password hash ({hashing_algorithm}) cannot be read"
            )),
        },
        MetaRecord::Vhost { name } => {
            if !vhosts.contains(name) {
                vhosts.push(name.clone());
            }
            Ok(())
        }
        MetaRecord::Permission {
            user,
            vhost,
            configure,
            write,
            read,
        } => permissions
            .set(
                user,
                vhost,
                Permission {
                    configure: configure.clone(),
                    write: write.clone(),
                    read: read.clone(),
                },
            )
            .map_err(|e| e.to_string()),
        MetaRecord::TopicPermission {
            user,
            vhost,
            exchange,
            write,
            read,
        } => permissions
            .set_topic(
                user,
                vhost,
                exchange,
                TopicPermission {
                    write: write.clone(),
                    read: read.clone(),
                },
            )
            .map_err(|e| e.to_string()),
        // The `parameters` module's and the `mqtt` front end's.
        MetaRecord::Parameter { .. }
        | MetaRecord::Retained { .. }
        | MetaRecord::Unreleased { .. } => Ok(()),
    };
    if let Err(problem) = outcome {
        tracing::error!(record = ?record.key(), %problem, "a stored user, vhost or permission is not restored");
    }
}

fn user_record(name: &str, user: &User) -> MetaRecord {
    let (password_hash, hashing_algorithm) = user.password_hash.to_rabbitmq();
    MetaRecord::User {
        name: name.to_owned(),
        password_hash,
        hashing_algorithm: hashing_algorithm.to_owned(),
        tags: user.tags.clone(),
    }
}

fn permission_record(user: &str, vhost: &str, permission: &Permission) -> MetaRecord {
    MetaRecord::Permission {
        user: user.to_owned(),
        vhost: vhost.to_owned(),
        configure: permission.configure.clone(),
        write: permission.write.clone(),
        read: permission.read.clone(),
    }
}

/// Why a run-time change to users, vhosts, permissions or parameters was
/// refused.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum AccessError {
    /// A pattern the regex engine cannot run.
    #[error(transparent)]
    Pattern(#[from] PatternError),
    /// No user by that name.
    #[error("no user '{0}'")]
    NoSuchUser(String),
    /// A name that cannot be used.
    #[error("{0}")]
    BadName(String),
    /// The store could not write it; nothing changed.
    #[error(
        "the store could not write the change, so nothing changed (the broker's log says why)"
    )]
    Storage,
}

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
    pub fn hash_pool_stats(&self) -> crate::hash_pool::HashPoolStats {
        self.core.users.hash_pool_stats()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::store::{KvOp, KvPair, MemoryStore, Store, StoreError, WriteMode};
    use crate::Broker;
    use std::sync::atomic::{AtomicBool, Ordering};
    use std::sync::Arc;

    /// A memory store whose writes can be made to fail.
    #[derive(Debug, Default)]
    struct Failing {
        inner: MemoryStore,
        fail: AtomicBool,
    }

    impl Store for Failing {
        fn write(&self, ops: Vec<KvOp>, mode: WriteMode) -> Result<(), StoreError> {
            if self.fail.load(Ordering::Relaxed) {
                return Err(StoreError::Engine("disk on fire".into()));
            }
            self.inner.write(ops, mode)
        }
        fn flush(&self) -> Result<(), StoreError> {
            self.inner.flush()
        }
        fn scan(&self) -> Result<Vec<KvPair>, StoreError> {
            self.inner.scan()
        }
    }

    fn recovered(store: &dyn Store) -> Recovered {
        Recovered::from_scan(store.scan().unwrap()).unwrap()
    }

    #[test]
    fn guest_is_seeded_once_and_only_when_no_user_is_configured() {
        let fresh = at_start(Configured::default(), &Recovered::default(), true).unwrap();
        let guest = fresh.users.get(GUEST).expect("guest");
        assert_eq!(guest.tags, ["administrator"]);
        assert!(fresh.permissions.may_open(GUEST, "/"));
        assert!(matches!(fresh.seed.last(), Some(StoreOp::Seeded)));
        assert_eq!(fresh.seed.len(), 3, "guest, its permission, the marker");

        let transient = at_start(Configured::default(), &Recovered::default(), false).unwrap();
        assert!(transient.users.contains(GUEST) && transient.seed.is_empty());

        let configured = Configured {
            users: vec![("robot".into(), User::new(PasswordHash::new("pw")))],
            ..Configured::default()
        };
        let named = at_start(configured, &Recovered::default(), true).unwrap();
        assert!(!named.users.contains(GUEST));
        assert!(matches!(named.seed[..], [StoreOp::Seeded]));

        // Seeded before, guest since deleted: it stays deleted.
        let later = Recovered {
            seeded: true,
            ..Recovered::default()
        };
        let restarted = at_start(Configured::default(), &later, true).unwrap();
        assert!(restarted.users.list().is_empty() && restarted.seed.is_empty());
    }

    #[test]
    fn the_configuration_replaces_what_was_changed_at_run_time() {
        let stored = Recovered {
            seeded: true,
            meta: vec![
                user_record("robot", &User::new(PasswordHash::new("old"))),
                user_record("tool", &User::new(PasswordHash::new("t"))),
                MetaRecord::Vhost {
                    name: "cell".into(),
                },
                permission_record("tool", "cell", &Permission::full()),
                MetaRecord::User {
                    name: "broken".into(),
                    password_hash: "x".into(),
                    hashing_algorithm: "rabbit_password_hashing_md5".into(),
                    tags: Vec::new(),
                },
            ],
            ..Recovered::default()
        };
        let configured = Configured {
            users: vec![("robot".into(), User::new(PasswordHash::new("new")))],
            ..Configured::default()
        };
        let start = at_start(configured, &stored, true).unwrap();
        assert!(start
            .users
            .get("robot")
            .unwrap()
            .password_hash
            .verify(b"new"));
        assert!(start.users.get("tool").unwrap().password_hash.verify(b"t"));
        assert!(
            !start.users.contains("broken"),
            "unreadable hash: logged, skipped"
        );
        assert_eq!(start.vhosts, ["/", "cell"]);
        assert!(start.permissions.may_open("tool", "cell"));
    }

    async fn run_time_changes_last_and_a_failed_write_changes_nothing() {
        let store = Arc::new(Failing::default());
        let broker = Broker::builder()
            .store(store.clone())
            .start()
            .await
            .unwrap();
        let admin = broker.admin();
        let robot = User {
            password_hash: PasswordHash::new("pw"),
            tags: vec!["monitoring".into()],
        };
        assert_eq!(admin.put_user("robot", robot.clone()).await, Ok(true));
        assert_eq!(admin.add_vhost("cell").await, Ok(true));
        admin
            .set_permission("robot", "cell", Permission::full())
            .await
            .unwrap();
        admin
            .set_topic_permission(
                "robot",
                "cell",
                "amq.topic",
                TopicPermission {
                    write: "^robot\\.".into(),
                    read: ".*".into(),
                },
            )
            .await
            .unwrap();
        assert_eq!(
            admin
                .set_permission("nobody", "cell", Permission::full())
                .await,
            Err(AccessError::NoSuchUser("nobody".into()))
        );
        assert!(admin.delete_user(GUEST).await.unwrap());

        store.fail.store(true, Ordering::Relaxed);
        assert_eq!(
            admin
                .put_user("late", User::new(PasswordHash::new("x")))
                .await,
            Err(AccessError::Storage)
        );
        assert!(admin.user("late").is_none(), "refused, so not in effect");
        assert_eq!(admin.delete_user("robot").await, Err(AccessError::Storage));
        assert!(admin.user("robot").is_some());
        store.fail.store(false, Ordering::Relaxed);
        broker.shutdown().await;

        let stored = recovered(store.as_ref());
        assert!(stored.seeded);
        let broker = Broker::builder()
            .store(store.clone())
            .start()
            .await
            .unwrap();
        let admin = broker.admin();
        assert_eq!(admin.user("robot"), Some(robot));
        assert!(admin.user(GUEST).is_none(), "deleting guest lasts");
        assert!(admin.vhosts().contains(&"cell".to_owned()));
        assert_eq!(admin.permissions().len(), 1);
        assert_eq!(admin.topic_permissions().len(), 1);

        assert_eq!(admin.delete_user("robot").await, Ok(true));
        assert_eq!(admin.delete_user("robot").await, Ok(false));
        broker.shutdown().await;
        let stored = recovered(store.as_ref());
        assert!(
            stored
                .meta
                .iter()
                .all(|r| matches!(r, MetaRecord::Vhost { .. })),
            "{:?}",
            stored.meta
        );
    }

    #[tokio::test]
    async fn run_time_changes_last_current_thread() {
        run_time_changes_last_and_a_failed_write_changes_nothing().await;
    }

    #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
    async fn run_time_changes_last_multi_thread() {
        run_time_changes_last_and_a_failed_write_changes_nothing().await;
    }
}
