//! The binary's running shovels, by name: started from the config file,
//! from `definitions.json` parameters (component `shovel`) and through the
//! management API (`PUT /api/parameters/shovel/VHOST/NAME`), listed by
//! `/api/shovels` and exported back as parameters. Holds the broker weakly
//! (local `amqp://` ends connect in process), so a clean shutdown can take
//! the broker back once the shovels are stopped. Uses the uplink crate.

use leveret_broker::BrokerHandle;
use leveret_uplink::{Shovel, ShovelConfig, ShovelStatus};
use serde_json::Value;
use std::collections::BTreeMap;
use std::sync::{Arc, Mutex, Weak};

/// Shovels run on the broker's runtime, wherever they are started from
/// (the management API has a thread and runtime of its own).
struct Entry {
    vhost: String,
    parameters: Value,
    shovel: Shovel,
}

/// The running shovels; cloning shares them.
#[derive(Clone, Default)]
pub struct Shovels {
    broker: Weak<BrokerHandle>,
    runtime: Option<tokio::runtime::Handle>,
    running: Arc<Mutex<BTreeMap<String, Entry>>>,
}

impl std::fmt::Debug for Shovels {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Shovels").finish_non_exhaustive()
    }
}

/// One shovel as listed.
#[derive(Debug, Clone)]
pub struct Listed {
    /// Its name.
    pub name: String,
    /// The vhost it was defined in.
    pub vhost: String,
    /// Its parameters, as given.
    pub parameters: Value,
    /// What it is doing.
    pub status: ShovelStatus,
}

impl Shovels {
    /// Shovels whose local ends are `broker`, run on the current runtime.
    pub fn new(broker: &Arc<BrokerHandle>) -> Shovels {
        Shovels {
            broker: Arc::downgrade(broker),
            runtime: Some(tokio::runtime::Handle::current()),
            running: Arc::default(),
        }
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, BTreeMap<String, Entry>> {
        self.running.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// Starts (or replaces) the shovel `name` from RabbitMQ's JSON
    /// parameters; an error says what is wrong with them.
    pub async fn start(&self, vhost: &str, name: &str, parameters: Value) -> Result<(), String> {
        let config = ShovelConfig::from_json(&parameters)?;
        let shovel = {
            let broker = self.broker.upgrade();
            let _on_the_broker_runtime = self.runtime.as_ref().map(|r| r.enter());
            Shovel::start(name, config, broker.as_ref())
        };
        let entry = Entry {
            vhost: vhost.to_owned(),
            parameters,
            shovel,
        };
        let replaced = self.lock().insert(name.to_owned(), entry);
        if let Some(old) = replaced {
            old.shovel.stop().await;
        }
        tracing::info!(shovel = %name, "shovel started");
        Ok(())
    }

    /// Stops and forgets the shovel `name`; false if there is none.
    pub async fn remove(&self, name: &str) -> bool {
        let removed = self.lock().remove(name);
        match removed {
            Some(entry) => {
                entry.shovel.stop().await;
                true
            }
            None => false,
        }
    }

    /// Every shovel, by name.
    pub fn list(&self) -> Vec<Listed> {
        self.lock()
            .iter()
            .map(|(name, entry)| Listed {
                name: name.clone(),
                vhost: entry.vhost.clone(),
                parameters: entry.parameters.clone(),
                status: entry.shovel.status(),
            })
            .collect()
    }

    /// Stops them all.
    pub async fn stop_all(&self) {
        let all = std::mem::take(&mut *self.lock());
        for entry in all.into_values() {
            entry.shovel.stop().await;
        }
    }
}
