//! Connection settings and their `amqp://` URI form, parsed as RabbitMQ's
//! URI specification describes: `amqp://user:pass@host:port/vhost?query`,
//! with percent-decoding of the user, password and vhost (`%2f` is `/`).
//!
//! Defaults: user `guest`, password `guest`, host `localhost`, port 5672,
//! vhost `/` when the path is empty (`amqp://host` and `amqp://host/` both
//! mean `/`; RabbitMQ's specification reads the latter as the empty vhost,
//! which no broker has, so this follows its clients instead). Query
//! parameters `heartbeat` (seconds), `frame_max` (bytes), `channel_max` and
//! `connection_timeout` (milliseconds) are understood; others are ignored,
//! as RabbitMQ's clients ignore the ones they do not implement.

use crate::error::{Error, Result};
use std::str::FromStr;
use std::time::Duration;

/// Everything needed to open a connection. Its `Debug` output hides the
/// password.
#[derive(Clone, PartialEq, Eq)]
pub struct ConnectionOptions {
    /// Host name or IP address (IPv6 without brackets).
    pub host: String,
    /// TCP port.
    pub port: u16,
    /// User name for PLAIN authentication.
    pub username: String,
    /// Password for PLAIN authentication.
    pub password: String,
    /// Virtual host.
    pub vhost: String,
    /// Heartbeat interval asked for, seconds; 0 takes the broker's.
    pub heartbeat: u16,
    /// Largest frame asked for, bytes; 0 takes the broker's.
    pub frame_max: u32,
    /// Highest channel number asked for; 0 takes the broker's.
    pub channel_max: u16,
    /// Limit on TCP connect plus handshake.
    pub connection_timeout: Duration,
    /// Shown by the broker's management tools (client property `connection_name`).
    pub connection_name: Option<String>,
}

impl std::fmt::Debug for ConnectionOptions {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("ConnectionOptions")
            .field("host", &self.host)
            .field("port", &self.port)
            .field("username", &self.username)
            .field("password", &"<hidden>")
            .field("vhost", &self.vhost)
            .field("heartbeat", &self.heartbeat)
            .field("frame_max", &self.frame_max)
            .field("channel_max", &self.channel_max)
            .field("connection_timeout", &self.connection_timeout)
            .field("connection_name", &self.connection_name)
            .finish()
    }
}

impl Default for ConnectionOptions {
    fn default() -> Self {
        ConnectionOptions {
            host: "localhost".to_owned(),
            port: 5672,
            username: "guest".to_owned(),
            password: "guest".to_owned(),
            vhost: "/".to_owned(),
            heartbeat: 60,
            frame_max: 131_072,
            channel_max: 2047,
            connection_timeout: Duration::from_secs(60),
            connection_name: None,
        }
    }
}

