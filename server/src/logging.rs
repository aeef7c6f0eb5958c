//! Logging set-up: `tracing` events from the library and the binary,
//! filtered by `--log` (a level or a tracing filter such as
//! `leveret_broker=debug,info`), written to standard error or to
//! `--log-file` (appended to, and reopened on SIGHUP, logrotate's
//! convention: rename the file, then send SIGHUP), in one of two formats
//! (`--log-format`):
//! - `text`: one human line per event; ANSI colours only when standard
//!   error is a terminal, so files, pipes and journald get plain text;
//! - `json`: one JSON object per line with the stable keys `timestamp`
//!   (RFC 3339, UTC), `level` (`INFO`...), `target` (the module) and
//!   `message`, and each of the event's fields as a key of its own.

use serde::{Deserialize, Serialize};
use std::fs::File;
use std::io::{IsTerminal, Write};
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex, MutexGuard};
use tracing_subscriber::fmt::writer::{BoxMakeWriter, MakeWriter};

/// How log lines are written.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Deserialize, Serialize, clap::ValueEnum)]
#[serde(rename_all = "kebab-case")]
pub enum LogFormat {
    /// One human-readable line per event.
    #[default]
    Text,
    /// One JSON object per line.
    Json,
}

/// The log file: each event is written whole under its lock; reopening
/// swaps the file under the same lock, so no line is split between the
/// old file and the new.
#[derive(Debug, Clone)]
pub struct LogFile(Arc<Shared>);

#[derive(Debug)]
struct Shared {
    path: PathBuf,
    file: Mutex<File>,
}

fn append(path: &Path) -> std::io::Result<File> {
    std::fs::OpenOptions::new()
        .create(true)
        .append(true)
        .open(path)
}

impl LogFile {
    /// Opens `path` for appending, creating it if missing.
    pub fn open(path: &Path) -> std::io::Result<LogFile> {
        Ok(LogFile(Arc::new(Shared {
            path: path.to_path_buf(),
            file: Mutex::new(append(path)?),
        })))
    }

    /// Opens the path again (a new file if the old one was renamed away);
    /// on an error the file in use stays.
    pub fn reopen(&self) -> std::io::Result<()> {
        let fresh = append(&self.0.path)?;
        *self.lock() = fresh;
        Ok(())
    }

    fn lock(&self) -> MutexGuard<'_, File> {
        self.0.file.lock().unwrap_or_else(|e| e.into_inner())
    }
}

/// One event's writes to the log file, under its lock.
pub struct LogFileWriter<'a>(MutexGuard<'a, File>);

impl Write for LogFileWriter<'_> {
    fn write(&mut self, bytes: &[u8]) -> std::io::Result<usize> {
        self.0.write(bytes)
    }

    fn flush(&mut self) -> std::io::Result<()> {
        self.0.flush()
    }
}

impl<'a> MakeWriter<'a> for LogFile {
    type Writer = LogFileWriter<'a>;

    fn make_writer(&'a self) -> Self::Writer {
        LogFileWriter(self.lock())
    }
}

/// Installs the subscriber, writing to `file` or else to standard error.
/// Directives of the filter that do not parse are ignored, as
/// `tracing_subscriber::EnvFilter::new` does.
pub fn init(filter: &str, format: LogFormat, file: Option<LogFile>) {
    let colour = file.is_none() && std::io::stderr().is_terminal();
    let writer = match file {
        Some(file) => BoxMakeWriter::new(file),
        None => BoxMakeWriter::new(std::io::stderr),
    };
    let builder = tracing_subscriber::fmt()
        .with_env_filter(tracing_subscriber::EnvFilter::new(filter))
        .with_writer(writer);
    match format {
        LogFormat::Text => builder.with_ansi(colour).init(),
        LogFormat::Json => builder
            .json()
            .flatten_event(true)
            .with_current_span(false)
            .with_span_list(false)
            .init(),
    }
}
