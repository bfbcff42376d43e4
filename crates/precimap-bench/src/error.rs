//! What can stop a benchmark.

use std::path::PathBuf;

#[derive(Debug, thiserror::Error)]
pub enum BenchError {
    #[error("simulating")]
    Simulate(#[source] precimap_sim::SimError),
    #[error(transparent)]
    Pipeline(#[from] precimap_pipeline::PipelineError),
    #[error(transparent)]
    Estimate(#[from] precimap_estimate::EstimateError),
    #[error(transparent)]
    Framework(#[from] precimap_framework::FrameworkError),
    #[error(transparent)]
    Jobs(#[from] precimap_jobs::JobError),
    #[error("PostgreSQL at {url}")]
    Postgres {
        url: String,
        #[source]
        source: precimap_jobs::JobError,
    },
    #[error(transparent)]
    Sparse(#[from] precimap_solve::sparse::SparseError),
    #[error(transparent)]
    Truth(#[from] precimap_sim::truth::TruthError),
    #[error("{} has more points than the strip", path.display())]
    TruthLonger { path: PathBuf },
    #[error("--parameters is not JSON")]
    ParametersJson(#[source] serde_json::Error),
    #[error("--parameters must be a JSON object, like a manifest's \"parameters\"")]
    ParametersNotObject,
    #[error("--parameters")]
    Parameters(#[source] serde_json::Error),
    #[error("--parameters: {0}")]
    ParameterValue(String),
    #[error(transparent)]
    ThreadPool(#[from] rayon::ThreadPoolBuildError),
    #[error(transparent)]
    Io(#[from] std::io::Error),
    #[error(transparent)]
    Json(#[from] serde_json::Error),
}
