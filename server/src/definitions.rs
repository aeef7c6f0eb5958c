//! RabbitMQ's `definitions.json`: reading one (`--definitions FILE` at
//! start, `POST /api/definitions` at run time) and writing the broker's
//! (`GET /api/definitions`) in the form RabbitMQ 3.10 imports.
//!
//! What Leveret acts on: vhosts, users (with RabbitMQ's SHA-256 and
//! SHA-512 password hashes and Leveret's argon2id, and their tags: what
//! they may do in the management API), exchanges, queues (with arguments)
//! and bindings, permissions and topic permissions (enforced by the
//! broker; a pattern its regex engine cannot run refuses the file), users'
//! and vhosts' limits (`parameters` with component `vhost-limits`), shovels
//! (`parameters` with component `shovel`, started by `uplink`),
//! federation upstreams (`parameters` with component
//! `federation-upstream`: `federation`), policies and operator policies
//! (`crate::policies`; one with a key Leveret refuses is reported and not
//! set), the `cluster_name` global parameter and the MQTT vhost mappings
//! (`mqtt_port_to_vhost_mapping`, `mqtt_default_vhosts`; a malformed one
//! refuses the file). Everything else is
//! reported, never dropped silently: other parameters, other global
//! parameters, unknown keys, other password hashing
//! algorithms, and queue types Leveret does not have (a quorum queue
//! gives a classic queue, without the arguments of its type, which a
//! classic queue refuses). Streams are imported and exported as streams. An empty `password_hash` is, as
//! in RabbitMQ, a user who cannot log in with a password.
//!
//! RabbitMQ 3.10 cannot take argon2id hashes (its import aborts on them,
//! `not_base64`) and ignores top-level keys it does not know. So the export
//! puts users with argon2id hashes, and their permissions and topic
//! permissions, in a Leveret-only section, `leveret` (with `warnings`
//! saying so, also logged); Leveret's import reads that section back, so
//! its own export round-trips whole.

use crate::management::json::{flag, text, user_tags};
use crate::uplink::Links;
use leveret_broker::{
    check_pattern, Admin, BindingSpec, BrokerBuilder, DestinationKind, ExchangeSettings,
    PasswordHash, Permission, PolicyKind, QueueSettings, TopicPermission, UnknownLimit, User,
    UserLimits, VhostLimits, LEVERET_ARGON2ID, RABBIT_SHA256, RABBIT_SHA512,
};
use leveret_protocol::json::{table, to_table};
use serde_json::{json, Map, Value};

/// A user from the file.
#[derive(Debug, Clone, PartialEq)]
pub struct UserDefinition {
    /// Name.
    pub name: String,
    /// Its password hash.
    pub hash: PasswordHash,
    /// Its tags.
    pub tags: Vec<String>,
    /// Its limits (`max-connections`, `max-channels`), if any.
    pub limits: Option<UserLimits>,
}

/// A parsed definitions file: what Leveret will apply, and what it
/// reports instead of applying.
#[derive(Debug, Clone, Default)]
pub struct Definitions {
    /// Vhost names.
    pub vhosts: Vec<String>,
    /// Users.
    pub users: Vec<UserDefinition>,
    exchanges: Vec<(String, String, ExchangeSettings)>,
    queues: Vec<(String, String, QueueSettings)>,
    bindings: Vec<(String, BindingSpec)>,
    /// (user, vhost, permission).
    pub permissions: Vec<(String, String, Permission)>,
    /// (user, vhost, exchange, topic permission).
    pub topic_permissions: Vec<(String, String, String, TopicPermission)>,
    /// Shovels (`parameters` with component `shovel`): vhost, name and
    /// RabbitMQ's JSON parameters, checked.
    pub shovels: Vec<(String, String, Value)>,
    /// Federation upstreams (`parameters` with component
    /// `federation-upstream`): vhost, name and parameters, checked.
    pub upstreams: Vec<(String, String, Value)>,
    /// Vhosts' limits (`parameters` with component `vhost-limits`).
    pub vhost_limits: Vec<(String, VhostLimits)>,
    /// Policies: vhost, name and the policy, checked.
    pub policies: Vec<(String, String, Value)>,
    /// Operator policies, likewise.
    pub operator_policies: Vec<(String, String, Value)>,
    /// The global parameters Leveret keeps (`cluster_name`, the MQTT
    /// vhost mappings): name and value, checked.
    pub global_parameters: Vec<(String, Value)>,
    /// Everything not applied, one line each.
    pub warnings: Vec<String>,
}

/// How much an import applied.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct Applied {
    /// Vhosts created.
    pub vhosts: usize,
    /// Users added or changed.
    pub users: usize,
    /// Exchanges declared.
    pub exchanges: usize,
    /// Queues declared.
    pub queues: usize,
    /// Bindings added.
    pub bindings: usize,
    /// Shovels started.
    pub shovels: usize,
    /// Federation upstreams set.
    pub upstreams: usize,
    /// Policies and operator policies set.
    pub policies: usize,
}

fn is_empty(value: &Value) -> bool {
    match value {
        Value::Null => true,
        Value::String(s) => s.is_empty(),
        Value::Array(a) => a.is_empty(),
        Value::Object(o) => o.is_empty(),
        _ => false,
    }
}

/// Reports the keys of `object` that are not `used` and say something.
fn unused_keys(object: &Map<String, Value>, used: &[&str], what: &str, warnings: &mut Vec<String>) {
    for (key, value) in object {
        if !used.contains(&key.as_str()) && !is_empty(value) {
            warnings.push(format!(
                "{what}: key '{key}' ({value}) is not supported; ignored"
            ));
        }
    }
}

