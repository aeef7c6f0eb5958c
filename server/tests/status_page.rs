//! The status page (`/` on the management listener) in a real headless
//! browser: Debian's chromium driven by Playwright for Node (npm;
//! `.ci/run` installs it with `npm ci` in `server/tests/browser`, whose
//! `status_page.mjs` is the browser's half of this test). After some
//! traffic, the page at 1280x900 shows the headroom bars, the rate and
//! queued-message charts and the listeners with the figures the JSON API
//! gives, links to that JSON, follows a queue by itself, and its
//! screenshot is kept in `target/tmp/status-page.png`. Skips with a
//! message only if chromium, node or Playwright is missing (outside CI;
//! under CI that fails).

mod common;

use common::ops::{basic, missing, request, tool_available, OpsBroker};
use futures_lite::StreamExt;
use lapin::options::{
    BasicAckOptions, BasicConsumeOptions, BasicPublishOptions, QueueDeclareOptions,
};
use lapin::types::FieldTable;
use lapin::{BasicProperties, Channel, Connection, ConnectionProperties};
use serde_json::Value;
use std::io::{BufRead, BufReader, Write};
use std::path::PathBuf;
use std::process::{Command, Stdio};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::Duration;

/// What the page asks for its charts.
const HISTORY: &str =
    "/api/overview?msg_rates_age=600&msg_rates_incr=5&lengths_age=600&lengths_incr=5";

/// `server/tests/browser`, where `npm ci` puts Playwright; `None` (after
/// the skip message, or a failure under CI) if node or Playwright is
/// missing.
fn playwright_dir() -> Option<PathBuf> {
    if !tool_available("node", "nodejs") {
        return None;
    }
    let dir = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("tests/browser");
    if dir.join("node_modules/playwright/package.json").exists() {
        return Some(dir);
    }
    missing(
        "Playwright for Node",
        "it with `npm ci` in server/tests/browser",
    );
    None
}

async fn publish(ch: &Channel, queue: &str, count: usize) {
    for _ in 0..count {
        ch.basic_publish(
            "",
            queue,
            BasicPublishOptions::default(),
            b"m",
            BasicProperties::default(),
        )
        .await
        .expect("publish");
    }
}

async fn get_json(broker: &OpsBroker, path: &str) -> Value {
    let auth = basic("guest", "guest");
    let response = request(broker.http, "GET", path, &[("Authorization", &auth)], b"").await;
    assert_eq!(response.status, 200, "{path}: {}", response.text());
    serde_json::from_slice(&response.body).unwrap_or_else(|e| panic!("{path}: {e}"))
}

/// The samples of `details` (`*_details` with `samples`), newest first, as
/// (timestamp, value).
fn samples(details: &Value) -> Vec<(u64, f64)> {
    details["samples"]
        .as_array()
        .expect("samples")
        .iter()
        .map(|s| {
            (
                s["timestamp"].as_u64().expect("timestamp"),
                s["sample"].as_f64().expect("sample"),
            )
        })
        .collect()
}

fn number(text: &Value) -> f64 {
    text.as_str()
        .and_then(|t| t.parse().ok())
        .unwrap_or_else(|| panic!("not a number: {text}"))
}

/// A queue `worked` that a consumer drains and acknowledges while this
/// publishes a few messages to it every 200 ms, until `stop`.
async fn steady_traffic(conn: &Connection, stop: Arc<AtomicBool>) -> tokio::task::JoinHandle<()> {
    let ch = conn.create_channel().await.expect("channel");
    ch.queue_declare(
        "worked",
        QueueDeclareOptions::default(),
        FieldTable::default(),
    )
    .await
    .expect("declare worked");
    let mut consumer = ch
        .basic_consume(
            "worked",
            "worker",
            BasicConsumeOptions::default(),
            FieldTable::default(),
        )
        .await
        .expect("consume");
    tokio::spawn(async move {
        // Until the broker goes away at the end of the test.
        while let Some(Ok(delivery)) = consumer.next().await {
            if delivery.ack(BasicAckOptions::default()).await.is_err() {
                return;
            }
        }
    });
    tokio::spawn(async move {
        while !stop.load(Ordering::Relaxed) {
            publish(&ch, "worked", 3).await;
            tokio::time::sleep(Duration::from_millis(200)).await;
        }
    })
}

