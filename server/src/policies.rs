//! The binary's policies, operator policies and cluster name, wherever
//! they come from (the config file, definitions, the management API,
//! leveretctl): RabbitMQ's JSON form read into the broker's
//! [`PolicySpec`] and back, each change put in force by the broker
//! (`Admin::set_policy`, which checks it and applies it to the vhost's
//! queues and exchanges at once) and kept as a runtime parameter
//! (components `policy` and `operator_policy`, as RabbitMQ keeps them), so
//! it outlasts a restart: `start_stored` sets them again at start. The
//! config file's policies are the config file's, not stored.
//!
//! The global parameters Leveret keeps (RabbitMQ's `set_global_parameter`),
//! each a runtime parameter of the component `global`: `cluster_name`, and
//! the broker's MQTT vhost mappings `mqtt_port_to_vhost_mapping` and
//! `mqtt_default_vhosts` (checked and read by the broker).

use crate::federation::Federation;
use crate::uplink::DeclareError;
use leveret_broker::{
    AccessError, Admin, ApplyTo, Policy, PolicyError, PolicyKind, PolicySpec, PolicyValue,
};
use serde_json::{json, Map, Value};
use std::collections::BTreeMap;

/// The runtime parameters' component for `kind`'s policies (RabbitMQ's).
pub fn component(kind: PolicyKind) -> &'static str {
    match kind {
        PolicyKind::User => "policy",
        PolicyKind::Operator => "operator_policy",
    }
}

/// The component and vhost the cluster name is kept under.
const GLOBAL: (&str, &str) = ("global", "");
/// RabbitMQ's name for the global parameter.
pub const CLUSTER_NAME: &str = "cluster_name";

/// Reads RabbitMQ's JSON form of a policy (`pattern`, `definition`,
/// `priority`, `apply-to`; `vhost` and `name` are the caller's).
pub fn spec_from_json(value: &Value) -> Result<PolicySpec, String> {
    let object = value.as_object().ok_or("a policy must be a JSON object")?;
    for key in object.keys() {
        if ![
            "pattern",
            "definition",
            "priority",
            "apply-to",
            "vhost",
            "name",
        ]
        .contains(&key.as_str())
        {
            return Err(format!("{key} is not a policy key"));
        }
    }
    let pattern = object
        .get("pattern")
        .and_then(Value::as_str)
        .ok_or("a policy needs a pattern")?;
    let apply_to = match object.get("apply-to") {
        None => ApplyTo::All,
        Some(word) => ApplyTo::parse(word.as_str().ok_or("apply-to must be a string")?)?,
    };
    // RabbitMQ takes the priority as a number or a numeric string.
    let priority = match object.get("priority") {
        None | Some(Value::Null) => 0,
        Some(Value::String(s)) => s
            .parse()
            .map_err(|_| format!("priority '{s}' is not an integer"))?,
        Some(n) => n.as_i64().ok_or("priority must be an integer")?,
    };
    let definition = object
        .get("definition")
        .and_then(Value::as_object)
        .ok_or("a policy needs a definition object")?
        .iter()
        .map(|(key, value)| (key.clone(), policy_value(value)))
        .collect();
    Ok(PolicySpec {
        pattern: pattern.to_owned(),
        apply_to,
        priority,
        definition,
    })
}

fn policy_value(value: &Value) -> PolicyValue {
    match value {
        Value::Number(n) => match n.as_i64() {
            Some(n) => PolicyValue::Integer(n),
            None => PolicyValue::Other("float".into()),
        },
        Value::String(s) => PolicyValue::Text(s.clone()),
        Value::Bool(_) => PolicyValue::Other("bool".into()),
        Value::Array(_) => PolicyValue::Other("list".into()),
        Value::Object(_) => PolicyValue::Other("object".into()),
        Value::Null => PolicyValue::Other("null".into()),
    }
}

fn value_json(value: &PolicyValue) -> Value {
    match value {
        PolicyValue::Integer(n) => json!(n),
        PolicyValue::Text(s) => json!(s),
        // Never in a checked policy.
        PolicyValue::Other(kind) => json!(kind),
    }
}

/// A definition as a JSON object.
pub fn definition_json<'a>(keys: impl IntoIterator<Item = (&'a String, &'a PolicyValue)>) -> Value {
    Value::Object(
        keys.into_iter()
            .map(|(key, value)| (key.clone(), value_json(value)))
            .collect::<Map<_, _>>(),
    )
}

/// RabbitMQ's listing of a policy (`/api/policies`, definitions).
pub fn policy_json(vhost: &str, policy: &Policy) -> Value {
    json!({
        "vhost": vhost,
        "name": policy.name,
        "pattern": policy.spec.pattern,
        "apply-to": policy.spec.apply_to.as_str(),
        "definition": definition_json(policy.spec.definition.iter().map(|(k, v)| (k, v))),
        "priority": policy.spec.priority,
    })
}

