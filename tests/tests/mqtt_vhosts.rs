//! Which vhost an MQTT client lands in (issue 32 item 2), as RabbitMQ
//! 3.10's plugin picks it: the global parameters
//! `mqtt_port_to_vhost_mapping` (listener port → vhost) and
//! `mqtt_default_vhosts` (client certificate subject DN → vhost), the
//! `vhost:user` user name and the default vhost, in RabbitMQ's order.
//! rumqttc clients (3.1.1 and 5.0) on two plain listeners, Mosquitto's
//! clients with certificates made here over TLS, a raw tungstenite client
//! on a WebSocket listener, lapin consumers in the picked vhost; a
//! subscription's queue (or the connection listing) shows where a
//! session lives.
//! Adversarial: a mapping to a vhost that does not exist or that the user
//! may not use refuses the CONNECT; a malformed mapping is refused when
//! set and nothing is stored.

#[macro_use]
mod common;

use common::*;
use leveret_broker::{AccessError, Broker, BrokerHandle, PeerVerification, Permission, TlsOptions};
use leveret_tests::certs::{Authority, PemFiles};
use rcgen::DnType;
use rumqttc::{Event, Incoming, QoS};
use std::net::SocketAddr;
use std::path::PathBuf;
use std::process::{Command, Output};
use std::time::Duration;

const PORTS: &str = "mqtt_port_to_vhost_mapping";
const CERTIFICATES: &str = "mqtt_default_vhosts";

fn any() -> SocketAddr {
    "127.0.0.1:0".parse().unwrap()
}

/// Users and vhosts: `robot` may use `/`, `robots` and `other`; `guest`
/// only `/`; `attic` exists but `robot` has no permission there.
fn builder() -> leveret_broker::BrokerBuilder {
    Broker::builder()
        .listen(any())
        .vhost("/")
        .vhost("robots")
        .vhost("other")
        .vhost("attic")
        .user("robot", "secret")
        .user("sensor-9", "not used: its certificate logs it in")
        .permission("robot", "/", Permission::full())
        .permission("robot", "robots", Permission::full())
        .permission("robot", "other", Permission::full())
        .permission("sensor-9", "robots", Permission::full())
}

/// A broker with two plain MQTT listeners.
async fn start() -> BrokerHandle {
    builder()
        .mqtt_listen(any())
        .mqtt_listen(any())
        .start()
        .await
        .expect("broker starts")
}

async fn set(handle: &BrokerHandle, name: &str, value: String) {
    handle
        .admin()
        .set_parameter("global", "", name, value)
        .await
        .expect("a well-formed mapping is taken");
}

fn options3(id: &str, port: u16, user: &str) -> rumqttc::MqttOptions {
    let mut options = rumqttc::MqttOptions::new(id, "127.0.0.1", port);
    options.set_credentials(user, "secret");
    options.set_keep_alive(Duration::from_secs(30));
    options
}

/// Connects, subscribes to `cells/+` at QoS 1 (so the session's queue
/// `mqtt-subscription-<id>qos1` is declared in its vhost), and returns
/// the client and its event loop once the SUBACK is in.
async fn subscribed(id: &str, port: u16, user: &str) -> (rumqttc::AsyncClient, rumqttc::EventLoop) {
    let (client, mut events) = rumqttc::AsyncClient::new(options3(id, port, user), 16);
    tmo!(client.subscribe("cells/+", QoS::AtLeastOnce)).unwrap();
    loop {
        match tmo!(events.poll()) {
            Ok(Event::Incoming(Incoming::SubAck(_))) => break,
            Ok(_) => {}
            Err(e) => panic!("{id} could not subscribe: {e:?}"),
        }
    }
    (client, events)
}

/// The vhosts a session's subscription queue is in.
fn vhosts_of(handle: &BrokerHandle, id: &str) -> Vec<String> {
    let queue = format!("mqtt-subscription-{id}qos1");
    handle
        .admin()
        .queues()
        .into_iter()
        .filter(|q| q.name == queue)
        .map(|q| q.vhost)
        .collect()
}

/// A lapin channel in `vhost` with a queue bound to `amq.topic` by `key`.
async fn amqp_queue(
    handle: &BrokerHandle,
    vhost: &str,
    key: &str,
) -> (lapin::Connection, lapin::Channel, String) {
    let url = format!("amqp://robot:secret@{}/{vhost}", handle.local_addrs()[0]);
    let amqp = tmo!(lapin::Connection::connect(
        &url,
        lapin::ConnectionProperties::default()
    ))
    .unwrap();
    let channel = tmo!(amqp.create_channel()).unwrap();
    let queue = unique("vhostmap");
    tmo!(channel.queue_declare(
        &queue,
        lapin::options::QueueDeclareOptions::default(),
        Default::default()
    ))
    .unwrap();
    tmo!(channel.queue_bind(
        &queue,
        "amq.topic",
        key,
        Default::default(),
        Default::default()
    ))
    .unwrap();
    (amqp, channel, queue)
}

