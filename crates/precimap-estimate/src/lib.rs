//! Strip adjustment numerics (paper §5–6, docs/design/estimation.md), pure and free of I/O:
//!
//! - [`prepare`]: per strip — point geometry against the trajectory, scan image, normals,
//!   points keyed into tiles ([`chunk::TileChunk`]);
//! - [`tile::estimate_tile`]: the map task — latent map of one tile and its normal-equation
//!   blocks per trajectory, and on request the latent map itself ([`latent`]);
//! - [`solve::solve_trajectory`]: the reduce task — one exact block-tridiagonal Gauss–Newton
//!   step per trajectory with prior and smoothness; [`solve::extend_corrections`] continues the
//!   result over a trajectory's run-up and run-out for export.

pub mod anderson;
pub mod blocks;
pub mod calibration;
pub mod chunk;
pub mod control;
pub mod field;
pub mod latent;
pub mod prepare;
pub mod process;
pub mod solve;
pub mod stats;
pub mod tile;

pub use blocks::{merge_blocks, AnchorBlock, TrajectoryBlocks};
pub use calibration::{CalibrationNormals, TileCalibration};
pub use chunk::TileChunk;
pub use field::{solve_field, FieldEquations, FieldSolution, FieldTrajectory};
pub use latent::{LatentMapGrid, LatentSample};
pub use precimap_segment::{NormalMethod, DROPPED as DROPPED_COLUMN};
pub use prepare::{
    measurement_geometry, prepare_strip, prepare_strip_observed, GeometryCursor, PrepareError, PreparePhase,
    PrepareStats, PreparedStrip, ScanImage, SegmentParams, SegmentStats, StripContext, StripSamples, DROPPED_SEGMENT,
    NO_SEGMENT,
};
pub use prepare::{usable_share_problem, TIME_GAP_S};
pub use process::{CurvatureModel, CurvatureMoments};
pub use solve::{campaign_prior_weights, extend_corrections, solve_trajectory, TrajectorySolution};
pub use stats::{LatentStdMap, ResidualHistogram, TileStats};
pub use tile::{estimate_tile, estimate_tile_recording, EstimateError, LatentGather, TileEstimate, UsedPoint};
