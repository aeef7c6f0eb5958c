//! One function per route of the management API. Listings of queues,
//! exchanges, vhosts, connections and channels are paginated when asked
//! (`pagination`). Unpaginated listings of queues are streamed: the body is a JSON array written [`CHUNK`] queues at a time as
//! the client reads it, each queue read under its own lock when its turn
//! comes, so a listing of 100k queues neither builds the whole answer in
//! memory nor holds the listeners' thread between chunks.

use super::caller::Caller;
use super::json;
use super::pagination::Pagination;
use super::{ApiError, Context};
use crate::definitions::Definitions;
use crate::process::ProcessFigures;
use axum::body::{Body, Bytes};
use axum::extract::{Path, Query, State};
use axum::http::{header, HeaderMap, StatusCode};
use axum::response::{IntoResponse, Response};
use axum::{Extension, Json};
use base64::Engine;
use leveret_broker::{
    BindingSpec, DestinationKind, ExchangeSettings, GetMode, PasswordHash, Permission, QueueRef,
    QueueSettings, TopicPermission, User, RABBIT_SHA256,
};
use leveret_protocol::json::{properties, properties_json, to_table};
use serde_json::{json, Value};
use std::collections::HashMap;
use std::sync::Arc;

pub(super) type Ctx = State<Arc<Context>>;
pub(super) type ApiResult<T = Response> = Result<T, ApiError>;

/// Queues written per chunk of a streamed listing.
const CHUNK: usize = 500;
/// The most messages one `get` may fetch.
const MAX_GET: u64 = 1000;
/// The close reason when the client gives none (RabbitMQ's).
const CLOSE_REASON: &str = "Closed via management plugin";

/// `amq.default` in a path means the default exchange, as in RabbitMQ.
fn exchange_name(name: &str) -> &str {
    if name == "amq.default" {
        ""
    } else {
        name
    }
}

pub(super) fn require_vhost(context: &Context, vhost: &str) -> ApiResult<()> {
    if context.admin.vhosts().iter().any(|v| v == vhost) {
        Ok(())
    } else {
        Err(ApiError::not_found(format!("no vhost '{vhost}'")))
    }
}

pub(super) fn no_content() -> Response {
    StatusCode::NO_CONTENT.into_response()
}

pub(super) fn created_or_not(created: bool) -> Response {
    if created {
        StatusCode::CREATED.into_response()
    } else {
        no_content()
    }
}

pub(super) fn body_object(body: &Bytes) -> ApiResult<serde_json::Map<String, Value>> {
    json::object(body).map_err(ApiError::bad_request)
}

type Params = Query<HashMap<String, String>>;

/// A listing of `objects`: one page of them when the query asks for one
/// (RabbitMQ's pagination), else all of them.
async fn listing(objects: Vec<Value>, query: &HashMap<String, String>) -> ApiResult<Json<Value>> {
    match Pagination::from_query(query)? {
        Some(pagination) => Ok(Json(
            pagination
                .page_of(objects, |o| o["name"].as_str().unwrap_or(""), Value::clone)
                .await?,
        )),
        None => Ok(Json(Value::Array(objects))),
    }
}

fn query_flag(query: &HashMap<String, String>, key: &str) -> bool {
    query.get(key).is_some_and(|v| v == "true")
}

pub async fn unknown() -> ApiError {
    ApiError::not_found("Not Found")
}

/// A window of samples asked for with RabbitMQ's `{prefix}_age` and
/// `{prefix}_incr` (seconds): `None` when neither is given.
fn sample_window(query: &HashMap<String, String>, prefix: &str) -> ApiResult<Option<(u64, u64)>> {
    let number = |key: String| -> ApiResult<Option<u64>> {
        query
            .get(&key)
            .map(|v| {
                v.parse::<u64>().map_err(|_| {
                    ApiError::bad_request(format!("{key} must be a whole number of seconds"))
                })
            })
            .transpose()
    };
    match (
        number(format!("{prefix}_age"))?,
        number(format!("{prefix}_incr"))?,
    ) {
        (None, None) => Ok(None),
        (Some(age), Some(incr)) if incr > 0 => Ok(Some((age, incr))),
        _ => Err(ApiError::bad_request(format!(
            "{prefix}_age needs {prefix}_incr (at least 1) beside it"
        ))),
    }
}

