//! # leveretctl
//!
//! A command line over Leveret's management HTTP API in the style of
//! `rabbitmqctl`: the same command names, `-p VHOST`, and for the `list_*`
//! commands rabbitmqctl's column names and tab-separated output (a header
//! line unless `--no-table-headers`; the "Listing ..." line unless `-q`).
//! `--url` names the API (default `http://127.0.0.1:15672`, guest/guest).
//! The `port` commands (`port list`, `stats`, `echo`, `hz`, `bw`)
//! speak AMQP instead, to `--amqp-url` (default
//! `amqp://guest:guest@127.0.0.1:5672/%2f`, its vhost the URL's), and
//! show the robot data ports that announce themselves there.
//!
//! `--formatter json` prints listings as a JSON array of objects keyed by
//! column name, and `status` as one JSON object; `table` (the default) is
//! rabbitmqctl's text. A column a listing does not have is reported on
//! standard error after the other columns are printed.
//!
//! Exit status, as rabbitmqctl's: 0 on success, 64 for a command line it
//! cannot use (an unknown column included), 69 when the API (or, for
//! `port`, the broker) cannot be reached, 75 when `await_startup` times
//! out, 1 when the broker refuses the request (or the port named does not
//! announce itself).
//!
//! # Layout
//! - `main`: the command line and the commands.
//! - `client`: the HTTP client (ureq).
//! - `columns`: rabbitmqctl's column names mapped onto the API's fields.
//! - `limits`: the vhost and user limit commands.
//! - `ports`: the `port` commands, over AMQP with leveret-client.
//! - `policies`: the policy, operator policy and cluster name commands.
#![forbid(unsafe_code)]

mod client;
mod columns;
mod limits;
mod policies;
mod ports;
mod recorder;

use clap::{Parser, Subcommand};
use client::{segment, Client, ClientError};
use serde_json::Value;
use std::io::{Read, Write};
use std::path::PathBuf;
use std::process::ExitCode;

/// Exit status for a command line that cannot be used (EX_USAGE).
const USAGE: u8 = 64;
/// Exit status when the API cannot be reached (EX_UNAVAILABLE).
const UNAVAILABLE: u8 = 69;
/// Exit status when waiting timed out (EX_TEMPFAIL).
const TIMED_OUT: u8 = 75;
/// How often `await_startup` asks.
const STARTUP_POLL: std::time::Duration = std::time::Duration::from_millis(200);

/// How results are printed.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
enum Formatter {
    /// rabbitmqctl's text: tab-separated listings.
    Table,
    /// JSON.
    Json,
}

/// Manage a Leveret broker through its management HTTP API.
#[derive(Debug, Parser)]
#[command(name = "leveretctl", version, about)]
struct Cli {
    /// The management API.
    #[arg(long, default_value = "http://127.0.0.1:15672", global = true)]
    url: String,
    /// The broker's AMQP listener, for the `port` commands.
    #[arg(
        long,
        default_value = "amqp://guest:guest@127.0.0.1:5672/%2f",
        global = true
    )]
    amqp_url: String,
    /// User for the API.
    #[arg(long, default_value = "guest", global = true)]
    username: String,
    /// Password for the API.
    #[arg(long, default_value = "guest", global = true)]
    password: String,
    /// Vhost for the commands that act on one.
    #[arg(short = 'p', long = "vhost", default_value = "/", global = true)]
    vhost: String,
    /// No informational lines, only results.
    #[arg(short = 'q', long, global = true)]
    quiet: bool,
    /// No header line in listings.
    #[arg(long, global = true)]
    no_table_headers: bool,
    /// Output format of listings and `status`.
    #[arg(long, value_enum, default_value = "table", global = true)]
    formatter: Formatter,
    #[command(subcommand)]
    command: Command,
}

