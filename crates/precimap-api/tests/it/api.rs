//! The REST API in-process (`app().oneshot`): authentication, bounded and validated requests,
//! every manifest problem with its JSON path, and the object-key rules.

use axum::body::Body;
use axum::http::{header, Method, StatusCode};
use precimap_api::{app, ApiState, ErrorBody};
use tower::ServiceExt;

use crate::common;
use common::{call, embedded_state, request, TOKEN};

async fn state(dir: &std::path::Path) -> ApiState {
    let mut s = embedded_state(dir).await;
    s.max_upload_bytes = 1000;
    s.max_manifest_bytes = 10_000;
    s
}

fn manifest(strip_uri: &str, traj_uri: &str) -> String {
    serde_json::json!({
        "name": "t",
        "scanners": {"left": {"lever_arm_m": [0.0, 0.5, 0.3]}},
        "trajectories": [{"id": "v01", "uri": traj_uri}],
        "strips": [{"id": "v01-left", "trajectory": "v01", "scanner": "left", "uri": strip_uri}]
    })
    .to_string()
}

#[tokio::test]
async fn health_and_reads_need_no_token() {
    let dir = tempfile::tempdir().unwrap();
    let s = state(dir.path()).await;
    let (status, body) = call(&s, request(Method::GET, "/healthz", None, Body::empty())).await;
    assert_eq!(status, StatusCode::OK, "{body}");
    assert_eq!(body["status"], "ok");
    let (status, body) = call(&s, request(Method::GET, "/v1/campaigns", None, Body::empty())).await;
    assert_eq!(status, StatusCode::OK);
    assert_eq!(body, serde_json::json!([]));
    let id = uuid::Uuid::new_v4();
    let (status, body) = call(&s, request(Method::GET, &format!("/v1/campaigns/{id}"), None, Body::empty())).await;
    assert_eq!(status, StatusCode::NOT_FOUND);
    assert!(body["error"].as_str().unwrap().contains(&id.to_string()));
    let (status, _) = call(&s, request(Method::GET, "/v1/campaigns/not-a-uuid", None, Body::empty())).await;
    assert_eq!(status, StatusCode::NOT_FOUND);
}

#[tokio::test]
async fn writes_need_the_bearer_token() {
    let dir = tempfile::tempdir().unwrap();
    let s = state(dir.path()).await;
    let (status, _) = call(&s, request(Method::GET, "/v1/token", Some(TOKEN), Body::empty())).await;
    assert_eq!(status, StatusCode::NO_CONTENT);
    let m = manifest("inputs/a/s.las", "inputs/a/t.csv");
    for token in [None, Some("wrong")] {
        let response = app(s.clone()).oneshot(request(Method::POST, "/v1/campaigns", token, m.clone())).await.unwrap();
        assert_eq!(response.status(), StatusCode::UNAUTHORIZED);
        assert_eq!(response.headers()[header::WWW_AUTHENTICATE], "Bearer");
        let (status, _) = call(&s, request(Method::PUT, "/v1/objects/inputs/a/s.las", token, "x")).await;
        assert_eq!(status, StatusCode::UNAUTHORIZED);
        let (status, _) = call(&s, request(Method::GET, "/v1/token", token, Body::empty())).await;
        assert_eq!(status, StatusCode::UNAUTHORIZED);
        let id = uuid::Uuid::new_v4();
        let (status, _) = call(&s, request(Method::POST, &format!("/v1/campaigns/{id}/cancel"), token, "")).await;
        assert_eq!(status, StatusCode::UNAUTHORIZED);
        let (status, _) = call(&s, request(Method::DELETE, &format!("/v1/campaigns/{id}"), token, "")).await;
        assert_eq!(status, StatusCode::UNAUTHORIZED);
    }
}

#[tokio::test]
async fn a_bad_manifest_gets_422_with_every_problem_and_its_path() {
    let dir = tempfile::tempdir().unwrap();
    let s = state(dir.path()).await;
    // Two schema problems at once.
    let bad = serde_json::json!({
        "name": "t",
        "scanners": {"left": {"lever_arm_m": [0.0, 0.5]}},
        "trajectories": [{"id": "v01", "uri": "../../etc/passwd"}],
        "strips": [{"id": "s", "trajectory": "nope", "scanner": "left", "uri": "file:///etc/passwd", "extra": 1}]
    })
    .to_string();
    let (status, body) = call(&s, request(Method::POST, "/v1/campaigns", Some(TOKEN), bad)).await;
    assert_eq!(status, StatusCode::UNPROCESSABLE_ENTITY, "{body}");
    let body: ErrorBody = serde_json::from_value(body).unwrap();
    let paths: Vec<&str> = body.problems.iter().map(|p| p.path.as_str()).collect();
    for expected in
        ["$.scanners.left.lever_arm_m", "$.trajectories[0].uri", "$.strips[0].uri", "$.strips[0].trajectory"]
    {
        assert!(paths.contains(&expected), "{expected} missing in {paths:?}");
    }
    // Syntactically fine, but the objects are not in the store.
    let (status, body) =
        call(&s, request(Method::POST, "/v1/campaigns", Some(TOKEN), manifest("inputs/a/s.las", "inputs/a/t.csv")))
            .await;
    assert_eq!(status, StatusCode::UNPROCESSABLE_ENTITY);
    let body: ErrorBody = serde_json::from_value(body).unwrap();
    let paths: Vec<&str> = body.problems.iter().map(|p| p.path.as_str()).collect();
    assert_eq!(paths, ["$.trajectories[0].uri", "$.strips[0].uri"]);
    assert!(body.problems[0].message.contains("upload"), "{}", body.problems[0].message);
    // Malformed JSON.
    let (status, body) = call(&s, request(Method::POST, "/v1/campaigns", Some(TOKEN), "{\"name\": ")).await;
    assert_eq!(status, StatusCode::UNPROCESSABLE_ENTITY);
    assert!(body["problems"][0]["message"].as_str().unwrap().contains("malformed JSON"), "{body}");
    // Oversized body.
    let huge = format!("{{\"name\": \"{}\"}}", "x".repeat(20_000));
    let (status, _) = call(&s, request(Method::POST, "/v1/campaigns", Some(TOKEN), huge)).await;
    assert_eq!(status, StatusCode::PAYLOAD_TOO_LARGE);
}

