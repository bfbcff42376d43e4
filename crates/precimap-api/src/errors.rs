//! Errors as clients see them: every error response is `{"error": "...", "problems": [...]}`
//! (problems only for manifests), with a 4xx status for what the client can fix. Server-side
//! details (database errors, file paths, store URLs) go to the log under a reference that the
//! response quotes, never into the response itself.

use crate::types::{ErrorBody, Problem};
use axum::body::Body;
use axum::extract::Request;
use axum::http::{header, HeaderValue, Method, StatusCode};
use axum::middleware::Next;
use axum::response::{IntoResponse, Response};
use axum::Json;
use precimap_framework::FrameworkError;
use precimap_jobs::JobError;
use uuid::Uuid;

/// An error response: a status and a JSON body saying what is wrong and what to do.
#[derive(Debug)]
pub struct ApiError {
    pub(crate) status: StatusCode,
    pub(crate) body: ErrorBody,
}

impl ApiError {
    pub fn new(status: StatusCode, error: impl Into<String>) -> Self {
        Self { status, body: ErrorBody { error: error.into(), problems: Vec::new() } }
    }

    pub fn not_found(id: Uuid) -> Self {
        Self::new(StatusCode::NOT_FOUND, format!("no campaign {id}"))
    }

    pub fn with_problems(status: StatusCode, problems: Vec<Problem>) -> Self {
        Self { status, body: ErrorBody { error: format!("the manifest has {} problem(s)", problems.len()), problems } }
    }

    /// A server-side failure: `detail` goes to the log under a fresh reference, the client gets
    /// `summary` and the reference.
    pub fn internal(status: StatusCode, summary: &str, detail: &dyn std::fmt::Display) -> Self {
        let reference = Uuid::new_v4().simple().to_string();
        let reference = &reference[..12];
        tracing::error!(reference, status = status.as_u16(), error = %detail, "{summary}");
        Self::new(status, format!("{summary} (reference {reference}; the server's log has the details)"))
    }

    pub fn status(&self) -> StatusCode {
        self.status
    }
}

impl IntoResponse for ApiError {
    fn into_response(mut self) -> Response {
        self.body.error = scrub(&self.body.error);
        for problem in &mut self.body.problems {
            problem.message = scrub(&problem.message);
        }
        let mut response = (self.status, Json(self.body)).into_response();
        if self.status == StatusCode::UNAUTHORIZED {
            response.headers_mut().insert(header::WWW_AUTHENTICATE, HeaderValue::from_static("Bearer"));
        }
        response
    }
}

impl From<JobError> for ApiError {
    fn from(e: JobError) -> Self {
        if e.is_transient() {
            Self::internal(StatusCode::SERVICE_UNAVAILABLE, "the job store is unavailable; retry shortly", &e)
        } else {
            Self::internal(StatusCode::INTERNAL_SERVER_ERROR, "the job store failed", &e)
        }
    }
}

impl From<FrameworkError> for ApiError {
    fn from(e: FrameworkError) -> Self {
        match e {
            FrameworkError::Jobs(j) => j.into(),
            // The key and the rule it breaks are the client's own input.
            FrameworkError::BadKey { .. } | FrameworkError::Invalid(_) => {
                Self::new(StatusCode::BAD_REQUEST, e.to_string())
            }
            FrameworkError::TooLarge { .. } => Self::new(StatusCode::PAYLOAD_TOO_LARGE, e.to_string()),
            FrameworkError::Exists { .. } => Self::new(StatusCode::CONFLICT, e.to_string()),
            FrameworkError::Store { ref key, .. } if e.is_not_found() => {
                Self::new(StatusCode::NOT_FOUND, format!("no object {key}"))
            }
            other => Self::internal(StatusCode::BAD_GATEWAY, "the object store failed", &other),
        }
    }
}

/// The answer to a request no route takes.
pub async fn no_route(method: Method) -> ApiError {
    ApiError::new(
        StatusCode::NOT_FOUND,
        format!("no endpoint answers {method} at this path; the API's paths are in its OpenAPI description"),
    )
}

/// Bodies of error responses longer than this are not quoted (they are no plain-text rejection).
const QUOTED_ERROR_LIMIT: usize = 2048;

