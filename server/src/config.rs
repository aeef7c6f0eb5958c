//! The TOML config file and how it merges with the command line: the file
//! is read into [`FileConfig`], then [`Settings::resolve`] takes each value
//! from the command line, else the file, else the default, and checks what
//! the types cannot (one credential per user). [`Settings::builder`] turns
//! the result into the library's plain [`BrokerBuilder`]; nothing here
//! knows how the broker works.

use crate::cli::Cli;
use crate::logging::LogFormat;
use leveret_broker::{
    check_pattern, Broker, BrokerBuilder, Limits, PasswordHash, PatternError, PeerVerification,
    Permission, ResidentMemoryWatermark, TlsOptions, TopicPermission, UserLimits, VhostLimits,
};
use leveret_uplink::ShovelConfig;
use serde::Deserialize;
use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::time::Duration;

/// Where AMQP connections are accepted unless told otherwise.
const DEFAULT_LISTEN: SocketAddr =
    SocketAddr::new(std::net::IpAddr::V4(std::net::Ipv4Addr::UNSPECIFIED), 5672);
/// Where MQTT connections are accepted unless told otherwise (RabbitMQ's
/// port; `--mqtt-listen none` or `mqtt-listen = []` turns it off).
const DEFAULT_MQTT_LISTEN: SocketAddr =
    SocketAddr::new(std::net::IpAddr::V4(std::net::Ipv4Addr::UNSPECIFIED), 1883);
/// The longest Session Expiry Interval an MQTT 5.0 session is given unless
/// told otherwise (s): RabbitMQ 3.13's `mqtt.max_session_expiry_interval_seconds`
/// default, a day, as the broker builder's.
const DEFAULT_MQTT_MAX_SESSION_EXPIRY: u32 = 86_400;
/// Where the Prometheus endpoint listens unless told otherwise (RabbitMQ's port).
const DEFAULT_METRICS_LISTEN: SocketAddr =
    SocketAddr::new(std::net::IpAddr::V4(std::net::Ipv4Addr::LOCALHOST), 15692);
/// Where the management API listens unless told otherwise (RabbitMQ's port).
const DEFAULT_HTTP_LISTEN: SocketAddr =
    SocketAddr::new(std::net::IpAddr::V4(std::net::Ipv4Addr::LOCALHOST), 15672);
/// Where durable state lives unless told otherwise.
const DEFAULT_DATA_DIR: &str = "leveret-data";
/// The log filter unless told otherwise.
const DEFAULT_LOG: &str = "info";
/// The default busy-poll window: Linux haltpoll's default poll time,
/// enough to catch a client's answer on a small VM (round trips with and
/// without it: perf/results/2026-11-24/busy-poll-contention.txt).
const DEFAULT_BUSY_POLL_MICROS: u64 = 200;

/// Why the configuration cannot be used.
#[derive(Debug, thiserror::Error)]
pub enum ConfigError {
    /// The file cannot be read.
    #[error("cannot read {path}: {source}")]
    Read {
        /// The file.
        path: PathBuf,
        /// The I/O error.
        source: std::io::Error,
    },
    /// The file is not valid TOML or has keys or values we do not know.
    #[error("invalid config {path}: {source}")]
    Parse {
        /// The file.
        path: PathBuf,
        /// What the TOML parser says.
        source: toml::de::Error,
    },
    /// A user has neither or both of `password` and `password-hash`.
    #[error("user {0}: give exactly one of password, password-hash")]
    Credentials(String),
    /// `mqtt-max-session-expiry-interval-seconds` is a word other than
    /// `infinity`.
    #[error(
        "mqtt-max-session-expiry-interval-seconds: a number of seconds or \"infinity\", not {0:?}"
    )]
    SessionExpiryCap(String),
    /// Only one of `mqtt-default-user` and `mqtt-default-pass` is given.
    #[error("give both mqtt-default-user and mqtt-default-pass, or neither")]
    MqttAnonymous,
    /// A user's `password-hash` is not one `leveret --hash-password` prints.
    #[error("user {0}: password-hash is not a leveret hash")]
    BadHash(String),
    /// A shovel's or federation upstream's parameters, or a policy, cannot
    /// be used.
    #[error("{what} {name}: {reason}")]
    Parameter {
        /// `shovel`, `federation upstream` or `policy`.
        what: &'static str,
        /// Its name.
        name: String,
        /// What is wrong.
        reason: String,
    },
    /// The TLS settings do not fit together.
    #[error("TLS: {0}")]
    Tls(String),
    /// A permission's pattern cannot be used.
    #[error("user {user}: {source}")]
    Pattern {
        /// The user.
        user: String,
        /// What is wrong with the pattern.
        source: PatternError,
    },
}

/// A number of seconds, or the word `infinity` (RabbitMQ's spelling).
#[derive(Debug, Deserialize)]
#[serde(untagged)]
enum SecondsOrInfinity {
    Seconds(u32),
    Word(String),
}

