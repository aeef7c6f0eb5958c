//! The broker's layering, held against its code.
//!
//! `src/lib.rs` describes the crate as layers, each using only the layers
//! below it and the shared pieces beside them. This test reads every file
//! under `src/`, finds each path it takes from another of the crate's
//! modules (`use crate::…`, `crate::…` in code, and `super::`
//! paths that climb out of their own module), and checks it against
//! [`LAYERS`]. A reference that runs up a layer fails the test with the
//! file and the module it names. Modules of one layer may use each other;
//! [`SHARED`] modules may be used from every layer. No circle between
//! layers is admitted, and no reference up.

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};

/// Each module, by its path from the crate root, and the layer it sits
/// in: higher numbers sit higher and may use every lower number.
/// [`SHARED`] modules may be used from anywhere. A module is placed by the
/// longest entry its path starts with, so `access::lasting` sits in the
/// operators' layer while the rest of `access` is shared.
const LAYERS: &[(&str, u8)] = &[
    // Highest first, as src/lib.rs's Layout numbers them from the top:
    // 1. Server: the entry point, listeners, connections, recovery, the
    // MQTT front end.
    ("embed", 10),
    ("server", 9),
    ("connection", 9),
    ("recovery", 9),
    ("mqtt", 9),
    // 2. Operators: the admin handle and the same acting as a user (both
    // in admin/); below them the plain structs the handle reads state into
    // and the users, vhosts and permissions it changes, which know no
    // handle.
    ("admin", 8),
    ("inspect", 7),
    ("access::lasting", 7),
    // 3. Channel.
    ("channel", 6),
    // 4. Core.
    ("core", 5),
    // 5. Vhost (with routing and dead-lettering) and exchanges.
    ("vhost", 4),
    ("exchange", 4),
    // 6. Queue; beside it the registry of connections and channels, which
    // names their consumers' links for closing them from outside.
    ("queue", 3),
    ("registry", 3),
    // 7. Consumer and outbox: they know no queue (an unacked delivery's
    // queue is a type parameter the queue layer fixes; an outbox wakes the
    // queues waiting for room through a trait of its own).
    ("consumer", 2),
    ("outbox", 2),
    // Beside the layers: the store.
    ("store", 0),
];

/// Modules every layer may use (they use only each other and the store).
const SHARED: &[&str] = &[
    "access",
    "admission",
    "alarm",
    "arguments",
    "busy_poll",
    "error",
    "limits",
    "message",
    "parameters",
    "policy",
    "slice",
    "stats",
    "tls",
    "word_hash",
];

/// Test and bench support (`#[cfg(test)]`, or the `bench-internals`
/// feature), which build fixtures from every layer; files named `tests.rs`
/// are passed over likewise.
const TEST_SUPPORT: &[&str] = &["testkit", "bench"];

fn src_dir() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("src")
}

fn rust_files(dir: &Path, out: &mut Vec<PathBuf>) {
    for entry in std::fs::read_dir(dir).expect("read src dir") {
        let path = entry.expect("dir entry").path();
        if path.is_dir() {
            rust_files(&path, out);
        } else if path.extension().is_some_and(|e| e == "rs") {
            out.push(path);
        }
    }
}

/// The module path of a file under `src/`: `queue/mod.rs` → `["queue"]`,
/// `queue/dispatch.rs` → `["queue", "dispatch"]`, `lib.rs` → `[]`.
fn module_path(relative: &Path) -> Vec<String> {
    let mut parts: Vec<String> = relative
        .iter()
        .map(|p| p.to_string_lossy().into_owned())
        .collect();
    let file = parts.pop().expect("a file name");
    let stem = file.trim_end_matches(".rs");
    if stem != "mod" && stem != "lib" {
        parts.push(stem.to_string());
    }
    parts
}

/// Strips line comments, block comments and string literals, so a path
/// in prose or in a message is not read as an import.
fn code_only(text: &str) -> String {
    let bytes = text.as_bytes();
    let mut out = String::with_capacity(text.len());
    let mut i = 0;
    while i < bytes.len() {
        match bytes[i] {
            b'/' if bytes.get(i + 1) == Some(&b'/') => {
                while i < bytes.len() && bytes[i] != b'\n' {
                    i += 1;
                }
            }
            b'/' if bytes.get(i + 1) == Some(&b'*') => {
                let mut depth = 0;
                while i < bytes.len() {
                    if bytes[i] == b'/' && bytes.get(i + 1) == Some(&b'*') {
                        depth += 1;
                        i += 2;
                    } else if bytes[i] == b'*' && bytes.get(i + 1) == Some(&b'/') {
                        depth -= 1;
                        i += 2;
                        if depth == 0 {
                            break;
                        }
                    } else {
                        i += 1;
                    }
                }
            }
            b'"' => {
                i += 1;
                while i < bytes.len() && bytes[i] != b'"' {
                    if bytes[i] == b'\\' {
                        i += 1;
                    }
                    i += 1;
                }
                i += 1;
                out.push_str("\"\"");
            }
            b'\'' if bytes.get(i + 2) == Some(&b'\'') || bytes.get(i + 1) == Some(&b'\\') => {
                // a char literal ('x' or '\n'); lifetimes have no closing quote
                i += 1;
                while i < bytes.len() && bytes[i] != b'\'' {
                    if bytes[i] == b'\\' {
                        i += 1;
                    }
                    i += 1;
                }
                i += 1;
            }
            _ => {
                out.push(bytes[i] as char);
                i += 1;
            }
        }
    }
    out
}

