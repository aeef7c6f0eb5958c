//! The TLS suite's checks with lapin (rustls): one JSON line per check,
//! `{"name", "outcome"}` with outcome `ok` or `refused: ...`.
//!
//!     tls-lapin --certs DIR --port PORT

use lapin::options::{BasicGetOptions, BasicPublishOptions, QueueDeclareOptions};
use lapin::tcp::{OwnedIdentity, OwnedTLSConfig};
use lapin::types::FieldTable;
use lapin::{BasicProperties, Connection, ConnectionProperties};
use std::path::{Path, PathBuf};
use std::time::Duration;

fn arg(name: &str) -> String {
    let args: Vec<String> = std::env::args().collect();
    let at = args
        .iter()
        .position(|a| a == name)
        .unwrap_or_else(|| panic!("missing {name}"));
    args[at + 1].clone()
}

fn read(dir: &Path, name: &str) -> String {
    std::fs::read_to_string(dir.join(name)).expect("certificate file")
}

async fn check(url: String, config: OwnedTLSConfig) -> Result<(), String> {
    let connect = Connection::connect_with_config(&url, ConnectionProperties::default(), config);
    let conn = tokio::time::timeout(Duration::from_secs(20), connect)
        .await
        .map_err(|_| "timed out".to_owned())?
        .map_err(|e| e.to_string())?;
    let ch = conn.create_channel().await.map_err(|e| e.to_string())?;
    let queue = ch
        .queue_declare(
            "",
            QueueDeclareOptions {
                exclusive: true,
                ..Default::default()
            },
            FieldTable::default(),
        )
        .await
        .map_err(|e| e.to_string())?;
    ch.basic_publish(
        "",
        queue.name().as_str(),
        BasicPublishOptions::default(),
        b"tls",
        BasicProperties::default(),
    )
    .await
    .map_err(|e| e.to_string())?
    .await
    .map_err(|e| e.to_string())?;
    let got = ch
        .basic_get(queue.name().as_str(), BasicGetOptions { no_ack: true })
        .await
        .map_err(|e| e.to_string())?;
    if got.map(|m| m.delivery.data) != Some(b"tls".to_vec()) {
        return Err("the message did not come back".into());
    }
    conn.close(200, "done").await.map_err(|e| e.to_string())
}

#[tokio::main]
async fn main() {
    let dir = PathBuf::from(arg("--certs"));
    let port = arg("--port");
    let identity = |stem: &str| OwnedIdentity {
        der: std::fs::read(dir.join(format!("{stem}.p12"))).expect("p12"),
        password: "pw".to_owned(),
    };
    let plain_url = format!("amqps://guest:guest@localhost:{port}/%2f");
    let external_url = format!("amqps://localhost:{port}/%2f?auth_mechanism=external");
    let checks = [
        (
            "handshake, PLAIN, round trip",
            plain_url.clone(),
            read(&dir, "ca.pem"),
            None,
        ),
        (
            "mutual TLS, EXTERNAL as robot-7",
            external_url.clone(),
            read(&dir, "ca.pem"),
            Some(identity("client")),
        ),
        (
            "server not trusted (rogue CA)",
            plain_url,
            read(&dir, "rogue-ca.pem"),
            None,
        ),
        (
            "client certificate from a rogue CA",
            external_url,
            read(&dir, "ca.pem"),
            Some(identity("rogue")),
        ),
    ];
    for (name, url, ca, identity) in checks {
        let config = OwnedTLSConfig {
            identity,
            cert_chain: Some(ca),
        };
        let outcome = match check(url, config).await {
            Ok(()) => "ok".to_owned(),
            Err(e) => format!("refused: {e}"),
        };
        println!("{}", serde_json::json!({"name": name, "outcome": outcome}));
    }
}
