//! The storage life cycle through the REST API in-process: inputs listed with the campaigns that
//! name them and deleted only when none does, inputs written once, manifests naming only
//! complete inputs within the server's bounds, cancel and delete removing what they leave.

use axum::body::Body;
use axum::http::{Method, StatusCode};
use precimap_api::ApiState;
use precimap_framework::CampaignLimits;

use crate::common;
use common::{call, embedded_state, request, TOKEN};

async fn state(dir: &std::path::Path) -> ApiState {
    embedded_state(dir).await
}

fn manifest(strips: &[&str], traj_uri: &str) -> String {
    let strips: Vec<_> = strips
        .iter()
        .enumerate()
        .map(|(i, uri)| serde_json::json!({"id": format!("s{i}"), "trajectory": "v01", "scanner": "left", "uri": uri}))
        .collect();
    serde_json::json!({
        "name": "t",
        "scanners": {"left": {"lever_arm_m": [0.0, 0.5, 0.3]}},
        "trajectories": [{"id": "v01", "uri": traj_uri}],
        "strips": strips,
    })
    .to_string()
}

async fn upload(s: &ApiState, key: &str, body: &'static str) -> (StatusCode, serde_json::Value) {
    call(s, request(Method::PUT, &format!("/v1/objects/{key}"), Some(TOKEN), body)).await
}

async fn submit(s: &ApiState, body: String) -> (StatusCode, serde_json::Value) {
    call(s, request(Method::POST, "/v1/campaigns", Some(TOKEN), body)).await
}

#[tokio::test]
async fn inputs_are_listed_with_their_campaigns_and_deleted_only_when_unnamed() {
    let dir = tempfile::tempdir().unwrap();
    let s = state(dir.path()).await;
    for key in ["inputs/u/t.csv", "inputs/u/a.las", "inputs/u/b.las", "inputs/v/c.las"] {
        assert_eq!(upload(&s, key, "data").await.0, StatusCode::CREATED);
    }
    // Written once: a second upload to the same key is refused and changes nothing.
    let (status, body) = upload(&s, "inputs/u/a.las", "other").await;
    assert_eq!(status, StatusCode::CONFLICT, "{body}");
    assert!(body["error"].as_str().unwrap().contains("immutable"), "{body}");
    assert_eq!(std::fs::read_to_string(dir.path().join("store/inputs/u/a.las")).unwrap(), "data");
    // A half-written upload is not listed.
    std::fs::write(dir.path().join("store/inputs/u/d.upload-0123456789abcdef0123456789abcdef"), "half").unwrap();

    let (status, body) = submit(&s, manifest(&["inputs/u/a.las"], "inputs/u/t.csv")).await;
    assert_eq!(status, StatusCode::CREATED, "{body}");
    let id = body["id"].as_str().unwrap().to_string();

    let (status, body) = call(&s, request(Method::GET, "/v1/inputs", None, Body::empty())).await;
    assert_eq!(status, StatusCode::OK, "{body}");
    let keys: Vec<&str> = body["inputs"].as_array().unwrap().iter().map(|i| i["key"].as_str().unwrap()).collect();
    assert_eq!(keys, ["inputs/u/a.las", "inputs/u/b.las", "inputs/u/t.csv", "inputs/v/c.las"]);
    assert_eq!(body["inputs"][0]["campaigns"], serde_json::json!([id]));
    assert_eq!(body["inputs"][1]["campaigns"], serde_json::json!([]));
    assert_eq!(body["inputs"][0]["bytes"], 4);
    assert_eq!(body["truncated"], false);
    let (_, body) = call(&s, request(Method::GET, "/v1/inputs?prefix=inputs/v&limit=5", None, Body::empty())).await;
    assert_eq!(body["inputs"].as_array().unwrap().len(), 1);
    let (_, body) = call(&s, request(Method::GET, "/v1/inputs?limit=1", None, Body::empty())).await;
    assert_eq!(body["truncated"], true);
    let (status, _) = call(&s, request(Method::GET, "/v1/inputs?prefix=c", None, Body::empty())).await;
    assert_eq!(status, StatusCode::BAD_REQUEST);

    // Deleting needs the token; a named input (or a folder holding one) is refused whole.
    for token in [None, Some("wrong")] {
        let (status, _) = call(&s, request(Method::DELETE, "/v1/inputs/u/b.las", token, Body::empty())).await;
        assert_eq!(status, StatusCode::UNAUTHORIZED);
    }
    let (status, body) = call(&s, request(Method::DELETE, "/v1/inputs/u/a.las", Some(TOKEN), Body::empty())).await;
    assert_eq!(status, StatusCode::CONFLICT, "{body}");
    assert!(body["error"].as_str().unwrap().contains(&id), "{body}");
    let (status, _) = call(&s, request(Method::DELETE, "/v1/inputs/u", Some(TOKEN), Body::empty())).await;
    assert_eq!(status, StatusCode::CONFLICT);
    assert!(dir.path().join("store/inputs/u/b.las").exists(), "nothing of a refused folder is deleted");
    let (status, body) = call(&s, request(Method::DELETE, "/v1/inputs/u/b.las", Some(TOKEN), Body::empty())).await;
    assert_eq!(status, StatusCode::OK, "{body}");
    assert_eq!(body["deleted"], serde_json::json!(["inputs/u/b.las"]));
    let (status, body) = call(&s, request(Method::DELETE, "/v1/inputs/v", Some(TOKEN), Body::empty())).await;
    assert_eq!((status, body["deleted"].clone()), (StatusCode::OK, serde_json::json!(["inputs/v/c.las"])));
    let (status, _) = call(&s, request(Method::DELETE, "/v1/inputs/v", Some(TOKEN), Body::empty())).await;
    assert_eq!(status, StatusCode::NOT_FOUND);
    // Deleted, an input may be uploaded again.
    assert_eq!(upload(&s, "inputs/u/b.las", "new").await.0, StatusCode::CREATED);

    // Cancelling removes everything under the campaign's prefix; deleting it removes the inputs
    // it alone named.
    let uuid: uuid::Uuid = id.parse().unwrap();
    let prefix = s.framework.jobs.object_prefix(uuid).await.unwrap().unwrap();
    s.framework.objects.put(&format!("{prefix}/tiles/0_0/s0.0123456789ab.chunk"), "x".into()).await.unwrap();
    let (status, _) = call(&s, request(Method::POST, &format!("/v1/campaigns/{id}/cancel"), Some(TOKEN), "")).await;
    assert_eq!(status, StatusCode::OK);
    assert!(s.framework.objects.list(&prefix).await.unwrap().is_empty());
    let (status, _) = call(&s, request(Method::DELETE, &format!("/v1/campaigns/{id}"), Some(TOKEN), "")).await;
    assert_eq!(status, StatusCode::NO_CONTENT);
    for (key, kept) in [("u/a.las", false), ("u/t.csv", false), ("u/b.las", true)] {
        assert_eq!(dir.path().join("store/inputs").join(key).exists(), kept, "{key}");
    }
}

