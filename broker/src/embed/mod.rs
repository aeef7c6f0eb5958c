//! The embedding API: [`Broker::builder`] configures a broker (listeners,
//! users, vhosts, limits), `start` binds the listeners and returns a
//! [`BrokerHandle`]; `shutdown` closes every connection with 320
//! CONNECTION_FORCED and waits for them to finish.
//!
//! Layout: this file is the builder, which only keeps the settings (and
//! why a start fails); `start` is the boot sequence, a function a step
//! (the store recovered, access settled, the listeners bound, the
//! background tasks started); `handle` is the running broker.

mod handle;
mod start;

pub use handle::BrokerHandle;

use crate::access::auth::User;
use crate::access::password::PasswordHash;
use crate::access::permissions::{PatternError, Permission, TopicPermission};
use crate::alarm::disk::FreeSpace;
use crate::core::{Limits, UserLimits};
use crate::store::{Store, StoreError};
#[cfg(feature = "tls")]
use crate::tls::{TlsError, TlsOptions};
use std::net::SocketAddr;
#[cfg(feature = "persistence")]
use std::path::PathBuf;
use std::sync::Arc;
use std::time::Duration;

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
    /// set through [`Admin::set_parameter`](crate::Admin::set_parameter)) and meet AMQP
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
    /// The longest Session Expiry Interval an MQTT 5.0 session is given,
    /// in seconds (RabbitMQ's `mqtt.max_session_expiry_interval_seconds`;
    /// a day by default; `None`: RabbitMQ's `infinity`). A longer one a
    /// client asks for is lowered and the CONNACK says so; 0 makes every
    /// session end with its connection. Whatever the cap, a finite
    /// interval is at most 4,294,967 s, as its queues' `x-expires` is at
    /// most 2^32 - 1 ms. MQTT 3.1.1 persistent sessions never expire.
    pub fn mqtt_max_session_expiry_interval(mut self, seconds: Option<u32>) -> Self {
        self.mqtt_options.max_session_expiry = seconds;
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
