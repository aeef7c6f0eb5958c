//! Unit tests of a vhost driven through the core harness
//! (`crate::testkit`): declaring, binding, routing, publishing, consuming,
//! acks and requeues, TTL and max-length with dead-lettering, and the
//! dead-letter cycle rule and budget. No sockets, no clients.

use super::deadletter::CASCADE_LIMIT;
use crate::exchange::ExchangeKind;
use crate::queue::Enqueued;
use crate::testkit::{death, s, Consume, Harness};
use leveret_protocol::{BasicProperties, FieldValue};
use std::sync::Arc;
use std::time::{Duration, Instant};

const MANUAL: Consume = Consume {
    no_ack: false,
    prefetch: 0,
};
const NO_ACK: Consume = Consume {
    no_ack: true,
    prefetch: 0,
};

fn bodies(delivered: &[crate::testkit::Delivered]) -> Vec<&str> {
    delivered.iter().map(|d| d.body.as_str()).collect()
}

fn text(value: &str) -> FieldValue {
    FieldValue::string(value)
}

#[test]
fn the_default_exchange_routes_by_queue_name() {
    let h = Harness::new();
    let q = h.queue("orders", &[]);
    assert_eq!(
        h.publish("", "orders", "one"),
        vec![Enqueued::Accepted { sync: 0 }]
    );
    assert!(h.publish("", "nobody", "lost").is_empty());
    assert_eq!(q.message_count(), 1);
}

/// A channel remembers the queue its last default-exchange publish
/// reached; once that queue is deleted (and declared again), the same name
/// finds nothing (then the new queue), never the deleted one.
#[test]
fn a_remembered_default_route_follows_deletes_and_redeclares() {
    let h = Harness::new();
    let old = h.queue("orders", &[]);
    let mut last = None;
    let found = h.vhost.queue_remembered(&s("orders"), &mut last);
    assert!(found.is_some_and(|q| Arc::ptr_eq(&q, &old)));
    let again = h.vhost.queue_remembered(&s("orders"), &mut last);
    assert!(again.is_some_and(|q| Arc::ptr_eq(&q, &old)));
    let _no_consumers = h.vhost.delete_queue(&old);
    assert!(h.vhost.queue_remembered(&s("orders"), &mut last).is_none());
    let new = h.queue("orders", &[]);
    let found = h.vhost.queue_remembered(&s("orders"), &mut last);
    assert!(found.is_some_and(|q| Arc::ptr_eq(&q, &new)));
    assert!(h.vhost.queue_remembered(&s("other"), &mut last).is_none());
    h.queue("other", &[]);
    assert!(h.vhost.queue_remembered(&s("other"), &mut last).is_some());
}

#[test]
fn direct_and_topic_exchanges_route_by_their_bindings() {
    let h = Harness::new();
    h.exchange("jobs", ExchangeKind::Direct);
    h.exchange("logs", ExchangeKind::Topic);
    let red = h.queue("red", &[]);
    let blue = h.queue("blue", &[]);
    let errors = h.queue("errors", &[]);
    h.bind(&red, "jobs", "red");
    h.bind(&blue, "jobs", "blue");
    h.bind(&errors, "logs", "*.error");
    h.bind(&errors, "logs", "kernel.#");
    h.publish("jobs", "red", "r");
    h.publish("jobs", "green", "g");
    h.publish("logs", "disk.error", "e1");
    h.publish("logs", "disk.info", "i");
    // Matching both bindings still delivers one copy.
    assert_eq!(h.publish("logs", "kernel.error", "e2").len(), 1);
    assert_eq!(red.message_count(), 1);
    assert_eq!(blue.message_count(), 0);
    assert_eq!(errors.message_count(), 2);
}

