//! Runtime CPU dispatch: hot loops are `#[inline(always)]` functions, instantiated twice by
//! [`multiversion!`]: once for baseline x86-64 (SSE2) and once compiled for AVX2+FMA, chosen at
//! run time. The crate itself is built for baseline x86-64, where LLVM may only use SSE2.

/// Set (to anything but empty or `0`) to run the portable kernels on any CPU: how the test
/// suite covers, on an AVX2 machine, the path other machines take.
const PORTABLE_KERNELS_VAR: &str = "SUNJITTER_PORTABLE_KERNELS";

/// Whether [`PORTABLE_KERNELS_VAR`] asks for the portable kernels; read once per process.
#[cfg(target_arch = "x86_64")]
fn portable_forced() -> bool {
    static FORCED: std::sync::OnceLock<bool> = std::sync::OnceLock::new();
    *FORCED.get_or_init(|| {
        std::env::var_os(PORTABLE_KERNELS_VAR).is_some_and(|v| !v.is_empty() && v != "0")
    })
}

/// `true` when the AVX2+FMA instantiation may run on this CPU.
#[inline]
pub(crate) fn has_avx2_fma() -> bool {
    #[cfg(target_arch = "x86_64")]
    {
        std::arch::is_x86_feature_detected!("avx2")
            && std::arch::is_x86_feature_detected!("fma")
            && !portable_forced()
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        false
    }
}

/// `true` when AVX-512's foundation and vector-length extensions may be used besides AVX2
/// and FMA: the same 256-bit vectors, but 32 vector registers instead of 16.
#[inline]
pub(crate) fn has_avx512vl() -> bool {
    #[cfg(target_arch = "x86_64")]
    {
        has_avx2_fma()
            && std::arch::is_x86_feature_detected!("avx512f")
            && std::arch::is_x86_feature_detected!("avx512vl")
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        false
    }
}

/// `multiversion!(fn name(args) -> R => body_fn);` defines `name`, which calls the
/// `#[inline(always)]` function `body_fn` compiled for AVX2+FMA when the CPU has them.
macro_rules! multiversion {
    ($vis:vis fn $name:ident($($arg:ident : $ty:ty),* $(,)?) $(-> $ret:ty)? => $body:path) => {
        $vis fn $name($($arg: $ty),*) $(-> $ret)? {
            #[cfg(target_arch = "x86_64")]
            {
                #[target_feature(enable = "avx2,fma")]
                unsafe fn fast($($arg: $ty),*) $(-> $ret)? {
                    $body($($arg),*)
                }
                if $crate::flow::simd::has_avx2_fma() {
                    // SAFETY: the CPU supports the features `fast` is compiled with.
                    return unsafe { fast($($arg),*) };
                }
            }
            $body($($arg),*)
        }
    };
}
pub(crate) use multiversion;
