//! The `leveret` binary's log as an operator reads it: the start banner
//! (every listener),
//! RabbitMQ's connection lines (accepting, authenticated, closing with
//! vhost, user, client-provided name, duration and reason) through
//! connection churn, refused logins with the user name and mechanism,
//! changes made through the management API with the acting user, the
//! definitions loaded at start as a sentence; plain text (no ANSI
//! colours) when standard error is not a terminal (coloured on one, plain
//! in a log file), and `--log-format json`
//! with one parseable object per line.

mod common;

use common::ops::{basic, request, OpsBroker};
use lapin::{Connection, ConnectionProperties};
use serde_json::Value;
use std::time::{Duration, Instant};
use tokio::io::AsyncWriteExt;

/// Connections each churn test opens and closes.
const CHURN: usize = 12;

/// Waits (up to 20 s) until `count` log lines satisfy `matches`; returns them.
fn wait_for_lines(broker: &OpsBroker, count: usize, matches: impl Fn(&str) -> bool) -> Vec<String> {
    let deadline = Instant::now() + Duration::from_secs(20);
    loop {
        let found: Vec<String> = broker
            .raw_log()
            .into_iter()
            .filter(|line| matches(line))
            .collect();
        if found.len() >= count {
            return found;
        }
        assert!(
            Instant::now() < deadline,
            "{} of {count} lines found; the log:\n{}",
            found.len(),
            broker.raw_log().join("\n")
        );
        std::thread::sleep(Duration::from_millis(20));
    }
}

/// Opens and cleanly closes `CHURN` connections named `churn-N`.
async fn churn(broker: &OpsBroker) {
    for n in 0..CHURN {
        let properties =
            ConnectionProperties::default().with_connection_name(format!("churn-{n}").into());
        let conn = Connection::connect(&broker.amqp_url(), properties)
            .await
            .expect("connect");
        conn.close(200, "bye").await.expect("close");
    }
}

