//! The embedding API: [`Broker::builder`] configures a broker (listeners,
//! users, vhosts, limits), `start` binds the listeners and returns a
//! [`BrokerHandle`]; `shutdown` closes every connection with 320
//! CONNECTION_FORCED and waits for them to finish.

use crate::access::Configured;
use crate::admin::Admin;
use crate::auth::User;
use crate::busy_poll::BusyPoll;
use crate::core::{Core, CoreOptions, Limits, UserLimits};
#[cfg(feature = "persistence")]
use crate::disk_alarm::DirFreeSpace;
use crate::disk_alarm::FreeSpace;
use crate::inspect::{Overview, QueueInfo};
use crate::password::PasswordHash;
use crate::permissions::{PatternError, Permission, TopicPermission};
#[cfg(feature = "persistence")]
use crate::store::{mark_clean, open_checked, StoreOp};
use crate::store::{Persistence, Recovered, Store, StoreError};
#[cfg(feature = "tls")]
use crate::tls::{TlsContext, TlsError, TlsOptions};
use std::net::SocketAddr;
#[cfg(feature = "persistence")]
use std::path::PathBuf;
use std::sync::Arc;
use std::time::Duration;
use tokio::net::TcpListener;
use tokio::sync::{mpsc, watch};

/// How often message TTLs and queue x-expires are checked.
const SWEEP_PERIOD: Duration = Duration::from_millis(50);
/// Bytes buffered each way in an in-process connection's pipe.
const IN_PROCESS_BUFFER: usize = 256 * 1024;
/// How long shutdown waits for connections to close.
const SHUTDOWN_GRACE: Duration = Duration::from_secs(5);
/// The product name announced in connection.start unless the builder sets one.
const DEFAULT_PRODUCT: &str = "Leveret";

/// Entry point of the embedding API.
pub struct Broker;

impl Broker {
    /// A builder with the defaults: no listener, user guest/guest, vhost `/`.
    pub fn builder() -> BrokerBuilder {
        BrokerBuilder::default()
    }
}

/// Options for a broker.
#[derive(Debug, Clone, Default)]
pub struct BrokerBuilder {
    listen: Vec<SocketAddr>,
    #[cfg(feature = "tls")]
    tls_listen: Vec<SocketAddr>,
    #[cfg(feature = "mqtt")]
    mqtt_listen: Vec<SocketAddr>,
    #[cfg(all(feature = "mqtt", feature = "tls"))]
    mqtts_listen: Vec<SocketAddr>,
    #[cfg(feature = "mqtt")]
    web_mqtt_listen: Vec<SocketAddr>,
    #[cfg(feature = "mqtt")]
    mqtt_options: crate::mqtt::Options,
    #[cfg(feature = "mqtt")]
    mqtt_retained_limits: crate::mqtt::RetainedLimits,
    #[cfg(feature = "tls")]
    tls: Option<TlsOptions>,
    users: Vec<(String, User)>,
    user_tags: std::collections::HashMap<String, Vec<String>>,
    /// `None`: RabbitMQ's default, `guest` only.
    loopback_users: Option<Vec<String>>,
    vhosts: Vec<String>,
    permissions: Vec<(String, String, Permission)>,
    topic_permissions: Vec<(String, String, String, TopicPermission)>,
    limits: Limits,
    storage: Storage,
    product: Option<String>,
    busy_poll: Duration,
    free_space: Option<Arc<dyn FreeSpace>>,
    #[cfg(feature = "persistence")]
    recover: bool,
    /// Listeners bound by `start` but accepting only once
    /// [`BrokerHandle::open_listeners`] is called.
    held: bool,
}

/// Where durable state lives.
#[derive(Debug, Clone, Default)]
enum Storage {
    /// Nothing is persisted.
    #[default]
    None,
    /// A [`crate::store::DiskStore`] in this directory.
    #[cfg(feature = "persistence")]
    Dir(PathBuf),
    /// A store the caller provides (for example a [`crate::store::MemoryStore`]).
    Custom(Arc<dyn Store>),
}

