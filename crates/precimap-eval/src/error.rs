//! What can go wrong reading a campaign, its truth and a result.

use super::*;

#[derive(Debug, thiserror::Error)]
pub enum EvalError {
    #[error("truth folder {}: {source}; pass the campaign's truth folder (CAMP/truth)", path.display())]
    TruthDir {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error(transparent)]
    Manifest(#[from] ManifestError),
    #[error("{}: {what} {id:?}: {message}", manifest.display())]
    Uri { manifest: PathBuf, what: &'static str, id: String, message: String },
    #[error("{what} id {id:?} cannot name a file (it contains a path separator or is . or ..)")]
    BadId { what: &'static str, id: String },
    #[error(transparent)]
    Format(#[from] FormatError),
    #[error(transparent)]
    Truth(#[from] TruthError),
    #[error("strip {strip}: the {which} strip {} has {found} points but its truth {} has {expected}; every point of the input must be kept, in order", path.display(), truth.display())]
    PointCount { strip: String, which: &'static str, path: PathBuf, truth: PathBuf, found: u64, expected: u64 },
    #[error("strip {strip}: no result strip: neither {} nor {} exists", las.display(), laz.display())]
    MissingResultStrip { strip: String, las: PathBuf, laz: PathBuf },
    #[error("trajectory {trajectory}: no corrected trajectory {}", path.display())]
    MissingResultTrajectory { trajectory: String, path: PathBuf },
    #[error("strip {strip}: point {index} of {} has GPS time {found} but the input's has {expected}; result points must keep the input order", path.display())]
    PointOrder { strip: String, path: PathBuf, index: usize, found: f64, expected: f64 },
    #[error("strip {strip}: truth point {index} of {} has an invalid normal {normal:?}", path.display())]
    BadNormal { strip: String, path: PathBuf, index: u64, normal: [f32; 3] },
    #[error("{}: {message}", path.display())]
    Report { path: PathBuf, message: String },
    #[error("the latent map (OUT/latent/*.las) has a point in cell {cells:?}, more than 2³¹ cells of 10 cm from its lowest cell {origin:?}: a map point's coordinates are corrupt; re-export the map with `precimap run`")]
    LatentMapExtent { cells: [i64; 3], origin: [i64; 3] },
    #[error(transparent)]
    CorrectionsTable(#[from] TableError),
    #[error("{strips} strips: the latent map's evaluation tells at most {most} strips apart")]
    TooManyStrips { strips: usize, most: usize },
}
