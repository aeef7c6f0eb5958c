//! Connection settings and their `amqp://` and `amqps://` URI forms,
//! parsed as RabbitMQ's URI specification describes:
//! `amqp://user:pass@host:port/vhost?query`, with percent-decoding of the
//! user, password, host, vhost and query values (`%2f` is `/`).
//!
//! `amqps://` is TLS (port 5671 by default), with RabbitMQ's TLS query
//! parameters `cacertfile` (PEM; the system's CA certificates without it),
//! `certfile` and `keyfile` (a client certificate, PEM) and
//! `server_name_indication`; `auth_mechanism=external` logs in with SASL
//! EXTERNAL (the client certificate's identity) instead of PLAIN.
//! `verify=verify_none` is refused: this client always checks the
//! broker's certificate.
//!
//! Defaults: user `guest`, password `guest`, host `localhost`, port 5672,
//! vhost `/` when the path is empty (`amqp://host` and `amqp://host/` both
//! mean `/`; RabbitMQ's specification reads the latter as the empty vhost,
//! which no broker has, so this follows its clients instead). Query
//! parameters `heartbeat` (seconds), `frame_max` (bytes), `channel_max`,
//! `connection_timeout` (milliseconds) and `connection_name` are
//! understood; others are ignored, as RabbitMQ's clients ignore the ones
//! they do not implement.
//!
//! The syntax is RFC 3986's, which the AMQP URI specification builds on,
//! checked by `fluent-uri`: a URI it refuses (a raw space or non-ASCII
//! character, a malformed `%` escape, two `@`, a fragment) is refused here.
//! Not the `url` crate: it follows the WHATWG URL standard, which refuses
//! the specification's own examples `amqp://user@` and `amqp://:10000`
//! (an empty host with credentials or a port) and cannot tell
//! `amqp://:@host` (empty user and password) from `amqp://host`.

use crate::error::{Error, Result};
use fluent_uri::component::Host;
use fluent_uri::pct_enc::{EStr, Encoder};
use fluent_uri::Uri;
use std::borrow::Cow;
use std::path::PathBuf;
use std::str::FromStr;
use std::time::Duration;

/// How the client proves who it is.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub enum AuthMechanism {
    /// SASL PLAIN with `username` and `password`.
    #[default]
    Plain,
    /// SASL EXTERNAL: the identity the transport established (a TLS client
    /// certificate's common name, for RabbitMQ and Leveret).
    External,
}

/// TLS settings of an `amqps://` connection.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct TlsSettings {
    /// CA certificates (PEM) the broker's certificate must chain to;
    /// `None` trusts the operating system's.
    pub cacertfile: Option<PathBuf>,
    /// A client certificate chain (PEM, leaf first), for mutual TLS.
    pub certfile: Option<PathBuf>,
    /// Its private key (PEM).
    pub keyfile: Option<PathBuf>,
    /// The name the broker's certificate must be for; the host by default.
    pub server_name: Option<String>,
}

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
    /// TLS (`amqps://`); `None` is plain TCP.
    pub tls: Option<TlsSettings>,
    /// PLAIN or EXTERNAL.
    pub auth_mechanism: AuthMechanism,
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
            .field("tls", &self.tls)
            .field("auth_mechanism", &self.auth_mechanism)
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
            tls: None,
            auth_mechanism: AuthMechanism::Plain,
        }
    }
}

