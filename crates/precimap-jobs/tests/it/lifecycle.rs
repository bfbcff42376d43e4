//! The storage life cycle's side of the job store, each scenario on SQLite (temp file) and
//! PostgreSQL (fresh database): parameters stored once per campaign, whether an attempt may
//! still write, which campaigns name an input, and deletion returning the inputs no other
//! campaign names.

use crate::common;

use std::time::Duration;

use common::*;
use precimap_jobs::*;
use serde_json::json;

const LONG: Duration = Duration::from_secs(60);

both_backends!(
    params_are_stored_once,
    attempts_may_write_only_while_they_hold_a_running_campaign,
    deleting_returns_the_inputs_no_other_campaign_names
);

/// A campaign naming `strips` and the trajectory `inputs/t.csv`.
fn campaign_naming(name: &str, strips: &[&str]) -> NewCampaign {
    let mut c = new_campaign(name, QueueConfig::default());
    c.strips = strips
        .iter()
        .enumerate()
        .map(|(i, uri)| StripRecord {
            index: i as i32,
            id: format!("s{i}"),
            trajectory: "t0".into(),
            uri: uri.to_string(),
            points: None,
        })
        .collect();
    c.trajectories = vec![TrajectoryRecord { index: 0, id: "t0".into(), uri: "inputs/t.csv".into() }];
    c
}

async fn params_are_stored_once(store: JobStore, _url: String) {
    let id = store.create_campaign(new_campaign("p", QueueConfig::default()), stage("s0", 0, 2)).await.unwrap();
    assert_eq!(store.campaign_params(id).await.unwrap(), Some(json!({ "grid_m": 1.0 })));
    let mut none = new_campaign("q", QueueConfig::default());
    none.params = serde_json::Value::Null;
    let id = store.create_campaign(none, stage("s0", 0, 1)).await.unwrap();
    assert_eq!(store.campaign_params(id).await.unwrap(), None);
    assert_eq!(store.campaign_params(uuid::Uuid::new_v4()).await.unwrap(), None);
}

async fn attempts_may_write_only_while_they_hold_a_running_campaign(store: JobStore, _url: String) {
    let id = store.create_campaign(new_campaign("w", QueueConfig::default()), stage("s0", 0, 3)).await.unwrap();
    let a = store.claim("w1", LONG).await.unwrap().unwrap();
    let b = store.claim("w2", LONG).await.unwrap().unwrap();
    assert!(store.attempt_may_write(a.id, a.lease_token).await.unwrap());
    assert!(!store.attempt_may_write(a.id, uuid::Uuid::new_v4()).await.unwrap(), "another token");
    // A lost lease: another attempt holds the task now.
    store.heartbeat(&b, Duration::ZERO).await.unwrap();
    tokio::time::sleep(Duration::from_millis(20)).await;
    store.reconcile(&ChainPlanner::new(&[3])).await.unwrap();
    assert!(!store.attempt_may_write(b.id, b.lease_token).await.unwrap(), "lease lost");
    // A cancelled campaign, then a deleted one.
    assert!(store.cancel_campaign(id).await.unwrap());
    assert!(!store.attempt_may_write(a.id, a.lease_token).await.unwrap(), "campaign cancelled");
    let id = store.create_campaign(new_campaign("x", QueueConfig::default()), stage("s0", 0, 1)).await.unwrap();
    let c = store.claim("w3", LONG).await.unwrap().unwrap();
    assert_eq!(c.campaign, id);
    assert!(store.attempt_may_write(c.id, c.lease_token).await.unwrap());
    store.delete_campaign_with_inputs(id).await.unwrap().unwrap();
    assert!(!store.attempt_may_write(c.id, c.lease_token).await.unwrap(), "campaign deleted");
}

async fn deleting_returns_the_inputs_no_other_campaign_names(store: JobStore, _url: String) {
    let first = campaign_naming("a", &["inputs/a.las", "inputs/shared.las", "outside/x.las"]);
    let a = store.create_campaign(first, stage("s0", 0, 1)).await.unwrap();
    let b = store.create_campaign(campaign_naming("b", &["inputs/shared.las"]), stage("s0", 0, 1)).await.unwrap();
    let keys: Vec<String> =
        ["inputs/a.las", "inputs/shared.las", "inputs/t.csv", "inputs/none"].iter().map(|k| k.to_string()).collect();
    let refs = store.input_references(&keys).await.unwrap();
    let mut expected = vec![
        InputReference { key: "inputs/a.las".into(), campaign: a },
        InputReference { key: "inputs/shared.las".into(), campaign: a },
        InputReference { key: "inputs/shared.las".into(), campaign: b },
        InputReference { key: "inputs/t.csv".into(), campaign: a },
        InputReference { key: "inputs/t.csv".into(), campaign: b },
    ];
    expected.sort_by(|x, y| (&x.key, x.campaign).cmp(&(&y.key, y.campaign)));
    assert_eq!(refs, expected);
    let prefix = store.object_prefix(a).await.unwrap().unwrap();
    let prefixes = store.object_prefixes().await.unwrap();
    assert!(prefixes.contains(&prefix.trim_end_matches('/').to_string()), "{prefixes:?}");
    // Only `a` names inputs/a.las; keys outside inputs/ are never returned.
    let deleted = store.delete_campaign_with_inputs(a).await.unwrap().unwrap();
    assert_eq!(deleted.object_prefix, prefix);
    assert_eq!(deleted.unreferenced_inputs, ["inputs/a.las"]);
    assert!(store.delete_campaign_with_inputs(a).await.unwrap().is_none());
    let deleted = store.delete_campaign_with_inputs(b).await.unwrap().unwrap();
    assert_eq!(deleted.unreferenced_inputs, ["inputs/shared.las", "inputs/t.csv"]);
    assert!(store.input_references(&keys).await.unwrap().is_empty());
    assert!(store.object_prefixes().await.unwrap().is_empty());
}