/// A limits object (RabbitMQ's: a negative value is no limit), each name
/// one `with` knows.
fn limits_from<L: Default>(
    limits: &Value,
    with: impl Fn(L, &str, i64) -> Result<L, UnknownLimit>,
) -> Result<L, String> {
    let object = limits
        .as_object()
        .ok_or_else(|| format!("limits must be an object, not {limits}"))?;
    object.iter().try_fold(L::default(), |acc, (key, value)| {
        let number = value
            .as_i64()
            .ok_or_else(|| format!("limit {key} must be an integer, not {value}"))?;
        with(acc, key, number).map_err(|e| e.to_string())
    })
}

/// A user's `limits` object (RabbitMQ's user limits).
fn user_limits(limits: Option<&Value>, what: &str) -> Result<Option<UserLimits>, String> {
    let Some(limits) = limits.filter(|v| !is_empty(v)) else {
        return Ok(None);
    };
    limits_from(limits, UserLimits::with)
        .map(Some)
        .map_err(|e| format!("{what}: {e}"))
}

/// A `vhost-limits` parameter's value (RabbitMQ's vhost limits).
fn vhost_limits(value: &Value) -> Result<VhostLimits, String> {
    limits_from(value, VhostLimits::with)
}

/// Limits as RabbitMQ exports them: `{"max-connections": 10}`.
fn limits_json(named: Vec<(&'static str, usize)>) -> Value {
    Value::Object(
        named
            .into_iter()
            .map(|(name, value)| (name.to_owned(), json!(value)))
            .collect(),
    )
}

/// A user's limits as RabbitMQ exports them.
fn user_limits_json(limits: Option<UserLimits>) -> Value {
    limits_json(limits.map(|limits| limits.named()).unwrap_or_default())
}

/// The top-level key of Leveret's own section of an export.
const LEVERET_SECTION: &str = "leveret";

/// A list in Leveret's own section of a document (empty when absent).
fn leveret_list<'a>(root: &'a Map<String, Value>, key: &str) -> Result<&'a [Value], String> {
    match root.get(LEVERET_SECTION) {
        None | Some(Value::Null) => Ok(&[]),
        Some(Value::Object(section)) => list(section, key),
        Some(other) => Err(format!(
            "'{LEVERET_SECTION}' must be an object, not {other}"
        )),
    }
}

/// One item of a list Leveret does not apply, named as RabbitMQ names it:
/// `operator_policies: 'name' in vhost 'v' ({...})`,
/// `global_parameters: 'cluster_name' ("value")`.
fn describe(key: &str, item: &Value) -> String {
    let field = |name: &str| item.get(name).and_then(Value::as_str);
    let mut out = format!("{key}: ");
    match field("name") {
        Some(name) => out.push_str(&format!("'{name}'")),
        None => out.push_str(&item.to_string()),
    }
    if let Some(vhost) = field("vhost") {
        out.push_str(&format!(" in vhost '{vhost}'"));
    }
    if let Some(detail) = item.get("definition").or_else(|| item.get("value")) {
        out.push_str(&format!(" ({detail})"));
    }
    out
}

fn list<'a>(root: &'a Map<String, Value>, key: &str) -> Result<&'a [Value], String> {
    match root.get(key) {
        None | Some(Value::Null) => Ok(&[]),
        Some(Value::Array(items)) => Ok(items),
        Some(other) => Err(format!("'{key}' must be a list, not {other}")),
    }
}

fn object<'a>(item: &'a Value, what: &str) -> Result<&'a Map<String, Value>, String> {
    item.as_object()
        .ok_or_else(|| format!("each of {what} must be an object, not {item}"))
}

fn name(item: &Map<String, Value>, key: &str, what: &str) -> Result<String, String> {
    match item.get(key) {
        Some(Value::String(s)) => Ok(s.clone()),
        _ => Err(format!("{what} without a '{key}'")),
    }
}

impl Definitions {
    /// What the document defines, counted, as a sentence ("2 vhosts,
    /// 1 user, 3 queues"; kinds it has none of are left out).
    pub fn summary(&self) -> String {
        let counts = [
            (self.vhosts.len(), "vhost", "vhosts"),
            (self.users.len(), "user", "users"),
            (self.permissions.len(), "permission", "permissions"),
            (
                self.topic_permissions.len(),
                "topic permission",
                "topic permissions",
            ),
            (self.exchanges.len(), "exchange", "exchanges"),
            (self.queues.len(), "queue", "queues"),
            (self.bindings.len(), "binding", "bindings"),
            (self.shovels.len(), "shovel", "shovels"),
            (
                self.upstreams.len(),
                "federation upstream",
                "federation upstreams",
            ),
            (
                self.policies.len() + self.operator_policies.len(),
                "policy",
                "policies",
            ),
        ];
        let parts: Vec<String> = counts
            .into_iter()
            .filter(|(count, ..)| *count > 0)
            .map(|(count, one, many)| format!("{count} {}", if count == 1 { one } else { many }))
            .collect();
        if parts.is_empty() {
            "nothing".to_owned()
        } else {
            parts.join(", ")
        }
    }

    /// Parses a definitions document; an error names what is malformed.
    pub fn parse(bytes: &[u8]) -> Result<Definitions, String> {
        Definitions::parse_into(bytes, None)
    }