fn is_ident(b: u8) -> bool {
    b.is_ascii_alphanumeric() || b == b'_'
}

fn skip_space(code: &[u8], mut i: usize) -> usize {
    while i < code.len() && code[i].is_ascii_whitespace() {
        i += 1;
    }
    i
}

/// The paths named at `start` (just past a `crate::`), each as its
/// segments after `prefix`: `["queue", "Queue"]` for `crate::queue::Queue`,
/// one path per item for `crate::{queue::Queue, outbox}` and for nested
/// groups. Returns where the path ends.
fn paths_at(code: &[u8], start: usize, prefix: &[String], out: &mut Vec<Vec<String>>) -> usize {
    let mut i = skip_space(code, start);
    if code.get(i) == Some(&b'{') {
        i += 1;
        loop {
            i = paths_at(code, i, prefix, out);
            // pass over a rename (`as Name`) to the item's end
            while i < code.len() && code[i] != b',' && code[i] != b'}' {
                i += 1;
            }
            match code.get(i) {
                Some(b',') => i += 1,
                Some(_) => return i + 1,
                None => return i,
            }
        }
    }
    let mut path = prefix.to_vec();
    loop {
        let begin = i;
        while i < code.len() && is_ident(code[i]) {
            i += 1;
        }
        if i == begin {
            break; // `*`, `<` or nothing
        }
        path.push(String::from_utf8_lossy(&code[begin..i]).into_owned());
        let after = skip_space(code, i);
        if !code[after..].starts_with(b"::") {
            break;
        }
        i = skip_space(code, after + 2);
        if code.get(i) == Some(&b'{') {
            return paths_at(code, i, &path, out);
        }
    }
    if !path.is_empty() {
        out.push(path);
    }
    i
}

/// The crate's paths that a file's code names, from the crate root:
/// `crate::` paths, and `super::` paths resolved against the file's own
/// module path.
fn referenced_paths(module: &[String], code: &str) -> Vec<Vec<String>> {
    let bytes = code.as_bytes();
    let mut paths = Vec::new();
    let mut i = 0;
    while i < bytes.len() {
        let preceded_by_ident = i > 0 && (is_ident(bytes[i - 1]) || bytes[i - 1] == b':');
        if !preceded_by_ident && bytes[i..].starts_with(b"crate::") {
            i = paths_at(bytes, i + "crate::".len(), &[], &mut paths).max(i + 1);
        } else if !preceded_by_ident && bytes[i..].starts_with(b"super::") {
            // climb: each `super::` drops one segment of this file's module
            let mut depth = module.len();
            let mut j = i;
            while bytes[j..].starts_with(b"super::") {
                depth = depth.saturating_sub(1);
                j += "super::".len();
            }
            i = paths_at(bytes, j, &module[..depth], &mut paths).max(j);
        } else {
            i += 1;
        }
    }
    paths
}

/// Where a module path sits: the longest entry of [`LAYERS`] or [`SHARED`]
/// that it starts with, and that entry's layer (`None` for a shared one).
fn place(path: &[String]) -> Option<(&'static str, Option<u8>)> {
    let starts = |entry: &str| {
        let segments: Vec<&str> = entry.split("::").collect();
        segments.len() <= path.len() && segments.iter().zip(path).all(|(a, b)| a == b)
    };
    LAYERS
        .iter()
        .map(|&(entry, layer)| (entry, Some(layer)))
        .chain(SHARED.iter().map(|&entry| (entry, None)))
        .filter(|(entry, _)| starts(entry))
        .max_by_key(|(entry, _)| entry.split("::").count())
}

/// The entries of [`LAYERS`] and [`SHARED`] that a file's code names, with
/// their layers.
fn referenced_modules(module: &[String], code: &str) -> BTreeMap<&'static str, Option<u8>> {
    referenced_paths(module, code)
        .iter()
        .filter_map(|path| place(path))
        .collect()
}

#[derive(Debug, PartialEq, Eq, PartialOrd, Ord)]
struct Reference {
    file: String,
    module: String,
}

/// Every reference up a layer in the crate's files, sorted.
fn upward_references() -> Vec<Reference> {
    let src = src_dir();
    let mut files = Vec::new();
    rust_files(&src, &mut files);
    let mut upward = Vec::new();
    for path in files {
        let relative = path.strip_prefix(&src).expect("under src");
        let text = std::fs::read_to_string(&path).expect("read source");
        upward.extend(upward_in(relative, &text));
    }
    upward.sort();
    upward
}

