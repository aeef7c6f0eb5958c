//! Policies on Leveret and on the machine's RabbitMQ 3.10 node, side by
//! side: the same policies and operator policies set with the same
//! rabbitmqctl syntax (`rabbitmqctl` there, `leveretctl` here), the same
//! AMQP steps with lapin, and the same outcome asked of both: how
//! arguments and policies combine (the smaller length, the argument's
//! overflow and dead-letter exchange, the smaller TTL), an operator
//! policy's clamp, a live change shortening a queue, a refused key.
//!
//! Starts a RabbitMQ node of its own (Debian's `rabbitmq-server`, which
//! `.ci/run` installs; outside CI a missing one skips the test loudly).

mod common;

use common::ops::{tool_available, OpsBroker};
use lapin::options::{
    BasicPublishOptions, ConfirmSelectOptions, ExchangeDeclareOptions, QueueBindOptions,
    QueueDeclareOptions,
};
use lapin::types::{AMQPValue, FieldTable};
use lapin::{BasicProperties, Channel, Connection, ConnectionProperties, ExchangeKind};
use leveret_tests::rabbit_node::{RabbitNode, BIN};
use std::collections::BTreeMap;
use std::process::Command;
use std::sync::Arc;
use std::time::{Duration, Instant};

/// How a broker's ctl tool is run.
type Ctl = Box<dyn Fn(&[&str]) -> std::process::Output>;

/// One broker: its AMQP URL and its ctl tool.
struct Side {
    amqp: String,
    ctl: Ctl,
}

impl Side {
    fn must(&self, args: &[&str]) -> String {
        let output = (self.ctl)(args);
        assert!(
            output.status.success(),
            "{args:?}: {}{}",
            String::from_utf8_lossy(&output.stdout),
            String::from_utf8_lossy(&output.stderr)
        );
        String::from_utf8_lossy(&output.stdout).into_owned()
    }
}

fn table(pairs: &[(&str, AMQPValue)]) -> FieldTable {
    let mut t = FieldTable::default();
    for (k, v) in pairs {
        t.insert((*k).into(), v.clone());
    }
    t
}

async fn declare(ch: &Channel, name: &str, args: FieldTable) {
    ch.queue_declare(name, QueueDeclareOptions::default(), args)
        .await
        .expect("queue.declare");
}

/// Publishes `n` messages to `queue`; how many were acked.
async fn publish(ch: &Channel, queue: &str, n: usize) -> usize {
    let mut acked = 0;
    for i in 0..n {
        let confirm = ch
            .basic_publish(
                "",
                queue,
                BasicPublishOptions::default(),
                i.to_string().as_bytes(),
                BasicProperties::default(),
            )
            .await
            .expect("publish")
            .await
            .expect("confirm");
        acked += usize::from(confirm.is_ack());
    }
    acked
}

async fn ready(ch: &Channel, queue: &str) -> u32 {
    let passive = QueueDeclareOptions {
        passive: true,
        ..Default::default()
    };
    ch.queue_declare(queue, passive, FieldTable::default())
        .await
        .expect("passive declare")
        .message_count()
}