/// The config file, as written: every key optional, unknown keys refused.
#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields, rename_all = "kebab-case")]
pub struct FileConfig {
    listen: Option<Vec<SocketAddr>>,
    /// RabbitMQ's `listeners.ssl`.
    tls_listen: Option<Vec<SocketAddr>>,
    /// RabbitMQ's `mqtt.listeners.tcp` (`[]` turns MQTT over TCP off).
    mqtt_listen: Option<Vec<SocketAddr>>,
    /// RabbitMQ's `mqtt.listeners.ssl`.
    mqtts_listen: Option<Vec<SocketAddr>>,
    /// RabbitMQ's `web_mqtt.tcp.port`.
    web_mqtt_listen: Option<Vec<SocketAddr>>,
    /// RabbitMQ's `mqtt.ssl_cert_login`: an MQTT client on a TLS listener
    /// without a user name logs in as its certificate's common name.
    mqtt_ssl_cert_login: Option<bool>,
    /// RabbitMQ's `mqtt.max_session_expiry_interval_seconds`: seconds, or
    /// `"infinity"`.
    mqtt_max_session_expiry_interval_seconds: Option<SecondsOrInfinity>,
    /// RabbitMQ's `mqtt.default_user` (with `mqtt.allow_anonymous`): the
    /// user MQTT clients without a user name log in as.
    mqtt_default_user: Option<String>,
    /// RabbitMQ's `mqtt.default_pass`.
    mqtt_default_pass: Option<String>,
    /// `ssl_options.certfile`.
    tls_certfile: Option<PathBuf>,
    /// `ssl_options.keyfile`.
    tls_keyfile: Option<PathBuf>,
    /// `ssl_options.cacertfile`.
    tls_cacertfile: Option<PathBuf>,
    /// `ssl_options.verify`: `verify_peer` (the default with a
    /// `tls-cacertfile`) or `verify_none`.
    tls_verify: Option<String>,
    /// `ssl_options.fail_if_no_peer_cert` (default false).
    tls_fail_if_no_peer_cert: Option<bool>,
    data_dir: Option<PathBuf>,
    log: Option<String>,
    log_format: Option<LogFormat>,
    log_file: Option<PathBuf>,
    #[serde(default)]
    users: Vec<UserConfig>,
    #[serde(default)]
    vhosts: Vec<String>,
    /// RabbitMQ's `loopback_users`: who may log in only from this host
    /// (`["guest"]` when absent; `[]` lets guest in from anywhere).
    loopback_users: Option<Vec<String>>,
    heartbeat: Option<u16>,
    frame_max: Option<u32>,
    channel_max: Option<u16>,
    max_message_size: Option<u64>,
    memory_high_watermark: Option<usize>,
    /// RabbitMQ's `vm_memory_high_watermark.absolute`, bytes of resident memory.
    vm_memory_high_watermark_absolute: Option<u64>,
    /// RabbitMQ's `vm_memory_high_watermark.relative`, a fraction of RAM.
    vm_memory_high_watermark_relative: Option<f64>,
    /// RabbitMQ's `disk_free_limit` (also spelt `disk-free-limit-absolute`,
    /// after `disk_free_limit.absolute`), bytes.
    #[serde(alias = "disk-free-limit-absolute")]
    disk_free_limit: Option<u64>,
    /// RabbitMQ's `connection_max`.
    max_connections: Option<usize>,
    /// RabbitMQ's `handshake_timeout`, milliseconds.
    handshake_timeout: Option<u64>,
    /// RabbitMQ's vhost limits, by vhost name.
    #[serde(default)]
    vhost_limits: std::collections::HashMap<String, VhostLimitsConfig>,
    product: Option<String>,
    busy_poll: Option<u64>,
    worker_threads: Option<usize>,
    metrics_listen: Option<SocketAddr>,
    http_listen: Option<SocketAddr>,
    definitions: Option<PathBuf>,
    /// `[shovels.NAME]`: RabbitMQ's dynamic-shovel parameters, by name.
    #[serde(default)]
    shovels: std::collections::BTreeMap<String, toml::Table>,
    /// `[federation-upstreams.NAME]`: RabbitMQ's `federation-upstream`
    /// parameters, by name (vhost `/`).
    #[serde(default)]
    federation_upstreams: std::collections::BTreeMap<String, toml::Table>,
    /// `[policies.NAME]`: RabbitMQ's policies (vhost `/`), checked as
    /// `crate::policies` checks them.
    #[serde(default)]
    policies: std::collections::BTreeMap<String, toml::Table>,
}

/// One `[vhost-limits."NAME"]` table (`rabbitmqctl set_vhost_limits`).
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields, rename_all = "kebab-case")]
struct VhostLimitsConfig {
    max_connections: Option<usize>,
    max_queues: Option<usize>,
}

/// One `[[users]]` table.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields, rename_all = "kebab-case")]
struct UserConfig {
    name: String,
    /// Plain text; prefer `password-hash`.
    password: Option<String>,
    /// As printed by `leveret --hash-password` (argon2id), or as RabbitMQ
    /// exports it with `hashing-algorithm`.
    password_hash: Option<String>,
    /// RabbitMQ's `hashing_algorithm` for a `password-hash` exported from
    /// it (`rabbit_password_hashing_sha256` or `_sha512`).
    hashing_algorithm: Option<String>,
    /// The user limit `max-connections`.
    max_connections: Option<usize>,
    /// The user limit `max-channels` (across all their connections).
    max_channels: Option<usize>,
    /// RabbitMQ's user tags (`administrator`, `monitoring`, `management`,
    /// `policymaker`): what the user may do in the management API.
    #[serde(default)]
    tags: Vec<String>,
    /// `[[users.permissions]]`: RabbitMQ's `set_permissions`, one per vhost.
    #[serde(default)]
    permissions: Vec<PermissionConfig>,
    /// `[[users.topic-permissions]]`: RabbitMQ's `set_topic_permissions`.
    #[serde(default)]
    topic_permissions: Vec<TopicPermissionConfig>,
}

/// One `[[users.permissions]]` table.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields, rename_all = "kebab-case")]
struct PermissionConfig {
    vhost: String,
    configure: String,
    write: String,
    read: String,
}

/// One `[[users.topic-permissions]]` table.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields, rename_all = "kebab-case")]
struct TopicPermissionConfig {
    vhost: String,
    exchange: String,
    write: String,
    read: String,
}

impl FileConfig {
    /// Reads and parses a config file.
    pub fn load(path: &Path) -> Result<FileConfig, ConfigError> {
        let text = std::fs::read_to_string(path).map_err(|source| ConfigError::Read {
            path: path.to_owned(),
            source,
        })?;
        FileConfig::parse(&text).map_err(|source| ConfigError::Parse {
            path: path.to_owned(),
            source,
        })
    }

    fn parse(text: &str) -> Result<FileConfig, toml::de::Error> {
        toml::from_str(text)
    }
}

/// How a user proves who they are.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Credential {
    /// A plain-text password (hashed by the builder).
    Password(String),
    /// A stored salted hash.
    Hash(PasswordHash),
}

