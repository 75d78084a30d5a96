//! Running the engine with the interpreter free: the work runs on a thread of its own while
//! the calling thread waits detached from Python, waking every few tens of milliseconds to
//! run Python's signal handlers (so Ctrl-C raises `KeyboardInterrupt`), report progress and
//! hand the log lines on to Python's `logging`.

use pyo3::prelude::*;
use std::sync::mpsc;
use std::time::Duration;

/// How often the waiting thread looks at signals and progress.
const TICK: Duration = Duration::from_millis(50);

/// What the caller does when Ctrl-C arrives while the work runs.
pub enum OnInterrupt {
    /// Raise `KeyboardInterrupt` at once; the work finishes on its own thread, unseen.
    Abandon,
    /// Call `stop` (which asks the work to finish cleanly), wait for the work, then raise.
    Stop(Box<dyn FnOnce() + Send>),
}

/// Run `work` on its own thread; `tick` is called with the interpreter attached at every
/// wake-up and once at the end. Ctrl-C, or an error from `tick` (a progress callback's),
/// ends the wait as `on_interrupt` says. A panic in `work` becomes a `SunjitterError` naming
/// `what`.
pub fn run<T: Send + 'static>(
    py: Python<'_>,
    what: &str,
    work: impl FnOnce() -> T + Send + 'static,
    on_interrupt: OnInterrupt,
    mut tick: impl FnMut(Python<'_>) -> PyResult<()>,
) -> PyResult<T> {
    let (tx, mut rx) = mpsc::channel();
    std::thread::Builder::new()
        // "sunjitter align", …: the kernel keeps 15 bytes of a thread's name.
        .name(format!("sunjitter {what}"))
        .spawn(move || {
            let outcome = std::panic::catch_unwind(std::panic::AssertUnwindSafe(work));
            let _ = tx.send(outcome);
        })
        .map_err(|e| pyo3::exceptions::PyOSError::new_err(format!("cannot start a thread: {e}")))?;
    let mut stop = Some(on_interrupt);
    let mut interrupted: Option<PyErr> = None;
    loop {
        let (got, back) = py.detach(move || (rx.recv_timeout(TICK), rx));
        rx = back;
        crate::logging::forward(py);
        match got {
            Ok(outcome) => {
                if let Some(err) = interrupted {
                    return Err(err);
                }
                // A Ctrl-C that came while the work ran, after the last look, ends the call
                // as an earlier one would: from within it, not at the caller's next line.
                py.check_signals()?;
                tick(py)?;
                return outcome.map_err(|panic| crate::errors::internal(what, panic));
            }
            Err(mpsc::RecvTimeoutError::Disconnected) => {
                return Err(crate::errors::internal(
                    what,
                    Box::new("the worker vanished"),
                ));
            }
            Err(mpsc::RecvTimeoutError::Timeout) => {}
        }
        if interrupted.is_none() {
            if let Err(err) = py.check_signals().and_then(|_| tick(py)) {
                match stop.take() {
                    Some(OnInterrupt::Stop(stop)) => {
                        stop();
                        interrupted = Some(err);
                    }
                    _ => return Err(err),
                }
            }
        }
    }
}

/// `work` on the calling thread with the interpreter detached; a panic becomes a
/// `SunjitterError` naming `what` (never a `PanicException`).
pub fn detached<T: Send>(
    py: Python<'_>,
    what: &str,
    work: impl FnOnce() -> T + Send,
) -> PyResult<T> {
    py.detach(|| std::panic::catch_unwind(std::panic::AssertUnwindSafe(work)))
        .map_err(|panic| crate::errors::internal(what, panic))
}