/// What the store keeps of a policy (RabbitMQ's parameter value).
fn stored_json(policy: &Policy) -> Value {
    let mut listed = policy_json("", policy);
    if let Some(map) = listed.as_object_mut() {
        map.remove("vhost");
        map.remove("name");
    }
    listed
}

/// A queue's or exchange's `policy`, `operator_policy` and
/// `effective_policy_definition`, as RabbitMQ lists them.
pub fn applied_json(applied: &leveret_broker::AppliedPolicies) -> [(&'static str, Value); 3] {
    let effective: BTreeMap<String, PolicyValue> = applied.effective_definition();
    [
        ("policy", json!(applied.policy_name())),
        ("operator_policy", json!(applied.operator_policy_name())),
        ("effective_policy_definition", definition_json(&effective)),
    ]
}

/// `value` with its `definition` as a JSON object: RabbitMQ 3.10 exports
/// an operator policy's as a list of `[key, value]` pairs.
pub fn with_definition_object(mut value: Value) -> Value {
    if let Some(Value::Array(pairs)) = value.get("definition") {
        let object: Option<Map<String, Value>> = pairs
            .iter()
            .map(|pair| match pair.as_array().map(Vec::as_slice) {
                Some([Value::String(key), value]) => Some((key.clone(), value.clone())),
                _ => None,
            })
            .collect();
        if let (Some(object), Some(map)) = (object, value.as_object_mut()) {
            map.insert("definition".into(), Value::Object(object));
        }
    }
    value
}

/// Checks RabbitMQ's JSON form of a policy of `kind` as setting it would.
pub fn check(kind: PolicyKind, value: &Value) -> Result<(), String> {
    let spec = spec_from_json(value)?;
    check_federation_keys(&spec)?;
    Policy::new(kind, "checked", spec).map(|_| ())
}

/// The federation has no named upstream sets: `federation-upstream-set`
/// is `all` or refused. It federates exchanges only (no queue
/// federation), so a policy with either federation key that applies to
/// queues alone is refused: there the key would be kept and do nothing.
/// One that applies to `all` (RabbitMQ's default) federates the
/// exchanges it matches; the queues it matches get its other keys.
fn check_federation_keys(spec: &PolicySpec) -> Result<(), String> {
    let federates = spec
        .definition
        .iter()
        .find(|(key, _)| key == "federation-upstream-set" || key == "federation-upstream");
    match federates {
        Some((key, _)) if spec.apply_to == ApplyTo::Queues => Err(format!(
            "{key}: Leveret federates exchanges only (it has no queue federation): \
             the policy must apply to exchanges or all, not queues"
        )),
        Some((key, PolicyValue::Text(set))) if key == "federation-upstream-set" && set != "all" => {
            Err("federation-upstream-set: only \"all\" (Leveret has no named upstream sets)".into())
        }
        _ => Ok(()),
    }
}

/// One policy in RabbitMQ's JSON form and where it goes.
pub struct Item<'a> {
    /// User or operator policy.
    pub kind: PolicyKind,
    /// Its vhost.
    pub vhost: &'a str,
    /// Its name.
    pub name: &'a str,
    /// RabbitMQ's JSON form.
    pub value: &'a Value,
}

/// Sets the policy `name` of `kind` in `vhost` from RabbitMQ's JSON form;
/// `store` keeps it as a runtime parameter (the API's and imports'). The
/// federation takes its keys at once.
pub async fn set(
    admin: &Admin,
    federation: &Federation,
    kind: PolicyKind,
    vhost: &str,
    name: &str,
    value: &Value,
    store: bool,
) -> Result<(), DeclareError> {
    let item = Item {
        kind,
        vhost,
        name,
        value,
    };
    set_all(admin, federation, &[item], store)
        .await
        .map_err(|(_, e)| e)
}

