//! The process allocator: mimalloc, keeping freed frame-sized pages for reuse.

// Frames are tens of MB and every alignment allocates a few dozen such arrays. glibc maps and
// unmaps each one, and on a virtual machine faulting fresh pages in can cost as much CPU as
// the numerics (docs/validation.md#freed-memory-kept). mimalloc keeps them for reuse.
#[global_allocator]
static ALLOCATOR: mimalloc::MiMalloc = mimalloc::MiMalloc;

/// Tell the allocator to keep freed pages for reuse instead of returning them to the system
/// 10 ms after they are freed (mimalloc's default): every frame allocates and frees the same
/// few frame-sized arrays, and faulting them in again would cost time on every frame; keeping
/// them costs some peak memory (docs/validation.md#freed-memory-kept). Idempotent;
/// the binary calls it first thing, and so do the benchmarks. A `MIMALLOC_PURGE_DELAY` set in
/// the environment is left to govern.
pub fn keep_freed_memory() {
    static ONCE: std::sync::Once = std::sync::Once::new();
    ONCE.call_once(|| {
        if std::env::var_os("MIMALLOC_PURGE_DELAY").is_none() {
            // SAFETY: sets a plain integer option; mimalloc synchronises option access.
            unsafe { libmimalloc_sys::mi_option_set(MI_OPTION_PURGE_DELAY, -1) };
        }
    });
}

/// `mi_option_purge_delay` in the mimalloc v3 header vendored by libmimalloc-sys 0.1.49
/// (`gcc -E` of `mimalloc.h`: the 16th enumerator), whose Rust bindings do not name it.
const MI_OPTION_PURGE_DELAY: libmimalloc_sys::mi_option_t = 15;

#[cfg(test)]
mod tests {
    #[test]
    fn freed_memory_is_kept_once_asked() {
        if std::env::var_os("MIMALLOC_PURGE_DELAY").is_some() {
            return; // the environment governs
        }
        super::keep_freed_memory();
        // SAFETY: reads a plain integer option.
        let delay = unsafe { libmimalloc_sys::mi_option_get(super::MI_OPTION_PURGE_DELAY) };
        assert_eq!(delay, -1);
    }
}
