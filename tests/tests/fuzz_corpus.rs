//! Replays the broker-level fuzz target's committed inputs
//! (`fuzz/corpus/broker/` and the findings kept in `fuzz/regressions/broker/`)
//! through the same driver the fuzzer uses, so every input that once
//! crashed, froze or exhausted the broker stays a test.

use arbitrary::{Arbitrary, Unstructured};
use leveret_tests::driver::{self, Argument, Key, Name, Op, Props, Script, Step};
use std::path::{Path, PathBuf};

fn inputs(dir: &str) -> Vec<PathBuf> {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("..").join(dir);
    let mut files: Vec<PathBuf> = std::fs::read_dir(&dir)
        .unwrap_or_else(|e| panic!("{}: {e}", dir.display()))
        .filter_map(|entry| entry.ok().map(|e| e.path()))
        .filter(|path| path.is_file())
        .collect();
    files.sort();
    files
}

fn replay(dir: &str) -> usize {
    let files = inputs(dir);
    for file in &files {
        let data = std::fs::read(file).expect("readable input");
        // libfuzzer-sys builds the target's argument the same way.
        let Ok(script) = Script::arbitrary_take_rest(Unstructured::new(&data)) else {
            continue;
        };
        eprintln!("replaying {}", file.display());
        driver::run(&script);
    }
    files.len()
}

#[test]
fn fuzz_findings_stay_fixed() {
    replay("fuzz/regressions/broker");
}

#[test]
fn fuzz_corpus_replays() {
    assert!(
        replay("fuzz/corpus/broker") > 0,
        "the broker fuzz corpus is committed"
    );
}

fn publish_to(queue: Name) -> Step {
    Step::Send {
        connection: 0,
        channel: 0,
        op: Op::Publish {
            exchange: Name::Empty,
            key: Key::Name(queue),
            flags: 0,
            props: Props {
                delivery_mode: None,
                priority: None,
                expiration: None,
                headers: Vec::new(),
                reply_to: None,
            },
            body: 3,
        },
    }
}

fn declare(queue: Name, arguments: Vec<Argument>) -> Step {
    Step::Send {
        connection: 0,
        channel: 0,
        op: Op::QueueDeclare {
            name: queue,
            flags: 0,
            arguments,
        },
    }
}

const OPEN: Step = Step::Send {
    connection: 0,
    channel: 0,
    op: Op::ChannelOpen,
};

/// Issue 12: a queue that dead-letters to itself through the default
/// exchange, with `x-max-length: 0`, overflowed the stack on one publish.
#[test]
fn dead_letter_self_cycle_by_max_length() {
    for multi_thread in [false, true] {
        driver::run(&Script {
            multi_thread,
            steps: vec![
                OPEN,
                declare(
                    Name::Q0,
                    vec![
                        Argument::MaxLength(0),
                        Argument::DeadLetterExchange(Name::Empty),
                    ],
                ),
                publish_to(Name::Q0),
                Step::Pause,
            ],
        });
    }
}

/// The TTL variant: two queues with `x-message-ttl: 0` dead-lettering to
/// each other.
#[test]
fn dead_letter_cycle_by_ttl() {
    for multi_thread in [false, true] {
        driver::run(&Script {
            multi_thread,
            steps: vec![
                OPEN,
                declare(
                    Name::Q0,
                    vec![
                        Argument::MessageTtl(0),
                        Argument::DeadLetterExchange(Name::Empty),
                        Argument::DeadLetterRoutingKey(Key::Name(Name::Q1)),
                    ],
                ),
                declare(
                    Name::Q1,
                    vec![
                        Argument::MessageTtl(0),
                        Argument::DeadLetterExchange(Name::Empty),
                        Argument::DeadLetterRoutingKey(Key::Name(Name::Q0)),
                    ],
                ),
                publish_to(Name::Q0),
                Step::Pause,
                Step::Pause,
            ],
        });
    }
}
