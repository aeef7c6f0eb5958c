//! Rust scenario driver (lapin and amqprs), same protocol as python/harness.py:
//!
//!     conformance-rust --lib lapin|amqprs --list
//!     conformance-rust --lib lapin|amqprs --url URL --prefix P [--only a,b]
//!
//! prints {"start": name} then one result record per scenario.

use serde_json::{json, Value};
use std::future::Future;
use std::pin::Pin;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

mod s_amqprs;
mod s_lapin;

pub type R = Result<(), String>;
pub type Fut = Pin<Box<dyn Future<Output = R> + Send>>;

pub struct Scenario {
    pub name: &'static str,
    pub run: fn(Arc<T>) -> Fut,
}

#[macro_export]
macro_rules! scenarios {
    ($lib:literal: $($name:literal => $f:ident),* $(,)?) => {
        pub fn all() -> Vec<$crate::Scenario> {
            vec![$($crate::Scenario { name: concat!($lib, ".", $name), run: |t| Box::pin($f(t)) }),*]
        }
    };
}

#[macro_export]
macro_rules! check {
    ($cond:expr, $($msg:tt)*) => {
        if !$cond {
            return Err(format!($($msg)*));
        }
    };
}

/// `e(result, "what")?` turns a client error into a scenario failure.
pub fn e<V, E: std::fmt::Debug>(r: Result<V, E>, what: &str) -> Result<V, String> {
    r.map_err(|err| format!("{what}: {err:?}"))
}

pub struct T {
    pub url: String,
    pub prefix: String,
    pub host: String,
    pub port: u16,
    pub user: String,
    pub password: String,
    pub vhost: String,
    obs: Mutex<Vec<Value>>,
}

fn pct_decode(s: &str) -> String {
    let b = s.as_bytes();
    let mut out = Vec::new();
    let mut i = 0;
    while i < b.len() {
        if b[i] == b'%' && i + 2 < b.len() {
            if let Ok(v) = u8::from_str_radix(&s[i + 1..i + 3], 16) {
                out.push(v);
                i += 3;
                continue;
            }
        }
        out.push(b[i]);
        i += 1;
    }
    String::from_utf8_lossy(&out).into_owned()
}

fn pct_encode(s: &str) -> String {
    s.bytes()
        .map(|c| {
            if c.is_ascii_alphanumeric() || b"-._~".contains(&c) {
                (c as char).to_string()
            } else {
                format!("%{c:02X}")
            }
        })
        .collect()
}

impl T {
    fn new(url: &str, prefix: &str) -> T {
        let rest = url.trim_start_matches("amqp://");
        let (auth, hostpart) = rest.split_once('@').unwrap_or(("guest:guest", rest));
        let (user, password) = auth.split_once(':').unwrap_or((auth, ""));
        let (hostport, vhost) = hostpart.split_once('/').unwrap_or((hostpart, ""));
        let vhost = vhost.split('?').next().unwrap_or("");
        let (host, port) = hostport.rsplit_once(':').unwrap_or((hostport, "5672"));
        T {
            url: url.to_string(),
            prefix: prefix.to_string(),
            host: host.to_string(),
            port: port.parse().unwrap_or(5672),
            user: pct_decode(user),
            password: pct_decode(password),
            vhost: if vhost.is_empty() {
                "/".into()
            } else {
                pct_decode(vhost)
            },
            obs: Mutex::new(Vec::new()),
        }
    }

    pub fn n(&self, name: &str) -> String {
        format!("{}{}", self.prefix, name)
    }

    pub fn url_with(
        &self,
        user: Option<&str>,
        password: Option<&str>,
        vhost: Option<&str>,
    ) -> String {
        format!(
            "amqp://{}:{}@{}:{}/{}",
            pct_encode(user.unwrap_or(&self.user)),
            pct_encode(password.unwrap_or(&self.password)),
            self.host,
            self.port,
            pct_encode(vhost.unwrap_or(&self.vhost))
        )
    }

    pub fn obs(&self, label: &str, v: Value) {
        self.obs.lock().unwrap().push(json!([label, v]));
    }

    pub fn eq(&self, label: &str, actual: Value, expected: Value) -> R {
        self.obs(label, actual.clone());
        if actual != expected {
            return Err(format!("{label}: expected {expected}, got {actual}"));
        }
        Ok(())
    }
}

/// How long a scenario waits for something it expects: a hang limit,
/// generous enough for a loaded CI machine (the wait ends as soon as the
/// thing happens).
pub const HANG: Duration = Duration::from_secs(30);

pub async fn wait_until<F, Fu>(timeout: Duration, what: &str, mut pred: F) -> R
where
    F: FnMut() -> Fu,
    Fu: Future<Output = bool>,
{
    let deadline = Instant::now() + timeout;
    while Instant::now() < deadline {
        if pred().await {
            return Ok(());
        }
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    Err(format!("timed out after {timeout:?} waiting for {what}"))
}

pub fn reply_name(text: &str) -> String {
    text.split(" - ").next().unwrap_or("").trim().to_string()
}

#[tokio::main]
async fn main() {
    let args: Vec<String> = std::env::args().collect();
    let arg = |k: &str| {
        args.iter()
            .position(|a| a == k)
            .and_then(|i| args.get(i + 1))
            .cloned()
    };
    let lib = arg("--lib").unwrap_or_default();
    let mut all = Vec::new();
    if lib.is_empty() || lib == "lapin" {
        all.extend(s_lapin::all());
    }
    if lib.is_empty() || lib == "amqprs" {
        all.extend(s_amqprs::all());
    }
    if args.iter().any(|a| a == "--list") {
        for s in &all {
            println!("{}", s.name);
        }
        return;
    }
    let url = arg("--url").expect("--url");
    let prefix = arg("--prefix").unwrap_or_else(|| "cf-".into());
    let only: Vec<String> = arg("--only")
        .unwrap_or_default()
        .split(',')
        .filter(|s| !s.is_empty())
        .map(String::from)
        .collect();
    for s in all {
        if !only.is_empty() && !only.iter().any(|o| o == s.name) {
            continue;
        }
        println!("{}", json!({ "start": s.name }));
        let t = Arc::new(T::new(&url, &prefix));
        let started = Instant::now();
        let handle = tokio::spawn((s.run)(t.clone()));
        let result = match tokio::time::timeout(Duration::from_secs(60), handle).await {
            Ok(Ok(r)) => r,
            Ok(Err(join)) => Err(format!("panicked: {join}")),
            Err(_) => Err("scenario timed out after 60s".into()),
        };
        let obs = t.obs.lock().unwrap().clone();
        let (ok, error) = match result {
            Ok(()) => (true, Value::Null),
            Err(m) => (false, Value::String(m)),
        };
        println!(
            "{}",
            json!({ "name": s.name, "ok": ok, "error": error, "obs": obs, "ms": started.elapsed().as_millis() as u64 })
        );
    }
    std::process::exit(0);
}
