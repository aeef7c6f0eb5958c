//! MQTT over TLS and over WebSocket (issue 32 item 1): Mosquitto's own
//! clients (`mosquitto_pub`/`mosquitto_sub` 2.0, OpenSSL) over TLS with
//! certificates made here (rcgen), a client certificate logging in as its
//! common name (RabbitMQ's `ssl_cert_login`) and a stranger's refused, and
//! no login by certificate unless it is turned on;
//! Eclipse Paho's Python client over WebSocket (`transport="websockets"`,
//! 3.1.1 and 5.0, a payload larger than a WebSocket read). Adversarial: a
//! TLS handshake that never completes and a WebSocket upgrade followed by
//! no CONNECT are closed by the handshake timeout; plaintext MQTT on the
//! TLS port, a wrong path, no `mqtt` subprotocol, a text message and a
//! frame over the packet limit are refused, with a raw tungstenite client;
//! a message sent before the CONNECT is not read past the unauthenticated
//! budget, while packets sent right after a CONNECT are served once it is
//! accepted.

#[macro_use]
mod common;

use bytes::BytesMut;
use common::*;
use futures_util::{SinkExt, StreamExt};
use leveret_broker::{Broker, BrokerHandle, Limits, PeerVerification, Permission, TlsOptions};
use leveret_mqtt::{Connect, Packet, ProtocolVersion};
use leveret_tests::certs::{Authority, PemFiles};
use std::path::Path;
use std::process::{Command, Output};
use std::time::Duration;
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::TcpStream;
use tokio_tungstenite::tungstenite::client::IntoClientRequest;
use tokio_tungstenite::tungstenite::http::HeaderValue;
use tokio_tungstenite::tungstenite::Message;

/// How long a close the broker owes may take (generous: CI is loaded).
const CLOSE_WITHIN: Duration = Duration::from_secs(30);

fn any() -> std::net::SocketAddr {
    "127.0.0.1:0".parse().unwrap()
}

fn builder(limits: Limits) -> leveret_broker::BrokerBuilder {
    Broker::builder()
        .user("robot", "secret")
        .user("sensor-9", "a password the certificate login does not use")
        .permission("robot", "/", Permission::full())
        .permission("sensor-9", "/", Permission::full())
        .limits(limits)
}

/// A broker with an MQTT over TLS listener: client certificates asked
/// for, checked against `ca`, and logging in as their common name.
async fn start_tls(files: &PemFiles, ca: &Authority, limits: Limits) -> BrokerHandle {
    start_tls_with(files, ca, limits, true).await
}

async fn start_tls_with(
    files: &PemFiles,
    ca: &Authority,
    limits: Limits,
    certificate_login: bool,
) -> BrokerHandle {
    let (certfile, keyfile) = files.signed(ca, "leveret");
    let options = TlsOptions {
        certfile,
        keyfile,
        cacertfile: Some(files.write("ca.pem", &ca.pem())),
        verify: PeerVerification::Optional,
    };
    builder(limits)
        .mqtts_listen(any())
        .tls(options)
        .mqtt_certificate_login(certificate_login)
        .start()
        .await
        .expect("broker starts with MQTT over TLS")
}

/// Runs a program to its end off the runtime's threads.
async fn run(mut command: Command) -> Output {
    let program = format!("{command:?}");
    within(
        "a client program",
        tokio::task::spawn_blocking(move || command.output()),
    )
    .await
    .expect("the blocking task")
    .unwrap_or_else(|e| panic!("{program} could not run (is it installed?): {e}"))
}

/// `mosquitto_pub` or `mosquitto_sub` over TLS to `port`, trusting `ca`.
fn mosquitto(program: &str, port: u16, ca: &Path) -> Command {
    let mut command = Command::new(program);
    command
        .args(["-h", "localhost", "-p", &port.to_string(), "-V", "mqttv311"])
        .arg("--cafile")
        .arg(ca);
    command
}

