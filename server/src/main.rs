//! # leveret
//!
//! The `leveret` binary: an edge AMQP 0.9.1 broker, the `leveret-broker`
//! library with a command line, a TOML config file and logging around it.
//! Options come from the command line, or from a TOML file given with
//! `--config` (every flag has a key of the same name; the command line
//! wins). An embedder uses the library directly and compiles none of this
//! crate's dependencies (clap, serde, toml, tracing-subscriber).
//!
//! # Layout
//! - `main`: the runtime, start-up, and shutdown on SIGINT or SIGTERM.
//! - `cli`: the command line (clap).
//! - `config`: the config file (serde, toml) and its merge with the
//!   command line into the library's `BrokerBuilder`; `environment`: the
//!   resolved settings as `leveretctl environment` shows them.
//! - `logging`: the tracing subscriber (text or JSON lines, to standard
//!   error or to a file reopened on SIGHUP).
//! - `ops`: the operators' listeners on a thread of their own, served by
//!   `http` (bounded connections, timeouts); `metrics` is the Prometheus
//!   endpoint, reading `process` figures beside the broker's; `management`
//!   is the management HTTP API; `definitions` reads and writes RabbitMQ's
//!   definitions.json (`--definitions`, `/api/definitions`).
//! - `resident`: the start-up code given back to the kernel once the
//!   broker serves.
//!
//! Each uses only the `leveret-broker` public API; `main` uses the others.
//!
//! The binary allocates with jemalloc (an embedder keeps its own
//! allocator): the persister thread frees what connections allocated, and
//! glibc's malloc serialises such frees on the allocating thread's arena
//! lock. `MALLOC_CONF` below sets its defaults; `_RJEM_MALLOC_CONF` in the
//! environment overrides them.
#![deny(unsafe_code)]

mod cli;
mod config;
mod definitions;
mod environment;
mod federation;
mod http;
mod logging;
mod management;
mod metrics;
mod ops;
mod policies;
mod process;
mod resident;
mod uplink;

use clap::Parser;
use cli::Cli;
use config::{FileConfig, Settings};
use definitions::Definitions;
use leveret_broker::PasswordHash;
use std::process::ExitCode;
use std::sync::Arc;

#[cfg(not(target_env = "msvc"))]
#[global_allocator]
static ALLOCATOR: tikv_jemallocator::Jemalloc = tikv_jemallocator::Jemalloc;

/// jemalloc's options, read once at its start (figures in
/// docs/performance.md, "Idle memory"):
/// - `percpu_arena:percpu`: one arena per CPU a thread runs on, instead
///   of four per CPU; fewer arenas idle with less metadata, and threads on
///   different cores still never share one.
/// - `background_thread:true`: a jemalloc thread returns freed pages to
///   the system on its own, so memory a burst used goes back while the
///   broker is idle (otherwise only a later allocation purges).
/// - `dirty_decay_ms:1000,muzzy_decay_ms:0`: freed pages go back after
///   about a second instead of ten.
///
/// The symbol is jemalloc's `malloc_conf` (tikv-jemalloc-sys prefixes its
/// names with `_rjem_`): a C string it reads before the first allocation.
#[cfg(not(target_env = "msvc"))]
#[allow(unsafe_code)] // an exported symbol, which the linker could clash.
#[unsafe(export_name = "_rjem_malloc_conf")]
pub static MALLOC_CONF: &[u8; 80] =
    b"percpu_arena:percpu,background_thread:true,dirty_decay_ms:1000,muzzy_decay_ms:0\0";

/// Exit status for a command line or config file that cannot be used.
const USAGE_ERROR: u8 = 2;

fn main() -> ExitCode {
    let cli = Cli::parse();
    if cli.hash_password {
        return hash_password();
    }
    let file = match &cli.config {
        Some(path) => FileConfig::load(path),
        None => Ok(FileConfig::default()),
    };
    let settings = match file.and_then(|file| Settings::resolve(cli, file)) {
        Ok(settings) => settings,
        Err(e) => {
            eprintln!("leveret: {e}");
            return ExitCode::from(USAGE_ERROR);
        }
    };
    let runtime = match runtime(settings.worker_threads) {
        Ok(runtime) => runtime,
        Err(e) => {
            eprintln!("leveret: cannot start the runtime: {e}");
            return ExitCode::FAILURE;
        }
    };
    runtime.block_on(serve(settings))
}

/// By default one thread serves every connection: busy polling needs the
/// thread that spins to be the one that polls the sockets (one worker
/// against two: perf/results/2026-11-27/worker-threads-9935aa7.txt).
/// `worker-threads` above 1 gives tokio's multi-thread runtime.
/// Storage has a thread of its own either way.
fn runtime(worker_threads: usize) -> std::io::Result<tokio::runtime::Runtime> {
    let mut builder = match worker_threads {
        0 | 1 => tokio::runtime::Builder::new_current_thread(),
        workers => {
            let mut builder = tokio::runtime::Builder::new_multi_thread();
            builder.worker_threads(workers);
            builder
        }
    };
    builder.enable_all().build()
}

