//! The one mapping from errors to HTTP statuses, and the JSON envelope every error is sent in.

use std::collections::BTreeMap;

use axum::http::{header, HeaderValue, StatusCode};
use axum::response::{IntoResponse, Response};
use axum::Json;
use serde::Serialize;
use utoipa::openapi::{RefOr, Response as DocResponse, ResponseBuilder};
use utoipa::{IntoResponses, ToSchema};

use crate::service::{ErrorKind, ServiceError};

/// Every error body: `{"error": {"code", "message"}}`.
#[derive(Debug, Serialize, ToSchema)]
pub struct ErrorBody {
    pub error: ErrorDetail,
}

/// What went wrong: a gRPC-style code (`INVALID_ARGUMENT`, `NOT_FOUND`, ...) and a message for a person (the
/// field and the reason for invalid input).
#[derive(Debug, Serialize, ToSchema)]
pub struct ErrorDetail {
    pub code: String,
    pub message: String,
}

/// The error answers of the API routes, documented once for all of them.
pub struct ApiErrors;

impl IntoResponses for ApiErrors {
    fn responses() -> BTreeMap<String, RefOr<DocResponse>> {
        [
            ("400", "Invalid input (field and reason in the message)"),
            ("401", "Missing or unknown API key"),
            ("403", "Read-only key used for a write, or a browser page of an origin that is not allowed"),
            ("404", "Unknown map or keyframe, or no such route"),
            ("405", "The route does not take this method"),
            ("408", "The request body did not arrive within server.body_read_timeout_ms"),
            ("409", "Already exists, or model mismatch"),
            ("413", "Body larger than the limit"),
            ("415", "Content-Type not accepted by this route, or a compressed body (Content-Encoding)"),
            ("429", "Saturated: retry after the Retry-After header (seconds)"),
            ("500", "Internal error (details in the server's log)"),
            ("507", "The data volume is full: nothing of the write was stored; retry once space is freed"),
            ("503", "Maps loading, map held back, or shutting down"),
            ("504", "Request deadline exceeded"),
        ]
        .into_iter()
        .map(|(status, description)| {
            let content = utoipa::openapi::ContentBuilder::new()
                .schema(Some(utoipa::openapi::Ref::from_schema_name("ErrorBody")))
                .build();
            let r = ResponseBuilder::new().description(description).content("application/json", content).build();
            (status.to_string(), RefOr::T(r))
        })
        .collect()
    }
}

/// Errors of the HTTP layer: the service's own, and the transport's (media types, origins, routing, slow
/// bodies). Its [`IntoResponse`] is the one mapping to HTTP statuses; every error body is the JSON envelope
/// `{"error": {"code", "message"}}`.
#[derive(Debug)]
pub enum ApiError {
    Service(ServiceError),
    /// The route does not take this body's `Content-Type` (415).
    UnsupportedMediaType {
        got: String,
        accepted: &'static [&'static str],
    },
    /// A body sent with a `Content-Encoding` (gzip, ...): bodies are taken uncompressed only (415).
    UnsupportedEncoding {
        got: String,
    },
    /// A write (or a CORS preflight) from a browser page of another origin (403).
    ForeignOrigin {
        origin: String,
    },
    /// The request body did not arrive within `server.body_read_timeout_ms` (408).
    BodyTimeout {
        ms: u64,
    },
    NoRoute {
        path: String,
    },
    MethodNotAllowed {
        method: String,
        path: String,
    },
}

impl From<ServiceError> for ApiError {
    fn from(e: ServiceError) -> Self {
        Self::Service(e)
    }
}

fn code_name(kind: ErrorKind) -> &'static str {
    match kind {
        ErrorKind::InvalidArgument => "INVALID_ARGUMENT",
        ErrorKind::NotFound => "NOT_FOUND",
        ErrorKind::AlreadyExists => "ALREADY_EXISTS",
        ErrorKind::FailedPrecondition => "FAILED_PRECONDITION",
        ErrorKind::Unavailable => "UNAVAILABLE",
        ErrorKind::ResourceExhausted => "RESOURCE_EXHAUSTED",
        ErrorKind::InsufficientStorage => "RESOURCE_EXHAUSTED",
        ErrorKind::PayloadTooLarge => "PAYLOAD_TOO_LARGE",
        ErrorKind::DeadlineExceeded => "DEADLINE_EXCEEDED",
        ErrorKind::Unauthenticated => "UNAUTHENTICATED",
        ErrorKind::PermissionDenied => "PERMISSION_DENIED",
        ErrorKind::Internal => "INTERNAL",
    }
}

