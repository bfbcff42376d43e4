//! precimap's serverless job framework (docs/design/framework.md): a campaign becomes stages of tasks in the job
//! store's queue table; stateless executors claim one task at a time, run the same functions as
//! the in-process driver over objects in the object store, and commit their outputs through the
//! database, whose completing transaction also plans the next stage.

pub mod campaigns;
pub mod codec;
mod cpu;
pub mod error;
pub mod exec;
pub mod lifecycle;
pub mod metrics;
pub mod objects;
pub mod plan;
pub mod worker;

pub use campaigns::{
    default_queue, plan_local_upload, run_embedded, upload_local_inputs, CampaignLimits, EmbeddedOptions, Framework,
    RunStatus, SubmitError,
};
pub use error::{FrameworkError, TaskError};
pub use exec::{TaskContext, TrajectoryCache, WriteGate};
pub use lifecycle::Retention;
pub use objects::{is_temporary_key, validate_key, Objects, StoredObject};
pub use plan::CampaignPlanner;
pub use worker::{Executor, ExecutorConfig, WorkOutcome};
