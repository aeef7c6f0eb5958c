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

/// `leveretctl port ...` against the AMQP listener of `broker`.
fn port_ctl(broker: &OpsBroker, args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_leveretctl"))
        .arg("--amqp-url")
        .arg(broker.amqp_url())
        .args(["-q", "port"])
        .args(args)
        .output()
        .expect("run leveretctl")
}

/// Runs `port_ctl` off the runtime's threads (the ports keep running);
/// it must succeed; its standard output's lines.
async fn port_lines(broker: &std::sync::Arc<OpsBroker>, args: &[&str]) -> Vec<String> {
    let broker = std::sync::Arc::clone(broker);
    let args: Vec<String> = args.iter().map(|arg| (*arg).to_owned()).collect();
    tokio::task::spawn_blocking(move || {
        let args: Vec<&str> = args.iter().map(String::as_str).collect();
        let output = port_ctl(&broker, &args);
        assert!(output.status.success(), "port {args:?}: {output:?}");
        String::from_utf8_lossy(&output.stdout)
            .lines()
            .map(str::to_owned)
            .collect()
    })
    .await
    .expect("leveretctl")
}

/// The value of `key=` in a `port stats` or `port echo` line.
fn field<'a>(line: &'a str, key: &str) -> Option<&'a str> {
    line.split(' ')
        .find_map(|part| part.strip_prefix(key)?.strip_prefix('='))
}

