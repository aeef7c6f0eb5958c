//! `/api/definitions[/{vhost}]`: exporting the broker's definitions and
//! importing a document (all of it, or into one vhost), answering what
//! was applied and what was not. Reading and applying a document is
//! `crate::definitions`' job; this file is its HTTP face. Uses `common`.

use super::api::{ApiError, Context};
use super::common::{require_vhost, ApiResult, Ctx};
use crate::definitions::Definitions;
use axum::body::Bytes;
use axum::extract::{Path, State};
use axum::Json;
use serde_json::{json, Value};

pub async fn definitions(State(c): Ctx) -> Json<Value> {
    Json(crate::definitions::export(&c.admin, &c.links))
}

/// Imports a definitions document; answers what was applied and what was
/// not (RabbitMQ answers 204 with no body).
pub async fn import_definitions(State(c): Ctx, body: Bytes) -> ApiResult<Json<Value>> {
    import(&c, &body, None).await
}

pub async fn vhost_definitions(State(c): Ctx, Path(vhost): Path<String>) -> ApiResult<Json<Value>> {
    require_vhost(&c, &vhost)?;
    Ok(Json(crate::definitions::export_vhost(
        &c.admin, &c.links, &vhost,
    )))
}

/// Imports one vhost's definitions: objects without a `vhost` go to it.
pub async fn import_vhost_definitions(
    State(c): Ctx,
    Path(vhost): Path<String>,
    body: Bytes,
) -> ApiResult<Json<Value>> {
    require_vhost(&c, &vhost)?;
    import(&c, &body, Some(&vhost)).await
}

async fn import(c: &Context, body: &Bytes, vhost: Option<&str>) -> ApiResult<Json<Value>> {
    // Reading checks every policy's pattern: work that grows with the
    // file, off the broker's threads.
    let (body, vhost_owned) = (body.clone(), vhost.map(str::to_owned));
    let mut definitions =
        tokio::task::spawn_blocking(move || Definitions::parse_into(&body, vhost_owned.as_deref()))
            .await
            .map_err(|e| ApiError::bad_request(e.to_string()))?
            .map_err(ApiError::bad_request)?;
    let applied = definitions
        .apply(&c.admin, &c.links)
        .await
        .map_err(ApiError::bad_request)?;
    for warning in &definitions.warnings {
        tracing::warn!(%warning, "definitions import");
    }
    Ok(Json(json!({
        "applied": {
            "vhosts": applied.vhosts,
            "users": applied.users,
            "exchanges": applied.exchanges,
            "queues": applied.queues,
            "bindings": applied.bindings,
            "shovels": applied.shovels,
            "federation_upstreams": applied.upstreams,
            "policies": applied.policies,
        },
        "warnings": definitions.warnings,
    })))
}