#[test]
fn a_consumer_gets_messages_in_order_within_its_prefetch() {
    let h = Harness::new();
    let q = h.queue("work", &[]);
    for body in ["a", "b", "c"] {
        h.publish("", "work", body);
    }
    let mut ch = h.channel();
    ch.consume(
        &q,
        "worker",
        Consume {
            no_ack: false,
            prefetch: 2,
        },
    );
    let first = ch.drain();
    assert_eq!(bodies(&first), ["a", "b"]);
    assert_eq!(first[0].tag, 1);
    assert_eq!(first[1].consumer, "worker");
    assert_eq!(q.message_count(), 1);
    ch.ack(first[0].tag, false);
    let next = ch.drain();
    assert_eq!(bodies(&next), ["c"]);
    assert_eq!(next[0].tag, 3);
    ch.ack(3, true);
    assert!(ch.drain().is_empty());
    assert_eq!(q.message_count(), 0);
}

#[test]
fn a_requeued_message_comes_back_first_and_redelivered() {
    let h = Harness::new();
    let q = h.queue("work", &[]);
    h.publish("", "work", "a");
    h.publish("", "work", "b");
    let mut ch = h.channel();
    ch.consume(
        &q,
        "worker",
        Consume {
            no_ack: false,
            prefetch: 1,
        },
    );
    let a = ch.drain();
    assert_eq!(bodies(&a), ["a"]);
    assert!(!a[0].redelivered);
    ch.nack(a[0].tag, false, true);
    let again = ch.drain();
    assert_eq!(bodies(&again), ["a"]);
    assert!(again[0].redelivered);
    ch.ack(again[0].tag, false);
    assert_eq!(bodies(&ch.drain()), ["b"]);
}

#[test]
fn basic_get_takes_the_head_and_counts_the_rest() {
    let h = Harness::new();
    let q = h.queue("q", &[]);
    let mut ch = h.channel();
    assert!(!ch.get(&q, false));
    h.publish("", "q", "a");
    h.publish("", "q", "b");
    assert!(ch.get(&q, false));
    assert!(ch.get(&q, true));
    let got = ch.drain();
    assert_eq!(bodies(&got), ["a", "b"]);
    assert_eq!((got[0].tag, got[1].tag), (1, 2));
    // Only the first (manual ack) waits for an ack.
    ch.ack(1, false);
    assert_eq!(q.message_count(), 0);
}

#[test]
fn expired_messages_are_dead_lettered_with_their_history() {
    let h = Harness::new();
    h.exchange("dlx", ExchangeKind::Fanout);
    let q = h.queue(
        "short-lived",
        &[
            ("x-message-ttl", FieldValue::I64(1_000)),
            ("x-dead-letter-exchange", text("dlx")),
        ],
    );
    let dead = h.queue("dead", &[]);
    h.bind(&dead, "dlx", "");
    h.publish("", "short-lived", "old");
    h.sweep_at(Instant::now());
    assert_eq!(q.message_count(), 1, "not expired yet");
    h.sweep_at(Instant::now() + Duration::from_secs(2));
    assert_eq!(q.message_count(), 0);
    let mut ch = h.channel();
    ch.consume(&dead, "c", NO_ACK);
    let got = ch.drain();
    assert_eq!(bodies(&got), ["old"]);
    assert_eq!(got[0].deaths(), [death("short-lived", "expired", 1)]);
    assert_eq!(
        got[0].header_text("x-first-death-reason").as_deref(),
        Some("expired")
    );
}

#[test]
fn max_length_drops_the_head_to_the_dead_letter_exchange() {
    let h = Harness::new();
    h.exchange("dlx", ExchangeKind::Fanout);
    let q = h.queue(
        "bounded",
        &[
            ("x-max-length", FieldValue::I64(2)),
            ("x-dead-letter-exchange", text("dlx")),
        ],
    );
    let dead = h.queue("dead", &[]);
    h.bind(&dead, "dlx", "");
    for body in ["1", "2", "3", "4"] {
        h.publish("", "bounded", body);
    }
    assert_eq!(q.message_count(), 2);
    let mut ch = h.channel();
    ch.consume(&dead, "c", NO_ACK);
    let got = ch.drain();
    assert_eq!(bodies(&got), ["1", "2"]);
    assert_eq!(got[0].deaths(), [death("bounded", "maxlen", 1)]);
    ch.consume(&q, "d", NO_ACK);
    assert_eq!(bodies(&ch.drain()), ["3", "4"]);
}