/// Everything the binary runs with, resolved from the command line, the
/// file and the defaults.
#[derive(Debug, Clone)]
pub struct Settings {
    /// AMQP listeners.
    pub listen: Vec<SocketAddr>,
    /// AMQP-over-TLS listeners.
    pub tls_listen: Vec<SocketAddr>,
    /// MQTT listeners.
    pub mqtt_listen: Vec<SocketAddr>,
    /// MQTT-over-TLS listeners.
    pub mqtts_listen: Vec<SocketAddr>,
    /// MQTT-over-WebSocket listeners.
    pub web_mqtt_listen: Vec<SocketAddr>,
    /// Whether MQTT clients may log in with their TLS certificate.
    pub mqtt_ssl_cert_login: bool,
    /// The longest Session Expiry Interval an MQTT 5.0 session is given
    /// (s; `None`: infinity).
    pub mqtt_max_session_expiry_interval: Option<u32>,
    /// The user and password of MQTT clients without a user name.
    pub mqtt_anonymous: Option<(String, String)>,
    /// Their certificates and client verification.
    pub tls: Option<TlsOptions>,
    /// The directory for durable state.
    pub data_dir: PathBuf,
    /// The tracing filter.
    pub log: String,
    /// Text or JSON log lines.
    pub log_format: LogFormat,
    /// The log file, if not standard error.
    pub log_file: Option<PathBuf>,
    /// The config file read, if any (for the start banner).
    pub config_file: Option<PathBuf>,
    /// Users; empty means the library's `guest`/`guest`.
    pub users: Vec<(String, Credential)>,
    /// Each configured user's tags.
    pub tags: std::collections::BTreeMap<String, Vec<String>>,
    /// (user, vhost, permission) for the users above.
    pub permissions: Vec<(String, String, Permission)>,
    /// (user, vhost, exchange, topic permission) for the users above.
    pub topic_permissions: Vec<(String, String, String, TopicPermission)>,
    /// Vhosts; empty means the library's `/`.
    pub vhosts: Vec<String>,
    /// Users who may log in only from this host; `None` is the library's
    /// default (`guest`).
    pub loopback_users: Option<Vec<String>>,
    /// Limits, each from the file or the library's default.
    pub limits: Limits,
    /// The product name, if not the library's default.
    pub product: Option<String>,
    /// The busy-poll window.
    pub busy_poll: Duration,
    /// Threads serving connections (1: a current-thread runtime).
    pub worker_threads: usize,
    /// The Prometheus endpoint.
    pub metrics_listen: SocketAddr,
    /// The management API.
    pub http_listen: SocketAddr,
    /// A definitions file to load at start.
    pub definitions: Option<PathBuf>,
    /// Start on a damaged store, keeping what is readable.
    pub recover: bool,
    /// Shovels, by name: RabbitMQ's JSON parameters, checked.
    pub shovels: Vec<(String, serde_json::Value)>,
    /// Federation upstreams, by name: RabbitMQ's JSON parameters, checked.
    pub federation_upstreams: Vec<(String, serde_json::Value)>,
    /// Policies, by name: RabbitMQ's JSON form, checked.
    pub policies: Vec<(String, serde_json::Value)>,
}

/// Tables of the file as RabbitMQ's JSON, each checked by `check`.
fn checked_json(
    tables: &std::collections::BTreeMap<String, toml::Table>,
    what: &'static str,
    check: impl Fn(&serde_json::Value) -> Result<(), String>,
) -> Result<Vec<(String, serde_json::Value)>, ConfigError> {
    tables
        .iter()
        .map(|(name, table)| {
            serde_json::to_value(table)
                .map_err(|e| e.to_string())
                .and_then(|value| check(&value).map(|()| value))
                .map(|value| (name.clone(), value))
                .map_err(|reason| ConfigError::Parameter {
                    what,
                    name: name.clone(),
                    reason,
                })
        })
        .collect()
}

/// RabbitMQ's `ssl_options` from their parts: `verify` defaults to
/// `verify_peer` when there is a CA bundle.
fn resolve_tls(
    certfile: Option<PathBuf>,
    keyfile: Option<PathBuf>,
    cacertfile: Option<PathBuf>,
    verify: Option<&str>,
    fail_if_no_peer_cert: bool,
) -> Result<Option<TlsOptions>, ConfigError> {
    let (certfile, keyfile) = match (certfile, keyfile) {
        (Some(cert), Some(key)) => (cert, key),
        (None, None) if cacertfile.is_none() && verify.is_none() => return Ok(None),
        _ => {
            return Err(ConfigError::Tls(
                "give both tls-certfile and tls-keyfile".into(),
            ))
        }
    };
    let verify_peer = match verify {
        None => cacertfile.is_some(),
        Some("verify_peer") => true,
        Some("verify_none") => false,
        Some(other) => {
            return Err(ConfigError::Tls(format!(
                "tls-verify is verify_peer or verify_none, not {other}"
            )))
        }
    };
    let verify = match (verify_peer, fail_if_no_peer_cert) {
        (false, _) => PeerVerification::None,
        (true, false) => PeerVerification::Optional,
        (true, true) => PeerVerification::Required,
    };
    if verify != PeerVerification::None && cacertfile.is_none() {
        return Err(ConfigError::Tls("verify_peer needs tls-cacertfile".into()));
    }
    Ok(Some(TlsOptions {
        certfile,
        keyfile,
        cacertfile,
        verify,
    }))
}

