//! The binary's federation: upstreams (RabbitMQ's `federation-upstream`
//! parameters) and the policies that federate local exchanges to them
//! (RabbitMQ's policies with a `federation-upstream` or
//! `federation-upstream-set` key), from the config file, definitions and
//! the management API; and the links they call for, one per (local
//! exchange, upstream), kept in step with them and with the local
//! exchanges (a policy also covers exchanges declared later) once a
//! second and after every change.
//!
//! Upstreams declared by a definitions import or the API are runtime
//! parameters in the broker's store (component `federation-upstream`, as
//! RabbitMQ keeps them), so they outlast restarts; the config file's are
//! the config file's. Policies are the broker's (`crate::policies` sets
//! them): the federation reads the one that applies to each exchange.
//!
//! Links run on the broker's runtime, wherever a change comes from. Uses
//! the uplink crate and the broker's `Admin`.

use crate::uplink::DeclareError;
use leveret_broker::{AccessError, Admin, BrokerHandle};
use leveret_uplink::{FederationLink, LinkStatus, LocalExchange, UpstreamConfig};
use serde_json::Value;
use std::collections::BTreeMap;
use std::sync::{Arc, Mutex, Weak};
use std::time::Duration;

/// The runtime parameters' component for upstreams.
pub const UPSTREAM_COMPONENT: &str = "federation-upstream";
/// How often links are compared with the policies and exchanges.
const RECONCILE: Duration = Duration::from_secs(1);

/// A declaration as given, and read.
struct Declared<T> {
    value: Value,
    parsed: T,
}

/// A running link and the upstream parameters it runs with.
struct Running {
    config: UpstreamConfig,
    link: FederationLink,
}

/// (vhost, local exchange, upstream).
type LinkKey = (String, String, String);

#[derive(Default)]
struct State {
    upstreams: BTreeMap<(String, String), Declared<UpstreamConfig>>,
    links: BTreeMap<LinkKey, Running>,
}

/// One link as listed (RabbitMQ's `/api/federation-links`).
#[derive(Debug, Clone)]
pub struct LinkListed {
    /// Vhost.
    pub vhost: String,
    /// The local exchange.
    pub exchange: String,
    /// The upstream's name.
    pub upstream: String,
    /// The upstream exchange.
    pub upstream_exchange: String,
    /// What it is doing.
    pub status: LinkStatus,
}

/// The upstreams, policies and links; cloning shares them.
#[derive(Clone)]
pub struct Federation {
    broker: Weak<BrokerHandle>,
    admin: Admin,
    runtime: tokio::runtime::Handle,
    node: String,
    state: Arc<Mutex<State>>,
    /// Held by one reconcile at a time.
    reconciling: Arc<tokio::sync::Mutex<()>>,
}

impl std::fmt::Debug for Federation {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Federation").finish_non_exhaustive()
    }
}

