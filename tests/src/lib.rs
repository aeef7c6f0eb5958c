//! Helpers for the cross-crate integration tests in `tests/tests/`.
//!
//! Every test gets its broker from [`broker`]:
//!
//! - with `LEVERET_TEST_AMQP_URL` set (for example
//!   `amqp://guest:guest@127.0.0.1:5672/%2f`), the tests run against that
//!   external broker (this is how the suite is validated against RabbitMQ);
//! - otherwise an in-process Leveret is started on `127.0.0.1:0` and shut
//!   down when the [`TestBroker`] is stopped or dropped.
//!
//! Tests share one external broker and run concurrently, so every queue and
//! exchange a test creates gets a name from [`unique`].
//!
//! Every test runs twice, on a current-thread and on a multi-thread runtime:
//! write it as an `async fn` under [`both_runtimes`] (re-exported from
//! `leveret-test-macros`) instead of `#[tokio::test]`. The in-process
//! broker starts on the test's runtime, as it does in an embedding
//! application.
//!
//! [`driver`] is the scripted adversarial peer behind the broker-level fuzz
//! target and the corpus replay test; [`fault_proxy`] injects a link's
//! faults (freeze, cut, latency, a bandwidth cap, a cut mid-frame) for the
//! client's and the uplink's tests; [`rabbit_node`] starts RabbitMQ nodes
//! of a test's own; [`certs`] makes the TLS tests' certificates;
//! [`reserved_port`] gives addresses a test binds again after an outage.

#![deny(missing_docs)]
#![forbid(unsafe_code)]

use std::net::SocketAddr;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::{SystemTime, UNIX_EPOCH};

use leveret_broker::{Broker, BrokerBuilder, BrokerHandle};
pub use leveret_test_macros::both_runtimes;

pub mod certs;
pub mod driver;
pub mod fault_proxy;
pub mod rabbit_node;
pub mod reserved_port;

/// The environment variable naming an external broker to test against.
pub const URL_ENV: &str = "LEVERET_TEST_AMQP_URL";

/// A broker for one test: either an external one named by
/// `LEVERET_TEST_AMQP_URL` or an in-process Leveret.
pub struct TestBroker {
    url: String,
    host: String,
    port: u16,
    handle: Option<BrokerHandle>,
}

/// Starts (or points at) the broker for one test.
///
/// # Panics
///
/// When the in-process broker cannot start, or the URL in
/// `LEVERET_TEST_AMQP_URL` has no parsable host and port.
pub async fn broker() -> TestBroker {
    match std::env::var(URL_ENV) {
        Ok(url) if !url.trim().is_empty() => TestBroker::external(url.trim()),
        _ => TestBroker::in_process().await,
    }
}

impl TestBroker {
    fn external(url: &str) -> Self {
        let (host, port) = host_port(url)
            .unwrap_or_else(|| panic!("{URL_ENV}={url:?} has no host:port I can parse"));
        TestBroker {
            url: url.to_owned(),
            host,
            port,
            handle: None,
        }
    }

    async fn in_process() -> Self {
        Self::leveret(Broker::builder()).await
    }

    /// An in-process Leveret from `builder` (for tests of a Leveret
    /// setting), listening on `127.0.0.1:0`.
    ///
    /// # Panics
    ///
    /// When the broker cannot start.
    pub async fn leveret(builder: BrokerBuilder) -> Self {
        let listen: SocketAddr = "127.0.0.1:0".parse().expect("static address");
        let handle = builder.listen(listen).start().await.unwrap_or_else(|e| {
            panic!("in-process Leveret failed to start: {e} (set {URL_ENV} to test an external broker)")
        });
        let addr = *handle
            .local_addrs()
            .first()
            .expect("the broker reports the address it listens on");
        TestBroker {
            url: format!("amqp://guest:guest@{}:{}/%2f", addr.ip(), addr.port()),
            host: addr.ip().to_string(),
            port: addr.port(),
            handle: Some(handle),
        }
    }

    /// The AMQP URL of the default vhost with guest/guest credentials.
    pub fn url(&self) -> &str {
        &self.url
    }

    /// The URL for another vhost (percent-encoded by the caller) and
    /// credentials.
    pub fn url_with(&self, user: &str, password: &str, vhost: &str) -> String {
        format!(
            "amqp://{user}:{password}@{}:{}/{vhost}",
            self.host_for_url(),
            self.port
        )
    }

