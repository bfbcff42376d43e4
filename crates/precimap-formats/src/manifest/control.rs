//! `$.control`: surveyed control and check targets (`precimap_core::control`).

use super::{child, describe, id_problem, Checker};
use precimap_core::control::{ControlPlane, ControlRole, ControlTarget};
use serde::{Deserialize, Serialize};
use serde_json::{Map, Value};
use std::collections::HashMap;

/// `$.control`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ControlSpec {
    /// EPSG code of the targets' coordinates: the processing CRS (the only one accepted), for a
    /// campaign with `$.crs`; absent in a campaign in a local frame.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub crs: Option<u32>,
    pub targets: Vec<ControlTargetSpec>,
}

/// One target as the manifest states it.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ControlTargetSpec {
    pub id: String,
    /// x, y (the CRS's easting and northing, or the local frame's) and the height in the
    /// strips' height system, metres.
    pub position_m: [f64; 3],
    /// Standard deviation: one number for every axis, or `[x, y, z]`.
    pub sigma_m: Sigma,
    #[serde(default)]
    pub role: ControlRole,
    /// A surveyed planar patch instead of a point.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub plane: Option<ControlPlane>,
}

/// A standard deviation for every axis, or one per axis.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(untagged)]
pub enum Sigma {
    All(f64),
    PerAxis([f64; 3]),
}

impl Sigma {
    pub fn per_axis(self) -> [f64; 3] {
        match self {
            Sigma::All(s) => [s; 3],
            Sigma::PerAxis(s) => s,
        }
    }
}

impl ControlTargetSpec {
    /// The target with its position and plane normal mapped by `to_frame` (the identity in a
    /// local-frame campaign); the normal is normalised.
    pub fn target<E>(&self, to_frame: impl Fn([f64; 3]) -> Result<[f64; 3], E>) -> Result<ControlTarget, E> {
        let position = to_frame(self.position_m)?;
        let plane = match self.plane {
            Some(p) => {
                let tip = to_frame([0, 1, 2].map(|a| self.position_m[a] + p.normal[a]))?;
                let n = [0, 1, 2].map(|a| tip[a] - position[a]);
                let norm = (n[0] * n[0] + n[1] * n[1] + n[2] * n[2]).sqrt();
                Some(ControlPlane { normal: n.map(|v| v / norm), radius_m: p.radius_m })
            }
            None => None,
        };
        Ok(ControlTarget { id: self.id.clone(), position, sigma_m: self.sigma_m.per_axis(), role: self.role, plane })
    }
}

/// The most targets a manifest may list.
pub const MAX_CONTROL_TARGETS: usize = 100_000;
/// The largest target standard deviation, metres: beyond it a target cannot help a map precise
/// to millimetres.
pub const MAX_CONTROL_SIGMA_M: f64 = 1.0;
/// The largest radius of a planar target, metres.
pub const MAX_PLANE_RADIUS_M: f64 = 50.0;

const CONTROL_FIELDS: [&str; 2] = ["crs", "targets"];
const TARGET_FIELDS: [&str; 5] = ["id", "position_m", "sigma_m", "role", "plane"];
const PLANE_FIELDS: [&str; 2] = ["normal", "radius_m"];

