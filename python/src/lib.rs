//! The extension module `sunjitter._sunjitter`: the library crates the command line is built
//! on, called from Python. The Python layer (`sunjitter/`) shapes what users see: numpy,
//! pandas, sunpy Maps and exceptions; this module runs the engine, the pipeline and the
//! log reader with the interpreter free.

mod align;
mod config;
mod errors;
mod logging;
mod logs;
mod replay;
mod wait;

use pyo3::prelude::*;

// Frames are tens of MB and every alignment allocates a few dozen such arrays: the Rust side
// allocates as the command line does (mimalloc, freed pages kept for reuse).
#[global_allocator]
static ALLOCATOR: mimalloc::MiMalloc = mimalloc::MiMalloc;

/// The mimalloc options this module sets, by their names in `mimalloc.h` (`mi_option_…`).
#[derive(Clone, Copy)]
enum MiOption {
    /// `mi_option_purge_delay`: ms before freed memory goes back to the system; -1 never.
    PurgeDelay,
    /// `mi_option_allow_thp`: whether the heap may use transparent huge pages.
    AllowThp,
}

impl MiOption {
    /// Its index in the header vendored by the pinned libmimalloc-sys, whose bindings do not
    /// name it (the command line's `src/allocator.rs` checks both against their variables).
    fn index(self) -> libmimalloc_sys::mi_option_t {
        match self {
            MiOption::PurgeDelay => 15,
            MiOption::AllowThp => 43,
        }
    }

    /// The environment variable that sets it when the process starts; it governs when set.
    fn variable(self) -> &'static str {
        match self {
            MiOption::PurgeDelay => "MIMALLOC_PURGE_DELAY",
            MiOption::AllowThp => "MIMALLOC_ALLOW_THP",
        }
    }
}

/// The allocator settings of the command line, for this module's own heap only (the rest of
/// the Python process is left as it is); each left to the environment when it sets it.
fn tune_allocator() {
    for (option, value) in [(MiOption::PurgeDelay, -1), (MiOption::AllowThp, 0)] {
        if std::env::var_os(option.variable()).is_none() {
            // SAFETY: sets a plain integer option; mimalloc synchronises option access.
            unsafe { libmimalloc_sys::mi_option_set(option.index(), value) };
        }
    }
}

#[pymodule]
fn _sunjitter(m: &Bound<'_, PyModule>) -> PyResult<()> {
    tune_allocator();
    logging::install();
    m.add("__version__", env!("CARGO_PKG_VERSION"))?;
    m.add_class::<align::Alignment>()?;
    m.add_function(wrap_pyfunction!(align::align, m)?)?;
    m.add_function(wrap_pyfunction!(align::read_frame, m)?)?;
    m.add_function(wrap_pyfunction!(logs::read_log, m)?)?;
    m.add_function(wrap_pyfunction!(logs::summary, m)?)?;
    m.add_function(wrap_pyfunction!(replay::replay, m)?)?;
    Ok(())
}