impl Federation {
    /// Federation on `broker` (links run on the current runtime), this
    /// node named `node`.
    pub fn new(broker: &Arc<BrokerHandle>, node: String) -> Federation {
        Federation {
            broker: Arc::downgrade(broker),
            admin: broker.admin(),
            runtime: tokio::runtime::Handle::current(),
            node,
            state: Arc::default(),
            reconciling: Arc::default(),
        }
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, State> {
        self.state.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// Keeps `value` as the runtime parameter `component` `name` of
    /// `vhost` when `store` says so (the API's and imports'; the config
    /// file's last while the broker runs).
    async fn keep(
        &self,
        component: &str,
        vhost: &str,
        name: &str,
        value: &Value,
        store: bool,
    ) -> Result<(), DeclareError> {
        if store {
            self.admin
                .set_parameter(component, vhost, name, value.to_string())
                .await?;
        }
        Ok(())
    }

    /// Clears the stored parameter and takes the declaration out of
    /// `state` with `remove`; whether either existed.
    async fn forget(
        &self,
        component: &str,
        vhost: &str,
        name: &str,
        remove: impl FnOnce(&mut State, &(String, String)) -> bool,
    ) -> Result<bool, AccessError> {
        let stored = self.admin.clear_parameter(component, vhost, name).await?;
        let removed = remove(&mut self.lock(), &(vhost.to_owned(), name.to_owned()));
        self.reconcile().await;
        Ok(stored || removed)
    }

    /// Sets the upstream `name` of `vhost`; `store` keeps it as a runtime
    /// parameter.
    pub async fn set_upstream(
        &self,
        vhost: &str,
        name: &str,
        value: Value,
        store: bool,
    ) -> Result<(), DeclareError> {
        let parsed = UpstreamConfig::from_json(&value).map_err(DeclareError::Invalid)?;
        self.keep(UPSTREAM_COMPONENT, vhost, name, &value, store)
            .await?;
        self.lock().upstreams.insert(
            (vhost.to_owned(), name.to_owned()),
            Declared { value, parsed },
        );
        self.reconcile().await;
        Ok(())
    }

    /// Removes an upstream (its links stop; their upstream queues stay,
    /// as RabbitMQ leaves them); false if there was none.
    pub async fn delete_upstream(&self, vhost: &str, name: &str) -> Result<bool, AccessError> {
        self.forget(UPSTREAM_COMPONENT, vhost, name, |state, key| {
            state.upstreams.remove(key).is_some()
        })
        .await
    }

    /// Loads the upstreams the broker's store kept; one that no longer
    /// reads is logged and left out.
    pub async fn start_stored(&self) {
        for (vhost, name, text) in self.admin.parameters(UPSTREAM_COMPONENT) {
            let outcome = match serde_json::from_str(&text) {
                Ok(value) => self.set_upstream(&vhost, &name, value, false).await,
                Err(e) => Err(DeclareError::Invalid(e.to_string())),
            };
            if let Err(e) = outcome {
                tracing::error!(component = UPSTREAM_COMPONENT, %name, %vhost, error = %e, "a stored parameter is not applied");
            }
        }
    }

    /// Keeps the links in step once a second (exchanges a policy matches
    /// come and go), on the broker's runtime, until the broker is gone.
    pub fn keep_in_step(&self) {
        let federation = self.clone();
        self.runtime.spawn(async move {
            let mut tick = tokio::time::interval(RECONCILE);
            tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
            loop {
                tick.tick().await;
                if federation.broker.strong_count() == 0 {
                    return;
                }
                federation.reconcile().await;
            }
        });
    }

    /// The links the policies call for: each local exchange whose policy
    /// (the one that applies, as in RabbitMQ) has a federation key, with
    /// each upstream it names.
    fn wanted(&self) -> BTreeMap<LinkKey, UpstreamConfig> {
        let upstreams: Vec<(String, String, UpstreamConfig)> = self
            .lock()
            .upstreams
            .iter()
            .map(|((vhost, name), u)| (vhost.clone(), name.clone(), u.parsed.clone()))
            .collect();
        let mut vhosts: Vec<String> = upstreams.iter().map(|(vhost, ..)| vhost.clone()).collect();
        vhosts.dedup();
        let mut wanted = BTreeMap::new();
        for vhost in vhosts {
            for exchange in self.admin.exchange_names(&vhost) {
                if exchange.is_empty() || exchange.starts_with("amq.") {
                    continue;
                }
                let applied = self.admin.exchange_policies(&vhost, &exchange);
                let Some(policy) = applied.policy else {
                    continue;
                };
                let definition = &policy.definition;
                for (v, name, config) in &upstreams {
                    let chosen = definition.federation_upstream.as_deref() == Some(name.as_str())
                        || definition.federation_upstream_set.as_deref() == Some("all");
                    if *v == vhost && chosen {
                        wanted.insert(
                            (vhost.clone(), exchange.clone(), name.clone()),
                            config.clone(),
                        );
                    }
                }
            }
        }
        wanted
    }

    /// Starts the links wanted and not running, restarts those whose
    /// upstream changed, and stops those no longer wanted.
    pub async fn reconcile(&self) {
        let _one_at_a_time = self.reconciling.lock().await;
        // Listing every exchange of a vhost and matching it is work that
        // grows with the exchanges: off the broker's thread.
        let federation = self.clone();
        let Ok(wanted) = tokio::task::spawn_blocking(move || federation.wanted()).await else {
            return;
        };
        let stale: Vec<Running> = {
            let mut state = self.lock();
            let keys: Vec<LinkKey> = state
                .links
                .iter()
                .filter(|(key, running)| wanted.get(*key) != Some(&running.config))
                .map(|(key, _)| key.clone())
                .collect();
            keys.iter()
                .filter_map(|key| state.links.remove(key))
                .collect()
        };
        for running in stale {
            running.link.stop().await;
        }
        let Some(broker) = self.broker.upgrade() else {
            return;
        };
        let mut state = self.lock();
        for ((vhost, exchange, upstream), config) in wanted {
            let key = (vhost.clone(), exchange.clone(), upstream.clone());
            if state.links.contains_key(&key) {
                continue;
            }
            let local = LocalExchange {
                vhost,
                exchange,
                node: self.node.clone(),
            };
            let link = {
                let _on_the_broker_runtime = self.runtime.enter();
                FederationLink::start(&upstream, config.clone(), local, &broker)
            };
            tracing::info!(upstream = %key.2, exchange = %key.1, vhost = %key.0, "federation link started");
            state.links.insert(key, Running { config, link });
        }
    }

    /// Every link.
    pub fn links(&self) -> Vec<LinkListed> {
        self.lock()
            .links
            .iter()
            .map(|((vhost, exchange, upstream), running)| LinkListed {
                vhost: vhost.clone(),
                exchange: exchange.clone(),
                upstream: upstream.clone(),
                upstream_exchange: running
                    .config
                    .exchange
                    .clone()
                    .unwrap_or_else(|| exchange.clone()),
                status: running.link.status(),
            })
            .collect()
    }

    /// Every upstream as (vhost, name, value given).
    pub fn upstreams(&self) -> Vec<(String, String, Value)> {
        self.lock()
            .upstreams
            .iter()
            .map(|((vhost, name), d)| (vhost.clone(), name.clone(), d.value.clone()))
            .collect()
    }

    /// Stops every link.
    pub async fn stop_all(&self) {
        let links = std::mem::take(&mut self.lock().links);
        for running in links.into_values() {
            running.link.stop().await;
        }
    }
}