impl Settings {
    /// Takes each value from the command line, else the file, else the default.
    pub fn resolve(cli: Cli, file: FileConfig) -> Result<Settings, ConfigError> {
        let listen = if cli.listen.is_empty() {
            file.listen.unwrap_or_else(|| vec![DEFAULT_LISTEN])
        } else {
            cli.listen
        };
        let tls_listen = if cli.tls_listen.is_empty() {
            file.tls_listen.unwrap_or_default()
        } else {
            cli.tls_listen
        };
        let mqtt_listen = if cli.mqtt_listen.is_empty() {
            file.mqtt_listen
                .unwrap_or_else(|| vec![DEFAULT_MQTT_LISTEN])
        } else {
            cli.mqtt_listen.iter().filter_map(|l| l.0).collect()
        };
        let mqtts_listen = if cli.mqtts_listen.is_empty() {
            file.mqtts_listen.unwrap_or_default()
        } else {
            cli.mqtts_listen
        };
        let web_mqtt_listen = if cli.web_mqtt_listen.is_empty() {
            file.web_mqtt_listen.unwrap_or_default()
        } else {
            cli.web_mqtt_listen
        };
        let mqtt_max_session_expiry_interval = match file.mqtt_max_session_expiry_interval_seconds {
            None => Some(DEFAULT_MQTT_MAX_SESSION_EXPIRY),
            Some(SecondsOrInfinity::Seconds(seconds)) => Some(seconds),
            Some(SecondsOrInfinity::Word(word)) if word == "infinity" => None,
            Some(SecondsOrInfinity::Word(word)) => return Err(ConfigError::SessionExpiryCap(word)),
        };
        let mqtt_anonymous = match (file.mqtt_default_user, file.mqtt_default_pass) {
            (Some(user), Some(pass)) => Some((user, pass)),
            (None, None) => None,
            _ => return Err(ConfigError::MqttAnonymous),
        };
        let tls = resolve_tls(
            cli.tls_certfile.or(file.tls_certfile),
            cli.tls_keyfile.or(file.tls_keyfile),
            cli.tls_cacertfile.or(file.tls_cacertfile),
            file.tls_verify.as_deref(),
            file.tls_fail_if_no_peer_cert.unwrap_or(false),
        )?;
        if !tls_listen.is_empty() && tls.is_none() {
            return Err(ConfigError::Tls(
                "tls-listen needs tls-certfile and tls-keyfile".into(),
            ));
        }
        if !mqtts_listen.is_empty() && tls.is_none() {
            return Err(ConfigError::Tls(
                "mqtts-listen needs tls-certfile and tls-keyfile".into(),
            ));
        }
        let defaults = Limits::default();
        let limits = Limits {
            channel_max: file.channel_max.unwrap_or(defaults.channel_max),
            frame_max: file.frame_max.unwrap_or(defaults.frame_max),
            heartbeat: file.heartbeat.unwrap_or(defaults.heartbeat),
            max_message_size: file.max_message_size.unwrap_or(defaults.max_message_size),
            memory_high_watermark: file
                .memory_high_watermark
                .unwrap_or(defaults.memory_high_watermark),
            resident_memory_high_watermark: match (
                file.vm_memory_high_watermark_absolute,
                file.vm_memory_high_watermark_relative,
            ) {
                (Some(bytes), _) => ResidentMemoryWatermark::Absolute(bytes),
                (None, Some(fraction)) => ResidentMemoryWatermark::Relative(fraction),
                (None, None) => defaults.resident_memory_high_watermark,
            },
            disk_free_limit: cli
                .disk_free_limit
                .or(file.disk_free_limit)
                .unwrap_or(defaults.disk_free_limit),
            max_connections: file.max_connections.or(defaults.max_connections),
            handshake_timeout: file
                .handshake_timeout
                .map_or(defaults.handshake_timeout, Duration::from_millis),
            vhost_limits: file
                .vhost_limits
                .into_iter()
                .map(|(vhost, limits)| {
                    let limits = VhostLimits {
                        max_connections: limits.max_connections,
                        max_queues: limits.max_queues,
                    };
                    (vhost, limits)
                })
                .collect(),
            user_limits: file
                .users
                .iter()
                .filter(|user| user.max_connections.is_some() || user.max_channels.is_some())
                .map(|user| {
                    let limits = UserLimits {
                        max_connections: user.max_connections,
                        max_channels: user.max_channels,
                    };
                    (user.name.clone(), limits)
                })
                .collect(),
        };
        let shovels = checked_json(&file.shovels, "shovel", |value| {
            ShovelConfig::from_json(value).map(|_| ())
        })?;
        let federation_upstreams =
            checked_json(&file.federation_upstreams, "federation upstream", |value| {
                leveret_uplink::UpstreamConfig::from_json(value).map(|_| ())
            })?;
        let policies = checked_json(&file.policies, "policy", |value| {
            crate::policies::check(leveret_broker::PolicyKind::User, value)
        })?;
        let tags = file
            .users
            .iter()
            .map(|user| (user.name.clone(), user.tags.clone()))
            .collect();
        let mut permissions = Vec::new();
        let mut topic_permissions = Vec::new();
        for user in &file.users {
            let bad = |source| ConfigError::Pattern {
                user: user.name.clone(),
                source,
            };
            for p in &user.permissions {
                for pattern in [&p.configure, &p.write, &p.read] {
                    check_pattern(pattern).map_err(bad)?;
                }
                let permission = Permission {
                    configure: p.configure.clone(),
                    write: p.write.clone(),
                    read: p.read.clone(),
                };
                permissions.push((user.name.clone(), p.vhost.clone(), permission));
            }
            for t in &user.topic_permissions {
                check_pattern(&t.write).map_err(bad)?;
                check_pattern(&t.read).map_err(bad)?;
                let permission = TopicPermission {
                    write: t.write.clone(),
                    read: t.read.clone(),
                };
                topic_permissions.push((
                    user.name.clone(),
                    t.vhost.clone(),
                    t.exchange.clone(),
                    permission,
                ));
            }
        }
        let users = file
            .users
            .into_iter()
            .map(|user| {
                let credential = match (user.password, user.password_hash) {
                    (Some(password), None) => Credential::Password(password),
                    (None, Some(stored)) => {
                        let hash = match user.hashing_algorithm.as_deref() {
                            Some(algorithm) => PasswordHash::from_rabbitmq(&stored, algorithm),
                            None => PasswordHash::parse(&stored),
                        };
                        match hash {
                            Some(hash) => Credential::Hash(hash),
                            None => return Err(ConfigError::BadHash(user.name)),
                        }
                    }
                    _ => return Err(ConfigError::Credentials(user.name)),
                };
                Ok((user.name, credential))
            })
            .collect::<Result<_, _>>()?;
        let busy_poll = cli
            .busy_poll
            .or(file.busy_poll)
            .unwrap_or(DEFAULT_BUSY_POLL_MICROS);
        Ok(Settings {
            listen,
            tls_listen,
            mqtt_listen,
            mqtts_listen,
            web_mqtt_listen,
            mqtt_ssl_cert_login: file.mqtt_ssl_cert_login.unwrap_or(false),
            mqtt_max_session_expiry_interval,
            mqtt_anonymous,
            tls,
            data_dir: cli
                .data_dir
                .or(file.data_dir)
                .unwrap_or_else(|| PathBuf::from(DEFAULT_DATA_DIR)),
            log: cli.log.or(file.log).unwrap_or_else(|| DEFAULT_LOG.into()),
            log_format: cli.log_format.or(file.log_format).unwrap_or_default(),
            log_file: cli.log_file.or(file.log_file),
            config_file: cli.config,
            users,
            tags,
            permissions,
            topic_permissions,
            vhosts: file.vhosts,
            loopback_users: file.loopback_users,
            limits,
            product: cli.product.or(file.product),
            busy_poll: Duration::from_micros(busy_poll),
            worker_threads: cli
                .worker_threads
                .or(file.worker_threads)
                .unwrap_or(1)
                .max(1),
            metrics_listen: cli
                .metrics_listen
                .or(file.metrics_listen)
                .unwrap_or(DEFAULT_METRICS_LISTEN),
            http_listen: cli
                .http_listen
                .or(file.http_listen)
                .unwrap_or(DEFAULT_HTTP_LISTEN),
            definitions: cli.definitions.or(file.definitions),
            recover: cli.recover,
            shovels,
            federation_upstreams,
            policies,
        })
    }

    /// The operators' listeners for these settings.
    pub fn ops(&self) -> crate::ops::OpsSettings {
        crate::ops::OpsSettings {
            metrics_listen: self.metrics_listen,
            http_listen: self.http_listen,
            data_dir: self.data_dir.clone(),
            tls: self
                .tls
                .clone()
                .filter(|_| !self.tls_listen.is_empty() || !self.mqtts_listen.is_empty()),
            environment: self.environment(),
        }
    }

