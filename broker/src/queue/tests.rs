//! Unit tests of queues through the core harness (`crate::testkit`).

use super::{Consumer, Overflow, QueueArgs, StartAt};
use crate::exchange::ExchangeKind;
use crate::outbox::OUTBOX_CAPACITY;
use crate::testkit::{message, s, table, Consume, Harness};
use leveret_protocol::{BasicProperties, FieldValue, ReplyCode};
use std::sync::Arc;
use std::time::{Duration, Instant};

/// On a multi-thread runtime several queues deliver to one channel at
/// once. Each delivery's tag must reach the outbox in tag order: a client
/// that acks `multiple` up to a tag it has seen would otherwise settle a
/// delivery it has not seen yet, and its later ack of that one gets a 406.
#[test]
fn delivery_tags_reach_the_outbox_in_order_from_several_threads() {
    const THREADS: usize = 6;
    const EACH: usize = 150_000;
    let harness = Harness::new();
    let mut channel = harness.channel();
    let queues: Vec<_> = (0..THREADS)
        .map(|i| harness.queue(&format!("q{i}"), &[]))
        .collect();
    for (i, queue) in queues.iter().enumerate() {
        let no_ack = Consume {
            no_ack: true,
            prefetch: 0,
        };
        channel.consume(queue, &format!("c{i}"), no_ack);
    }
    let body = message(&s(""), "k", "m", &BasicProperties::default());
    std::thread::scope(|scope| {
        for queue in &queues {
            let body = Arc::clone(&body);
            scope.spawn(move || {
                for _ in 0..EACH {
                    let (_, dead) = queue.publish(Arc::clone(&body));
                    assert!(dead.is_empty());
                }
            });
        }
        let deadline = Instant::now() + Duration::from_secs(60);
        let mut last = 0;
        while last < (THREADS * EACH) as u64 {
            let delivered = channel.drain();
            if delivered.is_empty() {
                assert!(Instant::now() < deadline, "stalled after tag {last}");
                std::thread::yield_now();
            }
            for delivery in delivered {
                assert_eq!(delivery.tag, last + 1, "tags out of order");
                last = delivery.tag;
            }
        }
    });
}

fn invalid(arguments: &[(&str, FieldValue)]) -> String {
    let error = QueueArgs::parse(&table(arguments), &s("q"), &s("/")).expect_err("refused");
    assert_eq!(error.code, ReplyCode::PreconditionFailed);
    error.text
}

#[test]
fn queue_arguments_are_checked_with_rabbitmq_texts() {
    assert_eq!(
        invalid(&[("x-message-ttl", FieldValue::I64(-1))]),
        "PRECONDITION_FAILED - invalid arg 'x-message-ttl' for queue 'q' in vhost '/': {value_negative,-1}"
    );
    assert!(invalid(&[("x-expires", FieldValue::I64(0))]).contains("{value_zero,0}"));
    assert!(
        invalid(&[("x-max-priority", FieldValue::I64(256))]).contains("{max_value_exceeded,256}")
    );
    assert!(
        invalid(&[("x-message-ttl", FieldValue::string("soon"))]).ends_with(
            "'x-message-ttl' for queue 'q' in vhost '/': \"expected integer, got longstr\""
        )
    );
    assert!(
        invalid(&[("x-single-active-consumer", FieldValue::string("yes"))])
            .ends_with("{unacceptable_type,longstr}")
    );
    assert!(invalid(&[("x-overflow", FieldValue::string("drop-tail"))]).contains("x-overflow"));
    assert!(
        invalid(&[("x-mqtt-shared-group", FieldValue::string("g"))]).ends_with(
            "'x-mqtt-shared-group' for queue 'q' in vhost '/': {unacceptable_type,longstr}"
        )
    );
    assert!(invalid(&[("x-mqtt-session", FieldValue::I64(1))])
        .ends_with("'x-mqtt-session' for queue 'q' in vhost '/': {unacceptable_type,long}"));
    for mark in [true, false] {
        for name in ["x-mqtt-shared-group", "x-mqtt-session"] {
            let marked = table(&[(name, FieldValue::Bool(mark))]);
            assert!(QueueArgs::parse(&marked, &s("q"), &s("/")).is_ok());
        }
    }
    assert!(
        invalid(&[("x-dead-letter-routing-key", FieldValue::string("k"))])
            .ends_with("routing_key_but_no_dlx_defined")
    );
    let args = QueueArgs::parse(
        &table(&[
            ("x-max-length", FieldValue::I64(3)),
            ("x-overflow", FieldValue::string("reject-publish-dlx")),
            ("x-unknown", FieldValue::Bool(true)),
        ]),
        &s("q"),
        &s("/"),
    )
    .expect("valid");
    assert_eq!(args.max_length, Some(3));
    assert_eq!(args.overflow, Overflow::RejectPublishDlx);
}

