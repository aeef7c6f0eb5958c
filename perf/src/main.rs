//! `leveret-perf`: a load generator for any AMQP 0.9.1 broker; see the
//! library's documentation and `leveret-perf --help`.

use clap::Parser;
use std::process::ExitCode;

fn main() -> ExitCode {
    let cli = leveret_perf::cli::Cli::parse();
    match leveret_perf::cli::main_with(cli) {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("leveret-perf: {e}");
            ExitCode::FAILURE
        }
    }
}
