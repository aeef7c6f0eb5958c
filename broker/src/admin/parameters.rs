//! Runtime parameters set and cleared by operators (RabbitMQ's
//! `set_parameter`, `clear_parameter`): each change is written to the store
//! and flushed under the core's access-change lock before it takes effect.
//!
//! Uses the core's [`Parameters`](crate::parameters::Parameters), `store`
//! and `access::lasting`.

use super::Admin;
use crate::access::lasting::AccessError;
use crate::store::{MetaKey, MetaRecord, StoreOp};

impl Admin {
    /// Sets a runtime parameter (RabbitMQ's `set_parameter COMPONENT NAME
    /// VALUE -p VHOST`): on disk before it returns.
    pub async fn set_parameter(
        &self,
        component: &str,
        vhost: &str,
        name: &str,
        value: String,
    ) -> Result<(), AccessError> {
        self.set_parameters(component, vec![(vhost.to_owned(), name.to_owned(), value)])
            .await
    }

    /// Sets runtime parameters of `component`, each (vhost, name, value),
    /// in one store write (an import of many policies): on disk before it
    /// returns, all or none. The MQTT vhost mappings (global
    /// `mqtt_port_to_vhost_mapping`, `mqtt_default_vhosts`) are checked
    /// first: a malformed one is refused, nothing set.
    pub async fn set_parameters(
        &self,
        component: &str,
        parameters: Vec<(String, String, String)>,
    ) -> Result<(), AccessError> {
        if component.is_empty() || parameters.iter().any(|(_, name, _)| name.is_empty()) {
            return Err(AccessError::BadName(
                "a parameter needs a component and a name".to_owned(),
            ));
        }
        #[cfg(feature = "mqtt")]
        for (vhost, name, value) in &parameters {
            if (component, vhost.as_str()) == ("global", "") {
                crate::parameters::check_global_parameter(name, value)
                    .map_err(AccessError::BadValue)?;
            }
        }
        let _turn = self.core.access_changes.lock().await;
        let records = parameters
            .iter()
            .map(|(vhost, name, value)| {
                StoreOp::PutMeta(MetaRecord::Parameter {
                    component: component.to_owned(),
                    vhost: vhost.clone(),
                    name: name.clone(),
                    value: value.clone(),
                })
            })
            .collect();
        self.write_meta(records).await?;
        let mut kept = self.core.parameters.write();
        for (vhost, name, value) in parameters {
            kept.insert((component.to_owned(), vhost, name), value);
        }
        Ok(())
    }

    /// Clears a runtime parameter (`clear_parameter`); false if there was
    /// none.
    pub async fn clear_parameter(
        &self,
        component: &str,
        vhost: &str,
        name: &str,
    ) -> Result<bool, AccessError> {
        let key = (component.to_owned(), vhost.to_owned(), name.to_owned());
        let _turn = self.core.access_changes.lock().await;
        if !self.core.parameters.read().contains_key(&key) {
            return Ok(false);
        }
        self.write_meta(vec![StoreOp::DeleteMeta(MetaKey::Parameter {
            component: key.0.clone(),
            vhost: key.1.clone(),
            name: key.2.clone(),
        })])
        .await?;
        self.core.parameters.write().remove(&key);
        Ok(true)
    }

    /// A component's parameters as (vhost, name, value), in order.
    pub fn parameters(&self, component: &str) -> Vec<(String, String, String)> {
        self.core
            .parameters
            .read()
            .iter()
            .filter(|((c, ..), _)| c == component)
            .map(|((_, vhost, name), value)| (vhost.clone(), name.clone(), value.clone()))
            .collect()
    }
}

#[cfg(test)]
mod tests {
    use crate::store::MemoryStore;
    use crate::Broker;
    use std::sync::Arc;

    async fn parameters_last_until_cleared() {
        let store = Arc::new(MemoryStore::default());
        let broker = Broker::builder()
            .store(store.clone())
            .start()
            .await
            .unwrap();
        let admin = broker.admin();
        admin
            .set_parameter("shovel", "/", "up", r#"{"a":1}"#.into())
            .await
            .unwrap();
        admin
            .set_parameter("shovel", "cell", "up", r#"{"b":2}"#.into())
            .await
            .unwrap();
        admin
            .set_parameter("federation-upstream", "/", "fleet", "{}".into())
            .await
            .unwrap();
        assert!(admin
            .set_parameter("", "/", "x", "{}".into())
            .await
            .is_err());
        broker.shutdown().await;

        let broker = Broker::builder()
            .store(store.clone())
            .start()
            .await
            .unwrap();
        let admin = broker.admin();
        assert_eq!(
            admin.parameters("shovel"),
            [
                ("/".into(), "up".into(), r#"{"a":1}"#.into()),
                ("cell".into(), "up".into(), r#"{"b":2}"#.into())
            ]
        );
        assert_eq!(admin.clear_parameter("shovel", "/", "up").await, Ok(true));
        assert_eq!(admin.clear_parameter("shovel", "/", "up").await, Ok(false));
        broker.shutdown().await;

        let broker = Broker::builder().store(store).start().await.unwrap();
        let admin = broker.admin();
        assert_eq!(admin.parameters("shovel").len(), 1);
        assert_eq!(admin.parameters("federation-upstream").len(), 1);
        broker.shutdown().await;
    }

    #[tokio::test]
    async fn parameters_last_current_thread() {
        parameters_last_until_cleared().await;
    }

    #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
    async fn parameters_last_multi_thread() {
        parameters_last_until_cleared().await;
    }
}
