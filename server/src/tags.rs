//! Users' tags (`administrator`, `monitoring`, `management`,
//! `policymaker`) as RabbitMQ has them: from the config file, definitions
//! and the default guest (`administrator`). The management API decides
//! from them what a caller may see and do (`management::caller`); an
//! export writes them back.
//!
//! Uses nothing of the broker.

use std::collections::BTreeMap;
use std::sync::{Arc, Mutex};

/// Each user's tags, shared by the listeners; an import replaces the tags
/// of the users it names.
#[derive(Debug, Clone, Default)]
pub struct Tags(Arc<Mutex<BTreeMap<String, Vec<String>>>>);

impl Tags {
    fn lock(&self) -> std::sync::MutexGuard<'_, BTreeMap<String, Vec<String>>> {
        self.0.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// Replaces the tags of each user `imported` names.
    pub fn record(&self, imported: &BTreeMap<String, Vec<String>>) {
        let mut tags = self.lock();
        for (user, list) in imported {
            tags.insert(user.clone(), list.clone());
        }
    }

    /// A user's recorded tags.
    pub fn of(&self, user: &str) -> Vec<String> {
        self.lock().get(user).cloned().unwrap_or_default()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn an_import_replaces_the_tags_of_the_users_it_names() {
        let tags = Tags::default();
        tags.record(&BTreeMap::from([
            ("robot".into(), vec!["monitoring".into()]),
            ("tool".into(), vec!["management".into()]),
        ]));
        tags.record(&BTreeMap::from([(
            "robot".into(),
            vec!["administrator".into()],
        )]));
        assert_eq!(tags.of("robot"), vec!["administrator".to_owned()]);
        assert_eq!(tags.of("tool"), vec!["management".to_owned()]);
        assert!(tags.of("guest").is_empty());
    }
}
