//! Reading OpenRTM-aist AMQP connector properties into a [`PortProfile`],
//! with the semantics of OpenRTM-aist's AMQP data-port module
//! (`interface_type` `amqp_cdr`): its defaults, which differ between the
//! in-port and the out-port, its key prefixes, its case-insensitive
//! exchange types, and its `serializer.cdr.endian`. Keys it does not
//! know are reported, not silently ignored.

use super::cdr::{Charset, Endian};
use super::profile::{ExchangeKind, FullPolicy, PortProfile};
use leveret_client::ConnectionOptions;
use leveret_client::{Error, Result};
use std::collections::HashMap;
use std::time::Duration;

/// Which end of a connector the properties configure: their defaults,
/// `bind`'s meaning and the `dataport.inport.` / `dataport.outport.`
/// prefixes differ.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum PortRole {
    /// An in-port (consumer).
    InPort,
    /// An out-port (producer).
    OutPort,
}

impl PortRole {
    fn prefix(self) -> &'static str {
        match self {
            PortRole::InPort => "inport.",
            PortRole::OutPort => "outport.",
        }
    }

    fn other_prefix(self) -> &'static str {
        match self {
            PortRole::InPort => "outport.",
            PortRole::OutPort => "inport.",
        }
    }
}

/// A profile read from connector properties, with what was not understood.
#[derive(Debug, Clone)]
pub struct ConnectorProfile {
    /// The profile.
    pub profile: PortProfile,
    /// Keys neither OpenRTM's connector nor Leveret knows (a misspelling,
    /// most likely), as given.
    pub unknown: Vec<String>,
}

/// OpenRTM connector-profile keys that are not about AMQP: known, unused.
const OPENRTM_KEYS: &[&str] = &[
    "interface_type",
    "dataflow_type",
    "subscription_type",
    "data_type",
    "marshaling_type",
    "publisher.push_policy",
    "publisher.skip_count",
    "publisher.push_rate",
    "buffer.read.empty_policy",
    "buffer.read.timeout",
    "buffer.write.empty_policy",
];

impl PortProfile {
    /// Reads OpenRTM-aist AMQP connector properties for one end of a
    /// connector, as OpenRTM-aist's AMQP data-port module does. Each key
    /// is looked up bare, then with a `dataport.` prefix, then with
    /// `dataport.inport.` (in-port) or `dataport.outport.` (out-port); the
    /// first found wins, and a key of the other role is ignored.
    ///
    /// The module's keys and defaults: `host` (`localhost`), `msport`
    /// (5672), `exname` (`exchange0` for an in-port, `exchange1` for an
    /// out-port), `extype` (direct; any case, see [`ExchangeKind::parse`]),
    /// `qname` (`queue0` / `queue1`), `bkey` (`test`), `rkey` (`test`),
    /// `bind` (in-port `true`: declare the exchange and bind the queue,
    /// which is declared either way; out-port `false`: with `true` it also
    /// declares the queue and binds it), `serializer.cdr.endian`
    /// (`little`/`big`). Leveret's own: `url` (an `amqp://` URI replacing
    /// host and port), `durable`, `persistent`, `confirms`, `prefetch`,
    /// `buffer.length`, `buffer.write.full_policy`, `buffer.write.timeout`
    /// (seconds), `max_unconfirmed`, `lifespan` (seconds) and
    /// `serializer.cdr.charset` (`latin-1`, the default: what OpenRTM-aist
    /// sends, omniORB's native code set; or `utf-8`).
    pub fn from_properties<'a>(
        role: PortRole,
        properties: impl IntoIterator<Item = (&'a str, &'a str)>,
    ) -> Result<ConnectorProfile> {
        let mut profile = PortProfile::default();
        profile.broker = ConnectionOptions {
            host: "localhost".to_owned(),
            port: 5672,
            ..profile.broker
        };
        let (exchange, queue, bind) = match role {
            PortRole::InPort => ("exchange0", "queue0", true),
            PortRole::OutPort => ("exchange1", "queue1", false),
        };
        profile.exchange = exchange.to_owned();
        profile.exchange_kind = ExchangeKind::Direct;
        profile.queue = queue.to_owned();
        profile.binding_key = "test".to_owned();
        profile.routing_key = "test".to_owned();
        profile.declare_queue = bind;
        // OpenRTM-aist's strings are ISO 8859-1: omniORB's default native
        // code set, which its CDR serializer marshals with.
        profile.cdr.charset = Charset::Latin1;

        // The most specific spelling of a key loses to a plainer one, as in
        // the module; remember which spelling each value came by.
        let mut found: HashMap<&str, (u8, &str, &str)> = HashMap::new();
        let mut unknown = Vec::new();
        for (key, value) in properties {
            let (rank, name) = match key.strip_prefix("dataport.") {
                None => (0, key),
                Some(rest) => match rest.strip_prefix(role.prefix()) {
                    Some(name) => (2, name),
                    None if rest.starts_with(role.other_prefix()) => continue,
                    None => (1, rest),
                },
            };
            if !is_known(name) {
                unknown.push(key.to_owned());
                continue;
            }
            let entry = found.entry(name).or_insert((rank, key, value));
            if rank < entry.0 {
                *entry = (rank, key, value);
            }
        }
        let mut keys: Vec<_> = found.into_iter().collect();
        // `url` first, so `host` and `msport` refine it.
        keys.sort_by_key(|(name, _)| *name != "url");
        for (name, (_, key, value)) in keys {
            apply(&mut profile, name, key, value)?;
        }
        if !unknown.is_empty() {
            tracing::warn!(?unknown, "unknown connector properties ignored");
        }
        Ok(ConnectorProfile { profile, unknown })
    }
}

