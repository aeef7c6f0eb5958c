//! Runtime parameters: RabbitMQ's `set_parameter` and `clear_parameter`
//! (a component, a vhost, a name and a JSON value), kept in the store so
//! they last, as RabbitMQ keeps them. The broker interprets only the MQTT
//! vhost mappings (`mqtt::vhosts`); each other component's owner
//! interprets its own (the `leveret` binary runs the `shovel` ones). This module holds them, as the core keeps them; changing them is
//! the operators' (`admin::parameters`), through the same lock and atomic,
//! flushed write as users and permissions.
//!
//! Uses `store`.

use crate::store::{MetaRecord, Recovered};
use std::collections::BTreeMap;
use std::sync::RwLock;

/// (component, vhost, name).
type Key = (String, String, String);

/// The broker's runtime parameters, by component, vhost and name.
#[derive(Debug, Default)]
pub struct Parameters {
    // Held for one lookup or change, never across an await.
    values: RwLock<BTreeMap<Key, String>>,
}

impl Parameters {
    /// The parameters the store kept.
    pub fn recovered(recovered: &Recovered) -> Parameters {
        let values = recovered
            .meta
            .iter()
            .filter_map(|record| match record {
                MetaRecord::Parameter {
                    component,
                    vhost,
                    name,
                    value,
                } => Some((
                    (component.clone(), vhost.clone(), name.clone()),
                    value.clone(),
                )),
                _ => None,
            })
            .collect();
        Parameters {
            values: RwLock::new(values),
        }
    }

    pub(crate) fn write(&self) -> std::sync::RwLockWriteGuard<'_, BTreeMap<Key, String>> {
        self.values.write().unwrap_or_else(|e| e.into_inner())
    }

    pub(crate) fn read(&self) -> std::sync::RwLockReadGuard<'_, BTreeMap<Key, String>> {
        self.values.read().unwrap_or_else(|e| e.into_inner())
    }
}
