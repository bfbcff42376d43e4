use std::path::{Path, PathBuf};

/// Errors of the framework's own machinery (store, database, configuration).
#[derive(Debug, thiserror::Error)]
pub enum FrameworkError {
    #[error("object store URL {url:?}: {message}")]
    BadStoreUrl { url: String, message: String },
    #[error("object key {key:?}: {message}")]
    BadKey { key: String, message: String },
    #[error("object {key}: {source}")]
    Store {
        key: String,
        #[source]
        source: object_store::Error,
    },
    #[error("{}: {source}", path.display())]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error(transparent)]
    Jobs(#[from] precimap_jobs::JobError),
    #[error("{0}")]
    Invalid(String),
    /// Inputs are written once: a second upload to the same key is refused, so a campaign never
    /// reads an input that changed under it.
    #[error("object {key} already exists; inputs are immutable: upload under a new key, or delete it first")]
    Exists { key: String },
    #[error("object {key} exceeds the upload limit of {limit} bytes")]
    TooLarge { key: String, limit: u64 },
    #[error(transparent)]
    Manifest(#[from] precimap_formats::ManifestError),
    #[error("campaign {id} {state}: {error}")]
    CampaignFailed { id: uuid::Uuid, state: String, error: String },
    #[error("internal: {0}")]
    Internal(String),
}

impl FrameworkError {
    pub fn store(key: &str, source: object_store::Error) -> Self {
        Self::Store { key: key.to_string(), source }
    }

    pub fn io(path: impl AsRef<Path>, source: std::io::Error) -> Self {
        Self::Io { path: path.as_ref().to_path_buf(), source }
    }

    pub fn is_not_found(&self) -> bool {
        matches!(self, Self::Store { source: object_store::Error::NotFound { .. }, .. })
    }
}

/// Why a task failed, and whether another attempt could succeed: bad input (a corrupt strip, a
/// trajectory that does not cover it) is `permanent` and fails the campaign at once; a store or
/// I/O hiccup is retried with back-off up to the campaign's maximum number of attempts.
#[derive(Debug, Clone, thiserror::Error)]
#[error("{message}")]
pub struct TaskError {
    pub permanent: bool,
    pub message: String,
}

impl TaskError {
    pub fn permanent(message: impl Into<String>) -> Self {
        Self { permanent: true, message: message.into() }
    }

    pub fn transient(e: impl std::fmt::Display) -> Self {
        Self { permanent: false, message: e.to_string() }
    }

    pub fn from_store(e: FrameworkError) -> Self {
        Self { permanent: e.is_not_found() || matches!(e, FrameworkError::BadKey { .. }), message: e.to_string() }
    }

    pub fn from_pipeline(e: precimap_pipeline::PipelineError) -> Self {
        use precimap_pipeline::PipelineError as P;
        let permanent = !matches!(e, P::Io { .. });
        Self { permanent, message: e.to_string() }
    }

    /// Names the input by its store key, the name the manifest gave it: every mention of `local`
    /// (the file store's copy or a scratch download, which mean nothing to the user) becomes the
    /// key, and the message starts with the key if it did not name it.
    pub fn naming(mut self, key: &str, local: &Path) -> Self {
        let local = local.display().to_string();
        if !local.is_empty() {
            self.message = self.message.replace(&local, key);
        }
        if !self.message.contains(key) {
            self.message = format!("{key}: {}", self.message);
        }
        self
    }
}
