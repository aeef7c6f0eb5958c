//! The management HTTP API: a compatible subset of RabbitMQ's (`/api/...`,
//! JSON with RabbitMQ's field names), enough for `rabbitmqadmin` and
//! scripts written against RabbitMQ to list, declare, delete, publish,
//! get and purge, and to add users and grant permissions. Every request
//! needs HTTP basic auth with one of the broker's users, whose RabbitMQ
//! user tags decide what they may see and do (`caller`); bodies are capped
//! at [`MAX_BODY`].
//!
//! Definitions (`/api/definitions`) are `crate::definitions`' job. `/` is a
//! status page (`status.html`: plain HTML and a little JavaScript, no build
//! step) that reads the same API with the browser's basic-auth credentials.
//!
//! Layout, a file a resource as RabbitMQ's API has them: `overview`
//! (the overview, nodes, environment and the status page), `vhosts`,
//! `users` (and `whoami`), `permissions` (and topic permissions),
//! `exchanges` (and publishing), `queues` (and getting messages),
//! `bindings` (every listing of bindings), `connections`, `channels`,
//! `consumers`, `definitions`, `shovels`, `federation`, `parameters` (the
//! runtime-parameter listings), `policies` (and operator policies, the
//! cluster name, global parameters), `limits` (vhost and user limits),
//! `health` (the health checks and the aliveness test). Beside them:
//! `mod` (router, auth, errors, the shared context), `common` (what every
//! resource's handlers share), `caller` (who calls and what their tags
//! let them do), `pagination` (RabbitMQ's `page`, `page_size`, `name`,
//! `sort`), `json` (objects and body parsing), `rates` (the sampler
//! behind `*_details`), `audit` (the log line of each change with the
//! acting user). A resource's file uses those and the broker; only
//! `bindings` uses two others' lookups (an exchange's, a queue's), and no
//! resource is used by those it uses.
//! Handlers reach the broker only
//! through [`Admin`]; they run on the listeners' thread.

mod audit;
mod bindings;
mod caller;
mod channels;
mod common;
mod connections;
mod consumers;
mod definitions;
mod exchanges;
mod federation;
mod health;
pub mod json;
mod limits;
mod overview;
mod pagination;
mod parameters;
mod permissions;
mod policies;
mod queues;
mod rates;
mod shovels;
mod users;
mod vhosts;

use crate::http::Peer;
use crate::uplink::{DeclareError, Links};
use axum::extract::{DefaultBodyLimit, Request, State};
use axum::http::{header, HeaderMap, StatusCode};
use axum::middleware::Next;
use axum::response::{IntoResponse, Response};
use axum::routing::{delete, get, post, put};
use axum::{Json, Router};
use base64::Engine;
pub(crate) use caller::percent_decoded;
use caller::Caller;
use leveret_broker::{AccessError, Admin, AmqpError};
use leveret_protocol::ReplyCode;
pub use rates::Rates;
use std::net::SocketAddr;
use std::path::PathBuf;
use std::sync::Arc;

/// The largest request body read (a publish's payload, a definitions file).
pub const MAX_BODY: usize = 1024 * 1024;

/// What the handlers share.
#[derive(Debug, Clone)]
pub struct Context {
    /// The broker.
    pub admin: Admin,
    /// The shovels and federation.
    pub links: Links,
    /// `leveret@HOST`.
    pub node: String,
    /// Where durable state lives (disk figures).
    pub data_dir: PathBuf,
    /// Every listener of the process by RabbitMQ's protocol name (`amqp`,
    /// `amqp/ssl`, `mqtt`, `http`, `http/prometheus`), for the overview
    /// and the health checks.
    pub listeners: Vec<(&'static str, SocketAddr)>,
    /// The TLS listeners' certificate files, if there are TLS listeners.
    pub tls: Option<leveret_broker::TlsOptions>,
    /// Message rates.
    pub rates: Rates,
    /// The effective configuration (`crate::environment`).
    pub environment: serde_json::Value,
}

/// An API error as RabbitMQ words them: `{"error": ..., "reason": ...}`.
#[derive(Debug)]
pub struct ApiError {
    status: StatusCode,
    error: &'static str,
    reason: String,
}

impl ApiError {
    /// 400 with `reason`.
    pub fn bad_request(reason: impl Into<String>) -> Self {
        ApiError {
            status: StatusCode::BAD_REQUEST,
            error: "bad_request",
            reason: reason.into(),
        }
    }

