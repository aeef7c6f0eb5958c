//! Logging set-up: `tracing` events from the library and the binary,
//! written to standard error, filtered by `--log` (a level or a tracing
//! filter such as `leveret_broker=debug,info`), in one of two formats
//! (`--log-format`):
//! - `text`: one human line per event; ANSI colours only when standard
//!   error is a terminal, so files, pipes and journald get plain text;
//! - `json`: one JSON object per line with the stable keys `timestamp`
//!   (RFC 3339, UTC), `level` (`INFO`...), `target` (the module) and
//!   `message`, and each of the event's fields as a key of its own.

use serde::Deserialize;
use std::io::IsTerminal;

/// How log lines are written.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "kebab-case")]
pub enum LogFormat {
    /// One human-readable line per event.
    #[default]
    Text,
    /// One JSON object per line.
    Json,
}

/// Installs the subscriber. Directives of the filter that do not parse are
/// ignored, as `tracing_subscriber::EnvFilter::new` does.
pub fn init(filter: &str, format: LogFormat) {
    let builder = tracing_subscriber::fmt()
        .with_env_filter(tracing_subscriber::EnvFilter::new(filter))
        .with_writer(std::io::stderr);
    match format {
        LogFormat::Text => builder.with_ansi(std::io::stderr().is_terminal()).init(),
        LogFormat::Json => builder
            .json()
            .flatten_event(true)
            .with_current_span(false)
            .with_span_list(false)
            .init(),
    }
}
