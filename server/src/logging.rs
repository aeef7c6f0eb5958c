//! Logging set-up: `tracing` events from the library, formatted to
//! standard error, filtered by `--log` (a level or a tracing filter such
//! as `leveret_broker=debug,info`).

/// Installs the subscriber. Directives of the filter that do not parse are
/// ignored, as `tracing_subscriber::EnvFilter::new` does.
pub fn init(filter: &str) {
    tracing_subscriber::fmt()
        .with_env_filter(tracing_subscriber::EnvFilter::new(filter))
        .with_writer(std::io::stderr)
        .init();
}
