//! TLS listeners (issue 14 item 1), driven by lapin over rustls with
//! certificates made here with rcgen: a CA, a server certificate for
//! localhost, client certificates for the user `robot-7` (valid, signed by
//! another CA, expired). Checked: the handshake and a round trip, mutual
//! TLS with SASL EXTERNAL logging in as the certificate's common name,
//! wrongly-signed and expired client certificates refused, a client
//! without a certificate refused where one is required, plaintext AMQP on
//! the TLS port closed without harm, and certificates reloaded while a
//! connection stays open.

#[macro_use]
mod common;

use common::*;
use lapin::tcp::{OwnedIdentity, OwnedTLSConfig};
use leveret_broker::{Broker, BrokerHandle, PeerVerification, Permission, TlsOptions};
use leveret_tests::certs::Authority;
use std::path::PathBuf;
use tokio::io::{AsyncReadExt, AsyncWriteExt};

fn identity(ca: &Authority, common_name: &str, expired: bool) -> OwnedIdentity {
    OwnedIdentity {
        der: ca.pkcs12(common_name, expired, "pw"),
        password: "pw".to_owned(),
    }
}

/// The server's certificate files, rewritable for a reload.
struct ServerFiles {
    dir: PathBuf,
}

impl ServerFiles {
    fn new(name: &str) -> ServerFiles {
        let dir = std::env::temp_dir().join(format!(
            "leveret-tls-test-{name}-{}-{}",
            std::process::id(),
            unique("d")
        ));
        std::fs::create_dir_all(&dir).expect("dir");
        ServerFiles { dir }
    }

    /// Writes a server certificate signed by `server_ca`, and `client_ca`
    /// as the bundle client certificates are checked against.
    fn write(&self, server_ca: &Authority, client_ca: &Authority) {
        let (cert, key) = server_ca.sign("leveret", false);
        std::fs::write(self.dir.join("cert.pem"), cert.pem()).expect("cert");
        std::fs::write(self.dir.join("key.pem"), key.serialize_pem()).expect("key");
        std::fs::write(self.dir.join("ca.pem"), client_ca.pem()).expect("ca");
    }

    fn options(&self, verify: PeerVerification) -> TlsOptions {
        TlsOptions {
            certfile: self.dir.join("cert.pem"),
            keyfile: self.dir.join("key.pem"),
            cacertfile: Some(self.dir.join("ca.pem")),
            verify,
        }
    }
}

impl Drop for ServerFiles {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.dir);
    }
}

async fn start(files: &ServerFiles, verify: PeerVerification) -> BrokerHandle {
    Broker::builder()
        .user("guest", "guest")
        .user("robot-7", "not used with EXTERNAL")
        .permission("guest", "/", Permission::full())
        .permission("robot-7", "/", Permission::full())
        .tls_listen("127.0.0.1:0".parse().expect("addr"))
        .tls(files.options(verify))
        .start()
        .await
        .expect("broker starts with TLS")
}

fn amqps(handle: &BrokerHandle, credentials: &str, query: &str) -> String {
    let port = handle.tls_addrs()[0].port();
    format!("amqps://{credentials}localhost:{port}/%2f{query}")
}

async fn connect(
    url: &str,
    ca: &Authority,
    identity: Option<OwnedIdentity>,
) -> lapin::Result<lp::Connection> {
    let config = OwnedTLSConfig {
        identity,
        cert_chain: Some(ca.pem()),
    };
    tmo!(lp::Connection::connect_with_config(
        url,
        lp::ConnectionProperties::default(),
        config
    ))
}

/// A publish and a get on `conn`: the connection works end to end.
async fn round_trip(conn: &lp::Connection) {
    let ch = lp::channel(conn).await;
    let queue = lp::queue(&ch, "tls").await;
    lp::publish(&ch, "", &queue, b"over TLS").await;
    let got = lp::get(&ch, &queue, true).await.expect("the message");
    assert_eq!(got.delivery.data, b"over TLS");
}

#[both_runtimes]
async fn a_tls_client_connects_with_the_ca_and_a_wrong_ca_is_refused() {
    let (ca, other) = (Authority::new("ca"), Authority::new("other"));
    let files = ServerFiles::new("basic");
    files.write(&ca, &ca);
    let handle = start(&files, PeerVerification::Optional).await;
    let conn = connect(&amqps(&handle, "guest:guest@", ""), &ca, None)
        .await
        .expect("TLS with the right CA, no client certificate");
    round_trip(&conn).await;
    assert!(
        connect(&amqps(&handle, "guest:guest@", ""), &other, None)
            .await
            .is_err(),
        "a client that does not trust the server's CA gets no connection"
    );
    handle.shutdown().await;
}

#[both_runtimes]
async fn mutual_tls_logs_in_with_external_as_the_certificates_common_name() {
    let ca = Authority::new("ca");
    let files = ServerFiles::new("external");
    files.write(&ca, &ca);
    let handle = start(&files, PeerVerification::Required).await;
    let url = amqps(&handle, "", "?auth_mechanism=external");
    let conn = connect(&url, &ca, Some(identity(&ca, "robot-7", false)))
        .await
        .expect("EXTERNAL with a certificate for robot-7");
    round_trip(&conn).await;
    let users: Vec<String> = handle
        .admin()
        .connections()
        .into_iter()
        .map(|c| c.user)
        .collect();
    assert_eq!(users, ["robot-7"]);
    // A certificate for a name that is no user is refused.
    assert!(connect(&url, &ca, Some(identity(&ca, "stranger", false)))
        .await
        .is_err());
    handle.shutdown().await;
}

