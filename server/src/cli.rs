//! The command line. Every option but `--hash-password`, `--recover` and
//! `--config` also has a key of the same name in the config file (`config`); the
//! command line wins.

use clap::Parser;
use std::net::SocketAddr;
use std::path::PathBuf;

/// A listener's address, or `none` (no listener).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Listen(pub Option<SocketAddr>);

impl std::str::FromStr for Listen {
    type Err = std::net::AddrParseError;

    fn from_str(text: &str) -> Result<Self, Self::Err> {
        match text {
            "none" => Ok(Listen(None)),
            addr => addr.parse().map(|addr| Listen(Some(addr))),
        }
    }
}

/// An embeddable AMQP 0.9.1 message broker.
#[derive(Debug, Default, Parser)]
#[command(name = "leveret", version, about)]
pub struct Cli {
    /// Address to accept AMQP connections on; may be given more than once
    /// [default: 0.0.0.0:5672].
    #[arg(long = "listen", value_name = "ADDR:PORT")]
    pub listen: Vec<SocketAddr>,
    /// Address to accept AMQP connections over TLS on (RabbitMQ's
    /// `listeners.ssl`, 5671 by convention); may be given more than once.
    /// Needs --tls-certfile and --tls-keyfile. SIGHUP re-reads the
    /// certificate files.
    #[arg(long = "tls-listen", value_name = "ADDR:PORT")]
    pub tls_listen: Vec<SocketAddr>,
    /// Address to accept MQTT 3.1.1 and 5.0 connections on (RabbitMQ's
    /// `mqtt.listeners.tcp`); may be given more than once; `none` turns
    /// MQTT over TCP off [default: 0.0.0.0:1883].
    #[arg(long = "mqtt-listen", value_name = "ADDR:PORT|none")]
    pub mqtt_listen: Vec<Listen>,
    /// Address to accept MQTT connections over TLS on (RabbitMQ's
    /// `mqtt.listeners.ssl`, 8883 by convention), with the --tls-* files;
    /// may be given more than once.
    #[arg(long = "mqtts-listen", value_name = "ADDR:PORT")]
    pub mqtts_listen: Vec<SocketAddr>,
    /// Address to accept MQTT over WebSocket on, path /ws (RabbitMQ's
    /// `web_mqtt.tcp.port`, 15675 by convention); may be given more than
    /// once.
    #[arg(long = "web-mqtt-listen", value_name = "ADDR:PORT")]
    pub web_mqtt_listen: Vec<SocketAddr>,
    /// The TLS certificate chain, PEM, leaf first (`ssl_options.certfile`).
    #[arg(long, value_name = "FILE")]
    pub tls_certfile: Option<PathBuf>,
    /// The TLS private key, PEM (`ssl_options.keyfile`).
    #[arg(long, value_name = "FILE")]
    pub tls_keyfile: Option<PathBuf>,
    /// CA certificates that client certificates are verified against, PEM
    /// (`ssl_options.cacertfile`); with it, clients are asked for a
    /// certificate (`verify_peer`) and one whose common name is a user may
    /// log in with SASL EXTERNAL.
    #[arg(long, value_name = "FILE")]
    pub tls_cacertfile: Option<PathBuf>,
    /// Directory for durable state; created if missing [default: ./leveret-data].
    #[arg(long, value_name = "DIR")]
    pub data_dir: Option<PathBuf>,
    /// Start even if the store in the data directory is damaged: copy the
    /// damaged files aside (`store.damaged-<time>`), keep every readable
    /// record and log what was lost (each unreadable stretch of the
    /// message log, and the queue positions that were in it). Without it,
    /// a damaged store refuses the start with an error saying what is
    /// wrong.
    #[arg(long)]
    pub recover: bool,
    /// Free bytes on the data directory's disk below which publishers are
    /// blocked until space returns (RabbitMQ's `disk_free_limit`)
    /// [default: 50000000].
    #[arg(long, value_name = "BYTES")]
    pub disk_free_limit: Option<u64>,
    /// TOML configuration file: the same keys as these flags, plus
    /// `[[users]]` (name, and password or password-hash), vhosts, and the
    /// limits heartbeat, frame-max, channel-max, max-message-size,
    /// memory-high-watermark.
    #[arg(long, value_name = "FILE")]
    pub config: Option<PathBuf>,
    /// Log level or tracing filter (error, warn, info, debug, trace) [default: info].
    #[arg(long, value_name = "LEVEL")]
    pub log: Option<String>,
    /// Log line format: `text` (coloured only on a terminal) or `json`
    /// (one object per line: timestamp, level, target, message and the
    /// event's fields) [default: text].
    #[arg(long, value_name = "FORMAT")]
    pub log_format: Option<crate::logging::LogFormat>,
    /// Write the log to this file (appended to) instead of standard
    /// error; SIGHUP reopens it, for logrotate.
    #[arg(long, value_name = "FILE")]
    pub log_file: Option<PathBuf>,
    /// The product name announced to clients in connection.start
    /// [default: Leveret]. Clients that gate RabbitMQ-only behaviour on
    /// the name may need `RabbitMQ`.
    #[arg(long, value_name = "NAME")]
    pub product: Option<String>,
    /// Longest the broker keeps polling for input after a socket read
    /// instead of sleeping, in microseconds; the window adapts to the
    /// traffic and shrinks to nothing when reads are further apart.
    /// 0 never busy-polls, for the least CPU time [default: 200].
    #[arg(long, value_name = "MICROS")]
    pub busy_poll: Option<u64>,
    /// Threads that serve connections. 1 (the default) runs everything on
    /// one thread, which busy polling works best with and which moved the
    /// most messages on small machines; more runs tokio's multi-thread
    /// runtime with that many workers [default: 1].
    #[arg(long, value_name = "N")]
    pub worker_threads: Option<usize>,
    /// Address of the Prometheus endpoint (`/metrics`, `/metrics/per-object`)
    /// [default: 127.0.0.1:15692].
    #[arg(long, value_name = "ADDR:PORT")]
    pub metrics_listen: Option<SocketAddr>,
    /// Address of the management HTTP API (RabbitMQ's `/api/...` subset)
    /// [default: 127.0.0.1:15672].
    #[arg(long, value_name = "ADDR:PORT")]
    pub http_listen: Option<SocketAddr>,
    /// RabbitMQ definitions file (definitions.json) to load at start:
    /// vhosts, users, exchanges, queues, bindings; what Leveret does not
    /// support is reported in the log.
    #[arg(long, value_name = "FILE")]
    pub definitions: Option<PathBuf>,
    /// Read a password on standard input, print its salted hash for the
    /// config file's `password-hash`, and exit.
    #[arg(long)]
    pub hash_password: bool,
}

#[cfg(test)]
mod tests {
    use super::Cli;
    use clap::CommandFactory;

    /// `packaging/leveret.1` is clap_mangen's rendering of this command
    /// line, the one `--help` prints; `LEVERET_WRITE_MAN=1` rewrites it.
    #[test]
    fn the_man_page_is_rendered_from_the_command_line() {
        let mut rendered = Vec::new();
        clap_mangen::Man::new(Cli::command())
            .render(&mut rendered)
            .expect("render");
        let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../packaging/leveret.1");
        if std::env::var_os("LEVERET_WRITE_MAN").is_some() {
            std::fs::write(&path, &rendered).expect("write the man page");
        }
        let kept = std::fs::read(&path).unwrap_or_default();
        assert!(
            kept == rendered,
            "packaging/leveret.1 differs from the command line: run this test with LEVERET_WRITE_MAN=1"
        );
    }
}