impl ConnectionOptions {
    /// Parses an `amqp://` or `amqps://` URI.
    pub fn from_uri(uri: &str) -> Result<Self> {
        let bad = |why: &str| Error::InvalidUri(format!("{why}: {uri:?}"));
        let parsed = Uri::parse(uri).map_err(|e| bad(&e.to_string()))?;
        let scheme = parsed.scheme().as_str();
        let tls = scheme.eq_ignore_ascii_case("amqps");
        if !tls && !scheme.eq_ignore_ascii_case("amqp") {
            return Err(bad("scheme must be amqp or amqps"));
        }
        if tls && !cfg!(feature = "tls") {
            return Err(bad("amqps needs leveret-client's `tls` feature"));
        }
        let authority = parsed
            .authority()
            .ok_or_else(|| bad("no authority (amqp://host...)"))?;
        if parsed.fragment().is_some() {
            return Err(bad("an AMQP URI has no fragment"));
        }
        let decode = |part: &str, value: Option<String>| {
            value.ok_or_else(|| bad(&format!("the {part} is not UTF-8")))
        };
        let mut options = ConnectionOptions::default();
        if tls {
            options.port = 5671;
            options.tls = Some(TlsSettings::default());
        }
        if let Some(userinfo) = authority.userinfo() {
            let (user, password) = match userinfo.split_once(':') {
                Some((user, password)) => (user, Some(password)),
                None => (userinfo, None),
            };
            options.username = decode("user name", decoded(user))?;
            if let Some(password) = password {
                options.password = decode("password", decoded(password))?;
            }
        }
        let host = match authority.host_parsed() {
            Host::RegName(name) => decode("host", decoded(name))?,
            Host::IpvFuture { .. } => return Err(bad("IPvFuture hosts are not supported")),
            // An IPv4 or IPv6 literal; IPv6 without its brackets.
            _ => authority
                .host()
                .trim_start_matches('[')
                .trim_end_matches(']')
                .to_owned(),
        };
        if !host.is_empty() {
            options.host = host;
        }
        match authority.port_to_u16() {
            Ok(Some(port)) => options.port = port,
            Ok(None) => {}
            Err(_) => return Err(bad("bad port")),
        }
        // With an authority the path is empty or starts with '/'; the rest
        // is the vhost, one segment.
        if let Some((_, vhost)) = parsed.path().split_once('/') {
            if vhost.as_str().contains('/') {
                return Err(bad("the vhost must be one path segment (write / as %2f)"));
            }
            if !vhost.is_empty() {
                options.vhost = decode("vhost", decoded(vhost))?;
            }
        }
        for pair in parsed.query().into_iter().flat_map(|q| q.split('&')) {
            if pair.is_empty() {
                continue;
            }
            let (key, value) = match pair.split_once('=') {
                Some((key, value)) => (key.as_str(), decode(key.as_str(), decoded(value))?),
                None => (pair.as_str(), String::new()),
            };
            let number = || -> Result<u64> {
                value
                    .parse::<u64>()
                    .map_err(|_| bad(&format!("bad {key} value {value:?}")))
            };
            let fits = |n: u64, max: u64| -> Result<u64> {
                if n > max {
                    Err(bad(&format!("{key} {n} is larger than {max}")))
                } else {
                    Ok(n)
                }
            };
            match key {
                "heartbeat" => options.heartbeat = fits(number()?, u64::from(u16::MAX))? as u16,
                "frame_max" => options.frame_max = fits(number()?, u64::from(u32::MAX))? as u32,
                "channel_max" => {
                    options.channel_max = fits(number()?, u64::from(u16::MAX))? as u16;
                }
                "connection_timeout" => {
                    options.connection_timeout = Duration::from_millis(number()?);
                }
                "connection_name" => options.connection_name = Some(value),
                "auth_mechanism" => {
                    options.auth_mechanism = match value.to_ascii_lowercase().as_str() {
                        "plain" => AuthMechanism::Plain,
                        "external" => AuthMechanism::External,
                        _ => return Err(bad(&format!("unknown auth_mechanism {value:?}"))),
                    }
                }
                "cacertfile" | "certfile" | "keyfile" | "server_name_indication" | "verify" => {
                    let Some(settings) = options.tls.as_mut() else {
                        return Err(bad(&format!("{key} needs an amqps:// URI")));
                    };
                    match key {
                        "cacertfile" => settings.cacertfile = Some(value.into()),
                        "certfile" => settings.certfile = Some(value.into()),
                        "keyfile" => settings.keyfile = Some(value.into()),
                        "server_name_indication" => settings.server_name = Some(value),
                        _ if value == "verify_peer" => {}
                        _ => return Err(bad("the broker's certificate is always verified")),
                    }
                }
                _ => {}
            }
        }
        Ok(options)
    }
}

/// Percent-decodes a URI component; `None` if the result is not UTF-8.
fn decoded<E: Encoder>(value: &EStr<E>) -> Option<String> {
    value.decode().to_string().ok().map(Cow::into_owned)
}

impl FromStr for ConnectionOptions {
    type Err = Error;
    fn from_str(uri: &str) -> Result<Self> {
        ConnectionOptions::from_uri(uri)
    }
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
}
