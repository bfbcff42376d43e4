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
        let mut strips = Vec::with_capacity(manifest.strips.len());
        let mut lever_sums = vec![(Vec3::zeros(), 0usize); trajectories.len()];
        for s in &manifest.strips {
            let path = resolve(&s.uri, &format!("strip {}", s.id))?;
            // The manifest validation guarantees both references exist.
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
            let lever_arm = Vec3::from(scanner.lever_arm_m);
            lever_sums[trajectory].0 += lever_arm;
            lever_sums[trajectory].1 += 1;
            strips.push(StripEntry {
                id: s.id.clone(),
                path,
                trajectory: trajectory as u32,
                lever_arm,
                georef: georef.clone(),
            });
        }
        for (t, (sum, n)) in trajectories.iter_mut().zip(lever_sums) {
            if n > 0 {
                t.mean_lever_arm = sum / n as f64;
            }
        }
        Ok(Self {
            name: manifest.name.clone(),
            manifest_path: manifest_path.to_path_buf(),
            params: manifest.parameters.clone(),
            trajectories,
            strips,
            control: control_targets(&manifest)?,
        })
    }
}
