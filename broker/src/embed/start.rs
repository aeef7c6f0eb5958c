//! Starting a broker, a function a step, in this order: the TLS context
//! (bad certificates refuse the start before anything is opened); the
//! store opened, checked and read (`open_store`); the users, vhosts and
//! permissions settled from the builder's and the store's, and this start
//! recorded (`settle_access`); the core; the durable exchanges, queues,
//! bindings and messages rebuilt (`rebuild_durable_state`, `recovery`'s
//! job); the AMQP and MQTT listeners bound (`bind_amqp_listeners`,
//! `bind_mqtt_listeners`), accepting at once or once told
//! ([`BrokerBuilder::hold_listeners`]); and the background tasks
//! (`spawn_background_tasks`: the TTL and expiry sweeper, the memory and
//! disk alarms' watches, the busy poller). Uses the builder's settings
//! (`mod`), the core, `access`, `recovery`, the store, and the accept
//! loops of `server` and `mqtt`; gives the running broker to `handle`.

use super::handle::BrokerHandle;
#[cfg(feature = "persistence")]
use super::handle::CleanShutdown;
use super::{BrokerBuilder, StartError, Storage};
use crate::access::auth::User;
use crate::access::lasting::{AtStart, Configured};
#[cfg(feature = "persistence")]
use crate::alarm::disk::DirFreeSpace;
use crate::alarm::disk::FreeSpace;
use crate::busy_poll::BusyPoll;
use crate::core::{Core, CoreOptions};
#[cfg(not(feature = "tls"))]
use crate::server::TlsContext;
#[cfg(feature = "persistence")]
use crate::store::open_checked;
use crate::store::{Persistence, Recovered, StoreError};
#[cfg(feature = "tls")]
use crate::tls::{TlsContext, TlsError, TlsOptions};
use std::collections::HashMap;
use std::net::SocketAddr;
use std::sync::Arc;
use std::time::{Duration, Instant};
use tokio::net::TcpListener;
use tokio::sync::{mpsc, watch};
use tokio::task::JoinHandle;

/// How often message TTLs and queue x-expires are checked.
const SWEEP_PERIOD: Duration = Duration::from_millis(50);
/// The product name announced in connection.start unless the builder sets one.
const DEFAULT_PRODUCT: &str = "Leveret";

