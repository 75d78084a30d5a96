//! The process allocator, chosen by the binary: mimalloc, keeping freed frame-sized pages for
//! reuse, in small pages. The library crates leave the allocator to whoever links them.

use libmimalloc_sys::mi_option_t;

// Frames are tens of MB and every alignment allocates a few dozen such arrays. glibc maps and
// unmaps each one, and on a virtual machine faulting fresh pages in can cost as much CPU as
// the numerics (docs/validation.md#freed-memory-kept). mimalloc keeps them for reuse.
#[global_allocator]
static ALLOCATOR: mimalloc::MiMalloc = mimalloc::MiMalloc;

/// The mimalloc options this process sets, by their names in `mimalloc.h` (`mi_option_…`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum MiOption {
    /// `mi_option_purge_delay`: ms before freed memory goes back to the system; -1 never.
    PurgeDelay,
    /// `mi_option_allow_thp`: whether the heap may use transparent huge pages.
    AllowThp,
}

impl MiOption {
    #[cfg(test)]
    const ALL: [MiOption; 2] = [MiOption::PurgeDelay, MiOption::AllowThp];

    /// Its index in the mimalloc v3 header vendored by the pinned libmimalloc-sys (`gcc -E` of
    /// `mimalloc.h`: the 16th and 44th enumerators), whose Rust bindings do not name these.
    /// The tests check each index against the option its environment variable sets.
    fn index(self) -> mi_option_t {
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

    #[cfg(test)]
    fn get(self) -> std::ffi::c_long {
        // SAFETY: reads a plain integer option; mimalloc synchronises option access.
        unsafe { libmimalloc_sys::mi_option_get(self.index()) }
    }

    fn set(self, value: std::ffi::c_long) {
        // SAFETY: sets a plain integer option; mimalloc synchronises option access.
        unsafe { libmimalloc_sys::mi_option_set(self.index(), value) }
    }

    /// Sets it unless the environment does.
    fn set_unless_given(self, value: std::ffi::c_long) -> bool {
        let given = std::env::var_os(self.variable()).is_some();
        if !given {
            self.set(value);
        }
        !given
    }
}

/// Set the allocator up for frame-sized arrays; `main` calls it first thing, and so do the
/// benchmarks. Idempotent. Two settings, each left to the environment when it sets it:
///
/// - Freed pages are kept for reuse instead of being returned to the system 10 ms after they
///   are freed (mimalloc's default, `MIMALLOC_PURGE_DELAY`): every frame allocates and frees
///   the same few frame-sized arrays, and faulting them in again would cost time on every
///   frame; keeping them costs some peak memory (docs/validation.md#freed-memory-kept).
/// - The heap uses small pages, not transparent huge pages (`MIMALLOC_ALLOW_THP`): where the
///   kernel compacts memory to make a huge page at the fault (`defrag` = `madvise`, a common
///   default), a cold alignment spends more system time on it than its TLB saves
///   (docs/validation.md#small-pages).
pub fn tune() {
    static ONCE: std::sync::Once = std::sync::Once::new();
    ONCE.call_once(|| {
        MiOption::PurgeDelay.set_unless_given(-1);
        // No further `madvise(MADV_HUGEPAGE)` on the memory mimalloc maps from now on ...
        if MiOption::AllowThp.set_unless_given(0) {
            // ... and none for what it mapped before `main` (its first arena), nor where the
            // system's setting is `always`: what mimalloc itself does when the option is set
            // in the environment, which it reads only at start-up.
            #[cfg(target_os = "linux")]
            // SAFETY: prctl with integer arguments only; it changes no memory of ours.
            unsafe {
                libc::prctl(libc::PR_SET_THP_DISABLE, 1, 0, 0, 0);
            }
        }
    });
}

#[cfg(test)]
mod tests {
    use super::MiOption;

    /// Set in a child process to the variable whose option it reads back.
    const PROBE: &str = "SUNJITTER_ALLOCATOR_PROBE";

    #[test]
    fn each_option_is_the_one_its_variable_sets() {
        if let Some(variable) = std::env::var_os(PROBE) {
            let option = MiOption::ALL
                .into_iter()
                .find(|o| variable == o.variable())
                .unwrap();
            assert_eq!(option.get(), 7, "{option:?}");
            return;
        }
        // mimalloc reads `MIMALLOC_<NAME>` into the option of that name: a child started with
        // the variable set reads it back through the index.
        let this = std::env::current_exe().unwrap();
        let name = "allocator::tests::each_option_is_the_one_its_variable_sets";
        for option in MiOption::ALL {
            let status = std::process::Command::new(&this)
                .args(["--exact", name, "--test-threads=1"])
                .env(PROBE, option.variable())
                .env(option.variable(), "7")
                .stdout(std::process::Stdio::null())
                .status()
                .unwrap();
            assert!(
                status.success(),
                "{option:?} is not option {}",
                option.index()
            );
        }
    }

    #[test]
    fn freed_memory_is_kept_once_asked() {
        if std::env::var_os(MiOption::PurgeDelay.variable()).is_some() {
            return; // the environment governs
        }
        super::tune();
        assert_eq!(MiOption::PurgeDelay.get(), -1);
    }

    #[test]
    fn huge_pages_are_off_once_asked() {
        if std::env::var_os(MiOption::AllowThp.variable()).is_some() {
            return; // the environment governs
        }
        super::tune();
        assert_eq!(MiOption::AllowThp.get(), 0);
        // The kernel's own word for the process.
        #[cfg(target_os = "linux")]
        {
            // SAFETY: prctl with integer arguments only.
            let disabled = unsafe { libc::prctl(libc::PR_GET_THP_DISABLE, 0, 0, 0, 0) };
            assert_eq!(disabled, 1);
        }
    }
}
