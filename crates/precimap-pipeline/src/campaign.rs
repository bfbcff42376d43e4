//! A campaign as the pipeline sees it: the validated manifest, every trajectory read, and every
//! strip resolved to a file inside the manifest's folder.

use crate::error::PipelineError;
use precimap_core::{Parameters, Trajectory, Vec3};
use precimap_formats::{load_manifest, read_trajectory_csv, resolve_uri, Manifest};
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
}

#[derive(Debug)]
pub struct StripEntry {
    pub id: String,
    pub path: PathBuf,
    pub trajectory: u32,
    pub lever_arm: Vec3,
}

#[derive(Debug)]
pub struct Campaign {
    pub name: String,
    pub manifest_path: PathBuf,
    pub params: Parameters,
    pub trajectories: Vec<TrajectoryEntry>,
    pub strips: Vec<StripEntry>,
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
        let mut trajectories = Vec::with_capacity(manifest.trajectories.len());
        for t in &manifest.trajectories {
            let path = resolve(&t.uri, &format!("trajectory {}", t.id))?;
            let data = read_trajectory_csv(&path)?;
            trajectories.push(TrajectoryEntry {
                id: t.id.clone(),
                path,
                data: Arc::new(data),
                mean_lever_arm: Vec3::zeros(),
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
            strips.push(StripEntry { id: s.id.clone(), path, trajectory: trajectory as u32, lever_arm });
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
        })
    }
}
