//! The benchmarks' campaigns: simulated once into a cache folder and reused by later runs, and
//! parameter variants of them.

use crate::{BenchError, Progress};
use precimap_core::Parameters;
use std::path::{Path, PathBuf};

/// A simulated benchmark campaign, written once into `cache` and reused by later runs; returns its
/// folder and its manifest.
pub fn cached_campaign(
    cache: &Path,
    scale: precimap_sim::Scale,
    seed: u64,
    laz: bool,
    progress: Progress<'_>,
) -> Result<(PathBuf, PathBuf), BenchError> {
    let suffix = if laz { "-laz" } else { "" };
    let dir = cache.join(format!("{scale:?}-{seed}{suffix}").to_lowercase());
    let manifest = dir.join("campaign").join("manifest.json");
    if !manifest.exists() {
        progress(&format!("simulating the {scale:?} campaign into {} (cached for later runs)", dir.display()));
        let config = precimap_sim::SimConfig::for_scale(scale, seed);
        precimap_sim::simulate(&config, &dir.join("campaign"), laz).map_err(BenchError::Simulate)?;
    }
    Ok((dir, manifest))
}

/// `params` with the fields of the JSON object `changes` replaced (unknown fields and
/// out-of-range values are errors, as in a manifest).
pub fn with_changes(params: &Parameters, changes: &str) -> Result<Parameters, BenchError> {
    let changes: serde_json::Value = serde_json::from_str(changes).map_err(BenchError::ParametersJson)?;
    let serde_json::Value::Object(changes) = changes else {
        return Err(BenchError::ParametersNotObject);
    };
    let mut merged = serde_json::to_value(params)?;
    if let serde_json::Value::Object(fields) = &mut merged {
        fields.extend(changes);
    }
    let params: Parameters = serde_json::from_value(merged).map_err(BenchError::Parameters)?;
    if let Some(first) = params.problems().first() {
        return Err(BenchError::ParameterValue(first.to_string()));
    }
    Ok(params)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parameter_changes_are_checked_like_a_manifest() {
        let defaults = Parameters::default();
        let changed = with_changes(&defaults, r#"{"anchor_spacing_m": 1.0}"#).unwrap();
        assert_eq!(changed.anchor_spacing_m, 1.0);
        assert!(matches!(with_changes(&defaults, r#"{"anchor_spacing_m": -1.0}"#), Err(BenchError::ParameterValue(_))));
        assert!(matches!(with_changes(&defaults, "[1]"), Err(BenchError::ParametersNotObject)));
        assert!(matches!(with_changes(&defaults, "{"), Err(BenchError::ParametersJson(_))));
        assert!(matches!(with_changes(&defaults, r#"{"no_such_parameter": 1}"#), Err(BenchError::Parameters(_))));
    }
}