    /// The library's builder for these settings.
    pub fn builder(self) -> BrokerBuilder {
        let mut builder = Broker::builder()
            .limits(self.limits)
            .data_dir(self.data_dir)
            .recover(self.recover)
            .busy_poll(self.busy_poll);
        if let Some(product) = self.product {
            builder = builder.product(product);
        }
        for addr in self.listen {
            builder = builder.listen(addr);
        }
        for addr in self.tls_listen {
            builder = builder.tls_listen(addr);
        }
        for addr in self.mqtt_listen {
            builder = builder.mqtt_listen(addr);
        }
        for addr in self.mqtts_listen {
            builder = builder.mqtts_listen(addr);
        }
        for addr in self.web_mqtt_listen {
            builder = builder.web_mqtt_listen(addr);
        }
        builder = builder.mqtt_certificate_login(self.mqtt_ssl_cert_login);
        builder = builder.mqtt_max_session_expiry_interval(self.mqtt_max_session_expiry_interval);
        if let Some((user, pass)) = self.mqtt_anonymous {
            builder = builder.mqtt_anonymous_login(user, &pass);
        }
        if let Some(tls) = self.tls {
            builder = builder.tls(tls);
        }
        for (name, credential) in self.users {
            builder = match credential {
                Credential::Password(password) => builder.user(name, &password),
                Credential::Hash(hash) => builder.user_hashed(name, hash),
            };
        }
        for (name, tags) in self.tags {
            builder = builder.user_tags(name, tags);
        }
        for (user, vhost, permission) in self.permissions {
            builder = builder.permission(user, vhost, permission);
        }
        for (user, vhost, exchange, permission) in self.topic_permissions {
            builder = builder.topic_permission(user, vhost, exchange, permission);
        }
        if let Some(names) = self.loopback_users {
            builder = builder.loopback_users(names);
        }
        for vhost in self.vhosts {
            builder = builder.vhost(vhost);
        }
        builder
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use clap::Parser;

    fn file(text: &str) -> FileConfig {
        FileConfig::parse(text).unwrap_or_else(|e| panic!("{text}: {e}"))
    }

    fn cli(args: &[&str]) -> Cli {
        Cli::try_parse_from(std::iter::once("leveret").chain(args.iter().copied()))
            .expect("valid command line")
    }

    #[test]
    fn the_environment_leaves_credentials_out() {
        let settings = Settings::resolve(
            cli(&[
                "--tls-listen",
                "127.0.0.1:0",
                "--mqtt-listen",
                "127.0.0.1:0",
            ]),
            file(concat!(
                "mqtt-default-user = \"anon\"\nmqtt-default-pass = \"mqtt-secret\"\n",
                "tls-certfile = \"c.pem\"\ntls-keyfile = \"k.pem\"\n",
                "vm-memory-high-watermark-absolute = 1000000\n",
                "[[users]]\nname = \"u\"\npassword = \"user-secret\"\n",
                "[shovels.up]\nsrc-uri = \"amqp://u:shovel-secret@a\"\nsrc-queue = \"t\"\n",
                "dest-uri = \"amqp://u:shovel-secret@b\"\ndest-queue = \"f\"\n",
                "[federation-upstreams.far]\nuri = \"amqp://u:upstream-secret@c\"\n",
            )),
        )
        .unwrap();
        let environment = settings.environment();
        let text = environment.to_string();
        assert!(!text.contains("secret"), "{text}");
        assert_eq!(environment["mqtt-default-user"], "anon");
        assert_eq!(environment["shovels"], serde_json::json!(["up"]));
        assert_eq!(
            environment["federation-upstreams"],
            serde_json::json!(["far"])
        );
        assert_eq!(environment["tls-keyfile"], "k.pem");
        assert_eq!(environment["tls-verify"], "verify_none");
        assert_eq!(environment["vm-memory-high-watermark-absolute"], 1_000_000);
        assert!(environment
            .get("vm-memory-high-watermark-relative")
            .is_none());
    }

    #[test]
    fn shovels_take_rabbitmqs_parameter_names() {
        let settings = Settings::resolve(
            cli(&[]),
            file("[shovels.up]\nsrc-uri = \"amqp://\"\nsrc-queue = \"t\"\ndest-uri = [\"amqp://a\", \"amqp://b\"]\ndest-queue = \"f\"\n"),
        )
        .unwrap();
        assert_eq!(settings.shovels.len(), 1);
        assert_eq!(settings.shovels[0].0, "up");
        assert_eq!(
            settings.shovels[0].1["dest-uri"],
            serde_json::json!(["amqp://a", "amqp://b"])
        );
        let error = Settings::resolve(
            cli(&[]),
            file("[shovels.bad]\nsrc-uri = \"amqp://\"\ndest-uri = \"amqp://a\"\ndest-queue = \"f\"\n"),
        )
        .unwrap_err()
        .to_string();
        assert!(
            error.contains("shovel bad") && error.contains("src-queue"),
            "{error}"
        );
        // A stream read from an offset: `src-consumer-args` as a TOML table.
        let stream = "[shovels.log]\nsrc-uri = \"amqp://\"\nsrc-queue = \"log\"\ndest-uri = \"amqp://a\"\ndest-queue = \"f\"\n";
        let settings = Settings::resolve(
            cli(&[]),
            file(&format!(
                "{stream}src-consumer-args = {{ x-stream-offset = \"first\" }}\n"
            )),
        )
        .unwrap();
        assert_eq!(
            settings.shovels[0].1["src-consumer-args"],
            serde_json::json!({"x-stream-offset": "first"})
        );
        let error = Settings::resolve(
            cli(&[]),
            file(&format!(
                "{stream}src-consumer-args = {{ x-stream-offset = -1 }}\n"
            )),
        )
        .unwrap_err()
        .to_string();
        assert!(
            error.contains("shovel log") && error.contains("is not an offset"),
            "{error}"
        );
    }

    #[test]
    fn mqtt_listeners_come_from_the_command_line_or_the_file() {
        let resolve = |cli_args: &[&str], text: &str| Settings::resolve(cli(cli_args), file(text));
        let default = "0.0.0.0:1883".parse::<SocketAddr>().unwrap();
        assert_eq!(resolve(&[], "").unwrap().mqtt_listen, [default]);
        assert!(resolve(&[], "mqtt-listen = []")
            .unwrap()
            .mqtt_listen
            .is_empty());
        let off = resolve(&["--mqtt-listen", "none"], "");
        assert!(off.unwrap().mqtt_listen.is_empty());
        let addr: SocketAddr = "127.0.0.1:1883".parse().unwrap();
        let from_file = resolve(&[], "mqtt-listen = [\"127.0.0.1:1883\"]").unwrap();
        assert_eq!(from_file.mqtt_listen, [addr]);
        let from_cli = resolve(
            &["--mqtt-listen", "127.0.0.1:1884"],
            "mqtt-listen = [\"127.0.0.1:1883\"]",
        );
        assert_eq!(
            from_cli.unwrap().mqtt_listen,
            ["127.0.0.1:1884".parse().unwrap()]
        );
        // TLS and WebSocket: off unless given; TLS needs the files.
        let plain = resolve(&[], "").unwrap();
        assert!(plain.mqtts_listen.is_empty() && plain.web_mqtt_listen.is_empty());
        assert!(!plain.mqtt_ssl_cert_login);
        assert!(resolve(&["--mqtts-listen", "127.0.0.1:8883"], "").is_err());
        let all = resolve(
            &["--web-mqtt-listen", "127.0.0.1:15675"],
            "mqtts-listen = [\"127.0.0.1:8883\"]\nmqtt-ssl-cert-login = true\n\
             tls-certfile = \"c.pem\"\ntls-keyfile = \"k.pem\"",
        )
        .unwrap();
        assert_eq!(all.mqtts_listen, ["127.0.0.1:8883".parse().unwrap()]);
        assert_eq!(all.web_mqtt_listen, ["127.0.0.1:15675".parse().unwrap()]);
        assert!(all.mqtt_ssl_cert_login);
        // The session expiry cap: a day, seconds, or infinity.
        assert_eq!(plain.mqtt_max_session_expiry_interval, Some(86_400));
        let capped = resolve(&[], "mqtt-max-session-expiry-interval-seconds = 60").unwrap();
        assert_eq!(capped.mqtt_max_session_expiry_interval, Some(60));
        let infinity = "mqtt-max-session-expiry-interval-seconds = \"infinity\"";
        assert_eq!(
            resolve(&[], infinity)
                .unwrap()
                .mqtt_max_session_expiry_interval,
            None
        );
        assert!(resolve(&[], "mqtt-max-session-expiry-interval-seconds = \"never\"").is_err());
        assert!(
            all.ops().tls.is_some(),
            "the certificate expiry check covers it"
        );
    }

    #[test]
    fn tls_settings_follow_rabbitmqs_ssl_options() {
        let tls = |cli_args: &[&str], text: &str| Settings::resolve(cli(cli_args), file(text));
        let plain = tls(&[], "").unwrap();
        assert!(plain.tls.is_none() && plain.tls_listen.is_empty());
        let settings = tls(
            &["--tls-listen", "127.0.0.1:5671"],
            "tls-certfile = \"c.pem\"\ntls-keyfile = \"k.pem\"\ntls-cacertfile = \"ca.pem\"\n\
             tls-fail-if-no-peer-cert = true",
        )
        .unwrap();
        assert_eq!(settings.tls_listen, ["127.0.0.1:5671".parse().unwrap()]);
        assert_eq!(
            settings.tls,
            Some(TlsOptions {
                certfile: "c.pem".into(),
                keyfile: "k.pem".into(),
                cacertfile: Some("ca.pem".into()),
                verify: PeerVerification::Required,
            })
        );
        let optional = tls(
            &[
                "--tls-certfile",
                "c",
                "--tls-keyfile",
                "k",
                "--tls-cacertfile",
                "ca",
            ],
            "",
        )
        .unwrap();
        assert_eq!(optional.tls.unwrap().verify, PeerVerification::Optional);
        for (args, text, why) in [
            (
                &["--tls-listen", "127.0.0.1:5671"][..],
                "",
                "needs tls-certfile",
            ),
            (&["--tls-certfile", "c"][..], "", "both"),
            (
                &["--tls-certfile", "c", "--tls-keyfile", "k"][..],
                "tls-verify = \"verify_peer\"",
                "needs tls-cacertfile",
            ),
            (
                &["--tls-certfile", "c", "--tls-keyfile", "k"][..],
                "tls-verify = \"sometimes\"",
                "not sometimes",
            ),
        ] {
            let error = tls(args, text).unwrap_err().to_string();
            assert!(error.contains(why), "{error}");
        }
    }

    #[test]
    fn defaults_without_a_file_or_flags() {
        let settings = Settings::resolve(Cli::default(), FileConfig::default()).unwrap();
        assert_eq!(settings.listen, vec!["0.0.0.0:5672".parse().unwrap()]);
        assert_eq!(settings.data_dir, PathBuf::from("leveret-data"));
        assert_eq!(settings.log, "info");
        assert_eq!(settings.log_format, LogFormat::Text);
        assert_eq!(settings.busy_poll, Duration::from_micros(200));
        assert_eq!(settings.product, None);
        assert_eq!(settings.metrics_listen, "127.0.0.1:15692".parse().unwrap());
        assert_eq!(settings.http_listen, "127.0.0.1:15672".parse().unwrap());
        assert!(settings.users.is_empty() && settings.vhosts.is_empty());
        let defaults = Limits::default();
        assert_eq!(settings.limits.frame_max, defaults.frame_max);
        assert_eq!(settings.limits.heartbeat, defaults.heartbeat);
    }

    #[test]
    fn every_file_key_is_read() {
        let hash = PasswordHash::new("secret");
        let text = format!(
            r#"
            listen = ["127.0.0.1:5700", "[::1]:5701"]
            data-dir = "/var/lib/leveret"
            log = "debug"
            log-format = "json"
            log-file = "/var/log/leveret/leveret.log"
            vhosts = ["/", "robots"]
            heartbeat = 30
            frame-max = 8192
            channel-max = 16
            max-message-size = 1000
            memory-high-watermark = 268435456
            product = "RabbitMQ"
            busy-poll = 0
            metrics-listen = "127.0.0.1:9999"
            http-listen = "127.0.0.1:9998"
            definitions = "/etc/leveret/definitions.json"

            [[users]]
            name = "robot"
            password-hash = "{}"

            [[users]]
            name = "tool"
            password = "plain"
            max-connections = 3
            max-channels = 10

            [[users]]
            name = "from-rabbitmq"
            password-hash = "XrbDVjlDKoAec+dZ1vISo+jt5TVEqQvMa8euInsOyfsIm1Ys"
            hashing-algorithm = "rabbit_password_hashing_sha256"
            "#,
            hash.to_phc().unwrap()
        );
        let settings = Settings::resolve(Cli::default(), file(&text)).unwrap();
        assert_eq!(
            settings.listen,
            vec![
                "127.0.0.1:5700".parse().unwrap(),
                "[::1]:5701".parse().unwrap()
            ]
        );
        assert_eq!(settings.data_dir, PathBuf::from("/var/lib/leveret"));
        assert_eq!(settings.log, "debug");
        assert_eq!(settings.log_format, LogFormat::Json);
        assert_eq!(
            settings.log_file,
            Some(PathBuf::from("/var/log/leveret/leveret.log"))
        );
        assert_eq!(settings.vhosts, ["/", "robots"]);
        assert_eq!(settings.loopback_users, None);
        let open = Settings::resolve(cli(&[]), file("loopback-users = []")).unwrap();
        assert_eq!(open.loopback_users, Some(Vec::new()));
        assert_eq!(settings.limits.heartbeat, 30);
        assert_eq!(settings.limits.frame_max, 8192);
        assert_eq!(settings.limits.channel_max, 16);
        assert_eq!(settings.limits.max_message_size, 1000);
        assert_eq!(settings.limits.memory_high_watermark, 268_435_456);
        assert_eq!(
            settings.limits.user_limits,
            [(
                "tool".to_owned(),
                UserLimits {
                    max_connections: Some(3),
                    max_channels: Some(10)
                }
            )]
            .into()
        );
        assert_eq!(settings.product.as_deref(), Some("RabbitMQ"));
        assert_eq!(settings.busy_poll, Duration::ZERO);
        assert_eq!(settings.metrics_listen, "127.0.0.1:9999".parse().unwrap());
        assert_eq!(settings.http_listen, "127.0.0.1:9998".parse().unwrap());
        assert_eq!(
            settings.definitions,
            Some(PathBuf::from("/etc/leveret/definitions.json"))
        );
        assert_eq!(
            settings.users,
            vec![
                ("robot".to_owned(), Credential::Hash(hash)),
                ("tool".to_owned(), Credential::Password("plain".into())),
                (
                    "from-rabbitmq".to_owned(),
                    Credential::Hash(
                        PasswordHash::from_rabbitmq(
                            "XrbDVjlDKoAec+dZ1vISo+jt5TVEqQvMa8euInsOyfsIm1Ys",
                            leveret_broker::RABBIT_SHA256
                        )
                        .unwrap()
                    )
                ),
            ]
        );
    }

    #[test]
    fn the_command_line_wins_over_the_file() {
        let text = r#"
            listen = ["127.0.0.1:5700"]
            data-dir = "from-file"
            log = "debug"
            product = "FromFile"
            busy-poll = 50
            worker-threads = 2
            metrics-listen = "127.0.0.1:9999"
        "#;
        let flags = cli(&[
            "--listen",
            "127.0.0.1:6000",
            "--data-dir",
            "from-flag",
            "--log",
            "warn",
            "--product",
            "FromFlag",
            "--busy-poll",
            "7",
            "--worker-threads",
            "4",
            "--metrics-listen",
            "127.0.0.1:0",
        ]);
        let settings = Settings::resolve(flags, file(text)).unwrap();
        assert_eq!(settings.listen, vec!["127.0.0.1:6000".parse().unwrap()]);
        assert_eq!(settings.data_dir, PathBuf::from("from-flag"));
        assert_eq!(settings.log, "warn");
        assert_eq!(settings.product.as_deref(), Some("FromFlag"));
        assert_eq!(settings.busy_poll, Duration::from_micros(7));
        assert_eq!(settings.worker_threads, 4);
        let from_file = Settings::resolve(cli(&[]), file("worker-threads = 2")).unwrap();
        assert_eq!(from_file.worker_threads, 2);
        let default = Settings::resolve(cli(&[]), file("")).unwrap();
        assert_eq!(default.worker_threads, 1);
        assert_eq!(settings.metrics_listen, "127.0.0.1:0".parse().unwrap());
    }

    #[test]
    fn rabbitmq_limit_keys_are_read() {
        let text = r#"
            max-connections = 100
            handshake-timeout = 2500
            vm-memory-high-watermark-absolute = 104857600

            [vhost-limits."/"]
            max-connections = 10
            max-queues = 50

            [vhost-limits.robots]
            max-queues = 5
        "#;
        let settings = Settings::resolve(Cli::default(), file(text)).unwrap();
        let limits = &settings.limits;
        assert_eq!(limits.max_connections, Some(100));
        assert_eq!(limits.handshake_timeout, Duration::from_millis(2500));
        assert_eq!(
            limits.resident_memory_high_watermark,
            ResidentMemoryWatermark::Absolute(104_857_600)
        );
        assert_eq!(limits.vhost_limits["/"].max_connections, Some(10));
        assert_eq!(limits.vhost_limits["/"].max_queues, Some(50));
        assert_eq!(limits.vhost_limits["robots"].max_connections, None);
        assert_eq!(limits.vhost_limits["robots"].max_queues, Some(5));
        let relative = file("vm-memory-high-watermark-relative = 0.6");
        let settings = Settings::resolve(Cli::default(), relative).unwrap();
        assert_eq!(
            settings.limits.resident_memory_high_watermark,
            ResidentMemoryWatermark::Relative(0.6)
        );
        assert!(FileConfig::parse("[vhost-limits.x]\nmax-queus = 1").is_err());
    }

    #[test]
    fn the_disk_free_limit_comes_from_the_flag_the_file_or_the_default() {
        let settings = Settings::resolve(Cli::default(), FileConfig::default()).unwrap();
        assert_eq!(settings.limits.disk_free_limit, 50_000_000);
        let settings =
            Settings::resolve(Cli::default(), file("disk-free-limit = 1000000000")).unwrap();
        assert_eq!(settings.limits.disk_free_limit, 1_000_000_000);
        let rabbitmq_style = file("disk-free-limit-absolute = 2000000000");
        let settings = Settings::resolve(Cli::default(), rabbitmq_style).unwrap();
        assert_eq!(settings.limits.disk_free_limit, 2_000_000_000);
        let flag = cli(&["--disk-free-limit", "123"]);
        let settings = Settings::resolve(flag, file("disk-free-limit = 5")).unwrap();
        assert_eq!(settings.limits.disk_free_limit, 123);
        assert!(FileConfig::parse("disk-free-limit = -1").is_err());
    }

    #[test]
    fn unknown_keys_and_wrong_types_are_refused() {
        assert!(FileConfig::parse("listne = []").is_err());
        assert!(FileConfig::parse("heartbeat = 70000").is_err());
        assert!(FileConfig::parse("listen = [\"not an address\"]").is_err());
        assert!(FileConfig::parse("[[users]]\nname = \"a\"\npasswd = \"x\"").is_err());
    }

    #[test]
    fn a_user_needs_exactly_one_valid_credential() {
        let both = file("[[users]]\nname = \"a\"\npassword = \"x\"\npassword-hash = \"00\"");
        assert!(matches!(
            Settings::resolve(Cli::default(), both),
            Err(ConfigError::Credentials(name)) if name == "a"
        ));
        let neither = file("[[users]]\nname = \"b\"");
        assert!(matches!(
            Settings::resolve(Cli::default(), neither),
            Err(ConfigError::Credentials(name)) if name == "b"
        ));
        let bad = file("[[users]]\nname = \"c\"\npassword-hash = \"zz\"");
        assert!(matches!(
            Settings::resolve(Cli::default(), bad),
            Err(ConfigError::BadHash(name)) if name == "c"
        ));
    }

    /// The fenced code blocks of a Markdown page: each block's language
    /// (the info string up to its first comma) and its text.
    fn fenced_blocks(page: &str) -> Vec<(&str, String)> {
        let mut blocks = Vec::new();
        let mut open: Option<(&str, String)> = None;
        for line in page.lines() {
            match (line.strip_prefix("```"), open.take()) {
                (Some(_), Some(block)) => blocks.push(block),
                (Some(info), None) => {
                    open = Some((info.split(',').next().unwrap_or_default(), String::new()))
                }
                (None, Some((language, mut text))) => {
                    text.push_str(line);
                    text.push('\n');
                    open = Some((language, text));
                }
                (None, None) => {}
            }
        }
        assert!(open.is_none(), "a code block is never closed");
        blocks
    }

    /// The README's and `docs/`' examples are what the binary takes: every
    /// `toml` block is a config file that parses and resolves as at start
    /// (or, when its first line is `# Cargo.toml`, a manifest whose path
    /// dependencies are this workspace's crates), and every `leveret`
    /// command line in a `sh` block parses with the binary's command line.
    /// `packaging/leveret.toml` with every commented setting (`# key = ..`,
    /// `# [table]`) uncommented is a config the binary takes, and every
    /// setting sits under a `##` line that explains it.
    #[test]
    fn the_packaged_example_config_is_one_the_binary_takes() {
        let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("../packaging/leveret.toml");
        let text = std::fs::read_to_string(&path).expect("read the example");
        let (mut all, mut explained, mut settings) = (String::new(), false, 0);
        for line in text.lines() {
            // `## text` explains; `# key = ..` is a setting, commented.
            let setting = line.strip_prefix("# ").unwrap_or(line);
            if line.starts_with("##") {
                explained = true;
            } else if line.trim().is_empty() {
                explained = false;
            } else {
                assert!(explained, "no ## line explains: {line}");
                settings += 1;
            }
            all.push_str(setting);
            all.push('\n');
        }
        assert!(settings > 60, "{settings} settings");
        // Every top-level key the binary knows (serde lists them when it
        // refuses an unknown one) is shown.
        let refusal = FileConfig::parse("no-such-key = 1")
            .expect_err("unknown keys are refused")
            .to_string();
        let known = refusal.split("expected one of").nth(1).expect("a key list");
        for key in known.split(',').map(|key| key.trim().trim_matches('`')) {
            assert!(text.contains(key), "the example does not show `{key}`");
        }
        let config = FileConfig::parse(&all).unwrap_or_else(|e| panic!("{all}{e}"));
        if let Err(e) = Settings::resolve(Cli::default(), config) {
            panic!("{all}{e}");
        }
    }

    #[test]
    fn every_toml_block_in_the_docs_is_a_config_the_binary_takes() {
        let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("..");
        let mut pages = vec![root.join("README.md")];
        for entry in std::fs::read_dir(root.join("docs")).expect("read docs/") {
            let path = entry.expect("a docs/ entry").path();
            if path.extension().is_some_and(|extension| extension == "md") {
                pages.push(path);
            }
        }
        let (mut configs, mut manifests, mut commands) = (0, 0, 0);
        for page in &pages {
            let text = std::fs::read_to_string(page).expect("read a page");
            for (language, block) in fenced_blocks(&text) {
                let whence = format!("{}:\n{block}", page.display());
                match language {
                    "toml" if block.starts_with("# Cargo.toml") => {
                        let manifest: toml::Table =
                            toml::from_str(&block).unwrap_or_else(|e| panic!("{whence}{e}"));
                        let dependencies = manifest["dependencies"].as_table().expect("deps");
                        for (name, dependency) in dependencies {
                            let Some(path) = dependency.get("path").and_then(|p| p.as_str()) else {
                                continue;
                            };
                            let crate_manifest = root.join(path).join("Cargo.toml");
                            let crate_manifest = std::fs::read_to_string(&crate_manifest)
                                .unwrap_or_else(|e| panic!("{whence}{path}: {e}"));
                            assert!(
                                crate_manifest.contains(&format!("name = \"{name}\"")),
                                "{whence}{path} is not the crate {name}"
                            );
                        }
                        manifests += 1;
                    }
                    "toml" => {
                        let config =
                            FileConfig::parse(&block).unwrap_or_else(|e| panic!("{whence}{e}"));
                        if let Err(e) = Settings::resolve(Cli::default(), config) {
                            panic!("{whence}{e}");
                        }
                        configs += 1;
                    }
                    "sh" => {
                        for line in block.lines() {
                            let words: Vec<&str> =
                                line.trim_end_matches('&').split_whitespace().collect();
                            let program = words.first().copied().unwrap_or_default();
                            if program == "leveret" || program.ends_with("/leveret") {
                                if let Err(e) = Cli::try_parse_from(&words) {
                                    panic!("{whence}{e}");
                                }
                                commands += 1;
                            }
                        }
                    }
                    _ => {}
                }
            }
        }
        // The configuration page's, the uplink's three, the ports' manifest,
        // the README's and the pages' command lines: none went unchecked.
        assert!(
            configs >= 4 && manifests >= 1 && commands >= 3,
            "{configs} configs, {manifests} manifests, {commands} command lines"
        );
    }

    #[test]
    fn a_missing_file_names_itself() {
        let path = Path::new("/nonexistent/leveret.toml");
        let error = FileConfig::load(path).unwrap_err();
        assert!(
            error.to_string().contains("/nonexistent/leveret.toml"),
            "{error}"
        );
    }
}
