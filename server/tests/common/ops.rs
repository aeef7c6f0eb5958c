//! The `leveret` binary with every listener on port 0 (AMQP, metrics,
//! management API), the addresses read from its log; a raw HTTP/1.1
//! client for exact requests (bad auth, oversized or malformed bodies);
//! and `promtool check metrics` when Prometheus' tools are installed.

use std::ffi::OsStr;
use std::io::{BufRead, BufReader};
use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::Duration;
use tokio::io::{AsyncReadExt, AsyncWriteExt};

/// A running `leveret` whose listeners all took free ports; killed when dropped.
pub struct OpsBroker {
    child: Child,
    dir: PathBuf,
    /// Whether dropping it removes its data directory.
    owns_dir: bool,
    /// The AMQP listener.
    pub amqp: SocketAddr,
    /// The AMQP-over-TLS listener, when `--tls-listen` was given.
    pub tls: Option<SocketAddr>,
    /// The Prometheus endpoint.
    pub metrics: SocketAddr,
    /// The management API.
    pub http: SocketAddr,
    log: std::sync::Arc<std::sync::Mutex<Vec<String>>>,
}

/// Removes ANSI colour sequences from a log line.
fn plain(line: &str) -> String {
    let mut out = String::with_capacity(line.len());
    let mut chars = line.chars();
    while let Some(c) = chars.next() {
        if c == '\u{1b}' {
            for c in chars.by_ref() {
                if c.is_ascii_alphabetic() {
                    break;
                }
            }
        } else {
            out.push(c);
        }
    }
    out
}

/// The `addr=` field of a log line that contains `marker` (the `addr`
/// key of a `--log-format json` line).
fn address(line: &str, marker: &str) -> Option<SocketAddr> {
    if let Ok(object) = serde_json::from_str::<serde_json::Value>(line) {
        let message = object["message"].as_str()?;
        return message
            .contains(marker)
            .then(|| object["addr"].as_str()?.parse().ok())?;
    }
    let line = plain(line);
    if !line.contains(marker) {
        return None;
    }
    let at = line.find("addr=")? + "addr=".len();
    line[at..].split_whitespace().next()?.parse().ok()
}

