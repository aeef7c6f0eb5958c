//! `amqps://` (issue 14 item 1): the client over rustls to a Leveret TLS
//! listener, with certificates made here (rcgen): the CA from
//! `cacertfile`, a client certificate with SASL EXTERNAL, the system's CA
//! certificates (which do not trust this CA: refused). The robot data
//! ports over TLS are tested in `ports/tests/tls.rs`.

mod common;

use bytes::Bytes;
use common::within;
use leveret_broker::{Broker, BrokerHandle, PeerVerification, Permission, TlsOptions};
use leveret_client::{BasicGetOptions, Connection, QueueDeclareOptions};
use leveret_tests::certs::Authority;
use std::path::{Path, PathBuf};

/// Writes a CA, a server certificate for localhost and a client
/// certificate for `robot-7` (each with its key) into `dir`.
fn certificates(dir: &Path) {
    let ca = Authority::new("test-ca");
    std::fs::write(dir.join("ca.pem"), ca.pem()).unwrap();
    for (stem, name) in [("server", "leveret"), ("client", "robot-7")] {
        let (cert, key) = ca.sign(name, false);
        std::fs::write(dir.join(format!("{stem}.pem")), cert.pem()).unwrap();
        std::fs::write(dir.join(format!("{stem}.key")), key.serialize_pem()).unwrap();
    }
}

async fn broker(dir: &Path) -> BrokerHandle {
    Broker::builder()
        .user("guest", "guest")
        .user("robot-7", "unused")
        .permission("guest", "/", Permission::full())
        .permission("robot-7", "/", Permission::full())
        .tls_listen("127.0.0.1:0".parse().unwrap())
        .tls(TlsOptions {
            certfile: dir.join("server.pem"),
            keyfile: dir.join("server.key"),
            cacertfile: Some(dir.join("ca.pem")),
            verify: PeerVerification::Optional,
        })
        .start()
        .await
        .expect("broker with TLS")
}

fn uri(handle: &BrokerHandle, dir: &Path, rest: &str) -> String {
    let port = handle.tls_addrs()[0].port();
    let ca = dir.join("ca.pem");
    format!(
        "amqps://localhost:{port}/%2f?cacertfile={}{rest}",
        ca.display()
    )
}

struct Scratch(PathBuf);

impl Drop for Scratch {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.0);
    }
}

fn scratch(name: &str) -> Scratch {
    let dir =
        std::env::temp_dir().join(format!("leveret-client-tls-{name}-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    certificates(&dir);
    Scratch(dir)
}

async fn round_trip(connection: &Connection) {
    let channel = within("channel", connection.open_channel()).await.unwrap();
    let queue = within(
        "declare",
        channel.queue_declare(
            "",
            QueueDeclareOptions {
                exclusive: true,
                ..Default::default()
            },
            Default::default(),
        ),
    )
    .await
    .unwrap();
    channel
        .basic_publish(
            "",
            &queue.name,
            Default::default(),
            Default::default(),
            Bytes::from_static(b"tls"),
        )
        .await
        .unwrap();
    let got = within(
        "get",
        channel.basic_get(&queue.name, BasicGetOptions { no_ack: true }),
    )
    .await
    .unwrap();
    assert_eq!(got.expect("the message").body.as_ref(), b"tls");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn amqps_with_a_ca_file_plain_and_external() {
    let dir = scratch("connect");
    let handle = broker(&dir.0).await;
    let plain = within("connect", Connection::connect(&uri(&handle, &dir.0, "")))
        .await
        .expect("amqps with PLAIN");
    round_trip(&plain).await;
    let client = format!(
        "&certfile={}&keyfile={}&auth_mechanism=external",
        dir.0.join("client.pem").display(),
        dir.0.join("client.key").display()
    );
    let external = within(
        "connect",
        Connection::connect(&uri(&handle, &dir.0, &client)),
    )
    .await
    .expect("amqps with EXTERNAL");
    round_trip(&external).await;
    let users: Vec<String> = handle
        .admin()
        .connections()
        .into_iter()
        .map(|c| c.user)
        .collect();
    assert!(users.contains(&"robot-7".to_owned()), "{users:?}");
    // Without cacertfile the system's CAs are trusted, and they do not
    // know this test's CA.
    let port = handle.tls_addrs()[0].port();
    let untrusted = within(
        "connect",
        Connection::connect(&format!("amqps://localhost:{port}/")),
    )
    .await;
    assert!(untrusted.is_err(), "{untrusted:?}");
    // EXTERNAL without a client certificate is refused by the broker.
    let anonymous = within(
        "connect",
        Connection::connect(&uri(&handle, &dir.0, "&auth_mechanism=external")),
    )
    .await;
    assert!(anonymous.is_err());
    handle.shutdown().await;
}