/// `port list`, `port stats` and `port echo` on ports running in this
/// process against the binary's AMQP listener: the listing's columns, the
/// counters and rates of two announcements, three values decoded as they
/// flow (the in-port still gets every one), and the exit statuses.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn port_commands_list_follow_and_echo_robot_ports() {
    use leveret_ports::{ExchangeKind, InPort, OutPort, PortProfile, Pose2D, Time, TimedPose2D};
    let broker = std::sync::Arc::new(OpsBroker::start("ctl-ports", &[]));
    let profile = PortProfile::new(&broker.amqp_url())
        .expect("URI")
        .exchange("poses", ExchangeKind::Fanout)
        .announce_interval(Some(Duration::from_millis(200)));
    let input = std::sync::Arc::new(
        InPort::<TimedPose2D>::connect(profile.clone().name("pose-in"))
            .await
            .expect("in-port"),
    );
    // The application takes every value (its latencies are measured then).
    let reader = {
        let input = std::sync::Arc::clone(&input);
        tokio::spawn(async move { while input.recv().await.is_some() {} })
    };
    let output = std::sync::Arc::new(
        OutPort::<TimedPose2D>::connect(profile.name("pose-out"))
            .await
            .expect("out-port"),
    );
    // Value n has heading n / 2: its sequence number says which it is.
    let publisher = {
        let output = std::sync::Arc::clone(&output);
        tokio::spawn(async move {
            for n in 1..=u32::MAX {
                let pose = TimedPose2D {
                    tm: Time::now(),
                    data: Pose2D {
                        heading: f64::from(n) / 2.0,
                        ..Default::default()
                    },
                };
                output.put(&pose).await;
                tokio::time::sleep(Duration::from_millis(20)).await;
            }
        })
    };

    let list = port_lines(&broker, &["list"]).await;
    assert_eq!(
        list[0],
        "name\tdirection\ttype\texchange\tkey\tqueue\tstate\taccepted\tconfirmed\treceived\tlost"
    );
    assert_eq!(list.len(), 3, "{list:?}");
    let row = |line: &str| line.split('\t').map(str::to_owned).collect::<Vec<_>>();
    let (pose_in, pose_out) = (row(&list[1]), row(&list[2]));
    let pose_type = "IDL:RTC/TimedPose2D:1.0";
    assert_eq!(
        pose_in[..7],
        [
            "pose-in",
            "in",
            pose_type,
            "poses",
            "",
            &input.queue().to_string_lossy(),
            "up"
        ]
    );
    assert_eq!((pose_in[7].as_str(), pose_in[8].as_str()), ("", ""));
    assert!(
        pose_in[9].parse::<u64>().is_ok() && pose_in[10] == "0",
        "{pose_in:?}"
    );
    assert_eq!(
        pose_out[..7],
        ["pose-out", "out", pose_type, "poses", "", "", "up"]
    );
    assert!(
        pose_out[7].parse::<u64>().expect("accepted") > 0,
        "{pose_out:?}"
    );
    // An out-port counts `lost` too (written on a link that dropped).
    assert_eq!((pose_out[9].as_str(), pose_out[10].as_str()), ("", "0"));
    let chosen = port_lines(
        &broker,
        &[
            "list",
            "--no-table-headers",
            "name",
            "resent",
            "interval_ms",
        ],
    )
    .await;
    assert_eq!(chosen, ["pose-in\t\t200", "pose-out\t0\t200"]);

    let stats = port_lines(&broker, &["stats", "pose-out", "--count", "2"]).await;
    assert_eq!(stats.len(), 2, "{stats:?}");
    assert!(
        stats
            .iter()
            .all(|l| l.starts_with("pose-out out up accepted=")),
        "{stats:?}"
    );
    assert_eq!(
        field(&stats[0], "accepted/s"),
        None,
        "no rate before a second announcement"
    );
    let rate: f64 = field(&stats[1], "accepted/s")
        .expect("a rate between announcements")
        .parse()
        .expect("a number");
    assert!(rate > 5.0 && rate < 200.0, "about 50 a second: {stats:?}");
    assert!(
        field(&stats[1], "accepted")
            .expect("counter")
            .parse::<u64>()
            .expect("number")
            > field(&stats[0], "accepted")
                .expect("counter")
                .parse::<u64>()
                .expect("number")
    );
    let in_stats = port_lines(&broker, &["stats", "pose-in", "--count", "2"]).await;
    assert!(field(&in_stats[1], "received/s").is_some(), "{in_stats:?}");
    let p99: f64 = field(&in_stats[1], "latency_p99_ms")
        .expect("latencies")
        .parse()
        .expect("a number");
    assert!(p99 > 0.0, "{in_stats:?}");

    let echoed = port_lines(&broker, &["echo", "pose-out", "--count", "3"]).await;
    assert_eq!(echoed.len(), 3, "{echoed:?}");
    let mut seqs = Vec::new();
    for line in &echoed {
        let seq: u32 = field(line, "seq").expect("seq").parse().expect("number");
        let age: f64 = field(line, "age_ms").expect("age").parse().expect("number");
        assert!((0.0..10_000.0).contains(&age), "{line}");
        let heading = f64::from(seq) / 2.0;
        assert!(
            line.contains("TimedPose2D { tm: Time { sec: ")
                && line.contains(&format!("heading: {heading:?} }}")),
            "value {seq} decoded: {line}"
        );
        seqs.push(seq);
    }
    assert_eq!(
        seqs,
        [seqs[0], seqs[0] + 1, seqs[0] + 2],
        "in order, none missed"
    );
    // An in-port is echoed through its exchange and binding key.
    let through_in = port_lines(&broker, &["echo", "pose-in", "--count", "1"]).await;
    assert!(through_in[0].contains("TimedPose2D {"), "{through_in:?}");

    publisher.abort();
    let _ = publisher.await;
    tokio::time::timeout(Duration::from_secs(10), output.flush())
        .await
        .expect("flushed");
    let mut watched = input.watch_stats();
    let accepted = output.stats().accepted;
    tokio::time::timeout(
        Duration::from_secs(10),
        watched.wait_for(|stats| stats.arrived == accepted),
    )
    .await
    .expect("the in-port got every value: echo took none")
    .expect("open");
    reader.abort();

    let connections = lines(
        &broker,
        &[
            "-q",
            "--no-table-headers",
            "list_connections",
            "client_properties",
        ],
    )
    .join("\n");
    assert!(
        connections.contains("leveret port out pose-out")
            && connections.contains("leveret port in pose-in"),
        "{connections}"
    );

    let missing = tokio::task::spawn_blocking({
        let broker = std::sync::Arc::clone(&broker);
        move || port_ctl(&broker, &["stats", "nosuch", "--wait", "0.5"])
    })
    .await
    .expect("leveretctl");
    assert_eq!(missing.status.code(), Some(1), "{missing:?}");
    assert!(String::from_utf8_lossy(&missing.stderr).contains("nosuch"));
    let unreachable = Command::new(env!("CARGO_BIN_EXE_leveretctl"))
        .args([
            "--amqp-url",
            "amqp://guest:guest@127.0.0.1:1/%2f",
            "port",
            "list",
        ])
        .output()
        .expect("run leveretctl");
    assert_eq!(unreachable.status.code(), Some(69), "{unreachable:?}");
}