#[derive(Debug, Subcommand)]
#[command(rename_all = "snake_case")]
enum Command {
    /// Lists queues: name, messages by default (rabbitmqctl's columns).
    ListQueues { columns: Vec<String> },
    /// Lists exchanges: name, type by default.
    ListExchanges { columns: Vec<String> },
    /// Lists bindings: source_name, source_kind, destination_name,
    /// destination_kind, routing_key, arguments by default.
    ListBindings { columns: Vec<String> },
    /// Lists connections: user, peer_host, peer_port, state by default.
    ListConnections { columns: Vec<String> },
    /// Lists consumers: queue_name, channel_pid, consumer_tag,
    /// ack_required, prefetch_count, active, arguments by default.
    ListConsumers { columns: Vec<String> },
    /// Lists users and their tags.
    ListUsers { columns: Vec<String> },
    /// Lists vhosts: name by default.
    ListVhosts { columns: Vec<String> },
    /// Adds a vhost (the caller gets full permissions on it, as with
    /// RabbitMQ's API).
    AddVhost { vhost: String },
    /// Deletes a vhost and everything in it: its connections are closed,
    /// its queues, exchanges, bindings, permissions and parameters go.
    DeleteVhost { vhost: String },
    /// Replaces the vhost's limits with a JSON definition
    /// (`{"max-connections": 10, "max-queues": 100}`; negative: none).
    SetVhostLimits { definition: String },
    /// Clears the vhost's limits.
    ClearVhostLimits,
    /// Lists the vhost's limits (every vhost's with `--global`).
    ListVhostLimits {
        #[arg(long)]
        global: bool,
    },
    /// Adds a JSON definition to a user's limits
    /// (`{"max-connections": 5, "max-channels": 50}`; negative: none).
    SetUserLimits { user: String, definition: String },
    /// Clears one limit of a user (`max-connections`, `max-channels`) or
    /// `all`.
    ClearUserLimits { user: String, limit: String },
    /// Lists a user's limits (every user's with `--global`).
    ListUserLimits {
        #[arg(long, default_value = "guest")]
        user: String,
        #[arg(long)]
        global: bool,
    },
    /// Lists channels: pid, user, consumer_count, messages_unacknowledged
    /// by default.
    ListChannels { columns: Vec<String> },
    /// Checks that the broker's API answers (exit 0), as rabbitmqctl ping.
    Ping {
        /// Seconds to wait for the answer.
        #[arg(short = 't', long, default_value_t = 60)]
        timeout: u64,
    },
    /// Waits until the broker has started (its API answers): exit 0 once
    /// it has, 75 if it has not within the timeout, 1 if it refuses the
    /// credentials.
    AwaitStartup {
        /// Seconds to wait.
        #[arg(short = 't', long, default_value_t = 300)]
        timeout: u64,
    },
    /// Adds a user (no tags, no permissions: grant some with
    /// set_permissions); refused if the user exists.
    AddUser {
        user: String,
        /// (Not `password`, which is the API's own, global option.)
        #[arg(value_name = "PASSWORD")]
        new_password: String,
    },
    /// Deletes a user and their permissions.
    DeleteUser { user: String },
    /// Changes a user's password, keeping their tags.
    ChangePassword {
        user: String,
        #[arg(value_name = "PASSWORD")]
        new_password: String,
    },
    /// Replaces a user's tags (none clears them).
    SetUserTags { user: String, tags: Vec<String> },
    /// Lists the permissions on the vhost: user, configure, write, read.
    ListPermissions { columns: Vec<String> },
    /// Sets a user's permissions on the vhost (regular expressions).
    SetPermissions {
        user: String,
        configure: String,
        write: String,
        read: String,
    },
    /// Removes a user's permissions on the vhost.
    ClearPermissions { user: String },
    /// Lists the topic permissions on the vhost: user, exchange, write,
    /// read.
    ListTopicPermissions { columns: Vec<String> },
    /// Sets a user's topic permissions on an exchange of the vhost
    /// (regular expressions over routing keys).
    SetTopicPermissions {
        user: String,
        exchange: String,
        write: String,
        read: String,
    },
    /// Removes a user's topic permissions on the vhost (on one exchange
    /// if named).
    ClearTopicPermissions {
        user: String,
        exchange: Option<String>,
    },
    /// Drops a queue's ready messages.
    PurgeQueue { queue: String },
    /// Deletes a queue.
    DeleteQueue {
        queue: String,
        /// Only if it has no consumers.
        #[arg(long = "if-unused", short = 'u')]
        if_unused: bool,
        /// Only if it has no messages.
        #[arg(long = "if-empty", short = 'e')]
        if_empty: bool,
    },
    /// Closes a connection (its name as list_connections name shows it).
    CloseConnection { name: String, reason: String },
    /// Writes the broker's definitions (RabbitMQ's definitions.json) to a
    /// file, or to standard output for `-`.
    ExportDefinitions { file: PathBuf },
    /// Loads definitions from a file, or from standard input for `-`.
    ImportDefinitions { file: PathBuf },
    /// The node's status: versions, memory, file descriptors, listeners,
    /// totals.
    Status,
    /// The status, then every listing: connections, channels, and each
    /// vhost's queues, exchanges, bindings, consumers and permissions.
    Report,
    /// The effective configuration (command line, config file and
    /// defaults), under the config file's key names, one `key = value`
    /// (JSON values) per line; credentials are not shown.
    Environment,
    #[command(flatten)]
    Policy(policies::PolicyCommand),
    /// The robot data ports that announce themselves (over AMQP, see
    /// --amqp-url).
    Port {
        #[command(subcommand)]
        command: ports::PortCommand,
    },
}

