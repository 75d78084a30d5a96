//! Buffers whose pages every thread faults in. The kernel clears a page on its first touch,
//! by the thread that touches it: written by one thread, a frame-sized buffer costs that
//! clearing serially (on a virtual machine the largest single item of a cold alignment).

use ndarray::Array2;
use rayon::prelude::*;

/// `out` as `n` copies of `value`, written by every thread. A buffer too small is replaced,
/// not grown, so its old contents are not copied.
pub(crate) fn fill_vec(out: &mut Vec<f32>, n: usize, value: f32) {
    if out.capacity() < n {
        *out = Vec::with_capacity(n);
    } else {
        out.clear();
    }
    out.par_extend(rayon::iter::repeat_n(value, n));
}

/// An `h × w` array of `value`, written by every thread.
pub(crate) fn filled(h: usize, w: usize, value: f32) -> Array2<f32> {
    let mut values = Vec::new();
    fill_vec(&mut values, h * w, value);
    Array2::from_shape_vec((h, w), values).expect("h × w values")
}
