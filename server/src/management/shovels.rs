//! The management API's shovel paths, as RabbitMQ's shovel plugins
//! serve them: `/api/shovels[/{vhost}]` (each shovel's state and ends,
//! URIs without credentials) and `/api/parameters/shovel/{vhost}/{name}`
//! (reading, starting or replacing, and removing one; the listings of
//! parameters are `parameters`'). Changes go to `crate::uplink`, which
//! keeps them in the broker's store. Uses `common`, `json`, `caller` and
//! `parameters`.

use super::api::{ApiError, Context};
use super::caller::Caller;
use super::common::{body_object, created_or_not, no_content, require_vhost, ApiResult, Ctx};
use super::json;
use axum::body::Bytes;
use axum::extract::{Path, State};
use axum::{Extension, Json};
use serde_json::Value;

/// RabbitMQ's shovel-management listing: each shovel's name, vhost,
/// state and ends (URIs without credentials), and Leveret's counts.
pub async fn shovels(State(c): Ctx, Extension(caller): Extension<Caller>) -> Json<Value> {
    Json(Value::Array(
        c.links
            .shovels
            .list()
            .into_iter()
            .filter(|s| caller.sees_vhost(&s.vhost))
            .map(|s| json::shovel(&s, &c.node))
            .collect(),
    ))
}

/// One vhost's shovels (`GET /api/shovels/VHOST`).
pub async fn shovels_in(State(c): Ctx, Path(vhost): Path<String>) -> ApiResult<Json<Value>> {
    require_vhost(&c, &vhost)?;
    Ok(Json(Value::Array(
        c.links
            .shovels
            .list()
            .into_iter()
            .filter(|s| s.vhost == vhost)
            .map(|s| json::shovel(&s, &c.node))
            .collect(),
    )))
}

fn shovel_named(c: &Context, vhost: &str, name: &str) -> ApiResult<crate::uplink::Listed> {
    c.links
        .shovels
        .list()
        .into_iter()
        .find(|s| s.name == name && s.vhost == vhost)
        .ok_or_else(|| ApiError::not_found(format!("no shovel '{name}' in vhost '{vhost}'")))
}

/// A shovel's parameters, as RabbitMQ's `GET /api/parameters/shovel/VHOST/NAME`.
pub async fn shovel_parameter(
    State(c): Ctx,
    Path((vhost, name)): Path<(String, String)>,
) -> ApiResult<Json<Value>> {
    Ok(Json(super::parameters::shovel_parameter(shovel_named(
        &c, &vhost, &name,
    )?)))
}

/// Starts (or replaces) a shovel: RabbitMQ's
/// `PUT /api/parameters/shovel/VHOST/NAME` with `{"value": {...}}`.
pub async fn put_shovel(
    State(c): Ctx,
    Path((vhost, name)): Path<(String, String)>,
    body: Bytes,
) -> ApiResult {
    require_vhost(&c, &vhost)?;
    let body = body_object(&body)?;
    let value = body
        .get("value")
        .cloned()
        .ok_or_else(|| ApiError::bad_request("a shovel parameter needs a 'value'"))?;
    let existed = shovel_named(&c, &vhost, &name).is_ok();
    c.links.shovels.declare(&vhost, &name, value).await?;
    Ok(created_or_not(!existed))
}

/// Stops and removes a shovel, and its stored parameter.
pub async fn delete_shovel(
    State(c): Ctx,
    Path((vhost, name)): Path<(String, String)>,
) -> ApiResult {
    if c.links.shovels.delete(&vhost, &name).await? {
        Ok(no_content())
    } else {
        Err(ApiError::not_found(format!(
            "no shovel '{name}' in vhost '{vhost}'"
        )))
    }
}