#[test]
fn reject_publish_refuses_and_reject_publish_dlx_also_dead_letters() {
    let h = Harness::new();
    h.exchange("dlx", ExchangeKind::Fanout);
    let dead = h.queue("dead", &[]);
    h.bind(&dead, "dlx", "");
    h.queue(
        "strict",
        &[
            ("x-max-length", FieldValue::I64(1)),
            ("x-overflow", text("reject-publish")),
            ("x-dead-letter-exchange", text("dlx")),
        ],
    );
    h.queue(
        "strict-dlx",
        &[
            ("x-max-length", FieldValue::I64(1)),
            ("x-overflow", text("reject-publish-dlx")),
            ("x-dead-letter-exchange", text("dlx")),
        ],
    );
    for queue in ["strict", "strict-dlx"] {
        assert_eq!(
            h.publish("", queue, "kept"),
            [Enqueued::Accepted { sync: 0 }]
        );
        assert_eq!(
            h.publish("", queue, "refused"),
            [Enqueued::Refused { sync: 0 }]
        );
    }
    let mut ch = h.channel();
    ch.consume(&dead, "c", NO_ACK);
    let got = ch.drain();
    assert_eq!(
        bodies(&got),
        ["refused"],
        "only reject-publish-dlx dead-letters"
    );
    assert_eq!(got[0].deaths(), [death("strict-dlx", "maxlen", 1)]);
}

#[test]
fn rejected_messages_are_dead_lettered_with_a_routing_key_override() {
    let h = Harness::new();
    h.exchange("dlx", ExchangeKind::Direct);
    let q = h.queue(
        "work",
        &[
            ("x-dead-letter-exchange", text("dlx")),
            ("x-dead-letter-routing-key", text("failed")),
        ],
    );
    let failed = h.queue("failed", &[]);
    h.bind(&failed, "dlx", "failed");
    h.publish("", "work", "bad");
    let mut ch = h.channel();
    ch.consume(&q, "worker", MANUAL);
    let got = ch.drain();
    ch.nack(got[0].tag, false, false);
    assert_eq!(q.message_count(), 0);
    assert_eq!(failed.message_count(), 1);
}

#[test]
fn an_unused_queue_expires() {
    let h = Harness::new();
    h.queue("temp", &[("x-expires", FieldValue::I64(1_000))]);
    h.sweep_at(Instant::now());
    assert!(h.vhost.queue(&s("temp")).is_some());
    h.sweep_at(Instant::now() + Duration::from_secs(2));
    assert!(h.vhost.queue(&s("temp")).is_none());
}

/// An expiry set after the declaration (an MQTT session's, changed at
/// DISCONNECT) is acted on, listed and compared on redeclaration in place
/// of the declared one; a policy's stricter expiry still wins.
#[cfg(feature = "mqtt")]
#[test]
fn an_expiry_set_later_replaces_the_declared_one() {
    let h = Harness::new();
    let q = h.queue("session", &[("x-expires", FieldValue::I64(1_000))]);
    assert!(h.vhost.set_queue_expires(&q, Some(3_600_000), None));
    assert_eq!(
        q.arguments().get("x-expires"),
        Some(&FieldValue::I64(3_600_000))
    );
    h.sweep_at(Instant::now() + Duration::from_secs(2));
    assert!(
        h.vhost.queue(&s("session")).is_some(),
        "the new expiry is an hour"
    );
    assert!(h.vhost.set_queue_expires(&q, None, None));
    assert!(q.arguments().get("x-expires").is_none());
    h.sweep_at(Instant::now() + Duration::from_secs(7_200));
    assert!(h.vhost.queue(&s("session")).is_some(), "no expiry at all");
    assert!(h.vhost.set_queue_expires(&q, Some(1_000), None));
    h.sweep_at(Instant::now() + Duration::from_secs(2));
    assert!(h.vhost.queue(&s("session")).is_none());
    // A deleted queue is not given one.
    assert!(!h.vhost.set_queue_expires(&q, Some(5_000), None));
}