#[test]
fn purge_drops_ready_messages_and_leaves_unacked_ones() {
    let h = Harness::new();
    let q = h.queue("q", &[]);
    for body in ["a", "b", "c"] {
        h.publish("", "q", body);
    }
    let mut ch = h.channel();
    assert!(ch.get(&q, false));
    assert_eq!(q.purge(), 2);
    assert_eq!(q.message_count(), 0);
    let got = ch.drain();
    // The unacked one comes back when rejected with requeue.
    ch.nack(got[0].tag, false, true);
    assert_eq!(q.message_count(), 1);
}

#[test]
fn a_deleted_queue_hands_back_its_consumers_and_takes_nothing_more() {
    let h = Harness::new();
    let q = h.queue("q", &[]);
    h.publish("", "q", "a");
    let ch = h.channel();
    let one_at_a_time = Consume {
        no_ack: false,
        prefetch: 1,
    };
    ch.consume(&q, "c", one_at_a_time);
    h.publish("", "q", "b");
    h.publish("", "q", "c");
    let deleted = h.vhost.delete_queue(&q);
    assert!(q.is_deleted());
    // One delivered (unacked), two ready.
    assert_eq!(deleted.notify(), 2);
    assert!(h.vhost.queue(&s("q")).is_none());
    let (_, dead) = q.publish(message(&s(""), "q", "late", &BasicProperties::default()));
    assert!(dead.is_empty());
    assert_eq!(q.message_count(), 0);
    assert_eq!(q.consumer_count(), 0);
}

#[test]
fn an_exclusive_consumer_keeps_others_out() {
    let h = Harness::new();
    let q = h.queue("q", &[]);
    let ch = h.channel();
    let exclusive = Arc::new(Consumer {
        tag: s("only"),
        channel: Arc::clone(&ch.link),
        no_ack: true,
        exclusive: true,
        prefetch: 0,
        priority: 0,
        wants_position: false,
        in_flight: Default::default(),
        active: Default::default(),
    });
    let dead = q
        .add_consumer(Arc::clone(&exclusive))
        .expect("first consumer");
    assert!(dead.is_empty());
    let second = Arc::new(Consumer {
        tag: s("second"),
        exclusive: false,
        channel: Arc::clone(&ch.link),
        no_ack: true,
        prefetch: 0,
        priority: 0,
        wants_position: false,
        in_flight: Default::default(),
        active: Default::default(),
    });
    let refused = q.add_consumer(second).expect_err("in exclusive use");
    assert_eq!(refused.code, ReplyCode::AccessRefused);
    assert!(refused.text.contains("in exclusive use"));
    assert!(!q.remove_consumer(&exclusive), "not auto-delete");
}

