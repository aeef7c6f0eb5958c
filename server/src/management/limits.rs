//! RabbitMQ's limit paths: `/api/vhost-limits[/{vhost}[/{name}]]` and
//! `/api/user-limits[/{user}[/{name}]]`. A listing is
//! `[{"vhost"|"user": ..., "value": {"max-connections": 10, ...}}]`; PUT
//! takes `{"value": N}` (negative: no limit) and sets that one limit,
//! DELETE clears it, both 204 as RabbitMQ answers. Changes go through
//! [`leveret_broker::Admin`], which keeps them in the store.

use super::api::{ApiError, Context};
use super::caller::Caller;
use super::common::{body_object, no_content, require_vhost, ApiResult, Ctx};
use axum::body::Bytes;
use axum::extract::{Path, State};
use axum::{Extension, Json};
use leveret_broker::{UserLimits, VhostLimits};
use serde_json::{json, Map, Value};

fn value_json(named: Vec<(&'static str, usize)>) -> Value {
    Value::Object(
        named
            .into_iter()
            .map(|(name, value)| (name.to_owned(), json!(value)))
            .collect::<Map<String, Value>>(),
    )
}

/// The integer a PUT body's `value` holds.
fn body_value(body: &Bytes) -> ApiResult<i64> {
    let body = body_object(body)?;
    match body.get("value") {
        Some(Value::Number(n)) => n
            .as_i64()
            .ok_or_else(|| ApiError::bad_request(format!("limit value {n} is not an integer"))),
        Some(Value::String(text)) => text
            .trim()
            .parse()
            .map_err(|_| ApiError::bad_request(format!("limit value '{text}' is not an integer"))),
        _ => Err(ApiError::bad_request("the body needs an integer \"value\"")),
    }
}

fn vhost_entry(vhost: &str, limits: VhostLimits) -> Value {
    json!({"vhost": vhost, "value": value_json(limits.named())})
}

fn user_entry(user: &str, limits: UserLimits) -> Value {
    json!({"user": user, "value": value_json(limits.named())})
}

pub async fn vhost_limits(State(c): Ctx, Extension(caller): Extension<Caller>) -> Json<Value> {
    let all = c.admin.all_vhost_limits();
    let seen = all.iter().filter(|(vhost, _)| caller.sees_vhost(vhost));
    Json(seen.map(|(v, l)| vhost_entry(v, *l)).collect())
}

pub async fn vhost_limits_of(State(c): Ctx, Path(vhost): Path<String>) -> ApiResult<Json<Value>> {
    require_vhost(&c, &vhost)?;
    let limits = c.admin.vhost_limits(&vhost);
    let listed = (limits != VhostLimits::default()).then(|| vhost_entry(&vhost, limits));
    Ok(Json(listed.into_iter().collect()))
}

pub async fn put_vhost_limit(
    State(c): Ctx,
    Path((vhost, name)): Path<(String, String)>,
    body: Bytes,
) -> ApiResult {
    require_vhost(&c, &vhost)?;
    let value = body_value(&body)?;
    let limits = (c.admin.vhost_limits(&vhost).with(&name, value))
        .map_err(|e| ApiError::bad_request(e.to_string()))?;
    c.admin.set_vhost_limits(&vhost, limits).await?;
    Ok(no_content())
}

pub async fn delete_vhost_limit(
    State(c): Ctx,
    Path((vhost, name)): Path<(String, String)>,
) -> ApiResult {
    require_vhost(&c, &vhost)?;
    let limits = (c.admin.vhost_limits(&vhost).with(&name, -1))
        .map_err(|e| ApiError::bad_request(e.to_string()))?;
    c.admin.set_vhost_limits(&vhost, limits).await?;
    Ok(no_content())
}

pub async fn user_limits(State(c): Ctx) -> Json<Value> {
    let all = c.admin.all_user_limits();
    Json(all.iter().map(|(u, l)| user_entry(u, *l)).collect())
}

fn require_user(c: &Context, user: &str) -> ApiResult<()> {
    match c.admin.users().iter().any(|(name, _)| name == user) {
        true => Ok(()),
        false => Err(ApiError::not_found(format!("no user '{user}'"))),
    }
}

pub async fn user_limits_of(State(c): Ctx, Path(user): Path<String>) -> ApiResult<Json<Value>> {
    require_user(&c, &user)?;
    let listed = c.admin.user_limits(&user).map(|l| user_entry(&user, l));
    Ok(Json(listed.into_iter().collect()))
}

pub async fn put_user_limit(
    State(c): Ctx,
    Path((user, name)): Path<(String, String)>,
    body: Bytes,
) -> ApiResult {
    require_user(&c, &user)?;
    let value = body_value(&body)?;
    let limits = (c
        .admin
        .user_limits(&user)
        .unwrap_or_default()
        .with(&name, value))
    .map_err(|e| ApiError::bad_request(e.to_string()))?;
    c.admin.set_user_limits(&user, limits).await?;
    Ok(no_content())
}

pub async fn delete_user_limit(
    State(c): Ctx,
    Path((user, name)): Path<(String, String)>,
) -> ApiResult {
    require_user(&c, &user)?;
    let limits = (c
        .admin
        .user_limits(&user)
        .unwrap_or_default()
        .with(&name, -1))
    .map_err(|e| ApiError::bad_request(e.to_string()))?;
    c.admin.set_user_limits(&user, limits).await?;
    Ok(no_content())
}
