//! precimap's REST API (the contract is `api/openapi.yaml`) and the HTTP client the `submit`,
//! `status` and `results` commands use, and the status dashboard it serves at `/`.

pub mod client;
pub mod dashboard;
mod inputs;
pub mod server;
pub mod types;

pub use client::{Client, ClientError};
pub use server::{app, ApiState, Auth};
pub use types::{CampaignStatus, ErrorBody, InputEntry, InputList, InputsDeleted, Problem, ResultEntry, Submitted};