/// A queue found to go (x-expires run out, or auto-delete's last consumer
/// gone), its deletion to follow, or deleted, takes no new consumer: 404,
/// as RabbitMQ answers a consume on a queue that is gone (groups review
/// NIT 10), instead of a consumer that then goes with the queue.
#[test]
fn a_queue_that_is_going_or_deleted_takes_no_new_consumer() {
    let h = Harness::new();
    let ch = h.channel();
    let consumer = |tag: &str| {
        Arc::new(Consumer {
            tag: s(tag),
            channel: Arc::clone(&ch.link),
            no_ack: true,
            exclusive: false,
            prefetch: 0,
            priority: 0,
            wants_position: false,
            in_flight: Default::default(),
            active: Default::default(),
        })
    };
    let refused = |queue: &Arc<super::Queue>| {
        let refused = queue.add_consumer(consumer("late")).expect_err("refused");
        assert_eq!(refused.code, ReplyCode::NotFound);
        let name = &queue.name;
        assert_eq!(
            refused.text,
            format!("NOT_FOUND - no queue '{name}' in vhost '/'")
        );
        assert_eq!(queue.consumer_count(), 0);
    };
    let expiring = h.queue("expiring", &[("x-expires", FieldValue::I64(1_000))]);
    assert!(expiring.take_expired(Instant::now() + Duration::from_secs(2)));
    refused(&expiring);
    let declaration = crate::vhost::QueueDeclaration {
        name: s("auto"),
        passive: false,
        server_named: false,
        max_queues: None,
        options: super::QueueOptions {
            durable: false,
            exclusive_owner: None,
            auto_delete: true,
            arguments: Default::default(),
        },
    };
    let (auto, _) = h.vhost.declare_queue(declaration, 0).expect("declared");
    let only = consumer("only");
    let dead = auto.add_consumer(Arc::clone(&only)).expect("consumes");
    assert!(dead.is_empty());
    assert!(auto.remove_consumer(&only), "auto-deleted");
    refused(&auto);
    let deleted = h.queue("deleted", &[]);
    h.vhost.delete_queue(&deleted).notify();
    refused(&deleted);
}

/// queue.delete's if-unused decides and marks in one lock hold: refused,
/// marking nothing, while the queue has a consumer or (MQTT) a member's
/// join is pending; once it is taken, neither a member's join nor a
/// consumer (404) gets in before the delete that follows (review RISK 3:
/// checked, then deleted after an await, a member could join between).
#[test]
fn an_if_unused_delete_takes_the_queue_so_nothing_comes_before_it_goes() {
    let h = Harness::new();
    let ch = h.channel();
    let q = h.queue("if-unused", &[]);
    let first = ch.consume(&q, "first", Consume::default());
    assert!(!q.take_unused(), "a consumer is use");
    assert!(!q.remove_consumer(&first), "not auto-delete");
    #[cfg(feature = "mqtt")]
    {
        assert!(q.join(false), "a member joins");
        assert!(!q.take_unused(), "a pending join is use");
        assert!(!q.leave_join(), "not auto-delete");
    }
    // Refused, it marked nothing: the queue is still consumed.
    let second = ch.consume(&q, "second", Consume::default());
    assert!(!q.remove_consumer(&second));
    assert!(q.take_unused(), "unused");
    #[cfg(feature = "mqtt")]
    assert!(!q.join(false), "no member joins a queue taken for deletion");
    let late = Arc::new(Consumer {
        tag: s("late"),
        channel: Arc::clone(&ch.link),
        no_ack: true,
        exclusive: false,
        prefetch: 0,
        priority: 0,
        wants_position: false,
        in_flight: Default::default(),
        active: Default::default(),
    });
    let refused = q.add_consumer(late).expect_err("no consumer either");
    assert_eq!(refused.code, ReplyCode::NotFound);
}