#[test]
fn higher_priorities_are_delivered_first() {
    let h = Harness::new();
    let q = h.queue("prio", &[("x-max-priority", FieldValue::I64(5))]);
    for (body, priority) in [("low", 1), ("high", 9), ("mid", 3)] {
        let properties = BasicProperties {
            priority: Some(priority),
            ..Default::default()
        };
        h.publish_with("", "prio", body, properties);
    }
    let mut ch = h.channel();
    ch.consume(&q, "c", NO_ACK);
    // 9 is capped at the queue's maximum, 5, and still goes first.
    assert_eq!(bodies(&ch.drain()), ["high", "mid", "low"]);
}

// --- dead-letter cycles (RabbitMQ's rule) and the cascade budget ---

/// A queue dead-lettering into a fanout exchange bound to itself and to a
/// witness queue, which the returned channel consumes.
fn self_cycle(h: &Harness, arguments: &[(&str, FieldValue)]) -> crate::testkit::FakeChannel {
    h.exchange("dlx", ExchangeKind::Fanout);
    let mut arguments = arguments.to_vec();
    arguments.push(("x-dead-letter-exchange", text("dlx")));
    let q = h.queue("cycling", &arguments);
    let witness = h.queue("witness", &[]);
    h.bind(&q, "dlx", "");
    h.bind(&witness, "dlx", "");
    let ch = h.channel();
    ch.consume(&witness, "w", NO_ACK);
    ch
}

#[test]
fn max_length_zero_dead_lettering_to_itself_through_the_default_exchange_ends() {
    let h = Harness::new();
    // Dead letters keep their routing key, the queue's own name, and the
    // default exchange routes them straight back.
    let q = h.queue(
        "self",
        &[
            ("x-max-length", FieldValue::I64(0)),
            ("x-dead-letter-exchange", text("")),
        ],
    );
    h.publish("", "self", "loop");
    assert_eq!(q.message_count(), 0);
}

#[test]
fn max_length_zero_self_cycle_dead_letters_once() {
    let h = Harness::new();
    let mut witness = self_cycle(&h, &[("x-max-length", FieldValue::I64(0))]);
    h.publish("", "cycling", "loop");
    let got = witness.drain();
    assert_eq!(bodies(&got), ["loop"]);
    assert_eq!(got[0].deaths(), [death("cycling", "maxlen", 1)]);
    assert_eq!(h.vhost.queue(&s("cycling")).unwrap().message_count(), 0);
}

#[test]
fn ttl_zero_self_cycle_dead_letters_once() {
    let h = Harness::new();
    let mut witness = self_cycle(&h, &[("x-message-ttl", FieldValue::I64(0))]);
    h.publish("", "cycling", "loop");
    let later = Instant::now() + Duration::from_secs(1);
    h.sweep_at(later);
    h.sweep_at(later + Duration::from_secs(1));
    let got = witness.drain();
    assert_eq!(bodies(&got), ["loop"]);
    assert_eq!(got[0].deaths(), [death("cycling", "expired", 1)]);
    assert_eq!(h.vhost.queue(&s("cycling")).unwrap().message_count(), 0);
}

#[test]
fn a_cycle_through_two_queues_and_two_exchanges_is_broken() {
    let h = Harness::new();
    h.exchange("to-second", ExchangeKind::Fanout);
    h.exchange("to-first", ExchangeKind::Fanout);
    let first = h.queue(
        "first",
        &[
            ("x-max-length", FieldValue::I64(0)),
            ("x-dead-letter-exchange", text("to-second")),
        ],
    );
    let second = h.queue(
        "second",
        &[
            ("x-max-length", FieldValue::I64(0)),
            ("x-dead-letter-exchange", text("to-first")),
        ],
    );
    let witness = h.queue("witness", &[]);
    h.bind(&second, "to-second", "");
    h.bind(&first, "to-first", "");
    h.bind(&witness, "to-first", "");
    let mut ch = h.channel();
    ch.consume(&witness, "w", NO_ACK);
    h.publish("", "first", "round");
    let got = ch.drain();
    assert_eq!(bodies(&got), ["round"]);
    assert_eq!(
        got[0].deaths(),
        [death("second", "maxlen", 1), death("first", "maxlen", 1)]
    );
    assert_eq!(first.message_count() + second.message_count(), 0);
}

