//! Users, vhosts and permissions that last, as RabbitMQ's do.
//!
//! At start ([`at_start`]): first what was changed at run time and kept in
//! the store ([`MetaRecord`]s), then what the embedder configured, over
//! it (a configuration names its users afresh at each start, as RabbitMQ's
//! definitions file does at boot). The default `guest` is created only
//! when nothing names a user and the store has never been started before,
//! and is then written to the store: deleting it lasts, as in RabbitMQ.
//!
//! At run time the operator layer changes them (`admin::access`), writing
//! the records this module defines ([`user_record`],
//! [`permission_record`]) and answering with its [`AccessError`].
//!
//! Uses `auth`, `password`, `permissions` and `store`; nothing of the
//! operator layer.

use crate::access::auth::{User, Users, GUEST};
use crate::access::password::PasswordHash;
use crate::access::permissions::{PatternError, Permission, Permissions, TopicPermission};
use crate::store::{MetaRecord, Recovered, StoreOp};

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
        | MetaRecord::Unreleased { .. }
        | MetaRecord::SharedSubscription { .. } => Ok(()),
    };
    if let Err(problem) = outcome {
        tracing::error!(record = ?record.key(), %problem, "a stored user, vhost or permission is not restored");
    }
}

pub(crate) fn user_record(name: &str, user: &User) -> MetaRecord {
    let (password_hash, hashing_algorithm) = user.password_hash.to_rabbitmq();
    MetaRecord::User {
        name: name.to_owned(),
        password_hash,
        hashing_algorithm: hashing_algorithm.to_owned(),
        tags: user.tags.clone(),
    }
}

pub(crate) fn permission_record(user: &str, vhost: &str, permission: &Permission) -> MetaRecord {
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
    /// A runtime parameter value its owner cannot use (the reason).
    #[error("{0}")]
    BadValue(String),
    /// The store could not write it; nothing changed.
    #[error(
        "the store could not write the change, so nothing changed (the broker's log says why)"
    )]
    Storage,
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