impl OpsBroker {
    /// Starts `leveret` with its data in a fresh directory named after
    /// `name`, and `extra` arguments; waits (up to 20 s) for its listeners.
    pub fn start(name: &str, extra: &[&str]) -> OpsBroker {
        let dir = std::env::temp_dir().join(format!("leveret-ops-{}-{name}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        Self::launch(dir, extra)
    }

    /// Kills the broker with SIGKILL (no clean shutdown: what it answered
    /// was already on disk, or is lost) and starts it again on the same
    /// data directory with `extra` arguments.
    pub fn kill_and_restart(mut self, extra: &[&str]) -> OpsBroker {
        let _ = self.child.kill();
        let _ = self.child.wait();
        self.owns_dir = false;
        Self::launch(self.dir.clone(), extra)
    }

    /// Starts `leveret` with its data in `dir`, which it leaves in place
    /// when dropped, and `extra` arguments; waits (up to 20 s) for its
    /// listeners.
    pub fn on_data_dir<S: AsRef<OsStr>>(dir: &Path, extra: &[S]) -> OpsBroker {
        let mut broker = Self::launch(dir.to_path_buf(), extra);
        broker.owns_dir = false;
        broker
    }

    fn launch<S: AsRef<OsStr>>(dir: PathBuf, extra: &[S]) -> OpsBroker {
        // `extra` may put the management API elsewhere.
        let http_default = if extra.iter().any(|arg| arg.as_ref() == "--http-listen") {
            &[][..]
        } else {
            &["--http-listen", "127.0.0.1:0"][..]
        };
        let mut child = Command::new(env!("CARGO_BIN_EXE_leveret"))
            .args(["--listen", "127.0.0.1:0", "--metrics-listen", "127.0.0.1:0"])
            .args(["--mqtt-listen", "none"])
            .args(http_default)
            .arg("--data-dir")
            .arg(&dir)
            .args(["--log", "info"])
            .args(extra)
            .stdout(Stdio::null())
            .stderr(Stdio::piped())
            .spawn()
            .expect("start leveret");
        let stderr = child.stderr.take().expect("stderr");
        let (found, addresses) = std::sync::mpsc::channel();
        let log = std::sync::Arc::new(std::sync::Mutex::new(Vec::new()));
        let kept = std::sync::Arc::clone(&log);
        std::thread::spawn(move || {
            // Reads the log to its end, so the broker never blocks on a full pipe.
            for line in BufReader::new(stderr).lines().map_while(Result::ok) {
                kept.lock().expect("log").push(line.clone());
                if line.contains("over TLS") {
                    if let Some(addr) = address(&line, "accepting AMQP") {
                        let _ = found.send(("TLS", addr));
                    }
                    continue;
                }
                for marker in [
                    "accepting AMQP",
                    "serving Prometheus metrics",
                    "serving the management API",
                ] {
                    if let Some(addr) = address(&line, marker) {
                        let _ = found.send((marker, addr));
                    }
                }
            }
        });
        let (mut amqp, mut metrics, mut http, mut tls) = (None, None, None, None);
        let wants_tls = extra.iter().any(|arg| arg.as_ref() == "--tls-listen");
        while amqp.is_none() || metrics.is_none() || http.is_none() || (wants_tls && tls.is_none())
        {
            match addresses.recv_timeout(Duration::from_secs(20)) {
                Ok(("accepting AMQP", addr)) => amqp = Some(addr),
                Ok(("TLS", addr)) => tls = Some(addr),
                Ok(("serving Prometheus metrics", addr)) => metrics = Some(addr),
                Ok((_, addr)) => http = Some(addr),
                Err(_) => {
                    let _ = child.kill();
                    let _ = child.wait();
                    std::thread::sleep(Duration::from_millis(100));
                    let lines = log.lock().expect("log").join("\n");
                    panic!("leveret did not report its listeners; its log:\n{lines}");
                }
            }
        }
        OpsBroker {
            child,
            dir,
            owns_dir: true,
            amqp: amqp.expect("seen"),
            tls,
            metrics: metrics.expect("seen"),
            http: http.expect("seen"),
            log,
        }
    }

    /// The broker's process id (for its figures in `/proc`).
    pub fn pid(&self) -> u32 {
        self.child.id()
    }

    /// The log lines so far, without colours.
    pub fn log(&self) -> Vec<String> {
        self.raw_log().iter().map(|line| plain(line)).collect()
    }

    /// The log lines so far, as written.
    pub fn raw_log(&self) -> Vec<String> {
        self.log.lock().expect("log").clone()
    }

    /// SIGKILL: no chance to flush anything.
    pub fn kill9(mut self) {
        self.child.kill().expect("kill -9");
        self.child.wait().expect("reap");
    }

    /// SIGTERM: a clean shutdown, which must exit 0.
    pub fn terminate(mut self) {
        self.signal("TERM");
        let exit = self.child.wait().expect("reap");
        assert!(exit.success(), "clean shutdown exits 0, got {exit}");
    }

    /// Sends a signal (`HUP`, `TERM`...) to the broker.
    pub fn signal(&self, name: &str) {
        let status = Command::new("kill")
            .args(["-s", name, &self.child.id().to_string()])
            .status()
            .expect("kill");
        assert!(status.success(), "kill -s {name}");
    }

    /// Waits (up to 10 s) for a log line containing `text`.
    pub fn wait_for_log(&self, text: &str) {
        let deadline = std::time::Instant::now() + Duration::from_secs(10);
        while !self.log().iter().any(|line| line.contains(text)) {
            assert!(
                std::time::Instant::now() < deadline,
                "no log line with {text:?}:\n{}",
                self.log().join("\n")
            );
            std::thread::sleep(Duration::from_millis(20));
        }
    }

    /// The AMQP URL of vhost `/` as guest.
    /// The address of the broker's first MQTT listener, as its log says.
    pub fn mqtt_addr(&self) -> SocketAddr {
        self.wait_for_log("accepting MQTT");
        self.raw_log()
            .iter()
            .find_map(|line| address(line, "accepting MQTT"))
            .expect("an MQTT listener")
    }

    pub fn amqp_url(&self) -> String {
        format!("amqp://guest:guest@{}/%2f", self.amqp)
    }
}

impl Drop for OpsBroker {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
        if self.owns_dir {
            let _ = std::fs::remove_dir_all(&self.dir);
        }
    }
}

/// An HTTP response.
#[derive(Debug)]
pub struct Response {
    /// Status code.
    pub status: u16,
    /// Header lines, names in lower case.
    pub headers: Vec<(String, String)>,
    /// The body, de-chunked.
    pub body: Vec<u8>,
}

impl Response {
    /// The body as text.
    pub fn text(&self) -> String {
        String::from_utf8_lossy(&self.body).into_owned()
    }