/// RabbitMQ's overview. With `msg_rates_age`/`msg_rates_incr` the message
/// rates' `*_details`, with `lengths_age`/`lengths_incr` the queue totals',
/// carry RabbitMQ's `samples`, `avg_rate` and `avg` (the last ten minutes
/// are kept, every 5 s: `rates::HISTORY`).
pub async fn overview(State(c): Ctx, Query(query): Params) -> ApiResult<Json<Value>> {
    use super::rates::OverviewFigure as F;
    let msg_rates = sample_window(&query, "msg_rates")?;
    let lengths = sample_window(&query, "lengths")?;
    let o = c.admin.overview();
    let r = c.rates.overview();
    let m = &o.message_stats;
    let q = &o.queue_totals;
    let t = &o.object_totals;
    let listeners: Vec<Value> = c
        .listeners
        .iter()
        .map(|(protocol, addr)| {
            json!({"node": c.node, "protocol": protocol, "ip_address": addr.ip().to_string(), "port": addr.port()})
        })
        .collect();
    let details = |rate: f64, figure: F, window: Option<(u64, u64)>| {
        let mut details = json!({ "rate": rate });
        if let Some((age, incr)) = window {
            let history = c.rates.history(figure, age, incr);
            let samples: Vec<Value> = history
                .samples
                .iter()
                .map(|(at, value)| json!({"sample": *value as u64, "timestamp": at}))
                .collect();
            details["samples"] = Value::Array(samples);
            details["avg_rate"] = json!(history.avg_rate);
            details["avg"] = json!(history.avg);
        }
        details
    };
    let d = |rate: f64, figure: F| details(rate, figure, msg_rates);
    let l = |rate: f64, figure: F| details(rate, figure, lengths);
    let exchange_types: Vec<Value> = ["direct", "fanout", "topic", "headers"]
        .iter()
        .map(|name| json!({"name": name, "enabled": true}))
        .collect();
    Ok(Json(json!({
        "management_version": o.version,
        "rates_mode": "basic",
        "exchange_types": exchange_types,
        "product_name": o.product,
        "product_version": o.version,
        "rabbitmq_version": o.version,
        "cluster_name": crate::policies::cluster_name(&c.admin, &c.node),
        "node": c.node,
        "disable_stats": false,
        "enable_queue_totals": true,
        "message_stats": {
            "publish": m.received, "publish_details": d(r.publish, F::Publish),
            "confirm": m.confirmed, "confirm_details": d(r.confirm, F::Confirm),
            "return_unroutable": m.unroutable_returned, "return_unroutable_details": d(r.return_unroutable, F::ReturnUnroutable),
            "drop_unroutable": m.unroutable_dropped, "drop_unroutable_details": d(r.drop_unroutable, F::DropUnroutable),
            "deliver": m.delivered_consume_manual_ack, "deliver_details": d(r.deliver, F::Deliver),
            "deliver_no_ack": m.delivered_consume_auto_ack, "deliver_no_ack_details": d(r.deliver_no_ack, F::DeliverNoAck),
            "get": m.delivered_get_manual_ack, "get_details": d(r.get, F::Get),
            "get_no_ack": m.delivered_get_auto_ack, "get_no_ack_details": d(r.get_no_ack, F::GetNoAck),
            "get_empty": m.get_empty, "get_empty_details": d(r.get_empty, F::GetEmpty),
            "deliver_get": m.delivered(), "deliver_get_details": d(r.deliver_get, F::DeliverGet),
            "redeliver": m.redelivered, "redeliver_details": d(r.redeliver, F::Redeliver),
            "ack": m.acknowledged, "ack_details": d(r.ack, F::Ack),
        },
        "churn_rates": {
            "connection_created": o.churn.connections_opened,
            "connection_closed": o.churn.connections_closed,
            "channel_created": o.churn.channels_opened,
            "channel_closed": o.churn.channels_closed,
            "queue_declared": o.churn.queues_declared,
            "queue_created": o.churn.queues_created,
            "queue_deleted": o.churn.queues_deleted,
        },
        "queue_totals": {
            "messages": q.messages(), "messages_details": l(r.messages, F::Messages),
            "messages_ready": q.messages_ready, "messages_ready_details": l(r.messages_ready, F::MessagesReady),
            "messages_unacknowledged": q.messages_unacknowledged, "messages_unacknowledged_details": l(r.messages_unacknowledged, F::MessagesUnacknowledged),
        },
        "object_totals": {
            "connections": t.connections, "channels": t.channels, "exchanges": t.exchanges,
            "queues": t.queues, "consumers": t.consumers,
        },
        "listeners": listeners,
    })))
}

