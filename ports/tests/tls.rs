//! The robot data ports over `amqps://` from a port profile's URI: a
//! Leveret TLS listener with a CA and a server certificate made here
//! (rcgen), the CA given in the URI's `cacertfile`.

mod common;

use common::within;
use leveret_broker::{Broker, BrokerHandle, PeerVerification, Permission, TlsOptions};
use leveret_ports::{InPort, OutPort, PortProfile, PortStatus, Time, TimedLong};
use leveret_tests::certs::Authority;
use std::path::{Path, PathBuf};

/// A directory with a CA and a server certificate for localhost (with
/// its key), removed when dropped.
struct Scratch(PathBuf);

impl Drop for Scratch {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.0);
    }
}

fn scratch(name: &str) -> Scratch {
    let dir = std::env::temp_dir().join(format!("leveret-ports-tls-{name}-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let ca = Authority::new("test-ca");
    std::fs::write(dir.join("ca.pem"), ca.pem()).unwrap();
    let (cert, key) = ca.sign("leveret", false);
    std::fs::write(dir.join("server.pem"), cert.pem()).unwrap();
    std::fs::write(dir.join("server.key"), key.serialize_pem()).unwrap();
    Scratch(dir)
}

async fn broker(dir: &Path) -> BrokerHandle {
    Broker::builder()
        .user("guest", "guest")
        .permission("guest", "/", Permission::full())
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

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn data_ports_run_over_tls_from_the_profiles_uri() {
    let dir = scratch("ports");
    let handle = broker(&dir.0).await;
    let profile = PortProfile::new(&uri(&handle, &dir.0, "&heartbeat=5"))
        .expect("an amqps profile")
        .queue("tls-pose")
        .routing_key("tls-pose");
    let input = InPort::<TimedLong>::connect(profile.clone())
        .await
        .expect("in-port");
    let output = OutPort::<TimedLong>::connect(profile)
        .await
        .expect("out-port");
    let value = TimedLong {
        tm: Time { sec: 1, nsec: 2 },
        data: 42,
    };
    assert_eq!(output.put(&value).await, PortStatus::Ok);
    let sample = within("sample", input.recv()).await.expect("a sample");
    assert_eq!(sample.value.data, 42);
    handle.shutdown().await;
}
