//! A campaign as the pipeline sees it: the validated manifest, every trajectory read into the
//! processing frame, and every strip resolved to a file inside the manifest's folder.

use crate::error::PipelineError;
use precimap_core::{ControlTarget, Parameters, Trajectory, Vec3};
use precimap_formats::crs::Georeference;
use precimap_formats::sbet::NavAccuracy;
use precimap_formats::trajectory::{load_trajectory, LoadedTrajectoryClock};
use precimap_formats::{load_manifest, resolve_uri, Manifest};
use std::path::{Path, PathBuf};
use std::sync::Arc;

#[derive(Debug)]
pub struct TrajectoryEntry {
    pub id: String,
    pub path: PathBuf,
    /// Shared: an executor's tasks read it from its trajectory cache without a copy.
    pub data: Arc<Trajectory>,
    /// Mean lever arm of the scanners whose strips use this trajectory: the corrected body pose
    /// is the one that moves these scan heads as the corrections say.
    pub mean_lever_arm: Vec3,
    /// What the trajectory's times count, to put its strips' times on the same scale.
    pub clock: LoadedTrajectoryClock,
    /// The processing frame of a field campaign (outputs are written in its CRS).
    pub georef: Option<Arc<Georeference>>,
    /// The per-epoch accuracy (SMRMSG) that shapes the anchors' prior ([`crate::prior`]), its
    /// times on the trajectory's scale.
    pub accuracy: Option<Arc<NavAccuracy>>,
    /// The accuracy file as the manifest names it (for messages); empty without one.
    pub accuracy_uri: String,
}

#[derive(Debug)]
pub struct StripEntry {
    pub id: String,
    pub path: PathBuf,
    pub trajectory: u32,
    pub lever_arm: Vec3,
    /// The index of its scanner among [`Campaign::scanners`].
    pub scanner: u32,
    /// The processing frame and the strip files' CRS of a field campaign.
    pub georef: Option<Arc<Georeference>>,
}

#[derive(Debug)]
pub struct Campaign {
    pub name: String,
    pub manifest_path: PathBuf,
    pub params: Parameters,
    pub trajectories: Vec<TrajectoryEntry>,
    pub strips: Vec<StripEntry>,
    /// Surveyed control and check targets in the processing frame.
    pub control: Vec<ControlTarget>,
    /// The scanners the strips use, by name (the calibration's order).
    pub scanners: Vec<String>,
}

impl Campaign {
    /// The layout of the calibration unknowns the parameters ask for.
    pub fn calibration_layout(&self) -> precimap_core::CalibrationLayout {
        self.params.calibration.layout(self.scanners.len())
    }

    /// Each strip's scanner index (the map tile tasks take).
    pub fn scanner_of_strip(&self) -> Vec<u32> {
        self.strips.iter().map(|s| s.scanner).collect()
    }
}

/// The georeference of a manifest with `$.crs`.
pub fn manifest_georeference(manifest: &Manifest) -> Result<Option<Arc<Georeference>>, PipelineError> {
    manifest
        .crs
        .as_ref()
        .map(|spec| {
            spec.georeference()
                .map(Arc::new)
                .map_err(|e| PipelineError::Input { what: "manifest $.crs".to_string(), message: e.to_string() })
        })
        .transpose()
}

/// The manifest's control targets in the processing frame: a field campaign's are converted from
/// the processing CRS's grid into its local frame.
pub fn control_targets(manifest: &Manifest) -> Result<Vec<ControlTarget>, PipelineError> {
    let Some(spec) = &manifest.control else { return Ok(Vec::new()) };
    let georef = manifest_georeference(manifest)?;
    spec.targets
        .iter()
        .enumerate()
        .map(|(i, t)| {
            t.target(|p| match &georef {
                Some(g) => g.frame.local_from_grid(p).map(|v| [v.x, v.y, v.z]).map_err(|e| PipelineError::Input {
                    what: format!("manifest $.control.targets[{i}]"),
                    message: format!("target {}: {e}; give its position in the processing CRS", t.id),
                }),
                None => Ok(p),
            })
        })
        .collect()
}

/// A strip's references followed: the index of the trajectory it was recorded on, and the lever
/// arm and index of the scanner that recorded it.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ResolvedStrip {
    pub trajectory: u32,
    pub lever_arm: [f64; 3],
    /// Index into [`ResolvedManifest::scanners`].
    pub scanner: u32,
}