    /// Parses a document for one vhost (RabbitMQ's per-vhost export, whose
    /// objects have no `vhost` key): objects without one go to `vhost`.
    pub fn parse_into(bytes: &[u8], vhost: Option<&str>) -> Result<Definitions, String> {
        let vhost_of = |item: &Map<String, Value>, what: &str| match (item.get("vhost"), vhost) {
            (None | Some(Value::Null), Some(vhost)) => Ok(vhost.to_owned()),
            _ => name(item, "vhost", what),
        };
        let root: Value =
            serde_json::from_slice(bytes).map_err(|e| format!("malformed JSON: {e}"))?;
        let root = root
            .as_object()
            .ok_or("definitions must be a JSON object")?;
        let mut d = Definitions::default();
        const METADATA: [&str; 4] = [
            "rabbit_version",
            "rabbitmq_version",
            "product_name",
            "product_version",
        ];
        const APPLIED: [&str; 12] = [
            LEVERET_SECTION,
            "parameters",
            "vhosts",
            "users",
            "exchanges",
            "queues",
            "bindings",
            "permissions",
            "topic_permissions",
            "policies",
            "operator_policies",
            "global_parameters",
        ];
        for key in root.keys() {
            if !METADATA.contains(&key.as_str()) && !APPLIED.contains(&key.as_str()) {
                d.warnings.push(format!("unknown key '{key}' ignored"));
            }
        }
        for item in list(root, "global_parameters")? {
            match (item.get("name").and_then(Value::as_str), item.get("value")) {
                (Some(name), Some(value)) if crate::policies::is_global_parameter(name) => {
                    crate::policies::check_global_parameter(name, value)
                        .map_err(|e| format!("global parameter '{name}': {e}"))?;
                    d.global_parameters.push((name.to_owned(), value.clone()));
                }
                _ => d.warnings.push(format!(
                    "{} not imported: Leveret keeps only the cluster_name and MQTT vhost mapping global parameters",
                    describe("global_parameters", item)
                )),
            }
        }
        for item in list(root, "parameters")? {
            let item = object(item, "parameters")?;
            let component = name(item, "component", "a parameter")?;
            let parameter = name(item, "name", "a parameter")?;
            let vhost = vhost_of(item, "a parameter")?;
            let value = item.get("value").cloned().unwrap_or(Value::Null);
            match component.as_str() {
                "shovel" => {
                    leveret_uplink::ShovelConfig::from_json(&value)
                        .map_err(|e| format!("shovel '{parameter}' in vhost '{vhost}': {e}"))?;
                    d.shovels.push((vhost, parameter, value));
                }
                "vhost-limits" => {
                    let limits = vhost_limits(&value)
                        .map_err(|e| format!("limits of vhost '{vhost}': {e}"))?;
                    d.vhost_limits.push((vhost, limits));
                }
                crate::federation::UPSTREAM_COMPONENT => {
                    leveret_uplink::UpstreamConfig::from_json(&value).map_err(|e| {
                        format!("federation upstream '{parameter}' in vhost '{vhost}': {e}")
                    })?;
                    d.upstreams.push((vhost, parameter, value));
                }
                // RabbitMQ 3.10 exports its operator policies here.
                "operator_policy" => {
                    let value = crate::policies::with_definition_object(value);
                    match crate::policies::check(PolicyKind::Operator, &value) {
                        Ok(()) => d.operator_policies.push((vhost, parameter, value)),
                        Err(e) => d.warnings.push(format!(
                            "parameter operator_policy '{parameter}' in vhost '{vhost}' not imported: {e}"
                        )),
                    }
                }
                _ => d.warnings.push(format!(
                    "parameter {component} '{parameter}' in vhost '{vhost}' ({value}) not imported: Leveret has shovel, federation-upstream, vhost-limits and operator_policy parameters only"
                )),
            }
        }
        for (key, kind) in [
            ("policies", PolicyKind::User),
            ("operator_policies", PolicyKind::Operator),
        ] {
            for item in list(root, key)? {
                let item = object(item, key)?;
                let policy = name(item, "name", "a policy")?;
                let vhost = vhost_of(item, "a policy")?;
                let value = Value::Object(item.clone());
                match crate::policies::check(kind, &value) {
                    Ok(()) if kind == PolicyKind::User => d.policies.push((vhost, policy, value)),
                    Ok(()) => d.operator_policies.push((vhost, policy, value)),
                    Err(e) => d.warnings.push(format!(
                        "{key}: '{policy}' in vhost '{vhost}' not imported: {e}"
                    )),
                }
            }
        }
        for item in list(root, "vhosts")? {
            let item = object(item, "vhosts")?;
            let vhost = name(item, "name", "a vhost")?;
            unused_keys(
                item,
                &[
                    "name",
                    "description",
                    "tags",
                    "metadata",
                    "default_queue_type",
                    "tracing",
                ],
                &format!("vhost '{vhost}'"),
                &mut d.warnings,
            );
            d.vhosts.push(vhost);
        }
        for item in list(root, "users")?
            .iter()
            .chain(leveret_list(root, "users")?)
        {
            let item = object(item, "users")?;
            let user = name(item, "name", "a user")?;
            let what = format!("user '{user}'");
            unused_keys(
                item,
                &[
                    "name",
                    "password_hash",
                    "hashing_algorithm",
                    "tags",
                    "limits",
                ],
                &what,
                &mut d.warnings,
            );
            let tags = user_tags(item.get("tags"));
            let algorithm = text(item, "hashing_algorithm", RABBIT_SHA256)?;
            if ![RABBIT_SHA256, RABBIT_SHA512, LEVERET_ARGON2ID].contains(&algorithm) {
                d.warnings.push(format!("{what} not imported: hashing algorithm {algorithm} is not supported (only {RABBIT_SHA256}, {RABBIT_SHA512} and {LEVERET_ARGON2ID})"));
                continue;
            }
            let limits = user_limits(item.get("limits"), &what)?;
            match PasswordHash::from_rabbitmq(text(item, "password_hash", "")?, algorithm) {
                Some(hash) => d.users.push(UserDefinition {
                    name: user,
                    hash,
                    tags,
                    limits,
                }),
                None => d
                    .warnings
                    .push(format!("{what} not imported: no usable password_hash")),
            }
        }
        for item in list(root, "permissions")?
            .iter()
            .chain(leveret_list(root, "permissions")?)
        {
            let item = object(item, "permissions")?;
            let user = name(item, "user", "a permission")?;
            let vhost = vhost_of(item, "a permission")?;
            let what = format!("permission of '{user}' on vhost '{vhost}'");
            unused_keys(
                item,
                &["user", "vhost", "configure", "write", "read"],
                &what,
                &mut d.warnings,
            );
            let permission = Permission {
                configure: pattern(item, "configure", &what)?,
                write: pattern(item, "write", &what)?,
                read: pattern(item, "read", &what)?,
            };
            d.permissions.push((user, vhost, permission));
        }
        for item in list(root, "topic_permissions")?
            .iter()
            .chain(leveret_list(root, "topic_permissions")?)
        {
            let item = object(item, "topic_permissions")?;
            let user = name(item, "user", "a topic permission")?;
            let vhost = vhost_of(item, "a topic permission")?;
            let exchange = name(item, "exchange", "a topic permission")?;
            let what = format!("topic permission of '{user}' on '{exchange}' in vhost '{vhost}'");
            unused_keys(
                item,
                &["user", "vhost", "exchange", "write", "read"],
                &what,
                &mut d.warnings,
            );
            let permission = TopicPermission {
                write: pattern(item, "write", &what)?,
                read: pattern(item, "read", &what)?,
            };
            d.topic_permissions
                .push((user, vhost, exchange, permission));
        }
        for item in list(root, "exchanges")? {
            let item = object(item, "exchanges")?;
            let exchange = name(item, "name", "an exchange")?;
            let vhost = vhost_of(item, "an exchange")?;
            let what = format!("exchange '{exchange}' in vhost '{vhost}'");
            unused_keys(
                item,
                &[
                    "name",
                    "vhost",
                    "type",
                    "durable",
                    "auto_delete",
                    "internal",
                    "arguments",
                ],
                &what,
                &mut d.warnings,
            );
            let settings = ExchangeSettings {
                kind: name(item, "type", &what)?,
                durable: flag(item, "durable", true)?,
                auto_delete: flag(item, "auto_delete", false)?,
                internal: flag(item, "internal", false)?,
                arguments: to_table(item.get("arguments").unwrap_or(&Value::Null))?,
            };
            d.exchanges.push((vhost, exchange, settings));
        }
        for item in list(root, "queues")? {
            let item = object(item, "queues")?;
            let queue = name(item, "name", "a queue")?;
            let vhost = vhost_of(item, "a queue")?;
            let what = format!("queue '{queue}' in vhost '{vhost}'");
            unused_keys(
                item,
                &[
                    "name",
                    "vhost",
                    "durable",
                    "auto_delete",
                    "arguments",
                    "type",
                ],
                &what,
                &mut d.warnings,
            );
            let arguments = to_table(item.get("arguments").unwrap_or(&Value::Null))?;
            let kind = arguments
                .get("x-queue-type")
                .and_then(|kind| kind.as_bytes())
                .map(|kind| String::from_utf8_lossy(kind).into_owned())
                .or_else(|| item.get("type").and_then(Value::as_str).map(str::to_owned))
                .unwrap_or_else(|| "classic".to_owned());
            if kind == "stream" {
                // A stream stays a stream, with its arguments (checked when
                // it is declared, as a client's declare is).
                let mut arguments = arguments;
                arguments.insert(
                    leveret_protocol::ShortStr::from_static("x-queue-type"),
                    leveret_protocol::FieldValue::LongStr(bytes::Bytes::from_static(b"stream")),
                );
                let settings = QueueSettings {
                    durable: flag(item, "durable", true)?,
                    auto_delete: flag(item, "auto_delete", false)?,
                    arguments,
                };
                d.queues.push((vhost, queue, settings));
                continue;
            }
            // A quorum queue from a RabbitMQ export becomes the classic
            // queue it can be here, without its type's arguments (which a
            // classic queue refuses), and says so.
            let (arguments, dropped) = leveret_broker::classic_queue_arguments(&arguments);
            if kind != "classic" {
                d.warnings.push(format!(
                    "{what}: queue type '{kind}' is not supported; declared as a classic queue"
                ));
            }
            let dropped: Vec<_> = dropped.iter().filter(|k| *k != "x-queue-type").collect();
            if !dropped.is_empty() {
                d.warnings.push(format!(
                    "{what}: arguments {dropped:?} are not available on a classic queue; declared without them"
                ));
            }
            let settings = QueueSettings {
                durable: flag(item, "durable", true)?,
                auto_delete: flag(item, "auto_delete", false)?,
                arguments,
            };
            d.queues.push((vhost, queue, settings));
        }
        for item in list(root, "bindings")? {
            let item = object(item, "bindings")?;
            let vhost = vhost_of(item, "a binding")?;
            let source = name(item, "source", "a binding")?;
            let destination = name(item, "destination", "a binding")?;
            let what = format!("binding from '{source}' to '{destination}' in vhost '{vhost}'");
            unused_keys(
                item,
                &[
                    "vhost",
                    "source",
                    "destination",
                    "destination_type",
                    "routing_key",
                    "arguments",
                    "properties_key",
                ],
                &what,
                &mut d.warnings,
            );
            let destination_kind = match text(item, "destination_type", "queue")? {
                "queue" => DestinationKind::Queue,
                "exchange" => DestinationKind::Exchange,
                other => return Err(format!("{what}: unknown destination_type '{other}'")),
            };
            d.bindings.push((
                vhost,
                BindingSpec {
                    source,
                    destination,
                    destination_kind,
                    routing_key: text(item, "routing_key", "")?.to_owned(),
                    arguments: to_table(item.get("arguments").unwrap_or(&Value::Null))?,
                },
            ));
        }
        Ok(d)
    }

