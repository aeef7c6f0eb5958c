//! # leveretctl
//!
//! A command line over Leveret's management HTTP API in the style of
//! `rabbitmqctl`: the same command names, `-p VHOST`, and for the `list_*`
//! commands rabbitmqctl's column names and tab-separated output (a header
//! line unless `--no-table-headers`; the "Listing ..." line unless `-q`).
//! `--url` names the API (default `http://127.0.0.1:15672`, guest/guest).
//! The `port` commands (`port list`, `port stats NAME`, `port echo NAME`)
//! speak AMQP instead, to `--amqp-url` (default
//! `amqp://guest:guest@127.0.0.1:5672/%2f`, its vhost the URL's), and
//! show the robot data ports that announce themselves there.
//!
//! Exit status: 0 on success, 64 for a command line it cannot use, 69 when
//! the API (or, for `port`, the broker) cannot be reached, 1 when the
//! broker refuses the request (or the port named does not announce
//! itself).
//!
//! # Layout
//! - `main`: the command line and the commands.
//! - `client`: the HTTP client (ureq).
//! - `columns`: rabbitmqctl's column names mapped onto the API's fields.
//! - `ports`: the `port` commands, over AMQP with leveret-client.
#![forbid(unsafe_code)]

mod client;
mod columns;
mod ports;

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
    let client = Client::new(&cli.url, &cli.username, &cli.password);
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
        Command::Port { command } => ports::run(cli, command),
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
    let unknown: Vec<&str> = names
        .iter()
        .copied()
        .filter(|name| !table.knows(name))
        .collect();
    if !unknown.is_empty() {
        return Err(Failure::Usage(format!(
            "unknown columns {}; known: {}",
            unknown.join(", "),
            table.known().join(", ")
        )));
    }
    let mut out = std::io::stdout().lock();
    if !cli.no_table_headers {
        writeln!(out, "{}", names.join("\t"))?;
    }
    for item in list.as_array().into_iter().flatten() {
        let row: Vec<String> = names.iter().map(|name| table.cell(name, item)).collect();
        writeln!(out, "{}", row.join("\t"))?;
    }
    Ok(())
}

/// Appends one formatted line to a report.
macro_rules! report_line {
    ($report:ident, $($arg:tt)*) => {{
        use std::fmt::Write as _;
        let _ = writeln!($report, $($arg)*);
    }};
}

fn status(cli: &Cli, client: &Client) -> Result<(), Failure> {
    let overview = client.get("/api/overview")?;
    let nodes = client.get("/api/nodes")?;
    let node = &nodes[0];
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
    if node["mem_alarm"] == Value::Bool(true) {
        report_line!(report, "Memory alarm on node {}", text(&node["name"]));
    } else {
        report_line!(report, "(none)");
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
        text(&node["mem_limit"])
    );
    report_line!(report, "\nFile Descriptors\n");
    report_line!(
        report,
        "Used: {}, limit: {}",
        text(&node["fd_used"]),
        text(&node["fd_total"])
    );
    report_line!(report, "\nFree Disk Space\n");
    report_line!(report, "Free (bytes): {}", text(&node["disk_free"]));
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
