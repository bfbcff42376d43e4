//! precimap's REST API (the contract is `api/openapi.yaml`) and the HTTP client the `submit`,
//! `status` and `results` commands use, and the status dashboard it serves at `/`.

pub mod admission;
pub mod client;
pub mod dashboard;
pub mod errors;
mod inputs;
pub mod listen;
pub mod ops;
pub mod server;
pub mod types;

pub use admission::{AdmissionLimits, Auth};
pub use client::{Client, ClientError};
pub use errors::ApiError;
pub use listen::{serve, ConnectionLimits};
pub use ops::MetricsRenderer;
pub use server::{app, ApiState};
pub use types::{CampaignStatus, ErrorBody, InputEntry, InputList, InputsDeleted, Problem, ResultEntry, Submitted};