    /// The users and vhosts, which a broker takes at start.
    pub fn configure(&self, mut builder: BrokerBuilder) -> BrokerBuilder {
        for vhost in &self.vhosts {
            builder = builder.vhost(vhost.clone());
        }
        for user in &self.users {
            builder = builder
                .user_hashed(user.name.clone(), user.hash.clone())
                .user_tags(user.name.clone(), user.tags.clone());
            if let Some(limits) = user.limits {
                builder = builder.user_limits(user.name.clone(), limits);
            }
        }
        for (user, vhost, permission) in &self.permissions {
            builder = builder.permission(user.clone(), vhost.clone(), permission.clone());
        }
        for (user, vhost, exchange, permission) in &self.topic_permissions {
            builder = builder.topic_permission(
                user.clone(),
                vhost.clone(),
                exchange.clone(),
                permission.clone(),
            );
        }
        builder
    }

    /// Applies vhosts, users, permissions, exchanges, queues, shovels and
    /// bindings to a running broker, in that order; stops at the first that
    /// fails, naming it. Users, permissions and limits last as those
    /// changed by the API do (in the store).
    pub async fn apply(&mut self, admin: &Admin, links: &Links) -> Result<Applied, String> {
        let mut applied = Applied::default();
        for vhost in &self.vhosts {
            if admin
                .add_vhost(vhost)
                .await
                .map_err(|e| format!("vhost '{vhost}': {e}"))?
            {
                applied.vhosts += 1;
            }
        }
        for user in &self.users {
            let same = admin.user(&user.name).is_some_and(|existing| {
                existing.password_hash == user.hash && existing.tags == user.tags
            });
            if !same {
                let mut entry = User::new(user.hash.clone());
                entry.tags.clone_from(&user.tags);
                admin
                    .put_user(&user.name, entry)
                    .await
                    .map_err(|e| format!("user '{}': {e}", user.name))?;
                applied.users += 1;
            }
            if let Some(limits) = user.limits {
                admin
                    .set_user_limits(&user.name, limits)
                    .await
                    .map_err(|e| format!("limits of user '{}': {e}", user.name))?;
            }
        }
        for (vhost, limits) in &self.vhost_limits {
            admin
                .set_vhost_limits(vhost, *limits)
                .await
                .map_err(|e| format!("limits of vhost '{vhost}': {e}"))?;
        }
        for (user, vhost, permission) in &self.permissions {
            admin
                .set_permission(user, vhost, permission.clone())
                .await
                .map_err(|e| format!("permission of '{user}' on vhost '{vhost}': {e}"))?;
        }
        for (user, vhost, exchange, permission) in &self.topic_permissions {
            admin
                .set_topic_permission(user, vhost, exchange, permission.clone())
                .await
                .map_err(|e| format!("topic permission of '{user}' on '{exchange}': {e}"))?;
        }
        for (vhost, name, settings) in &self.exchanges {
            admin
                .declare_exchange(vhost, name, settings.clone())
                .await
                .map_err(|e| format!("exchange '{name}' in vhost '{vhost}': {}", e.text))?;
            applied.exchanges += 1;
            tokio::task::yield_now().await;
        }
        for (vhost, name, settings) in &self.queues {
            admin
                .declare_queue(vhost, name, settings.clone())
                .await
                .map_err(|e| format!("queue '{name}' in vhost '{vhost}': {}", e.text))?;
            applied.queues += 1;
            tokio::task::yield_now().await;
        }
        for (vhost, name, parameters) in &self.shovels {
            links
                .shovels
                .declare(vhost, name, parameters.clone())
                .await
                .map_err(|e| format!("shovel '{name}': {e}"))?;
            applied.shovels += 1;
        }
        for (vhost, binding) in &self.bindings {
            admin.bind(vhost, binding.clone()).await.map_err(|e| {
                format!(
                    "binding from '{}' to '{}' in vhost '{vhost}': {}",
                    binding.source, binding.destination, e.text
                )
            })?;
            applied.bindings += 1;
            tokio::task::yield_now().await;
        }
        for (vhost, name, value) in &self.upstreams {
            links
                .federation
                .set_upstream(vhost, name, value.clone(), true)
                .await
                .map_err(|e| format!("federation upstream '{name}': {e}"))?;
            applied.upstreams += 1;
        }
        let policies: Vec<crate::policies::Item> = [
            (PolicyKind::User, &self.policies),
            (PolicyKind::Operator, &self.operator_policies),
        ]
        .into_iter()
        .flat_map(|(kind, policies)| {
            policies
                .iter()
                .map(move |(vhost, name, value)| crate::policies::Item {
                    kind,
                    vhost,
                    name,
                    value,
                })
        })
        .collect();
        crate::policies::set_all(admin, &links.federation, &policies, true)
            .await
            .map_err(|(at, e)| format!("policy '{}': {e}", policies[at].name))?;
        applied.policies += policies.len();
        for (name, value) in &self.global_parameters {
            crate::policies::set_global_parameter(admin, name, value)
                .await
                .map_err(|e| format!("global parameter '{name}': {e}"))?;
        }
        Ok(applied)
    }
}