impl BrokerBuilder {
    /// Binds the listeners and starts serving (with
    /// [`Self::hold_listeners`], once told to).
    pub async fn start(self) -> Result<BrokerHandle, StartError> {
        #[cfg(feature = "tls")]
        let tls = {
            let no_tls_listeners = !self.has_tls_listeners();
            tls_context(self.tls, no_tls_listeners)?
        };
        // Recovery time includes opening the store (sled replays its log, the
        // message log is read).
        let started = Instant::now();
        let free_space = free_space_probe(self.free_space, &self.storage);
        #[cfg(feature = "persistence")]
        let store = open_store(self.storage, self.recover)?;
        #[cfg(not(feature = "persistence"))]
        let store = open_store(self.storage)?;
        let configured = Configured {
            vhosts: self.vhosts,
            users: with_tags(self.users, &self.user_tags),
            permissions: self.permissions,
            topic_permissions: self.topic_permissions,
        };
        let access =
            settle_access(configured, &store.recovered, store.persistence.as_deref()).await?;
        let mut users = access.users;
        if let Some(names) = self.loopback_users {
            users.set_loopback_only(names);
        }
        let busy_poll = busy_poll_state(self.busy_poll);
        let core = Core::new(CoreOptions {
            vhosts: access.vhosts,
            users,
            permissions: access.permissions,
            parameters: crate::parameters::Parameters::recovered(&store.recovered),
            limits: self.limits,
            persistence: store.persistence,
            product: self.product.unwrap_or_else(|| DEFAULT_PRODUCT.to_owned()),
            busy_poll: busy_poll.clone(),
        });
        #[cfg(feature = "mqtt")]
        let mqtt_shared = Arc::new(crate::mqtt::Shared::new(
            &core,
            &store.recovered.meta,
            self.mqtt_options,
            self.mqtt_retained_limits,
        ));
        if let Err(problem) = rebuild_durable_state(&core, store.recovered, started) {
            // A damaged stream refuses the start as a damaged store does.
            #[cfg(feature = "persistence")]
            if let Some(clean) = &store.clean_shutdown {
                return Err(StartError::Storage(StoreError::Damaged {
                    path: clean.dir.clone(),
                    problem,
                }));
            }
            return Err(StartError::Storage(StoreError::Engine(problem.into())));
        }
        // Before the vhosts' sweeper starts: a stale x-expires could expire
        // a group's queue first, and a session's is capped from the start.
        #[cfg(feature = "mqtt")]
        mqtt_shared.reconcile_queues(&core).await;
        let (alive, finished) = mpsc::channel(1);
        let (open, opened) = watch::channel(!self.held);
        let mut listeners = Listeners {
            core: &core,
            opened,
            alive: &alive,
            tasks: Vec::new(),
        };
        let amqp = self.listen.into_iter().map(|addr| (addr, None));
        #[cfg(feature = "tls")]
        let amqp = amqp.chain(self.tls_listen.into_iter().map(|addr| (addr, tls.clone())));
        let (local_addrs, tls_addrs) = listeners.bind_amqp_listeners(amqp).await?;
        // TCP, TLS and WebSocket listeners' bound addresses.
        #[cfg(feature = "mqtt")]
        let mqtt_addrs = {
            use crate::mqtt::Transport;
            let mqtt = self.mqtt_listen.into_iter().map(|a| (a, Transport::Tcp));
            #[cfg(feature = "tls")]
            let mqtt = mqtt.chain(self.mqtts_listen.into_iter().filter_map(|a| {
                // `tls` is set whenever there are TLS listeners (above).
                tls.clone().map(|tls| (a, Transport::Tls(tls)))
            }));
            let mqtt = mqtt.chain(
                self.web_mqtt_listen
                    .into_iter()
                    .map(|a| (a, Transport::WebSocket)),
            );
            listeners.bind_mqtt_listeners(mqtt, &mqtt_shared).await?
        };
        #[cfg(not(feature = "mqtt"))]
        let mqtt_addrs = Default::default();
        let mut tasks = listeners.tasks;
        spawn_background_tasks(&core, free_space, busy_poll, &mut tasks);
        Ok(BrokerHandle {
            core,
            open,
            local_addrs,
            tls_addrs,
            mqtt_addrs,
            #[cfg(feature = "tls")]
            tls,
            tasks,
            alive: Some(alive),
            finished,
            #[cfg(feature = "persistence")]
            clean_shutdown: store.clean_shutdown,
        })
    }

    /// Whether any listener serves TLS.
    #[cfg(feature = "tls")]
    fn has_tls_listeners(&self) -> bool {
        #[cfg(feature = "mqtt")]
        let mqtts = !self.mqtts_listen.is_empty();
        #[cfg(not(feature = "mqtt"))]
        let mqtts = false;
        !self.tls_listen.is_empty() || mqtts
    }
}

/// The TLS listeners' context, loaded from `options`; none is needed
/// when there are no TLS listeners, and options without listeners are
/// loaded all the same (to be checked, and for `reload_tls`).
#[cfg(feature = "tls")]
fn tls_context(
    options: Option<TlsOptions>,
    no_tls_listeners: bool,
) -> Result<Option<Arc<TlsContext>>, StartError> {
    match (options, no_tls_listeners) {
        (None, false) => Err(StartError::Tls(TlsError::NoOptions)),
        (Some(options), _) => Ok(Some(Arc::new(
            TlsContext::load(options).map_err(StartError::Tls)?,
        ))),
        (None, true) => Ok(None),
    }
}

