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

/// `mi_option_purge_delay` in the mimalloc header vendored by the pinned libmimalloc-sys.
const MI_OPTION_PURGE_DELAY: libmimalloc_sys::mi_option_t = 15;
/// `mi_option_allow_thp` in the same header.
const MI_OPTION_ALLOW_THP: libmimalloc_sys::mi_option_t = 43;

/// The allocator settings of the command line, for this module's own heap only (the rest of
/// the Python process is left as it is); each left to the environment when it sets it.
fn tune_allocator() {
    for (var, option, value) in [
        ("MIMALLOC_PURGE_DELAY", MI_OPTION_PURGE_DELAY, -1),
        ("MIMALLOC_ALLOW_THP", MI_OPTION_ALLOW_THP, 0),
    ] {
        if std::env::var_os(var).is_none() {
            // SAFETY: sets a plain integer option; mimalloc synchronises option access.
            unsafe { libmimalloc_sys::mi_option_set(option, value) };
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
