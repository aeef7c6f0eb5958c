//! The log line of each change made through the management API (closing
//! a connection, importing definitions, adding users, granting
//! permissions, declaring and deleting...): who made it (the
//! authenticated user), what it was (method and path, as sent) and how it
//! ended (the status). Reads are not logged; refused logins and requests
//! the caller's tags forbid are logged where they are refused (`login`).

use super::caller::Caller;
use axum::extract::Request;
use axum::http::Method;
use axum::middleware::Next;
use axum::response::Response;

/// The longest path logged, in bytes (paths are percent-encoded ASCII).
const LOGGED_PATH_MAX: usize = 512;

/// Runs the request; logs it if it changes something.
pub async fn log_changes(request: Request, next: Next) -> Response {
    let method = request.method().clone();
    if [Method::GET, Method::HEAD, Method::OPTIONS].contains(&method) {
        return next.run(request).await;
    }
    let user = (request.extensions().get::<Caller>()).map(|caller| caller.user.clone());
    let path: String = request.uri().path().chars().take(LOGGED_PATH_MAX).collect();
    let response = next.run(request).await;
    let status = response.status().as_u16();
    let user = user.unwrap_or_default();
    tracing::info!(
        %user,
        %method,
        %path,
        status,
        "management API: {method} {path} by user '{user}': {status}"
    );
    response
}
