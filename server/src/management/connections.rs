//! `/api/connections[/{name}]`: listing the connections the caller may
//! see (paginated when asked), reading one, and closing one with the
//! reason the client gives in `X-Reason`. Uses `common`, `json`, `caller`
//! and the broker through `Admin`.

use super::api::{ApiError, Context};
use super::caller::Caller;
use super::common::{listing, no_content, ApiResult, Ctx, Params};
use super::json;
use axum::extract::{Path, Query, State};
use axum::http::HeaderMap;
use axum::{Extension, Json};
use serde_json::Value;

/// The close reason when the client gives none (RabbitMQ's).
const CLOSE_REASON: &str = "Closed via management plugin";

pub async fn connections(
    State(c): Ctx,
    Extension(caller): Extension<Caller>,
    Query(query): Params,
) -> ApiResult<Json<Value>> {
    let objects = c
        .admin
        .connections()
        .iter()
        .filter(|conn| caller.sees_user(&conn.user))
        .map(|conn| json::connection(conn, &c.node))
        .collect();
    listing(objects, &query).await
}

fn connection_named(c: &Context, name: &str) -> ApiResult<leveret_broker::ConnectionInfo> {
    c.admin
        .connections()
        .into_iter()
        .find(|conn| json::connection_name(conn.id, &conn.peer) == name)
        .ok_or_else(|| ApiError::not_found(format!("no connection '{name}'")))
}

pub async fn connection(State(c): Ctx, Path(name): Path<String>) -> ApiResult<Json<Value>> {
    let conn = connection_named(&c, &name)?;
    Ok(Json(json::connection(&conn, &c.node)))
}

pub async fn close_connection(
    State(c): Ctx,
    Path(name): Path<String>,
    headers: HeaderMap,
) -> ApiResult {
    let conn = connection_named(&c, &name)?;
    let reason = headers
        .get("x-reason")
        .and_then(|v| v.to_str().ok())
        .unwrap_or(CLOSE_REASON);
    if !c.admin.close_connection(conn.id, reason) {
        return Err(ApiError::not_found(format!("no connection '{name}'")));
    }
    Ok(no_content())
}