/// Why a command failed.
#[derive(Debug, thiserror::Error)]
enum Failure {
    #[error("{0}")]
    Client(#[from] ClientError),
    /// Waiting for the broker timed out.
    #[error("{0}")]
    TimedOut(String),
    #[error("{0}")]
    Usage(String),
    #[error("{0}")]
    Refused(String),
    /// The broker's AMQP listener cannot be reached (or was lost).
    #[error("{0}")]
    Unavailable(String),
    #[error("{0}")]
    Io(#[from] std::io::Error),
}

fn main() -> ExitCode {
    let cli = match Cli::try_parse() {
        Ok(cli) => cli,
        Err(e) => {
            let _ = e.print();
            return if e.use_stderr() {
                ExitCode::from(USAGE)
            } else {
                ExitCode::SUCCESS
            };
        }
    };
    match run(&cli) {
        Ok(()) => ExitCode::SUCCESS,
        Err(Failure::Io(e)) if e.kind() == std::io::ErrorKind::BrokenPipe => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("Error: {e}");
            ExitCode::from(match e {
                Failure::Usage(_) => USAGE,
                Failure::TimedOut(_) => TIMED_OUT,
                Failure::Client(ClientError::Unreachable { .. }) | Failure::Unavailable(_) => {
                    UNAVAILABLE
                }
                Failure::Client(ClientError::Api { .. }) | Failure::Refused(_) | Failure::Io(_) => {
                    1
                }
            })
        }
    }
}

/// Writes `text` to standard output.
fn emit(text: &str) -> Result<(), Failure> {
    let mut out = std::io::stdout().lock();
    out.write_all(text.as_bytes())?;
    out.flush()?;
    Ok(())
}

/// An informational line, unless `-q`.
fn info(cli: &Cli, line: &str) -> Result<(), Failure> {
    if cli.quiet {
        return Ok(());
    }
    emit(&format!("{line}\n"))
}

fn run(cli: &Cli) -> Result<(), Failure> {
    let timeout = match &cli.command {
        Command::Ping { timeout } | Command::AwaitStartup { timeout } => *timeout,
        _ => client::DEFAULT_TIMEOUT_SECS,
    };
    let client = Client::new(&cli.url, &cli.username, &cli.password)
        .timeout(std::time::Duration::from_secs(timeout));
    let vhost = segment(&cli.vhost);
    match &cli.command {
        Command::ListQueues { columns } => {
            info(cli, &format!("Listing queues for vhost {} ...", cli.vhost))?;
            let list = client.get(&format!("/api/queues/{vhost}"))?;
            print_table(cli, &columns::QUEUES, columns, &list)
        }
        Command::ListExchanges { columns } => {
            info(
                cli,
                &format!("Listing exchanges for vhost {} ...", cli.vhost),
            )?;
            let list = client.get(&format!("/api/exchanges/{vhost}"))?;
            print_table(cli, &columns::EXCHANGES, columns, &list)
        }
        Command::ListBindings { columns } => {
            info(cli, &format!("Listing bindings for vhost {}...", cli.vhost))?;
            let list = client.get(&format!("/api/bindings/{vhost}"))?;
            print_table(cli, &columns::BINDINGS, columns, &list)
        }
        Command::ListConnections { columns } => {
            info(cli, "Listing connections ...")?;
            let list = client.get("/api/connections")?;
            print_table(cli, &columns::CONNECTIONS, columns, &list)
        }
        Command::ListConsumers { columns } => {
            info(
                cli,
                &format!("Listing consumers in vhost {} ...", cli.vhost),
            )?;
            let list = client.get(&format!("/api/consumers/{vhost}"))?;
            print_table(cli, &columns::CONSUMERS, columns, &list)
        }
        Command::ListUsers { columns } => {
            info(cli, "Listing users ...")?;
            let list = client.get("/api/users")?;
            print_table(cli, &columns::USERS, columns, &list)
        }
        Command::ListVhosts { columns } => {
            info(cli, "Listing vhosts ...")?;
            let list = client.get("/api/vhosts")?;
            print_table(cli, &columns::VHOSTS, columns, &list)
        }
        Command::AddVhost { vhost } => {
            info(cli, &format!("Adding vhost \"{vhost}\" ..."))?;
            client.put(&format!("/api/vhosts/{}", segment(vhost)), b"{}")?;
            Ok(())
        }
        Command::SetVhostLimits { definition } => {
            limits::run(cli, &client, limits::LimitsCommand::SetVhost(definition))
        }
        Command::ClearVhostLimits => limits::run(cli, &client, limits::LimitsCommand::ClearVhost),
        Command::ListVhostLimits { global } => limits::run(
            cli,
            &client,
            limits::LimitsCommand::ListVhost { global: *global },
        ),
        Command::SetUserLimits { user, definition } => limits::run(
            cli,
            &client,
            limits::LimitsCommand::SetUser(user, definition),
        ),
        Command::ClearUserLimits { user, limit } => {
            limits::run(cli, &client, limits::LimitsCommand::ClearUser(user, limit))
        }
        Command::ListUserLimits { user, global } => limits::run(
            cli,
            &client,
            limits::LimitsCommand::ListUser {
                user,
                global: *global,
            },
        ),
        Command::DeleteVhost { vhost } => {
            info(cli, &format!("Deleting vhost \"{vhost}\" ..."))?;
            client.delete(&format!("/api/vhosts/{}", segment(vhost)), &[])?;
            Ok(())
        }
        Command::ListChannels { columns } => {
            info(cli, "Listing channels ...")?;
            let list = client.get("/api/channels")?;
            print_table(cli, &columns::CHANNELS, columns, &list)
        }
        Command::Ping { timeout } => {
            info(
                cli,
                &format!(
                    "Will ping the broker at {}. Timeout: {} ms.",
                    cli.url,
                    timeout * 1000
                ),
            )?;
            client.get("/api/overview")?;
            info(cli, "Ping succeeded")
        }
        Command::AwaitStartup { timeout } => await_startup(cli, &client, *timeout),
        Command::AddUser { user, new_password } => {
            info(cli, &format!("Adding user \"{user}\" ..."))?;
            let path = format!("/api/users/{}", segment(user));
            match client.get(&path) {
                Ok(_) => return Err(Failure::Refused(format!("user \"{user}\" already exists"))),
                Err(ClientError::Api { status: 404, .. }) => {}
                Err(e) => return Err(e.into()),
            }
            let body = serde_json::json!({"password": new_password, "tags": []});
            client.put(&path, body.to_string().as_bytes())?;
            Ok(())
        }
        Command::DeleteUser { user } => {
            info(cli, &format!("Deleting user \"{user}\" ..."))?;
            client.delete(&format!("/api/users/{}", segment(user)), &[])?;
            Ok(())
        }
        Command::ChangePassword { user, new_password } => {
            info(cli, &format!("Changing password for user \"{user}\" ..."))?;
            let path = format!("/api/users/{}", segment(user));
            let existing = client.get(&path)?;
            let body = serde_json::json!({"password": new_password, "tags": existing["tags"]});
            client.put(&path, body.to_string().as_bytes())?;
            Ok(())
        }
        Command::SetUserTags { user, tags } => {
            info(
                cli,
                &format!(
                    "Setting tags for user \"{user}\" to [{}] ...",
                    tags.join(", ")
                ),
            )?;
            let path = format!("/api/users/{}", segment(user));
            client.get(&path)?;
            let body = serde_json::json!({"tags": tags});
            client.put(&path, body.to_string().as_bytes())?;
            Ok(())
        }
        Command::ListPermissions { columns } => {
            info(
                cli,
                &format!("Listing permissions for vhost \"{}\" ...", cli.vhost),
            )?;
            let list = client.get("/api/permissions")?;
            let here: Vec<Value> = list
                .as_array()
                .into_iter()
                .flatten()
                .filter(|p| p["vhost"] == cli.vhost.as_str())
                .cloned()
                .collect();
            print_table(cli, &columns::PERMISSIONS, columns, &Value::Array(here))
        }
        Command::SetPermissions {
            user,
            configure,
            write,
            read,
        } => {
            info(
                cli,
                &format!(
                    "Setting permissions for user \"{user}\" in vhost \"{}\" ...",
                    cli.vhost
                ),
            )?;
            let body = serde_json::json!({"configure": configure, "write": write, "read": read});
            client.put(
                &format!("/api/permissions/{vhost}/{}", segment(user)),
                body.to_string().as_bytes(),
            )?;
            Ok(())
        }
        Command::ClearPermissions { user } => {
            info(
                cli,
                &format!(
                    "Clearing permissions for user \"{user}\" in vhost \"{}\" ...",
                    cli.vhost
                ),
            )?;
            client.delete(&format!("/api/permissions/{vhost}/{}", segment(user)), &[])?;
            Ok(())
        }
        Command::ListTopicPermissions { columns } => {
            info(
                cli,
                &format!("Listing topic permissions for vhost \"{}\" ...", cli.vhost),
            )?;
            let list = client.get("/api/topic-permissions")?;
            let here: Vec<Value> = (list.as_array().into_iter().flatten())
                .filter(|p| p["vhost"] == cli.vhost.as_str())
                .cloned()
                .collect();
            print_table(
                cli,
                &columns::TOPIC_PERMISSIONS,
                columns,
                &Value::Array(here),
            )
        }
        Command::SetTopicPermissions {
            user,
            exchange,
            write,
            read,
        } => {
            info(
                cli,
                &format!(
                    "Setting topic permissions on \"{exchange}\" for user \"{user}\" in vhost \"{}\" ...",
                    cli.vhost
                ),
            )?;
            let body = serde_json::json!({"exchange": exchange, "write": write, "read": read});
            client.put(
                &format!("/api/topic-permissions/{vhost}/{}", segment(user)),
                body.to_string().as_bytes(),
            )?;
            Ok(())
        }
        Command::ClearTopicPermissions { user, exchange } => {
            info(
                cli,
                &format!(
                    "Clearing topic permissions for user \"{user}\" in vhost \"{}\" ...",
                    cli.vhost
                ),
            )?;
            let mut path = format!("/api/topic-permissions/{vhost}/{}", segment(user));
            if let Some(exchange) = exchange {
                path.push_str(&format!("?exchange={}", segment(exchange)));
            }
            client.delete(&path, &[])?;
            Ok(())
        }
        Command::PurgeQueue { queue } => {
            info(
                cli,
                &format!("Purging queue '{queue}' in vhost '{}' ...", cli.vhost),
            )?;
            client.delete(
                &format!("/api/queues/{vhost}/{}/contents", segment(queue)),
                &[],
            )?;
            Ok(())
        }
        Command::DeleteQueue {
            queue,
            if_unused,
            if_empty,
        } => {
            info(
                cli,
                &format!("Deleting queue '{queue}' on vhost '{}' ...", cli.vhost),
            )?;
            let path = format!(
                "/api/queues/{vhost}/{}?if-unused={if_unused}&if-empty={if_empty}",
                segment(queue)
            );
            client.delete(&path, &[])?;
            Ok(())
        }
        Command::CloseConnection { name, reason } => {
            info(
                cli,
                &format!("Closing connection {name}, reason: {reason}..."),
            )?;
            let path = format!("/api/connections/{}", segment(name));
            client.delete(&path, &[("X-Reason", reason)])?;
            Ok(())
        }
        Command::ExportDefinitions { file } => {
            let definitions = client.get("/api/definitions")?;
            let text = serde_json::to_string_pretty(&definitions).unwrap_or_default();
            if file.as_os_str() == "-" {
                emit(&format!("{text}\n"))?;
            } else {
                std::fs::write(file, text)?;
                info(
                    cli,
                    &format!("Exported definitions to \"{}\"", file.display()),
                )?;
            }
            Ok(())
        }
        Command::ImportDefinitions { file } => {
            let mut bytes = Vec::new();
            if file.as_os_str() == "-" {
                std::io::stdin().read_to_end(&mut bytes)?;
            } else {
                bytes = std::fs::read(file)?;
            }
            let report = client.post("/api/definitions", &bytes)?;
            info(
                cli,
                &format!("Imported definitions from \"{}\"", file.display()),
            )?;
            for warning in report["warnings"].as_array().into_iter().flatten() {
                eprintln!("warning: {}", warning.as_str().unwrap_or_default());
            }
            Ok(())
        }
        Command::Status => status(cli, &client),
        Command::Report => report(cli, &client),
        Command::Environment => environment(cli, &client),
        Command::Port { command } => ports::run(cli, command),
        Command::Policy(command) => policies::run(cli, &client, command),
    }
}

fn print_table(
    cli: &Cli,
    table: &columns::Table,
    asked: &[String],
    list: &Value,
) -> Result<(), Failure> {
    let names: Vec<&str> = if asked.is_empty() {
        table.default.to_vec()
    } else {
        asked.iter().map(String::as_str).collect()
    };
    let (names, unknown): (Vec<&str>, Vec<&str>) =
        names.into_iter().partition(|name| table.knows(name));
    let mut out = std::io::stdout().lock();
    let items = list.as_array().into_iter().flatten();
    match cli.formatter {
        Formatter::Table => {
            if !cli.no_table_headers {
                writeln!(out, "{}", names.join("\t"))?;
            }
            for item in items {
                let row: Vec<String> = names.iter().map(|name| table.cell(name, item)).collect();
                writeln!(out, "{}", row.join("\t"))?;
            }
        }
        Formatter::Json => {
            let rows: Vec<Value> = items
                .map(|item| {
                    let row = names
                        .iter()
                        .map(|name| ((*name).to_owned(), table.value(name, item)));
                    Value::Object(row.collect())
                })
                .collect();
            writeln!(out, "{}", Value::Array(rows))?;
        }
    }
    out.flush()?;
    if !unknown.is_empty() {
        return Err(Failure::Usage(format!(
            "unknown column(s) {}, not shown; known: {}",
            unknown.join(", "),
            table.known().join(", ")
        )));
    }
    Ok(())
}

/// Asks the API until it answers, up to `timeout` seconds: rabbitmqctl's
/// await_startup for scripts and service units.
fn await_startup(cli: &Cli, client: &Client, timeout: u64) -> Result<(), Failure> {
    info(
        cli,
        &format!("Waiting for the broker at {} to start ...", cli.url),
    )?;
    let deadline = std::time::Instant::now() + std::time::Duration::from_secs(timeout);
    loop {
        match client.get("/api/overview") {
            Ok(_) => return Ok(()),
            Err(ClientError::Unreachable { .. }) | Err(ClientError::Api { status: 500.., .. }) => {}
            Err(refused) => return Err(refused.into()),
        }
        if std::time::Instant::now() + STARTUP_POLL > deadline {
            return Err(Failure::TimedOut(format!(
                "the broker at {} did not start within {timeout} s",
                cli.url
            )));
        }
        std::thread::sleep(STARTUP_POLL);
    }
}

/// Appends one formatted line to a report.
macro_rules! report_line {
    ($report:ident, $($arg:tt)*) => {{
        use std::fmt::Write as _;
        let _ = writeln!($report, $($arg)*);
    }};
}

/// The alarms in effect on a node of `/api/nodes`, in rabbitmqctl's
/// words: the memory and disk alarms as the broker holds them, and the
/// file-descriptor limit when every descriptor the process may open is
/// open (new connections are then refused).
fn alarms(node: &Value) -> Vec<&'static str> {
    let mut alarms = Vec::new();
    if node["mem_alarm"] == Value::Bool(true) {
        alarms.push("Memory alarm");
    }
    if node["disk_free_alarm"] == Value::Bool(true) {
        alarms.push("Free disk space alarm");
    }
    if let (Some(used), Some(limit)) = (node["fd_used"].as_u64(), node["fd_total"].as_u64()) {
        if used >= limit {
            alarms.push("File descriptor limit alarm");
        }
    }
    alarms
}

