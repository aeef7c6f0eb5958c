//! A RabbitMQ 3.10 node of a test's own, from Debian's `rabbitmq-server`
//! run unprivileged from its scripts: its own directory, AMQP and
//! distribution ports, and a `HOME` whose Erlang cookie nodes that are
//! to form a cluster share. Stopped when dropped.

use std::path::{Path, PathBuf};
use std::process::{Child, Command, Output, Stdio};
use std::time::{Duration, Instant};

/// Debian's unprivileged RabbitMQ scripts.
pub const BIN: &str = "/usr/lib/rabbitmq/bin";

fn free_port() -> u16 {
    crate::reserved_port::reserved_addr().port()
}

/// Whether RabbitMQ is installed; under CI (`CI` set) a missing one fails
/// the test instead, as `.ci/run` installs it.
pub fn installed() -> bool {
    if Path::new(BIN).join("rabbitmq-server").exists() {
        return true;
    }
    let in_ci = std::env::var_os("CI").is_some_and(|v| !v.is_empty() && v != "0" && v != "false");
    assert!(!in_ci, "rabbitmq-server is not installed, and CI needs it");
    eprintln!(
        "\n*** SKIPPED: rabbitmq-server is not installed (apt-get install rabbitmq-server)\n"
    );
    false
}

/// A running node.
#[derive(Debug)]
pub struct RabbitNode {
    /// Its Erlang node name (`NAME@localhost`).
    pub name: String,
    /// Its AMQP port on 127.0.0.1.
    pub port: u16,
    /// Its own directory (database, logs, config).
    pub dir: PathBuf,
    /// Its management API on 127.0.0.1, when started with it.
    pub management_port: Option<u16>,
    home: PathBuf,
    child: Child,
}

impl RabbitNode {
    fn env(&self, command: &mut Command) {
        RabbitNode::env_for(command, &self.home, &self.dir, &self.name);
    }

    fn env_for(command: &mut Command, home: &Path, dir: &Path, name: &str) {
        command
            .env("HOME", home)
            .env("RABBITMQ_NODENAME", name)
            .env("RABBITMQ_MNESIA_BASE", dir.join("mnesia"))
            .env("RABBITMQ_LOG_BASE", dir.join("log"))
            .env("RABBITMQ_ENABLED_PLUGINS_FILE", dir.join("enabled_plugins"))
            .env("RABBITMQ_CONFIG_FILE", dir.join("rabbitmq"))
            .env("RABBITMQ_PID_FILE", dir.join("pid"));
    }

    /// Starts a node named `name` in `dir` (created afresh) with `home` as
    /// its `HOME`, and waits until it runs.
    pub fn start(name: &str, dir: &Path, home: &Path) -> RabbitNode {
        RabbitNode::start_with(name, dir, home, false)
    }

    /// [`RabbitNode::start`] with the management plugin, its API on a port
    /// of its own ([`RabbitNode::management_port`]).
    pub fn start_with_management(name: &str, dir: &Path, home: &Path) -> RabbitNode {
        RabbitNode::start_with(name, dir, home, true)
    }

    fn start_with(name: &str, dir: &Path, home: &Path, management: bool) -> RabbitNode {
        let _ = std::fs::remove_dir_all(dir);
        std::fs::create_dir_all(dir).expect("node dir");
        let plugins = if management {
            "[rabbitmq_management].\n"
        } else {
            "[].\n"
        };
        std::fs::write(dir.join("enabled_plugins"), plugins).expect("plugins");
        let port = free_port();
        let management_port = management.then(free_port);
        let mut config = format!("listeners.tcp.1 = 127.0.0.1:{port}\nloopback_users = none\n");
        if let Some(http) = management_port {
            config.push_str(&format!(
                "management.tcp.ip = 127.0.0.1\nmanagement.tcp.port = {http}\n"
            ));
        }
        std::fs::write(dir.join("rabbitmq.conf"), config).expect("config");
        let name = format!("{name}-{}@localhost", std::process::id());
        let mut command = Command::new(format!("{BIN}/rabbitmq-server"));
        RabbitNode::env_for(&mut command, home, dir, &name);
        let child = command
            .env("RABBITMQ_DIST_PORT", free_port().to_string())
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .expect("start rabbitmq-server");
        let node = RabbitNode {
            name,
            port,
            dir: dir.to_owned(),
            management_port,
            home: home.to_owned(),
            child,
        };
        node.await_startup();
        node
    }

    /// `rabbitmqctl -n NODE args`, whatever its outcome.
    pub fn ctl(&self, args: &[&str]) -> Output {
        let mut command = Command::new(format!("{BIN}/rabbitmqctl"));
        self.env(&mut command);
        command
            .arg("-n")
            .arg(&self.name)
            .args(args)
            .output()
            .expect("rabbitmqctl")
    }

    /// `rabbitmqctl`, which must succeed; its standard output.
    pub fn must(&self, args: &[&str]) -> String {
        let out = self.ctl(args);
        assert!(out.status.success(), "rabbitmqctl {args:?}: {out:?}");
        String::from_utf8_lossy(&out.stdout).into_owned()
    }

    /// Waits (up to two minutes) until the node runs.
    pub fn await_startup(&self) {
        let deadline = Instant::now() + Duration::from_secs(120);
        while !self
            .ctl(&["await_startup", "--timeout", "30"])
            .status
            .success()
        {
            assert!(
                Instant::now() < deadline,
                "node {} did not start",
                self.name
            );
            std::thread::sleep(Duration::from_millis(500));
        }
    }

    /// Its AMQP URI as guest on vhost `/`.
    pub fn uri(&self) -> String {
        format!("amqp://guest:guest@127.0.0.1:{}/%2f", self.port)
    }

    /// A path in its directory.
    pub fn file(&self, name: &str) -> PathBuf {
        self.dir.join(name)
    }
}

impl Drop for RabbitNode {
    fn drop(&mut self) {
        let _ = self.ctl(&["stop"]);
        let _ = self.child.kill();
        let _ = self.child.wait();
        let _ = std::fs::remove_dir_all(&self.dir);
    }
}
