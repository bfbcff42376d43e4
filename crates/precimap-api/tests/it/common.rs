//! What the in-process API tests share: an embedded state, requests, and calls through the app.

use axum::body::Body;
use axum::http::{header, Method, Request, StatusCode};
use precimap_api::{app, ApiState, Auth};
use precimap_framework::{default_queue, Framework, Objects};
use precimap_jobs::JobStore;
use tower::ServiceExt;

pub const TOKEN: &str = "s3cret-token";

/// The API over SQLite `dir/jobs.db` and the file store `dir/store`, writers needing [`TOKEN`].
pub async fn embedded_state(dir: &std::path::Path) -> ApiState {
    let jobs = JobStore::connect(&format!("sqlite://{}", dir.join("jobs.db").display())).await.unwrap();
    let objects = Objects::from_url(&format!("file://{}", dir.join("store").display())).unwrap();
    ApiState::new(Framework { jobs, objects, queue: default_queue() }, Auth::Token(TOKEN.into()))
}

pub fn request(method: Method, uri: &str, token: Option<&str>, body: impl Into<Body>) -> Request<Body> {
    let mut b = Request::builder().method(method).uri(uri);
    if let Some(t) = token {
        b = b.header(header::AUTHORIZATION, format!("Bearer {t}"));
    }
    b.header(header::CONTENT_TYPE, "application/json").body(body.into()).unwrap()
}

/// The response's status and JSON body (null when it is not JSON).
pub async fn call(s: &ApiState, req: Request<Body>) -> (StatusCode, serde_json::Value) {
    let response = app(s.clone()).oneshot(req).await.unwrap();
    let status = response.status();
    let bytes = axum::body::to_bytes(response.into_body(), 1 << 20).await.unwrap();
    (status, serde_json::from_slice(&bytes).unwrap_or(serde_json::Value::Null))
}
