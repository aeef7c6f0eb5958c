//! The `active` state of consumers as the management API and leveretctl
//! list them (`/api/consumers`, `list_consumers ... active
//! activity_status`), read from the state the queue delivers by: on a
//! queue with `x-single-active-consumer` one consumer is `single_active`,
//! the others `waiting`, and the listing follows a hand-over, as
//! rabbitmqctl 3.10 shows it.

mod common;

use common::ops::OpsBroker;
use lapin::options::{BasicCancelOptions, BasicConsumeOptions, QueueDeclareOptions};
use lapin::types::{AMQPValue, FieldTable};
use lapin::{Connection, ConnectionProperties};
use std::process::Command;
use std::time::Duration;

fn consumers(broker: &OpsBroker) -> Vec<String> {
    let output = Command::new(env!("CARGO_BIN_EXE_leveretctl"))
        .arg("--url")
        .arg(format!("http://{}", broker.http))
        .args([
            "-q",
            "--no-table-headers",
            "list_consumers",
            "queue_name",
            "consumer_tag",
            "active",
            "activity_status",
        ])
        .output()
        .expect("run leveretctl");
    assert!(output.status.success(), "{output:?}");
    let mut lines: Vec<String> = String::from_utf8_lossy(&output.stdout)
        .lines()
        .map(str::to_owned)
        .collect();
    lines.sort();
    lines
}

/// Polls the listing until it is `expected` (the API reads the broker as
/// it is; a hand-over is over when basic.cancel-ok is back, so this takes
/// one read in practice), at most ten seconds.
async fn listing_becomes(broker: &OpsBroker, expected: &[&str]) {
    let deadline = tokio::time::Instant::now() + Duration::from_secs(10);
    loop {
        let listed = consumers(broker);
        if listed == expected {
            return;
        }
        assert!(
            tokio::time::Instant::now() < deadline,
            "listed {listed:?}, expected {expected:?}"
        );
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn single_active_consumers_are_listed_active_and_waiting() {
    let broker = OpsBroker::start("consumer-activity", &[]);
    let conn = Connection::connect(&broker.amqp_url(), ConnectionProperties::default())
        .await
        .expect("connect");
    let ch = conn.create_channel().await.expect("channel");
    let mut sac = FieldTable::default();
    sac.insert("x-single-active-consumer".into(), AMQPValue::Boolean(true));
    ch.queue_declare("orders", QueueDeclareOptions::default(), sac)
        .await
        .expect("declare");
    ch.queue_declare(
        "plain",
        QueueDeclareOptions::default(),
        FieldTable::default(),
    )
    .await
    .expect("declare");
    let mut kept = Vec::new();
    for (queue, tag) in [("orders", "first"), ("orders", "second"), ("plain", "any")] {
        kept.push(
            ch.basic_consume(
                queue,
                tag,
                BasicConsumeOptions::default(),
                FieldTable::default(),
            )
            .await
            .expect("consume"),
        );
    }
    listing_becomes(
        &broker,
        &[
            "orders\tfirst\ttrue\tsingle_active",
            "orders\tsecond\tfalse\twaiting",
            "plain\tany\ttrue\tup",
        ],
    )
    .await;
    ch.basic_cancel("first", BasicCancelOptions::default())
        .await
        .expect("cancel");
    listing_becomes(
        &broker,
        &[
            "orders\tsecond\ttrue\tsingle_active",
            "plain\tany\ttrue\tup",
        ],
    )
    .await;
}
