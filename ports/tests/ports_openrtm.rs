//! Ports configured from OpenRTM-aist AMQP connector properties behave as
//! OpenRTM-aist's AMQP data-port module does against a broker: its `bind`
//! semantics for each end, case-insensitive exchange types, and strings
//! in omniORB's default charset.

mod common;

use common::{unique, within};
use leveret_broker::{Broker, BrokerHandle};
use leveret_client::{Connection, FieldTable, QueueDeclareOptions};
use leveret_ports::{
    InPort, OutPort, PortProfile, PortRole, PortStatus, Time, TimedLong, TimedString,
};
use std::net::SocketAddr;

async fn leveret() -> (BrokerHandle, SocketAddr) {
    let handle = Broker::builder()
        .listen("127.0.0.1:0".parse().unwrap())
        .start()
        .await
        .expect("start an embedded Leveret");
    let addr = handle.local_addrs()[0];
    (handle, addr)
}

/// A profile for `role` read from `properties` plus the test broker's
/// address; no property may go unrecognised.
fn read(role: PortRole, addr: SocketAddr, properties: &[(&str, &str)]) -> PortProfile {
    let port = addr.port().to_string();
    let mut all = vec![("host", "127.0.0.1"), ("msport", port.as_str())];
    all.extend_from_slice(properties);
    let parsed = PortProfile::from_properties(role, all).expect("properties");
    assert!(parsed.unknown.is_empty(), "{:?}", parsed.unknown);
    parsed.profile
}

fn long(data: i32) -> TimedLong {
    TimedLong {
        tm: Time::now(),
        data,
    }
}

/// Whether `queue` exists (a passive declare).
async fn queue_exists(addr: SocketAddr, queue: &str) -> bool {
    let connection = Connection::connect(&format!("amqp://guest:guest@{addr}/%2f"))
        .await
        .unwrap();
    let channel = connection.open_channel().await.unwrap();
    let options = QueueDeclareOptions {
        passive: true,
        ..Default::default()
    };
    let exists = channel
        .queue_declare(queue, options, FieldTable::new())
        .await
        .is_ok();
    let _ = connection.close().await;
    exists
}

/// `bind=false` on an in-port still declares its queue (the module always
/// does), and does not bind it: before, the port consumed an undeclared
/// queue (404) and, without a queue name, bound anyway.
#[tokio::test]
async fn an_in_port_with_bind_false_declares_its_queue_and_does_not_bind() {
    let (_broker, addr) = leveret().await;
    let queue = unique("unbound");
    let exchange = unique("ex");
    let properties = [
        ("exname", exchange.as_str()),
        ("extype", "fanout"),
        ("qname", queue.as_str()),
        ("bind", "false"),
    ];
    let input = within(
        "in-port",
        InPort::<TimedLong>::connect(read(PortRole::InPort, addr, &properties)),
    )
    .await
    .expect("the queue is declared, so consuming it works");
    // The out-port declares the exchange (an out-port always does) and
    // publishes to it: no queue is bound, so the message is unroutable.
    let output = OutPort::<TimedLong>::connect(read(PortRole::OutPort, addr, &properties))
        .await
        .expect("out-port");
    assert_eq!(output.put(&long(1)).await, PortStatus::Ok);
    within("settled", output.flush()).await;
    let stats = output.stats();
    assert_eq!((stats.unroutable, stats.confirmed), (1, 0), "{stats:?}");
    // Through the default exchange, by the queue's name, it arrives.
    let direct = OutPort::<TimedLong>::connect(read(
        PortRole::OutPort,
        addr,
        &[("exname", ""), ("rkey", queue.as_str())],
    ))
    .await
    .expect("out-port");
    assert_eq!(direct.put(&long(2)).await, PortStatus::Ok);
    let sample = within("value", input.recv()).await.unwrap();
    assert_eq!(sample.value.data, 2);
}

/// An out-port given a `qname` but not `bind` (the module's default for
/// an out-port) neither declares nor binds it.
#[tokio::test]
async fn an_out_port_binds_only_when_told() {
    let (_broker, addr) = leveret().await;
    let queue = unique("outq");
    let exchange = unique("ex");
    let properties = [("exname", exchange.as_str()), ("qname", queue.as_str())];
    let output = OutPort::<TimedLong>::connect(read(PortRole::OutPort, addr, &properties))
        .await
        .expect("out-port");
    assert!(!queue_exists(addr, &queue).await, "declared without bind");
    drop(output);
    let mut bound = properties.to_vec();
    bound.push(("bind", "true"));
    let output = OutPort::<TimedLong>::connect(read(PortRole::OutPort, addr, &bound))
        .await
        .expect("out-port");
    assert!(queue_exists(addr, &queue).await);
    // Bound with the module's default keys (bkey = rkey = "test").
    assert_eq!(output.put(&long(1)).await, PortStatus::Ok);
    within("settled", output.flush()).await;
    assert_eq!(output.stats().confirmed, 1);
}

/// `extype=Fanout` and `DIRECT` are accepted as the module's types (they
/// were refused with 503 before).
#[tokio::test]
async fn exchange_types_in_any_case() {
    let (_broker, addr) = leveret().await;
    for extype in ["Fanout", "DIRECT", "AMQP::Topic"] {
        let queue = unique("case");
        let exchange = unique("ex");
        let properties = [
            ("exname", exchange.as_str()),
            ("extype", extype),
            ("qname", queue.as_str()),
            ("bkey", "pose"),
            ("rkey", "pose"),
        ];
        let input = InPort::<TimedLong>::connect(read(PortRole::InPort, addr, &properties))
            .await
            .unwrap_or_else(|e| panic!("extype {extype}: {e}"));
        let output = OutPort::<TimedLong>::connect(read(PortRole::OutPort, addr, &properties))
            .await
            .unwrap_or_else(|e| panic!("extype {extype}: {e}"));
        assert_eq!(output.put(&long(7)).await, PortStatus::Ok);
        let sample = within("value", input.recv()).await.unwrap();
        assert_eq!(sample.value.data, 7, "extype {extype}");
    }
}