async fn serve(settings: Settings) -> ExitCode {
    let log_file = match &settings.log_file {
        None => None,
        Some(path) => match logging::LogFile::open(path) {
            Ok(file) => Some(file),
            Err(e) => {
                eprintln!("leveret: cannot open the log file {}: {e}", path.display());
                return ExitCode::from(USAGE_ERROR);
            }
        },
    };
    logging::init(&settings.log, settings.log_format, log_file.clone());
    process::raise_open_files_limit();
    let ops_settings = settings.ops();
    let banner = Banner {
        config_file: settings.config_file.clone(),
        data_dir: settings.data_dir.clone(),
    };
    let configured = Configured {
        shovels: settings.shovels.clone(),
        federation_upstreams: settings.federation_upstreams.clone(),
        policies: settings.policies.clone(),
    };
    let definitions = match &settings.definitions {
        None => None,
        Some(path) => {
            let parsed = std::fs::read(path)
                .map_err(|e| e.to_string())
                .and_then(|bytes| Definitions::parse(&bytes));
            match parsed {
                Ok(definitions) => Some(definitions),
                Err(e) => {
                    eprintln!("leveret: definitions {}: {e}", path.display());
                    return ExitCode::from(USAGE_ERROR);
                }
            }
        }
    };
    let mut signals = match Signals::register(log_file) {
        Ok(signals) => signals,
        Err(e) => {
            tracing::error!(error = %e, "cannot watch for signals");
            return ExitCode::FAILURE;
        }
    };
    // The listeners accept once the stored policies and the definitions
    // are in force (`run`): a client never sees a queue without them.
    let mut builder = settings.builder().hold_listeners();
    if let Some(definitions) = &definitions {
        builder = definitions.configure(builder);
    }
    let handle = match builder.start().await {
        Ok(handle) => Arc::new(handle),
        Err(e) => {
            tracing::error!(error = %e, "cannot start");
            return ExitCode::FAILURE;
        }
    };
    let links = uplink::Links {
        shovels: uplink::Shovels::new(&handle),
        federation: federation::Federation::new(&handle, process::node_name()),
    };
    let outcome = run(
        &handle,
        &links,
        definitions,
        configured,
        (ops_settings, banner),
        &mut signals,
    )
    .await;
    links.stop_all().await;
    match Arc::try_unwrap(handle) {
        Ok(handle) => handle.shutdown().await,
        Err(_) => tracing::error!("the broker is still in use; stopping without a clean shutdown"),
    }
    outcome
}

/// The config file's shovels, federation upstreams and policies.
struct Configured {
    shovels: Vec<(String, serde_json::Value)>,
    federation_upstreams: Vec<(String, serde_json::Value)>,
    policies: Vec<(String, serde_json::Value)>,
}

/// What the start banner names besides the listeners.
struct Banner {
    config_file: Option<std::path::PathBuf>,
    data_dir: std::path::PathBuf,
}

impl Banner {
    /// One info line once everything listens: the version, the config
    /// file, the data directory and every listener with its protocol
    /// (RabbitMQ's names: amqp, amqp/ssl, mqtt, mqtt/ssl, http/web-mqtt,
    /// http, http/prometheus).
    fn log(self, ops: &ops::Ops) {
        let version = env!("CARGO_PKG_VERSION");
        let config_file = match &self.config_file {
            Some(path) => path.display().to_string(),
            None => "none".to_owned(),
        };
        let data_dir = std::fs::canonicalize(&self.data_dir).unwrap_or(self.data_dir);
        let listeners: Vec<String> = (ops.listeners.iter())
            .map(|(protocol, addr)| match *protocol {
                "http" => format!("http {addr} (management API)"),
                _ => format!("{protocol} {addr}"),
            })
            .collect();
        let listeners = listeners.join(", ");
        tracing::info!(
            version,
            %config_file,
            data_dir = %data_dir.display(),
            %listeners,
            "Leveret {version} started; config file: {config_file}; data directory: {}; listeners: {listeners}",
            data_dir.display()
        );
    }
}