/// Waits until the broker's history shows publishes in at least two steps.
async fn wait_for_history(broker: &OpsBroker) {
    for _ in 0..60 {
        let overview = get_json(broker, HISTORY).await;
        let publish = samples(&overview["message_stats"]["publish_details"]);
        if publish.len() >= 3 && publish[0].1 > publish[publish.len() - 1].1 {
            return;
        }
        tokio::time::sleep(Duration::from_millis(500)).await;
    }
    panic!("the broker's history never showed the publishes");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_status_page_shows_headroom_charts_listeners_and_follows_queues() {
    if !tool_available("chromium", "chromium") {
        return;
    }
    let Some(browser_dir) = playwright_dir() else {
        return;
    };
    let broker = OpsBroker::start("status-page", &[]);
    let anonymous = request(broker.http, "GET", "/", &[], b"").await;
    assert_eq!(anonymous.status, 401, "the page needs a login too");

    let conn = Connection::connect(&broker.amqp_url(), ConnectionProperties::default())
        .await
        .expect("connect");
    let stop = Arc::new(AtomicBool::new(false));
    let traffic = steady_traffic(&conn, Arc::clone(&stop)).await;
    let ch = conn.create_channel().await.expect("channel");
    ch.queue_declare(
        "dashboard",
        QueueDeclareOptions::default(),
        FieldTable::default(),
    )
    .await
    .expect("declare");
    publish(&ch, "dashboard", 7).await;
    wait_for_history(&broker).await;

    let chromium = String::from_utf8(
        Command::new("sh")
            .args(["-c", "command -v chromium"])
            .output()
            .expect("sh")
            .stdout,
    )
    .expect("path");
    let screenshot = PathBuf::from(env!("CARGO_TARGET_TMPDIR")).join("status-page.png");
    let _ = std::fs::remove_file(&screenshot);
    let url = format!("http://{}/", broker.http);
    let mut driver = Command::new("node")
        .arg(browser_dir.join("status_page.mjs"))
        .args([url.as_str(), chromium.trim()])
        .arg(&screenshot)
        .current_dir(&browser_dir)
        .stdin(Stdio::piped())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("start the Playwright driver");
    let mut told = driver.stdin.take().expect("stdin");
    let (said, hear) = std::sync::mpsc::channel();
    let stdout = driver.stdout.take().expect("stdout");
    std::thread::spawn(move || {
        for line in BufReader::new(stdout).lines().map_while(Result::ok) {
            let _ = said.send(line);
        }
    });
    let stderr = driver.stderr.take().expect("stderr");
    let complaints = Arc::new(std::sync::Mutex::new(String::new()));
    let heard = Arc::clone(&complaints);
    std::thread::spawn(move || {
        for line in BufReader::new(stderr).lines().map_while(Result::ok) {
            let mut heard = heard.lock().unwrap_or_else(|e| e.into_inner());
            heard.push_str(&line);
            heard.push('\n');
        }
    });
    let next_line = || {
        hear.recv_timeout(Duration::from_secs(90))
            .unwrap_or_else(|_| {
                std::thread::sleep(Duration::from_millis(500));
                panic!(
                    "the browser said nothing more; its standard error:\n{}",
                    complaints.lock().unwrap_or_else(|e| e.into_inner())
                )
            })
    };
    let line = tokio::task::block_in_place(next_line);
    let dom: Value = serde_json::from_str(line.strip_prefix("dom ").expect(&line)).expect("json");
    let overview = get_json(&broker, HISTORY).await;
    let node = get_json(&broker, "/api/nodes").await[0].clone();

    assert_eq!(dom["size"], serde_json::json!([1280, 900]));
    assert_eq!(dom["alarms"], serde_json::json!(["ok", "no alarms"]));
    assert_eq!(dom["connections"], "1");
    assert_eq!(dom["sparklines"], 2, "dashboard and worked: {dom}");

    // The listeners: every one the API lists, as it lists them, among
    // them this broker's AMQP port and the page's own.
    let listed: Vec<Value> = overview["listeners"]
        .as_array()
        .expect("listeners")
        .iter()
        .map(|l| serde_json::json!([l["protocol"], l["ip_address"], l["port"].to_string()]))
        .collect();
    assert_eq!(dom["listeners"], Value::Array(listed), "{dom}");
    for (protocol, port) in [("amqp", broker.amqp.port()), ("http", broker.http.port())] {
        assert!(
            dom["listeners"]
                .as_array()
                .expect("rows")
                .iter()
                .any(|row| row[0] == protocol && row[2] == port.to_string().as_str()),
            "{protocol} {port}: {dom}"
        );
    }

    // The headroom bars: exactly the figures of one of the API's answers
    // to the page (the figures move by themselves between answers), and
    // the limits the alarms act on, as the API gives them now.
    let bars = &dom["headroom"];
    let shown = |bar: &str, key: &str| number(&bars[bar][key]);
    let answered = dom["nodes_answered"].as_array().expect("answers");
    assert!(
        answered.iter().any(|answer| {
            let figure = |key: &str| answer[key].as_f64().expect(key);
            [
                ("memory", "used", "mem_used"),
                ("memory", "limit", "mem_limit"),
                ("disk", "used", "disk_free"),
                ("disk", "limit", "disk_free_limit"),
                ("fds", "used", "fd_used"),
                ("fds", "limit", "fd_total"),
            ]
            .iter()
            .all(|(bar, key, field)| shown(bar, key) == figure(field))
        }),
        "{bars} is none of {answered:?}"
    );
    for (bar, field) in [
        ("memory", "mem_limit"),
        ("disk", "disk_free_limit"),
        ("fds", "fd_total"),
    ] {
        assert_eq!(
            shown(bar, "limit"),
            node[field].as_f64().expect(field),
            "{bar}"
        );
    }
    let (memory, free, fds) = (
        shown("memory", "used"),
        shown("disk", "used"),
        shown("fds", "used"),
    );
    let width = |bar: &Value| -> f64 {
        bar["width"]
            .as_str()
            .and_then(|w| w.strip_suffix('%'))
            .expect("width")
            .parse()
            .expect("%")
    };
    for (bar, share) in [
        (&bars["memory"], memory / number(&bars["memory"]["limit"])),
        (&bars["disk"], number(&bars["disk"]["limit"]) / free),
        (&bars["fds"], fds / number(&bars["fds"]["limit"])),
    ] {
        assert!(
            (width(bar) - 100.0 * share.min(1.0)).abs() < 0.1,
            "{bar} {share}"
        );
    }
    assert!(
        bars["fds"]["text"].as_str().expect("text").contains(" of "),
        "{bars}"
    );

    // The charts: the newest point of each line is the API's figure at that
    // moment (rates: the change since the step before, per second), and
    // the publishes drawn are the traffic's.
    let stats = &overview["message_stats"];
    for field in ["publish", "deliver_get", "ack"] {
        let line = &dom["rates"][field];
        assert!(
            line["count"].as_u64().expect("count") >= 2,
            "{field}: {line}"
        );
        assert_eq!(line["points"], line["count"], "{line}");
        let newest: u64 = line["newest"]
            .as_str()
            .expect("newest")
            .parse()
            .expect("ms");
        let history = samples(&stats[format!("{field}_details")]);
        let at = history
            .iter()
            .position(|(t, _)| *t == newest)
            .expect("that sample");
        let ((t1, v1), (t0, v0)) = (history[at], history[at + 1]);
        let rate = (v1 - v0) / ((t1 - t0) as f64 / 1000.0);
        assert!(
            (number(&line["value"]) - rate).abs() < 1e-9,
            "{field}: {line} {history:?}"
        );
    }
    let published = samples(&stats["publish_details"]);
    assert!(
        published[0].1 > published[published.len() - 1].1,
        "{published:?}"
    );
    let totals = &overview["queue_totals"];
    for field in ["messages_ready", "messages_unacknowledged"] {
        let line = &dom["lengths"][field];
        assert!(
            line["count"].as_u64().expect("count") >= 2,
            "{field}: {line}"
        );
        let newest: u64 = line["newest"]
            .as_str()
            .expect("newest")
            .parse()
            .expect("ms");
        let history = samples(&totals[format!("{field}_details")]);
        let value = history
            .iter()
            .find(|(t, _)| *t == newest)
            .expect("that sample")
            .1;
        assert_eq!(number(&line["value"]), value, "{field}: {line}");
    }
    assert!(dom["axis_labels"]
        .as_array()
        .expect("labels")
        .contains(&"now".into()));
    assert!(dom["axis_labels"]
        .as_array()
        .expect("labels")
        .contains(&"−10 min".into()));

    // Every figure links to its JSON, and every link answers JSON.
    let links: Vec<String> = dom["links"]
        .as_array()
        .expect("links")
        .iter()
        .map(|l| l.as_str().expect("href").to_owned())
        .collect();
    for wanted in [
        "/api/nodes/",
        "msg_rates_age=600",
        "lengths_age=600",
        "/api/overview",
        "/api/queues",
        "/api/connections",
        "/api/health/checks/alarms",
    ] {
        assert!(
            links.iter().any(|l| l.contains(wanted)),
            "{wanted}: {links:?}"
        );
    }
    for link in &links {
        get_json(&broker, link).await;
    }

    let line = tokio::task::block_in_place(next_line);
    assert_eq!(line, format!("screenshot {}", screenshot.display()));
    let png = std::fs::read(&screenshot).expect("the screenshot");
    assert_eq!(&png[..8], b"\x89PNG\r\n\x1a\n");
    assert_eq!(
        (
            u32::from_be_bytes(png[16..20].try_into().expect("width")),
            u32::from_be_bytes(png[20..24].try_into().expect("height"))
        ),
        (1280, 900)
    );
    eprintln!("status page screenshot: {}", screenshot.display());

    stop.store(true, Ordering::Relaxed);
    traffic.await.expect("traffic");
    publish(&ch, "dashboard", 5).await;
    writeln!(told, "next").expect("tell the browser");
    assert_eq!(
        tokio::task::block_in_place(next_line),
        "ready 12",
        "the page follows by itself"
    );
    let status = driver.wait().expect("the driver ends");
    assert!(status.success(), "{status:?}");
}

/// The overview's history as the API gives it: RabbitMQ's `samples` only
/// when asked, a query that does not parse refused with 400, and any
/// window bounded by the ten minutes kept.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_overview_gives_its_bounded_history_only_when_asked() {
    let broker = OpsBroker::start("overview-history", &[]);
    let plain = get_json(&broker, "/api/overview").await;
    assert!(plain["message_stats"]["publish_details"]["samples"].is_null());
    assert!(plain["queue_totals"]["messages_details"]["samples"].is_null());

    let asked = get_json(&broker, "/api/overview?msg_rates_age=60&msg_rates_incr=5").await;
    let details = &asked["message_stats"]["publish_details"];
    assert!(details["samples"].is_array(), "{details}");
    assert!(
        details["avg_rate"].is_number() && details["avg"].is_number(),
        "{details}"
    );
    assert!(
        asked["queue_totals"]["messages_details"]["samples"].is_null(),
        "lengths only with lengths_age"
    );

    let widest = format!(
        "/api/overview?lengths_age={}&lengths_incr=1&msg_rates_age={}&msg_rates_incr=1",
        u64::MAX,
        u64::MAX
    );
    let widest = get_json(&broker, &widest).await;
    for details in [
        &widest["queue_totals"]["messages_ready_details"],
        &widest["message_stats"]["ack_details"],
    ] {
        let count = details["samples"].as_array().expect("samples").len();
        assert!((1..=121).contains(&count), "{details}");
    }

    let auth = basic("guest", "guest");
    for bad in [
        "msg_rates_age=60",
        "msg_rates_incr=5",
        "lengths_age=60&lengths_incr=0",
        "lengths_age=-1&lengths_incr=5",
        "msg_rates_age=ten&msg_rates_incr=5",
    ] {
        let path = format!("/api/overview?{bad}");
        let response = request(broker.http, "GET", &path, &[("Authorization", &auth)], b"").await;
        assert_eq!(response.status, 400, "{bad}: {}", response.text());
        assert!(
            response.text().contains("bad_request"),
            "{}",
            response.text()
        );
    }
}
