//! The quintic spline sampled at four positions at once with AVX2: the same operations as
//! [`HighOrderSpline`]'s one-position path, lane by lane and in the same order (no FMA), so
//! the values are identical bit for bit. The refinement, its self-test and the warps spend
//! most of their time here. Compiled twice ([`Isa`]): where the CPU has AVX-512, its 32
//! vector registers hold every weight of a block.

use super::high_order::HighOrderSpline;
use std::arch::x86_64::*;

/// Positions sampled side by side.
const LANES: usize = 4;
const TAPS: usize = 6;
/// Taps before `floor(x)`.
const REACH: usize = 2;

/// Where a block of positions reads the coefficients: the first sample of each lane's
/// support, and the fractions; `None` when a lane's support leaves the image's interior or
/// holds a blank (that block is sampled one position at a time).
struct Block {
    start: [usize; LANES],
    tx: [f64; LANES],
    ty: [f64; LANES],
}

#[inline(always)]
fn block(sp: &HighOrderSpline, positions: impl Iterator<Item = (f64, f64)>) -> Option<Block> {
    let (h, w) = sp.coeffs().dim();
    let mut b = Block {
        start: [0; LANES],
        tx: [0.0; LANES],
        ty: [0.0; LANES],
    };
    for (l, (x, y)) in positions.enumerate() {
        let ((ix, tx), (iy, ty)) = sp.locate_at(x, y)?;
        if !(ix >= REACH && iy >= REACH && ix + TAPS <= w + REACH && iy + TAPS <= h + REACH) {
            return None;
        }
        b.start[l] = (iy - REACH) * w + ix - REACH;
        // Each support row is read as 8 values: the last row's must lie in the image.
        if b.start[l] + (TAPS - 1) * w + 8 > h * w {
            return None;
        }
        (b.tx[l], b.ty[l]) = (tx, ty);
    }
    Some(b)
}

/// `bspline5_weights` on each lane.
#[inline]
#[target_feature(enable = "avx2")]
unsafe fn weights(t: __m256d) -> [__m256d; TAPS] {
    let t2 = mul(t, t);
    let last = div(mul(mul(t, t2), t2), c(120.0));
    let u2 = sub(t2, t);
    let u4 = mul(u2, u2);
    let m = sub(t, c(0.5));
    let v = mul(u2, sub(u2, c(3.0)));
    let first = sub(div(add(add(c(0.2), u2), u4), c(24.0)), last);
    let a0 = div(add(mul(u2, sub(u2, c(5.0))), c(46.0 / 5.0)), c(24.0));
    let a1 = div(mul(_mm256_xor_pd(m, c(-0.0)), add(v, c(4.0))), c(12.0));
    let b0 = div(sub(c(9.0 / 5.0), v), c(16.0));
    let b1 = div(mul(m, sub(sub(u4, u2), c(5.0))), c(24.0));
    [
        first,
        add(b0, b1),
        add(a0, a1),
        sub(a0, a1),
        sub(b0, b1),
        last,
    ]
}

/// `bspline_derivative_weights(5, ·)` on each lane: differences of `quartic_cardinal`.
#[inline]
#[target_feature(enable = "avx2")]
unsafe fn derivative_weights(t: __m256d) -> [__m256d; TAPS] {
    let (t2, u) = (mul(t, t), sub(c(1.0), t));
    let t4 = mul(t2, t2);
    let u2 = mul(u, u);
    let q0 = div(t4, c(24.0));
    let q1 = quartic_weight(t, [-4.0, 4.0, 6.0, 4.0, 1.0 / 24.0]);
    let q2 = quartic_weight(t, [6.0, -12.0, -6.0, 12.0, 11.0 / 24.0]);
    let q3 = quartic_weight(t, [-4.0, 12.0, -6.0, -12.0, 11.0 / 24.0]);
    let q4 = div(mul(u2, u2), c(24.0));
    [
        sub(c(0.0), q4),
        sub(q4, q3),
        sub(q3, q2),
        sub(q2, q1),
        sub(q1, q0),
        q0,
    ]
}

/// `((((a·t + b)·t + c)·t + d)·t) / 24 + e`, as `quartic_cardinal` writes its middle weights.
#[inline]
#[target_feature(enable = "avx2")]
unsafe fn quartic_weight(t: __m256d, [a, b, cc, d, e]: [f64; 5]) -> __m256d {
    let p = add(mul(c(a), t), c(b));
    let p = add(mul(p, t), c(cc));
    let p = add(mul(p, t), c(d));
    add(div(mul(p, t), c(24.0)), c(e))
}

#[inline]
#[target_feature(enable = "avx2")]
unsafe fn c(v: f64) -> __m256d {
    _mm256_set1_pd(v)
}

#[inline]
#[target_feature(enable = "avx2")]
unsafe fn mul(a: __m256d, b: __m256d) -> __m256d {
    _mm256_mul_pd(a, b)
}