#[tokio::test]
async fn manifests_name_only_complete_inputs_within_the_bounds() {
    let dir = tempfile::tempdir().unwrap();
    let mut s = state(dir.path()).await;
    for key in ["inputs/u/t.csv", "inputs/u/a.las", "inputs/u/b.las"] {
        assert_eq!(upload(&s, key, "data").await.0, StatusCode::CREATED);
    }
    // Existing objects outside inputs/ (another campaign's work) and a temporary upload file.
    s.framework.objects.put("c/0123/tiles/0_0/s.0123456789ab.chunk", "x".into()).await.unwrap();
    std::fs::write(dir.path().join("store/inputs/u/d.upload-0123456789abcdef0123456789abcdef"), "half").unwrap();
    let (status, body) = submit(
        &s,
        manifest(
            &["c/0123/tiles/0_0/s.0123456789ab.chunk", "inputs/u/d.upload-0123456789abcdef0123456789abcdef"],
            "inputs/u/t.csv",
        ),
    )
    .await;
    assert_eq!(status, StatusCode::UNPROCESSABLE_ENTITY, "{body}");
    let paths: Vec<&str> = body["problems"].as_array().unwrap().iter().map(|p| p["path"].as_str().unwrap()).collect();
    assert_eq!(paths, ["$.strips[0].uri", "$.strips[1].uri"], "{body}");

    s.limits = CampaignLimits { max_strips: 1, max_trajectories: 1, max_input_bytes: 100 };
    let (status, body) = submit(&s, manifest(&["inputs/u/a.las", "inputs/u/b.las"], "inputs/u/t.csv")).await;
    assert_eq!(status, StatusCode::UNPROCESSABLE_ENTITY, "{body}");
    assert_eq!(body["problems"][0]["path"], "$.strips");
    assert!(body["problems"][0]["message"].as_str().unwrap().contains("at most 1 strips"), "{body}");
    s.limits.max_input_bytes = 7;
    let (status, body) = submit(&s, manifest(&["inputs/u/a.las"], "inputs/u/t.csv")).await;
    assert_eq!(status, StatusCode::UNPROCESSABLE_ENTITY, "{body}");
    assert_eq!(body["problems"][0]["path"], "$");
    assert!(body["problems"][0]["message"].as_str().unwrap().contains("8 bytes"), "{body}");
    s.limits.max_input_bytes = 8;
    assert_eq!(submit(&s, manifest(&["inputs/u/a.las"], "inputs/u/t.csv")).await.0, StatusCode::CREATED);
}
