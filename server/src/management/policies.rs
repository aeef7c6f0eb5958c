//! The management API's policy paths, as RabbitMQ's: `/api/policies`
//! and `/api/operator-policies` (all, one vhost's, one policy: GET, PUT,
//! DELETE), `/api/cluster-name` and `/api/global-parameters` (all, one:
//! GET, PUT, DELETE). Who may call them is `caller`'s (policymaker for
//! policies, administrator for operator policies, global parameters and
//! setting the cluster name); the changes go through `crate::policies`.

use super::api::{ApiError, Context};
use super::caller::Caller;
use super::common::{body_object, created_or_not, no_content, require_vhost, ApiResult, Ctx};
use crate::policies;
use axum::body::Bytes;
use axum::extract::{Path, State};
use axum::{Extension, Json};
use leveret_broker::PolicyKind;
use serde_json::{json, Value};

fn listed(c: &Context, kind: PolicyKind, vhost: Option<&str>, caller: &Caller) -> Json<Value> {
    Json(Value::Array(
        c.admin
            .policies(kind, vhost)
            .iter()
            .filter(|(v, _)| caller.sees_vhost(v))
            .map(|(v, policy)| policies::policy_json(v, policy))
            .collect(),
    ))
}

async fn one(c: &Context, kind: PolicyKind, vhost: String, name: String) -> ApiResult<Json<Value>> {
    c.admin
        .policies(kind, Some(&vhost))
        .iter()
        .find(|(_, p)| p.name == name)
        .map(|(v, p)| Json(policies::policy_json(v, p)))
        .ok_or_else(|| ApiError::not_found(format!("no policy '{name}' in vhost '{vhost}'")))
}

async fn put(c: &Context, kind: PolicyKind, vhost: String, name: String, body: Bytes) -> ApiResult {
    require_vhost(c, &vhost)?;
    let value = Value::Object(body_object(&body)?);
    let existed = c
        .admin
        .policies(kind, Some(&vhost))
        .iter()
        .any(|(_, p)| p.name == name);
    policies::set(
        &c.admin,
        &c.links.federation,
        kind,
        &vhost,
        &name,
        &value,
        true,
    )
    .await?;
    Ok(created_or_not(!existed))
}

async fn delete(c: &Context, kind: PolicyKind, vhost: String, name: String) -> ApiResult {
    if policies::clear(&c.admin, &c.links.federation, kind, &vhost, &name).await? {
        Ok(no_content())
    } else {
        Err(ApiError::not_found(format!(
            "no policy '{name}' in vhost '{vhost}'"
        )))
    }
}

pub async fn all(State(c): Ctx, Extension(caller): Extension<Caller>) -> Json<Value> {
    listed(&c, PolicyKind::User, None, &caller)
}

pub async fn in_vhost(
    State(c): Ctx,
    Extension(caller): Extension<Caller>,
    Path(vhost): Path<String>,
) -> ApiResult<Json<Value>> {
    require_vhost(&c, &vhost)?;
    Ok(listed(&c, PolicyKind::User, Some(&vhost), &caller))
}

pub async fn get_one(
    State(c): Ctx,
    Path((vhost, name)): Path<(String, String)>,
) -> ApiResult<Json<Value>> {
    one(&c, PolicyKind::User, vhost, name).await
}

pub async fn put_one(
    State(c): Ctx,
    Path((vhost, name)): Path<(String, String)>,
    body: Bytes,
) -> ApiResult {
    put(&c, PolicyKind::User, vhost, name, body).await
}

pub async fn delete_one(State(c): Ctx, Path((vhost, name)): Path<(String, String)>) -> ApiResult {
    delete(&c, PolicyKind::User, vhost, name).await
}

pub async fn operator_all(State(c): Ctx, Extension(caller): Extension<Caller>) -> Json<Value> {
    listed(&c, PolicyKind::Operator, None, &caller)
}

pub async fn operator_in_vhost(
    State(c): Ctx,
    Extension(caller): Extension<Caller>,
    Path(vhost): Path<String>,
) -> ApiResult<Json<Value>> {
    require_vhost(&c, &vhost)?;
    Ok(listed(&c, PolicyKind::Operator, Some(&vhost), &caller))
}

pub async fn operator_get_one(
    State(c): Ctx,
    Path((vhost, name)): Path<(String, String)>,
) -> ApiResult<Json<Value>> {
    one(&c, PolicyKind::Operator, vhost, name).await
}

pub async fn operator_put_one(
    State(c): Ctx,
    Path((vhost, name)): Path<(String, String)>,
    body: Bytes,
) -> ApiResult {
    put(&c, PolicyKind::Operator, vhost, name, body).await
}

pub async fn operator_delete_one(
    State(c): Ctx,
    Path((vhost, name)): Path<(String, String)>,
) -> ApiResult {
    delete(&c, PolicyKind::Operator, vhost, name).await
}

/// RabbitMQ's `GET /api/cluster-name`.
pub async fn cluster_name(State(c): Ctx) -> Json<Value> {
    Json(json!({"name": policies::cluster_name(&c.admin, &c.node)}))
}

/// RabbitMQ's `PUT /api/cluster-name` (`{"name": "..."}`).
pub async fn put_cluster_name(State(c): Ctx, body: Bytes) -> ApiResult {
    let object = body_object(&body)?;
    let name = object
        .get("name")
        .and_then(Value::as_str)
        .ok_or_else(|| ApiError::bad_request("a cluster name needs a 'name'"))?;
    policies::set_cluster_name(&c.admin, name).await?;
    Ok(no_content())
}

/// RabbitMQ's `GET /api/global-parameters`.
pub async fn global_parameters(State(c): Ctx) -> Json<Value> {
    Json(Value::Array(policies::global_parameters(&c.admin, &c.node)))
}

/// RabbitMQ's `GET /api/global-parameters/{name}`.
pub async fn global_parameter(State(c): Ctx, Path(name): Path<String>) -> ApiResult<Json<Value>> {
    policies::global_parameters(&c.admin, &c.node)
        .into_iter()
        .find(|item| item["name"] == name.as_str())
        .map(Json)
        .ok_or_else(|| ApiError::not_found(format!("no global parameter '{name}'")))
}

/// RabbitMQ's `PUT /api/global-parameters/{name}` (`{"value": ...}`, as
/// `rabbitmqctl set_global_parameter`): a value Leveret cannot use is a
/// 400 with the reason, and nothing is stored.
pub async fn put_global_parameter(
    State(c): Ctx,
    Path(name): Path<String>,
    body: Bytes,
) -> ApiResult {
    let object = body_object(&body)?;
    let value = object
        .get("value")
        .ok_or_else(|| ApiError::bad_request("a global parameter needs a 'value'"))?;
    policies::set_global_parameter(&c.admin, &name, value).await?;
    Ok(no_content())
}

/// RabbitMQ's `DELETE /api/global-parameters/{name}`.
pub async fn delete_global_parameter(State(c): Ctx, Path(name): Path<String>) -> ApiResult {
    if policies::clear_global_parameter(&c.admin, &name).await? {
        Ok(no_content())
    } else {
        Err(ApiError::not_found(format!("no global parameter '{name}'")))
    }
}