/// One vhost's definitions, as RabbitMQ exports them: its exchanges,
/// queues and bindings without their `vhost` key, and the empty policies
/// and parameters.
pub fn export_vhost(admin: &Admin, links: &Links, vhost: &str) -> Value {
    let all = export(admin, links);
    let only = |key: &str| -> Vec<Value> {
        all[key]
            .as_array()
            .into_iter()
            .flatten()
            .filter(|item| item["vhost"] == vhost)
            .map(|item| {
                let mut item = item.clone();
                if let Some(map) = item.as_object_mut() {
                    map.remove("vhost");
                }
                item
            })
            .collect()
    };
    json!({
        "rabbit_version": all["rabbit_version"],
        "rabbitmq_version": all["rabbitmq_version"],
        "product_name": all["product_name"],
        "product_version": all["product_version"],
        "parameters": only("parameters"),
        "policies": only("policies"),
        "queues": only("queues"),
        "exchanges": only("exchanges"),
        "bindings": only("bindings"),
    })
}

/// The broker's definitions in RabbitMQ 3.10's form: vhosts, users with
/// their tags, permissions, topic permissions, and the exchanges,
/// queues and bindings a client declared (not the predefined exchanges,
/// exclusive queues or the default exchange's implicit bindings). Users
/// RabbitMQ cannot take (argon2id hashes) and their permissions go to the
/// `leveret` section, and a queue argument a classic queue refuses (stored
/// before it was refused) is left out: each said in the section's
/// `warnings` and logged.
pub fn export(admin: &Admin, links: &Links) -> Value {
    let vhosts = admin.vhosts();
    let mut warnings = Vec::new();
    let (users, leveret_users): (Vec<_>, Vec<_>) = admin
        .users()
        .into_iter()
        .map(|(name, user)| {
            let (password_hash, hashing_algorithm) = user.password_hash.to_rabbitmq();
            json!({
                "name": name, "password_hash": password_hash,
                "hashing_algorithm": hashing_algorithm, "tags": user.tags,
                "limits": user_limits_json(admin.user_limits(&name))})
        })
        .partition(|user| user["hashing_algorithm"] != LEVERET_ARGON2ID);
    let leveret_only: Vec<&str> = leveret_users
        .iter()
        .filter_map(|user| user["name"].as_str())
        .collect();
    for user in &leveret_only {
        warnings.push(format!(
            "user '{user}' is in the '{LEVERET_SECTION}' section, with its permissions: its password hash is argon2id, which RabbitMQ cannot import (set its password again there, or give it a RabbitMQ hash here)"
        ));
    }
    let (permissions, leveret_permissions): (Vec<_>, Vec<_>) = permissions_json(admin)
        .into_iter()
        .partition(|p| !leveret_only.contains(&p["user"].as_str().unwrap_or_default()));
    let (topic_permissions, leveret_topic_permissions): (Vec<_>, Vec<_>) =
        topic_permissions_json(admin)
            .into_iter()
            .partition(|p| !leveret_only.contains(&p["user"].as_str().unwrap_or_default()));
    let exclusive: Vec<(String, String)> = admin
        .queues()
        .into_iter()
        .filter(|q| q.exclusive_owner.is_some())
        .map(|q| (q.vhost, q.name))
        .collect();
    let queues: Vec<Value> = admin
        .queues()
        .iter()
        .filter(|q| q.exclusive_owner.is_none())
        .map(|q| {
            if q.kind() == "stream" {
                return json!({"name": q.name, "vhost": q.vhost, "type": "stream",
                    "durable": q.durable, "auto_delete": q.auto_delete,
                    "arguments": table(&q.arguments)});
            }
            let (arguments, dropped) = leveret_broker::classic_queue_arguments(&q.arguments);
            if !dropped.is_empty() {
                warnings.push(format!(
                    "queue '{}' in vhost '{}' exported without its arguments {dropped:?}: a classic queue has none of them (RabbitMQ refuses them)",
                    q.name, q.vhost
                ));
            }
            json!({"name": q.name, "vhost": q.vhost, "type": "classic", "durable": q.durable,
                   "auto_delete": q.auto_delete, "arguments": table(&arguments)})
        })
        .collect();
    let exchanges: Vec<Value> = admin
        .exchanges()
        .iter()
        .filter(|e| !e.name.is_empty() && !e.name.starts_with("amq."))
        .map(|e| {
            json!({"name": e.name, "vhost": e.vhost, "type": e.kind, "durable": e.durable,
                   "auto_delete": e.auto_delete, "internal": e.internal,
                   "arguments": table(&e.arguments)})
        })
        .collect();
    let bindings: Vec<Value> = admin
        .bindings()
        .iter()
        .filter(|b| !b.source.is_empty())
        .filter(|b| {
            b.destination_kind != DestinationKind::Queue
                || !exclusive.contains(&(b.vhost.clone(), b.destination.clone()))
        })
        .map(|b| {
            json!({"source": b.source, "vhost": b.vhost, "destination": b.destination,
                   "destination_type": b.destination_kind.as_str(),
                   "routing_key": b.routing_key, "arguments": table(&b.arguments)})
        })
        .collect();
    for warning in &warnings {
        tracing::warn!(%warning, "definitions export");
    }
    let overview = admin.overview();
    json!({
        "rabbit_version": "3.10.0",
        "rabbitmq_version": "3.10.0",
        "product_name": overview.product,
        "product_version": overview.version,
        "users": users,
        "vhosts": vhosts.iter().map(|name| json!({"name": name})).collect::<Vec<_>>(),
        "permissions": permissions,
        "topic_permissions": topic_permissions,
        "parameters": admin.all_vhost_limits().into_iter().map(|(vhost, limits)| json!({
            "value": limits_json(limits.named()), "vhost": vhost, "component": "vhost-limits", "name": "limits",
        })).chain(links.shovels.list().into_iter().map(|s| json!({
            "value": s.parameters, "vhost": s.vhost, "component": crate::uplink::SHOVEL_COMPONENT, "name": s.name,
        })).chain(links.federation.upstreams().into_iter().map(|(vhost, name, value)| json!({
            "value": value, "vhost": vhost, "component": crate::federation::UPSTREAM_COMPONENT,
            "name": name,
        })))).collect::<Vec<_>>(),
        "global_parameters": crate::policies::global_parameters(admin, &crate::process::node_name()),
        "policies": admin.policies(PolicyKind::User, None).iter()
            .map(|(vhost, p)| crate::policies::policy_json(vhost, p)).collect::<Vec<_>>(),
        "operator_policies": admin.policies(PolicyKind::Operator, None).iter()
            .map(|(vhost, p)| crate::policies::policy_json(vhost, p)).collect::<Vec<_>>(),
        "queues": queues,
        "exchanges": exchanges,
        "bindings": bindings,
        LEVERET_SECTION: {
            "users": leveret_users,
            "permissions": leveret_permissions,
            "topic_permissions": leveret_topic_permissions,
            "warnings": warnings,
        },
    })
}