#[test]
fn a_cycle_with_a_rejection_continues_and_counts_each_death() {
    let h = Harness::new();
    h.exchange("to-retry", ExchangeKind::Fanout);
    h.exchange("to-work", ExchangeKind::Fanout);
    let work = h.queue("work", &[("x-dead-letter-exchange", text("to-retry"))]);
    let retry = h.queue(
        "retry",
        &[
            ("x-message-ttl", FieldValue::I64(0)),
            ("x-dead-letter-exchange", text("to-work")),
        ],
    );
    h.bind(&retry, "to-retry", "");
    h.bind(&work, "to-work", "");
    let mut ch = h.channel();
    ch.consume(&work, "worker", MANUAL);
    h.publish("", "work", "job");
    let mut delivery = ch.drain().remove(0);
    let mut now = Instant::now();
    for round in 1..=3 {
        ch.nack(delivery.tag, false, false);
        now += Duration::from_secs(1);
        h.sweep_at(now);
        delivery = ch.drain().remove(0);
        assert_eq!(
            delivery.deaths(),
            [
                death("retry", "expired", round),
                death("work", "rejected", round)
            ]
        );
    }
}

#[test]
fn dead_letters_multiplying_through_a_fanout_stop_at_the_budget() {
    // Every queue is full at once and dead-letters into the fanout it is
    // bound to: each dead letter reaches all the other queues, which
    // dead-letter it again. Without a bound the copies grow like the
    // factorial of the number of queues.
    const QUEUES: usize = 10;
    let h = Harness::new();
    h.exchange("storm", ExchangeKind::Fanout);
    for i in 0..QUEUES {
        let q = h.queue(
            &format!("q{i}"),
            &[
                ("x-max-length", FieldValue::I64(0)),
                ("x-dead-letter-exchange", text("storm")),
            ],
        );
        h.bind(&q, "storm", "");
    }
    let witness = h.queue("witness", &[]);
    h.bind(&witness, "storm", "");
    h.publish("storm", "", "spark");
    // The publish itself reaches the witness once; each queue's dead
    // letter once more, plus at most the budget of letters it causes.
    let bound = 1 + QUEUES * (1 + CASCADE_LIMIT);
    let copies = witness.message_count() as usize;
    assert!(copies > QUEUES, "the dead letters were routed ({copies})");
    assert!(copies <= bound, "{copies} copies, more than {bound}");
    // And the vhost still serves.
    let q = h.queue("after", &[]);
    h.publish("", "after", "ok");
    assert_eq!(q.message_count(), 1);
}

#[tokio::test]
async fn durable_queues_get_a_store_id_and_reach_the_disk() {
    let h = Harness::durable();
    let durable = h.declare_queue("kept", true, &[]);
    let transient = h.declare_queue("gone", false, &[]);
    assert!(durable.store_id().is_some());
    assert!(transient.store_id().is_none());
    let persistence = h.persistence.as_ref().expect("a persister");
    assert!(persistence.sync().await);
}

/// Found by the broker fuzzer (LeakSanitizer): two exchanges bound to each
/// other kept each other alive after their vhost was gone.
#[test]
fn a_cycle_of_exchange_bindings_is_freed_with_its_vhost() {
    let h = Harness::new();
    h.exchange("a", ExchangeKind::Fanout);
    h.exchange("b", ExchangeKind::Fanout);
    for (destination, source) in [("a", "b"), ("b", "a"), ("a", "a")] {
        h.vhost
            .bind_exchange(
                &s(destination),
                &s(source),
                s(""),
                leveret_protocol::FieldTable::new(),
                crate::vhost::BindingChange::Bind,
            )
            .expect("exchange.bind");
    }
    let a = std::sync::Arc::downgrade(&h.vhost.exchange(&s("a")).expect("a"));
    let b = std::sync::Arc::downgrade(&h.vhost.exchange(&s("b")).expect("b"));
    drop(h);
    assert!(a.upgrade().is_none(), "exchange a leaked");
    assert!(b.upgrade().is_none(), "exchange b leaked");
}