/// A connection that sends the protocol header and then drops its socket.
async fn drop_after_header(broker: &OpsBroker) {
    let mut socket = tokio::net::TcpStream::connect(broker.amqp)
        .await
        .expect("connect");
    socket
        .write_all(b"AMQP\x00\x00\x09\x01")
        .await
        .expect("header");
    // Read connection.start so the broker has accepted the header.
    let mut start = [0u8; 7];
    tokio::io::AsyncReadExt::read_exact(&mut socket, &mut start)
        .await
        .expect("connection.start");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn text_log_has_the_banner_and_a_line_per_open_and_close_without_colours() {
    let broker = OpsBroker::start("log-text", &["--mqtt-listen", "127.0.0.1:0"]);
    let banner = wait_for_lines(&broker, 1, |line| line.contains("started; config file"));
    let version = env!("CARGO_PKG_VERSION");
    let expected = format!("Leveret {version} started; config file: none; data directory: ");
    assert!(banner[0].contains(&expected), "{}", banner[0]);
    // Every listener, the MQTT one (on a port only the API tells) too.
    let guest = basic("guest", "guest");
    let overview = request(
        broker.http,
        "GET",
        "/api/overview",
        &[("Authorization", &guest)],
        b"",
    )
    .await;
    let overview: Value = serde_json::from_slice(&overview.body).expect("json");
    let mqtt = (overview["listeners"].as_array().expect("listeners").iter())
        .find(|l| l["protocol"] == "mqtt")
        .map(|l| format!("{}:{}", l["ip_address"].as_str().expect("ip"), l["port"]))
        .expect("an mqtt listener in the overview");
    for listener in [
        format!("amqp {}, ", broker.amqp),
        format!("mqtt {mqtt}, "),
        format!("http {} (management API), ", broker.http),
        format!("http/prometheus {}", broker.metrics),
    ] {
        assert!(banner[0].contains(&listener), "{listener} in {}", banner[0]);
    }

    churn(&broker).await;
    let local = broker.amqp.to_string();
    let accepted = wait_for_lines(&broker, CHURN, |line| {
        line.contains("accepting AMQP connection #") && line.contains(&format!(" -> {local})"))
    });
    assert_eq!(accepted.len(), CHURN);
    let granted = wait_for_lines(&broker, CHURN, |line| {
        line.contains("): user 'guest' authenticated and granted access to vhost '/'")
    });
    for n in 0..CHURN {
        let name = format!(" -> {local} - churn-{n}): user 'guest'");
        assert_eq!(
            granted.iter().filter(|line| line.contains(&name)).count(),
            1,
            "one authenticated line for churn-{n}"
        );
    }
    let closed = wait_for_lines(&broker, CHURN, |line| {
        line.contains("closing AMQP connection #") && line.contains("closed by the client")
    });
    for n in 0..CHURN {
        let needle = format!(" - churn-{n}, vhost: '/', user: 'guest', duration: ");
        let line = closed
            .iter()
            .find(|line| line.contains(&needle))
            .unwrap_or_else(|| panic!("no closing line for churn-{n}: {closed:#?}"));
        assert!(line.contains(" INFO "), "a clean close is info: {line}");
    }

    drop_after_header(&broker).await;
    let dropped = wait_for_lines(&broker, 1, |line| {
        line.contains("client unexpectedly closed TCP connection")
    });
    assert!(dropped[0].contains(" WARN "), "{}", dropped[0]);
    assert!(
        dropped[0].contains("vhost: none, user: none"),
        "{}",
        dropped[0]
    );

    let log = broker.raw_log();
    assert!(
        log.iter().all(|line| !line.contains('\u{1b}')),
        "no ANSI escape when standard error is a pipe:\n{}",
        log.join("\n")
    );
    assert!(log.iter().all(|line| !line.contains("Applied {")));
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn json_log_is_one_object_per_line_with_stable_keys_and_connection_fields() {
    let broker = OpsBroker::start("log-json", &["--log-format", "json"]);
    churn(&broker).await;
    wait_for_lines(&broker, CHURN, |line| {
        line.contains("closing AMQP connection #")
    });
    let log = broker.raw_log();
    let objects: Vec<Value> = log
        .iter()
        .map(|line| serde_json::from_str(line).unwrap_or_else(|e| panic!("not JSON ({e}): {line}")))
        .collect();
    for object in &objects {
        for key in ["timestamp", "level", "target", "message"] {
            assert!(object[key].is_string(), "{key} in {object}");
        }
    }
    let with = |prefix: &str| -> Vec<&Value> {
        objects
            .iter()
            .filter(|o| {
                o["message"]
                    .as_str()
                    .unwrap_or_default()
                    .starts_with(prefix)
            })
            .collect()
    };
    let banner = with("Leveret ");
    assert_eq!(banner.len(), 1, "{log:#?}");
    assert_eq!(banner[0]["version"], env!("CARGO_PKG_VERSION"));
    assert_eq!(banner[0]["config_file"], "none");
    assert!(banner[0]["listeners"]
        .as_str()
        .is_some_and(|l| l.contains(&format!("amqp {}", broker.amqp))));

    let accepted = with("accepting AMQP connection #");
    assert_eq!(accepted.len(), CHURN, "{log:#?}");
    for line in &accepted {
        assert_eq!(line["level"], "INFO");
        assert_eq!(line["local"], broker.amqp.to_string());
        assert!(line["peer"]
            .as_str()
            .is_some_and(|p| p.starts_with("127.0.0.1:")));
        assert!(line["connection"].is_u64());
    }
    let opened = with("connection #");
    assert_eq!(opened.len(), CHURN);
    let closed = with("closing AMQP connection #");
    assert_eq!(closed.len(), CHURN);
    for n in 0..CHURN {
        let name = format!("churn-{n}");
        let open = opened
            .iter()
            .find(|o| o["client_name"] == name.as_str())
            .unwrap_or_else(|| panic!("an authenticated line for {name}"));
        assert_eq!(open["user"], "guest");
        assert_eq!(open["vhost"], "/");
        let close = closed
            .iter()
            .find(|o| o["client_name"] == name.as_str())
            .unwrap_or_else(|| panic!("a closing line for {name}"));
        assert_eq!(close["user"], "guest");
        assert_eq!(close["vhost"], "/");
        assert_eq!(close["reason"], "closed by the client");
        assert_eq!(close["connection"], open["connection"]);
        assert_eq!(close["peer"], open["peer"]);
        assert!(close["duration_secs"].as_f64().is_some_and(|d| d >= 0.0));
    }
}

/// A refused login names the user and mechanism (the client is told to
/// see the log); a user name with a line break cannot forge a log line.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_refused_login_is_logged_with_the_user_and_mechanism() {
    let broker = OpsBroker::start("log-auth", &[]);
    let wrong = format!("amqp://guest:wrong@{}/%2f", broker.amqp);
    let refused = Connection::connect(&wrong, ConnectionProperties::default()).await;
    assert!(refused.is_err(), "a wrong password is refused");
    let line = wait_for_lines(&broker, 1, |line| {
        line.contains("PLAIN login refused: user 'guest' - invalid credentials")
    });
    assert!(line[0].contains(" WARN "), "{}", line[0]);
    assert!(line[0].contains("peer=127.0.0.1:"), "{}", line[0]);

    let forged = format!("amqp://evil%0AINFO%20forged:x@{}/%2f", broker.amqp);
    let refused = Connection::connect(&forged, ConnectionProperties::default()).await;
    assert!(refused.is_err());
    wait_for_lines(&broker, 1, |line| {
        line.contains("login refused: user 'evil\\nINFO forged'")
    });
    assert!(broker
        .raw_log()
        .iter()
        .all(|line| !line.starts_with("INFO forged")));
}

/// A refused management API login is logged as RabbitMQ's management
/// plugin logs it, with the peer whose checks are queued and slowed apart
/// from every other address's.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_refused_management_login_is_logged_with_the_user_and_peer() {
    let broker = OpsBroker::start("log-http-auth", &[]);
    let wrong = basic("guest", "wrong");
    let refused = request(
        broker.http,
        "GET",
        "/api/overview",
        &[("Authorization", wrong.as_str())],
        b"",
    )
    .await;
    assert_eq!(refused.status, 401, "{}", refused.text());
    let line = wait_for_lines(&broker, 1, |line| {
        line.contains("HTTP access denied: user 'guest' - invalid credentials")
    });
    assert!(line[0].contains(" WARN "), "{}", line[0]);
    assert!(line[0].contains("peer=127.0.0.1:"), "{}", line[0]);
}

