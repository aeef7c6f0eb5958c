//! What every file of the management API shares: the [`Context`] its
//! handlers take, and [`ApiError`], an error as RabbitMQ's API words it,
//! with the broker's and the uplink's errors turned into it. Uses the
//! broker, the uplink's `Links` and `rates`; nothing else of the API.

use super::rates::Rates;
use crate::uplink::{DeclareError, Links};
use axum::http::{header, StatusCode};
use axum::response::{IntoResponse, Response};
use axum::Json;
use leveret_broker::{AccessError, Admin, AmqpError};
use leveret_protocol::ReplyCode;
use std::net::SocketAddr;
use std::path::PathBuf;

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
    pub(super) status: StatusCode,
    pub(super) error: &'static str,
    pub(super) reason: String,
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

    /// 401 for a login that failed.
    pub fn unauthorized() -> Self {
        ApiError {
            status: StatusCode::UNAUTHORIZED,
            error: "not_authorized",
            reason: "Login failed".into(),
        }
    }

    /// 401 `not_authorised` with `reason`, as RabbitMQ refuses a caller.
    pub fn not_authorised(reason: &str) -> Self {
        ApiError {
            status: StatusCode::UNAUTHORIZED,
            error: "not_authorised",
            reason: reason.to_owned(),
        }
    }
}

impl ApiError {
    /// An operation the caller's permissions refuse, as RabbitMQ answers
    /// `get` and the aliveness test: 401 with the AMQP reply text; other
    /// errors as [`From<AmqpError>`].
    pub fn refused_with_text(e: AmqpError) -> Self {
        match e.code {
            ReplyCode::AccessRefused => ApiError::not_authorised(&e.text),
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
            ReplyCode::AccessRefused => ApiError::not_authorised("Access refused."),
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