/// Policies put in force as a batch (an import, a start) cost work that
/// grows with policies plus queues: one ranking of the whole set and one
/// look-up per queue, which the prefix index keeps to a match or two —
/// where the same policies one change at a time rank the set once per
/// change (N²/2 policies ranked in all) and visit every queue per change.
#[test]
fn a_batch_of_policies_costs_work_linear_in_policies_and_queues() {
    use crate::policy::{work, ApplyTo, Policy, PolicyKind, PolicySpec, PolicyValue};
    const POLICIES: usize = 400;
    const QUEUES: usize = 2_000;
    let harness = Harness::new();
    let queues: Vec<_> = (0..QUEUES)
        .map(|i| harness.queue(&format!("app{}.q{i}", i % POLICIES), &[]))
        .collect();
    for _ in 0..3 {
        harness.publish("", "app7.q7", "m");
    }
    let policy = |i: usize, max_length: i64| {
        Policy::new(
            PolicyKind::User,
            &format!("p{i}"),
            PolicySpec {
                pattern: format!("^app{i}\\."),
                apply_to: ApplyTo::Queues,
                priority: 0,
                definition: vec![("max-length".into(), PolicyValue::Integer(max_length))],
            },
        )
        .expect("a policy")
    };
    work::take(&work::MATCHES);
    work::take(&work::RANKED);
    let batch: Vec<Policy> = (0..POLICIES).map(|i| policy(i, 1)).collect();
    let next = harness.vhost.policies().with_all(batch);
    harness.vhost.set_policies(next, None);
    let (matches, ranked) = (work::take(&work::MATCHES), work::take(&work::RANKED));
    assert_eq!(ranked, POLICIES as u64, "one ranking of the whole batch");
    // Each queue tries the policy filed under its own prefix `appN.`
    // (and `app1` is a prefix of `app1N.`: one more for some).
    assert!(
        matches <= 2 * QUEUES as u64,
        "{matches} matches for {QUEUES} queues"
    );
    for (i, queue) in queues.iter().enumerate() {
        let expected = format!("p{}", i % POLICIES);
        assert_eq!(queue.policies().policy_name(), Some(expected.as_str()));
    }
    assert_eq!(
        queues[7].message_count(),
        1,
        "a batch shortens a queue at once"
    );

    // A second batch replacing half of them and adding none ranks the
    // set once more, and the later of two same-named policies wins.
    let mut again: Vec<Policy> = (0..POLICIES / 2).map(|i| policy(i, 5)).collect();
    again.push(policy(3, 9));
    let next = harness.vhost.policies().with_all(again);
    harness.vhost.set_policies(next, None);
    assert_eq!(work::take(&work::RANKED), POLICIES as u64);
    assert!(work::take(&work::MATCHES) <= 2 * QUEUES as u64);
    let definition = |queue: &Arc<crate::queue::Queue>| {
        queue
            .policies()
            .policy
            .map(|p| format!("{:?}", p.spec.definition))
    };
    assert_eq!(
        definition(&queues[3]),
        Some(format!(
            "{:?}",
            vec![("max-length".to_owned(), PolicyValue::Integer(9))]
        ))
    );
    assert_eq!(
        harness.vhost.policies().all(PolicyKind::User).len(),
        POLICIES
    );

    // One change at a time ranks the whole set per change: N²/2.
    let fresh = Harness::new();
    let mut set = fresh.vhost.policies();
    work::take(&work::RANKED);
    for i in 0..POLICIES {
        let next = set.with(policy(i, 1));
        set = Arc::new(next);
    }
    assert_eq!(
        work::take(&work::RANKED),
        (POLICIES * (POLICIES + 1) / 2) as u64
    );
}

