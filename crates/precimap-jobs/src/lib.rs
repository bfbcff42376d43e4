//! Job store and queue table of precimap's serverless job framework (docs/design/framework.md).
//!
//! The database is the commit point: a task writes its objects under keys of its own attempt,
//! then [`JobStore::complete`] records the keys and marks it done in one transaction guarded by
//! its lease token; the completion that closes a stage also plans and enqueues the next one.
//! Works on SQLite (one machine) and PostgreSQL (many executors).

mod error;
mod migrations;
mod store;
mod types;
mod url;

pub use error::JobError;
pub use store::{JobStore, StoreOptions};
pub use types::*;
pub use url::with_database;
