//! The binary's TLS listener (issue 14 item 1): `--tls-listen` with
//! `--tls-certfile` and `--tls-keyfile` serves lapin over TLS beside the
//! plaintext listener, and SIGHUP re-reads the certificate files (a bad
//! file is logged and the certificates in use stay). Certificates are made
//! here with rcgen.

mod common;

use common::ops::OpsBroker;
use lapin::tcp::OwnedTLSConfig;
use lapin::{Connection, ConnectionProperties};
use leveret_tests::certs::Authority;
use std::path::Path;

/// A CA's PEM, and a certificate for localhost it signed, with its key.
fn issue(name: &str) -> (String, String, String) {
    let ca = Authority::new(name);
    let (leaf, key) = ca.sign("leveret", false);
    (ca.pem(), leaf.pem(), key.serialize_pem())
}

fn install(dir: &Path, cert: &str, key: &str) {
    std::fs::write(dir.join("cert.pem"), cert).expect("cert");
    std::fs::write(dir.join("key.pem"), key).expect("key");
}

async fn connect(port: u16, ca: &str) -> lapin::Result<Connection> {
    let url = format!("amqps://guest:guest@localhost:{port}/%2f");
    let config = OwnedTLSConfig {
        identity: None,
        cert_chain: Some(ca.to_owned()),
    };
    tokio::time::timeout(
        std::time::Duration::from_secs(10),
        Connection::connect_with_config(&url, ConnectionProperties::default(), config),
    )
    .await
    .expect("no hang")
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn tls_beside_plaintext_and_sighup_reloads_the_certificates() {
    let dir = std::env::temp_dir().join(format!("leveret-tls-bin-{}", std::process::id()));
    std::fs::create_dir_all(&dir).expect("dir");
    let (first_ca, cert, key) = issue("first");
    install(&dir, &cert, &key);
    let (cert_path, key_path) = (dir.join("cert.pem"), dir.join("key.pem"));
    let broker = OpsBroker::start(
        "tls",
        &[
            "--tls-listen",
            "127.0.0.1:0",
            "--tls-certfile",
            cert_path.to_str().unwrap(),
            "--tls-keyfile",
            key_path.to_str().unwrap(),
        ],
    );
    let port = broker.tls.expect("the TLS listener's address").port();
    let plain = Connection::connect(&broker.amqp_url(), ConnectionProperties::default())
        .await
        .expect("plaintext still served");
    let open = connect(port, &first_ca).await.expect("TLS");

    let (second_ca, cert, key) = issue("second");
    install(&dir, &cert, &key);
    broker.signal("HUP");
    broker.wait_for_log("TLS certificates reloaded");
    connect(port, &second_ca)
        .await
        .expect("the reloaded certificate");
    assert!(connect(port, &first_ca).await.is_err());
    assert!(
        open.status().connected(),
        "an open connection keeps its TLS session"
    );
    open.create_channel().await.expect("and still works");

    std::fs::write(&cert_path, "garbage").expect("write");
    broker.signal("HUP");
    broker.wait_for_log("TLS certificates not reloaded");
    connect(port, &second_ca)
        .await
        .expect("a bad file leaves the certificates in use");
    plain.close(200, "bye").await.expect("close");
    let _ = std::fs::remove_dir_all(&dir);
}