/// The entries of a listing that belong to `vhost`.
fn in_vhost(list: &Value, vhost: &str) -> Value {
    let here = (list.as_array().into_iter().flatten()).filter(|item| item["vhost"] == vhost);
    Value::Array(here.cloned().collect())
}

/// rabbitmqctl report: the status, then each listing with its default
/// columns (with `--formatter json`, one object of the API's objects).
fn report(cli: &Cli, client: &Client) -> Result<(), Failure> {
    let connections = client.get("/api/connections")?;
    let channels = client.get("/api/channels")?;
    let permissions = client.get("/api/permissions")?;
    let topic_permissions = client.get("/api/topic-permissions")?;
    let vhosts = client.get("/api/vhosts")?;
    let names: Vec<&str> = (vhosts.as_array().into_iter().flatten())
        .filter_map(|vhost| vhost["name"].as_str())
        .collect();
    let listings =
        |name: &str| -> Result<[(&'static str, &'static columns::Table, Value); 6], Failure> {
            let vhost = segment(name);
            Ok([
                (
                    "Queues",
                    &columns::QUEUES,
                    client.get(&format!("/api/queues/{vhost}"))?,
                ),
                (
                    "Exchanges",
                    &columns::EXCHANGES,
                    client.get(&format!("/api/exchanges/{vhost}"))?,
                ),
                (
                    "Bindings",
                    &columns::BINDINGS,
                    client.get(&format!("/api/bindings/{vhost}"))?,
                ),
                (
                    "Consumers",
                    &columns::CONSUMERS,
                    client.get(&format!("/api/consumers/{vhost}"))?,
                ),
                (
                    "Permissions",
                    &columns::PERMISSIONS,
                    in_vhost(&permissions, name),
                ),
                (
                    "Topic permissions",
                    &columns::TOPIC_PERMISSIONS,
                    in_vhost(&topic_permissions, name),
                ),
            ])
        };
    if cli.formatter == Formatter::Json {
        let mut by_vhost = serde_json::Map::new();
        for name in &names {
            let sections = listings(name)?
                .map(|(title, _, list)| (title.to_lowercase().replace(' ', "_"), list));
            by_vhost.insert(
                (*name).to_owned(),
                Value::Object(sections.into_iter().collect()),
            );
        }
        let report = serde_json::json!({
            "overview": client.get("/api/overview")?,
            "nodes": client.get("/api/nodes")?,
            "connections": connections,
            "channels": channels,
            "vhosts": by_vhost,
        });
        return emit(&format!("{report}\n"));
    }
    status(cli, client)?;
    emit("\nConnections:\n")?;
    print_table(cli, &columns::CONNECTIONS, &[], &connections)?;
    emit("\nChannels:\n")?;
    print_table(cli, &columns::CHANNELS, &[], &channels)?;
    for name in &names {
        for (title, table, list) in listings(name)? {
            emit(&format!("\n{title} on {name}:\n"))?;
            print_table(cli, table, &[], &list)?;
        }
    }
    Ok(())
}

