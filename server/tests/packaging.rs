//! The packaging files (issue 31): `packaging/leveret.service` passes
//! `systemd-analyze verify` (no warning either) with the built binaries in
//! place of `/usr/bin`, every flag its `ExecStart` gives is one `leveret`
//! takes, the broker starts with `packaging/leveret.toml` as its config
//! (listeners and data directory moved aside by the command line, which
//! wins), and the `ExecStartPost` line, run as systemd would run it, waits
//! for that broker and exits 0.

mod common;

use common::ops::{tool_available, OpsBroker};
use std::path::{Path, PathBuf};
use std::process::Command;

fn packaging(file: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../packaging")
        .join(file)
}

fn unit() -> String {
    std::fs::read_to_string(packaging("leveret.service")).expect("the unit file")
}

/// The words of the unit's `KEY=` line.
fn command_line(unit: &str, key: &str) -> Vec<String> {
    let line = unit
        .lines()
        .find_map(|line| line.strip_prefix(&format!("{key}=")))
        .unwrap_or_else(|| panic!("no {key} in the unit"));
    line.split_whitespace().map(str::to_owned).collect()
}

#[test]
fn the_unit_verifies_with_the_built_binaries() {
    if !tool_available("systemd-analyze", "systemd") {
        return;
    }
    let unit = unit()
        .replace("/usr/bin/leveretctl", env!("CARGO_BIN_EXE_leveretctl"))
        .replace(
            "/usr/bin/leveret ",
            &format!("{} ", env!("CARGO_BIN_EXE_leveret")),
        );
    let dir = std::env::temp_dir().join(format!("leveret-unit-{}", std::process::id()));
    std::fs::create_dir_all(&dir).expect("a directory");
    let path = dir.join("leveret.service");
    std::fs::write(&path, unit).expect("write the unit");
    let verified = Command::new("systemd-analyze")
        .arg("verify")
        .arg(&path)
        .output()
        .expect("systemd-analyze runs");
    let _ = std::fs::remove_dir_all(&dir);
    assert!(verified.status.success(), "{verified:?}");
    assert_eq!(
        String::from_utf8_lossy(&verified.stderr),
        "",
        "no warnings (an unknown key is only a warning)"
    );
}

#[test]
fn exec_start_names_real_flags_and_the_example_config_starts_the_broker() {
    let unit = unit();
    let start = command_line(&unit, "ExecStart");
    assert_eq!(start[0], "/usr/bin/leveret");
    let help = Command::new(env!("CARGO_BIN_EXE_leveret"))
        .arg("--help")
        .output()
        .expect("leveret --help");
    let help = String::from_utf8_lossy(&help.stdout);
    for flag in start.iter().filter(|word| word.starts_with("--")) {
        assert!(
            help.contains(flag.as_str()),
            "{flag} is not in leveret --help"
        );
    }
    assert_eq!(
        &start[1..3],
        ["--config", "/etc/leveret/leveret.toml"],
        "the unit reads the example config's installed path"
    );

    let config = packaging("leveret.toml");
    let broker = OpsBroker::start(
        "packaged",
        &["--config", config.to_str().expect("a UTF-8 path")],
    );
    // ExecStartPost as systemd runs it, $LEVERETCTL_ARGS pointing at this
    // broker's API.
    let post = command_line(&unit, "ExecStartPost");
    assert_eq!(post[0], "/usr/bin/leveretctl");
    let url = format!("http://{}", broker.http);
    let args: Vec<&str> = post[1..]
        .iter()
        .flat_map(|word| match word.as_str() {
            "$LEVERETCTL_ARGS" => vec!["--url", url.as_str()],
            other => vec![other],
        })
        .collect();
    let waited = Command::new(env!("CARGO_BIN_EXE_leveretctl"))
        .args(&args)
        .output()
        .expect("leveretctl runs");
    assert!(waited.status.success(), "{args:?}: {waited:?}");
}
