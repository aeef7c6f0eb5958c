//! `leveretctl` against a running `leveret`: rabbitmqctl's commands,
//! columns and tab-separated output, and its exit statuses (64 for a bad
//! command line, 69 when the API is unreachable, 1 when the broker
//! refuses).

mod common;

use common::ops::OpsBroker;
use lapin::options::{BasicConsumeOptions, BasicPublishOptions, QueueDeclareOptions};
use lapin::types::FieldTable;
use lapin::{BasicProperties, Connection, ConnectionProperties};
use std::process::{Command, Output};
use std::time::Duration;

fn ctl(broker: &OpsBroker, args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_leveretctl"))
        .arg("--url")
        .arg(format!("http://{}", broker.http))
        .args(args)
        .output()
        .expect("run leveretctl")
}

/// Runs a command that must succeed; its standard output's lines.
fn lines(broker: &OpsBroker, args: &[&str]) -> Vec<String> {
    let output = ctl(broker, args);
    assert!(output.status.success(), "{args:?}: {output:?}");
    String::from_utf8_lossy(&output.stdout)
        .lines()
        .map(str::to_owned)
        .collect()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn rabbitmqctl_style_commands_work_against_leveret() {
    let broker = OpsBroker::start("ctl", &[]);
    let conn = Connection::connect(&broker.amqp_url(), ConnectionProperties::default())
        .await
        .expect("connect");
    let ch = conn.create_channel().await.expect("channel");
    for queue in ["jobs", "idle"] {
        ch.queue_declare(queue, QueueDeclareOptions::default(), FieldTable::default())
            .await
            .expect("declare");
    }
    for _ in 0..3 {
        ch.basic_publish(
            "",
            "jobs",
            BasicPublishOptions::default(),
            b"job",
            BasicProperties::default(),
        )
        .await
        .expect("publish");
    }
    let _consumer = ch
        .basic_consume(
            "idle",
            "worker-1",
            BasicConsumeOptions::default(),
            FieldTable::default(),
        )
        .await
        .expect("consume");

    let deadline = tokio::time::Instant::now() + Duration::from_secs(10);
    let queues = loop {
        let queues = lines(
            &broker,
            &["list_queues", "name", "messages_ready", "consumers"],
        );
        if queues.iter().any(|l| l == "jobs\t3\t0") || tokio::time::Instant::now() > deadline {
            break queues;
        }
        tokio::time::sleep(Duration::from_millis(20)).await;
    };
    assert_eq!(
        queues,
        [
            "Listing queues for vhost / ...",
            "name\tmessages_ready\tconsumers",
            "idle\t0\t1",
            "jobs\t3\t0"
        ]
    );
    let quiet = lines(&broker, &["-q", "--no-table-headers", "list_queues"]);
    assert_eq!(quiet, ["idle\t0", "jobs\t3"]);
    let consumers = lines(
        &broker,
        &[
            "-q",
            "list_consumers",
            "queue_name",
            "consumer_tag",
            "ack_required",
        ],
    );
    assert_eq!(
        consumers,
        [
            "queue_name\tconsumer_tag\tack_required",
            "idle\tworker-1\ttrue"
        ]
    );
    let bindings = lines(&broker, &["-q", "--no-table-headers", "list_bindings"]);
    assert_eq!(
        bindings,
        [
            "\texchange\tidle\tqueue\tidle\t[]",
            "\texchange\tjobs\tqueue\tjobs\t[]"
        ]
    );
    let exchanges = lines(
        &broker,
        &["-q", "list_exchanges", "name", "type", "durable"],
    );
    assert!(
        exchanges.contains(&"amq.topic\ttopic\ttrue".to_owned()),
        "{exchanges:?}"
    );
    let status = lines(&broker, &["status"]).join("\n");
    assert!(
        status.contains("queues: 2") && status.contains("messages: 3 (3 ready"),
        "{status}"
    );

    lines(&broker, &["purge_queue", "jobs"]);
    assert_eq!(
        lines(&broker, &["-q", "--no-table-headers", "list_queues"]),
        ["idle\t0", "jobs\t0"]
    );
    let refused = ctl(&broker, &["delete_queue", "idle", "--if-unused"]);
    assert_eq!(refused.status.code(), Some(1), "{refused:?}");
    assert!(String::from_utf8_lossy(&refused.stderr).contains("in use"));

    let connections = lines(
        &broker,
        &[
            "-q",
            "--no-table-headers",
            "list_connections",
            "name",
            "user",
        ],
    );
    assert_eq!(connections.len(), 1);
    let (name, user) = connections[0].split_once('\t').expect("two columns");
    assert_eq!(user, "guest");
    lines(&broker, &["close_connection", name, "maintenance"]);
    let deadline = tokio::time::Instant::now() + Duration::from_secs(10);
    while conn.status().connected() {
        assert!(tokio::time::Instant::now() < deadline, "still connected");
        tokio::time::sleep(Duration::from_millis(10)).await;
    }

    let exported = ctl(&broker, &["export_definitions", "-"]);
    assert!(exported.status.success());
    let definitions: serde_json::Value = serde_json::from_slice(&exported.stdout).expect("JSON");
    assert_eq!(definitions["queues"].as_array().unwrap().len(), 2);
    lines(&broker, &["delete_queue", "jobs"]);
    let dir = std::env::temp_dir().join(format!("leveretctl-{}", std::process::id()));
    std::fs::create_dir_all(&dir).expect("dir");
    let file = dir.join("definitions.json");
    std::fs::write(&file, &exported.stdout).expect("write");
    lines(&broker, &["import_definitions", file.to_str().unwrap()]);
    assert_eq!(
        lines(&broker, &["-q", "--no-table-headers", "list_queues"]),
        ["idle\t0", "jobs\t0"]
    );
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn exit_statuses_say_what_went_wrong() {
    let broker = OpsBroker::start("ctl-exit", &[]);
    assert_eq!(ctl(&broker, &["no_such_command"]).status.code(), Some(64));
    assert_eq!(
        ctl(&broker, &["list_queues", "pid"]).status.code(),
        Some(64)
    );
    assert_eq!(
        ctl(&broker, &["--password", "wrong", "status"])
            .status
            .code(),
        Some(1)
    );
    assert_eq!(
        ctl(&broker, &["-p", "nowhere", "list_queues"])
            .status
            .code(),
        Some(1)
    );
    let unreachable = Command::new(env!("CARGO_BIN_EXE_leveretctl"))
        .args(["--url", "http://127.0.0.1:1", "status"])
        .output()
        .expect("run leveretctl");
    assert_eq!(unreachable.status.code(), Some(69));
}

/// list_users, set_permissions, list_permissions and clear_permissions,
/// in rabbitmqctl's words, and the broker enforcing what they set.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn permissions_are_set_listed_and_cleared() {
    let broker = OpsBroker::start("ctl-permissions", &[]);
    assert_eq!(
        lines(&broker, &["-q", "list_users"]),
        ["user\ttags", "guest\t[\"administrator\"]"]
    );
    lines(
        &broker,
        &["set_permissions", "guest", "^guest\\.", ".*", ".*"],
    );
    assert_eq!(
        lines(&broker, &["-q", "--no-table-headers", "list_permissions"]),
        ["guest\t^guest\\.\t.*\t.*"]
    );
    let conn = lapin::Connection::connect(&broker.amqp_url(), Default::default())
        .await
        .expect("guest still opens /");
    let channel = conn.create_channel().await.expect("channel");
    let refused = channel
        .queue_declare("other", Default::default(), Default::default())
        .await
        .expect_err("outside ^guest\\.");
    assert!(refused.to_string().contains("ACCESS_REFUSED"), "{refused}");
    lines(&broker, &["clear_permissions", "guest"]);
    assert!(lines(&broker, &["-q", "--no-table-headers", "list_permissions"]).is_empty());
    assert!(
        lapin::Connection::connect(&broker.amqp_url(), Default::default())
            .await
            .is_err()
    );
}

/// add_user, set_user_tags, change_password and delete_user in
/// rabbitmqctl's words: the user logs in with the password set, loses the
/// old one when it changes, and is refused once deleted; adding a user
/// twice is refused with status 1.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn users_are_added_changed_and_deleted() {
    let broker = OpsBroker::start("ctl-users", &[]);
    let login = |password: &str| {
        let url = format!("amqp://robot:{password}@{}/%2f", broker.amqp);
        async move { Connection::connect(&url, ConnectionProperties::default()).await }
    };
    lines(&broker, &["add_user", "robot", "pw1"]);
    let again = ctl(&broker, &["add_user", "robot", "other"]);
    assert_eq!(again.status.code(), Some(1), "{again:?}");
    assert!(String::from_utf8_lossy(&again.stderr).contains("already exists"));
    lines(
        &broker,
        &["set_user_tags", "robot", "monitoring", "management"],
    );
    lines(&broker, &["set_permissions", "robot", ".*", ".*", ".*"]);
    assert_eq!(
        lines(&broker, &["-q", "--no-table-headers", "list_users"]),
        [
            "guest\t[\"administrator\"]",
            "robot\t[\"monitoring\",\"management\"]"
        ]
    );
    login("pw1").await.expect("the password add_user set");
    lines(&broker, &["change_password", "robot", "pw2"]);
    assert!(login("pw1").await.is_err(), "the old password is gone");
    login("pw2").await.expect("the new password");
    assert_eq!(
        lines(&broker, &["-q", "--no-table-headers", "list_users"])[1],
        "robot\t[\"monitoring\",\"management\"]",
        "change_password keeps the tags"
    );
    lines(&broker, &["delete_user", "robot"]);
    assert!(login("pw2").await.is_err(), "deleted");
    let gone = ctl(&broker, &["delete_user", "robot"]);
    assert_eq!(gone.status.code(), Some(1), "{gone:?}");
}
