//! Which vhost an MQTT client's session lives in, as RabbitMQ's plugin
//! picks it: the global runtime parameters `mqtt_default_vhosts` (a
//! verified client certificate's subject DN → vhost) and
//! `mqtt_port_to_vhost_mapping` (the listener port the client connected
//! to, as a string → vhost), then the `vhost:user` user name, then the
//! default vhost `/`. With a client certificate the certificate mapping
//! comes first, then the port mapping, then the user name; without one
//! the user name comes before the port mapping (RabbitMQ 3.10's
//! `get_vhost`). The parameters are checked when set
//! ([`check_global_parameter`], from `Admin::set_parameters` and the
//! binary's definitions import) and read at each CONNECT.

use super::mapping;
use crate::core::Core;
use serde_json::Value;

/// RabbitMQ's global parameter mapping listener ports to vhosts.
pub const PORT_MAPPING: &str = "mqtt_port_to_vhost_mapping";
/// RabbitMQ's global parameter mapping certificate subject DNs to vhosts.
pub const CERTIFICATE_MAPPING: &str = "mqtt_default_vhosts";
/// The component and vhost global parameters are kept under.
const GLOBAL: (&str, &str) = ("global", "");
/// The largest mapping value taken (it is read at each CONNECT).
const MAX_VALUE: usize = 64 * 1024;
/// The longest vhost name (an AMQP short string).
const MAX_VHOST: usize = 255;

/// Checks a value for global parameter `name` (RabbitMQ's
/// `set_global_parameter`): a mapping must be a JSON object of non-empty
/// strings to vhost names (port numbers 1-65535 as the keys of the port
/// mapping); other global parameters are their owners'. The reason
/// otherwise.
pub fn check_global_parameter(name: &str, value: &str) -> Result<(), String> {
    if ![PORT_MAPPING, CERTIFICATE_MAPPING].contains(&name) {
        return Ok(());
    }
    if value.len() > MAX_VALUE {
        return Err(format!("{name} is longer than {MAX_VALUE} bytes"));
    }
    let parsed: Value =
        serde_json::from_str(value).map_err(|e| format!("{name} is not JSON: {e}"))?;
    let object = parsed
        .as_object()
        .ok_or_else(|| format!("{name} must be a JSON object"))?;
    for (key, target) in object {
        if key.is_empty() {
            return Err(format!("{name}: a key cannot be empty"));
        }
        if name == PORT_MAPPING && !key.parse::<u16>().is_ok_and(|port| port > 0) {
            return Err(format!(
                "{name}: '{key}' is not a port number (1-65535, in decimal)"
            ));
        }
        match target.as_str() {
            Some(vhost) if !vhost.is_empty() && vhost.len() <= MAX_VHOST => {}
            _ => {
                return Err(format!(
                    "{name}: the vhost of '{key}' must be a vhost name (a string of 1 to {MAX_VHOST} bytes)"
                ))
            }
        }
    }
    Ok(())
}

/// Where a session's vhost came from, as RabbitMQ's log line says it.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) enum Source {
    CertificateMapping,
    PortMapping,
    UserName,
    Default,
}

impl Source {
    pub(super) fn describe(self) -> &'static str {
        match self {
            Source::CertificateMapping => "client certificate to vhost mapping",
            Source::PortMapping => "MQTT port to vhost mapping",
            Source::UserName => "vhost in user name",
            Source::Default => "default vhost",
        }
    }
}

/// What a CONNECT brings to the choice.
pub(super) struct Client<'a> {
    /// The listener port the client connected to.
    pub port: u16,
    /// The verified client certificate's subject DN, RabbitMQ's form.
    pub subject: Option<&'a str>,
    /// The name the session logs in as, `vhost:user` or plain.
    pub login_name: &'a str,
    /// Whether `login_name` may name a vhost (not for a certificate's
    /// common name).
    pub splits: bool,
}

/// The vhost and user a client's session uses, and where the vhost came
/// from.
pub(super) fn pick<'a>(core: &Core, client: &Client<'a>) -> (String, &'a str, Source) {
    let (named, user) = match client.splits {
        true => mapping::vhost_in_user_name(client.login_name),
        false => (None, client.login_name),
    };
    let by_certificate = || {
        client
            .subject
            .and_then(|subject| mapped(core, CERTIFICATE_MAPPING, subject))
    };
    let by_port = || mapped(core, PORT_MAPPING, &client.port.to_string());
    let by_name = || named.map(str::to_owned);
    let found = if client.subject.is_some() {
        (by_certificate().map(|v| (v, Source::CertificateMapping)))
            .or_else(|| by_port().map(|v| (v, Source::PortMapping)))
            .or_else(|| by_name().map(|v| (v, Source::UserName)))
    } else {
        (by_name().map(|v| (v, Source::UserName)))
            .or_else(|| by_port().map(|v| (v, Source::PortMapping)))
    };
    let (vhost, source) =
        found.unwrap_or_else(|| (mapping::DEFAULT_VHOST.to_owned(), Source::Default));
    (vhost, user, source)
}

/// The vhost `key` maps to in global parameter `name`, if set.
fn mapped(core: &Core, name: &str, key: &str) -> Option<String> {
    let value = core
        .parameters
        .read()
        .get(&(GLOBAL.0.to_owned(), GLOBAL.1.to_owned(), name.to_owned()))
        .cloned()?;
    // Checked when set; a value the store kept from before is read the
    // same way, and a malformed one maps nothing.
    let parsed: Value = serde_json::from_str(&value).ok()?;
    parsed.get(key)?.as_str().map(str::to_owned)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn mappings_are_checked_when_set() {
        let port = |v: &str| check_global_parameter(PORT_MAPPING, v);
        let certificate = |v: &str| check_global_parameter(CERTIFICATE_MAPPING, v);
        assert_eq!(port(r#"{"1883": "robots", "1884": "/"}"#), Ok(()));
        assert_eq!(port("{}"), Ok(()));
        assert!(port(r#"{"http": "robots"}"#).unwrap_err().contains("port"));
        assert!(port(r#"{"0": "robots"}"#).is_err());
        assert!(port(r#"{"65536": "robots"}"#).is_err());
        assert!(port(r#"{"1883": 5}"#).unwrap_err().contains("vhost"));
        assert!(port(r#"{"1883": ""}"#).is_err());
        assert!(port(&format!(r#"{{"1883": "{}"}}"#, "v".repeat(256))).is_err());
        assert!(port(r#"["robots"]"#).unwrap_err().contains("object"));
        assert!(port("{").unwrap_err().contains("JSON"));
        assert_eq!(certificate(r#"{"O=client,CN=guest": "robots"}"#), Ok(()));
        assert!(certificate(r#"{"": "robots"}"#).is_err());
        assert!(certificate(r#"{"CN=a": null}"#).is_err());
        assert!(certificate(&format!(r#""{}""#, "x".repeat(MAX_VALUE))).is_err());
        // Other parameters are their owners'.
        assert_eq!(check_global_parameter("cluster_name", "{"), Ok(()));
    }
}
