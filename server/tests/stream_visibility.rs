//! A stream in listings and metrics (issue 33 item 2): `/api/queues`
//! gives its type, first and last offset, segment files and bytes on disk;
//! `leveretctl list_queues` prints them as columns; `/metrics/per-object`
//! has a sample of each `leveret_stream_*` family for the stream only, and
//! labels its `queue_type` `rabbit_stream_queue`. Every figure is checked
//! against the segment files on disk.

mod common;

use common::ops::{basic, promtool_check, request, tool_available, OpsBroker};
use lapin::options::{BasicPublishOptions, ConfirmSelectOptions, QueueDeclareOptions};
use lapin::types::{AMQPValue, FieldTable};
use lapin::{BasicProperties, Connection, ConnectionProperties};
use serde_json::Value;
use std::process::Command;

const MESSAGES: u64 = 60;

async fn fill(broker: &OpsBroker) {
    let conn = Connection::connect(&broker.amqp_url(), ConnectionProperties::default())
        .await
        .expect("connect");
    let channel = conn.create_channel().await.expect("channel");
    let durable = QueueDeclareOptions {
        durable: true,
        ..Default::default()
    };
    let mut args = FieldTable::default();
    args.insert(
        "x-queue-type".into(),
        AMQPValue::LongString("stream".into()),
    );
    args.insert(
        "x-stream-max-segment-size-bytes".into(),
        AMQPValue::LongInt(2_000),
    );
    channel
        .queue_declare("flight", durable, args)
        .await
        .expect("stream");
    channel
        .queue_declare("plain", durable, FieldTable::default())
        .await
        .expect("classic");
    channel
        .confirm_select(ConfirmSelectOptions::default())
        .await
        .expect("confirms");
    for n in 0..MESSAGES {
        let confirm = channel
            .basic_publish(
                "",
                "flight",
                BasicPublishOptions::default(),
                format!("{n:06}{}", ".".repeat(100)).as_bytes(),
                BasicProperties::default(),
            )
            .await
            .expect("publish");
        assert!(confirm.await.expect("confirm").is_ack());
    }
    conn.close(200, "done").await.expect("close");
}

/// The stream's segment files: how many and their bytes.
fn on_disk(dir: &std::path::Path) -> (u64, u64) {
    let root = dir.join("streams");
    let mut files = (0, 0);
    for stream in std::fs::read_dir(root).expect("streams dir") {
        for file in std::fs::read_dir(stream.unwrap().path()).unwrap() {
            let path = file.unwrap().path();
            if path.extension().is_some_and(|e| e == "seg") {
                files.0 += 1;
                files.1 += std::fs::metadata(&path).unwrap().len();
            }
        }
    }
    files
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_streams_offsets_segments_and_bytes_are_listed_and_exported_as_metrics() {
    let dir =
        std::env::temp_dir().join(format!("leveret-stream-visibility-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    let broker = OpsBroker::on_data_dir(&dir, &[] as &[&str]);
    fill(&broker).await;
    let (segments, bytes) = on_disk(&dir);
    assert!(segments >= 3, "several segments: {segments}");

    let auth = basic("guest", "guest");
    let response = request(
        broker.http,
        "GET",
        "/api/queues/%2F/flight",
        &[("Authorization", &auth)],
        b"",
    )
    .await;
    assert_eq!(response.status, 200, "{}", response.text());
    let queue: Value = serde_json::from_slice(&response.body).unwrap();
    assert_eq!(queue["type"], "stream");
    assert_eq!(queue["stream"]["first_offset"], 0);
    assert_eq!(queue["stream"]["last_offset"], MESSAGES - 1);
    assert_eq!(queue["stream"]["segments"], segments);
    assert_eq!(queue["stream"]["bytes"], bytes);
    let plain = request(
        broker.http,
        "GET",
        "/api/queues/%2F/plain",
        &[("Authorization", &auth)],
        b"",
    )
    .await;
    let plain: Value = serde_json::from_slice(&plain.body).unwrap();
    assert!(plain.get("stream").is_none(), "{plain}");

    let output = Command::new(env!("CARGO_BIN_EXE_leveretctl"))
        .arg("--url")
        .arg(format!("http://{}", broker.http))
        .args([
            "list_queues",
            "name",
            "type",
            "first_offset",
            "last_offset",
            "segments",
            "disk_bytes",
        ])
        .output()
        .expect("leveretctl");
    assert!(output.status.success(), "{output:?}");
    let text = String::from_utf8_lossy(&output.stdout);
    let row = |name: &str| -> Vec<String> {
        text.lines()
            .find(|l| l.split_whitespace().next() == Some(name))
            .unwrap_or_else(|| panic!("{name} listed: {text}"))
            .split_whitespace()
            .map(str::to_owned)
            .collect()
    };
    assert_eq!(
        row("flight"),
        [
            "flight".to_owned(),
            "stream".to_owned(),
            "0".to_owned(),
            (MESSAGES - 1).to_string(),
            segments.to_string(),
            bytes.to_string()
        ]
    );
    assert_eq!(row("plain"), ["plain", "classic"], "{text}");

    let metrics = request(broker.metrics, "GET", "/metrics/per-object", &[], b"").await;
    let metrics = metrics.text();
    for (family, value) in [
        ("leveret_stream_first_offset", 0),
        ("leveret_stream_last_offset", MESSAGES - 1),
        ("leveret_stream_segments", segments),
        ("leveret_stream_disk_bytes", bytes),
    ] {
        let sample = format!("{family}{{vhost=\"/\",queue=\"flight\"}} {value}");
        assert!(metrics.contains(&sample), "{sample} in:\n{metrics}");
        assert!(
            !metrics.contains(&format!("{family}{{vhost=\"/\",queue=\"plain\"}}")),
            "no {family} for a classic queue"
        );
    }
    assert!(metrics.contains(
        "rabbitmq_queue_info{vhost=\"/\",queue=\"flight\",queue_type=\"rabbit_stream_queue\""
    ));
    assert!(metrics.contains(
        "rabbitmq_queue_info{vhost=\"/\",queue=\"plain\",queue_type=\"rabbit_classic_queue\""
    ));
    if tool_available("promtool", "prometheus") {
        if let Some(Err(problems)) = promtool_check(&metrics) {
            panic!("promtool: {problems}");
        }
    }
    broker.terminate();
    let _ = std::fs::remove_dir_all(&dir);
}