/// What a manifest says once its references are followed, without reading any file: the part of
/// a campaign that the in-process driver ([`Campaign::from_manifest`]) and the job framework
/// (its campaign creation) share, resolved in one place so that both see the same campaign.
#[derive(Clone, Debug, PartialEq)]
pub struct ResolvedManifest {
    /// Per strip, in manifest order.
    pub strips: Vec<ResolvedStrip>,
    /// Per trajectory, in manifest order: the mean lever arm of the scanners whose strips use it
    /// (zero where no strip does). The corrected body pose is the one that moves these scan heads
    /// as the corrections say.
    pub mean_lever_arms: Vec<[f64; 3]>,
    /// Surveyed control and check targets in the processing frame ([`control_targets`]).
    pub control: Vec<ControlTarget>,
    /// The scanners at least one strip uses, by name in the manifest's (sorted) order.
    pub scanners: Vec<String>,
}

impl ResolvedManifest {
    /// Follows `manifest`'s references: a strip naming an unknown trajectory or scanner is an
    /// input error (a validated manifest has none), and so is a control target outside the
    /// processing CRS.
    pub fn new(manifest: &Manifest) -> Result<Self, PipelineError> {
        let mut lever_sums = vec![([0.0f64; 3], 0usize); manifest.trajectories.len()];
        let scanners: Vec<String> = manifest
            .scanners
            .keys()
            .filter(|name| manifest.strips.iter().any(|s| &s.scanner == *name))
            .cloned()
            .collect();
        let mut strips = Vec::with_capacity(manifest.strips.len());
        for s in &manifest.strips {
            let trajectory = manifest.trajectories.iter().position(|t| t.id == s.trajectory).ok_or_else(|| {
                PipelineError::Input {
                    what: format!("strip {}", s.id),
                    message: format!("unknown trajectory {}", s.trajectory),
                }
            })?;
            let scanner = manifest.scanners.get(&s.scanner).ok_or_else(|| PipelineError::Input {
                what: format!("strip {}", s.id),
                message: format!("unknown scanner {}", s.scanner),
            })?;
            let lever_arm = scanner.lever_arm_m;
            let sum = &mut lever_sums[trajectory];
            for k in 0..3 {
                sum.0[k] += lever_arm[k];
            }
            sum.1 += 1;
            let scanner_index = scanners.iter().position(|n| n == &s.scanner).unwrap_or_default() as u32;
            strips.push(ResolvedStrip { trajectory: trajectory as u32, lever_arm, scanner: scanner_index });
        }
        let mean_lever_arms =
            lever_sums.into_iter().map(|(sum, n)| if n > 0 { sum.map(|v| v / n as f64) } else { [0.0; 3] }).collect();
        Ok(Self { strips, mean_lever_arms, control: control_targets(manifest)?, scanners })
    }
}

impl Campaign {
    pub fn load(manifest_path: &Path) -> Result<Self, PipelineError> {
        let manifest = load_manifest(manifest_path)?;
        let dir = manifest_path.parent().unwrap_or(Path::new("."));
        Self::from_manifest(manifest, manifest_path, dir)
    }