impl Checker {
    /// `$.control`; `processing` is the usable `$.crs.processing`, if any.
    pub(super) fn control(&mut self, top: &Map<String, Value>, processing: Option<u32>) {
        let Some(v) = top.get("control") else { return };
        let Some(map) = self.object("$.control", v, &CONTROL_FIELDS.map(String::from)) else { return };
        match (map.get("crs"), processing) {
            (Some(c), Some(p)) => {
                if c.as_u64() != Some(u64::from(p)) {
                    self.push(
                        "$.control.crs",
                        format!(
                            "is {}, but control targets must be in the processing CRS (EPSG {p}); convert them, or \
                             omit the field",
                            describe(c)
                        ),
                    );
                }
            }
            (Some(_), None) => self.push(
                "$.control.crs",
                "a CRS for the targets needs $.crs (the processing CRS they must be in); remove it for a campaign in \
                 a local frame",
            ),
            (None, _) => {}
        }
        let Some(targets) = self.required(
            "$.control",
            map,
            "targets",
            "an array of {\"id\", \"position_m\": [x, y, z], \"sigma_m\", \"role\": \"control\" or \"check\"}",
        ) else {
            return;
        };
        let Some(items) = targets.as_array() else { return self.wrong_type("$.control.targets", targets, "an array") };
        if items.len() > MAX_CONTROL_TARGETS {
            self.push(
                "$.control.targets",
                format!("lists {} targets; at most {MAX_CONTROL_TARGETS} are accepted", items.len()),
            );
            return;
        }
        let mut seen: HashMap<&str, usize> = HashMap::new();
        for (i, item) in items.iter().enumerate() {
            let path = format!("$.control.targets[{i}]");
            let Some(t) = self.object(&path, item, &TARGET_FIELDS.map(String::from)) else { continue };
            if let Some(id) = self.required_str(&path, t, "id", "the surveyor's name of the target, e.g. \"GCP-017\"") {
                if let Some(m) = id_problem(id, "target id") {
                    self.push(&child(&path, "id"), m);
                } else if let Some(first) = seen.insert(id, i) {
                    self.push(
                        &child(&path, "id"),
                        format!("duplicate target id {id:?} (also $.control.targets[{first}]); give every target a unique id"),
                    );
                }
            }
            if let Some(p) = self.required(&path, t, "position_m", "[x, y, z] in metres") {
                self.vec3(&child(&path, "position_m"), p, "metres", 1e8);
            }
            if let Some(s) = self.required(&path, t, "sigma_m", "the survey's standard deviation, e.g. 0.005") {
                self.sigma(&child(&path, "sigma_m"), s);
            }
            if let Some(r) = t.get("role") {
                if serde_json::from_value::<ControlRole>(r.clone()).is_err() {
                    self.push(
                        &child(&path, "role"),
                        format!("expected \"control\" or \"check\", found {}", describe(r)),
                    );
                }
            }
            if let Some(p) = t.get("plane") {
                self.plane(&child(&path, "plane"), p);
            }
        }
    }

    fn sigma(&mut self, path: &str, v: &Value) {
        let values: Vec<f64> = match v {
            Value::Number(n) => n.as_f64().into_iter().collect(),
            Value::Array(a) if a.len() == 3 => a.iter().filter_map(Value::as_f64).collect(),
            _ => Vec::new(),
        };
        let expected = if v.is_array() { 3 } else { 1 };
        if values.len() != expected {
            return self.push(
                path,
                format!("expected a standard deviation in metres or [x, y, z] of them, found {}", describe(v)),
            );
        }
        if values.iter().any(|s| !(s.is_finite() && *s > 0.0 && *s <= MAX_CONTROL_SIGMA_M)) {
            self.push(
                path,
                format!(
                    "standard deviations must be above 0 and at most {MAX_CONTROL_SIGMA_M} m, found {}",
                    describe(v)
                ),
            );
        }
    }

