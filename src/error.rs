//! One error type for the library; the binary maps it to exit codes.

use std::path::PathBuf;

/// Everything that can go wrong, grouped by who is at fault.
///
/// `exit_code()` is the single place where the contract's exit codes are decided:
/// 2 for bad usage or bad input, 1 for work that ran but could not produce a result.
#[derive(Debug, thiserror::Error)]
pub enum Error {
    /// The file could not be read as the image we need (not FITS, truncated, absurd header...).
    #[error("{}: {reason}", path.display())]
    BadInput { path: PathBuf, reason: String },

    /// A required header keyword is missing or unusable.
    #[error("{}: header: {reason}", path.display())]
    BadHeader { path: PathBuf, reason: String },

    /// The command line or configuration asked for something impossible.
    #[error("{0}")]
    Usage(String),

    /// The alignment ran but found no usable result.
    #[error("alignment failed: {0}")]
    AlignmentFailed(String),

    /// Writing output (MCAP, CSV, PNG, FITS) failed.
    #[error("{}: {reason}", path.display())]
    Output { path: PathBuf, reason: String },

    /// Other I/O on a named path.
    #[error("{}: {source}", path.display())]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
}

impl Error {
    pub fn bad_input(path: impl Into<PathBuf>, reason: impl Into<String>) -> Self {
        Error::BadInput {
            path: path.into(),
            reason: reason.into(),
        }
    }

    pub fn bad_header(path: impl Into<PathBuf>, reason: impl Into<String>) -> Self {
        Error::BadHeader {
            path: path.into(),
            reason: reason.into(),
        }
    }

    pub fn output(path: impl Into<PathBuf>, reason: impl Into<String>) -> Self {
        Error::Output {
            path: path.into(),
            reason: reason.into(),
        }
    }

    pub fn io(path: impl Into<PathBuf>, source: std::io::Error) -> Self {
        Error::Io {
            path: path.into(),
            source,
        }
    }

    /// An I/O error that says nothing about the file: the same read may succeed later.
    pub fn is_transient(&self) -> bool {
        matches!(self, Error::Io { source, .. } if transient_io(source))
    }

    /// The contract's exit code for this error.
    pub fn exit_code(&self) -> i32 {
        match self {
            Error::BadInput { .. } | Error::BadHeader { .. } | Error::Usage(_) => 2,
            Error::Io { source, .. } if source.kind() == std::io::ErrorKind::NotFound => 2,
            Error::AlignmentFailed(_) | Error::Output { .. } | Error::Io { .. } => 1,
        }
    }
}

/// Errors of the moment (out of file descriptors or memory, interrupted, busy, timed out)
/// rather than of the file: worth retrying.
pub fn transient_io(e: &std::io::Error) -> bool {
    use std::io::ErrorKind::*;
    matches!(
        e.kind(),
        Interrupted | WouldBlock | OutOfMemory | ResourceBusy | TimedOut
    ) || matches!(
        e.raw_os_error(),
        Some(
            libc::EMFILE | libc::ENFILE | libc::ENOBUFS | libc::ENOMEM | libc::EAGAIN | libc::EINTR
        )
    )
}

pub type Result<T, E = Error> = std::result::Result<T, E>;