/// ping and await_startup as scripts and service units use them: 0 once
/// the broker answers, 69 (ping) when nothing answers, 75 when
/// await_startup's timeout passes, 1 when the credentials are refused.
#[test]
fn ping_and_await_startup_exit_as_rabbitmqctl() {
    let broker = OpsBroker::start("ctl-ping", &[]);
    let ping = lines(&broker, &["ping"]);
    assert_eq!(
        ping.last().map(String::as_str),
        Some("Ping succeeded"),
        "{ping:?}"
    );
    assert!(lines(&broker, &["-q", "await_startup", "--timeout", "5"]).is_empty());
    let refused = ctl(&broker, &["--password", "wrong", "await_startup"]);
    assert_eq!(refused.status.code(), Some(1), "{refused:?}");
    let nowhere = |args: &[&str]| {
        Command::new(env!("CARGO_BIN_EXE_leveretctl"))
            .args(["--url", "http://127.0.0.1:1"])
            .args(args)
            .output()
            .expect("run leveretctl")
    };
    assert_eq!(nowhere(&["ping", "-t", "2"]).status.code(), Some(69));
    let waited = nowhere(&["await_startup", "--timeout", "1"]);
    assert_eq!(waited.status.code(), Some(75), "{waited:?}");
    assert!(String::from_utf8_lossy(&waited.stderr).contains("did not start within 1 s"));
}

/// add_vhost, list_vhosts and delete_vhost, in text and with `--formatter json`.
#[test]
fn vhosts_are_added_and_listed_in_both_formats() {
    let broker = OpsBroker::start("ctl-vhosts", &[]);
    lines(&broker, &["add_vhost", "robots"]);
    assert_eq!(
        lines(&broker, &["-q", "list_vhosts"]),
        ["name", "/", "robots"]
    );
    let json = lines(
        &broker,
        &[
            "-q",
            "--formatter",
            "json",
            "list_vhosts",
            "name",
            "tracing",
        ],
    );
    let vhosts: serde_json::Value = serde_json::from_str(&json.join("\n")).expect("JSON");
    assert_eq!(
        vhosts,
        serde_json::json!([{"name": "/", "tracing": false}, {"name": "robots", "tracing": false}])
    );
    assert_eq!(
        lines(&broker, &["delete_vhost", "robots"]),
        ["Deleting vhost \"robots\" ..."]
    );
    assert_eq!(lines(&broker, &["-q", "list_vhosts"]), ["name", "/"]);
    let missing = ctl(&broker, &["delete_vhost", "robots"]);
    assert_eq!(missing.status.code(), Some(1), "{missing:?}");
}

/// list_channels with rabbitmqctl's default columns; an unknown column
/// is reported (exit 64) after the known ones are printed.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn channels_are_listed_and_unknown_columns_do_not_abort_the_rest() {
    let broker = OpsBroker::start("ctl-channels", &[]);
    let conn = Connection::connect(&broker.amqp_url(), ConnectionProperties::default())
        .await
        .expect("connect");
    let _one = conn.create_channel().await.expect("channel");
    let _two = conn.create_channel().await.expect("channel");
    let channels = lines(&broker, &["-q", "list_channels"]);
    assert_eq!(
        channels[0],
        "pid\tuser\tconsumer_count\tmessages_unacknowledged"
    );
    assert_eq!(channels.len(), 3, "{channels:?}");
    for row in &channels[1..] {
        assert!(row.ends_with(")\tguest\t0\t0"), "{row}");
    }
    let json = lines(
        &broker,
        &[
            "-q",
            "--formatter",
            "json",
            "list_channels",
            "number",
            "user",
        ],
    );
    let channels: serde_json::Value = serde_json::from_str(&json.join("\n")).expect("JSON");
    assert_eq!(
        channels,
        serde_json::json!([{"number": 1, "user": "guest"}, {"number": 2, "user": "guest"}])
    );

    let partial = ctl(
        &broker,
        &["-q", "list_connections", "user", "memory", "vhost"],
    );
    assert_eq!(partial.status.code(), Some(64), "{partial:?}");
    assert_eq!(
        String::from_utf8_lossy(&partial.stdout),
        "user\tvhost\nguest\t/\n"
    );
    let error = String::from_utf8_lossy(&partial.stderr);
    assert!(error.contains("unknown column(s) memory"), "{error}");
}

