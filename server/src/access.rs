//! Users' tags, permissions and topic permissions as RabbitMQ's
//! definitions state them: plain data, parsed from a definitions file
//! (`definitions`), kept so that an export gives back what was imported.
//!
//! Leveret does not enforce any of it yet (every user may use every vhost);
//! the broker's auth module is where enforcement belongs, and it can take
//! these records as they are. Until then an import says so in its
//! warnings, and an export writes the recorded permissions rather than
//! widening them to Leveret's grant-everything: a file that went through
//! Leveret grants nothing more in RabbitMQ than it did before.
//!
//! Uses nothing of the broker; the management listener and the
//! definitions export read it.

use serde_json::{json, Value};
use std::collections::BTreeMap;
use std::sync::{Arc, Mutex};

/// A user's `configure`, `write` and `read` patterns on a vhost.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Permission {
    /// The user.
    pub user: String,
    /// The vhost.
    pub vhost: String,
    /// Regex of the resources the user may declare and delete.
    pub configure: String,
    /// Regex of the resources the user may publish to.
    pub write: String,
    /// Regex of the resources the user may consume from.
    pub read: String,
}

/// A user's topic permission on one topic exchange of a vhost.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct TopicPermission {
    /// The user.
    pub user: String,
    /// The vhost.
    pub vhost: String,
    /// The topic exchange.
    pub exchange: String,
    /// Regex of the routing keys the user may publish with.
    pub write: String,
    /// Regex of the routing keys the user may bind with.
    pub read: String,
}

/// What a definitions file says about access.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct AccessRecords {
    /// Each user's tags (`administrator`, `monitoring`, ...).
    pub tags: BTreeMap<String, Vec<String>>,
    /// Permissions.
    pub permissions: Vec<Permission>,
    /// Topic permissions.
    pub topic_permissions: Vec<TopicPermission>,
}

/// The records, shared by the listeners; an import replaces those of the
/// users and vhosts it names.
#[derive(Debug, Clone, Default)]
pub struct Access(Arc<Mutex<AccessRecords>>);

impl Access {
    fn lock(&self) -> std::sync::MutexGuard<'_, AccessRecords> {
        self.0.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// Adds an import's records: a user's tags, and the permissions of a
    /// (user, vhost) or (user, vhost, exchange), replace those recorded
    /// before.
    pub fn record(&self, imported: &AccessRecords) {
        let mut records = self.lock();
        for (user, tags) in &imported.tags {
            records.tags.insert(user.clone(), tags.clone());
        }
        for new in &imported.permissions {
            records
                .permissions
                .retain(|p| (&p.user, &p.vhost) != (&new.user, &new.vhost));
            records.permissions.push(new.clone());
        }
        for new in &imported.topic_permissions {
            records.topic_permissions.retain(|p| {
                (&p.user, &p.vhost, &p.exchange) != (&new.user, &new.vhost, &new.exchange)
            });
            records.topic_permissions.push(new.clone());
        }
    }

    /// A user's recorded tags.
    pub fn tags(&self, user: &str) -> Vec<String> {
        self.lock().tags.get(user).cloned().unwrap_or_default()
    }

    /// RabbitMQ's `permissions` list for `users` on `vhosts`: the recorded
    /// permissions of the users that have any, and for the others what
    /// Leveret grants them (everything on every vhost).
    pub fn permissions_json(&self, users: &[String], vhosts: &[String]) -> Vec<Value> {
        let records = self.lock();
        let mut list = Vec::new();
        for user in users {
            let recorded: Vec<&Permission> = records
                .permissions
                .iter()
                .filter(|p| &p.user == user && vhosts.contains(&p.vhost))
                .collect();
            if recorded.is_empty() {
                for vhost in vhosts {
                    list.push(json!({"user": user, "vhost": vhost,
                                     "configure": ".*", "write": ".*", "read": ".*"}));
                }
            } else {
                for p in recorded {
                    list.push(json!({"user": p.user, "vhost": p.vhost,
                                     "configure": p.configure, "write": p.write, "read": p.read}));
                }
            }
        }
        list
    }

    /// RabbitMQ's `topic_permissions` list for `users`.
    pub fn topic_permissions_json(&self, users: &[String]) -> Vec<Value> {
        self.lock()
            .topic_permissions
            .iter()
            .filter(|p| users.contains(&p.user))
            .map(|p| {
                json!({"user": p.user, "vhost": p.vhost, "exchange": p.exchange,
                       "write": p.write, "read": p.read})
            })
            .collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn permission(user: &str, vhost: &str, configure: &str) -> Permission {
        Permission {
            user: user.into(),
            vhost: vhost.into(),
            configure: configure.into(),
            write: ".*".into(),
            read: ".*".into(),
        }
    }

    #[test]
    fn an_import_replaces_what_it_names_and_export_never_widens() {
        let access = Access::default();
        access.record(&AccessRecords {
            permissions: vec![permission("robot", "robots", "^a")],
            ..Default::default()
        });
        access.record(&AccessRecords {
            permissions: vec![permission("robot", "robots", "^b")],
            tags: BTreeMap::from([("robot".into(), vec!["monitoring".into()])]),
            ..Default::default()
        });
        let users = vec!["guest".to_owned(), "robot".to_owned()];
        let vhosts = vec!["/".to_owned(), "robots".to_owned()];
        let list = access.permissions_json(&users, &vhosts);
        let robot: Vec<&Value> = list.iter().filter(|p| p["user"] == "robot").collect();
        assert_eq!(robot.len(), 1, "only what was recorded: {list:?}");
        assert_eq!(robot[0]["configure"], "^b");
        assert_eq!(list.iter().filter(|p| p["user"] == "guest").count(), 2);
        assert_eq!(access.tags("robot"), vec!["monitoring".to_owned()]);
        assert!(access.tags("guest").is_empty());
    }
}
