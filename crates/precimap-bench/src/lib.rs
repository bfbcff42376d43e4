//! precimap's benchmarks: the drivers behind `precimap bench …` and their fixtures (simulated
//! campaigns cached between runs, synthetic solver systems). Every figure they return can be
//! measured again with the same command; the product crates only expose what a benchmark needs
//! through their normal API.
//!
//! - [`estimate`]: one estimation iteration, single-threaded and on all cores;
//! - [`preprocess`]: strip pre-processing, per phase, with the segmentation against the truth;
//! - [`queue`]: the job store's claim + complete cycles, and [`overhead`]: the framework against
//!   the in-process driver;
//! - [`solve`]: the block-tridiagonal and the sparse field solvers on synthetic systems.
//!
//! The drivers return figures (serialisable, and as text with `text()`); progress notes go to
//! a [`Progress`] callback the caller chooses.

mod error;
pub mod estimate;
pub mod fixtures;
pub mod overhead;
pub mod preprocess;
pub mod queue;
mod rng;
pub mod solve;
pub mod system;

pub use error::BenchError;
pub use system::cpu_seconds;

/// Where a driver reports what it is doing while it runs (one line per call).
pub type Progress<'a> = &'a dyn Fn(&str);
