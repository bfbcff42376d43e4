use std::path::PathBuf;

/// Everything that can stop a campaign, each naming the file or object it concerns.
#[derive(Debug, thiserror::Error)]
pub enum PipelineError {
    #[error(transparent)]
    Manifest(#[from] precimap_formats::ManifestError),
    #[error(transparent)]
    Format(#[from] precimap_formats::FormatError),
    #[error("{what}: {message}")]
    Input { what: String, message: String },
    #[error("strip {strip} ({path}): {source}")]
    Prepare { strip: String, path: PathBuf, source: precimap_estimate::PrepareError },
    #[error("tile chunk {path}: {source}")]
    Chunk { path: PathBuf, source: precimap_estimate::chunk::ChunkError },
    #[error("{path}: {source}")]
    Io { path: PathBuf, source: std::io::Error },
    #[error("tile {tile}: {source}")]
    Estimate { tile: String, source: precimap_estimate::EstimateError },
    #[error("trajectory {trajectory}: the normal equations could not be solved ({source}); the campaign parameters (sigma values) are probably inconsistent")]
    Solve { trajectory: String, source: precimap_solve::SolveError },
    #[error("common-mode field: {0}; check parameters.common_mode_field_m and the sigma values")]
    Field(precimap_estimate::field::FieldError),
    /// Cannot happen for histories the driver recorded itself; reported, not a panic.
    #[error("Anderson acceleration: {0}")]
    Anderson(precimap_estimate::anderson::AndersonError),
}

impl PipelineError {
    pub fn io(path: impl Into<PathBuf>, source: std::io::Error) -> Self {
        Self::Io { path: path.into(), source }
    }
}