/// A stream's if-unused delete takes it as a classic queue's does
/// (review-final-fixes RISK 3: a stream was only counted, so a consume
/// between the decision and the delete got consume-ok, then a reader the
/// delete had already drained, never cancelled, on a destroyed log):
/// refused while it has a reader, marking nothing; once taken, a consume
/// (basic.consume's stream path or `add_consumer`'s) gets 404, as it does
/// once the stream is deleted.
#[test]
fn an_if_unused_delete_takes_a_stream_so_no_consumer_comes_before_it_goes() {
    let dir = std::env::temp_dir().join(format!("leveret-if-unused-stream-{}", std::process::id()));
    let h = Harness::durable();
    h.persistence
        .as_ref()
        .expect("a store")
        .set_stream_root(dir.clone(), false);
    let stream = [("x-queue-type", FieldValue::string("stream"))];
    let q = h.declare_queue("s", true, &stream);
    let ch = h.channel();
    let reader = |tag| {
        Arc::new(Consumer {
            tag: s(tag),
            channel: Arc::clone(&ch.link),
            no_ack: false,
            exclusive: false,
            prefetch: 10,
            priority: 0,
            wants_position: false,
            in_flight: Default::default(),
            active: Default::default(),
        })
    };
    let first = reader("first");
    q.add_stream_consumer(Arc::clone(&first), StartAt::First)
        .expect("reads");
    assert!(!q.take_unused(), "a reader is use");
    assert!(!q.remove_consumer(&first), "a stream is never auto-deleted");
    // Refused, it marked nothing: the stream is still consumed.
    let second = reader("second");
    q.add_stream_consumer(Arc::clone(&second), StartAt::Next)
        .expect("still consumable");
    assert!(!q.remove_consumer(&second));
    assert!(q.take_unused(), "unused");
    let gone = "NOT_FOUND - no queue 's' in vhost '/'";
    let refused = q
        .add_stream_consumer(reader("late"), StartAt::Next)
        .expect_err("no reader comes before the delete");
    assert_eq!(
        (refused.code, refused.text.as_str()),
        (ReplyCode::NotFound, gone)
    );
    let refused = q.add_consumer(reader("late")).expect_err("nor a consumer");
    assert_eq!(
        (refused.code, refused.text.as_str()),
        (ReplyCode::NotFound, gone)
    );
    let deleted = h.vhost.delete_queue(&q);
    assert!(deleted.consumers.is_empty(), "no reader to cancel");
    let refused = q
        .add_stream_consumer(reader("after"), StartAt::First)
        .expect_err("deleted");
    assert_eq!(refused.code, ReplyCode::NotFound);
    let _ = std::fs::remove_dir_all(&dir);
}

/// A writer that finds room again dispatches, and may find expired
/// messages at the head; it cannot route them, so they wait in the queue
/// for the next sweep instead of being lost.
#[test]
fn dead_letters_found_by_a_writer_wait_for_the_sweep() {
    let h = Harness::new();
    h.exchange("dlx", ExchangeKind::Fanout);
    let q = h.queue(
        "q",
        &[("x-dead-letter-exchange", FieldValue::string("dlx"))],
    );
    let dead = h.queue("dead", &[]);
    h.bind(&dead, "dlx", "");
    let mut ch = h.channel();
    ch.consume(
        &q,
        "c",
        Consume {
            no_ack: true,
            prefetch: 0,
        },
    );
    for _ in 0..OUTBOX_CAPACITY {
        h.publish("", "q", "fill");
    }
    // The outbox is full: this one stays in the queue, and expires there.
    let expiring = BasicProperties {
        expiration: Some(s("0")),
        ..Default::default()
    };
    h.publish_with("", "q", "expired", expiring);
    assert_eq!(q.message_count(), 1);
    // Draining wakes the queue; its dispatch finds the message expired.
    assert_eq!(ch.drain().len(), OUTBOX_CAPACITY);
    assert_eq!(q.message_count(), 0);
    assert_eq!(dead.message_count(), 0, "not routed by the writer");
    h.sweep_at(Instant::now());
    assert_eq!(dead.message_count(), 1);
}

/// A consumer of `ch` with `priority` and `prefetch`, registered on `queue`
/// and active at once.
fn consumer_with(
    ch: &crate::testkit::FakeChannel,
    queue: &Arc<super::Queue>,
    tag: &str,
    priority: i64,
    prefetch: u32,
) -> Arc<Consumer> {
    let consumer = Arc::new(Consumer {
        tag: s(tag),
        channel: Arc::clone(&ch.link),
        no_ack: false,
        exclusive: false,
        prefetch,
        priority,
        wants_position: false,
        in_flight: Default::default(),
        active: Default::default(),
    });
    assert!(queue
        .add_consumer(Arc::clone(&consumer))
        .expect("consume")
        .is_empty());
    consumer.activate();
    assert!(queue.dispatch().is_empty());
    consumer
}

