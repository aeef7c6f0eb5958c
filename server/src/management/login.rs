//! Logging in to the management API: HTTP basic auth with one of the
//! broker's users, checked (queued and slowed per source address, as AMQP
//! logins are) and held to `loopback_users`; then the caller's tags must
//! let them in and allow the request (`caller`). Refusals are logged here,
//! with RabbitMQ's wording. Uses `api`, `caller` and the listener's
//! [`Peer`].

use super::api::{ApiError, Context};
use super::caller::{self, Caller};
use crate::http::Peer;
use axum::extract::{Request, State};
use axum::http::{header, HeaderMap};
use axum::middleware::Next;
use axum::response::{IntoResponse, Response};
use base64::Engine;
use std::sync::Arc;

/// The user and password of a basic `Authorization` header.
fn basic_credentials(headers: &HeaderMap) -> Option<(String, String)> {
    let value = headers.get(header::AUTHORIZATION)?.to_str().ok()?;
    let encoded = value.strip_prefix("Basic ")?.trim();
    let decoded = base64::engine::general_purpose::STANDARD
        .decode(encoded)
        .ok()?;
    let text = String::from_utf8(decoded).ok()?;
    let (user, password) = text.split_once(':')?;
    Some((user.to_owned(), password.to_owned()))
}

/// Lets a request through once its caller is logged in and allowed it;
/// else answers 401.
pub async fn authenticate(
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
            return ApiError::not_authorised("User can only log in via localhost").into_response();
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