/// Changes made through the management API are logged with the acting
/// user: closing a connection (whose own closing line gives the reason),
/// adding a user, granting a permission, importing definitions.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn management_changes_are_logged_with_the_acting_user() {
    let broker = OpsBroker::start("log-admin", &[]);
    let guest = basic("guest", "guest");
    let auth = [("Authorization", guest.as_str())];
    let conn = Connection::connect(&broker.amqp_url(), ConnectionProperties::default())
        .await
        .expect("connect");
    let list = request(broker.http, "GET", "/api/connections", &auth, b"").await;
    let list: Value = serde_json::from_slice(&list.body).expect("json");
    let name = list[0]["name"].as_str().expect("a connection").to_owned();
    let encoded: String = name
        .bytes()
        .map(|b| match b {
            b'A'..=b'Z' | b'a'..=b'z' | b'0'..=b'9' | b'.' | b'-' => (b as char).to_string(),
            _ => format!("%{b:02X}"),
        })
        .collect();
    let path = format!("/api/connections/{encoded}");
    let reason = [
        ("Authorization", guest.as_str()),
        ("X-Reason", "maintenance window"),
    ];
    let closed = request(broker.http, "DELETE", &path, &reason, b"").await;
    assert_eq!(closed.status, 204, "{}", closed.text());
    wait_for_lines(&broker, 1, |line| {
        line.contains(&format!(
            "management API: DELETE {path} by user 'guest': 204"
        ))
    });
    let forced = wait_for_lines(&broker, 1, |line| {
        line.contains("closing AMQP connection #") && line.contains("maintenance window")
    });
    assert!(forced[0].contains("user: 'guest'"), "{}", forced[0]);
    drop(conn);

    let user = br#"{"password": "pw", "tags": ""}"#;
    let added = request(broker.http, "PUT", "/api/users/newbie", &auth, user).await;
    assert!(
        added.status == 201 || added.status == 204,
        "{}",
        added.text()
    );
    wait_for_lines(&broker, 1, |line| {
        line.contains("management API: PUT /api/users/newbie by user 'guest': 20")
    });
    let permission = br#"{"configure": ".*", "write": ".*", "read": ".*"}"#;
    let path = "/api/permissions/%2F/newbie";
    let granted = request(broker.http, "PUT", path, &auth, permission).await;
    assert!(granted.status < 300, "{}", granted.text());
    wait_for_lines(&broker, 1, |line| {
        line.contains(&format!("management API: PUT {path} by user 'guest'"))
    });
    let definitions = br#"{"queues": [{"name": "imported", "vhost": "/"}]}"#;
    let imported = request(broker.http, "POST", "/api/definitions", &auth, definitions).await;
    assert!(imported.status < 300, "{}", imported.text());
    wait_for_lines(&broker, 1, |line| {
        line.contains("management API: POST /api/definitions by user 'guest'")
    });
    // Reads are not logged.
    assert!(broker
        .raw_log()
        .iter()
        .all(|line| !line.contains("management API: GET")));
}

