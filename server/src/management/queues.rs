//! `/api/queues[/{vhost}[/{name}]]`, `.../contents` and `.../get`:
//! listing queues, reading, declaring, deleting and purging one as the
//! caller (whose permissions the broker checks, `Admin::as_user`), and
//! getting messages from one. A page of queues (RabbitMQ's pagination) is
//! written out for the page's queues only; an unpaginated listing is
//! streamed: the body is a JSON array written [`CHUNK`] queues at a time
//! as the client reads it, each queue read under its own lock when its
//! turn comes, so a listing of 100k queues neither builds the whole
//! answer in memory nor holds the listeners' thread between chunks. Their
//! bindings' listing is `bindings`'. Uses `common`, `json`,
//! `pagination`, `rates`, `caller` and the broker through `Admin`.

use super::api::{ApiError, Context};
use super::caller::Caller;
use super::common::{
    body_object, created_or_not, no_content, query_flag, require_vhost, ApiResult, Ctx, Params,
};
use super::json;
use super::pagination::Pagination;
use axum::body::{Body, Bytes};
use axum::extract::{Path, Query, State};
use axum::http::header;
use axum::response::{IntoResponse, Response};
use axum::{Extension, Json};
use leveret_broker::{GetMode, QueueRef, QueueSettings};
use leveret_protocol::json::{properties_json, to_table};
use serde_json::{json, Value};
use std::collections::HashMap;
use std::sync::Arc;

/// Queues written per chunk of a streamed listing.
const CHUNK: usize = 500;

/// The most messages one `get` may fetch.
const MAX_GET: u64 = 1000;

/// A JSON array of queues, written a chunk at a time as the client reads.
fn queue_stream(c: Arc<Context>, queues: Vec<QueueRef>) -> Response {
    let state = (c, queues, 0usize);
    let stream = futures_util::stream::unfold(state, |(c, queues, at)| async move {
        if at > queues.len() {
            return None;
        }
        let mut chunk = Vec::new();
        if at == 0 {
            chunk.push(b'[');
        }
        let end = (at + CHUNK).min(queues.len());
        for (i, queue) in queues[at..end].iter().enumerate() {
            if at + i > 0 {
                chunk.push(b',');
            }
            let info = queue.info();
            let rates = c.rates.queue(&info.vhost, &info.name);
            let object = json::queue(&info, &c.node, &rates);
            if serde_json::to_writer(&mut chunk, &object).is_err() {
                return None;
            }
        }
        if end == queues.len() {
            chunk.push(b']');
        }
        tokio::task::yield_now().await;
        let next = if end == queues.len() {
            queues.len() + 1
        } else {
            end
        };
        Some((
            Ok::<_, std::io::Error>(Bytes::from(chunk)),
            (c, queues, next),
        ))
    });
    (
        [(header::CONTENT_TYPE, "application/json")],
        Body::from_stream(stream),
    )
        .into_response()
}

/// A listing of queues: one page (RabbitMQ's pagination), written out
/// for the page's queues only, or all of them, streamed.
async fn queue_listing(
    c: Arc<Context>,
    refs: Vec<QueueRef>,
    query: &HashMap<String, String>,
) -> ApiResult {
    let Some(pagination) = Pagination::from_query(query)? else {
        return Ok(queue_stream(c, refs));
    };
    let page = pagination
        .page_of(refs, QueueRef::name, |queue| {
            let info = queue.info();
            json::queue(&info, &c.node, &c.rates.queue(&info.vhost, &info.name))
        })
        .await?;
    Ok(Json(page).into_response())
}

pub async fn queues(
    State(c): Ctx,
    Extension(caller): Extension<Caller>,
    Query(query): Params,
) -> ApiResult {
    let refs = c
        .admin
        .queue_refs()
        .into_iter()
        .filter(|q| caller.sees_vhost(q.vhost()))
        .collect();
    queue_listing(c, refs, &query).await
}

pub async fn queues_in(
    State(c): Ctx,
    Path(vhost): Path<String>,
    Query(query): Params,
) -> ApiResult {
    require_vhost(&c, &vhost)?;
    let refs: Vec<QueueRef> = c
        .admin
        .queue_refs()
        .into_iter()
        .filter(|q| q.vhost() == vhost)
        .collect();
    queue_listing(c, refs, &query).await
}

