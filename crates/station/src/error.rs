//! The station library's errors.

use std::path::PathBuf;

/// What can go wrong in the station outside a request (requests answer [`crate::api::ApiError`]).
#[derive(Debug, thiserror::Error)]
pub enum StationError {
    /// A key of the station file is wrong: the key, the value and what is allowed.
    #[error("{file}: {key}: {message}")]
    Config {
        /// The station file.
        file: String,
        /// The key's path in the file.
        key: String,
        /// What is wrong and what is allowed.
        message: String,
    },
    /// A file could not be read or written.
    #[error("{}: {source}", path.display())]
    Io {
        /// The file.
        path: PathBuf,
        /// The operating system's error.
        source: std::io::Error,
    },
    /// A file the station wrote is unreadable (its own state or keys).
    #[error("{}: {message}", path.display())]
    Corrupt {
        /// The file.
        path: PathBuf,
        /// What is wrong.
        message: String,
    },
    /// A key operation refused (unknown id, bad scope, bad duration).
    #[error("{0}")]
    Key(String),
    /// The server could not start (bind, TLS).
    #[error("{0}")]
    Serve(String),
    /// The station answered a client with an error, or could not be reached.
    #[error("{0}")]
    Client(String),
    /// An upload to the bucket failed (the object or file, and why).
    #[error("upload: {0}")]
    Upload(String),
}

impl StationError {
    /// An I/O error on `path`.
    pub fn io(path: impl Into<PathBuf>, source: std::io::Error) -> StationError {
        StationError::Io {
            path: path.into(),
            source,
        }
    }
}
