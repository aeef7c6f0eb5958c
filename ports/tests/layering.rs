//! The crate boundary, read from the sources: the ports are built on the
//! client's public API only (no `leveret_protocol`, not even through the
//! client's `protocol` re-export), and the client carries no ports; the
//! client's `Dedupe` still knows a port's message by its headers.

use std::path::{Path, PathBuf};

/// Every `.rs` file under `dir`, depth first.
fn rust_files(dir: &Path) -> Vec<PathBuf> {
    let mut files = Vec::new();
    let mut dirs = vec![dir.to_path_buf()];
    while let Some(dir) = dirs.pop() {
        for entry in std::fs::read_dir(&dir).unwrap_or_else(|e| panic!("{}: {e}", dir.display())) {
            let path = entry.expect("directory entry").path();
            if path.is_dir() {
                dirs.push(path);
            } else if path.extension().is_some_and(|ext| ext == "rs") {
                files.push(path);
            }
        }
    }
    files.sort();
    files
}

fn manifest_dir() -> &'static Path {
    Path::new(env!("CARGO_MANIFEST_DIR"))
}

/// The lines of `file` (code, not comments) that mention one of `names`.
fn offending_lines(file: &Path, names: &[&str]) -> Vec<String> {
    let text = std::fs::read_to_string(file).unwrap_or_else(|e| panic!("{}: {e}", file.display()));
    text.lines()
        .enumerate()
        .filter(|(_, line)| !line.trim_start().starts_with("//"))
        .filter(|(_, line)| names.iter().any(|name| line.contains(name)))
        .map(|(number, line)| format!("{}:{}: {}", file.display(), number + 1, line.trim()))
        .collect()
}

#[test]
fn ports_use_only_the_clients_public_api() {
    let files = rust_files(&manifest_dir().join("src"));
    assert!(files.len() >= 10, "the ports' sources: {files:?}");
    let offending: Vec<String> = files
        .iter()
        .flat_map(|file| offending_lines(file, &["leveret_protocol", "leveret_client::protocol"]))
        .collect();
    assert!(
        offending.is_empty(),
        "protocol imports in ports/src:\n{}",
        offending.join("\n")
    );
    let manifest = std::fs::read_to_string(manifest_dir().join("Cargo.toml")).expect("Cargo.toml");
    assert!(
        !manifest.contains("leveret-protocol"),
        "ports/Cargo.toml depends on leveret-protocol"
    );
}

#[test]
fn the_client_carries_no_ports() {
    let client = manifest_dir().join("../client");
    assert!(
        !client.join("src/ports").exists() && !client.join("src/ports.rs").exists(),
        "client/src has a ports module again"
    );
    let offending: Vec<String> = rust_files(&client.join("src"))
        .iter()
        .flat_map(|file| offending_lines(file, &["mod ports", "leveret_ports"]))
        .collect();
    assert!(
        offending.is_empty(),
        "ports in client/src:\n{}",
        offending.join("\n")
    );
    let manifest = std::fs::read_to_string(client.join("Cargo.toml")).expect("client/Cargo.toml");
    for ports_only in ["postcard", "leveret-ports"] {
        assert!(
            !manifest.contains(ports_only),
            "client/Cargo.toml depends on {ports_only}"
        );
    }
}

/// `leveret_client::identity` names a port's message by the headers the
/// out-port stamps: the client keeps their names without depending on
/// this crate, so this is where they must agree.
#[test]
fn the_clients_dedupe_reads_the_ports_headers() {
    let mut headers = leveret_client::FieldTable::new();
    headers.insert(
        leveret_client::ShortStr::from_static(leveret_ports::PORT_HEADER),
        leveret_client::FieldValue::string("pose-out-1"),
    );
    headers.insert(
        leveret_client::ShortStr::from_static(leveret_ports::SEQ_HEADER),
        leveret_client::FieldValue::I64(7),
    );
    let properties = leveret_client::BasicProperties {
        headers: Some(headers),
        ..Default::default()
    };
    assert_eq!(
        leveret_client::identity(&properties).as_deref(),
        Some("port:pose-out-1:7")
    );
}