fn node_json(c: &Context) -> Value {
    let o = c.admin.overview();
    let p = ProcessFigures::read(&c.data_dir);
    json!({
        "name": c.node,
        "type": "disc",
        "running": true,
        "os_pid": std::process::id().to_string(),
        "mem_used": p.resident_memory_bytes,
        "mem_limit": o.resident_memory_limit,
        "queued_bytes_limit": o.memory_high_watermark,
        "mem_alarm": o.memory_alarm,
        "disk_free": p.disk_free_bytes,
        "disk_free_limit": o.disk_free_limit,
        "disk_free_alarm": o.disk_alarm,
        "fd_used": p.open_fds,
        "fd_total": p.max_fds,
        "uptime": o.uptime.as_millis() as u64,
        "rates_mode": "basic",
    })
}

pub async fn nodes(State(c): Ctx) -> Json<Value> {
    Json(json!([node_json(&c)]))
}

pub async fn node(State(c): Ctx, Path(node): Path<String>) -> ApiResult<Json<Value>> {
    if node != c.node {
        return Err(ApiError::not_found(format!("no node '{node}'")));
    }
    Ok(Json(node_json(&c)))
}

fn vhost_json(c: &Context, name: &str) -> Value {
    let (mut ready, mut unacked) = (0, 0);
    for q in c.admin.queue_refs().iter().filter(|q| q.vhost() == name) {
        let info = q.info();
        ready += info.messages_ready;
        unacked += info.messages_unacknowledged;
    }
    json!({
        "name": name,
        "description": "",
        "tags": [],
        "metadata": {"description": "", "tags": []},
        "default_queue_type": "classic",
        "tracing": false,
        "messages": ready + unacked,
        "messages_ready": ready,
        "messages_unacknowledged": unacked,
        "cluster_state": { c.node.as_str(): "running" },
    })
}

pub async fn vhosts(
    State(c): Ctx,
    Extension(caller): Extension<Caller>,
    Query(query): Params,
) -> ApiResult<Json<Value>> {
    let names = c.admin.vhosts();
    let objects = names
        .iter()
        .filter(|n| caller.sees_vhost(n))
        .map(|n| vhost_json(&c, n))
        .collect();
    listing(objects, &query).await
}

pub async fn vhost(State(c): Ctx, Path(vhost): Path<String>) -> ApiResult<Json<Value>> {
    require_vhost(&c, &vhost)?;
    Ok(Json(vhost_json(&c, &vhost)))
}

pub async fn users(State(c): Ctx) -> Json<Value> {
    let users = c.admin.users();
    Json(Value::Array(
        users
            .iter()
            .map(|(name, user)| user_json(name, user))
            .collect(),
    ))
}

/// A user as RabbitMQ's `/api/users` shows one.
fn user_json(name: &str, user: &User) -> Value {
    let (password_hash, hashing_algorithm) = user.password_hash.to_rabbitmq();
    json!({
        "name": name,
        "password_hash": password_hash,
        "hashing_algorithm": hashing_algorithm,
        "tags": user.tags,
        "limits": {},
    })
}

pub async fn user(State(c): Ctx, Path(name): Path<String>) -> ApiResult<Json<Value>> {
    let user = c
        .admin
        .user(&name)
        .ok_or_else(|| ApiError::not_found(format!("no user '{name}'")))?;
    Ok(Json(user_json(&name, &user)))
}

/// RabbitMQ's `PUT /api/users/{name}`: `password` (hashed here) or
/// `password_hash` with `hashing_algorithm`, and `tags` (a list or a
/// comma-separated string). A new user needs a password; an existing one
/// without either keeps theirs. 201 for a new user, 204 for a change.
pub async fn put_user(State(c): Ctx, Path(name): Path<String>, body: Bytes) -> ApiResult {
    let body = body_object(&body)?;
    let field = |key: &str| json::text(&body, key, "").map_err(ApiError::bad_request);
    let existing = c.admin.user(&name);
    let password = field("password")?;
    let password_hash = field("password_hash")?;
    let hash = if !password.is_empty() {
        // argon2id takes tens of milliseconds: off the listeners' thread.
        let password = password.to_owned();
        tokio::task::spawn_blocking(move || PasswordHash::new(&password))
            .await
            .map_err(|_| ApiError::bad_request("the password could not be hashed"))?
    } else if body.contains_key("password_hash") {
        let algorithm =
            json::text(&body, "hashing_algorithm", RABBIT_SHA256).map_err(ApiError::bad_request)?;
        PasswordHash::from_rabbitmq(password_hash, algorithm).ok_or_else(|| {
            ApiError::bad_request(format!(
                "password_hash is not a {algorithm} hash Leveret can check"
            ))
        })?
    } else {
        existing
            .as_ref()
            .map(|user| user.password_hash.clone())
            .ok_or_else(|| {
                ApiError::bad_request("a new user needs a password or a password_hash")
            })?
    };
    let tags = json::user_tags(body.get("tags"));
    let created = c
        .admin
        .put_user(
            &name,
            User {
                password_hash: hash,
                tags,
            },
        )
        .await?;
    Ok(created_or_not(created))
}

