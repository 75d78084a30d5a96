//! The process allocator: mimalloc, keeping freed frame-sized pages for reuse, in small pages.

// Frames are tens of MB and every alignment allocates a few dozen such arrays. glibc maps and
// unmaps each one, and on a virtual machine faulting fresh pages in can cost as much CPU as
// the numerics (docs/validation.md#freed-memory-kept). mimalloc keeps them for reuse.
#[global_allocator]
static ALLOCATOR: mimalloc::MiMalloc = mimalloc::MiMalloc;

/// Set the allocator up for frame-sized arrays; the binary calls it first thing, and so do the
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
pub fn tune_allocator() {
    static ONCE: std::sync::Once = std::sync::Once::new();
    ONCE.call_once(|| {
        if std::env::var_os("MIMALLOC_PURGE_DELAY").is_none() {
            // SAFETY: sets a plain integer option; mimalloc synchronises option access.
            unsafe { libmimalloc_sys::mi_option_set(MI_OPTION_PURGE_DELAY, -1) };
        }
        if std::env::var_os("MIMALLOC_ALLOW_THP").is_none() {
            // No further `madvise(MADV_HUGEPAGE)` on the memory mimalloc maps from now on ...
            // SAFETY: as above.
            unsafe { libmimalloc_sys::mi_option_set(MI_OPTION_ALLOW_THP, 0) };
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

/// `mi_option_purge_delay` in the mimalloc v3 header vendored by libmimalloc-sys 0.1.49
/// (`gcc -E` of `mimalloc.h`: the 16th enumerator), whose Rust bindings do not name it.
const MI_OPTION_PURGE_DELAY: libmimalloc_sys::mi_option_t = 15;

/// `mi_option_allow_thp` in the same header (the 44th enumerator).
const MI_OPTION_ALLOW_THP: libmimalloc_sys::mi_option_t = 43;

#[cfg(test)]
mod tests {
    #[test]
    fn freed_memory_is_kept_once_asked() {
        if std::env::var_os("MIMALLOC_PURGE_DELAY").is_some() {
            return; // the environment governs
        }
        super::tune_allocator();
        // SAFETY: reads a plain integer option.
        let delay = unsafe { libmimalloc_sys::mi_option_get(super::MI_OPTION_PURGE_DELAY) };
        assert_eq!(delay, -1);
    }

    #[test]
    fn huge_pages_are_off_once_asked() {
        if std::env::var_os("MIMALLOC_ALLOW_THP").is_some() {
            return; // the environment governs
        }
        super::tune_allocator();
        // SAFETY: reads a plain integer option.
        let allowed = unsafe { libmimalloc_sys::mi_option_get(super::MI_OPTION_ALLOW_THP) };
        assert_eq!(allowed, 0);
        // The kernel's own word for the process.
        #[cfg(target_os = "linux")]
        {
            // SAFETY: prctl with integer arguments only.
            let disabled = unsafe { libc::prctl(libc::PR_GET_THP_DISABLE, 0, 0, 0, 0) };
            assert_eq!(disabled, 1);
        }
    }
}