/// The definitions loaded at start are counted in a sentence, every kind
/// the file defines, including what the builder took before the apply.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn definitions_loaded_at_start_are_counted_in_a_sentence() {
    let dir = std::env::temp_dir().join(format!("leveret-log-defs-{}", std::process::id()));
    std::fs::create_dir_all(&dir).expect("dir");
    let file = dir.join("definitions.json");
    std::fs::write(
        &file,
        br#"{"vhosts": [{"name": "/"}, {"name": "robots"}],
            "users": [{"name": "guest", "password_hash": "XrbDVjlDKoAec+dZ1vISo+jt5TVEqQvMa8euInsOyfsIm1Ys",
                "hashing_algorithm": "rabbit_password_hashing_sha256", "tags": ["administrator"]}],
            "permissions": [{"user": "guest", "vhost": "/", "configure": ".*", "write": ".*", "read": ".*"},
                {"user": "guest", "vhost": "robots", "configure": ".*", "write": ".*", "read": ".*"}],
            "queues": [{"name": "a", "vhost": "/"}, {"name": "b", "vhost": "robots"}]}"#,
    )
    .expect("write");
    let file = file.to_str().expect("utf-8").to_owned();
    let broker = OpsBroker::start("log-defs", &["--definitions", &file]);
    wait_for_lines(&broker, 1, |line| {
        line.contains("definitions loaded: 2 vhosts, 1 user, 2 permissions, 2 queues")
    });
    drop(broker);
    let _ = std::fs::remove_dir_all(&dir);
}

/// The lines of the file at `path` once one contains `text` (up to 20 s).
fn wait_in_file(path: &std::path::Path, text: &str) -> Vec<String> {
    let deadline = Instant::now() + Duration::from_secs(20);
    loop {
        let content = std::fs::read_to_string(path).unwrap_or_default();
        if content.contains(text) {
            return content.lines().map(str::to_owned).collect();
        }
        assert!(
            Instant::now() < deadline,
            "no {text:?} in {}:\n{content}",
            path.display()
        );
        std::thread::sleep(Duration::from_millis(20));
    }
}

