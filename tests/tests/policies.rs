//! Policies and operator policies acting on what applications declare,
//! as RabbitMQ 3.10 applies them: a policy's `message-ttl`,
//! `dead-letter-exchange`, `max-length` and `alternate-exchange` on a
//! queue or exchange declared without arguments; a change applied at once
//! to an existing queue (a shorter `max-length` dead-letters its head
//! now); arguments combined with policies by RabbitMQ's rules; an
//! operator policy clamping a user policy; and many policies and queues
//! costing one match per queue per change.
//!
//! Policies are set through the in-process broker's `Admin` (against an
//! external broker the tests have no API to set them and return early).

#[macro_use]
mod common;

use common::lp::AMQPValue;
use common::*;
use leveret_broker::{Admin, ApplyTo, PolicyKind, PolicySpec, PolicyValue};

fn spec(pattern: &str, apply_to: ApplyTo, keys: &[(&str, PolicyValue)]) -> PolicySpec {
    PolicySpec {
        pattern: pattern.to_owned(),
        apply_to,
        priority: 0,
        definition: keys
            .iter()
            .map(|(k, v)| (k.to_string(), v.clone()))
            .collect(),
    }
}

fn int(n: i64) -> PolicyValue {
    PolicyValue::Integer(n)
}

fn text(s: &str) -> PolicyValue {
    PolicyValue::Text(s.to_owned())
}

/// The exact-name pattern of `name` (its dots match themselves too).
fn exactly(name: &str) -> String {
    format!("^{}$", name.replace('.', "\\."))
}

async fn set(admin: &Admin, kind: PolicyKind, name: &str, spec: PolicySpec) {
    admin
        .set_policy(kind, "/", name, spec)
        .await
        .expect("set_policy");
}

async fn declare(ch: &lp::Channel, name: &str, args: lp::FieldTable) {
    tmo!(ch.queue_declare(name, Default::default(), args)).expect("queue.declare");
}

async fn confirm_channel(conn: &lp::Connection) -> lp::Channel {
    let ch = lp::channel(conn).await;
    tmo!(ch.confirm_select(Default::default())).expect("confirm.select");
    ch
}

/// A fanout exchange with one queue bound and a no-ack consumer on it.
async fn sink(ch: &lp::Channel, prefix: &str) -> (String, lp::Consumer) {
    let exchange = lp::exchange(ch, prefix, lp::ExchangeKind::Fanout).await;
    let queue = lp::queue(ch, prefix).await;
    lp::bind(ch, &queue, &exchange, "").await;
    let options = lp::BasicConsumeOptions {
        no_ack: true,
        ..Default::default()
    };
    let consumer = lp::consume_opts(ch, &queue, "", options).await;
    (exchange, consumer)
}

fn ready(admin: &Admin, queue: &str) -> u64 {
    admin
        .queues()
        .into_iter()
        .find(|q| q.name == queue)
        .map(|q| q.messages_ready)
        .expect("the queue is listed")
}

#[both_runtimes]
async fn a_policys_ttl_and_dead_letter_exchange_act_on_a_queue_declared_without_them() {
    let b = broker().await;
    let Some(admin) = b.admin() else { return };
    let conn = lp::connect(&b).await;
    let ch = confirm_channel(&conn).await;
    let (dlx, mut dead) = sink(&ch, "policy-dlx").await;
    let q = unique("policy-ttl");
    let keys = [
        ("message-ttl", int(20)),
        ("dead-letter-exchange", text(&dlx)),
    ];
    set(
        &admin,
        PolicyKind::User,
        "ttl",
        spec(&exactly(&q), ApplyTo::Queues, &keys),
    )
    .await;
    declare(&ch, &q, Default::default()).await;
    assert!(
        lp::publish_confirmed(&ch, "", &q, b"short-lived", Default::default())
            .await
            .is_ack()
    );
    let d = lp::next(&mut dead).await;
    assert_eq!(lp::text(&d), "short-lived");
    let deaths = d
        .properties
        .headers()
        .as_ref()
        .and_then(|h| h.inner().get("x-death").cloned());
    let Some(AMQPValue::FieldArray(deaths)) = deaths else {
        panic!("no x-death: {:?}", d.properties.headers())
    };
    let Some(AMQPValue::FieldTable(first)) = deaths.as_slice().first() else {
        panic!("empty x-death")
    };
    assert_eq!(first.inner().get("reason"), Some(&lp::lstr("expired")));
    let listed = admin.queues().into_iter().find(|i| i.name == q).unwrap();
    assert_eq!(listed.policies.policy_name(), Some("ttl"));
    assert_eq!(listed.policies.operator_policy_name(), None);
    b.stop().await;
}