    pub fn from_manifest(manifest: Manifest, manifest_path: &Path, dir: &Path) -> Result<Self, PipelineError> {
        let resolve = |uri: &str, what: &str| {
            resolve_uri(dir, uri).map_err(|problem| PipelineError::Input {
                what: what.to_string(),
                message: format!("uri {uri:?}: {problem}"),
            })
        };
        let georef = manifest_georeference(&manifest)?;
        let mut trajectories = Vec::with_capacity(manifest.trajectories.len());
        for t in &manifest.trajectories {
            let what = format!("trajectory {}", t.id);
            let path = resolve(&t.uri, &what)?;
            let accuracy = t.accuracy_uri.as_deref().map(|u| resolve(u, &what)).transpose()?;
            let frame = georef.as_deref().map(|g| &g.frame);
            let loaded = load_trajectory(&path, t, accuracy.as_deref(), frame, manifest.gps_week)?;
            if let Some(a) = &loaded.accuracy {
                let [h_median, h_max, heading_median, heading_max] = a.summary();
                tracing::info!(
                    trajectory = %t.id,
                    horizontal_sigma_median_m = h_median,
                    horizontal_sigma_max_m = h_max,
                    heading_sigma_median_deg = heading_median,
                    heading_sigma_max_deg = heading_max,
                    "trajectory accuracy file read: it shapes the anchors' prior"
                );
            }
            trajectories.push(TrajectoryEntry {
                id: t.id.clone(),
                path,
                clock: loaded.clock(),
                data: Arc::new(loaded.trajectory),
                mean_lever_arm: Vec3::zeros(),
                georef: georef.clone(),
                accuracy: loaded.accuracy.map(Arc::new),
                accuracy_uri: t.accuracy_uri.clone().unwrap_or_default(),
            });
        }
        let strip_paths = manifest
            .strips
            .iter()
            .map(|s| resolve(&s.uri, &format!("strip {}", s.id)))
            .collect::<Result<Vec<_>, _>>()?;
        let resolved = ResolvedManifest::new(&manifest)?;
        for (t, mean) in trajectories.iter_mut().zip(&resolved.mean_lever_arms) {
            t.mean_lever_arm = Vec3::from(*mean);
        }
        let strips = manifest
            .strips
            .iter()
            .zip(strip_paths)
            .zip(&resolved.strips)
            .map(|((s, path), r)| StripEntry {
                id: s.id.clone(),
                path,
                trajectory: r.trajectory,
                lever_arm: Vec3::from(r.lever_arm),
                scanner: r.scanner,
                georef: georef.clone(),
            })
            .collect();
        Ok(Self {
            name: manifest.name.clone(),
            manifest_path: manifest_path.to_path_buf(),
            params: manifest.parameters.clone(),
            trajectories,
            strips,
            control: resolved.control,
            scanners: resolved.scanners,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn manifest(strips: serde_json::Value) -> Manifest {
        serde_json::from_value(serde_json::json!({
            "name": "lever arms",
            "scanners": {
                "left": { "lever_arm_m": [0.0, 0.5, 0.3] },
                "right": { "lever_arm_m": [0.0, -0.5, 0.25] },
                "roof": { "lever_arm_m": [1.0, 2.0, 3.0] },
            },
            "trajectories": [
                { "id": "a", "uri": "a.csv" },
                { "id": "b", "uri": "b.csv" },
                { "id": "c", "uri": "c.csv" },
            ],
            "strips": strips,
        }))
        .unwrap()
    }

    /// Each strip gets its trajectory's index and its scanner's lever arm and index among the
    /// scanners in use (by name); a trajectory's mean lever arm averages its strips' scanners
    /// (zero for a trajectory no strip uses).
    #[test]
    fn strips_follow_their_references_and_trajectories_average_their_scanners() {
        let m = manifest(serde_json::json!([
            { "id": "s1", "uri": "s1.las", "trajectory": "a", "scanner": "left" },
            { "id": "s2", "uri": "s2.las", "trajectory": "b", "scanner": "roof" },
            { "id": "s3", "uri": "s3.las", "trajectory": "a", "scanner": "right" },
        ]));
        let r = ResolvedManifest::new(&m).unwrap();
        let strip = |trajectory, lever_arm, scanner| ResolvedStrip { trajectory, lever_arm, scanner };
        assert_eq!(
            r.strips,
            vec![strip(0, [0.0, 0.5, 0.3], 0), strip(1, [1.0, 2.0, 3.0], 2), strip(0, [0.0, -0.5, 0.25], 1)]
        );
        assert_eq!(r.scanners, ["left", "right", "roof"]);
        assert_eq!(r.mean_lever_arms, vec![[0.0, 0.0, 0.275], [1.0, 2.0, 3.0], [0.0; 3]]);
        assert!(r.control.is_empty());
    }

    #[test]
    fn an_unknown_scanner_or_trajectory_is_an_input_error() {
        for (trajectory, scanner, expected) in
            [("a", "nadir", "unknown scanner nadir"), ("d", "left", "unknown trajectory d")]
        {
            let m = manifest(serde_json::json!([
                { "id": "s1", "uri": "s1.las", "trajectory": trajectory, "scanner": scanner },
            ]));
            let e = ResolvedManifest::new(&m).unwrap_err().to_string();
            assert!(e.contains("strip s1") && e.contains(expected), "{e}");
        }
    }
}