/// Many consumers with distinct priorities, each with room for one
/// delivery: every message goes to the highest one with room, and
/// choosing costs a bounded number of looks per message, not a scan of
/// the blocked consumers above for each (that would be 80,000 looks here).
#[test]
fn distinct_priorities_cost_bounded_looks_per_message() {
    const CONSUMERS: i64 = 400;
    const MESSAGES: usize = 1200;
    let h = Harness::new();
    let q = h.queue("q", &[]);
    let mut ch = h.channel();
    for priority in 0..CONSUMERS {
        consumer_with(&ch, &q, &format!("p{priority}"), priority, 1);
    }
    q.lock().consumers.examined = 0;
    for _ in 0..MESSAGES {
        h.publish("", "q", "m");
    }
    let delivered = ch.drain();
    let order: Vec<String> = delivered.iter().map(|d| d.consumer.clone()).collect();
    let expected: Vec<String> = (0..CONSUMERS).rev().map(|p| format!("p{p}")).collect();
    assert_eq!(
        order, expected,
        "highest priority with room first, one each"
    );
    assert_eq!(q.message_count() as usize, MESSAGES - CONSUMERS as usize);
    let examined = q.lock().consumers.examined;
    assert!(
        examined <= 2 * (CONSUMERS as u64 + MESSAGES as u64),
        "{examined} looks for {MESSAGES} messages and {CONSUMERS} consumers"
    );
    // Room comes back to one low consumer: it gets the next message.
    let low = delivered
        .iter()
        .find(|d| d.consumer == "p3")
        .expect("p3 got one");
    ch.ack(low.tag, false);
    let next = ch.drain();
    assert_eq!(next.len(), 1);
    assert_eq!(next[0].consumer, "p3");
}

/// With `x-single-active-consumer` only the first consumer gets messages;
/// when it goes the next registered one takes over (delivered to once the
/// first holds nothing unacked), and the listing says which is active.
#[test]
fn a_single_active_consumer_gets_everything_until_it_goes() {
    let h = Harness::new();
    let q = h.queue("q", &[("x-single-active-consumer", FieldValue::Bool(true))]);
    let mut ch = h.channel();
    let first = consumer_with(&ch, &q, "first", 0, 0);
    let _second = consumer_with(&ch, &q, "second", 0, 0);
    let _third = consumer_with(&ch, &q, "third", 0, 0);
    for _ in 0..10 {
        h.publish("", "q", "m");
    }
    let got = ch.drain();
    assert_eq!(got.len(), 10);
    assert!(got.iter().all(|d| d.consumer == "first"));
    let active: Vec<(String, bool)> = q
        .consumers_snapshot()
        .iter()
        .map(|(c, active)| (c.tag.to_string(), *active))
        .collect();
    assert_eq!(
        active,
        [
            ("first".into(), true),
            ("second".into(), false),
            ("third".into(), false)
        ]
    );
    // The first goes holding its ten unacked: the second is active at
    // once, and gets messages once those are settled.
    assert!(!q.remove_consumer(&first));
    assert!(q.dispatch().is_empty());
    for _ in 0..4 {
        h.publish("", "q", "m");
    }
    assert!(ch.drain().is_empty(), "nothing while the first holds some");
    assert!(q
        .consumers_snapshot()
        .iter()
        .any(|(c, active)| *active && c.tag == "second"));
    ch.ack(got.last().expect("ten").tag, true);
    let got = ch.drain();
    assert_eq!(got.len(), 4);
    assert!(got.iter().all(|d| d.consumer == "second"));
}

/// A channel's `global` prefetch is shared between its queues, and a unit
/// freed by one queue's ack dispatches only that queue: a publish to the
/// other must still find the consumer that now has room (it is never
/// skipped as blocked).
#[test]
fn a_global_prefetch_freed_elsewhere_is_seen_by_the_next_publish() {
    let h = Harness::new();
    let q1 = h.queue("q1", &[]);
    let q2 = h.queue("q2", &[]);
    let mut ch = h.channel();
    ch.link
        .global_prefetch
        .store(1, std::sync::atomic::Ordering::Relaxed);
    consumer_with(&ch, &q1, "c1", 0, 0);
    consumer_with(&ch, &q2, "c2", 0, 0);
    h.publish("", "q2", "held");
    let held = ch.drain();
    assert_eq!(held.len(), 1);
    h.publish("", "q1", "first");
    assert!(ch.drain().is_empty(), "the channel's one unit is taken");
    // Acked through q2: only q2 dispatches.
    ch.ack(held[0].tag, false);
    h.publish("", "q1", "second");
    let got: Vec<String> = ch.drain().into_iter().map(|d| d.body).collect();
    assert_eq!(got, ["first"]);
}