#[both_runtimes]
async fn a_new_max_length_dead_letters_the_head_of_an_existing_queue_at_once() {
    let b = broker().await;
    let Some(admin) = b.admin() else { return };
    let conn = lp::connect(&b).await;
    let ch = confirm_channel(&conn).await;
    let (dlx, mut dead) = sink(&ch, "shortened-dlx").await;
    let q = unique("shortened");
    declare(&ch, &q, Default::default()).await;
    for i in 1..=5 {
        let body = i.to_string();
        assert!(
            lp::publish_confirmed(&ch, "", &q, body.as_bytes(), Default::default())
                .await
                .is_ack()
        );
    }
    assert_eq!(ready(&admin, &q), 5);
    let keys = [("max-length", int(2)), ("dead-letter-exchange", text(&dlx))];
    set(
        &admin,
        PolicyKind::User,
        "short",
        spec(&exactly(&q), ApplyTo::All, &keys),
    )
    .await;
    assert_eq!(ready(&admin, &q), 2, "shortened when the policy was set");
    for expected in ["1", "2", "3"] {
        assert_eq!(lp::text(&lp::next(&mut dead).await), expected);
    }
    // Cleared: the queue grows again.
    assert!(admin.clear_policy(PolicyKind::User, "/", "short").await);
    for _ in 0..3 {
        assert!(
            lp::publish_confirmed(&ch, "", &q, b"more", Default::default())
                .await
                .is_ack()
        );
    }
    assert_eq!(ready(&admin, &q), 5);
    let listed = admin.queues().into_iter().find(|i| i.name == q).unwrap();
    assert_eq!(listed.policies.policy_name(), None);
    b.stop().await;
}

#[both_runtimes]
async fn an_alternate_exchange_from_a_policy_takes_what_nothing_routes() {
    let b = broker().await;
    let Some(admin) = b.admin() else { return };
    let conn = lp::connect(&b).await;
    let ch = confirm_channel(&conn).await;
    let (alternate, mut caught) = sink(&ch, "policy-ae").await;
    let x = lp::exchange(&ch, "policy-x", lp::ExchangeKind::Direct).await;
    let keys = [("alternate-exchange", text(&alternate))];
    // A policy for queues only does not touch the exchange.
    set(
        &admin,
        PolicyKind::User,
        "ae",
        spec(&exactly(&x), ApplyTo::Queues, &keys),
    )
    .await;
    lp::publish(&ch, &x, "nowhere", b"lost").await;
    lp::nothing(&mut caught).await;
    set(
        &admin,
        PolicyKind::User,
        "ae",
        spec(&exactly(&x), ApplyTo::Exchanges, &keys),
    )
    .await;
    lp::publish(&ch, &x, "nowhere", b"caught").await;
    assert_eq!(lp::text(&lp::next(&mut caught).await), "caught");
    assert!(admin.clear_policy(PolicyKind::User, "/", "ae").await);
    lp::publish(&ch, &x, "nowhere", b"lost again").await;
    lp::nothing(&mut caught).await;
    b.stop().await;
}

#[both_runtimes]
async fn arguments_and_policies_combine_by_rabbitmqs_rules() {
    let b = broker().await;
    let Some(admin) = b.admin() else { return };
    let conn = lp::connect(&b).await;
    let ch = confirm_channel(&conn).await;
    let prefix = unique("combine");
    let keys = [("max-length", int(2)), ("overflow", text("drop-head"))];
    let pattern = format!("^{}", prefix.replace('.', "\\."));
    set(
        &admin,
        PolicyKind::User,
        "combine",
        spec(&pattern, ApplyTo::Queues, &keys),
    )
    .await;
    // x-max-length 10 and the policy's 2: the smaller, 2.
    let loose = format!("{prefix}.loose");
    declare(
        &ch,
        &loose,
        lp::table(vec![("x-max-length", AMQPValue::LongInt(10))]),
    )
    .await;
    // x-max-length 1 and the policy's 2: 1. x-overflow reject-publish wins
    // over the policy's drop-head: the second publish is refused.
    let strict = format!("{prefix}.strict");
    let args = lp::table(vec![
        ("x-max-length", AMQPValue::LongInt(1)),
        ("x-overflow", lp::lstr("reject-publish")),
    ]);
    declare(&ch, &strict, args).await;
    for _ in 0..4 {
        lp::publish_confirmed(&ch, "", &loose, b"m", Default::default()).await;
    }
    assert_eq!(ready(&admin, &loose), 2);
    let first = lp::publish_confirmed(&ch, "", &strict, b"1", Default::default()).await;
    let second = lp::publish_confirmed(&ch, "", &strict, b"2", Default::default()).await;
    assert!(first.is_ack() && second.is_nack(), "{first:?} {second:?}");
    assert_eq!(ready(&admin, &strict), 1);
    b.stop().await;
}