/// Where the disk alarm reads free space: the builder's probe, else the
/// data directory's file system; without either, there is no disk alarm.
fn free_space_probe(
    probe: Option<Arc<dyn FreeSpace>>,
    storage: &Storage,
) -> Option<Arc<dyn FreeSpace>> {
    match (probe, storage) {
        (Some(probe), _) => Some(probe),
        #[cfg(feature = "persistence")]
        (None, Storage::Dir(dir)) => {
            Some(Arc::new(DirFreeSpace::new(dir.clone())) as Arc<dyn FreeSpace>)
        }
        (None, _) => None,
    }
}

/// What opening the store gave.
struct OpenedStore {
    /// The persister over it (none without a store).
    persistence: Option<Arc<Persistence>>,
    /// What it held.
    recovered: Recovered,
    /// For a store in a data directory: what a clean shutdown records.
    #[cfg(feature = "persistence")]
    clean_shutdown: Option<CleanShutdown>,
}

/// Opens the store and reads what it holds, and starts its persister. A
/// data directory's store is checked for damage (`recover` keeps every
/// readable record of a damaged one); a custom one is its provider's
/// business (a record that cannot be decoded still refuses the start).
fn open_store(
    storage: Storage,
    #[cfg(feature = "persistence")] recover: bool,
) -> Result<OpenedStore, StartError> {
    #[cfg(feature = "persistence")]
    let mut clean_shutdown = None;
    #[cfg_attr(not(feature = "persistence"), allow(unused_mut))]
    let mut stream_root = None;
    let opened = match storage {
        Storage::None => None,
        #[cfg(feature = "persistence")]
        Storage::Dir(dir) => {
            let opened = open_checked(&dir, recover).map_err(StartError::Storage)?;
            stream_root = Some((dir.join("streams"), recover));
            clean_shutdown = Some(CleanShutdown {
                dir,
                generation: opened.next_generation,
            });
            Some((opened.store, opened.recovered))
        }
        Storage::Custom(store) => {
            let pairs =
                crate::store::guarded("scan", || store.scan()).map_err(StartError::Storage)?;
            let recovered = Recovered::from_scan(pairs)
                .map_err(|bad| StartError::Storage(StoreError::Engine(bad.to_string().into())))?;
            Some((store, recovered))
        }
    };
    let (persistence, recovered) = match opened {
        Some((store, recovered)) => {
            let persistence = Persistence::start(store, &recovered).map_err(StartError::Storage)?;
            if let Some((root, recover)) = stream_root {
                persistence.set_stream_root(root, recover);
            }
            (Some(persistence), recovered)
        }
        None => (None, Recovered::default()),
    };
    Ok(OpenedStore {
        persistence,
        recovered,
        #[cfg(feature = "persistence")]
        clean_shutdown,
    })
}

/// The configured users, each with the tags the builder gave them.
fn with_tags(
    mut users: Vec<(String, User)>,
    tags: &HashMap<String, Vec<String>>,
) -> Vec<(String, User)> {
    for (name, user) in &mut users {
        if let Some(tags) = tags.get(name) {
            user.tags.clone_from(tags);
        }
    }
    users
}

/// The users, vhosts and permissions to start with, from the builder's
/// and the store's (`access::at_start`). This start's number, and the
/// default user on a first start (the seed, taken), are on disk before
/// anything is served.
async fn settle_access(
    configured: Configured,
    recovered: &Recovered,
    persistence: Option<&Persistence>,
) -> Result<AtStart, StartError> {
    let mut access = crate::access::lasting::at_start(configured, recovered, persistence.is_some())
        .map_err(StartError::Permission)?;
    if let Some(persistence) = persistence {
        let mut ops = std::mem::take(&mut access.seed);
        ops.push(persistence.start_record());
        let number = persistence.submit_atomic(ops);
        if !persistence.wait(number).await {
            return Err(StartError::Storage(StoreError::Engine(
                "the start could not be recorded".into(),
            )));
        }
    }
    Ok(access)
}

