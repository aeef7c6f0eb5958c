//! Runtime parameters: RabbitMQ's `set_parameter` and `clear_parameter`
//! (a component, a vhost, a name and a JSON value), kept in the store so
//! they last, as RabbitMQ keeps them. The broker interprets only the MQTT
//! vhost mappings (`mqtt::vhosts` reads them; their values are checked
//! here, [`check_global_parameter`]); each other component's owner
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

#[cfg(feature = "mqtt")]
mod mqtt_mappings {
    use serde_json::Value;

    /// RabbitMQ's global parameter mapping listener ports to vhosts.
    pub const PORT_MAPPING: &str = "mqtt_port_to_vhost_mapping";
    /// RabbitMQ's global parameter mapping certificate subject DNs to vhosts.
    pub const CERTIFICATE_MAPPING: &str = "mqtt_default_vhosts";
    /// The largest mapping value taken (it is read at each CONNECT).
    const MAX_VALUE: usize = 64 * 1024;
    /// The longest vhost name (an AMQP short string).
    const MAX_VHOST: usize = 255;

    /// Checks a value for global parameter `name` (RabbitMQ's
    /// `set_global_parameter`): a mapping must be a JSON object of non-empty
    /// strings to vhost names (port numbers 1-65535 as the keys of the port
    /// mapping); other global parameters are their owners'. The reason
    /// otherwise.
    pub fn check_global_parameter(name: &str, value: &str) -> Result<(), String> {
        if ![PORT_MAPPING, CERTIFICATE_MAPPING].contains(&name) {
            return Ok(());
        }
        if value.len() > MAX_VALUE {
            return Err(format!("{name} is longer than {MAX_VALUE} bytes"));
        }
        let parsed: Value =
            serde_json::from_str(value).map_err(|e| format!("{name} is not JSON: {e}"))?;
        let object = parsed
            .as_object()
            .ok_or_else(|| format!("{name} must be a JSON object"))?;
        for (key, target) in object {
            if key.is_empty() {
                return Err(format!("{name}: a key cannot be empty"));
            }
            if name == PORT_MAPPING
                && !key
                    .parse::<u16>()
                    .is_ok_and(|port| port > 0 && port.to_string() == *key)
            {
                return Err(format!(
                    "{name}: '{key}' is not a port number (1-65535, in decimal)"
                ));
            }
            match target.as_str() {
                Some(vhost) if !vhost.is_empty() && vhost.len() <= MAX_VHOST => {}
                _ => {
                    return Err(format!(
                        "{name}: the vhost of '{key}' must be a vhost name (a string of 1 to {MAX_VHOST} bytes)"
                    ))
                }
            }
        }
        Ok(())
    }

    #[cfg(test)]
    mod tests {
        use super::*;

        #[test]
        fn mappings_are_checked_when_set() {
            let port = |v: &str| check_global_parameter(PORT_MAPPING, v);
            let certificate = |v: &str| check_global_parameter(CERTIFICATE_MAPPING, v);
            assert_eq!(port(r#"{"1883": "robots", "1884": "/"}"#), Ok(()));
            assert_eq!(port("{}"), Ok(()));
            assert!(port(r#"{"http": "robots"}"#).unwrap_err().contains("port"));
            assert!(port(r#"{"0": "robots"}"#).is_err());
            // Spellings a listener's port never matches.
            assert!(port(r#"{"01883": "robots"}"#).is_err());
            assert!(port(r#"{"+1883": "robots"}"#).is_err());
            assert!(port(r#"{"65536": "robots"}"#).is_err());
            assert!(port(r#"{"1883": 5}"#).unwrap_err().contains("vhost"));
            assert!(port(r#"{"1883": ""}"#).is_err());
            assert!(port(&format!(r#"{{"1883": "{}"}}"#, "v".repeat(256))).is_err());
            assert!(port(r#"["robots"]"#).unwrap_err().contains("object"));
            assert!(port("{").unwrap_err().contains("JSON"));
            assert_eq!(certificate(r#"{"O=client,CN=guest": "robots"}"#), Ok(()));
            assert!(certificate(r#"{"": "robots"}"#).is_err());
            assert!(certificate(r#"{"CN=a": null}"#).is_err());
            assert!(certificate(&format!(r#""{}""#, "x".repeat(MAX_VALUE))).is_err());
            // Other parameters are their owners'.
            assert_eq!(check_global_parameter("cluster_name", "{"), Ok(()));
        }
    }
}

#[cfg(feature = "mqtt")]
pub use mqtt_mappings::{check_global_parameter, CERTIFICATE_MAPPING, PORT_MAPPING};