impl BrokerBuilder {
    /// Adds a TCP listener (port 0 picks a free port).
    pub fn listen(mut self, addr: SocketAddr) -> Self {
        self.listen.push(addr);
        self
    }

    #[cfg(feature = "tls")]
    /// Adds a TLS listener (RabbitMQ's `listeners.ssl`; 5671 by
    /// convention, port 0 picks a free port), served with
    /// [`BrokerBuilder::tls`].
    pub fn tls_listen(mut self, addr: SocketAddr) -> Self {
        self.tls_listen.push(addr);
        self
    }

    #[cfg(feature = "mqtt")]
    /// Adds an MQTT 3.1.1/5.0 listener (RabbitMQ's `mqtt.listeners.tcp`;
    /// 1883 by convention, port 0 picks a free port). MQTT clients log in
    /// as the broker's users (a vhost picked as RabbitMQ picks it: `vhost:user`,
    /// the global parameters `mqtt_port_to_vhost_mapping` and `mqtt_default_vhosts`
    /// set through [`Admin::set_parameter`]) and meet AMQP
    /// clients on `amq.topic`; `docs/mqtt.md` says what is supported.
    pub fn mqtt_listen(mut self, addr: SocketAddr) -> Self {
        self.mqtt_listen.push(addr);
        self
    }

    #[cfg(feature = "mqtt")]
    /// Lets MQTT clients without a user name in: they log in as `user`
    /// with `password`, checked like any login (RabbitMQ's
    /// `mqtt.allow_anonymous` with `mqtt.default_user` and
    /// `mqtt.default_pass`). Without it such a CONNECT is refused
    /// (not authorized).
    pub fn mqtt_anonymous_login(mut self, user: impl Into<String>, password: &str) -> Self {
        self.mqtt_options.anonymous = Some((user.into(), password.to_owned()));
        self
    }

    #[cfg(all(feature = "mqtt", feature = "tls"))]
    /// Adds an MQTT over TLS listener (RabbitMQ's `mqtt.listeners.ssl`;
    /// 8883 by convention, port 0 picks a free port), served with
    /// [`BrokerBuilder::tls`] as the AMQP TLS listeners are.
    pub fn mqtts_listen(mut self, addr: SocketAddr) -> Self {
        self.mqtts_listen.push(addr);
        self
    }

    #[cfg(all(feature = "mqtt", feature = "tls"))]
    /// Lets an MQTT client on a TLS listener whose verified certificate
    /// has a common name, and whose CONNECT has no user name, log in as
    /// that user without a password (RabbitMQ's `mqtt.ssl_cert_login`,
    /// SASL EXTERNAL on the AMQP side). Off by default.
    pub fn mqtt_certificate_login(mut self, enabled: bool) -> Self {
        self.mqtt_options.certificate_login = enabled;
        self
    }

    #[cfg(feature = "mqtt")]
    /// Adds an MQTT over WebSocket listener (RabbitMQ's `web_mqtt`; 15675
    /// by convention, port 0 picks a free port): path `/ws`, subprotocol
    /// `mqtt`, for browser dashboards.
    pub fn web_mqtt_listen(mut self, addr: SocketAddr) -> Self {
        self.web_mqtt_listen.push(addr);
        self
    }

    #[cfg(feature = "mqtt")]
    /// How many MQTT retained messages the broker keeps (over every vhost;
    /// by default 10,000 and 64 MiB): a retained publish past them is
    /// published but not retained, with a log line.
    pub fn mqtt_retained_limits(mut self, limits: crate::mqtt::RetainedLimits) -> Self {
        self.mqtt_retained_limits = limits;
        self
    }

    #[cfg(feature = "tls")]
    /// The TLS listeners' certificate, key and client verification
    /// (RabbitMQ's `ssl_options`); [`BrokerHandle::reload_tls`] re-reads
    /// the files. A client whose verified certificate's common name is a
    /// user may log in with SASL EXTERNAL.
    pub fn tls(mut self, options: TlsOptions) -> Self {
        self.tls = Some(options);
        self
    }