/// `status --formatter json`: one object with the alarms, limits and totals.
#[test]
fn status_prints_json_when_asked() {
    let broker = OpsBroker::start("ctl-status-json", &[]);
    let json = lines(&broker, &["-q", "--formatter", "json", "status"]);
    let status: serde_json::Value = serde_json::from_str(&json.join("\n")).expect("JSON");
    assert_eq!(status["alarms"], serde_json::json!([]));
    assert!(status["memory"]["queued_bytes_limit"].is_u64(), "{status}");
    assert!(status["disk"]["limit"].is_u64(), "{status}");
    assert_eq!(status["totals"]["connections"], 0);
}

/// set_topic_permissions, list_topic_permissions and
/// clear_topic_permissions (all, or one exchange's) in rabbitmqctl's words.
#[test]
fn topic_permissions_are_set_listed_and_cleared() {
    let broker = OpsBroker::start("ctl-topic-permissions", &[]);
    let listed = |broker: &OpsBroker| {
        lines(
            broker,
            &["-q", "--no-table-headers", "list_topic_permissions"],
        )
    };
    lines(
        &broker,
        &[
            "set_topic_permissions",
            "guest",
            "amq.topic",
            "^robots\\.",
            ".*",
        ],
    );
    lines(
        &broker,
        &["set_topic_permissions", "guest", "events", "^a", "^b"],
    );
    let mut both = listed(&broker);
    both.sort();
    assert_eq!(
        both,
        ["guest\tamq.topic\t^robots\\.\t.*", "guest\tevents\t^a\t^b"]
    );
    lines(&broker, &["clear_topic_permissions", "guest", "events"]);
    assert_eq!(listed(&broker), ["guest\tamq.topic\t^robots\\.\t.*"]);
    lines(&broker, &["clear_topic_permissions", "guest"]);
    assert!(listed(&broker).is_empty());
}

/// report: the status, then every listing, vhost by vhost; in JSON one
/// object holding the API's objects.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn report_shows_the_status_and_every_listing() {
    let broker = OpsBroker::start("ctl-report", &[]);
    lines(&broker, &["add_vhost", "robots"]);
    let conn = Connection::connect(&broker.amqp_url(), ConnectionProperties::default())
        .await
        .expect("connect");
    let ch = conn.create_channel().await.expect("channel");
    ch.queue_declare(
        "reported",
        QueueDeclareOptions::default(),
        FieldTable::default(),
    )
    .await
    .expect("declare");
    let text = lines(&broker, &["report"]).join("\n");
    for expected in [
        "\nAlarms\n",
        "\nConnections:\nuser\tpeer_host\tpeer_port\tstate\nguest\t127.0.0.1\t",
        "\nChannels:\npid\tuser\tconsumer_count\tmessages_unacknowledged\n",
        "\nQueues on /:\nname\tmessages\nreported\t0\n",
        "\nPermissions on robots:\nuser\tconfigure\twrite\tread\nguest\t.*\t.*\t.*\n",
        "\nTopic permissions on robots:\n",
    ] {
        assert!(text.contains(expected), "{expected:?} in:\n{text}");
    }
    let json = lines(&broker, &["--formatter", "json", "report"]).join("\n");
    let report: serde_json::Value = serde_json::from_str(&json).expect("JSON");
    assert_eq!(report["vhosts"]["/"]["queues"][0]["name"], "reported");
    assert_eq!(
        report["vhosts"]["robots"]["permissions"][0]["user"],
        "guest"
    );
    assert_eq!(report["connections"][0]["user"], "guest");
}

