//! `/api/exchanges[/{vhost}[/{name}]]` and `.../publish`: listing
//! exchanges (paginated when asked), reading, declaring and deleting one
//! as the caller (whose permissions the broker checks, `Admin::as_user`),
//! and publishing through one. Their bindings' listings are `bindings`'.
//! Uses `common`, `json`, `caller` and the broker through `Admin`.

use super::api::{ApiError, Context};
use super::caller::Caller;
use super::common::{
    body_object, created_or_not, exchange_name, listing, no_content, query_flag, require_vhost,
    ApiResult, Ctx, Params,
};
use super::json;
use axum::body::Bytes;
use axum::extract::{Path, Query, State};
use axum::{Extension, Json};
use base64::Engine;
use leveret_broker::ExchangeSettings;
use leveret_protocol::json::{properties, to_table};
use serde_json::{json, Value};
use std::collections::HashMap;

async fn exchange_list(
    c: &Context,
    caller: &Caller,
    vhost: Option<&str>,
    query: &HashMap<String, String>,
) -> ApiResult<Json<Value>> {
    let objects = c
        .admin
        .exchanges()
        .iter()
        .filter(|e| vhost.is_none_or(|v| e.vhost == v) && caller.sees_vhost(&e.vhost))
        .map(json::exchange)
        .collect();
    listing(objects, query).await
}

pub async fn exchanges(
    State(c): Ctx,
    Extension(caller): Extension<Caller>,
    Query(query): Params,
) -> ApiResult<Json<Value>> {
    exchange_list(&c, &caller, None, &query).await
}

pub async fn exchanges_in(
    State(c): Ctx,
    Extension(caller): Extension<Caller>,
    Path(vhost): Path<String>,
    Query(query): Params,
) -> ApiResult<Json<Value>> {
    require_vhost(&c, &vhost)?;
    exchange_list(&c, &caller, Some(&vhost), &query).await
}

pub async fn exchange(
    State(c): Ctx,
    Path((vhost, name)): Path<(String, String)>,
) -> ApiResult<Json<Value>> {
    require_vhost(&c, &vhost)?;
    let exchange = c
        .admin
        .exchange(&vhost, exchange_name(&name))
        .ok_or_else(|| ApiError::not_found(format!("no exchange '{name}' in vhost '{vhost}'")))?;
    Ok(Json(json::exchange(&exchange)))
}

pub async fn put_exchange(
    State(c): Ctx,
    Extension(caller): Extension<Caller>,
    Path((vhost, name)): Path<(String, String)>,
    body: Bytes,
) -> ApiResult {
    let body = body_object(&body)?;
    let settings = ExchangeSettings {
        kind: json::text(&body, "type", "")
            .map_err(ApiError::bad_request)?
            .to_owned(),
        durable: json::flag(&body, "durable", true).map_err(ApiError::bad_request)?,
        auto_delete: json::flag(&body, "auto_delete", false).map_err(ApiError::bad_request)?,
        internal: json::flag(&body, "internal", false).map_err(ApiError::bad_request)?,
        arguments: to_table(body.get("arguments").unwrap_or(&Value::Null))
            .map_err(ApiError::bad_request)?,
    };
    if settings.kind.is_empty() {
        return Err(ApiError::bad_request("an exchange needs a type"));
    }
    let existed = c.admin.exchange(&vhost, &name).is_some();
    c.admin
        .as_user(&caller.user)
        .declare_exchange(&vhost, &name, settings)
        .await?;
    Ok(created_or_not(!existed))
}

pub async fn delete_exchange(
    State(c): Ctx,
    Extension(caller): Extension<Caller>,
    Path((vhost, name)): Path<(String, String)>,
    Query(query): Query<HashMap<String, String>>,
) -> ApiResult {
    c.admin
        .as_user(&caller.user)
        .delete_exchange(&vhost, &name, query_flag(&query, "if-unused"))
        .await?;
    Ok(no_content())
}

/// RabbitMQ's `POST /api/exchanges/VHOST/NAME/publish`. A refusal is
/// RabbitMQ's answer to a publish its channel refused (400, the reply code
/// and text); during a memory or disk alarm, when AMQP publishers are
/// blocked, 503 (RabbitMQ 3.10 takes the message).
pub async fn publish(
    State(c): Ctx,
    Extension(caller): Extension<Caller>,
    Path((vhost, name)): Path<(String, String)>,
    body: Bytes,
) -> ApiResult<Json<Value>> {
    require_vhost(&c, &vhost)?;
    let body = body_object(&body)?;
    let bad = ApiError::bad_request;
    let routing_key = json::text(&body, "routing_key", "").map_err(bad)?;
    let properties = properties(body.get("properties")).map_err(ApiError::bad_request)?;
    let payload = json::text(&body, "payload", "").map_err(ApiError::bad_request)?;
    let payload =
        match json::text(&body, "payload_encoding", "string").map_err(ApiError::bad_request)? {
            "string" => Bytes::copy_from_slice(payload.as_bytes()),
            "base64" => Bytes::from(
                base64::engine::general_purpose::STANDARD
                    .decode(payload.trim())
                    .map_err(|e| ApiError::bad_request(format!("payload is not base64: {e}")))?,
            ),
            other => {
                return Err(ApiError::bad_request(format!(
                    "unknown payload_encoding {other}"
                )))
            }
        };
    let routed = c
        .admin
        .as_user(&caller.user)
        .publish(
            &vhost,
            exchange_name(&name),
            routing_key,
            properties,
            payload,
        )
        .await
        .map_err(ApiError::publish_refused)?;
    Ok(Json(json!({ "routed": routed })))
}
pub(super) fn require_exchange(c: &Context, vhost: &str, name: &str) -> ApiResult<String> {
    require_vhost(c, vhost)?;
    let name = exchange_name(name);
    c.admin
        .exchange(vhost, name)
        .map(|e| e.name)
        .ok_or_else(|| ApiError::not_found(format!("no exchange '{name}' in vhost '{vhost}'")))
}
