//! The binary's running shovels, by vhost and name: started from the
//! config file, from `definitions.json` parameters (component `shovel`),
//! through the management API (`PUT /api/parameters/shovel/VHOST/NAME`)
//! and, at start, from the parameters the broker's store kept; listed by
//! `/api/shovels` and exported back as parameters. Shovels declared by a
//! definitions import or the API are runtime parameters of the broker,
//! written to its store before they start, so they outlast a restart as
//! RabbitMQ's do; the config file's are the config file's. Holds the broker
//! weakly (local `amqp://` ends connect in process), so a clean shutdown
//! can take the broker back once the shovels are stopped. Uses the uplink
//! crate and the broker's `Admin`.

use leveret_broker::{AccessError, Admin, BrokerHandle};
use leveret_uplink::{Shovel, ShovelConfig, ShovelStatus};
use serde_json::Value;
use std::collections::BTreeMap;
use std::sync::{Arc, Mutex, Weak};

/// The binary's links to other brokers: shovels and federation
/// (`crate::federation`).
#[derive(Debug, Clone)]
pub struct Links {
    /// The shovels.
    pub shovels: Shovels,
    /// The federation upstreams, policies and links.
    pub federation: crate::federation::Federation,
}

impl Links {
    /// Stops every shovel and federation link.
    pub async fn stop_all(&self) {
        self.shovels.stop_all().await;
        self.federation.stop_all().await;
    }
}

/// The runtime parameters' component for shovels.
pub const SHOVEL_COMPONENT: &str = "shovel";

/// Shovels run on the broker's runtime, wherever they are started from
/// (the management API has a thread and runtime of its own).
struct Entry {
    /// Tells this entry from a later one of the same name.
    id: u64,
    parameters: Value,
    shovel: Shovel,
}

/// The running shovels by (vhost, name); cloning shares them.
#[derive(Clone)]
pub struct Shovels {
    broker: Weak<BrokerHandle>,
    admin: Admin,
    runtime: tokio::runtime::Handle,
    running: Arc<Mutex<BTreeMap<(String, String), Entry>>>,
    next_id: Arc<std::sync::atomic::AtomicU64>,
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

/// Why a shovel was not declared.
#[derive(Debug, thiserror::Error)]
pub enum DeclareError {
    /// Its parameters are not usable.
    #[error("{0}")]
    Invalid(String),
    /// The store did not take it.
    #[error(transparent)]
    Storage(#[from] AccessError),
}

impl Shovels {
    /// Shovels whose local ends are `broker`, run on the current runtime.
    pub fn new(broker: &Arc<BrokerHandle>) -> Shovels {
        Shovels {
            broker: Arc::downgrade(broker),
            admin: broker.admin(),
            runtime: tokio::runtime::Handle::current(),
            running: Arc::default(),
            next_id: Arc::default(),
        }
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, BTreeMap<(String, String), Entry>> {
        self.running.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// Starts (or replaces) the shovel `name` of `vhost` from RabbitMQ's
    /// JSON parameters without storing them (the config file's); an error
    /// says what is wrong with them.
    pub async fn start(&self, vhost: &str, name: &str, parameters: Value) -> Result<(), String> {
        let config = ShovelConfig::from_json(&parameters)?;
        let shovel = {
            let broker = self.broker.upgrade();
            let _on_the_broker_runtime = self.runtime.enter();
            Shovel::start(name, config, broker.as_ref())
        };
        let id = self
            .next_id
            .fetch_add(1, std::sync::atomic::Ordering::Relaxed);
        self.delete_when_completed(vhost, name, id, shovel.watch());
        let entry = Entry {
            id,
            parameters,
            shovel,
        };
        let replaced = self
            .lock()
            .insert((vhost.to_owned(), name.to_owned()), entry);
        if let Some(old) = replaced {
            old.shovel.stop().await;
        }
        tracing::info!(shovel = %name, %vhost, "shovel started");
        Ok(())
    }

    /// Deletes shovel `id` once it has forwarded all `src-delete-after`
    /// asked for, as RabbitMQ deletes such a shovel (and its parameter).
    fn delete_when_completed(
        &self,
        vhost: &str,
        name: &str,
        id: u64,
        mut status: tokio::sync::watch::Receiver<ShovelStatus>,
    ) {
        let shovels = self.clone();
        let key = (vhost.to_owned(), name.to_owned());
        self.runtime.spawn(async move {
            // Ends with an error when the shovel is stopped first.
            if status.wait_for(|s| s.completed).await.is_err() {
                return;
            }
            let current = shovels.lock().get(&key).is_some_and(|e| e.id == id);
            if current {
                if let Err(e) = shovels.delete(&key.0, &key.1).await {
                    tracing::error!(shovel = %key.1, vhost = %key.0, error = %e, "a completed shovel could not be deleted");
                }
            }
        });
    }

    /// Declares a shovel as a runtime parameter: checked, written to the
    /// broker's store, then started (replacing one of the same name).
    pub async fn declare(
        &self,
        vhost: &str,
        name: &str,
        parameters: Value,
    ) -> Result<(), DeclareError> {
        if let Err(reason) = ShovelConfig::from_json(&parameters) {
            tracing::warn!(shovel = %name, %vhost, %reason, "shovel declaration refused");
            return Err(DeclareError::Invalid(reason));
        }
        self.admin
            .set_parameter(SHOVEL_COMPONENT, vhost, name, parameters.to_string())
            .await?;
        self.start(vhost, name, parameters)
            .await
            .map_err(DeclareError::Invalid)
    }

    /// Starts the shovels the broker's store kept; one whose parameters
    /// no longer read is logged and left stopped.
    pub async fn start_stored(&self) {
        for (vhost, name, text) in self.admin.parameters(SHOVEL_COMPONENT) {
            let parameters = serde_json::from_str(&text).map_err(|e| e.to_string());
            if let Err(e) = match parameters {
                Ok(parameters) => self.start(&vhost, &name, parameters).await,
                Err(e) => Err(e),
            } {
                tracing::error!(shovel = %name, %vhost, error = %e, "a stored shovel cannot start");
            }
        }
    }

    /// Stops and forgets the shovel `name` of `vhost`, and its stored
    /// parameter; false if there is none.
    pub async fn delete(&self, vhost: &str, name: &str) -> Result<bool, AccessError> {
        let stored = self
            .admin
            .clear_parameter(SHOVEL_COMPONENT, vhost, name)
            .await?;
        let removed = self.lock().remove(&(vhost.to_owned(), name.to_owned()));
        match removed {
            Some(entry) => {
                entry.shovel.stop().await;
                Ok(true)
            }
            None => Ok(stored),
        }
    }

    /// Every shovel, by vhost and name.
    pub fn list(&self) -> Vec<Listed> {
        self.lock()
            .iter()
            .map(|((vhost, name), entry)| Listed {
                name: name.clone(),
                vhost: vhost.clone(),
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