/// A declaration of queue `name` by connection `owner` (exclusive to it
/// if given), with `arguments`.
fn declaration(
    name: &str,
    durable: bool,
    owner: Option<u64>,
    arguments: &[(&str, FieldValue)],
) -> super::QueueDeclaration {
    super::QueueDeclaration {
        name: s(name),
        passive: false,
        server_named: false,
        max_queues: None,
        options: crate::queue::QueueOptions {
            durable,
            exclusive_owner: owner,
            auto_delete: !durable,
            arguments: crate::testkit::table(arguments),
        },
    }
}

#[test]
fn a_queue_declared_since_the_lookup_is_taken_as_it_is_unless_exclusive() {
    use leveret_protocol::ReplyCode;
    let h = Harness::new();
    // An MQTT member's lookup found no group queue; an AMQP client then
    // declared the name with arguments of its own.
    let minute = [("x-expires", FieldValue::I64(60_000))];
    let amqp = h.declare_queue("mqtt-shared-g/x", true, &minute);
    let mark = [("x-mqtt-shared-group", FieldValue::Bool(true))];
    let member = declaration("mqtt-shared-g/x", false, None, &mark);
    // Compared (queue.declare's first step, which members used to take
    // here), it is 406 inequivalent ...
    let refused = h
        .vhost
        .declare_queue(member.clone(), 0)
        .expect_err("compared");
    assert_eq!(refused.code, ReplyCode::PreconditionFailed);
    // ... the creation step takes it as it is.
    let (queue, created) = h.vhost.create_queue(member, 0).expect("taken as it is");
    assert!(!created && Arc::ptr_eq(&queue, &amqp));
    // Another connection's exclusive queue is refused there too (405).
    let exclusive = declaration("owned", false, Some(7), &[]);
    h.vhost
        .declare_queue(exclusive.clone(), 7)
        .expect("declared");
    let locked = h
        .vhost
        .create_queue(exclusive.clone(), 8)
        .expect_err("locked");
    assert_eq!(locked.code, ReplyCode::ResourceLocked);
    assert!(h.vhost.create_queue(exclusive, 7).is_ok(), "its owner's");
}

#[test]
fn a_marked_mqtt_group_queues_x_expires_is_not_compared_on_redeclaration() {
    use leveret_protocol::ReplyCode;
    let h = Harness::durable();
    let mark = ("x-mqtt-shared-group", FieldValue::Bool(true));
    // As the start-up reconcile leaves a group queue without persistent
    // members: 1 ms.
    let marked = h.declare_queue(
        "mqtt-shared-g/x",
        true,
        &[("x-expires", FieldValue::I64(1)), mark.clone()],
    );
    // A definitions file exported while the group was kept (an hour).
    let exported = [("x-expires", FieldValue::I64(3_600_000)), mark];
    let import = declaration("mqtt-shared-g/x", true, None, &exported);
    let (queue, created) = h.vhost.declare_queue(import, 0).expect("equivalent");
    assert!(!created && Arc::ptr_eq(&queue, &marked));
    assert_eq!(
        queue.arguments().get("x-expires"),
        Some(&FieldValue::I64(1)),
        "left as MQTT set it"
    );
    // Other arguments are still compared, and so is an unmarked queue's x-expires.
    let ttl = [
        ("x-message-ttl", FieldValue::I64(5)),
        ("x-mqtt-shared-group", FieldValue::Bool(true)),
    ];
    let other = h
        .vhost
        .declare_queue(declaration("mqtt-shared-g/x", true, None, &ttl), 0);
    assert_eq!(
        other.expect_err("inequivalent").code,
        ReplyCode::PreconditionFailed
    );
    h.declare_queue("plain", true, &[("x-expires", FieldValue::I64(1))]);
    let plain = declaration("plain", true, None, &[("x-expires", FieldValue::I64(2))]);
    let refused = h.vhost.declare_queue(plain, 0).expect_err("inequivalent");
    assert_eq!(refused.code, ReplyCode::PreconditionFailed);
}