/// rabbitmqctl environment: the broker's effective configuration.
fn environment(cli: &Cli, client: &Client) -> Result<(), Failure> {
    let environment = client.get("/api/environment")?;
    if cli.formatter == Formatter::Json {
        return emit(&format!("{environment}\n"));
    }
    let node = client.get("/api/overview")?["node"].clone();
    info(
        cli,
        &format!(
            "Effective configuration of node {} ...",
            columns::render(&node)
        ),
    )?;
    let mut lines = String::new();
    for (key, value) in environment.as_object().into_iter().flatten() {
        lines.push_str(&format!("{key} = {value}\n"));
    }
    emit(&lines)
}

fn status(cli: &Cli, client: &Client) -> Result<(), Failure> {
    let overview = client.get("/api/overview")?;
    let nodes = client.get("/api/nodes")?;
    let node = &nodes[0];
    if cli.formatter == Formatter::Json {
        let status = serde_json::json!({
            "node": overview["node"],
            "product_name": overview["product_name"],
            "product_version": overview["product_version"],
            "uptime_seconds": node["uptime"].as_u64().unwrap_or(0) / 1000,
            "alarms": alarms(node),
            "memory": {
                "used": node["mem_used"],
                "high_watermark": node["mem_limit"],
                "queued_bytes_limit": node["queued_bytes_limit"],
            },
            "file_descriptors": {"used": node["fd_used"], "limit": node["fd_total"]},
            "disk": {"free": node["disk_free"], "limit": node["disk_free_limit"]},
            "listeners": overview["listeners"],
            "totals": overview["object_totals"],
            "queue_totals": overview["queue_totals"],
        });
        return emit(&format!("{status}\n"));
    }
    let text = |v: &Value| columns::render(v);
    info(
        cli,
        &format!("Status of node {} ...", text(&overview["node"])),
    )?;
    let mut report = String::new();
    report_line!(report, "Runtime\n");
    report_line!(report, "Product name: {}", text(&overview["product_name"]));
    report_line!(
        report,
        "Product version: {}",
        text(&overview["product_version"])
    );
    report_line!(
        report,
        "Uptime (seconds): {}",
        node["uptime"].as_u64().unwrap_or(0) / 1000
    );
    report_line!(report, "\nAlarms\n");
    let alarms = alarms(node);
    if alarms.is_empty() {
        report_line!(report, "(none)");
    }
    for alarm in alarms {
        report_line!(report, "{alarm} on node {}", text(&node["name"]));
    }
    report_line!(report, "\nMemory\n");
    report_line!(
        report,
        "Resident memory (bytes): {}",
        text(&node["mem_used"])
    );
    report_line!(
        report,
        "Memory high watermark (bytes): {}",
        match &node["mem_limit"] {
            Value::Null => "none (resident memory not watched here)".to_owned(),
            limit => text(limit),
        }
    );
    report_line!(
        report,
        "Queued message bytes limit: {}",
        text(&node["queued_bytes_limit"])
    );
    report_line!(report, "\nFree Disk Space\n");
    report_line!(report, "Free (bytes): {}", text(&node["disk_free"]));
    report_line!(report, "Limit (bytes): {}", text(&node["disk_free_limit"]));
    report_line!(report, "\nFile Descriptors\n");
    report_line!(
        report,
        "Used: {}, limit: {}",
        text(&node["fd_used"]),
        text(&node["fd_total"])
    );
    report_line!(report, "\nListeners\n");
    for listener in overview["listeners"].as_array().into_iter().flatten() {
        report_line!(
            report,
            "Interface: {}, port: {}, protocol: {}",
            text(&listener["ip_address"]),
            text(&listener["port"]),
            text(&listener["protocol"])
        );
    }
    report_line!(report, "\nTotals\n");
    let totals = &overview["object_totals"];
    for key in [
        "connections",
        "channels",
        "queues",
        "consumers",
        "exchanges",
    ] {
        report_line!(report, "{key}: {}", text(&totals[key]));
    }
    report_line!(
        report,
        "messages: {} ({} ready, {} unacknowledged)",
        text(&overview["queue_totals"]["messages"]),
        text(&overview["queue_totals"]["messages_ready"]),
        text(&overview["queue_totals"]["messages_unacknowledged"])
    );
    emit(&report)
}

#[cfg(test)]
mod tests {
    use super::Cli;
    use clap::CommandFactory;

    /// `packaging/leveretctl.1` is clap_mangen's rendering of this command
    /// line, the one `--help` prints (the commands are listed, each with
    /// its own `--help`); `LEVERET_WRITE_MAN=1` rewrites it.
    #[test]
    fn the_man_page_is_rendered_from_the_command_line() {
        let mut rendered = Vec::new();
        clap_mangen::Man::new(Cli::command())
            .render(&mut rendered)
            .expect("render");
        let path =
            std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../packaging/leveretctl.1");
        if std::env::var_os("LEVERET_WRITE_MAN").is_some() {
            std::fs::write(&path, &rendered).expect("write the man page");
        }
        let kept = std::fs::read(&path).unwrap_or_default();
        assert!(
            kept == rendered,
            "packaging/leveretctl.1 differs from the command line: run this test with LEVERET_WRITE_MAN=1"
        );
    }
}