    /// Adds a user; without any, the broker has RabbitMQ's `guest`/`guest`.
    /// The password is kept only as a salted hash.
    pub fn user(mut self, name: impl Into<String>, password: &str) -> Self {
        self.users
            .push((name.into(), User::new(PasswordHash::new(password))));
        self
    }

    /// Adds a user whose password is given as a stored hash
    /// (see `leveret --hash-password`).
    pub fn user_hashed(mut self, name: impl Into<String>, hash: PasswordHash) -> Self {
        self.users.push((name.into(), User::new(hash)));
        self
    }

    /// Gives a user RabbitMQ's user tags (`administrator`, `monitoring`,
    /// `management`, `policymaker`): the broker keeps them for the
    /// management API, which decides from them what the user may see and
    /// do there. The default `guest` is an `administrator`.
    pub fn user_tags<I, S>(mut self, name: impl Into<String>, tags: I) -> Self
    where
        I: IntoIterator<Item = S>,
        S: Into<String>,
    {
        self.user_tags
            .insert(name.into(), tags.into_iter().map(Into::into).collect());
        self
    }

    /// RabbitMQ's `loopback_users`: the users who may connect only from
    /// this host (loopback addresses and in-process clients). By default
    /// `guest`, as in RabbitMQ; an empty list lets every user connect
    /// from anywhere.
    pub fn loopback_users<I, S>(mut self, names: I) -> Self
    where
        I: IntoIterator<Item = S>,
        S: Into<String>,
    {
        self.loopback_users = Some(names.into_iter().map(Into::into).collect());
        self
    }

    /// Adds a vhost; without any, the broker has `/`.
    pub fn vhost(mut self, name: impl Into<String>) -> Self {
        self.vhosts.push(name.into());
        self
    }

    /// Grants `user` a permission on `vhost` (RabbitMQ's
    /// `set_permissions`). A user added with [`BrokerBuilder::user`] has
    /// none until given one, as in RabbitMQ: they can log in but open no
    /// vhost. The default `guest` (when no user is added) has `.*` for all
    /// three on every vhost. [`BrokerBuilder::start`] refuses a pattern
    /// the regex engine cannot run ([`StartError::Permission`]).
    ///
    /// ```
    /// use leveret_broker::{Broker, Permission};
    ///
    /// let builder = Broker::builder()
    ///     .user("robot-7", "secret")
    ///     .permission("robot-7", "/", Permission {
    ///         configure: "^robot-7\\.".into(),
    ///         write: "^(robot-7\\.|amq\\.topic$)".into(),
    ///         read: "^robot-7\\.".into(),
    ///     });
    /// ```
    pub fn permission(
        mut self,
        user: impl Into<String>,
        vhost: impl Into<String>,
        permission: Permission,
    ) -> Self {
        self.permissions
            .push((user.into(), vhost.into(), permission));
        self
    }

    /// Grants `user` a topic permission on `exchange` in `vhost`
    /// (RabbitMQ's `set_topic_permissions`): the routing keys they may
    /// publish with (`write`) and bind with (`read`) on that topic
    /// exchange; `{username}` and `{vhost}` stand for theirs.
    pub fn topic_permission(
        mut self,
        user: impl Into<String>,
        vhost: impl Into<String>,
        exchange: impl Into<String>,
        permission: TopicPermission,
    ) -> Self {
        self.topic_permissions
            .push((user.into(), vhost.into(), exchange.into(), permission));
        self
    }

    #[cfg(feature = "persistence")]
    /// Keeps durable state in `dir` (created if missing): durable
    /// definitions and persistent messages survive restarts and crashes.
    pub fn data_dir(mut self, dir: impl Into<PathBuf>) -> Self {
        self.storage = Storage::Dir(dir.into());
        self
    }