#[tokio::test]
async fn uploads_stay_inside_inputs_and_within_the_limit() {
    let dir = tempfile::tempdir().unwrap();
    let s = state(dir.path()).await;
    let (status, body) = call(&s, request(Method::PUT, "/v1/objects/inputs/u1/t.csv", Some(TOKEN), "a,b\n")).await;
    assert_eq!(status, StatusCode::CREATED, "{body}");
    assert_eq!(body["bytes"], 4);
    assert_eq!(std::fs::read_to_string(dir.path().join("store/inputs/u1/t.csv")).unwrap(), "a,b\n");
    let (status, _) = call(&s, request(Method::PUT, "/v1/objects/c/x/report.json", Some(TOKEN), "{}")).await;
    assert_eq!(status, StatusCode::FORBIDDEN);
    let (status, _) = call(&s, request(Method::PUT, "/v1/objects/inputs/../../etc/x", Some(TOKEN), "x")).await;
    assert!(status == StatusCode::BAD_REQUEST || status == StatusCode::NOT_FOUND, "{status}");
    let (status, _) = call(&s, request(Method::PUT, "/v1/objects/inputs/u1/%2e%2e/x", Some(TOKEN), "x")).await;
    assert_eq!(status, StatusCode::BAD_REQUEST);
    let (status, _) = call(&s, request(Method::PUT, "/v1/objects/inputs/u1/big", Some(TOKEN), vec![0u8; 2000])).await;
    assert_eq!(status, StatusCode::PAYLOAD_TOO_LARGE);
    assert!(!dir.path().join("store/inputs/u1/big").exists());
}

/// The dashboard's three files need no token, carry their types, and forbid inline script,
/// foreign origins and framing; the page loads exactly its own script and stylesheet.
#[tokio::test]
async fn the_dashboard_is_served_under_a_strict_policy() {
    let dir = tempfile::tempdir().unwrap();
    let s = state(dir.path()).await;
    let mut bodies = Vec::new();
    for (path, content_type) in [
        ("/", "text/html; charset=utf-8"),
        ("/dashboard.js", "text/javascript; charset=utf-8"),
        ("/dashboard.css", "text/css; charset=utf-8"),
    ] {
        let response = app(s.clone()).oneshot(request(Method::GET, path, None, Body::empty())).await.unwrap();
        assert_eq!(response.status(), StatusCode::OK, "{path}");
        let headers = response.headers();
        assert_eq!(headers[header::CONTENT_TYPE], content_type, "{path}");
        assert_eq!(headers[header::X_CONTENT_TYPE_OPTIONS], "nosniff");
        let policy = headers[header::CONTENT_SECURITY_POLICY].to_str().unwrap();
        for directive in ["default-src 'none'", "script-src 'self'", "connect-src 'self'", "frame-ancestors 'none'"] {
            assert!(policy.split(';').any(|d| d.trim() == directive), "{path}: {directive} missing in {policy}");
        }
        assert!(!policy.contains("unsafe"), "{policy}");
        let bytes = axum::body::to_bytes(response.into_body(), 1 << 20).await.unwrap();
        bodies.push(String::from_utf8(bytes.to_vec()).unwrap());
    }
    let page = &bodies[0];
    assert!(page.contains(r#"<script src="/dashboard.js" defer></script>"#), "{page}");
    assert!(page.contains(r#"<link rel="stylesheet" href="/dashboard.css">"#), "{page}");
    // The policy refuses inline script and style, so the page must not depend on any.
    assert_eq!(page.matches("<script").count(), 1, "only the external script");
    assert!(!page.contains("<style") && !page.contains(" style="), "inline style in the page");
    let handler_attribute = page.split(" on").skip(1).any(|rest| {
        let name: String = rest.chars().take_while(|c| c.is_ascii_alphabetic()).collect();
        !name.is_empty() && rest[name.len()..].starts_with('=')
    });
    assert!(!handler_attribute, "an inline event handler in the page");
    // Server data enters the page as text only.
    let script = &bodies[1];
    for sink in ["innerHTML", "outerHTML", "insertAdjacentHTML", "document.write", "eval("] {
        assert!(!script.contains(sink), "the dashboard script uses {sink}");
    }
}

/// `tail` (the newest events) cannot be mixed with forward paging.
#[tokio::test]
async fn events_tail_excludes_paging() {
    let dir = tempfile::tempdir().unwrap();
    let s = state(dir.path()).await;
    let id = uuid::Uuid::new_v4();
    let (status, body) =
        call(&s, request(Method::GET, &format!("/v1/campaigns/{id}/events?tail=5"), None, Body::empty())).await;
    assert_eq!((status, body), (StatusCode::OK, serde_json::json!({ "events": [] })));
    for query in ["tail=5&after=3", "tail=5&limit=9"] {
        let (status, body) =
            call(&s, request(Method::GET, &format!("/v1/campaigns/{id}/events?{query}"), None, Body::empty())).await;
        assert_eq!(status, StatusCode::BAD_REQUEST, "{query}");
        assert!(body["error"].as_str().unwrap().contains("after"), "{body}");
    }
}
