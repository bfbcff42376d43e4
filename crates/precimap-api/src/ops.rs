//! What an operator's tooling reads: `GET /readyz` (can this server do its work: the job store
//! and the object store answer) and `GET /metrics` (Prometheus text format: this process's
//! series, and the queue and running campaigns read from the job store at each scrape).

use crate::server::ApiState;
use axum::extract::State;
use axum::http::{header, StatusCode};
use axum::response::{IntoResponse, Response};
use axum::routing::get;
use axum::{Json, Router};
use std::sync::Arc;
use std::time::Duration;

/// Renders the process's metrics in the Prometheus text format (the binary's recorder).
#[derive(Clone)]
pub struct MetricsRenderer(pub Arc<dyn Fn() -> String + Send + Sync>);

impl std::fmt::Debug for MetricsRenderer {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("MetricsRenderer")
    }
}

pub(crate) fn routes() -> Router<Arc<ApiState>> {
    Router::new().route("/readyz", get(readyz)).route("/metrics", get(metrics))
}

/// Each check gets this long; a probe that hangs is a failed probe.
const CHECK_TIMEOUT: Duration = Duration::from_secs(3);

/// 200 when the job store and the object store both answer, else 503 naming which does not
/// (never where it is: the logs say that).
async fn readyz(State(state): State<Arc<ApiState>>) -> Response {
    let jobs = tokio::time::timeout(CHECK_TIMEOUT, state.framework.jobs.now_ms());
    let store = tokio::time::timeout(CHECK_TIMEOUT, state.framework.objects.exists("readyz-probe"));
    let (jobs, store) = tokio::join!(jobs, store);
    let mut failing = Vec::new();
    match jobs {
        Ok(Ok(_)) => {}
        Ok(Err(e)) => {
            tracing::warn!(error = %e, "readiness: job store");
            failing.push("job store");
        }
        Err(_) => {
            tracing::warn!("readiness: job store did not answer within {CHECK_TIMEOUT:?}");
            failing.push("job store");
        }
    }
    match store {
        Ok(Ok(_)) => {}
        Ok(Err(e)) => {
            tracing::warn!(error = %e, "readiness: object store");
            failing.push("object store");
        }
        Err(_) => {
            tracing::warn!("readiness: object store did not answer within {CHECK_TIMEOUT:?}");
            failing.push("object store");
        }
    }
    if failing.is_empty() {
        (StatusCode::OK, Json(serde_json::json!({ "status": "ready" }))).into_response()
    } else {
        let body = serde_json::json!({ "status": "not ready", "failing": failing });
        (StatusCode::SERVICE_UNAVAILABLE, Json(body)).into_response()
    }
}

async fn metrics(State(state): State<Arc<ApiState>>) -> Response {
    let Some(render) = &state.metrics else {
        let body = serde_json::json!({ "error": "this server records no metrics" });
        return (StatusCode::NOT_FOUND, Json(body)).into_response();
    };
    // The queue and the campaigns as the job store has them now; a database that does not
    // answer leaves the last values (and says so in the log), the process's own series stand.
    match tokio::time::timeout(CHECK_TIMEOUT, precimap_framework::metrics::observe_job_store(&state.framework.jobs))
        .await
    {
        Ok(Ok(())) => {}
        Ok(Err(e)) => tracing::warn!(error = %e, "metrics: reading the job store"),
        Err(_) => tracing::warn!("metrics: the job store did not answer within {CHECK_TIMEOUT:?}"),
    }
    ([(header::CONTENT_TYPE, "text/plain; version=0.0.4; charset=utf-8")], (render.0)()).into_response()
}