    /// Keeps durable state in a store the caller provides.
    pub fn store(mut self, store: Arc<dyn Store>) -> Self {
        self.storage = Storage::Custom(store);
        self
    }

    #[cfg(feature = "persistence")]
    /// Starts even on a damaged store in [`BrokerBuilder::data_dir`]:
    /// copies the damaged files aside, keeps every readable record and
    /// logs what was lost (the server's `--recover`). Without it a
    /// damaged store refuses the start with [`StoreError::Damaged`].
    pub fn recover(mut self, recover: bool) -> Self {
        self.recover = recover;
        self
    }

    /// Where the disk alarm reads free space (by default the file system
    /// of [`BrokerBuilder::data_dir`]; without a data directory and
    /// without this, there is no disk alarm). For embedders whose store
    /// lives elsewhere, and for tests that simulate a full disk.
    pub fn free_space(mut self, probe: Arc<dyn FreeSpace>) -> Self {
        self.free_space = Some(probe);
        self
    }

    /// Replaces the limits: RabbitMQ's `channel_max`, `frame_max`,
    /// `heartbeat`, `max_message_size`, the memory watermarks (counted
    /// bytes and resident memory), `connection_max`, `handshake_timeout`
    /// and the vhost limits `max-connections` and `max-queues`. See
    /// [`Limits`] for each one's meaning and default.
    ///
    /// ```
    /// use leveret_broker::{Broker, Limits, VhostLimits};
    /// use std::time::Duration;
    ///
    /// let limits = Limits {
    ///     max_connections: Some(200),
    ///     channel_max: 64,
    ///     handshake_timeout: Duration::from_secs(5),
    ///     vhost_limits: [(
    ///         "/".to_owned(),
    ///         VhostLimits { max_connections: Some(50), max_queues: Some(1000) },
    ///     )]
    ///     .into(),
    ///     ..Limits::default()
    /// };
    /// let builder = Broker::builder().limits(limits);
    /// ```
    pub fn limits(mut self, limits: Limits) -> Self {
        self.limits = limits;
        self
    }

    /// Sets one user's limits (RabbitMQ's `max-connections` and
    /// `max-channels`); a later [`BrokerBuilder::limits`] replaces them.
    pub fn user_limits(mut self, user: impl Into<String>, limits: UserLimits) -> Self {
        self.limits.user_limits.insert(user.into(), limits);
        self
    }

    /// The `product` announced in connection.start (default `Leveret`).
    /// Some clients and test suites switch RabbitMQ-only behaviour on when
    /// it is exactly `RabbitMQ` (amqp091-go's integration tests, for one);
    /// a deployment serving such clients can announce that name.
    pub fn product(mut self, name: impl Into<String>) -> Self {
        self.product = Some(name.into());
        self
    }

    /// Busy-polls for at most `max_window` after a socket read (zero, the
    /// default, never busy-polls): the broker's thread keeps polling for
    /// input instead of sleeping, trading CPU time for wake-ups. The
    /// window adapts to the gaps between reads. It needs a current-thread
    /// runtime, which is how the `leveret` binary runs: on a multi-thread
    /// runtime the spinning worker is not the one that polls the sockets,
    /// so `start` warns and does not busy-poll there.
    pub fn busy_poll(mut self, max_window: Duration) -> Self {
        self.busy_poll = max_window;
        self
    }

    /// Binds the listeners in `start` (their addresses are known and a
    /// port in use fails the start) but accepts no client until
    /// [`BrokerHandle::open_listeners`]: an embedder that sets up state
    /// after the start (the `leveret` binary's stored policies and
    /// definitions) so never serves a client the state half set up. A
    /// client that connects meanwhile waits in the listen backlog.
    pub fn hold_listeners(mut self) -> Self {
        self.held = true;
        self
    }