/// Profiles from OpenRTM properties speak Latin-1 (omniORB's default, what
/// OpenRTM-aist sends) unless told otherwise: a Latin-1 `TimedString`
/// reaches such an in-port; one set to `utf-8` counts it as a decode
/// error.
#[tokio::test]
async fn latin1_strings_by_default_and_utf8_when_set() {
    let (_broker, addr) = leveret().await;
    let queue = unique("latin1");
    let base = [
        ("exname", ""),
        ("qname", queue.as_str()),
        ("rkey", queue.as_str()),
        ("dataport.serializer.cdr.endian", "big"),
    ];
    let input = InPort::<TimedString>::connect(read(PortRole::InPort, addr, &base))
        .await
        .expect("in-port");
    let output = OutPort::<TimedString>::connect(read(PortRole::OutPort, addr, &base))
        .await
        .expect("out-port");
    let text = TimedString {
        tm: Time::now(),
        data: "Ångström".into(),
    };
    assert_eq!(output.put(&text).await, PortStatus::Ok);
    let sample = within("value", input.recv()).await.unwrap();
    assert_eq!(sample.value, text);
    input.close().await;

    let utf8 = [
        ("exname", ""),
        ("qname", queue.as_str()),
        ("rkey", queue.as_str()),
        ("serializer.cdr.charset", "utf-8"),
        ("dataport.serializer.cdr.endian", "big"),
    ];
    let input = InPort::<TimedString>::connect(read(PortRole::InPort, addr, &utf8))
        .await
        .expect("in-port");
    assert_eq!(output.put(&text).await, PortStatus::Ok);
    let mut stats = input.watch_stats();
    within("the decode error", stats.wait_for(|s| s.decode_errors == 1))
        .await
        .unwrap();
}

/// An `extype` the module does not know means `x-consistent-hash` (as in
/// the module), which Leveret implements: binding keys are weights, and
/// each value reaches exactly one of the bound in-ports.
#[tokio::test]
async fn an_unknown_extype_is_a_consistent_hash_exchange() {
    let (_broker, addr) = leveret().await;
    let exchange = unique("ring");
    let mut inputs = Vec::new();
    for _ in 0..2 {
        let queue = unique("ring-q");
        let properties = [
            ("exname", exchange.as_str()),
            ("extype", "ring"),
            ("qname", queue.as_str()),
            ("bkey", "3"),
        ];
        let input = InPort::<TimedLong>::connect(read(PortRole::InPort, addr, &properties))
            .await
            .expect("in-port: the weight is a valid binding key");
        inputs.push(input);
    }
    let mut total = 0;
    for robot in 0..20 {
        let key = format!("robot-{robot}");
        let properties = [
            ("exname", exchange.as_str()),
            ("extype", "ring"),
            ("rkey", key.as_str()),
        ];
        let output = OutPort::<TimedLong>::connect(read(PortRole::OutPort, addr, &properties))
            .await
            .expect("out-port");
        assert_eq!(output.put(&long(robot)).await, PortStatus::Ok);
        within("confirmed", output.flush()).await;
        assert_eq!(output.stats().confirmed, 1, "routed");
        total += 1;
    }
    let mut counts = Vec::new();
    within("every value once", async {
        loop {
            counts = inputs.iter().map(|i| i.stats().arrived).collect();
            if counts.iter().sum::<u64>() >= total {
                break;
            }
            tokio::time::sleep(std::time::Duration::from_millis(5)).await;
        }
    })
    .await;
    assert_eq!(counts.iter().sum::<u64>(), total, "exactly one copy each");
}

/// A big-endian port says so in its messages' `content-type` (it said
/// `endian=little` whatever the port's byte order).
#[tokio::test]
async fn a_big_endian_port_labels_its_messages_big_endian() {
    let (_broker, addr) = leveret().await;
    let queue = unique("big-endian");
    let properties = [
        ("exname", ""),
        ("qname", queue.as_str()),
        ("rkey", queue.as_str()),
        ("bind", "true"),
        ("serializer.cdr.endian", "big"),
    ];
    let output = OutPort::<TimedLong>::connect(read(PortRole::OutPort, addr, &properties))
        .await
        .expect("out-port");
    let connection = Connection::connect(&format!("amqp://guest:guest@{addr}/%2f"))
        .await
        .expect("connect");
    let channel = connection.open_channel().await.expect("channel");
    channel
        .queue_declare(&queue, QueueDeclareOptions::default(), FieldTable::new())
        .await
        .expect("declare");
    let value = TimedLong {
        tm: Time::now(),
        data: 258,
    };
    assert_eq!(output.put(&value).await, PortStatus::Ok);
    let message = within("the message", async {
        loop {
            let got = channel
                .basic_get(&queue, leveret_client::BasicGetOptions { no_ack: true })
                .await
                .expect("get");
            if let Some(message) = got {
                return message;
            }
            tokio::time::sleep(std::time::Duration::from_millis(10)).await;
        }
    })
    .await;
    let content_type = message
        .properties
        .content_type
        .clone()
        .expect("content-type");
    assert_eq!(
        content_type.as_str(),
        Some("application/x-omg-cdr; endian=big")
    );
    // And the body is big-endian: the long's bytes after the time.
    assert_eq!(&message.body[8..12], &[0, 0, 1, 2]);
}