fn is_known(name: &str) -> bool {
    matches!(
        name,
        "url"
            | "host"
            | "msport"
            | "exname"
            | "extype"
            | "qname"
            | "bkey"
            | "bind"
            | "rkey"
            | "durable"
            | "persistent"
            | "confirms"
            | "prefetch"
            | "buffer.length"
            | "buffer.write.full_policy"
            | "buffer.write.timeout"
            | "max_unconfirmed"
            | "lifespan"
            | "serializer.cdr.endian"
            | "serializer.cdr.charset"
    ) || OPENRTM_KEYS.contains(&name)
}

fn bad(key: &str, value: &str) -> Error {
    Error::InvalidArgument(format!("connector property {key}={value:?}"))
}

/// OpenRTM's spellings of a boolean.
fn flag(key: &str, value: &str) -> Result<bool> {
    match value.trim().to_ascii_lowercase().as_str() {
        "true" | "t" | "1" | "yes" => Ok(true),
        "false" | "f" | "0" | "no" => Ok(false),
        _ => Err(bad(key, value)),
    }
}

fn seconds(key: &str, value: &str) -> Result<Duration> {
    let seconds: f64 = value.trim().parse().map_err(|_| bad(key, value))?;
    Duration::try_from_secs_f64(seconds).map_err(|_| bad(key, value))
}

fn number<N: std::str::FromStr>(key: &str, value: &str) -> Result<N> {
    value.trim().parse().map_err(|_| bad(key, value))
}