/// `--log-file`: the log goes to the file (plain text), and SIGHUP after
/// a rename (logrotate's way) reopens the path: later lines go to the new
/// file, none to the renamed one.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_log_file_is_reopened_on_sighup_after_a_rename() {
    let dir = std::env::temp_dir().join(format!("leveret-log-file-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).expect("dir");
    let path = dir.join("leveret.log");
    let mut child = std::process::Command::new(env!("CARGO_BIN_EXE_leveret"))
        .args(["--listen", "127.0.0.1:0", "--metrics-listen", "127.0.0.1:0"])
        .args(["--mqtt-listen", "none"])
        .args(["--http-listen", "127.0.0.1:0", "--log", "info"])
        .arg("--data-dir")
        .arg(dir.join("data"))
        .arg("--log-file")
        .arg(&path)
        .stderr(std::process::Stdio::null())
        .spawn()
        .expect("start leveret");
    let lines = wait_in_file(&path, "started; config file");
    let amqp: std::net::SocketAddr = lines
        .iter()
        .find(|line| line.contains("accepting AMQP 0.9.1 connections"))
        .and_then(|line| line.split("addr=").nth(1))
        .and_then(|addr| addr.split_whitespace().next())
        .and_then(|addr| addr.parse().ok())
        .expect("the AMQP listener's line");
    assert!(lines.iter().all(|line| !line.contains('\u{1b}')));

    let rotated = dir.join("leveret.log.1");
    std::fs::rename(&path, &rotated).expect("rename");
    let hup = std::process::Command::new("kill")
        .args(["-s", "HUP", &child.id().to_string()])
        .status()
        .expect("kill");
    assert!(hup.success());
    wait_in_file(&path, "log file reopened");
    let url = format!("amqp://guest:guest@{amqp}/%2f");
    let properties = ConnectionProperties::default().with_connection_name("after-rotation".into());
    let conn = Connection::connect(&url, properties)
        .await
        .expect("connect");
    conn.close(200, "bye").await.expect("close");
    wait_in_file(&path, "- after-rotation, vhost: '/', user: 'guest'");
    let old = std::fs::read_to_string(&rotated).expect("rotated file");
    assert!(old.contains("started; config file"), "{old}");
    assert!(!old.contains("after-rotation"), "{old}");

    let _ = child.kill();
    let _ = child.wait();
    let _ = std::fs::remove_dir_all(&dir);
}

/// A log file that cannot be opened stops the start with a clear error
/// (exit 2), not a broker logging nowhere.
#[test]
fn an_unopenable_log_file_refuses_the_start() {
    let output = std::process::Command::new(env!("CARGO_BIN_EXE_leveret"))
        .args(["--listen", "127.0.0.1:0", "--metrics-listen", "127.0.0.1:0"])
        .args(["--mqtt-listen", "none"])
        .args(["--http-listen", "127.0.0.1:0"])
        .args(["--log-file", "/nonexistent-leveret-dir/leveret.log"])
        .output()
        .expect("run leveret");
    assert_eq!(output.status.code(), Some(2), "{output:?}");
    let error = String::from_utf8_lossy(&output.stderr);
    assert!(
        error.contains("cannot open the log file /nonexistent-leveret-dir/leveret.log"),
        "{error}"
    );
}

/// On a terminal (a pseudo-terminal from util-linux's `script`) the text
/// log is coloured; with `--log-file` beside the same terminal, the file
/// gets plain text. (The pipe case is in the first test.)
#[test]
fn colours_only_on_a_terminal() {
    if !common::ops::tool_available("script", "bsdutils (util-linux's script)") {
        return;
    }
    let dir = std::env::temp_dir().join(format!("leveret-log-tty-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).expect("dir");
    let run_on_a_terminal = |name: &str, extra: &str| -> String {
        let pid_file = dir.join(format!("{name}.pid"));
        let command = format!(
            "echo $$ > '{}'; exec '{}' --listen 127.0.0.1:0 --metrics-listen 127.0.0.1:0 \
             --http-listen 127.0.0.1:0 --mqtt-listen none --data-dir '{}' --log info {extra}",
            pid_file.display(),
            env!("CARGO_BIN_EXE_leveret"),
            dir.join(name).display(),
        );
        let mut script = std::process::Command::new("script")
            .args(["-qefc", &command, "/dev/null"])
            .stdin(std::process::Stdio::piped())
            .stdout(std::process::Stdio::piped())
            .stderr(std::process::Stdio::null())
            .spawn()
            .expect("script");
        let stdout = script.stdout.take().expect("stdout");
        let (said, hear) = std::sync::mpsc::channel();
        std::thread::spawn(move || {
            use std::io::BufRead;
            for line in std::io::BufReader::new(stdout)
                .lines()
                .map_while(Result::ok)
            {
                let _ = said.send(line);
            }
        });
        // Until the banner is on the terminal or in the log file.
        let banner = "started; config file";
        let log_file = dir.join("leveret.log");
        let deadline = std::time::Instant::now() + Duration::from_secs(20);
        let mut output = Vec::new();
        while !output.iter().any(|line: &String| line.contains(banner))
            && !std::fs::read_to_string(&log_file).is_ok_and(|log| log.contains(banner))
            && std::time::Instant::now() < deadline
        {
            if let Ok(line) = hear.recv_timeout(Duration::from_millis(100)) {
                output.push(line);
            }
        }
        // Stop leveret (by the pid its shell wrote before exec) cleanly.
        let pid = std::fs::read_to_string(&pid_file).expect("pid file");
        let killed = std::process::Command::new("kill")
            .args(["-TERM", pid.trim()])
            .status()
            .expect("kill");
        assert!(killed.success());
        let _ = script.wait();
        output.join("\n")
    };

    let coloured = run_on_a_terminal("tty", "");
    assert!(coloured.contains("started; config file"), "{coloured}");
    assert!(
        coloured.contains("\u{1b}["),
        "ANSI colours on a terminal:\n{coloured}"
    );

    let file = dir.join("leveret.log");
    let to_file = run_on_a_terminal("file", &format!("--log-file '{}'", file.display()));
    assert!(
        !to_file.contains("started; config file"),
        "the log went to the file: {to_file}"
    );
    let logged = std::fs::read_to_string(&file).expect("the log file");
    assert!(logged.contains("started; config file"), "{logged}");
    assert!(!logged.contains('\u{1b}'), "no colour in a file:\n{logged}");
    let _ = std::fs::remove_dir_all(&dir);
}