    fn plane(&mut self, path: &str, v: &Value) {
        let Some(p) = self.object(path, v, &PLANE_FIELDS.map(String::from)) else { return };
        if let Some(n) = self.required(path, p, "normal", "the patch's normal [x, y, z], e.g. [0, 0, 1]") {
            self.vec3(&child(path, "normal"), n, "a direction", 1e6);
            let len = n.as_array().map(|a| a.iter().filter_map(Value::as_f64).map(|x| x * x).sum::<f64>().sqrt());
            if len.is_some_and(|l| l.is_nan() || l <= 1e-6) {
                self.push(&child(path, "normal"), "is zero; give the patch's normal direction, e.g. [0, 0, 1]");
            }
        }
        if let Some(r) = self.required(path, p, "radius_m", "the patch's radius in metres, e.g. 1.0") {
            if r.as_f64().is_none_or(|r| !(r > 0.0 && r <= MAX_PLANE_RADIUS_M)) {
                self.push(
                    &child(path, "radius_m"),
                    format!("expected a radius above 0 and at most {MAX_PLANE_RADIUS_M} m, found {}", describe(r)),
                );
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use crate::manifest::{parse_manifest, ManifestError};
    use serde_json::json;

    fn manifest(control: serde_json::Value) -> Result<crate::Manifest, ManifestError> {
        let v = json!({
            "name": "c",
            "scanners": {"left": {"lever_arm_m": [0, 0, 0]}},
            "trajectories": [{"id": "t", "uri": "t.csv"}],
            "strips": [{"id": "s", "trajectory": "t", "scanner": "left", "uri": "s.las"}],
            "control": control,
        });
        parse_manifest(&v.to_string())
    }

    fn problems(control: serde_json::Value) -> Vec<String> {
        match manifest(control) {
            Err(ManifestError::Invalid { problems, .. }) => problems.iter().map(ToString::to_string).collect(),
            other => panic!("expected problems, got {other:?}"),
        }
    }

    #[test]
    fn targets_parse_with_defaults_and_planes() {
        let m = manifest(json!({"targets": [
            {"id": "G1", "position_m": [1, 2, 3], "sigma_m": 0.005},
            {"id": "C1", "position_m": [4, 5, 6], "sigma_m": [0.01, 0.01, 0.005], "role": "check"},
            {"id": "P1", "position_m": [7, 8, 9], "sigma_m": 0.003, "plane": {"normal": [0, 0, 2], "radius_m": 1.5}},
        ]}))
        .unwrap();
        let c = m.control.unwrap();
        let targets: Vec<_> = c.targets.iter().map(|t| t.target(Ok::<_, ()>).unwrap()).collect();
        assert_eq!(targets[0].sigma_m, [0.005; 3]);
        assert_eq!(targets[0].role, precimap_core::ControlRole::Control);
        assert_eq!(targets[1].role, precimap_core::ControlRole::Check);
        assert_eq!(targets[2].plane.unwrap().normal, [0.0, 0.0, 1.0]);
    }

    #[test]
    fn every_bad_target_is_named_with_its_path() {
        let p = problems(json!({"crs": 25832, "targets": [
            {"id": "G1", "position_m": [1, 2], "sigma_m": 0},
            {"id": "G1", "position_m": [1, 2, 3], "sigma_m": [0.1, 0.1], "role": "reference"},
            {"id": "bad/id", "position_m": [1, 2, 3], "sigma_m": 0.01, "plane": {"normal": [0, 0, 0], "radius_m": -1}},
            {"position_m": [1, 2, 3], "sigma_m": 0.01, "elevation": 3},
        ]}));
        let has = |path: &str, text: &str| p.iter().any(|x| x.starts_with(path) && x.contains(text));
        assert!(has("$.control.crs", "needs $.crs"), "{p:#?}");
        assert!(has("$.control.targets[0].position_m", "3 numbers"), "{p:#?}");
        assert!(has("$.control.targets[0].sigma_m", "above 0"), "{p:#?}");
        assert!(has("$.control.targets[1].id", "duplicate target id"), "{p:#?}");
        assert!(has("$.control.targets[1].sigma_m", "[x, y, z]"), "{p:#?}");
        assert!(has("$.control.targets[1].role", "\"control\" or \"check\""), "{p:#?}");
        assert!(has("$.control.targets[2].id", "not a safe file name"), "{p:#?}");
        assert!(has("$.control.targets[2].plane.normal", "is zero"), "{p:#?}");
        assert!(has("$.control.targets[2].plane.radius_m", "above 0"), "{p:#?}");
        assert!(has("$.control.targets[3].id", "missing required field"), "{p:#?}");
        assert!(has("$.control.targets[3].elevation", "unknown field"), "{p:#?}");
    }
}
