//! Serving an axum router on a TCP listener with bounds a peer cannot get
//! around: at most [`MAX_CONNECTIONS`] connections at once (more are
//! closed at accept), the request head within [`HEADER_TIMEOUT`], each
//! connection at most [`CONNECTION_LIFETIME`] (then closed after its
//! current request), request bodies capped by the router's own
//! `DefaultBodyLimit`. HTTP/1.1 only, as RabbitMQ's listeners are served.
//!
//! hyper (through hyper-util's connection builder) does the protocol;
//! axum's `Router` is the service. The loop is ours rather than
//! `axum::serve` so the connection cap and timeouts sit in one place.

use axum::Router;
use hyper_util::rt::{TokioIo, TokioTimer};
use hyper_util::service::TowerToHyperService;
use std::sync::Arc;
use std::time::Duration;
use tokio::net::TcpListener;
use tokio::sync::{watch, Semaphore};

/// Connections served at once per listener.
pub const MAX_CONNECTIONS: usize = 64;
/// Time a client has to send a request's head.
pub const HEADER_TIMEOUT: Duration = Duration::from_secs(10);
/// Longest a connection is kept (keep-alive included).
pub const CONNECTION_LIFETIME: Duration = Duration::from_secs(300);

/// Serves `router` on `listener` until `stop` turns true.
pub async fn serve(
    listener: TcpListener,
    router: Router,
    what: &'static str,
    mut stop: watch::Receiver<bool>,
) {
    let slots = Arc::new(Semaphore::new(MAX_CONNECTIONS));
    loop {
        let accepted = tokio::select! {
            accepted = listener.accept() => accepted,
            _ = stop.wait_for(|stop| *stop) => return,
        };
        let (stream, peer) = match accepted {
            Ok(pair) => pair,
            Err(e) => {
                tracing::warn!(listener = what, error = %e, "accept failed");
                tokio::time::sleep(Duration::from_millis(50)).await;
                continue;
            }
        };
        let Ok(slot) = Arc::clone(&slots).try_acquire_owned() else {
            tracing::warn!(listener = what, %peer, limit = MAX_CONNECTIONS, "too many HTTP connections; closing a new one");
            continue;
        };
        let service = TowerToHyperService::new(router.clone());
        let mut stop = stop.clone();
        tokio::spawn(async move {
            let connection = hyper::server::conn::http1::Builder::new()
                .timer(TokioTimer::new())
                .header_read_timeout(HEADER_TIMEOUT)
                .serve_connection(TokioIo::new(stream), service);
            tokio::pin!(connection);
            let deadline = tokio::time::sleep(CONNECTION_LIFETIME);
            tokio::pin!(deadline);
            let mut closing = false;
            loop {
                tokio::select! {
                    result = connection.as_mut() => {
                        if let Err(e) = result {
                            tracing::debug!(listener = what, %peer, error = %e, "HTTP connection ended with an error");
                        }
                        break;
                    }
                    _ = &mut deadline, if !closing => {
                        closing = true;
                        connection.as_mut().graceful_shutdown();
                    }
                    _ = stop.wait_for(|stop| *stop), if !closing => {
                        closing = true;
                        connection.as_mut().graceful_shutdown();
                    }
                }
            }
            drop(slot);
        });
    }
}