/// `port echo` on a port of the default exchange (straight to its queue,
/// no exchange to copy from) peeks at the queue: it prints values in
/// order, and the in-port still gets every one, none twice.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn port_echo_peeks_at_a_default_exchange_port() {
    use leveret_ports::{InPort, OutPort, PortProfile, Time, TimedLong};
    let broker = std::sync::Arc::new(OpsBroker::start("ctl-echo-default", &[]));
    let profile = PortProfile::new(&broker.amqp_url())
        .expect("URI")
        .queue("cmd_vel")
        .routing_key("cmd_vel")
        .announce_interval(Some(Duration::from_millis(200)));
    let input = InPort::<TimedLong>::connect(profile.clone().name("cmd-in"))
        .await
        .expect("in-port");
    let output = std::sync::Arc::new(
        OutPort::<TimedLong>::connect(profile.name("cmd-out"))
            .await
            .expect("out-port"),
    );
    // Value n is n: its sequence number says which it is.
    let publisher = {
        let output = std::sync::Arc::clone(&output);
        tokio::spawn(async move {
            for data in 1..=i32::MAX {
                output
                    .put(&TimedLong {
                        tm: Time::now(),
                        data,
                    })
                    .await;
                tokio::time::sleep(Duration::from_millis(20)).await;
            }
        })
    };
    let echoed = port_lines(&broker, &["echo", "cmd-out", "--count", "3"]).await;
    assert_eq!(echoed.len(), 3, "{echoed:?}");
    let mut seqs = Vec::new();
    for line in &echoed {
        let seq: u64 = field(line, "seq").expect("seq").parse().expect("number");
        assert!(
            line.contains("TimedLong { tm: Time { sec: ")
                && line.contains(&format!("data: {seq} }}")),
            "value {seq} decoded: {line}"
        );
        seqs.push(seq);
    }
    assert!(seqs.windows(2).all(|w| w[0] < w[1]), "{seqs:?}");

    publisher.abort();
    let _ = publisher.await;
    tokio::time::timeout(Duration::from_secs(10), output.flush())
        .await
        .expect("flushed");
    let accepted = output.stats().accepted;
    let mut watched = input.watch_stats();
    tokio::time::timeout(
        Duration::from_secs(10),
        watched.wait_for(|stats| stats.arrived == accepted),
    )
    .await
    .expect("the in-port got every value: the echo handed back what it took")
    .expect("open");
    assert_eq!(input.stats().duplicates, 0, "{:?}", input.stats());
}

/// `port hz` and `port bw` on a port of a named exchange and on one of the
/// default exchange: rate and gaps that agree with each other (the mean
/// gap between the shortest and the longest), the window counted, and the
/// bodies' exact size (a `TimedLong` is 12 bytes of CDR).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn port_hz_and_bw_measure_a_ports_messages() {
    use leveret_ports::{ExchangeKind, InPort, OutPort, PortProfile, Time, TimedLong};
    let broker = std::sync::Arc::new(OpsBroker::start("ctl-hz-bw", &[]));
    let base = PortProfile::new(&broker.amqp_url())
        .expect("URI")
        .announce_interval(Some(Duration::from_millis(200)));
    let fanout = OutPort::<TimedLong>::connect(
        base.clone()
            .exchange("ticks", ExchangeKind::Fanout)
            .name("ticks-out"),
    )
    .await
    .expect("out-port");
    let direct_profile = base.queue("ticks_q").routing_key("ticks_q");
    // The default exchange's queue has a reader, as a command port does:
    // the tap peeks at messages on their way to it.
    let reader = InPort::<TimedLong>::connect(direct_profile.clone().name("ticks-in"))
        .await
        .expect("in-port");
    let direct = OutPort::<TimedLong>::connect(direct_profile.name("ticks-direct"))
        .await
        .expect("out-port");
    let publisher = tokio::spawn(async move {
        for data in 1..=i32::MAX {
            let value = TimedLong {
                tm: Time::now(),
                data,
            };
            fanout.put(&value).await;
            direct.put(&value).await;
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
    });
    let number = |line: &str, key: &str| -> f64 {
        field(line, key)
            .unwrap_or_else(|| panic!("{key} in {line}"))
            .parse()
            .expect("a number")
    };
    for port in ["ticks-out", "ticks-direct"] {
        let rates = port_lines(&broker, &["hz", port, "--count", "2"]).await;
        assert_eq!(rates.len(), 2, "{rates:?}");
        for line in &rates {
            let rate = number(line, "rate_hz");
            let (min, max) = (number(line, "min_s"), number(line, "max_s"));
            assert!(rate > 0.0 && min <= max, "{line}");
            let mean_gap = 1.0 / rate;
            assert!(min - 2e-6 <= mean_gap && mean_gap <= max + 2e-6, "{line}");
            assert!(number(line, "std_s") >= 0.0, "{line}");
            assert!(number(line, "window") >= 2.0, "{line}");
        }
        let bandwidth = port_lines(&broker, &["bw", port, "--count", "1", "--window", "5"]).await;
        assert_eq!(bandwidth.len(), 1, "{bandwidth:?}");
        let line = &bandwidth[0];
        assert_eq!(field(line, "min_bytes"), Some("12"), "{line}");
        assert_eq!(field(line, "max_bytes"), Some("12"), "{line}");
        assert_eq!(field(line, "mean_bytes"), Some("12.0"), "{line}");
        assert!(number(line, "bytes_per_s") > 0.0, "{line}");
        assert!(number(line, "window") <= 5.0, "{line}");
    }
    let refused = port_ctl(&broker, &["hz", "ticks-out", "--window", "1"]);
    assert_eq!(refused.status.code(), Some(64), "{refused:?}");
    publisher.abort();
    reader.close().await;
}

