//! sunjitter's errors as Python exceptions (classes defined in `sunjitter/_errors.py`), each
//! carrying the command line's one-line message.

use pyo3::prelude::*;
use sunjitter_core::Error;

/// The exception class of `sunjitter._errors` that stands for `e`, and its arguments.
fn class_of(e: &Error) -> &'static str {
    match e {
        Error::BadInput { path, .. } | Error::BadHeader { path, .. } if is_missing(path) => {
            "InputNotFoundError"
        }
        Error::BadInput { .. } | Error::BadHeader { .. } => "BadInputError",
        Error::Usage(_) => "UsageError",
        Error::AlignmentFailed(_) => "AlignmentFailedError",
        Error::Io { source, .. } if source.kind() == std::io::ErrorKind::NotFound => {
            "InputNotFoundError"
        }
        Error::Refused { .. } => "OutputRefusedError",
        Error::Unwritable { .. } | Error::Output { .. } | Error::Io { .. } => "SunjitterIOError",
    }
}

/// Whether `path` names nothing (the reader's "cannot open" of a file that is not there);
/// never for the names the package gives pixels held in memory (`<frame array>`, `<map>`).
fn is_missing(path: &std::path::Path) -> bool {
    let text = path.to_string_lossy();
    let in_memory = text.starts_with('<') && text.ends_with('>');
    !text.is_empty()
        && !in_memory
        && matches!(std::fs::symlink_metadata(path), Err(e) if e.kind() == std::io::ErrorKind::NotFound)
}

/// `e` as the Python exception users catch: its message is the line the command prints
/// (without the `sunjitter: ` prefix); an OS error also carries `errno` and `filename`.
pub fn to_py(e: &Error) -> PyErr {
    let message = sunjitter_core::text::escape(&e.to_string()).into_owned();
    Python::attach(|py| {
        let made = (|| -> PyResult<PyErr> {
            let class = py.import("sunjitter._errors")?.getattr(class_of(e))?;
            let value = match e {
                Error::BadInput { path, .. } | Error::BadHeader { path, .. }
                    if is_missing(path) =>
                {
                    class.call1((libc::ENOENT, message.clone(), path.display().to_string()))?
                }
                Error::Io { path, source, .. } => {
                    let errno = source.raw_os_error();
                    class.call1((errno, message.clone(), path.display().to_string()))?
                }
                Error::Unwritable { path, .. }
                | Error::Output { path, .. }
                | Error::Refused { path, .. } => {
                    class.call1((None::<i32>, message.clone(), path.display().to_string()))?
                }
                _ => class.call1((message.clone(),))?,
            };
            Ok(PyErr::from_value(value))
        })();
        made.unwrap_or_else(|err| err)
    })
}

/// A panic that reached the boundary, as a `SunjitterError` (never a `PanicException`).
pub fn internal(what: &str, panic: Box<dyn std::any::Any + Send>) -> PyErr {
    let detail = panic
        .downcast_ref::<&str>()
        .map(|s| s.to_string())
        .or_else(|| panic.downcast_ref::<String>().cloned())
        .unwrap_or_default();
    let message = format!("internal error in {what}: {detail} (please report it)");
    Python::attach(|py| {
        py.import("sunjitter._errors")
            .and_then(|m| m.getattr("SunjitterError"))
            .and_then(|c| c.call1((message,)))
            .map(PyErr::from_value)
            .unwrap_or_else(|e| e)
    })
}

/// `Result<T, Error>` → `PyResult<T>`.
pub trait IntoPy<T> {
    fn py_err(self) -> PyResult<T>;
}

impl<T> IntoPy<T> for sunjitter_core::Result<T> {
    fn py_err(self) -> PyResult<T> {
        self.map_err(|e| to_py(&e))
    }
}