pub(super) fn queue_ref(c: &Context, vhost: &str, name: &str) -> ApiResult<QueueRef> {
    require_vhost(c, vhost)?;
    c.admin
        .queue(vhost, name)
        .ok_or_else(|| ApiError::not_found(format!("no queue '{name}' in vhost '{vhost}'")))
}

pub async fn queue(
    State(c): Ctx,
    Path((vhost, name)): Path<(String, String)>,
) -> ApiResult<Json<Value>> {
    let info = queue_ref(&c, &vhost, &name)?.info();
    let rates = c.rates.queue(&vhost, &name);
    Ok(Json(json::queue(&info, &c.node, &rates)))
}

pub async fn put_queue(
    State(c): Ctx,
    Extension(caller): Extension<Caller>,
    Path((vhost, name)): Path<(String, String)>,
    body: Bytes,
) -> ApiResult {
    let body = body_object(&body)?;
    let settings = QueueSettings {
        durable: json::flag(&body, "durable", true).map_err(ApiError::bad_request)?,
        auto_delete: json::flag(&body, "auto_delete", false).map_err(ApiError::bad_request)?,
        arguments: to_table(body.get("arguments").unwrap_or(&Value::Null))
            .map_err(ApiError::bad_request)?,
    };
    let created = c
        .admin
        .as_user(&caller.user)
        .declare_queue(&vhost, &name, settings)
        .await?;
    Ok(created_or_not(created))
}

pub async fn delete_queue(
    State(c): Ctx,
    Extension(caller): Extension<Caller>,
    Path((vhost, name)): Path<(String, String)>,
    Query(query): Query<HashMap<String, String>>,
) -> ApiResult {
    c.admin
        .as_user(&caller.user)
        .delete_queue(
            &vhost,
            &name,
            query_flag(&query, "if-unused"),
            query_flag(&query, "if-empty"),
        )
        .await?;
    Ok(no_content())
}

pub async fn purge(
    State(c): Ctx,
    Extension(caller): Extension<Caller>,
    Path((vhost, name)): Path<(String, String)>,
) -> ApiResult {
    c.admin.as_user(&caller.user).purge_queue(&vhost, &name)?;
    Ok(no_content())
}

pub async fn get_messages(
    State(c): Ctx,
    Extension(caller): Extension<Caller>,
    Path((vhost, name)): Path<(String, String)>,
    body: Bytes,
) -> ApiResult<Json<Value>> {
    let body = body_object(&body)?;
    let count = json::count(&body, "count", 1).map_err(ApiError::bad_request)?;
    if count == 0 || count > MAX_GET {
        return Err(ApiError::bad_request(format!(
            "count must be from 1 to {MAX_GET}"
        )));
    }
    let mode =
        match json::text(&body, "ackmode", "ack_requeue_true").map_err(ApiError::bad_request)? {
            "ack_requeue_true" | "reject_requeue_true" => GetMode::Requeue,
            "ack_requeue_false" => GetMode::Ack,
            "reject_requeue_false" => GetMode::RejectDrop,
            other => return Err(ApiError::bad_request(format!("unknown ackmode {other}"))),
        };
    let force_base64 = match json::text(&body, "encoding", "auto").map_err(ApiError::bad_request)? {
        "auto" => false,
        "base64" => true,
        other => return Err(ApiError::bad_request(format!("unknown encoding {other}"))),
    };
    let truncate = match body.get("truncate") {
        None | Some(Value::Null) => None,
        Some(_) => Some(json::count(&body, "truncate", 0).map_err(ApiError::bad_request)? as usize),
    };
    let got = c
        .admin
        .as_user(&caller.user)
        .get(&vhost, &name, count as usize, mode)
        .map_err(ApiError::refused_with_text)?;
    let list = got
        .iter()
        .map(|m| {
            let shown = truncate.map_or(&m.body[..], |n| &m.body[..n.min(m.body.len())]);
            let (payload, encoding) = json::payload(shown, force_base64);
            json!({
                "payload_bytes": m.body.len(),
                "redelivered": m.redelivered,
                "exchange": m.exchange,
                "routing_key": m.routing_key,
                "message_count": m.remaining,
                "properties": properties_json(&m.properties),
                "payload": payload,
                "payload_encoding": encoding,
            })
        })
        .collect();
    Ok(Json(Value::Array(list)))
}
