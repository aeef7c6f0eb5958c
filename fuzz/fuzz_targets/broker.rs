//! The broker-level fuzz target: arbitrary scripts of methods, content and
//! raw bytes from several connections and channels against an in-process
//! broker (`leveret_tests::driver`). A panic anywhere, a broker that stops
//! reading or answering, or memory past libFuzzer's RSS limit is a finding.
#![no_main]

use libfuzzer_sys::fuzz_target;
use leveret_tests::driver::{run, Script};

fuzz_target!(|script: Script| run(&script));