/// Rewrites every error response that is not JSON yet (axum's own rejections: a bad query
/// string, an oversized body, a method a path does not take) into the JSON error shape, keeping
/// its status and headers (`Allow`, `Retry-After`, `WWW-Authenticate`) and quoting its text.
pub async fn json_errors(request: Request, next: Next) -> Response {
    let response = next.run(request).await;
    let status = response.status();
    if !(status.is_client_error() || status.is_server_error()) {
        return response;
    }
    let is_json = response
        .headers()
        .get(header::CONTENT_TYPE)
        .and_then(|v| v.to_str().ok())
        .is_some_and(|v| v.starts_with("application/json"));
    if is_json {
        return response;
    }
    let (mut parts, body) = response.into_parts();
    let text = axum::body::to_bytes(body, QUOTED_ERROR_LIMIT)
        .await
        .ok()
        .and_then(|b| String::from_utf8(b.to_vec()).ok())
        .map(|t| t.trim().to_string())
        .filter(|t| !t.is_empty());
    let error = match (status, text) {
        (StatusCode::PAYLOAD_TOO_LARGE, _) => {
            "the request body is larger than this endpoint accepts; see the limits in the API description".to_string()
        }
        (StatusCode::METHOD_NOT_ALLOWED, _) => {
            "this path does not take that method; the Allow header lists the ones it takes".to_string()
        }
        (_, Some(text)) => text,
        (status, None) => status.canonical_reason().unwrap_or("error").to_lowercase(),
    };
    let body = serde_json::to_vec(&ErrorBody { error, problems: Vec::new() }).unwrap_or_default();
    parts.headers.insert(header::CONTENT_TYPE, HeaderValue::from_static("application/json"));
    parts.headers.remove(header::CONTENT_LENGTH);
    Response::from_parts(parts, Body::from(body))
}

/// A handler that panicked: logged, and answered like any other internal error.
pub fn panicked(panic: Box<dyn std::any::Any + Send + 'static>) -> Response {
    let detail = panic
        .downcast_ref::<String>()
        .cloned()
        .or_else(|| panic.downcast_ref::<&str>().map(|s| s.to_string()))
        .unwrap_or_else(|| "a handler panicked".to_string());
    ApiError::internal(StatusCode::INTERNAL_SERVER_ERROR, "internal error", &detail).into_response()
}

/// `text` with every absolute file path cut to its file name and every store URL replaced, so
/// that messages from deeper layers (a task's error, a missing input) can be shown to clients.
/// Quoted tokens are left alone: they are the client's own keys and names.
pub fn scrub(text: &str) -> String {
    let mut out = String::with_capacity(text.len());
    let mut rest = text;
    let mut at_boundary = true;
    while let Some(c) = rest.chars().next() {
        let is_url = ["file://", "s3://"].iter().any(|scheme| rest.starts_with(scheme));
        if at_boundary && (is_url || (c == '/' && rest.len() > 1)) {
            let end = rest
                .find(|c: char| c.is_whitespace() || matches!(c, '"' | '\'' | ')' | ',' | ';'))
                .unwrap_or(rest.len());
            let token = &rest[..end];
            // A trailing ':' separates the path from what went wrong with it.
            let (path, tail) = match token.strip_suffix(':') {
                Some(path) => (path, ":"),
                None => (token, ""),
            };
            if is_url {
                // Said where it stands ("in the store <url>"): dropped with its space.
                if out.ends_with(' ') && (tail.is_empty() || rest[end..].is_empty()) {
                    out.pop();
                }
            } else {
                out.push_str(path.trim_end_matches('/').rsplit('/').next().unwrap_or(""));
            }
            out.push_str(tail);
            rest = &rest[end..];
            at_boundary = false;
            continue;
        }
        out.push(c);
        at_boundary = c.is_whitespace() || matches!(c, '(' | '=' | '[');
        rest = &rest[c.len_utf8()..];
    }
    out
}

#[cfg(test)]
mod tests {
    use super::scrub;

    #[test]
    fn paths_and_store_urls_are_cut_from_messages() {
        assert_eq!(
            scrub("/var/lib/precimap/store/inputs/a.las: Permission denied (os error 13)"),
            "a.las: Permission denied (os error 13)"
        );
        assert_eq!(
            scrub("no object \"inputs/x\" in the store file:///srv/store; upload it"),
            "no object \"inputs/x\" in the store; upload it"
        );
        assert_eq!(scrub("Object at location /tmp/x/c/1/y.blk not found"), "Object at location y.blk not found");
        assert_eq!(scrub("key \"/etc/passwd\" is absolute"), "key \"/etc/passwd\" is absolute");
        assert_eq!(scrub("ratio 1/2 and a/b stay"), "ratio 1/2 and a/b stay");
        assert_eq!(scrub("s3://bucket/prefix/c/1: timeout"), ": timeout");
    }
}