fn apply(profile: &mut PortProfile, name: &str, key: &str, value: &str) -> Result<()> {
    match name {
        "url" => {
            let timeout = profile.broker.connection_timeout;
            let heartbeat = profile.broker.heartbeat;
            profile.broker = ConnectionOptions::from_uri(value)?;
            profile.broker.connection_timeout = timeout;
            if !value.contains("heartbeat=") {
                profile.broker.heartbeat = heartbeat;
            }
        }
        "host" => profile.broker.host = value.to_owned(),
        "msport" => profile.broker.port = number(key, value)?,
        "exname" => profile.exchange = value.to_owned(),
        "extype" => profile.exchange_kind = ExchangeKind::parse(value),
        "qname" => profile.queue = value.to_owned(),
        "bkey" => profile.binding_key = value.to_owned(),
        "bind" => profile.declare_queue = flag(key, value)?,
        "rkey" => profile.routing_key = value.to_owned(),
        "durable" => profile.durable = flag(key, value)?,
        "persistent" => profile.persistent = flag(key, value)?,
        "confirms" => profile.confirms = flag(key, value)?,
        "prefetch" => profile.prefetch = number(key, value)?,
        "buffer.length" => profile.buffer_size = number(key, value)?,
        "buffer.write.full_policy" => {
            profile.full_policy = FullPolicy::parse(value).ok_or_else(|| bad(key, value))?
        }
        "buffer.write.timeout" => profile.put_timeout = seconds(key, value)?,
        "max_unconfirmed" => profile.max_unconfirmed = number(key, value)?,
        "lifespan" => profile.lifespan = Some(seconds(key, value)?),
        "serializer.cdr.endian" => {
            profile.cdr.endian = match value.trim().to_ascii_lowercase().as_str() {
                "little" => Endian::Little,
                "big" => Endian::Big,
                _ => return Err(bad(key, value)),
            }
        }
        "serializer.cdr.charset" => {
            profile.cdr.charset = match value.trim().to_ascii_lowercase().as_str() {
                "utf-8" | "utf8" => Charset::Utf8,
                "latin-1" | "latin1" | "iso-8859-1" | "iso8859-1" => Charset::Latin1,
                _ => return Err(bad(key, value)),
            }
        }
        _ => {}
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn read(role: PortRole, properties: &[(&str, &str)]) -> ConnectorProfile {
        PortProfile::from_properties(role, properties.iter().copied()).unwrap()
    }

    #[test]
    fn the_modules_defaults_differ_by_role() {
        let input = read(PortRole::InPort, &[]).profile;
        assert_eq!(
            (input.broker.host.as_str(), input.broker.port),
            ("localhost", 5672)
        );
        assert_eq!(
            (input.exchange.as_str(), input.queue.as_str()),
            ("exchange0", "queue0")
        );
        assert_eq!(input.binding_key, "test");
        assert_eq!(input.exchange_kind, ExchangeKind::Direct);
        assert!(input.declare_queue, "an in-port binds by default");
        assert_eq!(input.cdr.charset, Charset::Latin1, "OpenRTM-aist's strings");
        let output = read(PortRole::OutPort, &[]).profile;
        assert_eq!(
            (output.exchange.as_str(), output.queue.as_str()),
            ("exchange1", "queue1")
        );
        assert_eq!(output.routing_key, "test");
        assert!(
            !output.declare_queue,
            "an out-port does not bind by default"
        );
    }

    #[test]
    fn openrtm_properties() {
        let parsed = read(
            PortRole::InPort,
            &[
                ("dataport.host", "robot.local"),
                ("msport", "5673"),
                ("exname", "poses"),
                ("extype", "Fanout"),
                ("qname", "pose-in"),
                ("bkey", "pose"),
                ("bind", "FALSE"),
                ("buffer.length", "8"),
                ("buffer.write.full_policy", "block"),
                ("buffer.write.timeout", "0.25"),
                ("durable", "1"),
                ("dataport.serializer.cdr.endian", "big"),
                ("dataport.serializer.cdr.charset", "Latin-1"),
                ("dataport.interface_type", "amqp_cdr"),
                ("lifespan", "0.2"),
            ],
        );
        assert!(parsed.unknown.is_empty(), "{:?}", parsed.unknown);
        let profile = parsed.profile;
        assert_eq!(profile.broker.host, "robot.local");
        assert_eq!(profile.broker.port, 5673);
        assert_eq!(profile.exchange, "poses");
        assert_eq!(profile.exchange_kind, ExchangeKind::Fanout);
        assert_eq!(profile.queue, "pose-in");
        assert_eq!(profile.binding_key, "pose");
        assert!(!profile.declare_queue);
        assert_eq!(profile.buffer_size, 8);
        assert_eq!(profile.full_policy, FullPolicy::BlockBroker);
        assert_eq!(profile.put_timeout, Duration::from_millis(250));
        assert!(profile.durable && !profile.persistent);
        assert_eq!(profile.cdr.endian, Endian::Big);
        assert_eq!(profile.cdr.charset, Charset::Latin1);
        assert_eq!(profile.lifespan, Some(Duration::from_millis(200)));
        assert!(PortProfile::from_properties(PortRole::InPort, [("msport", "x")]).is_err());
        assert!(PortProfile::from_properties(
            PortRole::InPort,
            [("serializer.cdr.endian", "middle")]
        )
        .is_err());
    }

    #[test]
    fn role_prefixes_and_precedence() {
        let parsed = read(
            PortRole::OutPort,
            &[
                ("dataport.outport.rkey", "specific"),
                ("dataport.inport.rkey", "for-the-other-end"),
                ("dataport.outport.exname", "outs"),
                ("dataport.exname", "plain"),
                ("dataport.outport.qname", "q"),
            ],
        );
        assert!(parsed.unknown.is_empty(), "{:?}", parsed.unknown);
        assert_eq!(parsed.profile.routing_key, "specific");
        assert_eq!(parsed.profile.exchange, "plain", "a plainer key wins");
        assert_eq!(parsed.profile.queue, "q");
    }

    #[test]
    fn unknown_keys_are_reported() {
        let parsed = read(
            PortRole::InPort,
            &[
                ("exnme", "typo"),
                ("dataport.inport.bkye", "typo"),
                ("exname", "fine"),
            ],
        );
        assert_eq!(parsed.unknown, ["exnme", "dataport.inport.bkye"]);
        assert_eq!(parsed.profile.exchange, "fine");
    }

    #[test]
    fn url_then_host_and_port() {
        let profile = read(
            PortRole::InPort,
            &[
                ("msport", "5999"),
                ("url", "amqp://robot:secret@broker.local:5673/fleet"),
            ],
        )
        .profile;
        assert_eq!(profile.broker.host, "broker.local");
        assert_eq!(profile.broker.port, 5999);
        assert_eq!(profile.broker.vhost, "fleet");
    }
}
