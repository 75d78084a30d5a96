//! One error type for the library; the binary maps it to exit codes.

use std::path::PathBuf;

/// Everything that can go wrong, grouped by who is at fault.
///
/// `exit_code()` is the single place where the contract's exit codes are decided:
/// 2 for bad usage or bad input, 1 for work that ran but could not produce a result.
#[derive(Debug, thiserror::Error)]
pub enum Error {
    /// The file could not be read as the image needed (not FITS, truncated, absurd header...).
    #[error("{}: {reason}", crate::text::path(path))]
    BadInput { path: PathBuf, reason: String },

    /// A required header keyword is missing or unusable.
    #[error("{}: header: {reason}", crate::text::path(path))]
    BadHeader { path: PathBuf, reason: String },

    /// The command line or configuration asked for something impossible.
    #[error("{0}")]
    Usage(String),

    /// The alignment ran but found no usable result.
    #[error("alignment failed: {0}")]
    AlignmentFailed(String),

    /// An output cannot be created where it was asked for (read-only or missing directory, a
    /// file in the way): the command line's or configuration's to fix, found before any work.
    #[error("{}: cannot write here: {reason}", crate::text::path(path))]
    Unwritable { path: PathBuf, reason: String },

    /// Writing output (MCAP, CSV, PNG, FITS) failed.
    #[error("{}: {reason}", crate::text::path(path))]
    Output { path: PathBuf, reason: String },

    /// An output that would destroy what the user did not ask to lose (an input, a log), or
    /// would write where a running daemon writes.
    #[error("{}: {reason}", path.display())]
    Refused { path: PathBuf, reason: String },

    /// Other I/O on a named path.
    #[error("{}: {source}", crate::text::path(path))]
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

    pub fn unwritable(path: impl Into<PathBuf>, source: std::io::Error) -> Self {
        Error::Unwritable {
            path: path.into(),
            reason: source.to_string(),
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

    /// The one-line reason, without the path prefix (for a `/log` entry, which names the file).
    pub fn reason(&self) -> String {
        match self {
            Error::BadInput { reason, .. }
            | Error::Output { reason, .. }
            | Error::Unwritable { reason, .. } => reason.clone(),
            Error::BadHeader { reason, .. } => format!("header: {reason}"),
            Error::Io { source, .. } => source.to_string(),
            other => other.to_string(),
        }
    }

    /// The contract's exit code for this error: the one mapping from errors to exit codes.
    pub fn exit_code(&self) -> ExitCode {
        match self {
            Error::BadInput { .. }
            | Error::BadHeader { .. }
            | Error::Usage(_)
            | Error::Refused { .. }
            | Error::Unwritable { .. } => ExitCode::BadInput,
            Error::Io { source, .. } if source.kind() == std::io::ErrorKind::NotFound => {
                ExitCode::BadInput
            }
            Error::AlignmentFailed(_) | Error::Output { .. } | Error::Io { .. } => ExitCode::Failed,
        }
    }
}

/// The contract's exit codes (docs/contract.md), each with its one number: commands return
/// one, errors map to one ([`Error::exit_code`]), and the binary hands it to the system.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ExitCode {
    /// The work was done.
    Ok,
    /// The work ran but failed: nothing could be aligned, nothing measured, an output failed.
    Failed,
    /// Bad usage or bad input: one line on stderr names the file and the problem.
    BadInput,
}

impl ExitCode {
    /// The process's exit status.
    pub const fn code(self) -> i32 {
        match self {
            ExitCode::Ok => 0,
            ExitCode::Failed => 1,
            ExitCode::BadInput => 2,
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

/// Check, before any work, that the file `path` can be written: an existing file is opened
/// for writing (not truncated), a new one is created and removed again.
pub fn check_writable(path: &std::path::Path) -> Result<()> {
    let opened = if path.exists() {
        std::fs::OpenOptions::new()
            .write(true)
            .open(path)
            .map(|_| ())
    } else {
        std::fs::OpenOptions::new()
            .write(true)
            .create_new(true)
            .open(path)
            .and_then(|_| std::fs::remove_file(path))
    };
    opened.map_err(|e| Error::unwritable(path, e))
}

/// The name of [`check_writable_dir`]'s probe file, before its process id: a process killed
/// between creating and removing it leaves one, which whoever cleans the directory removes.
pub const WRITE_PROBE_PREFIX: &str = ".sunjitter-write-check-";

/// Check, before any work, that files can be created in the directory `dir`.
pub fn check_writable_dir(dir: &std::path::Path) -> Result<()> {
    let probe = dir.join(format!("{WRITE_PROBE_PREFIX}{}", std::process::id()));
    std::fs::OpenOptions::new()
        .write(true)
        .create_new(true)
        .open(&probe)
        .and_then(|_| std::fs::remove_file(&probe))
        .map_err(|e| Error::unwritable(dir, e))
}