/// Rebuilds the durable exchanges, queues, bindings and messages in the
/// core (`recovery`), and logs what was recovered and how long it took
/// since `started`; a damaged stream is the problem returned.
fn rebuild_durable_state(
    core: &Core,
    recovered: Recovered,
    started: Instant,
) -> Result<(), String> {
    let report = crate::recovery::recover(core, recovered)?;
    if core.persistence.is_some() {
        tracing::info!(
            exchanges = report.exchanges,
            queues = report.queues,
            bindings = report.bindings,
            messages = report.messages,
            elapsed_ms = started.elapsed().as_millis() as u64,
            "recovered durable state"
        );
    }
    Ok(())
}

/// What binding the listeners needs: each accept loop serves once
/// `opened` says so, and holds `alive` while it and its connections run.
struct Listeners<'a> {
    core: &'a Arc<Core>,
    opened: watch::Receiver<bool>,
    alive: &'a mpsc::Sender<()>,
    /// The accept loops' tasks.
    tasks: Vec<JoinHandle<()>>,
}

impl Listeners<'_> {
    /// Binds the AMQP listeners, plaintext and TLS (with their context);
    /// returns the addresses they got, plaintext first.
    async fn bind_amqp_listeners(
        &mut self,
        listeners: impl Iterator<Item = (SocketAddr, Option<Arc<TlsContext>>)>,
    ) -> Result<(Vec<SocketAddr>, Vec<SocketAddr>), StartError> {
        let mut local_addrs = Vec::new();
        let mut tls_addrs = Vec::new();
        for (addr, tls) in listeners {
            let (listener, bound) = bind_listener(addr, &self.core.users).await?;
            if tls.is_some() {
                tracing::info!(addr = %bound, "accepting AMQP 0.9.1 connections over TLS");
                tls_addrs.push(bound);
            } else {
                tracing::info!(addr = %bound, "accepting AMQP 0.9.1 connections");
                local_addrs.push(bound);
            }
            let core = Arc::clone(self.core);
            let serve = crate::server::accept_loop(core, listener, tls, self.alive.clone());
            self.spawn_once_open(serve);
        }
        Ok((local_addrs, tls_addrs))
    }

    /// Binds the MQTT listeners; returns the addresses they got: TCP,
    /// TLS, WebSocket.
    #[cfg(feature = "mqtt")]
    async fn bind_mqtt_listeners(
        &mut self,
        listeners: impl Iterator<Item = (SocketAddr, crate::mqtt::Transport)>,
        shared: &Arc<crate::mqtt::Shared>,
    ) -> Result<[Vec<SocketAddr>; 3], StartError> {
        use crate::mqtt::Transport;
        let mut mqtt_addrs: [Vec<SocketAddr>; 3] = Default::default();
        // Recovered sessions expire whether or not a listener serves them.
        let sweeper = crate::mqtt::sweeper(Arc::clone(self.core), Arc::clone(shared));
        self.tasks.push(tokio::spawn(sweeper));
        for (addr, transport) in listeners {
            let (listener, bound) = bind_listener(addr, &self.core.users).await?;
            let (kind, over) = match transport {
                Transport::Tcp => (0, ""),
                #[cfg(feature = "tls")]
                Transport::Tls(_) => (1, " over TLS"),
                Transport::WebSocket => (2, " over WebSocket"),
            };
            tracing::info!(addr = %bound, "accepting MQTT 3.1.1 and 5.0 connections{over}");
            mqtt_addrs[kind].push(bound);
            let serve = crate::mqtt::accept_loop(
                Arc::clone(self.core),
                listener,
                transport,
                Arc::clone(shared),
                self.alive.clone(),
            );
            self.spawn_once_open(serve);
        }
        Ok(mqtt_addrs)
    }

    /// Spawns an accept loop that serves once the listeners are opened.
    fn spawn_once_open(&mut self, serve: impl std::future::Future<Output = ()> + Send + 'static) {
        let shutdown = self.core.shutdown_signal();
        let opened = self.opened.clone();
        self.tasks
            .push(tokio::spawn(once_open(opened, shutdown, serve)));
    }
}