#[both_runtimes]
async fn mosquitto_clients_over_tls_with_a_password_and_a_certificate_login() {
    let files = PemFiles::new("mqtts");
    let ca = Authority::new("mqtt test CA");
    let handle = start_tls(&files, &ca, Limits::default()).await;
    let port = handle.mqtts_addrs()[0].port();
    let ca_file = files.dir().join("ca.pem");

    // The client certificate's common name is the user: no -u.
    let (cert, key) = files.signed(&ca, "sensor-9");
    let mut publish = mosquitto("mosquitto_pub", port, &ca_file);
    publish
        .args([
            "-i", "sensor-9", "-t", "cells/7", "-m", "21.5", "-q", "1", "-r",
        ])
        .arg("--cert")
        .arg(&cert)
        .arg("--key")
        .arg(&key);
    let published = run(publish).await;
    assert!(published.status.success(), "{published:?}");

    // A password login over TLS gets the (retained) message.
    let mut subscribe = mosquitto("mosquitto_sub", port, &ca_file);
    subscribe.args([
        "-i", "reader", "-u", "robot", "-P", "secret", "-t", "cells/#", "-C", "1", "-W", "30", "-v",
    ]);
    let got = run(subscribe).await;
    assert!(got.status.success(), "{got:?}");
    assert_eq!(String::from_utf8_lossy(&got.stdout).trim(), "cells/7 21.5");

    // A certificate whose common name is no user is refused, as is a
    // wrong password with a valid certificate (the user name wins, as in
    // RabbitMQ's plugin).
    let (cert, key) = files.signed(&ca, "stranger");
    let mut stranger = mosquitto("mosquitto_pub", port, &ca_file);
    stranger
        .args(["-i", "stranger", "-t", "cells/8", "-m", "x", "-q", "1"])
        .arg("--cert")
        .arg(&cert)
        .arg("--key")
        .arg(&key);
    let refused = run(stranger).await;
    assert!(!refused.status.success(), "{refused:?}");
    let (cert, key) = files.signed(&ca, "sensor-9");
    let mut wrong = mosquitto("mosquitto_pub", port, &ca_file);
    wrong
        .args([
            "-i", "wrong", "-u", "robot", "-P", "nope", "-t", "cells/9", "-m", "x",
        ])
        .arg("--cert")
        .arg(&cert)
        .arg("--key")
        .arg(&key);
    let refused = run(wrong).await;
    assert!(!refused.status.success(), "{refused:?}");
    handle.shutdown().await;
}

/// Reads until the broker closes `socket` (EOF or an error).
async fn assert_closed(socket: &mut TcpStream) {
    let closed = tokio::time::timeout(CLOSE_WITHIN, async {
        let mut buf = [0u8; 1024];
        loop {
            match socket.read(&mut buf).await {
                Ok(0) | Err(_) => return,
                Ok(_) => {}
            }
        }
    })
    .await;
    assert!(closed.is_ok(), "the broker closed the connection");
}

#[both_runtimes]
async fn without_certificate_login_a_certificate_is_no_credential() {
    let files = PemFiles::new("mqtts-no-cert-login");
    let ca = Authority::new("mqtt test CA");
    let handle = start_tls_with(&files, &ca, Limits::default(), false).await;
    let port = handle.mqtts_addrs()[0].port();
    let ca_file = files.dir().join("ca.pem");
    let (cert, key) = files.signed(&ca, "sensor-9");
    let with_certificate = |user: Option<&str>| {
        let mut publish = mosquitto("mosquitto_pub", port, &ca_file);
        publish
            .args(["-i", "sensor-9", "-t", "cells/7", "-m", "x", "-q", "1"])
            .arg("--cert")
            .arg(&cert)
            .arg("--key")
            .arg(&key);
        if let Some(user) = user {
            publish.args(["-u", user, "-P", "secret"]);
        }
        publish
    };
    let refused = run(with_certificate(None)).await;
    assert!(!refused.status.success(), "{refused:?}");
    let accepted = run(with_certificate(Some("robot"))).await;
    assert!(accepted.status.success(), "{accepted:?}");
    handle.shutdown().await;
}

