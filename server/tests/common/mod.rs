//! The `leveret` binary as a child process on a free loopback port, for
//! the tests that need a real process (kill -9, signals, the command line).

#![allow(dead_code)] // Each test file uses its own share of these helpers.

pub mod ops;

use std::ffi::OsStr;
use std::path::Path;
use std::process::{Child, Command, Stdio};
use std::time::Duration;

/// A running `leveret`; killed when dropped.
pub struct BrokerProcess {
    child: Child,
    port: u16,
}

impl BrokerProcess {
    /// Starts `leveret` on a free port with its data in `dir`.
    pub async fn start(dir: &Path) -> BrokerProcess {
        BrokerProcess::start_with(dir, std::iter::empty::<&OsStr>()).await
    }

    /// Starts `leveret` on a free port with its data in `dir` and `extra`
    /// arguments, and waits until it accepts connections.
    pub async fn start_with<I, S>(dir: &Path, extra: I) -> BrokerProcess
    where
        I: IntoIterator<Item = S>,
        S: AsRef<OsStr>,
    {
        let port = std::net::TcpListener::bind("127.0.0.1:0")
            .and_then(|l| l.local_addr())
            .expect("free port")
            .port();
        let mut child = Command::new(env!("CARGO_BIN_EXE_leveret"))
            .arg("--listen")
            .arg(format!("127.0.0.1:{port}"))
            .arg("--data-dir")
            .arg(dir)
            .arg("--log")
            .arg("warn")
            .args([
                "--metrics-listen",
                "127.0.0.1:0",
                "--http-listen",
                "127.0.0.1:0",
            ])
            .args(extra)
            .stdout(Stdio::null())
            .spawn()
            .expect("start leveret");
        // The listener is the event to wait for; the broker starts in
        // milliseconds, so poll it briefly.
        for _ in 0..2000 {
            if tokio::net::TcpStream::connect(("127.0.0.1", port))
                .await
                .is_ok()
            {
                return BrokerProcess { child, port };
            }
            tokio::time::sleep(Duration::from_millis(5)).await;
        }
        let _ = child.kill();
        let _ = child.wait();
        panic!("leveret did not start listening on {port}");
    }

    /// The URL of vhost `/` as `guest`.
    pub fn url(&self) -> String {
        self.url_as("guest", "guest")
    }

    /// The URL of vhost `/` as `user`.
    pub fn url_as(&self, user: &str, password: &str) -> String {
        format!("amqp://{user}:{password}@127.0.0.1:{}/%2f", self.port)
    }

    /// SIGKILL: no chance to flush anything.
    pub fn kill9(mut self) {
        self.child.kill().expect("kill -9");
        self.child.wait().expect("reap");
    }

    /// SIGTERM: a clean shutdown.
    pub fn terminate(mut self) {
        let status = Command::new("kill")
            .arg("-TERM")
            .arg(self.child.id().to_string())
            .status()
            .expect("kill -TERM");
        assert!(status.success());
        let exit = self.child.wait().expect("reap");
        assert!(exit.success(), "clean shutdown exits 0, got {exit}");
    }
}

impl Drop for BrokerProcess {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}
