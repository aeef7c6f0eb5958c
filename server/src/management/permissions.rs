//! `/api/permissions[/{vhost}/{user}]` and
//! `/api/topic-permissions[/{vhost}/{user}]`: every user's permissions
//! (as the definitions export writes them, `crate::definitions`), one
//! user's on one vhost, granting and clearing them. Uses `common`, `json`
//! and the broker through `Admin`.

use super::api::{ApiError, Context};
use super::common::{body_object, created_or_not, no_content, require_vhost, ApiResult, Ctx};
use super::json;
use axum::body::Bytes;
use axum::extract::{Path, Query, State};
use axum::Json;
use leveret_broker::{Permission, TopicPermission};
use serde_json::Value;
use std::collections::HashMap;

/// Every user's permissions.
pub async fn permissions(State(c): Ctx) -> Json<Value> {
    Json(Value::Array(crate::definitions::permissions_json(&c.admin)))
}

fn require_user(c: &Context, user: &str) -> ApiResult<()> {
    if c.admin.users().iter().any(|(name, _)| name == user) {
        Ok(())
    } else {
        Err(ApiError::not_found(format!("no user '{user}'")))
    }
}

/// A permission request's text fields (RabbitMQ's: missing is `""`),
/// once the vhost and the user are known to exist.
fn permission_body(
    c: &Context,
    vhost: &str,
    user: &str,
    body: &Bytes,
) -> ApiResult<impl Fn(&str) -> ApiResult<String>> {
    require_vhost(c, vhost)?;
    require_user(c, user)?;
    let body = body_object(body)?;
    Ok(move |key: &str| {
        json::text(&body, key, "")
            .map(str::to_owned)
            .map_err(ApiError::bad_request)
    })
}

/// One user's permission on one vhost.
pub async fn permission(
    State(c): Ctx,
    Path((vhost, user)): Path<(String, String)>,
) -> ApiResult<Json<Value>> {
    crate::definitions::permissions_json(&c.admin)
        .into_iter()
        .find(|p| p["vhost"] == vhost.as_str() && p["user"] == user.as_str())
        .map(Json)
        .ok_or_else(|| ApiError::not_found(format!("no permission of '{user}' on vhost '{vhost}'")))
}

/// RabbitMQ's `PUT /api/permissions/{vhost}/{user}` with `configure`,
/// `write` and `read`; applies to the user's open channels from their
/// next operation.
pub async fn put_permission(
    State(c): Ctx,
    Path((vhost, user)): Path<(String, String)>,
    body: Bytes,
) -> ApiResult {
    let field = permission_body(&c, &vhost, &user, &body)?;
    let permission = Permission {
        configure: field("configure")?,
        write: field("write")?,
        read: field("read")?,
    };
    let existed = c
        .admin
        .permissions()
        .iter()
        .any(|(u, v, _)| *u == user && *v == vhost);
    c.admin.set_permission(&user, &vhost, permission).await?;
    Ok(created_or_not(!existed))
}

pub async fn delete_permission(
    State(c): Ctx,
    Path((vhost, user)): Path<(String, String)>,
) -> ApiResult {
    c.admin.clear_permission(&user, &vhost).await?;
    Ok(no_content())
}

/// RabbitMQ's `PUT /api/topic-permissions/{vhost}/{user}` with
/// `exchange`, `write` and `read`.
pub async fn put_topic_permission(
    State(c): Ctx,
    Path((vhost, user)): Path<(String, String)>,
    body: Bytes,
) -> ApiResult {
    let field = permission_body(&c, &vhost, &user, &body)?;
    let exchange = field("exchange")?;
    let permission = TopicPermission {
        write: field("write")?,
        read: field("read")?,
    };
    c.admin
        .set_topic_permission(&user, &vhost, &exchange, permission)
        .await?;
    Ok(no_content())
}

/// Removes the user's topic permissions on the vhost (on one exchange
/// with `?exchange=`).
pub async fn delete_topic_permission(
    State(c): Ctx,
    Path((vhost, user)): Path<(String, String)>,
    Query(query): Query<HashMap<String, String>>,
) -> ApiResult {
    for (u, v, exchange, _) in c.admin.topic_permissions() {
        if u == user && v == vhost && query.get("exchange").is_none_or(|e| *e == exchange) {
            c.admin
                .clear_topic_permission(&user, &vhost, &exchange)
                .await?;
        }
    }
    Ok(no_content())
}

/// Every user's topic permissions.
pub async fn topic_permissions(State(c): Ctx) -> Json<Value> {
    Json(Value::Array(crate::definitions::topic_permissions_json(
        &c.admin,
    )))
}