    /// 404.
    pub fn not_found(reason: impl Into<String>) -> Self {
        ApiError {
            status: StatusCode::NOT_FOUND,
            error: "Object Not Found",
            reason: reason.into(),
        }
    }

    fn unauthorized() -> Self {
        ApiError {
            status: StatusCode::UNAUTHORIZED,
            error: "not_authorized",
            reason: "Login failed".into(),
        }
    }
}

impl ApiError {
    /// An operation the caller's permissions refuse, as RabbitMQ answers
    /// `get` and the aliveness test: 401 with the AMQP reply text; other
    /// errors as [`From<AmqpError>`].
    pub fn refused_with_text(e: AmqpError) -> Self {
        match e.code {
            ReplyCode::AccessRefused => caller::not_authorised(&e.text),
            _ => e.into(),
        }
    }

    /// A publish the broker did not take, as RabbitMQ answers one its
    /// channel refused: 400 with the reply code and text. During a
    /// resource alarm (or when the store cannot write), 503.
    pub fn publish_refused(e: AmqpError) -> Self {
        match e.code {
            ReplyCode::ResourceError => ApiError {
                status: StatusCode::SERVICE_UNAVAILABLE,
                error: "service_unavailable",
                reason: e.text,
            },
            _ => ApiError::bad_request(e.to_string()),
        }
    }
}

impl From<AmqpError> for ApiError {
    /// Refusals by permission are RabbitMQ's 401 `Access refused.` for
    /// declaring, deleting, binding and purging.
    fn from(e: AmqpError) -> Self {
        match e.code {
            ReplyCode::NotFound => ApiError::not_found(e.text),
            ReplyCode::AccessRefused => caller::not_authorised("Access refused."),
            _ => ApiError::bad_request(e.text),
        }
    }
}

impl From<AccessError> for ApiError {
    fn from(e: AccessError) -> Self {
        match e {
            AccessError::NoSuchUser(_) => ApiError::not_found(e.to_string()),
            AccessError::Storage => ApiError {
                status: StatusCode::INTERNAL_SERVER_ERROR,
                error: "internal_server_error",
                reason: e.to_string(),
            },
            AccessError::Pattern(_) | AccessError::BadName(_) | AccessError::BadValue(_) => {
                ApiError::bad_request(e.to_string())
            }
        }
    }
}

impl From<DeclareError> for ApiError {
    fn from(e: DeclareError) -> Self {
        match e {
            DeclareError::Invalid(reason) => ApiError::bad_request(reason),
            DeclareError::Storage(e) => e.into(),
        }
    }
}

impl IntoResponse for ApiError {
    fn into_response(self) -> Response {
        let body = Json(serde_json::json!({ "error": self.error, "reason": self.reason }));
        let mut response = (self.status, body).into_response();
        if self.status == StatusCode::UNAUTHORIZED {
            response.headers_mut().insert(
                header::WWW_AUTHENTICATE,
                header::HeaderValue::from_static("Basic realm=\"RabbitMQ Management\""),
            );
        }
        response
    }
}

/// The user and password of a basic `Authorization` header.
pub(super) fn basic_credentials(headers: &HeaderMap) -> Option<(String, String)> {
    let value = headers.get(header::AUTHORIZATION)?.to_str().ok()?;
    let encoded = value.strip_prefix("Basic ")?.trim();
    let decoded = base64::engine::general_purpose::STANDARD
        .decode(encoded)
        .ok()?;
    let text = String::from_utf8(decoded).ok()?;
    let (user, password) = text.split_once(':')?;
    Some((user.to_owned(), password.to_owned()))
}

async fn authenticate(
    State(context): State<Arc<Context>>,
    request: Request,
    next: Next,
) -> Response {
    let mut request = request;
    let credentials = basic_credentials(request.headers());
    let peer = request.extensions().get::<Peer>().map(|peer| peer.0);
    // Checks are queued and failures slowed per source address (as AMQP
    // logins are), so one address's flood never delays another's login.
    let source = peer.map_or_else(|| "management API".to_owned(), |peer| peer.to_string());
    let passed = match &credentials {
        Some((user, password)) => context.admin.authenticate(user, password, &source).await,
        None => false,
    };
    if let (true, Some((user, _))) = (passed, &credentials) {
        if !peer.is_none_or(|peer| context.admin.may_connect_from(user, peer)) {
            tracing::info!(%user, ?peer, "management API login refused: loopback_users");
            return caller::not_authorised("User can only log in via localhost").into_response();
        }
        let caller = match Caller::new(user, &context.admin) {
            Ok(caller) => caller,
            Err(refused) => {
                tracing::info!(%user, "management API refused: no management tag");
                return refused.into_response();
            }
        };
        if let Some(segments) = caller::api_segments(request.uri().path()) {
            if let Err(refused) = caller.authorize(request.method(), &segments) {
                tracing::info!(%user, path = %request.uri().path(), "management API refused by the user's tags");
                return refused.into_response();
            }
        }
        request.extensions_mut().insert(caller);
        return next.run(request).await;
    }
    // RabbitMQ's management plugin's line, with the peer the check was
    // queued and slowed under.
    match credentials {
        Some((user, _)) => tracing::warn!(
            peer = %source,
            "HTTP access denied: user '{}' - invalid credentials",
            user.escape_debug()
        ),
        None => tracing::warn!(peer = %source, "HTTP access denied: no credentials"),
    }
    ApiError::unauthorized().into_response()
}

/// The router of the management listener.
pub fn router(context: Context) -> Router {
    let context = Arc::new(context);
    let api = Router::new()
        .route("/", get(overview::status_page))
        .route("/api/overview", get(overview::overview))
        .route("/api/nodes", get(overview::nodes))
        .route("/api/nodes/{node}", get(overview::node))
        .route("/api/vhosts", get(vhosts::vhosts))
        .route(
            "/api/vhosts/{vhost}",
            get(vhosts::vhost)
                .put(vhosts::put_vhost)
                .delete(vhosts::delete_vhost),
        )
        .route("/api/vhost-limits", get(limits::vhost_limits))
        .route("/api/vhost-limits/{vhost}", get(limits::vhost_limits_of))
        .route(
            "/api/vhost-limits/{vhost}/{name}",
            put(limits::put_vhost_limit).delete(limits::delete_vhost_limit),
        )
        .route("/api/user-limits", get(limits::user_limits))
        .route("/api/user-limits/{user}", get(limits::user_limits_of))
        .route(
            "/api/user-limits/{user}/{name}",
            put(limits::put_user_limit).delete(limits::delete_user_limit),
        )
        .route("/api/users", get(users::users))
        .route(
            "/api/users/{name}",
            get(users::user)
                .put(users::put_user)
                .delete(users::delete_user),
        )
        .route("/api/whoami", get(users::whoami))
        .route("/api/environment", get(overview::environment))
        .route("/api/permissions", get(permissions::permissions))
        .route(
            "/api/permissions/{vhost}/{user}",
            get(permissions::permission)
                .put(permissions::put_permission)
                .delete(permissions::delete_permission),
        )
        .route(
            "/api/topic-permissions",
            get(permissions::topic_permissions),
        )
        .route(
            "/api/topic-permissions/{vhost}/{user}",
            put(permissions::put_topic_permission).delete(permissions::delete_topic_permission),
        )
        .route("/api/exchanges", get(exchanges::exchanges))
        .route("/api/exchanges/{vhost}", get(exchanges::exchanges_in))
        .route(
            "/api/exchanges/{vhost}/{name}",
            get(exchanges::exchange)
                .put(exchanges::put_exchange)
                .delete(exchanges::delete_exchange),
        )
        .route(
            "/api/exchanges/{vhost}/{name}/publish",
            post(exchanges::publish),
        )
        .route(
            "/api/exchanges/{vhost}/{name}/bindings/source",
            get(bindings::exchange_bindings_source),
        )
        .route(
            "/api/exchanges/{vhost}/{name}/bindings/destination",
            get(bindings::exchange_bindings_destination),
        )
        .route("/api/queues", get(queues::queues))
        .route("/api/queues/{vhost}", get(queues::queues_in))
        .route(
            "/api/queues/{vhost}/{name}",
            get(queues::queue)
                .put(queues::put_queue)
                .delete(queues::delete_queue),
        )
        .route("/api/queues/{vhost}/{name}/contents", delete(queues::purge))
        .route("/api/queues/{vhost}/{name}/get", post(queues::get_messages))
        .route(
            "/api/queues/{vhost}/{name}/bindings",
            get(bindings::queue_bindings),
        )
        .route("/api/bindings", get(bindings::bindings))
        .route("/api/bindings/{vhost}", get(bindings::bindings_in))
        .route(
            "/api/bindings/{vhost}/e/{source}/{kind}/{destination}",
            get(bindings::bindings_between).post(bindings::post_binding),
        )
        .route(
            "/api/bindings/{vhost}/e/{source}/{kind}/{destination}/{props}",
            get(bindings::binding).delete(bindings::delete_binding),
        )
        .route("/api/connections", get(connections::connections))
        .route(
            "/api/connections/{name}",
            get(connections::connection).delete(connections::close_connection),
        )
        .route("/api/channels", get(channels::channels))
        .route("/api/consumers", get(consumers::consumers))
        .route("/api/consumers/{vhost}", get(consumers::consumers_in))
        .route(
            "/api/definitions",
            get(definitions::definitions).post(definitions::import_definitions),
        )
        .route(
            "/api/definitions/{vhost}",
            get(definitions::vhost_definitions).post(definitions::import_vhost_definitions),
        )
        .route("/api/aliveness-test/{vhost}", get(health::aliveness_test))
        .route("/api/shovels", get(shovels::shovels))
        .route("/api/shovels/{vhost}", get(shovels::shovels_in))
        .route(
            "/api/parameters/shovel/{vhost}/{name}",
            get(shovels::shovel_parameter)
                .put(shovels::put_shovel)
                .delete(shovels::delete_shovel),
        )
        .route("/api/parameters", get(parameters::all))
        .route("/api/parameters/{component}", get(parameters::of_component))
        .route(
            "/api/parameters/{component}/{vhost}",
            get(parameters::of_component_in),
        )
        .route(
            "/api/parameters/federation-upstream/{vhost}/{name}",
            get(federation::upstream)
                .put(federation::put_upstream)
                .delete(federation::delete_upstream),
        )
        .route("/api/policies", get(policies::all))
        .route("/api/policies/{vhost}", get(policies::in_vhost))
        .route(
            "/api/policies/{vhost}/{name}",
            get(policies::get_one)
                .put(policies::put_one)
                .delete(policies::delete_one),
        )
        .route("/api/operator-policies", get(policies::operator_all))
        .route(
            "/api/operator-policies/{vhost}",
            get(policies::operator_in_vhost),
        )
        .route(
            "/api/operator-policies/{vhost}/{name}",
            get(policies::operator_get_one)
                .put(policies::operator_put_one)
                .delete(policies::operator_delete_one),
        )
        .route(
            "/api/cluster-name",
            get(policies::cluster_name).put(policies::put_cluster_name),
        )
        .route("/api/global-parameters", get(policies::global_parameters))
        .route(
            "/api/global-parameters/{name}",
            get(policies::global_parameter)
                .put(policies::put_global_parameter)
                .delete(policies::delete_global_parameter),
        )
        .route("/api/federation-links", get(federation::links))
        .route("/api/federation-links/{vhost}", get(federation::links_in))
        .route("/api/health/checks/alarms", get(health::alarms))
        .route("/api/health/checks/local-alarms", get(health::local_alarms))
        .route(
            "/api/health/checks/port-listener/{port}",
            get(health::port_listener),
        )
        .route(
            "/api/health/checks/protocol-listener/{protocol}",
            get(health::protocol_listener),
        )
        .route(
            "/api/health/checks/virtual-hosts",
            get(health::virtual_hosts),
        )
        .route(
            "/api/health/checks/node-is-quorum-critical",
            get(health::node_is_quorum_critical),
        )
        .route(
            "/api/health/checks/node-is-mirror-sync-critical",
            get(health::node_is_mirror_sync_critical),
        )
        .route(
            "/api/health/checks/certificate-expiration/{within}/{unit}",
            get(health::certificate_expiration),
        )
        .fallback(common::unknown)
        .route_layer(axum::middleware::from_fn(audit::log_changes))
        .route_layer(axum::middleware::from_fn_with_state(
            Arc::clone(&context),
            authenticate,
        ));
    api.layer(DefaultBodyLimit::max(MAX_BODY))
        .with_state(context)
}