#[inline]
#[target_feature(enable = "avx2")]
unsafe fn add(a: __m256d, b: __m256d) -> __m256d {
    _mm256_add_pd(a, b)
}

#[inline]
#[target_feature(enable = "avx2")]
unsafe fn sub(a: __m256d, b: __m256d) -> __m256d {
    _mm256_sub_pd(a, b)
}

#[inline]
#[target_feature(enable = "avx2")]
unsafe fn div(a: __m256d, b: __m256d) -> __m256d {
    _mm256_div_pd(a, b)
}

/// The six taps of support row `j` of the four lanes, tap by tap across the lanes, as f64:
/// each lane's row read as eight contiguous values (two past its support) and transposed.
///
/// # Safety
/// The CPU must have AVX2, and `start[l] + offset + 8` must not pass the end of `data` for
/// any lane (as [`block`] checks for every support row).
#[inline]
#[target_feature(enable = "avx2")]
unsafe fn row_taps(data: *const f32, start: &[usize; LANES], offset: usize) -> [__m256d; TAPS] {
    let r = |l: usize| _mm256_loadu_ps(data.add(start[l] + offset));
    let (r0, r1, r2, r3) = (r(0), r(1), r(2), r(3));
    let (t0, t1) = (_mm256_unpacklo_ps(r0, r1), _mm256_unpackhi_ps(r0, r1));
    let (t2, t3) = (_mm256_unpacklo_ps(r2, r3), _mm256_unpackhi_ps(r2, r3));
    // Taps (0, 4), (1, 5), (2, 6), (3, 7) of the four lanes, in each half.
    let u0 = _mm256_shuffle_ps::<0b01_00_01_00>(t0, t2);
    let u1 = _mm256_shuffle_ps::<0b11_10_11_10>(t0, t2);
    let u2 = _mm256_shuffle_ps::<0b01_00_01_00>(t1, t3);
    let u3 = _mm256_shuffle_ps::<0b11_10_11_10>(t1, t3);
    let low = |u: __m256| _mm256_cvtps_pd(_mm256_castps256_ps128(u));
    let high = |u: __m256| _mm256_cvtps_pd(_mm256_extractf128_ps::<1>(u));
    [low(u0), low(u1), low(u2), low(u3), high(u0), high(u1)]
}

/// The instruction sets the kernels are compiled for; both perform the same operations in
/// the same order, so they give the same values.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(super) enum Isa {
    Avx2,
    /// AVX2's 256-bit vectors with AVX-512's 32 vector registers (AVX512F and VL): the 24
    /// weight vectors of a block of positions stay in registers instead of the stack.
    Avx512Vl,
}

impl Isa {
    /// The best this CPU runs; `None` without AVX2 and FMA.
    pub(super) fn detect() -> Option<Isa> {
        if crate::flow::simd::has_avx512vl() {
            Some(Isa::Avx512Vl)
        } else if crate::flow::simd::has_avx2_fma() {
            Some(Isa::Avx2)
        } else {
            None
        }
    }

    /// Every one this CPU runs.
    #[cfg(test)]
    pub(super) fn available() -> Vec<Isa> {
        match Isa::detect() {
            Some(Isa::Avx512Vl) => vec![Isa::Avx2, Isa::Avx512Vl],
            Some(Isa::Avx2) => vec![Isa::Avx2],
            None => vec![],
        }
    }
}

/// Value and gradient at each of `positions`, as `sample_with_gradient`.
///
/// # Safety
/// The CPU must have `isa`'s features, and `sp` must be quintic.
pub(super) unsafe fn gradients_at(
    isa: Isa,
    sp: &HighOrderSpline,
    positions: &[[f64; 2]],
    out: &mut [[f64; 3]],
) {
    #[target_feature(enable = "avx2")]
    unsafe fn with_avx2(sp: &HighOrderSpline, p: &[[f64; 2]], out: &mut [[f64; 3]]) {
        gradients_in(sp, p, out)
    }
    #[target_feature(enable = "avx2,avx512f,avx512vl")]
    unsafe fn with_avx512vl(sp: &HighOrderSpline, p: &[[f64; 2]], out: &mut [[f64; 3]]) {
        gradients_in(sp, p, out)
    }
    // SAFETY (both arms): the CPU has `isa`'s features (this function's contract).
    match isa {
        Isa::Avx2 => unsafe { with_avx2(sp, positions, out) },
        Isa::Avx512Vl => unsafe { with_avx512vl(sp, positions, out) },
    }
}