/// The ready count once it is `want` (policies apply, and TTL 0 drops,
/// within moments on both brokers), or whatever it is after 5 s.
async fn settled(ch: &Channel, queue: &str, want: u32) -> u32 {
    let deadline = Instant::now() + Duration::from_secs(5);
    loop {
        let now = ready(ch, queue).await;
        if now == want || Instant::now() > deadline {
            return now;
        }
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
}

/// Runs the scenario on `side` with names starting `p`; the outcome of
/// each step by name.
async fn scenario(side: &Side, p: &str) -> BTreeMap<String, String> {
    let mut out = BTreeMap::new();
    let conn = Connection::connect(&side.amqp, ConnectionProperties::default())
        .await
        .expect("connect");
    let ch = conn.create_channel().await.expect("channel");
    ch.confirm_select(ConfirmSelectOptions::default())
        .await
        .expect("confirm.select");
    let q = |suffix: &str| format!("{p}{suffix}");
    let pattern = |case: &str| format!("^{}{case}\\.", p.replace('.', "\\."));
    let int = |n: i32| AMQPValue::LongInt(n);
    let text = |s: &str| AMQPValue::LongString(s.into());

    // A: arguments against a policy and an operator policy (smaller wins).
    side.must(&[
        "set_policy",
        "--apply-to",
        "queues",
        "a-pol",
        &pattern("a"),
        r#"{"max-length":5}"#,
    ]);
    side.must(&[
        "set_operator_policy",
        "--apply-to",
        "queues",
        "a-op",
        &pattern("a"),
        r#"{"max-length":3}"#,
    ]);
    declare(&ch, &q("a.plain"), FieldTable::default()).await;
    declare(&ch, &q("a.arg10"), table(&[("x-max-length", int(10))])).await;
    declare(&ch, &q("a.arg2"), table(&[("x-max-length", int(2))])).await;
    for name in ["a.plain", "a.arg10", "a.arg2"] {
        publish(&ch, &q(name), 8).await;
        out.insert(name.to_owned(), ready(&ch, &q(name)).await.to_string());
    }
    // B: the argument's overflow wins over the policy's.
    side.must(&[
        "set_policy",
        "b-pol",
        &pattern("b"),
        r#"{"max-length":1,"overflow":"drop-head"}"#,
    ]);
    declare(
        &ch,
        &q("b.reject"),
        table(&[("x-overflow", text("reject-publish"))]),
    )
    .await;
    let acked = publish(&ch, &q("b.reject"), 3).await;
    out.insert("b.acked".into(), acked.to_string());
    out.insert(
        "b.ready".into(),
        ready(&ch, &q("b.reject")).await.to_string(),
    );
    // C: the policy's TTL 0 is smaller than the argument's.
    side.must(&["set_policy", "c-pol", &pattern("c"), r#"{"message-ttl":0}"#]);
    declare(&ch, &q("c.arg"), table(&[("x-message-ttl", int(600_000))])).await;
    publish(&ch, &q("c.arg"), 2).await;
    out.insert(
        "c.ready".into(),
        settled(&ch, &q("c.arg"), 0).await.to_string(),
    );
    // D: the argument's dead-letter exchange wins over the policy's.
    for sink in ["sink-a", "sink-b"] {
        let exchange = q(sink);
        ch.exchange_declare(
            &exchange,
            ExchangeKind::Fanout,
            ExchangeDeclareOptions::default(),
            FieldTable::default(),
        )
        .await
        .expect("exchange.declare");
        declare(&ch, &exchange, FieldTable::default()).await;
        ch.queue_bind(
            &exchange,
            &exchange,
            "",
            QueueBindOptions::default(),
            FieldTable::default(),
        )
        .await
        .expect("bind");
    }
    let dlx_b = format!(
        r#"{{"dead-letter-exchange":"{}","max-length":0}}"#,
        q("sink-b")
    );
    side.must(&["set_policy", "d-pol", &pattern("d"), &dlx_b]);
    declare(
        &ch,
        &q("d.q"),
        table(&[("x-dead-letter-exchange", text(&q("sink-a")))]),
    )
    .await;
    publish(&ch, &q("d.q"), 1).await;
    out.insert(
        "d.sink-a".into(),
        settled(&ch, &q("sink-a"), 1).await.to_string(),
    );
    out.insert(
        "d.sink-b".into(),
        ready(&ch, &q("sink-b")).await.to_string(),
    );
    // E: a live change shortens a queue; clearing lets it grow.
    declare(&ch, &q("e.q"), FieldTable::default()).await;
    publish(&ch, &q("e.q"), 6).await;
    side.must(&["set_policy", "e-pol", &pattern("e"), r#"{"max-length":2}"#]);
    out.insert(
        "e.shortened".into(),
        settled(&ch, &q("e.q"), 2).await.to_string(),
    );
    side.must(&["clear_policy", "e-pol"]);
    publish(&ch, &q("e.q"), 1).await;
    out.insert(
        "e.regrown".into(),
        settled(&ch, &q("e.q"), 3).await.to_string(),
    );
    // F: max-priority is not a policy key.
    let refused = (side.ctl)(&[
        "set_policy",
        "f-pol",
        &pattern("f"),
        r#"{"max-priority":5}"#,
    ]);
    out.insert("f.refused".into(), (!refused.status.success()).to_string());
    // The policy each queue lists.
    let listed = side.must(&["-q", "--no-table-headers", "list_queues", "name", "policy"]);
    for line in listed.lines().filter(|line| line.starts_with(p)) {
        let mut fields = line.split('\t');
        let name = fields.next().unwrap_or_default().trim_start_matches(p);
        out.insert(
            format!("policy of {name}"),
            fields.next().unwrap_or_default().to_owned(),
        );
    }
    for name in ["a-pol", "b-pol", "c-pol", "d-pol"] {
        side.must(&["clear_policy", name]);
    }
    side.must(&["clear_operator_policy", "a-op"]);
    drop(ch);
    let _ = conn.close(200, "done").await;
    out
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn leveret_combines_policies_as_rabbitmq_does() {
    if !tool_available(&format!("{BIN}/rabbitmq-server"), "rabbitmq-server") {
        return;
    }
    let dir = std::env::temp_dir().join(format!("leveret-policies-diff-{}", std::process::id()));
    let node = Arc::new(tokio::task::block_in_place(|| {
        RabbitNode::start("leveret-policies-diff", &dir, &dir)
    }));
    let prefix = format!(
        "pd{}x{}.",
        std::process::id(),
        Instant::now().elapsed().as_nanos()
    );
    let rabbit = Side {
        amqp: node.uri(),
        ctl: Box::new(move |args| node.ctl(args)),
    };
    let broker = OpsBroker::start("policies-differential", &[]);
    let url = format!("http://{}", broker.http);
    let leveret = Side {
        amqp: format!("amqp://guest:guest@{}/%2f", broker.amqp),
        ctl: Box::new(move |args| {
            Command::new(env!("CARGO_BIN_EXE_leveretctl"))
                .args(["--url", &url])
                .args(args)
                .output()
                .expect("run leveretctl")
        }),
    };
    let from_rabbitmq = scenario(&rabbit, &prefix).await;
    let from_leveret = scenario(&leveret, &prefix).await;
    for suffix in [
        "a.plain", "a.arg10", "a.arg2", "b.reject", "c.arg", "d.q", "e.q", "sink-a", "sink-b",
    ] {
        let _ = (rabbit.ctl)(&["delete_queue", &format!("{prefix}{suffix}")]);
    }
    assert_eq!(from_leveret, from_rabbitmq);
    // And what both did, spelled out.
    let expected = [
        ("a.plain", "3"),
        ("a.arg10", "3"),
        ("a.arg2", "2"),
        ("b.acked", "1"),
        ("b.ready", "1"),
        ("c.ready", "0"),
        ("d.sink-a", "1"),
        ("d.sink-b", "0"),
        ("e.shortened", "2"),
        ("e.regrown", "3"),
        ("f.refused", "true"),
        ("policy of a.plain", "a-pol"),
        ("policy of e.q", ""),
    ];
    for (key, value) in expected {
        assert_eq!(
            from_leveret.get(key).map(String::as_str),
            Some(value),
            "{key}: {from_leveret:?}"
        );
    }
}
