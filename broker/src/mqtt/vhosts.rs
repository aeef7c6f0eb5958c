//! Which vhost an MQTT client's session lives in, as RabbitMQ's plugin
//! picks it: the global runtime parameters `mqtt_default_vhosts` (a
//! verified client certificate's subject DN → vhost) and
//! `mqtt_port_to_vhost_mapping` (the listener port the client connected
//! to, as a string → vhost), then the `vhost:user` user name, then the
//! default vhost `/`. With a client certificate the certificate mapping
//! comes first, then the port mapping, then the user name; without one
//! the user name comes before the port mapping (RabbitMQ 3.10's
//! `get_vhost`). The parameters are checked when set
//! (`parameters::check_global_parameter`, from `Admin::set_parameters`
//! and the binary's definitions import) and read at each CONNECT.

use super::mapping;
use crate::core::Core;
use crate::parameters::{CERTIFICATE_MAPPING, PORT_MAPPING};
use serde_json::Value;

/// The component and vhost global parameters are kept under.
const GLOBAL: (&str, &str) = ("global", "");

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
