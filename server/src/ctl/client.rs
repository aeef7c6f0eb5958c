//! The management API over plain HTTP/1.1 (ureq, blocking: a command
//! makes a request or two and exits), with basic auth. Errors carry what
//! the broker said (`reason`) or why it could not be reached.

use base64::Engine;
use serde_json::Value;
use std::time::Duration;

/// Why a request failed.
#[derive(Debug, thiserror::Error)]
pub enum ClientError {
    /// Nothing answered at the URL.
    #[error("cannot reach the management API at {url}: {detail}")]
    Unreachable {
        /// The base URL.
        url: String,
        /// The transport's error.
        detail: String,
    },
    /// The API answered with an error.
    #[error("{status}: {reason}")]
    Api {
        /// HTTP status.
        status: u16,
        /// RabbitMQ's `reason`, or the body.
        reason: String,
    },
}

/// A management API endpoint with credentials.
pub struct Client {
    base: String,
    authorization: String,
    agent: ureq::Agent,
}

/// Percent-encodes one path segment (a vhost `/` is `%2F`).
pub fn segment(text: &str) -> String {
    text.bytes()
        .map(|b| match b {
            b'a'..=b'z' | b'A'..=b'Z' | b'0'..=b'9' | b'-' | b'_' | b'.' | b'~' => {
                (b as char).to_string()
            }
            other => format!("%{other:02X}"),
        })
        .collect()
}

/// Longest a request may take unless told otherwise, in seconds.
pub const DEFAULT_TIMEOUT_SECS: u64 = 60;

fn agent(timeout: Duration) -> ureq::Agent {
    ureq::Agent::config_builder()
        .http_status_as_error(false)
        .timeout_global(Some(timeout))
        .build()
        .into()
}

impl Client {
    /// A client of the API at `base` (`http://HOST:PORT`).
    pub fn new(base: &str, user: &str, password: &str) -> Client {
        let token = base64::engine::general_purpose::STANDARD.encode(format!("{user}:{password}"));
        Client {
            base: base.trim_end_matches('/').to_owned(),
            authorization: format!("Basic {token}"),
            agent: agent(Duration::from_secs(DEFAULT_TIMEOUT_SECS)),
        }
    }

    /// The same client with requests limited to `timeout` each.
    pub fn timeout(self, timeout: Duration) -> Client {
        Client {
            agent: agent(timeout),
            ..self
        }
    }

    fn unreachable(&self, e: ureq::Error) -> ClientError {
        ClientError::Unreachable {
            url: self.base.clone(),
            detail: e.to_string(),
        }
    }

    fn finish(
        &self,
        result: Result<ureq::http::Response<ureq::Body>, ureq::Error>,
    ) -> Result<Value, ClientError> {
        let mut response = result.map_err(|e| self.unreachable(e))?;
        let status = response.status().as_u16();
        let text = response
            .body_mut()
            .read_to_string()
            .map_err(|e| self.unreachable(e))?;
        let json: Value = if text.trim().is_empty() {
            Value::Null
        } else {
            serde_json::from_str(&text).unwrap_or(Value::String(text.clone()))
        };
        if status >= 400 {
            let reason = json["reason"].as_str().map_or(text, str::to_owned);
            return Err(ClientError::Api { status, reason });
        }
        Ok(json)
    }

    /// GET `path` (starting `/api/`).
    pub fn get(&self, path: &str) -> Result<Value, ClientError> {
        let request = self
            .agent
            .get(format!("{}{path}", self.base))
            .header("Authorization", &self.authorization);
        self.finish(request.call())
    }

    /// DELETE `path`, with extra headers.
    pub fn delete(&self, path: &str, headers: &[(&str, &str)]) -> Result<Value, ClientError> {
        let mut request = self
            .agent
            .delete(format!("{}{path}", self.base))
            .header("Authorization", &self.authorization);
        for (name, value) in headers {
            request = request.header(*name, *value);
        }
        self.finish(request.call())
    }

    /// PUT `body` (JSON) to `path`.
    pub fn put(&self, path: &str, body: &[u8]) -> Result<Value, ClientError> {
        let request = self
            .agent
            .put(format!("{}{path}", self.base))
            .header("Authorization", &self.authorization)
            .header("Content-Type", "application/json");
        self.finish(request.send(body))
    }

    /// POST `body` (JSON) to `path`.
    pub fn post(&self, path: &str, body: &[u8]) -> Result<Value, ClientError> {
        let request = self
            .agent
            .post(format!("{}{path}", self.base))
            .header("Authorization", &self.authorization)
            .header("Content-Type", "application/json");
        self.finish(request.send(body))
    }
}
