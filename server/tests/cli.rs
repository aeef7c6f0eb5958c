//! The `leveret` binary's command line and config file, end to end: the
//! password hash it prints is one its config accepts, a config file's users
//! and vhosts are what the broker serves, and a config it cannot use stops
//! it with status 2 and a message naming the file.

mod common;

use common::BrokerProcess;
use lapin::{Connection, ConnectionProperties};
use leveret_broker::PasswordHash;
use std::ffi::OsStr;
use std::io::Write;
use std::path::PathBuf;
use std::process::{Command, Stdio};
use std::time::Duration;

fn scratch(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("leveret-cli-{}-{name}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).expect("scratch dir");
    dir
}

fn hash_password(password: &str) -> String {
    let mut child = Command::new(env!("CARGO_BIN_EXE_leveret"))
        .arg("--hash-password")
        .stdin(Stdio::piped())
        .stdout(Stdio::piped())
        .spawn()
        .expect("start leveret --hash-password");
    writeln!(child.stdin.take().expect("stdin"), "{password}").expect("write the password");
    let output = child.wait_with_output().expect("leveret --hash-password");
    assert!(output.status.success(), "{output:?}");
    String::from_utf8(output.stdout)
        .expect("utf-8")
        .trim()
        .to_owned()
}

async fn connects(url: &str) -> bool {
    let attempt = Connection::connect(url, ConnectionProperties::default());
    match tokio::time::timeout(Duration::from_secs(10), attempt).await {
        Ok(Ok(connection)) => {
            let _ = connection.close(200, "bye").await;
            true
        }
        Ok(Err(_)) => false,
        Err(_) => panic!("no answer from {url}"),
    }
}

/// `rabbitmqctl add_user robot512 robot-pw` on RabbitMQ 3.10 with
/// `password_hashing_module` set to `rabbit_password_hashing_sha512`, as
/// `export_definitions` gave it (the hash does not depend on the name).
const RABBITMQ_SHA512: &str =
    "QAJWCkh0XzlKuSwlxX7hzyjZmn6as792tFARsbbDNmV8vzgtI31i5J24yPZQLbAvHYllEK9xcKzusoOUeakD4AfG74E=";

#[test]
fn hash_password_prints_a_hash_of_standard_input() {
    let printed = hash_password("s3cret");
    assert!(printed.starts_with("$argon2id$v=19$"), "{printed}");
    let hash = PasswordHash::parse(&printed).expect("a leveret hash");
    assert!(hash.verify(b"s3cret"));
    assert!(!hash.verify(b"s3cret\n"), "the newline is not part of it");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_config_files_users_and_vhosts_are_served() {
    let dir = scratch("users");
    let config = dir.join("leveret.toml");
    std::fs::write(
        &config,
        format!(
            "vhosts = [\"robots\"]\n\n[[users]]\nname = \"robot\"\npassword-hash = \"{}\"\n\
             [[users.permissions]]\nvhost = \"robots\"\nconfigure = \".*\"\nwrite = \".*\"\nread = \".*\"\n\n\
             [[users]]\nname = \"moved\"\npassword-hash = \"{RABBITMQ_SHA512}\"\n\
             hashing-algorithm = \"rabbit_password_hashing_sha512\"\n\
             [[users.permissions]]\nvhost = \"robots\"\nconfigure = \".*\"\nwrite = \".*\"\nread = \".*\"\n",
            hash_password("s3cret")
        ),
    )
    .expect("write the config");
    let broker = BrokerProcess::start_with(
        &dir.join("data"),
        [OsStr::new("--config"), config.as_os_str()],
    )
    .await;
    let robots =
        |user: &str, password: &str| broker.url_as(user, password).replace("/%2f", "/robots");
    assert!(
        connects(&robots("robot", "s3cret")).await,
        "robot reaches vhost robots"
    );
    assert!(
        !connects(&robots("robot", "wrong")).await,
        "a wrong password is refused"
    );
    assert!(
        connects(&robots("robot", "s3cret")).await,
        "again (the argon2id check passed once and is remembered)"
    );
    assert!(
        connects(&robots("moved", "robot-pw")).await,
        "a user exported from RabbitMQ logs in with its password"
    );
    assert!(!connects(&robots("moved", "robot-pW")).await);
    assert!(
        !connects(&robots("guest", "guest")).await,
        "guest exists only when the config names no users"
    );
    broker.terminate();
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn an_unusable_config_exits_with_status_2_naming_the_file() {
    let dir = scratch("bad");
    let unknown_key = dir.join("unknown-key.toml");
    std::fs::write(&unknown_key, "listne = [\"127.0.0.1:1\"]\n").expect("write");
    let missing = dir.join("missing.toml");
    for config in [unknown_key, missing] {
        let output = Command::new(env!("CARGO_BIN_EXE_leveret"))
            .arg("--config")
            .arg(&config)
            .output()
            .expect("run leveret");
        assert_eq!(output.status.code(), Some(2), "{output:?}");
        let stderr = String::from_utf8_lossy(&output.stderr);
        assert!(
            stderr.contains(&*config.to_string_lossy()),
            "stderr names {}: {stderr}",
            config.display()
        );
    }
    let _ = std::fs::remove_dir_all(&dir);
}
