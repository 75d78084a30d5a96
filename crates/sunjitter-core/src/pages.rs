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

/// `blocks` one after another, the blocks copied into place by all the pool's threads: what a
/// parallel filter kept, block by block, put together without one thread copying it all.
pub(crate) fn concat<T: Copy + Send + Sync>(blocks: &[Vec<T>]) -> Vec<T> {
    let total = blocks.iter().map(Vec::len).sum();
    let mut out = Vec::with_capacity(total);
    let mut parts = Vec::with_capacity(blocks.len());
    let mut rest = &mut out.spare_capacity_mut()[..total];
    for block in blocks {
        let (part, tail) = rest.split_at_mut(block.len());
        parts.push(part);
        rest = tail;
    }
    parts.into_par_iter().zip(blocks).for_each(|(part, block)| {
        for (slot, &v) in part.iter_mut().zip(block) {
            slot.write(v);
        }
    });
    // SAFETY: the parts cover the first `total` slots, and each was written in full above.
    unsafe { out.set_len(total) };
    out
}

/// An `h × w` array of `value`, written by every thread.
pub(crate) fn filled(h: usize, w: usize, value: f32) -> Array2<f32> {
    let mut values = Vec::new();
    fill_vec(&mut values, h * w, value);
    Array2::from_shape_vec((h, w), values).expect("h × w values")
}

#[cfg(test)]
mod tests {
    #[test]
    fn blocks_are_put_together_in_order() {
        // Blocks of none, one and thousands of values that together count up from 1.
        let lengths = [0, 1, 4096, 0, 3, 5000, 17, 0, 1];
        let mut next = 0u64;
        let blocks: Vec<Vec<u64>> = lengths
            .iter()
            .map(|&n| {
                (0..n)
                    .map(|_| {
                        next += 1;
                        next * 7919
                    })
                    .collect()
            })
            .collect();
        let joined = super::concat(&blocks);
        let want: Vec<u64> = (1..=next).map(|k| k * 7919).collect();
        assert_eq!(joined, want);
        assert!(super::concat::<u64>(&[]).is_empty());
    }
}
