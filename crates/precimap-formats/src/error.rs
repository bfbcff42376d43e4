//! The one error type for trajectory CSV and LAS/LAZ problems. Every variant names the file; line-
//! and point-level variants also say where in it, so a user can go straight to the bad record.

use std::path::PathBuf;

#[derive(Debug, thiserror::Error)]
pub enum FormatError {
    /// The operating system refused (open, read, write, rename).
    #[error("{}: cannot {action}: {source}", path.display())]
    Io {
        path: PathBuf,
        action: &'static str,
        #[source]
        source: std::io::Error,
    },
    /// A bad line of a text file (1-based line number).
    #[error("{}:{line}: {message}", path.display())]
    Line { path: PathBuf, line: usize, message: String },
    /// A bad point of a LAS/LAZ file (0-based index in file order).
    #[error("{}: point {index}: {message}", path.display())]
    Point { path: PathBuf, index: u64, message: String },
    /// A problem with the file as a whole (header, point format, too few records, bad arguments).
    #[error("{}: {message}", path.display())]
    File { path: PathBuf, message: String },
}

impl FormatError {
    /// The file the error is about.
    pub fn path(&self) -> &std::path::Path {
        match self {
            Self::Io { path, .. } | Self::Line { path, .. } | Self::Point { path, .. } | Self::File { path, .. } => {
                path
            }
        }
    }

    pub(crate) fn io(path: &std::path::Path, action: &'static str, source: std::io::Error) -> Self {
        Self::Io { path: path.to_path_buf(), action, source }
    }

    pub(crate) fn file(path: &std::path::Path, message: impl Into<String>) -> Self {
        Self::File { path: path.to_path_buf(), message: message.into() }
    }
}
