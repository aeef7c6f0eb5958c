//! The status page (`/` on the management listener) in a real headless
//! browser (Debian's chromium): it renders behind basic auth, shows a
//! queue a client declared, and its numbers move as messages flow. Skips
//! with a message only if chromium is not installed.

mod common;

use common::ops::{request, tool_available, OpsBroker};
use lapin::options::{BasicPublishOptions, QueueDeclareOptions};
use lapin::types::FieldTable;
use lapin::{BasicProperties, Channel, Connection, ConnectionProperties};
use std::process::Command;

/// The page's DOM after its scripts ran a few refreshes, or `None` without chromium.
fn rendered(broker: &OpsBroker) -> Option<String> {
    let url = format!("http://guest:guest@{}/", broker.http);
    let output = match Command::new("chromium")
        .args([
            "--headless",
            "--no-sandbox",
            "--disable-gpu",
            "--virtual-time-budget=5000",
            "--dump-dom",
        ])
        .arg(&url)
        .output()
    {
        Ok(output) => output,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return None,
        Err(e) => panic!("cannot run chromium: {e}"),
    };
    assert!(output.status.success(), "{output:?}");
    Some(String::from_utf8_lossy(&output.stdout).into_owned())
}

/// The text of the ready cell of `queue`'s row.
fn ready_cell(dom: &str, queue: &str) -> Option<String> {
    let row = dom.find(&format!("<tr data-queue=\"{queue}\">"))?;
    let rest = &dom[row..];
    let cell = rest.find("data-field=\"ready\">")? + "data-field=\"ready\">".len();
    let end = rest[cell..].find('<')?;
    Some(rest[cell..cell + end].to_owned())
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

    let before = rendered(&broker).expect("chromium is installed");
    assert!(
        before.contains("id=\"alarms\" class=\"ok\">no alarms"),
        "{before}"
    );
    assert_eq!(
        ready_cell(&before, "dashboard").as_deref(),
        Some("7"),
        "{before}"
    );
    assert!(
        before.contains("<svg class=\"spark\""),
        "a sparkline per queue"
    );
    assert!(before.contains("<b id=\"t-connections\">1</b>"), "{before}");

    publish(&ch, 5).await;
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
    let after = rendered(&broker).expect("chromium ran before");
    assert_eq!(
        ready_cell(&after, "dashboard").as_deref(),
        Some("12"),
        "{after}"
    );
}