/// RabbitMQ's `DELETE /api/users/{name}`: the user and their permissions.
pub async fn delete_user(State(c): Ctx, Path(name): Path<String>) -> ApiResult {
    if c.admin.delete_user(&name).await? {
        Ok(no_content())
    } else {
        Err(ApiError::not_found(format!("no user '{name}'")))
    }
}

pub async fn whoami(State(c): Ctx, Extension(caller): Extension<Caller>) -> Json<Value> {
    let tags = c.admin.user(&caller.user).map(|user| user.tags);
    Json(json!({ "name": caller.user, "tags": tags.unwrap_or_default() }))
}

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

fn queue_ref(c: &Context, vhost: &str, name: &str) -> ApiResult<QueueRef> {
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

pub async fn channels(
    State(c): Ctx,
    Extension(caller): Extension<Caller>,
    Query(query): Params,
) -> ApiResult<Json<Value>> {
    let objects = c
        .admin
        .channels()
        .iter()
        .filter(|ch| caller.sees_user(&ch.user))
        .map(|ch| json::channel(ch, &c.node))
        .collect();
    listing(objects, &query).await
}

fn consumer_list(c: &Context, caller: &Caller, vhost: Option<&str>) -> Json<Value> {
    let peers: HashMap<u64, String> = c
        .admin
        .connections()
        .into_iter()
        .map(|conn| (conn.id, conn.peer))
        .collect();
    Json(Value::Array(
        c.admin
            .consumers()
            .iter()
            .filter(|consumer| vhost.is_none_or(|v| consumer.vhost == v))
            .filter(|consumer| caller.sees_vhost(&consumer.vhost))
            .map(|consumer| {
                let peer = peers
                    .get(&consumer.connection_id)
                    .map_or("", String::as_str);
                json::consumer(consumer, peer, &c.node)
            })
            .collect(),
    ))
}

pub async fn consumers(State(c): Ctx, Extension(caller): Extension<Caller>) -> Json<Value> {
    consumer_list(&c, &caller, None)
}

pub async fn consumers_in(
    State(c): Ctx,
    Extension(caller): Extension<Caller>,
    Path(vhost): Path<String>,
) -> ApiResult<Json<Value>> {
    require_vhost(&c, &vhost)?;
    Ok(consumer_list(&c, &caller, Some(&vhost)))
}

pub async fn aliveness_test(
    State(c): Ctx,
    Extension(caller): Extension<Caller>,
    Path(vhost): Path<String>,
) -> ApiResult<Json<Value>> {
    require_vhost(&c, &vhost)?;
    c.admin
        .as_user(&caller.user)
        .aliveness_test(&vhost)
        .await
        .map_err(ApiError::refused_with_text)?;
    Ok(Json(json!({ "status": "ok" })))
}

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

/// Creates a vhost (201), or leaves an existing one be (204); it lasts
/// across restarts. As in RabbitMQ (since 3.7), the user who creates it
/// is granted everything on it.
pub async fn put_vhost(
    State(c): Ctx,
    Extension(caller): Extension<Caller>,
    Path(vhost): Path<String>,
) -> ApiResult {
    let created = c.admin.add_vhost(&vhost).await?;
    if created {
        c.admin
            .set_permission(&caller.user, &vhost, Permission::full())
            .await?;
    }
    Ok(created_or_not(created))
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

fn require_exchange(c: &Context, vhost: &str, name: &str) -> ApiResult<String> {
    require_vhost(c, vhost)?;
    let name = exchange_name(name);
    c.admin
        .exchange(vhost, name)
        .map(|e| e.name)
        .ok_or_else(|| ApiError::not_found(format!("no exchange '{name}' in vhost '{vhost}'")))
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

/// The effective configuration (Leveret's; RabbitMQ shows its
/// application environment with `rabbitmqctl environment` only).
pub async fn environment(State(c): Ctx) -> Json<Value> {
    Json(c.environment.clone())
}

/// The status page: alarms, memory/disk/file-descriptor headroom, charts
/// of the overview's 10-minute history, listeners, queues, connections,
/// each linking to its JSON; it refreshes itself from the API.
pub async fn status_page() -> axum::response::Html<&'static str> {
    axum::response::Html(include_str!("status.html"))
}

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