/// [`gradients_at`]'s loop, compiled into each of its instantiations.
#[inline(always)]
unsafe fn gradients_in(sp: &HighOrderSpline, positions: &[[f64; 2]], out: &mut [[f64; 3]]) {
    let (_, w) = sp.coeffs().dim();
    // Row-major and contiguous, as `HighOrderSpline::new` leaves them.
    debug_assert!(sp.coeffs().is_standard_layout());
    let data = sp.coeffs().as_ptr();
    let mut blocks = positions.chunks_exact(LANES);
    let mut outs = out.chunks_exact_mut(LANES);
    for (p, o) in (&mut blocks).zip(&mut outs) {
        let Some(b) = block(sp, p.iter().map(|&[x, y]| (x, y))) else {
            for (&[x, y], o) in p.iter().zip(o) {
                *o = sp.sample_with_gradient(x, y);
            }
            continue;
        };
        let (tx, ty) = (
            _mm256_loadu_pd(b.tx.as_ptr()),
            _mm256_loadu_pd(b.ty.as_ptr()),
        );
        let (wx, dx) = (weights(tx), derivative_weights(tx));
        let (wy, dy) = (weights(ty), derivative_weights(ty));
        let zero = _mm256_setzero_pd();
        let (mut v, mut gx, mut gy) = (zero, zero, zero);
        for j in 0..TAPS {
            let taps = row_taps(data, &b.start, j * w);
            let (mut r, mut rd) = (zero, zero);
            for (i, &c) in taps.iter().enumerate() {
                r = add(r, mul(wx[i], c));
                rd = add(rd, mul(dx[i], c));
            }
            v = add(v, mul(wy[j], r));
            gx = add(gx, mul(wy[j], rd));
            gy = add(gy, mul(dy[j], r));
        }
        let mut lanes = [[0.0; LANES]; 3];
        for (k, s) in [v, gx, gy].into_iter().enumerate() {
            _mm256_storeu_pd(lanes[k].as_mut_ptr(), s);
        }
        for (l, o) in o.iter_mut().enumerate() {
            *o = [lanes[0][l], lanes[1][l], lanes[2][l]];
        }
    }
    for (&[x, y], o) in blocks.remainder().iter().zip(outs.into_remainder()) {
        *o = sp.sample_with_gradient(x, y);
    }
}

/// Values at `positions(k)` for `k` in `0..out.len()`, as `sample_at` (the sum over rows
/// starts from the first, as `Iterator::sum` does from −0).
///
/// # Safety
/// The CPU must have `isa`'s features, and `sp` must be quintic.
#[inline]
pub(super) unsafe fn values_at(
    isa: Isa,
    sp: &HighOrderSpline,
    positions: impl Fn(usize) -> (f64, f64),
    out: &mut [f32],
) {
    #[target_feature(enable = "avx2")]
    unsafe fn with_avx2(sp: &HighOrderSpline, p: impl Fn(usize) -> (f64, f64), out: &mut [f32]) {
        values_in(sp, p, out)
    }
    #[target_feature(enable = "avx2,avx512f,avx512vl")]
    unsafe fn with_avx512vl(
        sp: &HighOrderSpline,
        p: impl Fn(usize) -> (f64, f64),
        out: &mut [f32],
    ) {
        values_in(sp, p, out)
    }
    // SAFETY (both arms): the CPU has `isa`'s features (this function's contract).
    match isa {
        Isa::Avx2 => unsafe { with_avx2(sp, positions, out) },
        Isa::Avx512Vl => unsafe { with_avx512vl(sp, positions, out) },
    }
}

/// [`values_at`]'s loop, compiled into each of its instantiations.
#[inline(always)]
unsafe fn values_in(
    sp: &HighOrderSpline,
    positions: impl Fn(usize) -> (f64, f64),
    out: &mut [f32],
) {
    let (_, w) = sp.coeffs().dim();
    // Row-major and contiguous, as `HighOrderSpline::new` leaves them.
    debug_assert!(sp.coeffs().is_standard_layout());
    let data = sp.coeffs().as_ptr();
    let n = out.len();
    let full = n - n % LANES;
    for k0 in (0..full).step_by(LANES) {
        let Some(b) = block(sp, (k0..k0 + LANES).map(&positions)) else {
            for (k, o) in out.iter_mut().enumerate().skip(k0).take(LANES) {
                let (x, y) = positions(k);
                *o = sp.sample_at(x, y);
            }
            continue;
        };
        let (tx, ty) = (
            _mm256_loadu_pd(b.tx.as_ptr()),
            _mm256_loadu_pd(b.ty.as_ptr()),
        );
        let (wx, wy) = (weights(tx), weights(ty));
        let mut v = _mm256_setzero_pd();
        for (j, &wyj) in wy.iter().enumerate() {
            let taps = row_taps(data, &b.start, j * w);
            let mut r = _mm256_setzero_pd();
            for (&wxi, &c) in wx.iter().zip(&taps) {
                r = add(r, mul(wxi, c));
            }
            let p = mul(wyj, r);
            v = if j == 0 { p } else { add(v, p) };
        }
        let mut lanes = [0.0; LANES];
        _mm256_storeu_pd(lanes.as_mut_ptr(), v);
        for (o, &l) in out[k0..k0 + LANES].iter_mut().zip(&lanes) {
            *o = l as f32;
        }
    }
    for (k, o) in out.iter_mut().enumerate().skip(full) {
        let (x, y) = positions(k);
        *o = sp.sample_at(x, y);
    }
}