    fn host_for_url(&self) -> String {
        if self.host.contains(':') {
            format!("[{}]", self.host)
        } else {
            self.host.clone()
        }
    }

    /// `host:port`, for raw sockets.
    pub fn addr(&self) -> String {
        format!("{}:{}", self.host_for_url(), self.port)
    }

    /// The host (an IP address or name, without brackets).
    pub fn host(&self) -> &str {
        &self.host
    }

    /// The TCP port.
    pub fn port(&self) -> u16 {
        self.port
    }

    /// The in-process broker's first MQTT listener, if it has one (`None`
    /// for an external broker).
    pub fn mqtt_addr(&self) -> Option<SocketAddr> {
        self.handle.as_ref()?.mqtt_addrs().first().copied()
    }

    /// The in-process broker's administration handle (`None` for an
    /// external broker).
    pub fn admin(&self) -> Option<leveret_broker::Admin> {
        self.handle.as_ref().map(BrokerHandle::admin)
    }

    /// Whether this is an external broker (`LEVERET_TEST_AMQP_URL`).
    pub fn is_external(&self) -> bool {
        self.handle.is_none()
    }

    /// Shuts an in-process broker down and waits for it; does nothing for
    /// an external one.
    pub async fn stop(mut self) {
        if let Some(handle) = self.handle.take() {
            handle.shutdown().await;
        }
    }
}

impl Drop for TestBroker {
    fn drop(&mut self) {
        let Some(handle) = self.handle.take() else {
            return;
        };
        // Drop cannot await: on a multi-threaded runtime wait for the
        // shutdown in place, otherwise hand it to the runtime (whose
        // teardown at the end of the test ends the broker's tasks anyway).
        if let Ok(rt) = tokio::runtime::Handle::try_current() {
            match rt.runtime_flavor() {
                tokio::runtime::RuntimeFlavor::MultiThread => {
                    tokio::task::block_in_place(|| rt.block_on(handle.shutdown()));
                }
                _ => {
                    rt.spawn(handle.shutdown());
                }
            }
        }
    }
}

/// Host and port out of `amqp://user:pass@host:port/vhost` (port defaults
/// to 5672).
fn host_port(url: &str) -> Option<(String, u16)> {
    let rest = url
        .strip_prefix("amqp://")
        .or_else(|| url.strip_prefix("amqps://"))?;
    let authority = rest.split('/').next()?;
    let hostport = authority.rsplit('@').next()?;
    if let Some(v6) = hostport.strip_prefix('[') {
        let (host, after) = v6.split_once(']')?;
        let port = match after.strip_prefix(':') {
            Some(p) => p.parse().ok()?,
            None => 5672,
        };
        return Some((host.to_owned(), port));
    }
    match hostport.rsplit_once(':') {
        Some((host, port)) => Some((host.to_owned(), port.parse().ok()?)),
        None => Some((hostport.to_owned(), 5672)),
    }
}

/// A name no other test (in this process or another run) uses:
/// `prefix.PID.COUNTER.NANOS`. Never starts with `amq.` unless `prefix`
/// does.
pub fn unique(prefix: &str) -> String {
    static COUNTER: AtomicU64 = AtomicU64::new(0);
    let n = COUNTER.fetch_add(1, Ordering::Relaxed);
    let nanos = SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map(|d| d.subsec_nanos())
        .unwrap_or(0);
    format!("{prefix}.{}.{n}.{nanos:x}", std::process::id())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parses_urls() {
        assert_eq!(
            host_port("amqp://guest:guest@127.0.0.1:5672/%2f"),
            Some(("127.0.0.1".into(), 5672))
        );
        assert_eq!(
            host_port("amqp://localhost/vh"),
            Some(("localhost".into(), 5672))
        );
        assert_eq!(
            host_port("amqp://u:p@[::1]:5673/%2f"),
            Some(("::1".into(), 5673))
        );
    }

    #[test]
    fn unique_names_differ() {
        let a = unique("q");
        let b = unique("q");
        assert_ne!(a, b);
        assert!(a.starts_with("q."));
        assert!(a.len() < 255);
    }
}
