//! The limits and alarms an operator reads mean what they say: the
//! memory limit of `/api/nodes`, `rabbitmq_resident_memory_limit_bytes`
//! and `leveretctl status` is the resident-memory watermark the broker
//! blocks publishers at (RabbitMQ's `vm_memory_high_watermark`), the
//! queued-bytes limit has its own name, and `leveretctl status` lists the
//! alarm the broker is acting on.

mod common;

use common::ops::{basic, request, OpsBroker};
use serde_json::Value;
use std::process::Command;

/// `leveretctl status` against `broker`; its standard output.
fn status(broker: &OpsBroker) -> String {
    let output = Command::new(env!("CARGO_BIN_EXE_leveretctl"))
        .arg("--url")
        .arg(format!("http://{}", broker.http))
        .arg("status")
        .output()
        .expect("run leveretctl");
    assert!(output.status.success(), "{output:?}");
    String::from_utf8_lossy(&output.stdout).into_owned()
}

async fn node(broker: &OpsBroker) -> Value {
    let guest = basic("guest", "guest");
    let auth = [("Authorization", guest.as_str())];
    let nodes = request(broker.http, "GET", "/api/nodes", &auth, b"").await;
    assert_eq!(nodes.status, 200, "{}", nodes.text());
    let nodes: Value = serde_json::from_slice(&nodes.body).expect("json");
    nodes[0].clone()
}

async fn metrics(broker: &OpsBroker) -> String {
    request(broker.metrics, "GET", "/metrics", &[], b"")
        .await
        .text()
}

/// The section of a status report that starts at `title`.
fn section<'a>(report: &'a str, title: &str) -> &'a str {
    let start = report
        .find(&format!("\n{title}\n"))
        .unwrap_or_else(|| panic!("no {title} in {report}"));
    let rest = report[start + title.len() + 2..].trim_start_matches('\n');
    let end = rest.find("\n\n").unwrap_or(rest.len());
    &rest[..end]
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_disk_alarm_is_listed_by_leveretctl_status_and_the_api() {
    let broker = OpsBroker::start("status-disk", &["--disk-free-limit", "1000000000000000000"]);
    let figures = node(&broker).await;
    assert_eq!(figures["disk_free_alarm"], true, "{figures}");
    let report = status(&broker);
    let alarms = section(&report, "Alarms");
    let name = figures["name"].as_str().expect("node name");
    assert!(
        alarms.contains(&format!("Free disk space alarm on node {name}")),
        "{report}"
    );
    assert!(!alarms.contains("(none)"), "{report}");
    assert!(
        report.contains("Limit (bytes): 1000000000000000000"),
        "{report}"
    );

    let calm = OpsBroker::start("status-calm", &[]);
    let report = status(&calm);
    assert!(section(&report, "Alarms").contains("(none)"), "{report}");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn memory_limits_shown_are_the_configured_watermarks() {
    let dir = std::env::temp_dir().join(format!("leveret-status-mem-{}", std::process::id()));
    std::fs::create_dir_all(&dir).expect("dir");
    let config = dir.join("leveret.toml");
    std::fs::write(
        &config,
        "vm-memory-high-watermark-absolute = 3000000000\nmemory-high-watermark = 98765432\n",
    )
    .expect("write");
    let config = config.to_str().expect("utf-8").to_owned();
    let broker = OpsBroker::start("status-mem", &["--config", &config]);
    let figures = node(&broker).await;
    assert_eq!(figures["mem_limit"], 3_000_000_000u64, "{figures}");
    assert_eq!(figures["queued_bytes_limit"], 98_765_432u64, "{figures}");
    let scrape = metrics(&broker).await;
    assert!(
        scrape.contains("\nrabbitmq_resident_memory_limit_bytes 3000000000\n"),
        "{scrape}"
    );
    assert!(
        scrape.contains("\nleveret_queued_bytes_limit_bytes 98765432\n"),
        "{scrape}"
    );
    let report = status(&broker);
    assert!(
        report.contains("Memory high watermark (bytes): 3000000000"),
        "{report}"
    );
    assert!(
        report.contains("Queued message bytes limit: 98765432"),
        "{report}"
    );
    drop(broker);
    let _ = std::fs::remove_dir_all(&dir);

    // The default: 0.4 of the machine's memory, as RabbitMQ's.
    let Some(total) = std::fs::read_to_string("/proc/meminfo")
        .ok()
        .and_then(|meminfo| {
            let line = meminfo.lines().find(|l| l.starts_with("MemTotal:"))?;
            line.split_whitespace().nth(1)?.parse::<u64>().ok()
        })
    else {
        return;
    };
    let broker = OpsBroker::start("status-mem-default", &[]);
    let expected = (total as f64 * 1024.0 * 0.4) as u64;
    assert_eq!(node(&broker).await["mem_limit"], expected);
    assert!(metrics(&broker).await.contains(&format!(
        "\nrabbitmq_resident_memory_limit_bytes {expected}\n"
    )));
}
