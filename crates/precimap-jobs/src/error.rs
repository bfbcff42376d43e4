//! Errors of the job store.

/// What went wrong in the job store.
#[derive(Debug, thiserror::Error)]
pub enum JobError {
    /// The lease token no longer holds the task (expired and rescued, cancelled, or already done).
    #[error("lease lost: the task is no longer held by this attempt")]
    LeaseLost,
    /// The campaign (or another named row) does not exist.
    #[error("not found: {0}")]
    NotFound(String),
    /// The database cannot be reached (connection refused/reset, pool timed out, server shutting
    /// down). Transient: the caller retries.
    #[error("database unavailable: {0}")]
    Unavailable(#[source] sqlx::Error),
    /// The database refused the transaction because of a concurrent one (deadlock, serialisation
    /// failure, SQLite busy). Transient: the caller retries.
    #[error("database conflict: {0}")]
    Conflict(#[source] sqlx::Error),
    /// Any other database error.
    #[error("database error: {0}")]
    Database(#[source] sqlx::Error),
    /// The schema migrations could not be applied.
    #[error("migration failed: {0}")]
    Migration(#[from] sqlx::migrate::MigrateError),
    /// The database URL is not one this store understands.
    #[error("bad database url `{url}`: {reason}")]
    BadUrl { url: String, reason: String },
    /// A caller-supplied value the store cannot accept.
    #[error("invalid argument: {0}")]
    Invalid(String),
    /// A stored row holds something this version cannot read (e.g. an unknown state).
    #[error("corrupt row: {0}")]
    Corrupt(String),
}

impl JobError {
    /// True for errors that go away by themselves (a database restart, a lock conflict): a worker
    /// retries these instead of dying.
    pub fn is_transient(&self) -> bool {
        matches!(self, JobError::Unavailable(_) | JobError::Conflict(_))
    }
}

impl From<sqlx::Error> for JobError {
    fn from(e: sqlx::Error) -> Self {
        match &e {
            sqlx::Error::Io(_)
            | sqlx::Error::Tls(_)
            | sqlx::Error::PoolTimedOut
            | sqlx::Error::PoolClosed
            | sqlx::Error::WorkerCrashed
            | sqlx::Error::Protocol(_) => JobError::Unavailable(e),
            sqlx::Error::Database(db) if db.try_downcast_ref::<sqlx::sqlite::SqliteError>().is_some() => {
                // SQLite BUSY (5) and LOCKED (6), also as extended codes (primary code in the low byte).
                match db.code().and_then(|c| c.parse::<i32>().ok()) {
                    Some(n) if n & 0xff == 5 || n & 0xff == 6 => JobError::Conflict(e),
                    _ => JobError::Database(e),
                }
            }
            sqlx::Error::Database(db) => match db.code().as_deref() {
                // PostgreSQL class 08 (connection exception), 57P01..57P03 (shutdown, cannot
                // connect now), 53300 (too many connections).
                Some(c) if c.starts_with("08") || c.starts_with("57P") || c == "53300" => JobError::Unavailable(e),
                // Serialisation failure, deadlock.
                Some("40001" | "40P01") => JobError::Conflict(e),
                _ => JobError::Database(e),
            },
            _ => JobError::Database(e),
        }
    }
}