/// Sets every policy of `items` (an import, the stored ones at start):
/// all are read and checked first, and none is set if one is refused
/// (its index in `items` and why are returned); then each vhost's set is ranked and
/// carried to its queues once (`Admin::set_policies`), each is stored if
/// `store`, and the federation takes their keys once: work that grows
/// with policies plus queues, not with their product.
pub async fn set_all(
    admin: &Admin,
    federation: &Federation,
    items: &[Item<'_>],
    store: bool,
) -> Result<(), (usize, DeclareError)> {
    if items.is_empty() {
        return Ok(());
    }
    // Compiling N patterns is work that grows with N: off the broker's
    // threads.
    let given: Vec<(PolicyKind, String, String, Value)> = items
        .iter()
        .map(|item| {
            (
                item.kind,
                item.vhost.to_owned(),
                item.name.to_owned(),
                item.value.clone(),
            )
        })
        .collect();
    let checked = tokio::task::spawn_blocking(move || {
        let mut checked = Vec::with_capacity(given.len());
        for (at, (kind, vhost, name, value)) in given.into_iter().enumerate() {
            let read = spec_from_json(&value)
                .and_then(|spec| check_federation_keys(&spec).map(|()| spec))
                .and_then(|spec| Policy::new(kind, &name, spec));
            checked.push((vhost, read.map_err(|e| (at, e))?));
        }
        Ok(checked)
    })
    .await
    .unwrap_or_else(|e| Err((0, format!("the check failed: {e}"))))
    .map_err(|(at, e)| (at, DeclareError::Invalid(e)))?;
    // Kept by component, each in one store write.
    let mut stored: BTreeMap<&'static str, Vec<(String, String, String)>> = BTreeMap::new();
    if store {
        for (vhost, policy) in &checked {
            let text = stored_json(policy).to_string();
            let kept = (vhost.clone(), policy.name.clone(), text);
            stored.entry(component(policy.kind)).or_default().push(kept);
        }
    }
    admin.set_policies(checked).await.map_err(|e| {
        let at = match &e {
            PolicyError::NoVhost(vhost) => items.iter().position(|item| item.vhost == vhost),
            PolicyError::Invalid(_) => None,
        };
        (at.unwrap_or(0), DeclareError::Invalid(e.to_string()))
    })?;
    for (of, parameters) in stored {
        // A store that fails fails them all: the first is named.
        let first = items.iter().position(|item| component(item.kind) == of);
        admin
            .set_parameters(of, parameters)
            .await
            .map_err(|e| (first.unwrap_or(0), e.into()))?;
    }
    federation.reconcile().await;
    Ok(())
}

/// Clears the policy `name` of `kind` in `vhost`; false if there was none.
pub async fn clear(
    admin: &Admin,
    federation: &Federation,
    kind: PolicyKind,
    vhost: &str,
    name: &str,
) -> Result<bool, AccessError> {
    let stored = admin.clear_parameter(component(kind), vhost, name).await?;
    let cleared = admin.clear_policy(kind, vhost, name).await;
    federation.reconcile().await;
    Ok(stored || cleared)
}

/// Sets the policies the broker's store kept, all at once; one that no
/// longer reads is logged and left out.
pub async fn start_stored(admin: &Admin, federation: &Federation) {
    let mut stored = Vec::new();
    for kind in [PolicyKind::User, PolicyKind::Operator] {
        for (vhost, name, text) in admin.parameters(component(kind)) {
            match serde_json::from_str::<Value>(&text) {
                Ok(value) => stored.push((kind, vhost, name, value)),
                Err(e) => {
                    tracing::error!(component = component(kind), %name, %vhost, error = %e, "a stored policy is not applied");
                }
            }
        }
    }
    // A stored policy that no longer reads (a key a later version
    // refuses) must not keep the others out: those are left out one by
    // one until the rest is set.
    loop {
        let items: Vec<Item> = stored
            .iter()
            .map(|(kind, vhost, name, value)| Item {
                kind: *kind,
                vhost,
                name,
                value,
            })
            .collect();
        let Err((at, e)) = set_all(admin, federation, &items, false).await else {
            return;
        };
        let (kind, vhost, name, _) = stored.remove(at);
        tracing::error!(component = component(kind), %name, %vhost, error = %e, "a stored policy is not applied");
    }
}

/// The cluster name: the one set, else `default` (RabbitMQ's default is
/// its node's name).
pub fn cluster_name(admin: &Admin, default: &str) -> String {
    admin
        .parameters(GLOBAL.0)
        .into_iter()
        .find(|(vhost, name, _)| vhost == GLOBAL.1 && name == CLUSTER_NAME)
        .and_then(|(_, _, text)| serde_json::from_str::<String>(&text).ok())
        .unwrap_or_else(|| default.to_owned())
}

/// Sets the cluster name (`rabbitmqctl set_cluster_name`), kept in the
/// store.
pub async fn set_cluster_name(admin: &Admin, name: &str) -> Result<(), DeclareError> {
    if name.is_empty() {
        return Err(DeclareError::Invalid(
            "a cluster name cannot be empty".into(),
        ));
    }
    admin
        .set_parameter(GLOBAL.0, GLOBAL.1, CLUSTER_NAME, json!(name).to_string())
        .await?;
    Ok(())
}

/// The MQTT vhost mappings: global parameters the broker reads.
const MQTT_MAPPINGS: [&str; 2] = [
    leveret_broker::PORT_MAPPING,
    leveret_broker::CERTIFICATE_MAPPING,
];

/// The global parameters, as RabbitMQ lists them (`name`, `value`): the
/// cluster name (its default when unset), and the MQTT mappings set.
pub fn global_parameters(admin: &Admin, node: &str) -> Vec<Value> {
    let cluster = json!({"name": CLUSTER_NAME, "value": cluster_name(admin, node)});
    let mappings = admin
        .parameters(GLOBAL.0)
        .into_iter()
        .filter(|(vhost, name, _)| vhost == GLOBAL.1 && MQTT_MAPPINGS.contains(&name.as_str()))
        .filter_map(|(_, name, text)| {
            let value = serde_json::from_str::<Value>(&text).ok()?;
            Some(json!({"name": name, "value": value}))
        });
    std::iter::once(cluster).chain(mappings).collect()
}

/// Whether Leveret keeps global parameter `name`.
pub fn is_global_parameter(name: &str) -> bool {
    name == CLUSTER_NAME || MQTT_MAPPINGS.contains(&name)
}

/// Whether global parameter `name` is one Leveret keeps and `value` one it
/// can use; the reason otherwise.
pub fn check_global_parameter(name: &str, value: &Value) -> Result<(), String> {
    match (name, value) {
        (CLUSTER_NAME, Value::String(text)) if !text.is_empty() => Ok(()),
        (CLUSTER_NAME, _) => Err("cluster_name must be a non-empty string".into()),
        (name, value) if MQTT_MAPPINGS.contains(&name) => {
            leveret_broker::check_global_parameter(name, &value.to_string())
        }
        (other, _) => Err(format!(
            "Leveret keeps only the global parameters {CLUSTER_NAME}, {} and {}, not '{other}'",
            MQTT_MAPPINGS[0], MQTT_MAPPINGS[1]
        )),
    }
}

/// Sets global parameter `name` (`rabbitmqctl set_global_parameter`),
/// kept in the store; a name or value Leveret cannot use is refused.
pub async fn set_global_parameter(
    admin: &Admin,
    name: &str,
    value: &Value,
) -> Result<(), DeclareError> {
    check_global_parameter(name, value).map_err(DeclareError::Invalid)?;
    match value {
        Value::String(text) if name == CLUSTER_NAME => set_cluster_name(admin, text).await,
        _ => Ok(admin
            .set_parameter(GLOBAL.0, GLOBAL.1, name, value.to_string())
            .await?),
    }
}

/// Clears global parameter `name` (`clear_global_parameter`); false if
/// it was not set.
pub async fn clear_global_parameter(admin: &Admin, name: &str) -> Result<bool, DeclareError> {
    Ok(admin.clear_parameter(GLOBAL.0, GLOBAL.1, name).await?)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rabbitmqs_json_reads_and_lists_back() {
        let given = json!({"pattern": "^q", "apply-to": "queues", "priority": "3",
                           "definition": {"max-length": 5, "overflow": "reject-publish"}});
        let spec = spec_from_json(&given).unwrap();
        assert_eq!(spec.priority, 3);
        assert_eq!(spec.apply_to, ApplyTo::Queues);
        let policy = Policy::new(PolicyKind::User, "p", spec).unwrap();
        assert_eq!(
            policy_json("/", &policy),
            json!({"vhost": "/", "name": "p", "pattern": "^q", "apply-to": "queues", "priority": 3,
                   "definition": {"max-length": 5, "overflow": "reject-publish"}})
        );
        for bad in [
            json!({"definition": {"max-length": 1}}),
            json!({"pattern": ".*"}),
            json!({"pattern": ".*", "apply-to": "bindings", "definition": {"max-length": 1}}),
            json!({"pattern": ".*", "colour": "red", "definition": {"max-length": 1}}),
        ] {
            assert!(spec_from_json(&bad).is_err(), "{bad}");
        }
        let federating = |apply_to: &str| {
            json!({"pattern": ".*", "apply-to": apply_to,
                   "definition": {"federation-upstream-set": "all"}})
        };
        let refused = check(PolicyKind::User, &federating("queues")).unwrap_err();
        assert!(refused.contains("federates exchanges only"), "{refused}");
        check(PolicyKind::User, &federating("all")).unwrap();
        check(
            PolicyKind::User,
            &json!({"pattern": ".*", "apply-to": "exchanges",
                    "definition": {"federation-upstream": "fleet"}}),
        )
        .unwrap();
        let float =
            spec_from_json(&json!({"pattern": ".*", "definition": {"max-length": 1.5}})).unwrap();
        assert!(Policy::new(PolicyKind::User, "f", float)
            .unwrap_err()
            .contains("a float"));
    }
}
