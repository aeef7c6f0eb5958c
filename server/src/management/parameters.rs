//! RabbitMQ's runtime-parameter listings over the components Leveret has
//! (`shovel`, `federation-upstream`): `GET /api/parameters` (what
//! `rabbitmqadmin list parameters` asks), `/api/parameters/{component}`
//! and `/api/parameters/{component}/{vhost}`, each parameter as
//! `{"value", "vhost", "component", "name"}`, only in the vhosts the
//! caller sees. A component Leveret does not have lists nothing, as
//! RabbitMQ lists a component no plugin registered. One parameter, and
//! changing one, are the components' own paths (`shovels`,
//! `federation`).

use super::api::Context;
use super::caller::Caller;
use super::common::{require_vhost, ApiResult, Ctx};
use crate::federation::UPSTREAM_COMPONENT;
use crate::uplink::{Listed, SHOVEL_COMPONENT};
use axum::extract::{Path, State};
use axum::{Extension, Json};
use serde_json::{json, Value};

/// A shovel's parameter as the API shows it.
pub fn shovel_parameter(shovel: Listed) -> Value {
    json!({"value": shovel.parameters, "vhost": shovel.vhost, "component": SHOVEL_COMPONENT, "name": shovel.name})
}

/// A federation upstream's parameter as the API shows it.
pub fn upstream_parameter((vhost, name, value): (String, String, Value)) -> Value {
    json!({"value": value, "vhost": vhost, "component": UPSTREAM_COMPONENT, "name": name})
}

/// Every parameter of `component` (of every component for `None`) in the
/// vhosts `keep` accepts.
fn listing(c: &Context, component: Option<&str>, keep: impl Fn(&str) -> bool) -> Json<Value> {
    let wanted = |name: &str| component.is_none_or(|c| c == name);
    let mut parameters = Vec::new();
    if wanted(SHOVEL_COMPONENT) {
        let shovels = c.links.shovels.list().into_iter();
        parameters.extend(shovels.filter(|s| keep(&s.vhost)).map(shovel_parameter));
    }
    if wanted(UPSTREAM_COMPONENT) {
        let upstreams = c.links.federation.upstreams().into_iter();
        parameters.extend(upstreams.filter(|(v, ..)| keep(v)).map(upstream_parameter));
    }
    Json(Value::Array(parameters))
}

/// `GET /api/parameters`.
pub async fn all(State(c): Ctx, Extension(caller): Extension<Caller>) -> Json<Value> {
    listing(&c, None, |vhost| caller.sees_vhost(vhost))
}

/// `GET /api/parameters/{component}`.
pub async fn of_component(
    State(c): Ctx,
    Path(component): Path<String>,
    Extension(caller): Extension<Caller>,
) -> Json<Value> {
    listing(&c, Some(&component), |vhost| caller.sees_vhost(vhost))
}

/// `GET /api/parameters/{component}/{vhost}`: 404 for a vhost that does
/// not exist.
pub async fn of_component_in(
    State(c): Ctx,
    Path((component, vhost)): Path<(String, String)>,
    Extension(caller): Extension<Caller>,
) -> ApiResult<Json<Value>> {
    require_vhost(&c, &vhost)?;
    Ok(listing(&c, Some(&component), |v| {
        v == vhost && caller.sees_vhost(v)
    }))
}
