//! Every listing of bindings and the bindings themselves:
//! `/api/bindings[/{vhost}]`, between an exchange and a queue or exchange
//! (`/api/bindings/{vhost}/e/{source}/{q|e}/{destination}[/{props}]`:
//! reading, binding and unbinding as the caller), and those of one
//! exchange (`/api/exchanges/{vhost}/{name}/bindings/{source|destination}`)
//! or one queue (`/api/queues/{vhost}/{name}/bindings`), as RabbitMQ's
//! bindings resource serves them all. Uses `common`, `json`, `caller`,
//! the exchange and queue lookups of `exchanges` and `queues`, and the
//! broker through `Admin`.

use super::api::{ApiError, Context};
use super::caller::Caller;
use super::common::{body_object, exchange_name, no_content, require_vhost, ApiResult, Ctx};
use super::exchanges::require_exchange;
use super::json;
use super::queues::queue_ref;
use axum::body::Bytes;
use axum::extract::{Path, State};
use axum::http::{header, StatusCode};
use axum::response::IntoResponse;
use axum::{Extension, Json};
use leveret_broker::{BindingSpec, DestinationKind};
use leveret_protocol::json::to_table;
use serde_json::Value;

fn binding_list(c: &Context, keep: impl Fn(&leveret_broker::BindingInfo) -> bool) -> Json<Value> {
    Json(Value::Array(
        c.admin
            .bindings()
            .iter()
            .filter(|b| keep(b))
            .map(json::binding)
            .collect(),
    ))
}

pub async fn bindings(State(c): Ctx, Extension(caller): Extension<Caller>) -> Json<Value> {
    binding_list(&c, |b| caller.sees_vhost(&b.vhost))
}

pub async fn bindings_in(State(c): Ctx, Path(vhost): Path<String>) -> ApiResult<Json<Value>> {
    require_vhost(&c, &vhost)?;
    Ok(binding_list(&c, |b| b.vhost == vhost))
}

fn destination_kind(kind: &str) -> ApiResult<DestinationKind> {
    match kind {
        "q" => Ok(DestinationKind::Queue),
        "e" => Ok(DestinationKind::Exchange),
        other => Err(ApiError::not_found(format!(
            "destination kind must be q or e, not {other}"
        ))),
    }
}

pub async fn bindings_between(
    State(c): Ctx,
    Path((vhost, source, kind, destination)): Path<(String, String, String, String)>,
) -> ApiResult<Json<Value>> {
    require_vhost(&c, &vhost)?;
    let kind = destination_kind(&kind)?;
    let source = exchange_name(&source).to_owned();
    Ok(binding_list(&c, |b| {
        b.vhost == vhost
            && b.source == source
            && b.destination == destination
            && b.destination_kind == kind
    }))
}

pub async fn post_binding(
    State(c): Ctx,
    Extension(caller): Extension<Caller>,
    Path((vhost, source, kind, destination)): Path<(String, String, String, String)>,
    body: Bytes,
) -> ApiResult {
    let kind = destination_kind(&kind)?;
    let body = body_object(&body)?;
    let spec = BindingSpec {
        source,
        destination,
        destination_kind: kind,
        routing_key: json::text(&body, "routing_key", "")
            .map_err(ApiError::bad_request)?
            .to_owned(),
        arguments: to_table(body.get("arguments").unwrap_or(&Value::Null))
            .map_err(ApiError::bad_request)?,
    };
    let info = leveret_broker::BindingInfo {
        vhost: vhost.clone(),
        source: spec.source.clone(),
        destination: spec.destination.clone(),
        destination_kind: kind,
        routing_key: spec.routing_key.clone(),
        arguments: spec.arguments.clone(),
    };
    c.admin.as_user(&caller.user).bind(&vhost, spec).await?;
    Ok((
        StatusCode::CREATED,
        [(header::LOCATION, info.properties_key())],
    )
        .into_response())
}

pub async fn binding(
    State(c): Ctx,
    Path((vhost, source, kind, destination, props)): Path<(String, String, String, String, String)>,
) -> ApiResult<Json<Value>> {
    require_vhost(&c, &vhost)?;
    let kind = destination_kind(&kind)?;
    let source = exchange_name(&source).to_owned();
    c.admin
        .bindings()
        .iter()
        .find(|b| {
            b.vhost == vhost
                && b.source == source
                && b.destination == destination
                && b.destination_kind == kind
                && b.properties_key() == props
        })
        .map(|b| Json(json::binding(b)))
        .ok_or_else(|| ApiError::not_found(format!("no binding '{props}'")))
}

pub async fn delete_binding(
    State(c): Ctx,
    Extension(caller): Extension<Caller>,
    Path((vhost, source, kind, destination, props)): Path<(String, String, String, String, String)>,
) -> ApiResult {
    let kind = destination_kind(&kind)?;
    c.admin
        .as_user(&caller.user)
        .unbind(&vhost, &source, &destination, kind, &props)
        .await?;
    Ok(no_content())
}
pub async fn queue_bindings(
    State(c): Ctx,
    Path((vhost, name)): Path<(String, String)>,
) -> ApiResult<Json<Value>> {
    queue_ref(&c, &vhost, &name)?;
    Ok(binding_list(&c, |b| {
        b.vhost == vhost && b.destination == name && b.destination_kind == DestinationKind::Queue
    }))
}
pub async fn exchange_bindings_source(
    State(c): Ctx,
    Path((vhost, name)): Path<(String, String)>,
) -> ApiResult<Json<Value>> {
    let name = require_exchange(&c, &vhost, &name)?;
    Ok(binding_list(&c, |b| b.vhost == vhost && b.source == name))
}

pub async fn exchange_bindings_destination(
    State(c): Ctx,
    Path((vhost, name)): Path<(String, String)>,
) -> ApiResult<Json<Value>> {
    let name = require_exchange(&c, &vhost, &name)?;
    Ok(binding_list(&c, |b| {
        b.vhost == vhost && b.destination == name && b.destination_kind == DestinationKind::Exchange
    }))
}