#[both_runtimes]
async fn wrongly_signed_expired_and_missing_client_certificates_are_refused() {
    let (ca, rogue) = (Authority::new("ca"), Authority::new("rogue"));
    let files = ServerFiles::new("refused");
    files.write(&ca, &ca);
    let handle = start(&files, PeerVerification::Required).await;
    let url = amqps(&handle, "guest:guest@", "");
    for (what, identity) in [
        (
            "signed by another CA",
            Some(identity(&rogue, "robot-7", false)),
        ),
        ("expired", Some(identity(&ca, "robot-7", true))),
        ("none where one is required", None),
    ] {
        assert!(
            connect(&url, &ca, identity).await.is_err(),
            "a client certificate {what} is refused"
        );
    }
    let good = connect(&url, &ca, Some(identity(&ca, "robot-7", false)))
        .await
        .expect("a valid certificate, with PLAIN");
    round_trip(&good).await;
    handle.shutdown().await;
}

#[both_runtimes]
async fn plaintext_on_the_tls_port_is_closed_without_harm() {
    let ca = Authority::new("ca");
    let files = ServerFiles::new("plaintext");
    files.write(&ca, &ca);
    let handle = start(&files, PeerVerification::Optional).await;
    let mut socket = tokio::net::TcpStream::connect(handle.tls_addrs()[0])
        .await
        .expect("tcp");
    socket
        .write_all(b"AMQP\x00\x00\x09\x01")
        .await
        .expect("write");
    let mut answer = Vec::new();
    let read = tokio::time::timeout(TIMEOUT, socket.read_to_end(&mut answer))
        .await
        .expect("the broker closes the connection");
    assert!(
        read.is_err() || !answer.starts_with(b"AMQP"),
        "no AMQP in the clear: {answer:?}"
    );
    let conn = connect(&amqps(&handle, "guest:guest@", ""), &ca, None)
        .await
        .expect("still serving TLS");
    round_trip(&conn).await;
    handle.shutdown().await;
}

#[both_runtimes]
async fn certificates_reload_while_a_connection_stays_open() {
    let (first, second) = (Authority::new("first"), Authority::new("second"));
    let files = ServerFiles::new("reload");
    files.write(&first, &first);
    let handle = start(&files, PeerVerification::Optional).await;
    let url = amqps(&handle, "guest:guest@", "");
    let open = connect(&url, &first, None)
        .await
        .expect("first certificate");
    files.write(&second, &second);
    handle.reload_tls().expect("reload");
    let new = connect(&url, &second, None)
        .await
        .expect("the reloaded certificate");
    round_trip(&new).await;
    assert!(
        connect(&url, &first, None).await.is_err(),
        "new connections no longer get the old certificate"
    );
    round_trip(&open).await;
    // Files that do not load leave the certificates in use.
    std::fs::write(files.dir.join("cert.pem"), "garbage").expect("write");
    assert!(handle.reload_tls().is_err());
    connect(&url, &second, None)
        .await
        .expect("still the second certificate");
    handle.shutdown().await;
}

/// Clients that open the TLS port and never finish the handshake (no
/// bytes, or a ClientHello cut short) are dropped at the handshake
/// timeout, each holding only its connection slot meanwhile, and the
/// listener keeps serving.
#[both_runtimes]
async fn handshakes_that_never_finish_are_dropped_at_the_timeout() {
    let ca = Authority::new("ca");
    let files = ServerFiles::new("slow");
    files.write(&ca, &ca);
    // Long enough for the real client's TLS and AMQP handshakes at the end
    // (a debug build's rustls on a loaded machine), short enough to wait for.
    let limits = leveret_broker::Limits {
        handshake_timeout: std::time::Duration::from_secs(2),
        ..Default::default()
    };
    let handle = Broker::builder()
        .limits(limits)
        .tls_listen("127.0.0.1:0".parse().expect("addr"))
        .tls(files.options(PeerVerification::Optional))
        .start()
        .await
        .expect("broker starts with TLS");
    let mut stalled = Vec::new();
    for n in 0..50 {
        let mut socket = tokio::net::TcpStream::connect(handle.tls_addrs()[0])
            .await
            .expect("tcp");
        if n % 2 == 1 {
            // The first bytes of a TLS record carrying a ClientHello.
            socket
                .write_all(&[0x16, 0x03, 0x01, 0x02, 0x00, 0x01])
                .await
                .expect("write");
        }
        stalled.push(socket);
    }
    for mut socket in stalled {
        let mut rest = Vec::new();
        let closed = tokio::time::timeout(TIMEOUT, socket.read_to_end(&mut rest)).await;
        assert!(closed.is_ok(), "a stalled handshake was never dropped");
    }
    let conn = connect(&amqps(&handle, "guest:guest@", ""), &ca, None)
        .await
        .expect("still serving TLS");
    round_trip(&conn).await;
    handle.shutdown().await;
}
