//! Pure domain types shared by every precimap crate.
//!
//! Nothing in here does I/O: rotations and poses ([`geom`]), trajectories with arc length
//! ([`trajectory`]), the estimation parameters with the paper's defaults ([`params`]), tile keys
//! ([`tile`]), the per-anchor pose corrections ([`corrections`]), the scanners' mounting
//! calibration ([`calibration`]), the exported latent map's points ([`latent`]) and a fast hasher
//! for integer keys ([`hash`]).

pub mod calibration;
pub mod control;
pub mod corrections;
pub mod geom;
pub mod hash;
pub mod histogram;
pub mod latent;
pub mod params;
pub mod tile;
pub mod trajectory;

pub use calibration::{CalibrationLayout, CalibrationOptions, CalibrationUnknown, ScannerCalibration};
pub use control::{ControlOffset, ControlPlane, ControlRole, ControlSums, ControlTarget};
pub use corrections::{AnchorCovariance, ChangeHistogram, Correction, TrajectoryCorrections};
pub use geom::{Mat3, Vec3};
pub use latent::LatentMapPoint;
pub use params::{IterationStep, NormalSource, Parameters, ProcessModel, RingSource};
pub use tile::TileKey;
pub use trajectory::{Pose, Trajectory, TrajectoryError};