/// The references up a layer in one file: `relative` is its path under
/// `src/`, `text` its source.
fn upward_in(relative: &Path, text: &str) -> Vec<Reference> {
    let module = module_path(relative);
    let Some(top) = module.first() else {
        return Vec::new(); // lib.rs declares and re-exports everything
    };
    if TEST_SUPPORT.contains(&top.as_str()) || module.last().is_some_and(|m| m == "tests") {
        return Vec::new(); // test support reaches into every layer on purpose
    }
    let (own, own_layer) = place(&module).unwrap_or_else(|| {
        panic!("module `{top}` ({relative:?}) is in no layer: add it to LAYERS or SHARED")
    });
    let own_layer = own_layer.unwrap_or(0);
    let mut upward = Vec::new();
    for (name, their_layer) in referenced_modules(&module, &code_only(text)) {
        let Some(their_layer) = their_layer else {
            continue; // a shared piece
        };
        if name != own && their_layer > own_layer {
            upward.push(Reference {
                file: relative.to_string_lossy().into_owned(),
                module: name.to_string(),
            });
        }
    }
    upward
}

#[test]
fn no_module_uses_a_layer_above_it() {
    let upward = upward_references();
    assert!(
        upward.is_empty(),
        "these files use a module of a layer above their own (see src/lib.rs's Layout and LAYERS in this test):\n{}",
        upward
            .iter()
            .map(|r| format!("  src/{} uses crate::{}", r.file, r.module))
            .collect::<Vec<_>>()
            .join("\n")
    );
}

#[test]
fn the_reader_finds_grouped_inline_and_super_paths() {
    let module = vec!["channel".to_string(), "basic".to_string()];
    let code = code_only(
        "use crate::{queue::Queue, outbox::{Outbound, Outbox}};\n\
         // crate::admin in a comment\n\
         let s = \"crate::inspect in a string\";\n\
         fn f() { crate::vhost::route(); super::super::core::Core::new(); super::tx::x(); }\n\
         use crate::access::{auth::User, lasting::{at_start, AccessError as E}};",
    );
    let found: BTreeSet<&str> = referenced_modules(&module, &code).into_keys().collect();
    let expected: BTreeSet<&str> = [
        "queue",
        "outbox",
        "vhost",
        "core",
        "channel",
        "access",
        "access::lasting",
    ]
    .into_iter()
    .collect();
    assert_eq!(found, expected);
}

/// The check on deliberate violations: the consumer layer and the outbox
/// naming the queue (the circle the crate once had), a queue file climbing
/// to the channel with `super::`, a shared piece naming the core, and the
/// operators' views naming their handle, a shared piece of `access` and
/// the channel naming `access::lasting` (a module placed by a longer path
/// than its folder's); a reference down, beside or to a shared piece
/// passes.
#[test]
fn a_reference_up_a_layer_is_reported_with_its_file_and_module() {
    let up = |file: &str, module: &str| Reference {
        file: file.to_string(),
        module: module.to_string(),
    };
    let check = |file: &str, text: &str| upward_in(Path::new(file), text);
    assert_eq!(
        check(
            "consumer.rs",
            "use crate::outbox::Outbox;\npub struct Unacked { pub queue: Arc<crate::queue::Queue> }"
        ),
        [up("consumer.rs", "queue")]
    );
    assert_eq!(
        check("outbox.rs", "use crate::{message::Message, queue::Queue};"),
        [up("outbox.rs", "queue")]
    );
    assert_eq!(
        check(
            "queue/dispatch.rs",
            "use super::Queue;\nuse super::super::channel::Channel;"
        ),
        [up("queue/dispatch.rs", "channel")]
    );
    assert_eq!(
        check("stats.rs", "use crate::core::Core;"),
        [up("stats.rs", "core")]
    );
    assert_eq!(
        check(
            "inspect.rs",
            "use crate::admin::Admin;\nuse crate::queue::Queue;"
        ),
        [up("inspect.rs", "admin")]
    );
    assert_eq!(
        check(
            "channel/basic.rs",
            "use crate::queue::{Consumer, Unacked};\nuse crate::admin::Admin as _;\nuse crate::stats::QueueCounters;"
        ),
        [up("channel/basic.rs", "admin")]
    );
    assert_eq!(
        check(
            "access/auth.rs",
            "use super::password::PasswordHash;\nuse crate::access::lasting::at_start;"
        ),
        [up("access/auth.rs", "access::lasting")]
    );
    assert_eq!(
        check(
            "channel/mod.rs",
            "use crate::access::{permissions::Permission, lasting::AccessError};"
        ),
        [up("channel/mod.rs", "access::lasting")]
    );
    assert_eq!(
        check(
            "access/lasting.rs",
            "use crate::access::auth::Users;\nuse crate::store::StoreOp;"
        ),
        []
    );
}
