//! What the handlers of every resource share, so each is written once:
//! the handler types (`Ctx`, `ApiResult`, `Params`), looking up a vhost,
//! reading a JSON body or a `?flag=true`, `amq.default` for the default
//! exchange, the empty answers (201/204, the fallback 404) and a listing,
//! paginated when asked (`pagination`). Uses only `api`'s context and
//! errors, `json` and `pagination`; the resources' files use it, it uses
//! none of them.

use super::api::{ApiError, Context};
use super::json;
use super::pagination::Pagination;
use axum::body::Bytes;
use axum::extract::{Query, State};
use axum::http::StatusCode;
use axum::response::{IntoResponse, Response};
use axum::Json;
use serde_json::Value;
use std::collections::HashMap;
use std::sync::Arc;

/// The shared context, as a handler takes it.
pub(super) type Ctx = State<Arc<Context>>;
/// A handler's answer, or the error RabbitMQ would give.
pub(super) type ApiResult<T = Response> = Result<T, ApiError>;

/// The query string's parameters.
pub(super) type Params = Query<HashMap<String, String>>;

/// `amq.default` in a path means the default exchange, as in RabbitMQ.
pub(super) fn exchange_name(name: &str) -> &str {
    if name == "amq.default" {
        ""
    } else {
        name
    }
}

/// 404 unless `vhost` exists.
pub(super) fn require_vhost(context: &Context, vhost: &str) -> ApiResult<()> {
    if context.admin.vhosts().iter().any(|v| v == vhost) {
        Ok(())
    } else {
        Err(ApiError::not_found(format!("no vhost '{vhost}'")))
    }
}

/// 204, RabbitMQ's answer to a change.
pub(super) fn no_content() -> Response {
    StatusCode::NO_CONTENT.into_response()
}

/// 201 for an object created, 204 for one changed.
pub(super) fn created_or_not(created: bool) -> Response {
    if created {
        StatusCode::CREATED.into_response()
    } else {
        no_content()
    }
}

/// The request body as a JSON object, or 400.
pub(super) fn body_object(body: &Bytes) -> ApiResult<serde_json::Map<String, Value>> {
    json::object(body).map_err(ApiError::bad_request)
}

/// A listing of `objects`: one page of them when the query asks for one
/// (RabbitMQ's pagination), else all of them.
pub(super) async fn listing(
    objects: Vec<Value>,
    query: &HashMap<String, String>,
) -> ApiResult<Json<Value>> {
    match Pagination::from_query(query)? {
        Some(pagination) => Ok(Json(
            pagination
                .page_of(objects, |o| o["name"].as_str().unwrap_or(""), Value::clone)
                .await?,
        )),
        None => Ok(Json(Value::Array(objects))),
    }
}

/// Whether `?key=true` was asked.
pub(super) fn query_flag(query: &HashMap<String, String>, key: &str) -> bool {
    query.get(key).is_some_and(|v| v == "true")
}

/// The answer to a path no route has.
pub async fn unknown() -> ApiError {
    ApiError::not_found("Not Found")
}
