//! Figures about this process and its machine that RabbitMQ reports
//! beside its own counters: resident memory, open and allowed file
//! descriptors and the start time (Linux's /proc; absent elsewhere), free disk space where
//! the data lives, and the node name (`leveret@HOST`, in the style of
//! RabbitMQ's `rabbit@HOST`). Reading them costs a few small file reads,
//! done on the listeners' thread at scrape time.

use std::path::Path;

/// What was read; `None` where the platform does not say.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct ProcessFigures {
    /// Resident set size, bytes.
    pub resident_memory_bytes: Option<u64>,
    /// Open file descriptors.
    pub open_fds: Option<u64>,
    /// The soft limit on open file descriptors.
    pub max_fds: Option<u64>,
    /// Bytes free to unprivileged users on the data directory's file system.
    pub disk_free_bytes: Option<u64>,
    /// When the process started, seconds since the Unix epoch (Linux:
    /// its start in clock ticks after boot, plus the boot time).
    pub start_time_seconds: Option<f64>,
}

impl ProcessFigures {
    /// Reads them now; `data_dir` is where the disk figure is taken.
    pub fn read(data_dir: &Path) -> ProcessFigures {
        ProcessFigures {
            resident_memory_bytes: resident_memory_bytes(),
            open_fds: std::fs::read_dir("/proc/self/fd")
                .ok()
                .map(|entries| entries.count() as u64),
            max_fds: std::fs::read_to_string("/proc/self/limits")
                .ok()
                .and_then(|text| max_open_files(&text)),
            disk_free_bytes: rustix::fs::statvfs(data_dir)
                .ok()
                .map(|fs| fs.f_bavail.saturating_mul(fs.f_frsize)),
            start_time_seconds: start_time_seconds(),
        }
    }
}

fn start_time_seconds() -> Option<f64> {
    let stat = std::fs::read_to_string("/proc/self/stat").ok()?;
    // The command name (field 2) may hold spaces: count from after it.
    // starttime is field 22, the 20th after the name.
    let after_name = &stat[stat.rfind(')')? + 1..];
    let ticks: u64 = after_name.split_whitespace().nth(19)?.parse().ok()?;
    let boot = std::fs::read_to_string("/proc/stat").ok()?;
    let boot: u64 = boot
        .lines()
        .find_map(|line| line.strip_prefix("btime "))?
        .trim()
        .parse()
        .ok()?;
    let per_second = rustix::param::clock_ticks_per_second();
    Some(boot as f64 + ticks as f64 / per_second as f64)
}

fn resident_memory_bytes() -> Option<u64> {
    let statm = std::fs::read_to_string("/proc/self/statm").ok()?;
    let pages: u64 = statm.split_whitespace().nth(1)?.parse().ok()?;
    Some(pages * rustix::param::page_size() as u64)
}

/// The soft limit from /proc/self/limits' "Max open files" line.
fn max_open_files(limits: &str) -> Option<u64> {
    let line = limits.lines().find(|l| l.starts_with("Max open files"))?;
    line["Max open files".len()..]
        .split_whitespace()
        .next()?
        .parse()
        .ok()
}

/// Raises the soft limit on open file descriptors to the hard limit, as
/// servers commonly do at start (the soft limit is often 1024, the hard
/// one far higher): every AMQP connection and every HTTP connection holds
/// one. Logs the change, or why there was none.
pub fn raise_open_files_limit() {
    use rustix::process::{getrlimit, setrlimit, Resource};
    let mut limit = getrlimit(Resource::Nofile);
    let before = limit.current;
    if before == limit.maximum {
        return;
    }
    limit.current = limit.maximum;
    match setrlimit(Resource::Nofile, limit) {
        Ok(()) => tracing::info!(from = ?before, to = ?limit.maximum, "raised the open-file limit"),
        Err(e) => tracing::warn!(limit = ?before, error = %e, "cannot raise the open-file limit"),
    }
}

/// This node's name, `leveret@HOST`.
pub fn node_name() -> String {
    let uname = rustix::system::uname();
    let host = uname.nodename().to_string_lossy();
    let short = host.split('.').next().unwrap_or("localhost");
    format!("leveret@{short}")
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_soft_limit_is_read_from_proc_limits() {
        let text = "Limit                     Soft Limit           Hard Limit           Units     \n\
                    Max cpu time              unlimited            unlimited            seconds   \n\
                    Max open files            1024                 524288               files     \n";
        assert_eq!(max_open_files(text), Some(1024));
        assert_eq!(max_open_files("nothing here"), None);
    }

    #[test]
    fn this_process_has_figures_on_linux() {
        let figures = ProcessFigures::read(Path::new("/"));
        if cfg!(target_os = "linux") {
            assert!(figures.resident_memory_bytes.unwrap() > 0);
            assert!(figures.open_fds.unwrap() > 0);
            assert!(figures.max_fds.unwrap() > 0);
        }
        assert!(figures.disk_free_bytes.is_some());
        assert!(node_name().starts_with("leveret@"));
    }
}