    /// A header's value.
    pub fn header(&self, name: &str) -> Option<&str> {
        self.headers
            .iter()
            .find(|(n, _)| n == name)
            .map(|(_, v)| v.as_str())
    }
}

/// Sends one request (`Connection: close`) and reads the whole answer.
pub async fn request(
    addr: SocketAddr,
    method: &str,
    path: &str,
    headers: &[(&str, &str)],
    body: &[u8],
) -> Response {
    try_request(addr, method, path, headers, body)
        .await
        .unwrap_or_else(|| panic!("{method} {path}: closed without an answer"))
}

/// As [`request`]; `None` if the server closed without answering.
pub async fn try_request(
    addr: SocketAddr,
    method: &str,
    path: &str,
    headers: &[(&str, &str)],
    body: &[u8],
) -> Option<Response> {
    let exchange = async {
        let mut stream = tokio::net::TcpStream::connect(addr).await.expect("connect");
        let mut head = format!("{method} {path} HTTP/1.1\r\nHost: {addr}\r\nConnection: close\r\n");
        for (name, value) in headers {
            head.push_str(&format!("{name}: {value}\r\n"));
        }
        head.push_str(&format!("Content-Length: {}\r\n\r\n", body.len()));
        stream.write_all(head.as_bytes()).await.expect("write head");
        // A server may answer (413) before reading all of a large body.
        let _ = stream.write_all(body).await;
        let mut raw = Vec::new();
        let _ = stream.read_to_end(&mut raw).await;
        raw
    };
    let raw = tokio::time::timeout(Duration::from_secs(30), exchange)
        .await
        .expect("an answer within 30 s");
    if raw.is_empty() {
        return None;
    }
    Some(parse(&raw))
}

fn parse(raw: &[u8]) -> Response {
    let split = raw
        .windows(4)
        .position(|w| w == b"\r\n\r\n")
        .unwrap_or_else(|| panic!("no HTTP head in {:?}", String::from_utf8_lossy(raw)));
    let head = String::from_utf8_lossy(&raw[..split]).into_owned();
    let mut lines = head.split("\r\n");
    let status = lines
        .next()
        .and_then(|l| l.split_whitespace().nth(1))
        .and_then(|s| s.parse().ok())
        .expect("a status line");
    let headers: Vec<(String, String)> = lines
        .filter_map(|l| l.split_once(':'))
        .map(|(n, v)| (n.trim().to_ascii_lowercase(), v.trim().to_owned()))
        .collect();
    let mut body = raw[split + 4..].to_vec();
    let chunked = headers
        .iter()
        .any(|(n, v)| n == "transfer-encoding" && v.contains("chunked"));
    if chunked {
        body = dechunk(&body);
    }
    Response {
        status,
        headers,
        body,
    }
}

fn dechunk(mut data: &[u8]) -> Vec<u8> {
    let mut out = Vec::new();
    loop {
        let Some(end) = data.windows(2).position(|w| w == b"\r\n") else {
            return out;
        };
        let size_text = String::from_utf8_lossy(&data[..end]);
        let size = usize::from_str_radix(size_text.split(';').next().unwrap_or("0").trim(), 16)
            .expect("chunk size");
        if size == 0 {
            return out;
        }
        out.extend_from_slice(&data[end + 2..end + 2 + size]);
        data = &data[end + 2 + size + 2..];
    }
}

/// `promtool check metrics` on `text`: `None` when promtool is not
/// installed, else its verdict (the problems it lists on failure).
pub fn promtool_check(text: &str) -> Option<Result<(), String>> {
    use std::io::Write;
    let mut child = match Command::new("promtool")
        .args(["check", "metrics"])
        .stdin(Stdio::piped())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
    {
        Ok(child) => child,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return None,
        Err(e) => panic!("cannot run promtool: {e}"),
    };
    child
        .stdin
        .take()
        .expect("stdin")
        .write_all(text.as_bytes())
        .expect("feed promtool");
    let output = child.wait_with_output().expect("promtool");
    Some(if output.status.success() {
        Ok(())
    } else {
        Err(format!(
            "{}{}",
            String::from_utf8_lossy(&output.stdout),
            String::from_utf8_lossy(&output.stderr)
        ))
    })
}

/// The `Authorization` header for `user:password`.
pub fn basic(user: &str, password: &str) -> String {
    use base64::Engine;
    let token = base64::engine::general_purpose::STANDARD.encode(format!("{user}:{password}"));
    format!("Basic {token}")
}

/// Whether the operators' tool `program` (run as `program version_arg`)
/// is installed. Outside CI a missing tool skips the test that needs it
/// with a loud message naming the package; under CI (`CI` set, as
/// `.ci/run` does) it is a failure, since `.ci/run` installs every tool.
pub fn tool_available(program: &str, package: &str) -> bool {
    let found = Command::new("sh")
        .args(["-c", &format!("command -v {program}")])
        .stdout(Stdio::null())
        .status()
        .is_ok_and(|s| s.success());
    if found {
        return true;
    }
    missing(program, &format!("Debian's {package}"));
    false
}

/// Reports a tool a test needs and cannot find: a failure under CI (`CI`
/// set), a skip message otherwise. `install` says where `.ci/run` gets it.
pub fn missing(program: &str, install: &str) {
    let in_ci = std::env::var_os("CI").is_some_and(|v| !v.is_empty() && v != "0" && v != "false");
    assert!(
        !in_ci,
        "{program} is not installed, and CI needs it (.ci/run installs {install})"
    );
    eprintln!(
        "\n*** SKIPPED: {program} is not installed ({install}); \
         this test ran nothing. Under CI (CI=1) this is a failure. ***\n"
    );
}
