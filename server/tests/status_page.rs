//! The status page (`/` on the management listener) in a real headless
//! browser: Debian's chromium driven by Playwright (from pip; `.ci/run`
//! installs it and names its Python in `LEVERET_PLAYWRIGHT_PYTHON`). The
//! page renders behind basic auth, shows a queue a client declared, and
//! its numbers move by themselves as messages flow, in the one page left
//! open. Skips with a message only if chromium or Playwright is missing
//! (outside CI).

mod common;

use common::ops::{missing, request, tool_available, OpsBroker};
use lapin::options::{BasicPublishOptions, QueueDeclareOptions};
use lapin::types::FieldTable;
use lapin::{BasicProperties, Channel, Connection, ConnectionProperties};
use std::io::{BufRead, BufReader, Write};
use std::process::{Command, Stdio};

/// What the browser does, told step by step on standard input: open the
/// page with guest's credentials and wait until `dashboard` shows 7 ready
/// (then report the alarms, the connection count and the sparklines), and
/// on `next`, wait in the same page until it shows 12.
const DRIVER: &str = r##"
import sys
from playwright.sync_api import sync_playwright

url, chromium = sys.argv[1], sys.argv[2]
cell = 'tr[data-queue="dashboard"] [data-field="ready"]'

def wait_for_ready(page, value):
    page.wait_for_function(
        "([sel, v]) => { const c = document.querySelector(sel); return c && c.textContent === v; }",
        arg=[cell, value], timeout=20000)

with sync_playwright() as p:
    browser = p.chromium.launch(executable_path=chromium, args=["--no-sandbox", "--disable-gpu"])
    context = browser.new_context(http_credentials={"username": "guest", "password": "guest"})
    page = context.new_page()
    page.goto(url)
    wait_for_ready(page, "7")
    page.wait_for_function("document.getElementById('alarms').className !== 'muted'", timeout=20000)
    print("alarms", page.get_attribute("#alarms", "class"), page.text_content("#alarms"), flush=True)
    print("connections", page.text_content("#t-connections"), flush=True)
    print("sparklines", page.locator("svg.spark").count(), flush=True)
    print("ready 7", flush=True)
    sys.stdin.readline()
    wait_for_ready(page, "12")
    print("ready 12", flush=True)
    browser.close()
"##;

/// The Python that has Playwright: `LEVERET_PLAYWRIGHT_PYTHON`, else
/// `python3` if it can import it; `None` (after the skip message, or a
/// failure under CI) if neither.
fn playwright_python() -> Option<String> {
    let candidate = std::env::var("LEVERET_PLAYWRIGHT_PYTHON").unwrap_or_else(|_| "python3".into());
    let found = Command::new(&candidate)
        .args(["-c", "import playwright.sync_api"])
        .stderr(Stdio::null())
        .status()
        .is_ok_and(|s| s.success());
    if found {
        return Some(candidate);
    }
    missing(
        "Playwright for Python",
        "Playwright from pip, in target/ops-venv",
    );
    None
}

async fn publish(ch: &Channel, count: usize) {
    for _ in 0..count {
        ch.basic_publish(
            "",
            "dashboard",
            BasicPublishOptions::default(),
            b"m",
            BasicProperties::default(),
        )
        .await
        .expect("publish");
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_status_page_shows_queues_and_follows_them() {
    if !tool_available("chromium", "chromium") {
        return;
    }
    let Some(python) = playwright_python() else {
        return;
    };
    let broker = OpsBroker::start("status-page", &[]);
    let anonymous = request(broker.http, "GET", "/", &[], b"").await;
    assert_eq!(anonymous.status, 401, "the page needs a login too");

    let conn = Connection::connect(&broker.amqp_url(), ConnectionProperties::default())
        .await
        .expect("connect");
    let ch = conn.create_channel().await.expect("channel");
    ch.queue_declare(
        "dashboard",
        QueueDeclareOptions::default(),
        FieldTable::default(),
    )
    .await
    .expect("declare");
    publish(&ch, 7).await;
    ch.queue_declare(
        "dashboard",
        QueueDeclareOptions {
            passive: true,
            ..Default::default()
        },
        FieldTable::default(),
    )
    .await
    .expect("the publishes arrived");

    let chromium = String::from_utf8(
        Command::new("sh")
            .args(["-c", "command -v chromium"])
            .output()
            .expect("sh")
            .stdout,
    )
    .expect("path");
    let url = format!("http://{}/", broker.http);
    let mut driver = Command::new(&python)
        .args(["-c", DRIVER, &url, chromium.trim()])
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
    let next_line = || {
        hear.recv_timeout(std::time::Duration::from_secs(60))
            .unwrap_or_else(|_| panic!("the browser said nothing more"))
    };
    let mut seen = Vec::new();
    while seen.last().map(String::as_str) != Some("ready 7") {
        seen.push(tokio::task::block_in_place(next_line));
    }
    assert_eq!(
        seen[..3],
        ["alarms ok no alarms", "connections 1", "sparklines 1"],
        "{seen:?}"
    );

    publish(&ch, 5).await;
    writeln!(told, "next").expect("tell the browser");
    assert_eq!(
        tokio::task::block_in_place(next_line),
        "ready 12",
        "the page follows by itself"
    );
    let output = driver.wait_with_output().expect("the driver ends");
    assert!(output.status.success(), "{output:?}");
}