/// RabbitMQ's `permissions` list (definitions, `GET /api/permissions`).
pub fn permissions_json(admin: &Admin) -> Vec<Value> {
    admin
        .permissions()
        .into_iter()
        .map(|(user, vhost, p)| {
            json!({"user": user, "vhost": vhost,
                   "configure": p.configure, "write": p.write, "read": p.read})
        })
        .collect()
}

/// RabbitMQ's `topic_permissions` list.
pub fn topic_permissions_json(admin: &Admin) -> Vec<Value> {
    admin
        .topic_permissions()
        .into_iter()
        .map(|(user, vhost, exchange, t)| {
            json!({"user": user, "vhost": vhost, "exchange": exchange,
                   "write": t.write, "read": t.read})
        })
        .collect()
}

/// A permission pattern the broker can run (`""` when absent, which
/// RabbitMQ reads as `^$`).
fn pattern(item: &Map<String, Value>, key: &str, what: &str) -> Result<String, String> {
    let pattern = text(item, key, "")?;
    check_pattern(pattern).map_err(|e| format!("{what}: {e}"))?;
    Ok(pattern.to_owned())
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The start-up line counts everything the file defines, each kind once.
    #[test]
    fn summary_counts_every_kind_defined() {
        let text = br#"{"vhosts": [{"name": "/"}, {"name": "a"}],
            "users": [{"name": "u", "password_hash": "XrbDVjlDKoAec+dZ1vISo+jt5TVEqQvMa8euInsOyfsIm1Ys",
                "hashing_algorithm": "rabbit_password_hashing_sha256", "tags": []}],
            "permissions": [{"user": "u", "vhost": "/", "configure": ".*", "write": ".*", "read": ".*"},
                {"user": "u", "vhost": "a", "configure": ".*", "write": ".*", "read": ".*"}],
            "queues": [{"name": "q1", "vhost": "/"}, {"name": "q2", "vhost": "a"}, {"name": "q3", "vhost": "a"}],
            "exchanges": [{"name": "x", "vhost": "/", "type": "fanout"}],
            "bindings": [{"source": "x", "vhost": "/", "destination": "q1", "destination_type": "queue"}]}"#;
        let d = Definitions::parse(text).unwrap();
        assert_eq!(
            d.summary(),
            "2 vhosts, 1 user, 2 permissions, 1 exchange, 3 queues, 1 binding"
        );
        assert_eq!(Definitions::parse(b"{}").unwrap().summary(), "nothing");
    }

    /// RabbitMQ's user limits in `users[].limits` (-1: none) are taken
    /// and exported back.
    #[test]
    fn user_limits_are_read_and_written_as_rabbitmq_does() {
        let text = br#"{"users": [{"name": "lim", "password_hash": "XrbDVjlDKoAec+dZ1vISo+jt5TVEqQvMa8euInsOyfsIm1Ys",
            "hashing_algorithm": "rabbit_password_hashing_sha256", "tags": [],
            "limits": {"max-connections": 5, "max-channels": -1}}]}"#;
        let d = Definitions::parse(text).unwrap();
        let limits = d.users[0].limits.expect("limits");
        assert_eq!(limits.max_connections, Some(5));
        assert_eq!(limits.max_channels, None);
        assert_eq!(
            user_limits_json(Some(limits)),
            json!({"max-connections": 5})
        );
        assert_eq!(user_limits_json(None), json!({}));
        let bad =
            br#"{"users": [{"name": "x", "password_hash": "", "limits": {"max-queues": 1}}]}"#;
        assert!(Definitions::parse(bad)
            .unwrap_err()
            .contains("unknown limit 'max-queues'"));
    }

    #[test]
    fn what_is_not_applied_is_reported() {
        let text = br#"{
            "rabbit_version": "3.10.8",
            "users": [{"name": "a", "password_hash": "x", "hashing_algorithm": "rabbit_password_hashing_md5", "tags": ["administrator"]}],
            "vhosts": [{"name": "/", "limits": {"max-queues": 5}}],
            "permissions": [{"user": "a", "vhost": "/", "configure": ".*", "write": ".*", "read": ".*"}],
            "policies": [],
            "queues": [{"name": "q", "vhost": "/", "durable": true, "auto_delete": false, "arguments": {"x-queue-type": "quorum", "x-delivery-limit": 5, "x-message-ttl": 1000}}],
            "exchanges": [{"name": "x", "vhost": "/", "type": "topic", "durable": true, "auto_delete": false, "internal": false, "arguments": {}}],
            "bindings": [{"source": "x", "vhost": "/", "destination": "q", "destination_type": "queue", "routing_key": "k", "arguments": {}}],
            "shovels": [1]
        }"#;
        let d = Definitions::parse(text).unwrap();
        let all = d.warnings.join("\n");
        for expected in [
            "unknown key 'shovels'",
            "hashing algorithm rabbit_password_hashing_md5",
            "key 'limits'",
            "queue type 'quorum'",
            "arguments [\"x-delivery-limit\"] are not available on a classic queue",
        ] {
            assert!(all.contains(expected), "{expected} in:\n{all}");
        }
        assert!(!all.contains("policies"), "empty lists say nothing: {all}");
        assert_eq!(d.queues.len(), 1);
        let kept = &d.queues[0].2.arguments;
        assert!(kept.get("x-queue-type").is_none() && kept.get("x-delivery-limit").is_none());
        assert_eq!(
            kept.get("x-message-ttl").and_then(|v| v.as_i64()),
            Some(1000)
        );
        assert_eq!((d.exchanges.len(), d.bindings.len()), (1, 1));
    }

    #[test]
    fn a_stream_is_imported_as_a_stream_with_its_arguments() {
        let text = br#"{
            "queues": [{"name": "rec", "vhost": "/", "type": "stream", "durable": true, "auto_delete": false, "arguments": {"x-max-age": "7D", "x-stream-max-segment-size-bytes": 1000}},
                       {"name": "rec2", "vhost": "/", "durable": true, "auto_delete": false, "arguments": {"x-queue-type": "stream"}}]
        }"#;
        let d = Definitions::parse(text).unwrap();
        assert!(d.warnings.is_empty(), "{:?}", d.warnings);
        for (_, _, settings) in &d.queues {
            let kind = settings
                .arguments
                .get("x-queue-type")
                .and_then(|v| v.as_bytes());
            assert_eq!(kind, Some(&b"stream"[..]));
        }
        let age = d.queues[0]
            .2
            .arguments
            .get("x-max-age")
            .and_then(|v| v.as_bytes());
        assert_eq!(age, Some(&b"7D"[..]));
    }

    /// An empty `password_hash` is a user without a password, kept with
    /// its permissions; the `leveret` section's users and permissions are
    /// read as the others; unapplied lists are named item by item.
    #[test]
    fn users_without_passwords_and_the_leveret_section_are_read() {
        let text = br#"{
            "users": [{"name": "guest", "password_hash": "", "hashing_algorithm": "rabbit_password_hashing_sha256", "tags": ["administrator"]}],
            "permissions": [{"user": "guest", "vhost": "/", "configure": ".*", "write": ".*", "read": ".*"}],
            "operator_policies": [{"vhost": "/", "name": "cap", "pattern": ".*", "definition": {"max-length": 5}}],
            "leveret": {"users": [{"name": "arm", "password_hash": "", "hashing_algorithm": "leveret_password_hashing_argon2id", "tags": []}],
                        "permissions": [{"user": "arm", "vhost": "/", "configure": "", "write": ".*", "read": ""}],
                        "warnings": ["user 'arm' is in the 'leveret' section"]}
        }"#;
        let d = Definitions::parse(text).unwrap();
        let names: Vec<&str> = d.users.iter().map(|u| u.name.as_str()).collect();
        assert_eq!(names, ["guest", "arm"]);
        assert!(d.users.iter().all(|u| !u.hash.verify(b"guest")));
        assert_eq!(
            d.users[0].hash.to_rabbitmq(),
            (String::new(), RABBIT_SHA256)
        );
        assert_eq!(d.permissions.len(), 2);
        assert_eq!(d.operator_policies.len(), 1);
        assert!(d.warnings.is_empty(), "{:?}", d.warnings);
        assert!(Definitions::parse(br#"{"leveret": []}"#)
            .unwrap_err()
            .contains("'leveret' must be an object"));
    }

    #[test]
    fn malformed_documents_are_refused_with_a_reason() {
        for (text, reason) in [
            (&b"{"[..], "malformed JSON"),
            (b"[]", "must be a JSON object"),
            (b"{\"queues\": 5}", "'queues' must be a list"),
            (b"{\"queues\": [{\"vhost\": \"/\"}]}", "without a 'name'"),
            (b"{\"bindings\": [{\"vhost\": \"/\", \"source\": \"a\", \"destination\": \"b\", \"destination_type\": \"topic\"}]}", "unknown destination_type"),
        ] {
            let error = Definitions::parse(text).unwrap_err();
            assert!(error.contains(reason), "{error}");
        }
    }
}