#[both_runtimes]
async fn a_tls_handshake_that_never_completes_or_plaintext_mqtt_is_closed() {
    let files = PemFiles::new("mqtts-stall");
    let ca = Authority::new("mqtt test CA");
    let limits = Limits {
        handshake_timeout: Duration::from_millis(500),
        ..Limits::default()
    };
    let handle = start_tls(&files, &ca, limits).await;
    let port = handle.mqtts_addrs()[0].port();
    // The start of a TLS record, then nothing.
    let mut stalled = tmo!(TcpStream::connect(("127.0.0.1", port))).unwrap();
    stalled.write_all(&[0x16, 0x03, 0x01]).await.unwrap();
    // A plaintext CONNECT on the TLS port.
    let mut plaintext = tmo!(TcpStream::connect(("127.0.0.1", port))).unwrap();
    let mut out = BytesMut::new();
    connect_packet("plain")
        .encode(ProtocolVersion::V3_1_1, &mut out)
        .unwrap();
    plaintext.write_all(&out).await.unwrap();
    assert_closed(&mut plaintext).await;
    assert_closed(&mut stalled).await;
    // Neither is left counted as a connection.
    within("the connections released", async {
        while handle.admin().overview().object_totals.connections != 0 {
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
    })
    .await;
    handle.shutdown().await;
}

fn connect_packet(id: &str) -> Packet {
    Packet::Connect(Box::new(Connect {
        version: ProtocolVersion::V3_1_1,
        clean_start: true,
        keep_alive: 0,
        properties: Default::default(),
        client_id: leveret_mqtt::MqttString::from_utf8(id.to_owned().into()).unwrap(),
        will: None,
        username: Some(leveret_mqtt::MqttString::from_static("robot")),
        password: Some(bytes::Bytes::from_static(b"secret")),
    }))
}

async fn start_websocket(limits: Limits) -> BrokerHandle {
    builder(limits)
        .listen(any())
        .web_mqtt_listen(any())
        .start()
        .await
        .expect("broker starts with MQTT over WebSocket")
}

/// Paho's Python client over WebSocket: a 3.1.1 subscriber and a 5.0
/// publisher of a 100 kB QoS 1 message and a small QoS 0 one.
const PAHO_WEBSOCKET: &str = r#"
import sys, threading
import paho.mqtt.client as mqtt

port = int(sys.argv[1])
got, subscribed = [], threading.Event()
done = threading.Event()

def client(name, protocol):
    c = mqtt.Client(mqtt.CallbackAPIVersion.VERSION2, client_id=name,
                    transport="websockets", protocol=protocol)
    c.ws_set_options(path="/ws")
    c.username_pw_set("robot", "secret")
    return c

def on_message(c, userdata, message):
    got.append((message.topic, message.qos, len(message.payload)))
    if len(got) == 2:
        done.set()

sub = client("ws-sub", mqtt.MQTTv311)
sub.on_message = on_message
sub.on_subscribe = lambda *args: subscribed.set()
sub.connect("127.0.0.1", port)
sub.loop_start()
sub.subscribe("dash/#", qos=1)
assert subscribed.wait(30), "no SUBACK"

pub = client("ws-pub", mqtt.MQTTv5)
pub.connect("127.0.0.1", port)
pub.loop_start()
pub.publish("dash/big", b"x" * 100000, qos=1).wait_for_publish(30)
pub.publish("dash/small", b"hi", qos=0).wait_for_publish(30)
assert done.wait(30), got
for topic, qos, size in got:
    print(topic, qos, size)
pub.disconnect(); sub.disconnect()
pub.loop_stop(); sub.loop_stop()
"#;

#[both_runtimes]
async fn paho_clients_publish_and_subscribe_over_websocket() {
    let handle = start_websocket(Limits::default()).await;
    let port = handle.web_mqtt_addrs()[0].port();
    let mut paho = Command::new("python3");
    paho.args(["-c", PAHO_WEBSOCKET, &port.to_string()]);
    let output = run(paho).await;
    assert!(output.status.success(), "{output:?}");
    assert_eq!(
        String::from_utf8_lossy(&output.stdout).trim(),
        "dash/big 1 100000\ndash/small 0 2"
    );
    handle.shutdown().await;
}

/// A raw WebSocket to the broker's `/ws` (or `path`), offering `protocol`.
async fn websocket(
    port: u16,
    path: &str,
    protocol: Option<&str>,
) -> Result<tokio_tungstenite::WebSocketStream<TcpStream>, tokio_tungstenite::tungstenite::Error> {
    let mut request = format!("ws://127.0.0.1:{port}{path}")
        .into_client_request()
        .unwrap();
    if let Some(protocol) = protocol {
        request.headers_mut().insert(
            "sec-websocket-protocol",
            HeaderValue::from_str(protocol).unwrap(),
        );
    }
    let socket = tmo!(TcpStream::connect(("127.0.0.1", port))).unwrap();
    tmo!(tokio_tungstenite::client_async(request, socket)).map(|(stream, _)| stream)
}

/// Reads until the broker ends the WebSocket.
async fn assert_ws_closed(ws: &mut tokio_tungstenite::WebSocketStream<TcpStream>) {
    let closed = tokio::time::timeout(CLOSE_WITHIN, async {
        loop {
            match ws.next().await {
                None | Some(Err(_)) | Some(Ok(Message::Close(_))) => return,
                Some(Ok(_)) => {}
            }
        }
    })
    .await;
    assert!(closed.is_ok(), "the broker closed the WebSocket");
}

#[both_runtimes]
async fn websocket_upgrades_frames_and_silence_are_checked() {
    let limits = Limits {
        max_message_size: 4096,
        handshake_timeout: Duration::from_millis(500),
        ..Limits::default()
    };
    let handle = start_websocket(limits).await;
    let port = handle.web_mqtt_addrs()[0].port();
    assert!(
        websocket(port, "/mqtt", Some("mqtt")).await.is_err(),
        "wrong path"
    );
    assert!(
        websocket(port, "/ws", None).await.is_err(),
        "no subprotocol"
    );
    assert!(
        websocket(port, "/ws", Some("chat")).await.is_err(),
        "not mqtt"
    );

    // A CONNECT over WebSocket, split over two messages, is answered.
    let mut ws = websocket(port, "/ws", Some("mqtt")).await.unwrap();
    let mut out = BytesMut::new();
    connect_packet("split")
        .encode(ProtocolVersion::V3_1_1, &mut out)
        .unwrap();
    let (head, tail) = out.split_at(5);
    ws.send(Message::Binary(head.to_vec().into()))
        .await
        .unwrap();
    ws.send(Message::Binary(tail.to_vec().into()))
        .await
        .unwrap();
    let answer = tmo!(ws.next()).expect("a message").expect("no error");
    let mut bytes = BytesMut::from(&answer.into_data()[..]);
    let connack = leveret_mqtt::decode_packet(&mut bytes, ProtocolVersion::V3_1_1, 1024).unwrap();
    assert!(
        matches!(&connack, Some(Packet::ConnAck(ack)) if ack.reason == leveret_mqtt::ReasonCode::Success),
        "{connack:?}"
    );
    // A frame over the packet limit ends the connection, even made of
    // packets the session would take (PINGREQs, answered one by one if
    // the frame were let through).
    let big = [0xc0u8, 0x00].repeat(4100);
    let _ = ws.send(Message::Binary(big.into())).await;
    assert_ws_closed(&mut ws).await;

    // A text message ends it (MQTT travels in binary messages).
    let mut ws = websocket(port, "/ws", Some("mqtt")).await.unwrap();
    ws.send(Message::Text("hello".into())).await.unwrap();
    assert_ws_closed(&mut ws).await;

    // An upgrade and no CONNECT: the handshake timeout closes it.
    let mut ws = websocket(port, "/ws", Some("mqtt")).await.unwrap();
    assert_ws_closed(&mut ws).await;
    within("the connections released", async {
        while handle.admin().overview().object_totals.connections != 0 {
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
    })
    .await;
    handle.shutdown().await;
}

/// A message of 32 MiB sent after the upgrade and before any CONNECT,
/// under a 64 MiB packet limit: tungstenite would buffer it whole before
/// the session saw it, so the broker reads no more than its
/// unauthenticated budget (tens of KiB) and the handshake timeout then
/// closes the connection. The client's send therefore cannot finish:
/// more than the socket buffers of both sides hold stays unread. (A
/// broker that read it all would let the send finish well within the
/// 5 s timeout on an idle machine; on a loaded one it might not, and the
/// test would pass where it should fail, never the other way.)
#[both_runtimes]
async fn a_websocket_message_before_connect_is_not_read_past_the_budget() {
    let limits = Limits {
        max_message_size: 64 * 1024 * 1024,
        handshake_timeout: Duration::from_secs(5),
        ..Limits::default()
    };
    let handle = start_websocket(limits).await;
    let port = handle.web_mqtt_addrs()[0].port();
    let mut ws = websocket(port, "/ws", Some("mqtt")).await.unwrap();
    let big = vec![0u8; 32 * 1024 * 1024];
    let sent = tokio::time::timeout(CLOSE_WITHIN, ws.send(Message::Binary(big.into()))).await;
    assert!(
        matches!(sent, Ok(Err(_))),
        "the send ends in an error when the broker closes, unread: {sent:?}"
    );
    within("the connection released", async {
        while handle.admin().overview().object_totals.connections != 0 {
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
    })
    .await;
    handle.shutdown().await;
}

/// A client that sends its SUBSCRIBE and a 1 MiB PUBLISH right after its
/// CONNECT, each in a message of its own, without waiting for the
/// CONNACK (as pipelining clients do): the reads held back before login
/// resume once the CONNECT is accepted, and the publish comes back to it.
#[both_runtimes]
async fn packets_sent_right_after_a_websocket_connect_are_served_after_login() {
    let limits = Limits {
        max_message_size: 4 * 1024 * 1024,
        ..Limits::default()
    };
    let handle = start_websocket(limits).await;
    let port = handle.web_mqtt_addrs()[0].port();
    let mut ws = websocket(port, "/ws", Some("mqtt")).await.unwrap();
    let mut connect = BytesMut::new();
    connect_packet("pipelined")
        .encode(ProtocolVersion::V3_1_1, &mut connect)
        .unwrap();
    let mut subscribe = 1u16.to_be_bytes().to_vec();
    subscribe.extend(mqtt_string("big/one"));
    subscribe.push(0);
    let payload: Vec<u8> = (0..1024 * 1024).map(|i| (i % 251) as u8).collect();
    let mut publish = mqtt_string("big/one");
    publish.extend_from_slice(&payload);
    for message in [
        connect.to_vec(),
        mqtt_packet(0x82, &subscribe),
        mqtt_packet(0x30, &publish),
    ] {
        tmo!(ws.send(Message::Binary(message.into()))).unwrap();
    }
    // CONNACK, SUBACK, then the PUBLISH, whatever the message boundaries.
    let mut received = BytesMut::new();
    let mut packets = Vec::new();
    while packets.len() < 3 {
        if let Some(packet) =
            leveret_mqtt::decode_packet(&mut received, ProtocolVersion::V3_1_1, 8 << 20).unwrap()
        {
            packets.push(packet);
            continue;
        }
        let message = tmo!(ws.next()).expect("a message").expect("no error");
        received.extend_from_slice(&message.into_data());
    }
    assert!(
        matches!(&packets[0], Packet::ConnAck(ack) if ack.reason == leveret_mqtt::ReasonCode::Success),
        "{:?}",
        packets[0]
    );
    assert!(matches!(&packets[1], Packet::SubAck(_)), "{:?}", packets[1]);
    match &packets[2] {
        Packet::Publish(p) => {
            assert_eq!(p.topic.as_str(), "big/one");
            assert!(p.payload == payload, "the payload comes back whole");
        }
        other => panic!("expected the publish, got {other:?}"),
    }
    handle.shutdown().await;
}
