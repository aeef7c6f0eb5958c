//! The management API's federation paths, as RabbitMQ's federation
//! endpoints: upstreams (`/api/parameters/federation-upstream/VHOST/NAME`;
//! their listings are `parameters`') and the
//! links the policies run (`/api/federation-links`); policies are
//! `policies`'. Changes go to `crate::federation`, which keeps them in the
//! broker's store.

use super::api::ApiError;
use super::caller::Caller;
use super::common::{body_object, created_or_not, no_content, require_vhost, ApiResult, Ctx};
use super::parameters::upstream_parameter;
use crate::federation::Federation;
use axum::body::Bytes;
use axum::extract::{Path, State};
use axum::{Extension, Json};
use serde_json::{json, Value};

fn named(
    all: Vec<(String, String, Value)>,
    vhost: &str,
    name: &str,
    what: &str,
) -> ApiResult<(String, String, Value)> {
    all.into_iter()
        .find(|(v, n, _)| v == vhost && n == name)
        .ok_or_else(|| ApiError::not_found(format!("no {what} '{name}' in vhost '{vhost}'")))
}

pub async fn upstream(
    State(c): Ctx,
    Path((vhost, name)): Path<(String, String)>,
) -> ApiResult<Json<Value>> {
    let found = named(c.links.federation.upstreams(), &vhost, &name, "upstream")?;
    Ok(Json(upstream_parameter(found)))
}

/// The `value` of a parameter body (RabbitMQ's `{"value": {...}}`).
fn value_of(body: &Bytes, what: &str) -> ApiResult<Value> {
    body_object(body)?
        .remove("value")
        .ok_or_else(|| ApiError::bad_request(format!("a {what} needs a 'value'")))
}

fn exists(all: Vec<(String, String, Value)>, vhost: &str, name: &str) -> bool {
    all.iter().any(|(v, n, _)| v == vhost && n == name)
}

/// RabbitMQ's `PUT /api/parameters/federation-upstream/VHOST/NAME`.
pub async fn put_upstream(
    State(c): Ctx,
    Path((vhost, name)): Path<(String, String)>,
    body: Bytes,
) -> ApiResult {
    require_vhost(&c, &vhost)?;
    let value = value_of(&body, "federation upstream")?;
    let federation: &Federation = &c.links.federation;
    let existed = exists(federation.upstreams(), &vhost, &name);
    federation.set_upstream(&vhost, &name, value, true).await?;
    Ok(created_or_not(!existed))
}

pub async fn delete_upstream(
    State(c): Ctx,
    Path((vhost, name)): Path<(String, String)>,
) -> ApiResult {
    if c.links.federation.delete_upstream(&vhost, &name).await? {
        Ok(no_content())
    } else {
        Err(ApiError::not_found(format!(
            "no upstream '{name}' in vhost '{vhost}'"
        )))
    }
}

fn link_json(link: crate::federation::LinkListed, node: &str) -> Value {
    json!({
        "node": node,
        "vhost": link.vhost,
        "exchange": link.exchange,
        "upstream_exchange": link.upstream_exchange,
        "upstream": link.upstream,
        "type": "exchange",
        "id": format!("{}:{}:{}", link.vhost, link.exchange, link.upstream),
        "status": link.status.state.as_str(),
        "uri": link.status.upstream,
        "error": link.status.last_error,
        "forwarded": link.status.forwarded,
        "dropped_hops": link.status.dropped_hops,
        "bindings": link.status.bindings,
    })
}

/// RabbitMQ's `GET /api/federation-links`: each link's status, upstream
/// URI (without credentials) and last error, and Leveret's counts.
pub async fn links(State(c): Ctx, Extension(caller): Extension<Caller>) -> Json<Value> {
    Json(Value::Array(
        c.links
            .federation
            .links()
            .into_iter()
            .filter(|l| caller.sees_vhost(&l.vhost))
            .map(|l| link_json(l, &c.node))
            .collect(),
    ))
}

pub async fn links_in(State(c): Ctx, Path(vhost): Path<String>) -> ApiResult<Json<Value>> {
    require_vhost(&c, &vhost)?;
    Ok(Json(Value::Array(
        c.links
            .federation
            .links()
            .into_iter()
            .filter(|l| l.vhost == vhost)
            .map(|l| link_json(l, &c.node))
            .collect(),
    )))
}
