//! The `leveret` binary as a child process, for the tests that need a
//! real process (kill -9, signals, the command line).

#![allow(dead_code)] // Each test file uses its own share of these helpers.

pub mod damage;
pub mod ops;

use std::ffi::{OsStr, OsString};
use std::path::Path;

/// A running `leveret` with its data in a directory the test owns; killed
/// when dropped. Its listeners take free ports and their addresses are
/// read from its log, so no other process can take its port in between.
pub struct BrokerProcess {
    broker: ops::OpsBroker,
}

impl BrokerProcess {
    /// Starts `leveret` with its data in `dir`.
    pub async fn start(dir: &Path) -> BrokerProcess {
        BrokerProcess::start_with(dir, std::iter::empty::<&OsStr>()).await
    }

    /// Starts `leveret` with its data in `dir` and `extra` arguments, and
    /// waits until it accepts connections.
    pub async fn start_with<I, S>(dir: &Path, extra: I) -> BrokerProcess
    where
        I: IntoIterator<Item = S>,
        S: AsRef<OsStr>,
    {
        let dir = dir.to_path_buf();
        let extra: Vec<OsString> = extra.into_iter().map(|a| a.as_ref().into()).collect();
        // Waiting for its log blocks; keep the test's runtime free meanwhile.
        let broker = tokio::task::spawn_blocking(move || ops::OpsBroker::on_data_dir(&dir, &extra))
            .await
            .expect("start leveret");
        BrokerProcess { broker }
    }

    /// The URL of vhost `/` as `guest`.
    pub fn url(&self) -> String {
        self.url_as("guest", "guest")
    }

    /// The URL of vhost `/` as `user`.
    pub fn url_as(&self, user: &str, password: &str) -> String {
        format!("amqp://{user}:{password}@{}/%2f", self.broker.amqp)
    }

    /// SIGKILL: no chance to flush anything.
    pub fn kill9(self) {
        self.broker.kill9();
    }

    /// SIGTERM: a clean shutdown.
    pub fn terminate(self) {
        self.broker.terminate();
    }
}