fn service_status(kind: ErrorKind) -> StatusCode {
    match kind {
        ErrorKind::InvalidArgument => StatusCode::BAD_REQUEST,
        ErrorKind::NotFound => StatusCode::NOT_FOUND,
        ErrorKind::AlreadyExists => StatusCode::CONFLICT,
        ErrorKind::FailedPrecondition => StatusCode::CONFLICT,
        ErrorKind::Unavailable => StatusCode::SERVICE_UNAVAILABLE,
        ErrorKind::ResourceExhausted => StatusCode::TOO_MANY_REQUESTS,
        ErrorKind::InsufficientStorage => StatusCode::INSUFFICIENT_STORAGE,
        ErrorKind::PayloadTooLarge => StatusCode::PAYLOAD_TOO_LARGE,
        ErrorKind::DeadlineExceeded => StatusCode::GATEWAY_TIMEOUT,
        ErrorKind::Unauthenticated => StatusCode::UNAUTHORIZED,
        ErrorKind::PermissionDenied => StatusCode::FORBIDDEN,
        ErrorKind::Internal => StatusCode::INTERNAL_SERVER_ERROR,
    }
}

impl IntoResponse for ApiError {
    fn into_response(self) -> Response {
        // Refused on its headers, the body is left unread: the connection cannot carry another request, and a
        // client that reused it would meet it closing.
        let unread = matches!(
            self,
            Self::UnsupportedMediaType { .. } | Self::UnsupportedEncoding { .. } | Self::ForeignOrigin { .. }
        );
        let (status, code, message, retry_after) = match self {
            Self::Service(e) => {
                let kind = e.kind();
                (service_status(kind), code_name(kind), e.client_message(), e.retry_after_s())
            }
            Self::UnsupportedMediaType { got, accepted } => (
                StatusCode::UNSUPPORTED_MEDIA_TYPE,
                "UNSUPPORTED_MEDIA_TYPE",
                format!(
                    "content-type {} is not accepted here: send {}",
                    if got.is_empty() { "(none)".to_string() } else { format!("'{got}'") },
                    accepted.join(", ")
                ),
                None,
            ),
            Self::UnsupportedEncoding { got } => (
                StatusCode::UNSUPPORTED_MEDIA_TYPE,
                "UNSUPPORTED_MEDIA_TYPE",
                format!("content-encoding '{got}' is not accepted: send the body uncompressed"),
                None,
            ),
            Self::ForeignOrigin { origin } => (
                StatusCode::FORBIDDEN,
                "PERMISSION_DENIED",
                format!("origin '{origin}' is not allowed to call this API (server.allowed_origins)"),
                None,
            ),
            Self::BodyTimeout { ms } => (
                StatusCode::REQUEST_TIMEOUT,
                "DEADLINE_EXCEEDED",
                format!("the request body did not arrive within {ms} ms"),
                None,
            ),
            Self::NoRoute { path } => (StatusCode::NOT_FOUND, "NOT_FOUND", format!("no route {path}"), None),
            Self::MethodNotAllowed { method, path } => {
                (StatusCode::METHOD_NOT_ALLOWED, "METHOD_NOT_ALLOWED", format!("{path} does not take {method}"), None)
            }
        };
        let body = ErrorBody { error: ErrorDetail { code: code.to_string(), message } };
        let mut resp = (status, Json(body)).into_response();
        if let Some(s) = retry_after {
            resp.headers_mut().insert(header::RETRY_AFTER, HeaderValue::from(s));
        }
        if unread {
            resp.headers_mut().insert(header::CONNECTION, HeaderValue::from_static("close"));
        }
        resp
    }
}

pub type ApiResult<T> = Result<T, ApiError>;

pub fn invalid(field: &str, reason: impl Into<String>) -> ApiError {
    ApiError::Service(ServiceError::invalid(field, reason))
}