impl ConnectionOptions {
    /// Parses an `amqp://` URI.
    pub fn from_uri(uri: &str) -> Result<Self> {
        let bad = |why: &str| Error::InvalidUri(format!("{why}: {uri:?}"));
        let (scheme, rest) = uri.split_once("://").ok_or_else(|| bad("no scheme"))?;
        if scheme.eq_ignore_ascii_case("amqps") {
            return Err(bad("amqps (TLS) is not supported"));
        }
        if !scheme.eq_ignore_ascii_case("amqp") {
            return Err(bad("scheme must be amqp"));
        }
        let mut options = ConnectionOptions::default();
        let (rest, query) = match rest.split_once('?') {
            Some((rest, query)) => (rest, Some(query)),
            None => (rest, None),
        };
        let (authority, path) = match rest.find('/') {
            Some(at) => (&rest[..at], Some(&rest[at + 1..])),
            None => (rest, None),
        };
        let host_port = match authority.rsplit_once('@') {
            Some((userinfo, host_port)) => {
                let (user, password) = match userinfo.split_once(':') {
                    Some((user, password)) => (user, Some(password)),
                    None => (userinfo, None),
                };
                options.username = percent_decode(user).ok_or_else(|| bad("bad user name"))?;
                if let Some(password) = password {
                    options.password =
                        percent_decode(password).ok_or_else(|| bad("bad password"))?;
                }
                host_port
            }
            None => authority,
        };
        let (host, port) = if let Some(bracketed) = host_port.strip_prefix('[') {
            let (host, after) = bracketed
                .split_once(']')
                .ok_or_else(|| bad("unclosed IPv6 literal"))?;
            let port = match after {
                "" => None,
                p => Some(p.strip_prefix(':').ok_or_else(|| bad("bad port"))?),
            };
            (host.to_owned(), port)
        } else {
            match host_port.rsplit_once(':') {
                Some((host, port)) => (host.to_owned(), Some(port)),
                None => (host_port.to_owned(), None),
            }
        };
        if !host.is_empty() {
            options.host = percent_decode(&host).ok_or_else(|| bad("bad host"))?;
        }
        if let Some(port) = port.filter(|p| !p.is_empty()) {
            options.port = port.parse().map_err(|_| bad("bad port"))?;
        }
        if let Some(path) = path {
            if path.contains('/') {
                return Err(bad("the vhost must be one path segment (write / as %2f)"));
            }
            if !path.is_empty() {
                options.vhost = percent_decode(path).ok_or_else(|| bad("bad vhost"))?;
            }
        }
        for pair in query.into_iter().flat_map(|q| q.split('&')) {
            if pair.is_empty() {
                continue;
            }
            let (key, value) = pair.split_once('=').unwrap_or((pair, ""));
            let number = |what: &str| -> Result<u64> {
                value
                    .parse::<u64>()
                    .map_err(|_| bad(&format!("bad {what} value {value:?}")))
            };
            let fits = |what: &str, n: u64, max: u64| -> Result<u64> {
                if n > max {
                    Err(bad(&format!("{what} {n} is larger than {max}")))
                } else {
                    Ok(n)
                }
            };
            match key {
                "heartbeat" => {
                    options.heartbeat = fits(key, number(key)?, u64::from(u16::MAX))? as u16;
                }
                "frame_max" => {
                    options.frame_max = fits(key, number(key)?, u64::from(u32::MAX))? as u32;
                }
                "channel_max" => {
                    options.channel_max = fits(key, number(key)?, u64::from(u16::MAX))? as u16;
                }
                "connection_timeout" => {
                    options.connection_timeout = Duration::from_millis(number(key)?);
                }
                "connection_name" => {
                    options.connection_name =
                        Some(percent_decode(value).ok_or_else(|| bad("bad connection_name"))?);
                }
                _ => {}
            }
        }
        Ok(options)
    }
}

impl FromStr for ConnectionOptions {
    type Err = Error;
    fn from_str(uri: &str) -> Result<Self> {
        ConnectionOptions::from_uri(uri)
    }
}

/// Decodes `%XX` escapes; `None` on a malformed escape or invalid UTF-8.
fn percent_decode(s: &str) -> Option<String> {
    let bytes = s.as_bytes();
    let mut out = Vec::with_capacity(bytes.len());
    let mut i = 0;
    while i < bytes.len() {
        if bytes[i] == b'%' {
            let hex = bytes.get(i + 1..i + 3)?;
            if !hex.iter().all(u8::is_ascii_hexdigit) {
                return None;
            }
            let hex = std::str::from_utf8(hex).ok()?;
            out.push(u8::from_str_radix(hex, 16).ok()?);
            i += 3;
        } else {
            out.push(bytes[i]);
            i += 1;
        }
    }
    String::from_utf8(out).ok()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn debug_hides_the_password() {
        let options = ConnectionOptions::from_uri("amqp://u:s3cret@h").unwrap();
        let shown = format!("{options:?}");
        assert!(!shown.contains("s3cret"), "{shown}");
        assert!(shown.contains("\"u\""), "{shown}");
    }

    #[test]
    fn decodes_escapes() {
        assert_eq!(percent_decode("a%2Fb%2f").as_deref(), Some("a/b/"));
        assert_eq!(percent_decode("%zz"), None);
        assert_eq!(percent_decode("%2"), None);
        assert_eq!(percent_decode("%+1"), None);
        assert_eq!(percent_decode("%C3%A9").as_deref(), Some("é"));
    }
}
