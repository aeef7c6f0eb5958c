//! Deleting a vhost (RabbitMQ's `delete_vhost`, `DELETE /api/vhosts/NAME`):
//! its connections are closed with 320 CONNECTION_FORCED and RabbitMQ's
//! text, everything in it (queues and their messages, exchanges,
//! bindings) is deleted in time slices, and its permissions, topic
//! permissions, runtime parameters and limits go with it, on disk before the caller
//! hears it is done.
//!
//! Uses the core, `vhost`, `slice`, `store` and `access::lasting`'s meta writes.

use super::Admin;
use crate::access::lasting::AccessError;
use crate::slice::{Progress, Slice};
use crate::store::{MetaKey, StoreOp};
use leveret_protocol::ShortStr;

impl Admin {
    /// Deletes the vhost called `name`; false if there is none. From the
    /// moment it starts, connection.open to the vhost is refused and
    /// nothing can be declared in it; its open connections are told to
    /// close ("vhost 'NAME' is deleted"). Its queues and exchanges are
    /// deleted a slice of work at a time with a yield between slices, so a
    /// vhost of any size holds no runtime thread for long. If the final
    /// write fails, the objects are gone but the vhost's record, its
    /// permissions and parameters may come back at the next start.
    pub async fn delete_vhost(&self, name: &str) -> Result<bool, AccessError> {
        let Ok(key) = ShortStr::try_from(name) else {
            return Ok(false);
        };
        let _turn = self.core.access_changes.lock().await;
        let Some(vhost) = self.core.remove_vhost(&key) else {
            return Ok(false);
        };
        let reason = format!("vhost '{name}' is deleted");
        let mut closed = 0;
        for connection in self.core.registry.connections() {
            let in_vhost = connection
                .opened
                .get()
                .is_some_and(|opened| opened.vhost == name);
            if in_vhost && self.core.registry.close(connection.id, &reason) {
                closed += 1;
            }
        }
        let mut slice = Slice::start();
        while vhost.delete_everything_step(&mut slice) == Progress::More {
            tokio::task::yield_now().await;
            slice = Slice::start();
        }
        let permissions = &self.core.permissions;
        let granted: Vec<String> = permissions
            .list()
            .into_iter()
            .filter(|(_, vhost, _)| vhost == name)
            .map(|(user, ..)| user)
            .collect();
        let topics: Vec<(String, String)> = permissions
            .list_topics()
            .into_iter()
            .filter(|(_, vhost, ..)| vhost == name)
            .map(|(user, _, exchange, _)| (user, exchange))
            .collect();
        let parameters: Vec<(String, String, String)> = self
            .core
            .parameters
            .read()
            .keys()
            .filter(|(_, vhost, _)| vhost == name)
            .cloned()
            .collect();
        let mut ops: Vec<StoreOp> = granted
            .iter()
            .map(|user| {
                StoreOp::DeleteMeta(MetaKey::Permission {
                    user: user.clone(),
                    vhost: name.to_owned(),
                })
            })
            .collect();
        ops.extend(topics.iter().map(|(user, exchange)| {
            StoreOp::DeleteMeta(MetaKey::TopicPermission {
                user: user.clone(),
                vhost: name.to_owned(),
                exchange: exchange.clone(),
            })
        }));
        ops.extend(parameters.iter().map(|(component, vhost, name)| {
            StoreOp::DeleteMeta(MetaKey::Parameter {
                component: component.clone(),
                vhost: vhost.clone(),
                name: name.clone(),
            })
        }));
        ops.push(StoreOp::DeleteMeta(MetaKey::Vhost(name.to_owned())));
        // Submitted after every queue and exchange deletion above, and the
        // store writes in order: on disk, all of it is.
        self.write_meta(ops).await?;
        for user in &granted {
            permissions.clear(user, name);
        }
        for (user, exchange) in &topics {
            permissions.clear_topic(user, name, exchange);
        }
        {
            let mut values = self.core.parameters.write();
            for key in &parameters {
                values.remove(key);
            }
        }
        // Its limits were among its parameters.
        self.core.limit_tables.set_vhost(name, None);
        tracing::info!(vhost = %name, connections = closed, "deleted vhost '{name}' and everything in it ({closed} connections closed)");
        Ok(true)
    }
}
