//! Public file formats at the edge: campaign manifest, trajectory CSV, LAS/LAZ strips, and the
//! exported latent map (LAS with extra bytes).
//!
//! Everything read here comes from users, so nothing panics on file contents: every problem is an
//! error naming the file and the place in it (JSON path, line, point index) and what to do.
//! Files written here appear atomically (temporary + rename).

mod atomic;
pub mod crs;
mod error;
pub mod gps_time;
pub mod latent_map;
pub mod manifest;
pub mod navigation;
pub mod sbet;
pub mod segments;
mod sniff;
pub mod strip;
pub mod strip_crs;
pub mod trajectory;
pub mod trajectory_ascii;
pub mod trajectory_csv;

pub use error::FormatError;
pub use latent_map::{encode_latent_map, read_latent_map, write_latent_map};
pub use manifest::{
    load_manifest, parse_manifest, resolve_uri, CrsSpec, Manifest, ManifestError, ManifestProblem, ScannerSpec,
    StripRef, TrajectoryFormat, TrajectoryRef,
};
pub use segments::{decode_segments, encode_assignments, encode_segments, read_assignments, read_segments};
pub use strip::{
    read_strip, read_strip_with_ring, rewrite_strip, rewrite_strip_declaring, rewrite_strip_timed, strip_info,
    NewPoint, StripInfo, StripPoints, StripWriter,
};
pub use strip_crs::{DeclaredCrs, StripDeclarations};
pub use trajectory_csv::{read_trajectory_csv, write_trajectory_csv};