#[both_runtimes]
async fn an_operator_policy_clamps_a_users_policy() {
    let b = broker().await;
    let Some(admin) = b.admin() else { return };
    let conn = lp::connect(&b).await;
    let ch = confirm_channel(&conn).await;
    let q = unique("clamped");
    let pattern = exactly(&q);
    set(
        &admin,
        PolicyKind::User,
        "roomy",
        spec(&pattern, ApplyTo::All, &[("max-length", int(100))]),
    )
    .await;
    set(
        &admin,
        PolicyKind::Operator,
        "cap",
        spec(&pattern, ApplyTo::Queues, &[("max-length", int(3))]),
    )
    .await;
    declare(&ch, &q, Default::default()).await;
    for _ in 0..10 {
        lp::publish_confirmed(&ch, "", &q, b"m", Default::default()).await;
    }
    assert_eq!(ready(&admin, &q), 3);
    let listed = admin.queues().into_iter().find(|i| i.name == q).unwrap();
    assert_eq!(listed.policies.policy_name(), Some("roomy"));
    assert_eq!(listed.policies.operator_policy_name(), Some("cap"));
    assert_eq!(listed.policies.effective_definition()["max-length"], int(3));
    // An operator policy takes only its keys.
    let refused = admin
        .set_policy(
            PolicyKind::Operator,
            "/",
            "dlx",
            spec(
                ".*",
                ApplyTo::Queues,
                &[("dead-letter-exchange", text("x"))],
            ),
        )
        .await;
    assert!(refused.is_err());
    // The operator policy goes: the user's 100 holds again.
    assert!(admin.clear_policy(PolicyKind::Operator, "/", "cap").await);
    for _ in 0..10 {
        lp::publish_confirmed(&ch, "", &q, b"m", Default::default()).await;
    }
    assert_eq!(ready(&admin, &q), 13);
    b.stop().await;
}

/// 1,000 policies and 1,000 queues: every change and every declare still
/// completes (a change is one match per queue, a declare one per
/// policy), publishing is untouched, and only the queue a policy matches
/// takes it.
#[both_runtimes]
async fn many_policies_and_queues_stay_bounded_per_operation() {
    const N: usize = 1_000;
    let b = broker().await;
    let Some(admin) = b.admin() else { return };
    let conn = lp::connect(&b).await;
    let ch = confirm_channel(&conn).await;
    let prefix = unique("many");
    let escaped = prefix.replace('.', "\\.");
    let limits: [(&str, PolicyValue); 1] = [("max-length", int(1))];
    for i in 0..N {
        let pattern = format!("^{escaped}\\.q{i}$");
        let mut s = spec(&pattern, ApplyTo::Queues, &limits);
        s.priority = (i % 7) as i64;
        set(&admin, PolicyKind::User, &format!("p{i}"), s).await;
    }
    for i in 0..N {
        declare(&ch, &format!("{prefix}.q{i}"), Default::default()).await;
    }
    // A catastrophic-backtracking shape is linear in this regex engine.
    let evil = spec("^(a+)+$", ApplyTo::All, &[("max-length", int(1))]);
    set(&admin, PolicyKind::User, "evil", evil).await;
    for i in [0, N / 2, N - 1] {
        let q = format!("{prefix}.q{i}");
        for _ in 0..3 {
            lp::publish_confirmed(&ch, "", &q, b"m", Default::default()).await;
        }
        assert_eq!(ready(&admin, &q), 1);
        let listed = admin.queues().into_iter().find(|l| l.name == q).unwrap();
        assert_eq!(
            listed.policies.policy_name(),
            Some(format!("p{i}").as_str())
        );
    }
    b.stop().await;
}

/// A long queue shortened by a policy dead-letters everything over the
/// new limit, in steps (the queue's lock is never held for the whole
/// cut), and every message is accounted for.
#[both_runtimes]
async fn a_long_queue_is_shortened_in_steps_and_nothing_is_lost() {
    const N: u64 = 1_000;
    let b = broker().await;
    let Some(admin) = b.admin() else { return };
    let conn = lp::connect(&b).await;
    let ch = confirm_channel(&conn).await;
    let dlx = lp::exchange(&ch, "cut-dlx", lp::ExchangeKind::Fanout).await;
    let sink = lp::queue(&ch, "cut-sink").await;
    lp::bind(&ch, &sink, &dlx, "").await;
    let q = unique("cut");
    declare(&ch, &q, Default::default()).await;
    for i in 0..N {
        lp::publish(&ch, "", &q, i.to_string().as_bytes()).await;
    }
    assert!(
        lp::publish_confirmed(&ch, "", &q, b"last", Default::default())
            .await
            .is_ack()
    );
    let keys = [
        ("max-length", int(10)),
        ("dead-letter-exchange", text(&dlx)),
    ];
    set(
        &admin,
        PolicyKind::User,
        "cut",
        spec(&exactly(&q), ApplyTo::Queues, &keys),
    )
    .await;
    assert_eq!(ready(&admin, &q), 10);
    // Routing a long run of dead letters may finish in the background
    // (the stall budget): every one arrives.
    within("the dead letters", async {
        while ready(&admin, &sink) < N + 1 - 10 {
            tokio::time::sleep(std::time::Duration::from_millis(10)).await;
        }
    })
    .await;
    assert_eq!(ready(&admin, &sink), N + 1 - 10);
    let first = lp::get(&ch, &sink, true).await.expect("a dead letter");
    assert_eq!(first.delivery.data, b"0", "the head went first");
    b.stop().await;
}