/// Sets the stored and configured policies, loads the definitions,
/// starts the shovels and federation, then opens the listeners (held
/// until then) and the operators' listeners, logs the start banner, and
/// serves until a signal says stop.
async fn run(
    handle: &Arc<leveret_broker::BrokerHandle>,
    links: &uplink::Links,
    definitions: Option<Definitions>,
    configured: Configured,
    (ops_settings, banner): (ops::OpsSettings, Banner),
    signals: &mut Signals,
) -> ExitCode {
    links.shovels.start_stored().await;
    links.federation.start_stored().await;
    policies::start_stored(&handle.admin(), &links.federation).await;
    for (name, parameters) in configured.shovels {
        if let Err(e) = links.shovels.start("/", &name, parameters).await {
            tracing::error!(shovel = %name, error = %e, "cannot start the shovel");
            return ExitCode::FAILURE;
        }
    }
    for (name, value) in configured.federation_upstreams {
        if let Err(e) = links
            .federation
            .set_upstream("/", &name, value, false)
            .await
        {
            tracing::error!(upstream = %name, error = %e, "cannot use the federation upstream");
            return ExitCode::FAILURE;
        }
    }
    let configured_policies: Vec<policies::Item> = configured
        .policies
        .iter()
        .map(|(name, value)| policies::Item {
            kind: leveret_broker::PolicyKind::User,
            vhost: "/",
            name,
            value,
        })
        .collect();
    if let Err((at, e)) = policies::set_all(
        &handle.admin(),
        &links.federation,
        &configured_policies,
        false,
    )
    .await
    {
        let name = configured_policies[at].name;
        tracing::error!(policy = %name, error = %e, "cannot use the policy");
        return ExitCode::FAILURE;
    }
    links.federation.keep_in_step();
    if let Some(mut definitions) = definitions {
        match definitions.apply(&handle.admin(), links).await {
            // Vhosts, users and permissions were in place before the
            // apply (the builder took them): every item counts, not only
            // what the apply changed.
            Ok(_changed) => tracing::info!("definitions loaded: {}", definitions.summary()),
            Err(e) => {
                tracing::error!(error = %e, "cannot load the definitions");
                return ExitCode::FAILURE;
            }
        }
        for warning in &definitions.warnings {
            tracing::warn!(%warning, "definitions");
        }
    }
    handle.open_listeners();
    let ops = match ops::Ops::start(
        handle.admin(),
        links.clone(),
        handle.local_addrs(),
        (handle.tls_addrs().iter().map(|addr| ("amqp/ssl", *addr)))
            .chain(handle.mqtt_addrs().iter().map(|addr| ("mqtt", *addr)))
            .chain(handle.mqtts_addrs().iter().map(|addr| ("mqtt/ssl", *addr)))
            .chain(
                handle
                    .web_mqtt_addrs()
                    .iter()
                    .map(|a| ("http/web-mqtt", *a)),
            )
            .collect(),
        ops_settings,
    ) {
        Ok(ops) => ops,
        Err(e) => {
            tracing::error!(error = %e, "cannot start");
            return ExitCode::FAILURE;
        }
    };
    banner.log(&ops);
    // Its own task: a stop asked for meanwhile is not kept waiting.
    tokio::spawn(resident::release_start_up_code());
    signals.wait_for_stop(handle).await;
    tracing::info!("shutting down");
    ops.stop();
    ExitCode::SUCCESS
}

/// `--hash-password`: one line of standard input in, its hash out.
fn hash_password() -> ExitCode {
    let mut password = String::new();
    if std::io::stdin().read_line(&mut password).is_err() {
        eprintln!("leveret: cannot read the password from standard input");
        return ExitCode::from(USAGE_ERROR);
    }
    let password = password.trim_end_matches(['\r', '\n']);
    let hash = PasswordHash::new(password);
    println!("{}", hash.to_phc().unwrap_or_default());
    ExitCode::SUCCESS
}

/// SIGINT, SIGTERM and SIGHUP, watched from before the broker starts: a
/// signal sent as soon as a listener answers is acted on, where without a
/// handler SIGTERM would end the process with no clean shutdown.
#[cfg(unix)]
struct Signals {
    interrupt: tokio::signal::unix::Signal,
    terminate: tokio::signal::unix::Signal,
    hangup: tokio::signal::unix::Signal,
    /// The log file SIGHUP reopens.
    log_file: Option<logging::LogFile>,
}

#[cfg(unix)]
impl Signals {
    fn register(log_file: Option<logging::LogFile>) -> std::io::Result<Signals> {
        use tokio::signal::unix::{signal, SignalKind};
        Ok(Signals {
            interrupt: signal(SignalKind::interrupt())?,
            terminate: signal(SignalKind::terminate())?,
            hangup: signal(SignalKind::hangup())?,
            log_file,
        })
    }

    /// Waits for SIGINT or SIGTERM; SIGHUP meanwhile reopens the log
    /// file and re-reads the TLS certificate files.
    async fn wait_for_stop(&mut self, handle: &leveret_broker::BrokerHandle) {
        loop {
            tokio::select! {
                _ = self.interrupt.recv() => return,
                _ = self.terminate.recv() => return,
                _ = self.hangup.recv() => {
                    if let Some(file) = &self.log_file {
                        match file.reopen() {
                            Ok(()) => tracing::info!("log file reopened"),
                            Err(e) => tracing::error!(error = %e, "log file not reopened; writing on to the one open"),
                        }
                    }
                    if handle.tls_addrs().is_empty() {
                        continue;
                    }
                    match handle.reload_tls() {
                        Ok(()) => tracing::info!("TLS certificates reloaded"),
                        Err(e) => tracing::error!(error = %e, "TLS certificates not reloaded; the previous ones stay in use"),
                    }
                }
            }
        }
    }
}

/// Ctrl-C, where there are no Unix signals.
#[cfg(not(unix))]
struct Signals;

#[cfg(not(unix))]
impl Signals {
    /// (A log file is not reopened where there is no SIGHUP.)
    fn register(_log_file: Option<logging::LogFile>) -> std::io::Result<Signals> {
        Ok(Signals)
    }

    async fn wait_for_stop(&mut self, _handle: &leveret_broker::BrokerHandle) {
        let _ = tokio::signal::ctrl_c().await;
    }
}