    /// Binds the listeners and starts serving (with
    /// [`Self::hold_listeners`], once told to).
    pub async fn start(self) -> Result<BrokerHandle, StartError> {
        #[cfg(all(feature = "tls", feature = "mqtt"))]
        let no_tls_listeners = self.tls_listen.is_empty() && self.mqtts_listen.is_empty();
        #[cfg(all(feature = "tls", not(feature = "mqtt")))]
        let no_tls_listeners = self.tls_listen.is_empty();
        #[cfg(feature = "tls")]
        let tls = match (self.tls, no_tls_listeners) {
            (None, false) => return Err(StartError::Tls(TlsError::NoOptions)),
            (Some(options), _) => Some(Arc::new(
                TlsContext::load(options).map_err(StartError::Tls)?,
            )),
            (None, true) => None,
        };
        // Recovery time includes opening the store (sled replays its log, the
        // message log is read).
        let started = std::time::Instant::now();
        let free_space = match (self.free_space, &self.storage) {
            (Some(probe), _) => Some(probe),
            #[cfg(feature = "persistence")]
            (None, Storage::Dir(dir)) => {
                Some(Arc::new(DirFreeSpace::new(dir.clone())) as Arc<dyn FreeSpace>)
            }
            (None, _) => None,
        };
        // A data directory's store is checked for damage; a custom one is
        // its provider's business (a record that cannot be decoded still
        // refuses the start).
        #[cfg(feature = "persistence")]
        let mut clean_shutdown = None;
        #[cfg_attr(not(feature = "persistence"), allow(unused_mut))]
        let mut stream_root = None;
        let opened = match self.storage {
            Storage::None => None,
            #[cfg(feature = "persistence")]
            Storage::Dir(dir) => {
                let opened = open_checked(&dir, self.recover).map_err(StartError::Storage)?;
                stream_root = Some((dir.join("streams"), self.recover));
                clean_shutdown = Some(CleanShutdown {
                    dir,
                    generation: opened.next_generation,
                });
                Some((opened.store, opened.recovered))
            }
            Storage::Custom(store) => {
                let pairs =
                    crate::store::guarded("scan", || store.scan()).map_err(StartError::Storage)?;
                let recovered = Recovered::from_scan(pairs).map_err(|bad| {
                    StartError::Storage(StoreError::Engine(bad.to_string().into()))
                })?;
                Some((store, recovered))
            }
        };
        let (persistence, recovered) = match opened {
            Some((store, recovered)) => {
                let persistence =
                    Persistence::start(store, &recovered).map_err(StartError::Storage)?;
                if let Some((root, recover)) = stream_root {
                    persistence.set_stream_root(root, recover);
                }
                (Some(persistence), recovered)
            }
            None => (None, Recovered::default()),
        };
        let mut configured_users = self.users;
        for (name, user) in &mut configured_users {
            if let Some(tags) = self.user_tags.get(name) {
                user.tags.clone_from(tags);
            }
        }
        let access = crate::access::at_start(
            Configured {
                vhosts: self.vhosts,
                users: configured_users,
                permissions: self.permissions,
                topic_permissions: self.topic_permissions,
            },
            &recovered,
            persistence.is_some(),
        )
        .map_err(StartError::Permission)?;
        if let Some(persistence) = &persistence {
            // This start's number, and the default user on a first start,
            // on disk before anything is served.
            let mut ops = access.seed;
            ops.push(persistence.start_record());
            let number = persistence.submit_atomic(ops);
            if !persistence.wait(number).await {
                return Err(StartError::Storage(StoreError::Engine(
                    "the start could not be recorded".into(),
                )));
            }
        }
        let mut users = access.users;
        if let Some(names) = self.loopback_users {
            users.set_loopback_only(names);
        }
        let busy_poll = busy_poll_state(self.busy_poll);
        let core = Core::new(CoreOptions {
            vhosts: access.vhosts,
            users,
            permissions: access.permissions,
            parameters: crate::parameters::Parameters::recovered(&recovered),
            limits: self.limits,
            persistence,
            product: self.product.unwrap_or_else(|| DEFAULT_PRODUCT.to_owned()),
            busy_poll: busy_poll.clone(),
        });
        #[cfg(feature = "mqtt")]
        let mqtt_shared = Arc::new(crate::mqtt::Shared::new(
            &core,
            &recovered.meta,
            self.mqtt_options,
            self.mqtt_retained_limits,
        ));
        let report = match crate::recovery::recover(&core, recovered) {
            Ok(report) => report,
            // A damaged stream refuses the start as a damaged store does.
            Err(problem) => {
                #[cfg(feature = "persistence")]
                if let Some(clean) = &clean_shutdown {
                    return Err(StartError::Storage(StoreError::Damaged {
                        path: clean.dir.clone(),
                        problem,
                    }));
                }
                return Err(StartError::Storage(StoreError::Engine(problem.into())));
            }
        };
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
        let (alive, finished) = mpsc::channel(1);
        let (open, opened) = watch::channel(!self.held);
        let mut local_addrs = Vec::new();
        let mut tls_addrs = Vec::new();
        let mut tasks = Vec::new();
        let listeners = self.listen.into_iter().map(|addr| (addr, None));
        #[cfg(feature = "tls")]
        let listeners =
            listeners.chain(self.tls_listen.into_iter().map(|addr| (addr, tls.clone())));
        for (addr, tls) in listeners {
            let (listener, bound) = bind_listener(addr, &core.users).await?;
            if tls.is_some() {
                tracing::info!(addr = %bound, "accepting AMQP 0.9.1 connections over TLS");
                tls_addrs.push(bound);
            } else {
                tracing::info!(addr = %bound, "accepting AMQP 0.9.1 connections");
                local_addrs.push(bound);
            }
            tasks.push(tokio::spawn(once_open(
                opened.clone(),
                core.shutdown_signal(),
                crate::server::accept_loop(Arc::clone(&core), listener, tls, alive.clone()),
            )));
        }
        // TCP, TLS and WebSocket listeners' bound addresses.
        #[cfg_attr(not(feature = "mqtt"), allow(unused_mut))]
        let mut mqtt_addrs: [Vec<SocketAddr>; 3] = Default::default();
        #[cfg(feature = "mqtt")]
        {
            use crate::mqtt::Transport;
            let listeners = self.mqtt_listen.into_iter().map(|a| (a, Transport::Tcp));
            #[cfg(feature = "tls")]
            let listeners = listeners.chain(self.mqtts_listen.into_iter().filter_map(|a| {
                // `tls` is set whenever there are TLS listeners (above).
                tls.clone().map(|tls| (a, Transport::Tls(tls)))
            }));
            let listeners = listeners.chain(
                self.web_mqtt_listen
                    .into_iter()
                    .map(|a| (a, Transport::WebSocket)),
            );
            for (addr, transport) in listeners {
                let (listener, bound) = bind_listener(addr, &core.users).await?;
                let (kind, over) = match transport {
                    Transport::Tcp => (0, ""),
                    #[cfg(feature = "tls")]
                    Transport::Tls(_) => (1, " over TLS"),
                    Transport::WebSocket => (2, " over WebSocket"),
                };
                tracing::info!(addr = %bound, "accepting MQTT 3.1.1 and 5.0 connections{over}");
                mqtt_addrs[kind].push(bound);
                tasks.push(tokio::spawn(once_open(
                    opened.clone(),
                    core.shutdown_signal(),
                    crate::mqtt::accept_loop(
                        Arc::clone(&core),
                        listener,
                        transport,
                        Arc::clone(&mqtt_shared),
                        alive.clone(),
                    ),
                )));
            }
        }
        tasks.push(tokio::spawn(crate::server::sweeper(
            Arc::clone(&core),
            SWEEP_PERIOD,
        )));
        tasks.push(tokio::spawn(crate::resident_memory::watch(
            Arc::clone(&core.gauge),
            core.limits.resident_memory_high_watermark,
            core.shutdown_signal(),
        )));
        if let Some(probe) = free_space {
            tasks.push(tokio::spawn(crate::disk_alarm::watch(
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
            clean_shutdown,
        })
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

/// A running broker.
pub struct BrokerHandle {
    core: Arc<Core>,
    /// Says the held listeners may accept.
    open: watch::Sender<bool>,
    local_addrs: Vec<SocketAddr>,
    tls_addrs: Vec<SocketAddr>,
    /// The MQTT listeners': TCP, TLS, WebSocket.
    mqtt_addrs: [Vec<SocketAddr>; 3],
    #[cfg(feature = "tls")]
    tls: Option<Arc<TlsContext>>,
    tasks: Vec<tokio::task::JoinHandle<()>>,
    alive: Option<mpsc::Sender<()>>,
    finished: mpsc::Receiver<()>,
    /// For a store in a data directory: what a clean shutdown records.
    #[cfg(feature = "persistence")]
    clean_shutdown: Option<CleanShutdown>,
}

/// Where and with which generation a clean shutdown is recorded.
#[cfg(feature = "persistence")]
#[derive(Debug)]
struct CleanShutdown {
    dir: PathBuf,
    generation: u64,
}

impl BrokerHandle {
    /// Lets the listeners [`BrokerBuilder::hold_listeners`] held accept
    /// clients (a no-op when they already do).
    pub fn open_listeners(&self) {
        self.open.send_replace(true);
    }

    /// The addresses the plaintext listeners are bound to.
    pub fn local_addrs(&self) -> &[SocketAddr] {
        &self.local_addrs
    }

    /// The addresses the TLS listeners are bound to (none without the
    /// `tls` feature).
    pub fn tls_addrs(&self) -> &[SocketAddr] {
        &self.tls_addrs
    }

    /// The addresses the MQTT listeners are bound to (none without the
    /// `mqtt` feature).
    pub fn mqtt_addrs(&self) -> &[SocketAddr] {
        &self.mqtt_addrs[0]
    }

    /// The addresses the MQTT over TLS listeners are bound to.
    pub fn mqtts_addrs(&self) -> &[SocketAddr] {
        &self.mqtt_addrs[1]
    }

    /// The addresses the MQTT over WebSocket listeners are bound to.
    pub fn web_mqtt_addrs(&self) -> &[SocketAddr] {
        &self.mqtt_addrs[2]
    }

    #[cfg(feature = "tls")]
    /// Re-reads the TLS certificate, key and CA bundle: connections
    /// accepted from now on use them, open ones keep theirs. On an error
    /// the files in use before stay in use.
    pub fn reload_tls(&self) -> Result<(), TlsError> {
        match &self.tls {
            Some(tls) => tls.reload(),
            None => Err(TlsError::NoOptions),
        }
    }

    /// Opens an in-process connection: the returned stream is the client's
    /// end of an in-memory pipe whose other end the broker serves exactly
    /// like a TCP socket (same protocol, no network, no TCP stack). Works
    /// with or without listeners.
    pub fn connect_in_process(&self) -> tokio::io::DuplexStream {
        let (client, server) = tokio::io::duplex(IN_PROCESS_BUFFER);
        let (read, write) = tokio::io::split(server);
        let core = Arc::clone(&self.core);
        let slot = core.connections.admit_local();
        let alive = self.alive.clone();
        tokio::spawn(async move {
            let identity = crate::connection::Identity::None;
            let ends = ("in-process".to_owned(), None);
            crate::connection::serve(core, read, write, ends, slot, identity).await;
            drop(alive);
        });
        client
    }

    /// Opens an in-process connection that exchanges AMQP frames as values
    /// (the fast path `leveret-client` takes with its `embedded` feature):
    /// no bytes are encoded or parsed and no writer task runs, while the
    /// handshake, permissions, routing, queues, acks, limits and
    /// statistics are those of every other connection. For a client with a
    /// codec of its own, [`BrokerHandle::connect_in_process`] is the byte
    /// pipe. Works with or without listeners.
    pub fn connect_direct(&self) -> crate::connection::DirectLink {
        let core = Arc::clone(&self.core);
        let slot = core.connections.admit_local();
        let peer = "in-process".to_owned();
        crate::connection::serve_direct(
            core,
            slot,
            (peer, crate::connection::Identity::None),
            (crate::connection::AMQP_0_9_1, None),
            self.alive.clone(),
        )
    }

    /// A cloneable view of this broker's state, for readers that outlive
    /// a borrow of the handle (the `leveret` binary's HTTP listeners).
    pub fn admin(&self) -> Admin {
        Admin {
            core: Arc::clone(&self.core),
        }
    }

    /// Broker-wide figures with RabbitMQ's meanings: object and message
    /// totals, message counters, churn. Reads every queue once.
    pub fn overview(&self) -> Overview {
        self.admin().overview()
    }

    /// Every queue's depth, consumers and counters, sorted by vhost and
    /// name: a robot application reads queue depth here without HTTP.
    pub fn queues(&self) -> Vec<QueueInfo> {
        self.admin().queues()
    }

    /// Closes every connection with 320 CONNECTION_FORCED and stops.
    pub async fn shutdown(mut self) {
        self.core.begin_shutdown();
        for task in self.tasks.drain(..) {
            let _ = task.await;
        }
        self.alive = None;
        // Resolves once every connection task has dropped its sender.
        let _ = tokio::time::timeout(SHUTDOWN_GRACE, self.finished.recv()).await;
        if let Some(persistence) = &self.core.persistence {
            if !persistence.sync().await {
                tracing::error!("the last writes to storage failed at shutdown");
            }
            #[cfg(not(feature = "persistence"))]
            persistence.close(Vec::new()).await;
            // The marker is the store's last write; the manifest says
            // `clean` only once it is on disk.
            #[cfg(feature = "persistence")]
            {
                let marker = self
                    .clean_shutdown
                    .as_ref()
                    .map(|clean| StoreOp::CleanShutdown {
                        generation: clean.generation,
                    });
                let marked = persistence.close(marker.into_iter().collect()).await;
                if let Some(clean) = &self.clean_shutdown {
                    let recorded = if marked {
                        mark_clean(&clean.dir, clean.generation)
                    } else {
                        Err(StoreError::Engine("the marker could not be written".into()))
                    };
                    if let Err(e) = recorded {
                        tracing::error!(error = %e, "could not record a clean shutdown");
                    }
                }
            }
        }
    }
}

impl Drop for BrokerHandle {
    fn drop(&mut self) {
        self.core.begin_shutdown();
    }
}

/// Why a broker could not start.
#[derive(Debug, thiserror::Error)]
pub enum StartError {
    /// The data directory could not be opened or read.
    #[error("cannot open storage: {0}")]
    Storage(StoreError),
    /// A permission's pattern cannot be used.
    #[error(transparent)]
    Permission(PatternError),
    /// The TLS certificates, key or CA bundle cannot be used.
    #[cfg(feature = "tls")]
    #[error("TLS: {0}")]
    Tls(TlsError),
    /// A listener could not be bound.
    #[error("cannot listen on {addr}: {source}")]
    Bind {
        /// The address.
        addr: SocketAddr,
        /// The error.
        source: std::io::Error,
    },
}

/// Binds a listener on `addr`; returns it and the address it got, with
/// [`warn_if_only_guest`]'s warning when it reaches beyond this host.
async fn bind_listener(
    addr: SocketAddr,
    users: &crate::auth::Users,
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
fn warn_if_only_guest(users: &crate::auth::Users, bound: SocketAddr) {
    if bound.ip().to_canonical().is_loopback() || !users.only_guest() {
        return;
    }
    if users.is_loopback_only(crate::auth::GUEST) {
        tracing::warn!(addr = %bound, "listening beyond this host, but the only user is guest, who may connect only via localhost: add a user for remote clients");
    } else {
        tracing::warn!(addr = %bound, "listening beyond this host with guest/guest as the only user and loopback_users empty: anyone on the network can log in");
    }
}