/// The body of the next message on `queue`, within the timeout.
async fn next_body(channel: &lapin::Channel, queue: &str) -> Vec<u8> {
    for _ in 0..300 {
        let got = tmo!(channel.basic_get(queue, lapin::options::BasicGetOptions { no_ack: true }))
            .unwrap();
        if let Some(message) = got {
            return message.delivery.data.clone();
        }
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    panic!("nothing reached {queue}");
}

/// Publishes `body` at QoS 1 and waits for its PUBACK.
async fn publish_acked(client: &rumqttc::AsyncClient, events: &mut rumqttc::EventLoop, body: &str) {
    tmo!(client.publish("cells/7", QoS::AtLeastOnce, false, body.as_bytes().to_vec())).unwrap();
    loop {
        match tmo!(events.poll()) {
            Ok(Event::Incoming(Incoming::PubAck(_))) => break,
            Ok(_) => {}
            Err(e) => panic!("publish failed: {e:?}"),
        }
    }
}

#[both_runtimes]
async fn a_port_mapping_sends_a_client_to_its_vhost() {
    let handle = start().await;
    let (mapped, unmapped) = (handle.mqtt_addrs()[0].port(), handle.mqtt_addrs()[1].port());
    set(&handle, PORTS, format!(r#"{{"{mapped}": "robots"}}"#)).await;
    let (_amqp, channel, queue) = amqp_queue(&handle, "robots", "cells.*").await;

    // 3.1.1 on the mapped port: its queue is in `robots`, and an AMQP
    // consumer there gets its publish.
    let (client, mut events) = subscribed("mapped-311", mapped, "robot").await;
    assert_eq!(vhosts_of(&handle, "mapped-311"), ["robots"]);
    publish_acked(&client, &mut events, "21.5").await;
    assert_eq!(next_body(&channel, &queue).await, b"21.5");

    // 5.0 likewise.
    let mut options = rumqttc::v5::MqttOptions::new("mapped-5", "127.0.0.1", mapped);
    options.set_credentials("robot", "secret");
    let (client5, mut events5) = rumqttc::v5::AsyncClient::new(options, 16);
    tmo!(client5.subscribe("cells/+", rumqttc::v5::mqttbytes::QoS::AtLeastOnce)).unwrap();
    loop {
        match tmo!(events5.poll()) {
            Ok(rumqttc::v5::Event::Incoming(rumqttc::v5::mqttbytes::v5::Packet::SubAck(_))) => {
                break
            }
            Ok(_) => {}
            Err(e) => panic!("5.0 subscribe: {e:?}"),
        }
    }
    assert_eq!(vhosts_of(&handle, "mapped-5"), ["robots"]);

    // The other listener is not mapped: the default vhost.
    let (_other, _other_events) = subscribed("unmapped", unmapped, "robot").await;
    assert_eq!(vhosts_of(&handle, "unmapped"), ["/"]);

    // Cleared, the mapping sends nobody anywhere.
    assert!(handle
        .admin()
        .clear_parameter("global", "", PORTS)
        .await
        .unwrap());
    let (_later, _later_events) = subscribed("after-clear", mapped, "robot").await;
    assert_eq!(vhosts_of(&handle, "after-clear"), ["/"]);
    handle.shutdown().await;
}

#[both_runtimes]
async fn without_a_certificate_a_vhost_in_the_user_name_beats_the_port_mapping() {
    let handle = start().await;
    let mapped = handle.mqtt_addrs()[0].port();
    set(&handle, PORTS, format!(r#"{{"{mapped}": "robots"}}"#)).await;
    let (_client, _events) = subscribed("named", mapped, "other:robot").await;
    assert_eq!(vhosts_of(&handle, "named"), ["other"]);
    let (_client, _events) = subscribed("plain", mapped, "robot").await;
    assert_eq!(vhosts_of(&handle, "plain"), ["robots"]);
    handle.shutdown().await;
}

/// The CONNACK a 3.1.1 and a 5.0 client get on `port` as `robot`.
async fn refused_both(port: u16, id: &str) {
    let (_client, mut events) = rumqttc::AsyncClient::new(options3(id, port, "robot"), 4);
    let refused = tmo!(events.poll());
    assert!(
        matches!(
            refused,
            Err(rumqttc::ConnectionError::ConnectionRefused(
                rumqttc::ConnectReturnCode::NotAuthorized
            ))
        ),
        "{refused:?}"
    );
    let mut options = rumqttc::v5::MqttOptions::new(format!("{id}-5"), "127.0.0.1", port);
    options.set_credentials("robot", "secret");
    let (_client, mut events) = rumqttc::v5::AsyncClient::new(options, 4);
    let refused = tmo!(events.poll());
    assert!(
        matches!(
            refused,
            Err(rumqttc::v5::ConnectionError::ConnectionRefused(
                rumqttc::v5::mqttbytes::v5::ConnectReturnCode::NotAuthorized
            ))
        ),
        "{refused:?}"
    );
}

#[both_runtimes]
async fn a_mapping_to_a_missing_or_forbidden_vhost_refuses_the_connect() {
    let handle = start().await;
    let (first, second) = (handle.mqtt_addrs()[0].port(), handle.mqtt_addrs()[1].port());
    set(
        &handle,
        PORTS,
        format!(r#"{{"{first}": "nowhere", "{second}": "attic"}}"#),
    )
    .await;
    refused_both(first, "to-nowhere").await;
    refused_both(second, "to-attic").await;
    assert!(handle
        .admin()
        .queues()
        .iter()
        .all(|q| !q.name.starts_with("mqtt-")));
    // Nothing lingers: a client whose user name names a vhost it may use
    // still gets in on the same port.
    let (_client, _events) = subscribed("still-fine", first, "robots:robot").await;
    assert_eq!(vhosts_of(&handle, "still-fine"), ["robots"]);
    handle.shutdown().await;
}

#[both_runtimes]
async fn a_malformed_mapping_is_refused_and_not_stored() {
    let handle = start().await;
    let admin = handle.admin();
    for (name, value) in [
        (PORTS, r#"{"mqtt": "robots"}"#),
        (PORTS, r#"{"70000": "robots"}"#),
        (PORTS, r#"{"1883": 7}"#),
        (PORTS, r#"["robots"]"#),
        (CERTIFICATES, r#"{"CN=a": ""}"#),
        (CERTIFICATES, "not json"),
    ] {
        let refused = admin
            .set_parameter("global", "", name, value.to_owned())
            .await;
        assert!(
            matches!(refused, Err(AccessError::BadValue(_))),
            "{name} {value}: {refused:?}"
        );
    }
    assert!(admin.parameters("global").is_empty());
    // And a client still lands in the default vhost.
    let port = handle.mqtt_addrs()[0].port();
    let (_client, _events) = subscribed("default", port, "robot").await;
    assert_eq!(vhosts_of(&handle, "default"), ["/"]);
    handle.shutdown().await;
}

/// A certificate signed by `ca` for subject `/CN=common_name/O=fleet`
/// (RabbitMQ writes it `O=fleet,CN=common_name`), and its key.
fn fleet_signed(files: &PemFiles, ca: &Authority, common_name: &str) -> (PathBuf, PathBuf) {
    let subject = [
        (DnType::CommonName, common_name),
        (DnType::OrganizationName, "fleet"),
    ];
    files.signed_subject(ca, &subject, common_name)
}

/// `mosquitto_pub` over TLS to `port` with a client certificate for
/// `common_name`, publishing `body` to `cells/7` at QoS 1, with `args`.
async fn mosquitto_pub(
    files: &PemFiles,
    ca: &Authority,
    port: u16,
    common_name: &str,
    args: &[&str],
) -> Output {
    let (cert, key) = fleet_signed(files, ca, common_name);
    let mut command = Command::new("mosquitto_pub");
    command
        .args(["-h", "localhost", "-p", &port.to_string(), "-V", "mqttv311"])
        .arg("--cafile")
        .arg(files.dir().join("ca.pem"))
        .arg("--cert")
        .arg(&cert)
        .arg("--key")
        .arg(&key)
        .args(["-t", "cells/7", "-q", "1"])
        .args(args);
    let program = format!("{command:?}");
    within(
        "mosquitto_pub",
        tokio::task::spawn_blocking(move || command.output()),
    )
    .await
    .expect("the blocking task")
    .unwrap_or_else(|e| panic!("{program} could not run (is it installed?): {e}"))
}

async fn start_tls(files: &PemFiles, ca: &Authority) -> BrokerHandle {
    let (certfile, keyfile) = fleet_signed(files, ca, "leveret");
    let options = TlsOptions {
        certfile,
        keyfile,
        cacertfile: Some(files.write("ca.pem", &ca.pem())),
        verify: PeerVerification::Optional,
    };
    builder()
        .mqtts_listen(any())
        .tls(options)
        .mqtt_certificate_login(true)
        .start()
        .await
        .expect("broker starts with MQTT over TLS")
}

#[both_runtimes]
async fn a_certificate_mapping_sends_a_client_to_its_vhost_before_the_port_mapping() {
    let files = PemFiles::new("certs");
    let ca = Authority::new("vhostmap test CA");
    let handle = start_tls(&files, &ca).await;
    let port = handle.mqtts_addrs()[0].port();
    // The key is the whole subject DN as RabbitMQ writes it (RFC 4514,
    // the last RDN first); a common name alone matches nothing.
    set(
        &handle,
        CERTIFICATES,
        r#"{"O=fleet,CN=sensor-9": "robots", "CN=someone": "robots"}"#.to_owned(),
    )
    .await;
    set(&handle, PORTS, format!(r#"{{"{port}": "other"}}"#)).await;
    let (_a, robots, robots_queue) = amqp_queue(&handle, "robots", "cells.*").await;
    let (_b, other, other_queue) = amqp_queue(&handle, "other", "cells.*").await;

    // sensor-9's certificate is mapped: `robots`, before the port mapping
    // (sensor-9 has no permission on `other`, so a wrong pick is refused).
    let published = mosquitto_pub(
        &files,
        &ca,
        port,
        "sensor-9",
        &["-i", "s9", "-m", "by-cert"],
    )
    .await;
    assert!(published.status.success(), "{published:?}");
    assert_eq!(next_body(&robots, &robots_queue).await, b"by-cert");

    // A certificate not in the mapping (`O=fleet,CN=someone`): the port
    // mapping, before a vhost in the user name (RabbitMQ's order with a
    // certificate).
    let published = mosquitto_pub(
        &files,
        &ca,
        port,
        "someone",
        &[
            "-i",
            "pw",
            "-u",
            "robots:robot",
            "-P",
            "secret",
            "-m",
            "by-port",
        ],
    )
    .await;
    assert!(published.status.success(), "{published:?}");
    assert_eq!(next_body(&other, &other_queue).await, b"by-port");

    // A certificate mapped to a vhost that does not exist is refused.
    set(
        &handle,
        CERTIFICATES,
        r#"{"O=fleet,CN=sensor-9": "nowhere"}"#.to_owned(),
    )
    .await;
    let refused = mosquitto_pub(&files, &ca, port, "sensor-9", &["-i", "s9b", "-m", "x"]).await;
    assert!(!refused.status.success(), "{refused:?}");
    assert!(
        String::from_utf8_lossy(&refused.stderr).contains("not authorised"),
        "{refused:?}"
    );
    handle.shutdown().await;
}

#[both_runtimes]
async fn a_port_mapping_applies_to_a_websocket_listener() {
    use futures_util::{SinkExt, StreamExt};
    use tokio_tungstenite::tungstenite::client::IntoClientRequest;
    use tokio_tungstenite::tungstenite::http::HeaderValue;
    use tokio_tungstenite::tungstenite::Message;

    let handle = builder()
        .web_mqtt_listen(any())
        .start()
        .await
        .expect("broker starts with MQTT over WebSocket");
    let port = handle.web_mqtt_addrs()[0].port();
    set(&handle, PORTS, format!(r#"{{"{port}": "robots"}}"#)).await;
    let mut request = format!("ws://127.0.0.1:{port}/ws")
        .into_client_request()
        .unwrap();
    request
        .headers_mut()
        .insert("sec-websocket-protocol", HeaderValue::from_static("mqtt"));
    let socket = tmo!(tokio::net::TcpStream::connect(("127.0.0.1", port))).unwrap();
    let (mut ws, _) = tmo!(tokio_tungstenite::client_async(request, socket)).unwrap();
    let connect = leveret_mqtt::Packet::Connect(Box::new(leveret_mqtt::Connect {
        version: leveret_mqtt::ProtocolVersion::V3_1_1,
        clean_start: true,
        keep_alive: 0,
        properties: Default::default(),
        client_id: leveret_mqtt::MqttString::from_static("over-ws"),
        will: None,
        username: Some(leveret_mqtt::MqttString::from_static("robot")),
        password: Some(bytes::Bytes::from_static(b"secret")),
    }));
    let mut out = bytes::BytesMut::new();
    connect
        .encode(leveret_mqtt::ProtocolVersion::V3_1_1, &mut out)
        .unwrap();
    tmo!(ws.send(Message::binary(out.to_vec()))).unwrap();
    let Some(Ok(Message::Binary(connack))) = tmo!(ws.next()) else {
        panic!("no CONNACK");
    };
    // CONNACK: session present 0, return code 0 (accepted).
    assert_eq!(&connack[..], [0x20, 0x02, 0x00, 0x00]);
    let vhosts: Vec<String> = handle
        .admin()
        .connections()
        .into_iter()
        .filter(|c| c.protocol.starts_with("MQTT"))
        .map(|c| c.vhost)
        .collect();
    assert_eq!(vhosts, ["robots"]);
    handle.shutdown().await;
}