/// Runs `serve` (a listener's accept loop) once `open` says true; never
/// if the broker shuts down first.
async fn once_open(
    mut open: watch::Receiver<bool>,
    mut shutdown: watch::Receiver<bool>,
    serve: impl std::future::Future<Output = ()>,
) {
    // The guard `wait_for` returns is dropped before serving.
    let opened = tokio::select! {
        opened = open.wait_for(|open| *open) => opened.is_ok(),
        _ = shutdown.wait_for(|stop| *stop) => false,
    };
    if opened {
        serve.await;
    }
}

/// Starts what runs beside the connections: the sweeper of message TTLs
/// and queue expiries, the resident-memory watch, the free-disk watch
/// (with a probe) and the busy poller (when busy polling).
fn spawn_background_tasks(
    core: &Arc<Core>,
    free_space: Option<Arc<dyn FreeSpace>>,
    busy_poll: Option<Arc<BusyPoll>>,
    tasks: &mut Vec<JoinHandle<()>>,
) {
    tasks.push(tokio::spawn(crate::server::sweeper(
        Arc::clone(core),
        SWEEP_PERIOD,
    )));
    tasks.push(tokio::spawn(crate::alarm::resident::watch(
        Arc::clone(&core.gauge),
        core.limits.resident_memory_high_watermark,
        core.shutdown_signal(),
    )));
    if let Some(probe) = free_space {
        tasks.push(tokio::spawn(crate::alarm::disk::watch(
            Arc::clone(&core.gauge),
            probe,
            core.limits.disk_free_limit,
            core.persistence.as_ref().map(|p| p.write_failures()),
            core.shutdown_signal(),
        )));
    }
    if let Some(busy_poll) = busy_poll {
        let shutdown = core.shutdown_signal();
        tasks.push(tokio::spawn(async move { busy_poll.run(shutdown).await }));
    }
}

/// The busy-poll state if busy polling is asked for and can work here.
fn busy_poll_state(max_window: Duration) -> Option<Arc<BusyPoll>> {
    if max_window.is_zero() {
        return None;
    }
    let flavor = tokio::runtime::Handle::current().runtime_flavor();
    if flavor != tokio::runtime::RuntimeFlavor::CurrentThread {
        tracing::warn!(
            ?flavor,
            "busy polling needs a current-thread runtime; not busy-polling"
        );
        return None;
    }
    Some(Arc::new(BusyPoll::new(max_window)))
}

/// Binds a listener on `addr`; returns it and the address it got, with
/// [`warn_if_only_guest`]'s warning when it reaches beyond this host.
async fn bind_listener(
    addr: SocketAddr,
    users: &crate::access::auth::Users,
) -> Result<(TcpListener, SocketAddr), StartError> {
    let listener = TcpListener::bind(addr)
        .await
        .map_err(|source| StartError::Bind { addr, source })?;
    let bound = listener
        .local_addr()
        .map_err(|source| StartError::Bind { addr, source })?;
    warn_if_only_guest(users, bound);
    Ok((listener, bound))
}

/// The start-up warning of a listener beyond this host when `guest` is the
/// only user: either nobody can log in from the network, or anyone can.
fn warn_if_only_guest(users: &crate::access::auth::Users, bound: SocketAddr) {
    if bound.ip().to_canonical().is_loopback() || !users.only_guest() {
        return;
    }
    if users.is_loopback_only(crate::access::auth::GUEST) {
        tracing::warn!(addr = %bound, "listening beyond this host, but the only user is guest, who may connect only via localhost: add a user for remote clients");
    } else {
        tracing::warn!(addr = %bound, "listening beyond this host with guest/guest as the only user and loopback_users empty: anyone on the network can log in");
    }
}