/// The limit commands with rabbitmqctl's output (recorded from rabbitmqctl
/// 3.10.8), the API paths behind them, and the limits in force over AMQP.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn vhost_and_user_limits_are_set_listed_enforced_and_cleared() {
    let broker = OpsBroker::start("ctl-limits", &[]);
    lines(&broker, &["add_vhost", "capped"]);
    assert_eq!(
        lines(
            &broker,
            &[
                "-p",
                "capped",
                "set_vhost_limits",
                r#"{"max-connections": 1, "max-queues": 5}"#
            ]
        ),
        [
            r#"Setting vhost limits to "{"max-connections": 1, "max-queues": 5}" for vhost "capped" ..."#
        ]
    );
    assert_eq!(
        lines(&broker, &["-p", "capped", "list_vhost_limits"]),
        [
            r#"Listing limits for vhost "capped" ..."#,
            r#"{"max-connections":1,"max-queues":5}"#
        ]
    );
    // The definition replaces the vhost's limits, as in RabbitMQ.
    lines(
        &broker,
        &[
            "-p",
            "capped",
            "set_vhost_limits",
            r#"{"max-connections": 1}"#,
        ],
    );
    assert_eq!(
        lines(&broker, &["-q", "list_vhost_limits", "--global"]),
        ["vhost\tlimits", "capped\t{\"max-connections\":1}"]
    );
    let url = format!("amqp://guest:guest@{}/capped", broker.amqp);
    let first = Connection::connect(&url, ConnectionProperties::default())
        .await
        .expect("the first connection");
    let refused = Connection::connect(&url, ConnectionProperties::default())
        .await
        .expect_err("over max-connections");
    assert!(
        refused
            .to_string()
            .contains("connection limit (1) is reached"),
        "{refused}"
    );
    drop(first);
    // A term RabbitMQ does not know changes nothing (exit 64).
    let bogus = ctl(
        &broker,
        &["-p", "capped", "set_vhost_limits", r#"{"bogus": 6}"#],
    );
    assert_eq!(bogus.status.code(), Some(64), "{bogus:?}");
    assert!(String::from_utf8_lossy(&bogus.stderr).contains("Unrecognised terms"));
    lines(&broker, &["-p", "capped", "clear_vhost_limits"]);
    assert_eq!(
        lines(&broker, &["-q", "-p", "capped", "list_vhost_limits"]),
        ["{}"]
    );

    // User limits are added to, and cleared one by one or all.
    lines(
        &broker,
        &["set_user_limits", "guest", r#"{"max-connections": 3}"#],
    );
    lines(
        &broker,
        &["set_user_limits", "guest", r#"{"max-channels": 7}"#],
    );
    assert_eq!(
        lines(&broker, &["list_user_limits", "--user", "guest"]),
        [
            r#"Listing limits for user "guest" ..."#,
            r#"{"max-channels":7,"max-connections":3}"#
        ]
    );
    lines(&broker, &["clear_user_limits", "guest", "max-channels"]);
    assert_eq!(
        lines(&broker, &["-q", "list_user_limits", "--global"]),
        ["user\tlimits", "guest\t{\"max-connections\":3}"]
    );
    let json = lines(
        &broker,
        &["-q", "--formatter", "json", "list_user_limits", "--global"],
    );
    let listed: serde_json::Value = serde_json::from_str(&json.join("\n")).expect("JSON");
    assert_eq!(
        listed,
        serde_json::json!([{"user": "guest", "limits": {"max-connections": 3}}])
    );
    lines(&broker, &["clear_user_limits", "guest", "all"]);
    assert_eq!(lines(&broker, &["-q", "list_user_limits"]), ["{}"]);
    let unknown_user = ctl(
        &broker,
        &["set_user_limits", "nobody", r#"{"max-channels": 1}"#],
    );
    assert_eq!(unknown_user.status.code(), Some(1), "{unknown_user:?}");
}

/// environment: the effective configuration (the config file's values,
/// the command line's over them, the defaults for the rest) under the
/// config file's names, in both formats; no password in it; only an
/// administrator may read it.
#[test]
fn environment_shows_the_effective_configuration_without_secrets() {
    let dir = std::env::temp_dir().join(format!("leveret-ctl-env-{}", std::process::id()));
    std::fs::create_dir_all(&dir).expect("dir");
    let config = dir.join("leveret.toml");
    std::fs::write(
        &config,
        r#"
heartbeat = 30
disk-free-limit = 123456789
log = "warn"
vhosts = ["/", "robots"]

[[users]]
name = "admin"
password = "s3cret-admin-pw"
tags = ["administrator"]

[[users]]
name = "watcher"
password = "s3cret-watcher-pw"
tags = ["monitoring"]
max-connections = 3
"#,
    )
    .expect("write config");
    let config_arg = config.to_str().expect("utf-8");
    // The command line's --log (info, from OpsBroker) wins over the file's.
    let broker = OpsBroker::start("ctl-environment", &["--config", config_arg]);
    let as_admin = |extra: &[&str]| {
        let mut args = vec!["--username", "admin", "--password", "s3cret-admin-pw"];
        args.extend_from_slice(extra);
        ctl(&broker, &args)
    };

    let json = as_admin(&["--formatter", "json", "environment"]);
    assert!(json.status.success(), "{json:?}");
    let text = String::from_utf8_lossy(&json.stdout);
    assert!(!text.contains("s3cret"), "{text}");
    let env: serde_json::Value = serde_json::from_str(&text).expect("JSON");
    assert_eq!(env["heartbeat"], 30);
    assert_eq!(env["disk-free-limit"], 123456789);
    assert_eq!(env["log"], "info", "the command line over the file");
    assert_eq!(env["config-file"], config_arg);
    assert_eq!(env["vhosts"], serde_json::json!(["/", "robots"]));
    assert_eq!(env["frame-max"], 131072, "a default");
    assert_eq!(env["vm-memory-high-watermark-relative"], 0.4, "a default");
    assert_eq!(env["http-listen"], "127.0.0.1:0");
    assert_eq!(
        env["users"],
        serde_json::json!([
            {"name": "admin", "tags": ["administrator"], "max-connections": null, "max-channels": null},
            {"name": "watcher", "tags": ["monitoring"], "max-connections": 3, "max-channels": null},
        ])
    );

    let table = as_admin(&["environment"]);
    assert!(table.status.success(), "{table:?}");
    let lines: Vec<String> = String::from_utf8_lossy(&table.stdout)
        .lines()
        .map(str::to_owned)
        .collect();
    assert!(
        lines[0].starts_with("Effective configuration of node leveret@"),
        "{lines:?}"
    );
    for wanted in [
        "heartbeat = 30",
        "disk-free-limit = 123456789",
        "log = \"info\"",
    ] {
        assert!(lines.iter().any(|l| l == wanted), "{wanted}: {lines:?}");
    }
    assert!(!lines.iter().any(|l| l.contains("s3cret")), "{lines:?}");

    let refused = ctl(
        &broker,
        &[
            "--username",
            "watcher",
            "--password",
            "s3cret-watcher-pw",
            "environment",
        ],
    );
    assert_eq!(refused.status.code(), Some(1), "{refused:?}");
    assert!(
        String::from_utf8_lossy(&refused.stderr).contains("Not administrator user"),
        "{refused:?}"
    );
    drop(broker);
    let _ = std::fs::remove_dir_all(&dir);
}
