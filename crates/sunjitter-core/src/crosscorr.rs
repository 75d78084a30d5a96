//! Cross-correlation (CC) translation: the baseline the paper compares optical flow with (§4.1).
//!
//! Both images are made zero-mean and multiplied by a 2-D Hann window (the reference also by
//! the mask, if any: masking only one side keeps the mask's own edge from producing a spurious
//! peak at zero shift), correlated through an FFT (sizes padded to powers of two; the window
//! makes the circular wrap harmless), the integer peak is located, and a 2-D quadratic fitted
//! to the 3×3 values around it gives the sub-pixel position.

use nalgebra::Complex;
use ndarray::ArrayView2;
use rayon::prelude::*;
use std::f64::consts::PI;

type C64 = Complex<f64>;

/// Translation `(dx, dy)` such that reference content appears in the frame at `+dx, +dy`
/// (the contract's sense). `None` when the inputs differ in shape, are smaller than 4×4, have
/// no finite pixels under the mask, or carry no structure to correlate.
pub fn cc_translation(
    reference: ArrayView2<f32>,
    frame: ArrayView2<f32>,
    mask: Option<ArrayView2<bool>>,
) -> Option<(f64, f64)> {
    let (h, w) = reference.dim();
    if frame.dim() != (h, w) || h < 4 || w < 4 {
        return None;
    }
    if let Some(m) = &mask {
        if m.dim() != (h, w) {
            return None;
        }
    }
    let (ph, pw) = (h.next_power_of_two(), w.next_power_of_two());
    let wy = hann(h);
    let wx = hann(w);
    let in_mask = |y: usize, x: usize| mask.as_ref().is_none_or(|m| m[[y, x]]);
    let weight_ref = |y: usize, x: usize| {
        if in_mask(y, x) && reference[[y, x]].is_finite() {
            wy[y] * wx[x]
        } else {
            0.0
        }
    };
    let weight_frame = |y: usize, x: usize| {
        if frame[[y, x]].is_finite() {
            wy[y] * wx[x]
        } else {
            0.0
        }
    };
    let mean_ref = weighted_mean(h, w, &weight_ref, |y, x| reference[[y, x]] as f64)?;
    let mean_frame = weighted_mean(h, w, &weight_frame, |y, x| frame[[y, x]] as f64)?;

    // Pack both real inputs into one complex array: z = r + i·f.
    let mut z = vec![C64::new(0.0, 0.0); ph * pw];
    for y in 0..h {
        for x in 0..w {
            let (wr, wf) = (weight_ref(y, x), weight_frame(y, x));
            let r = if wr > 0.0 {
                (reference[[y, x]] as f64 - mean_ref) * wr
            } else {
                0.0
            };
            let f = if wf > 0.0 {
                (frame[[y, x]] as f64 - mean_frame) * wf
            } else {
                0.0
            };
            z[y * pw + x] = C64::new(r, f);
        }
    }
    fft2(&mut z, ph, pw, false);
    // Separate the spectra (R(k) = (Z(k) + Z*(−k))/2, F(k) = (Z(k) − Z*(−k))/2i) and form
    // the cross-power R*(k)·F(k), whose inverse is c(d) = Σ r(p) f(p + d).
    let mut cross = vec![C64::new(0.0, 0.0); ph * pw];
    for ky in 0..ph {
        for kx in 0..pw {
            let zk = z[ky * pw + kx];
            let zm = z[((ph - ky) % ph) * pw + (pw - kx) % pw].conj();
            let rk = (zk + zm) * 0.5;
            let fk = (zk - zm) * C64::new(0.0, -0.5);
            cross[ky * pw + kx] = rk.conj() * fk;
        }
    }
    fft2(&mut cross, ph, pw, true);
    let corr: Vec<f64> = cross.iter().map(|c| c.re).collect();

    let (mut best, mut best_value) = (0, f64::NEG_INFINITY);
    for (i, &v) in corr.iter().enumerate() {
        if v > best_value {
            best_value = v;
            best = i;
        }
    }
    if !best_value.is_finite() || best_value <= 0.0 {
        return None;
    }
    let (iy, ix) = (best / pw, best % pw);
    // 3×3 neighbourhood, n[j + 1][i + 1] = c(iy + j, ix + i), circular.
    let n = [0usize, 1, 2].map(|j| {
        [0usize, 1, 2].map(|i| corr[((iy + ph + j - 1) % ph) * pw + (ix + pw + i - 1) % pw])
    });
    let (sub_x, sub_y) = quadratic_peak(&n);
    Some((signed_lag(ix, pw) + sub_x, signed_lag(iy, ph) + sub_y))
}

/// Sub-pixel peak of a 3×3 neighbourhood `n[y][x]` centred on the integer maximum.
///
/// A least-squares 2-D quadratic `a + bx + cy + dx² + exy + fy²` is fitted to the nine
/// values and its vertex returned. The cross term matters: solar images give elongated,
/// tilted correlation peaks, and separate 1-D parabolas along x and y then miss the vertex
/// (docs/validation.md#cross-correlation-peak-2-d-quadratic). Falls back to 1-D parabolas
/// when the fitted surface is not a proper maximum.
fn quadratic_peak(n: &[[f64; 3]; 3]) -> (f64, f64) {
    let sum_row = |j: usize| n[j].iter().sum::<f64>();
    let sum_col = |i: usize| n.iter().map(|r| r[i]).sum::<f64>();
    let b = (sum_col(2) - sum_col(0)) / 6.0;
    let c = (sum_row(2) - sum_row(0)) / 6.0;
    let d = (sum_col(0) + sum_col(2) - 2.0 * sum_col(1)) / 6.0;
    let f = (sum_row(0) + sum_row(2) - 2.0 * sum_row(1)) / 6.0;
    let e = (n[2][2] - n[2][0] - n[0][2] + n[0][0]) / 4.0;
    // Vertex: [2d e; e 2f]·(x, y) = −(b, c); a maximum needs d < 0 and 4df − e² > 0.
    let det = 4.0 * d * f - e * e;
    if d < 0.0 && det > 0.0 {
        let x = (-2.0 * f * b + e * c) / det;
        let y = (-2.0 * d * c + e * b) / det;
        if x.abs() <= 1.0 && y.abs() <= 1.0 {
            return (x, y);
        }
    }
    (
        parabolic_offset(n[1][0], n[1][1], n[1][2]),
        parabolic_offset(n[0][1], n[1][1], n[2][1]),
    )
}

/// Vertex of the parabola through (−1, a), (0, b), (1, c), clamped to ±0.5.
fn parabolic_offset(a: f64, b: f64, c: f64) -> f64 {
    let curvature = a - 2.0 * b + c;
    if curvature < 0.0 {
        (0.5 * (a - c) / curvature).clamp(-0.5, 0.5)
    } else {
        0.0
    }
}

/// Circular index → lag in (−n/2, n/2].
fn signed_lag(i: usize, n: usize) -> f64 {
    if i > n / 2 {
        i as f64 - n as f64
    } else {
        i as f64
    }
}

/// Symmetric Hann window, zero at both ends.
fn hann(n: usize) -> Vec<f64> {
    (0..n)
        .map(|i| 0.5 - 0.5 * (2.0 * PI * i as f64 / (n - 1) as f64).cos())
        .collect()
}

fn weighted_mean(
    h: usize,
    w: usize,
    weight: &impl Fn(usize, usize) -> f64,
    value: impl Fn(usize, usize) -> f64,
) -> Option<f64> {
    let (mut sw, mut swv) = (0.0, 0.0);
    for y in 0..h {
        for x in 0..w {
            let wt = weight(y, x);
            if wt > 0.0 {
                sw += wt;
                swv += wt * value(y, x);
            }
        }
    }
    (sw > 0.0).then(|| swv / sw)
}

/// In-place radix-2 FFT of a power-of-two length; `inverse` uses e^{+i} and divides by n.
fn fft(buf: &mut [C64], inverse: bool) {
    let n = buf.len();
    if n <= 1 {
        return;
    }
    let bits = n.trailing_zeros();
    for i in 0..n {
        let j = i.reverse_bits() >> (usize::BITS - bits);
        if j > i {
            buf.swap(i, j);
        }
    }
    let sign = if inverse { 1.0 } else { -1.0 };
    let mut len = 2;
    while len <= n {
        let step = C64::from_polar(1.0, sign * 2.0 * PI / len as f64);
        for start in (0..n).step_by(len) {
            let mut tw = C64::new(1.0, 0.0);
            for k in 0..len / 2 {
                // Recompute every 64 steps to keep the twiddle recurrence from drifting.
                if k % 64 == 0 {
                    tw = C64::from_polar(1.0, sign * 2.0 * PI * k as f64 / len as f64);
                }
                let a = buf[start + k];
                let b = buf[start + k + len / 2] * tw;
                buf[start + k] = a + b;
                buf[start + k + len / 2] = a - b;
                tw *= step;
            }
        }
        len *= 2;
    }
    if inverse {
        let scale = 1.0 / n as f64;
        buf.iter_mut().for_each(|v| *v *= scale);
    }
}

/// 2-D FFT of a row-major `h × w` array (both powers of two): rows, then columns.
fn fft2(data: &mut [C64], h: usize, w: usize, inverse: bool) {
    data.par_chunks_mut(w).for_each(|row| fft(row, inverse));
    let mut transposed = vec![C64::new(0.0, 0.0); h * w];
    for y in 0..h {
        for x in 0..w {
            transposed[x * h + y] = data[y * w + x];
        }
    }
    transposed
        .par_chunks_mut(h)
        .for_each(|col| fft(col, inverse));
    for x in 0..w {
        for y in 0..h {
            data[y * w + x] = transposed[x * h + y];
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use ndarray::{s, Array2};

    #[test]
    fn fft_matches_the_direct_dft() {
        let x: Vec<C64> = (0..16)
            .map(|k| {
                C64::new(
                    (k as f64 * 0.7).sin() + 0.1 * k as f64,
                    (k as f64 * 1.3).cos(),
                )
            })
            .collect();
        let mut fast = x.clone();
        fft(&mut fast, false);
        for (k, got) in fast.iter().enumerate() {
            let direct: C64 = x
                .iter()
                .enumerate()
                .map(|(j, v)| v * C64::from_polar(1.0, -2.0 * PI * (j * k) as f64 / 16.0))
                .sum();
            assert!((got - direct).norm() < 1e-12, "bin {k}");
        }
        fft(&mut fast, true);
        for (a, b) in fast.iter().zip(&x) {
            assert!((a - b).norm() < 1e-12);
        }
    }

    /// The TRACE 171 Å image of the bundled data (1024² int16), as f64.
    fn trace_image() -> Array2<f64> {
        let path = crate::test_data::real_path("trace_171_19980519T222143_1024.fits");
        let mut f = fitsio::FitsFile::open(path).expect("bundled TRACE file opens");
        let hdu = f.primary_hdu().expect("primary HDU");
        let pixels: Vec<f64> = hdu.read_image(&mut f).expect("image data");
        Array2::from_shape_vec((1024, 1024), pixels).expect("1024² image")
    }

    /// Band-limited periodic shift by (dx, dy): content moves to +dx, +dy.
    fn fourier_shift(img: &Array2<f64>, dx: f64, dy: f64) -> Array2<f64> {
        let (h, w) = img.dim();
        let mut z: Vec<C64> = img.iter().map(|&v| C64::new(v, 0.0)).collect();
        fft2(&mut z, h, w, false);
        let freq = |k: usize, n: usize| signed_lag(k, n) / n as f64;
        for ky in 0..h {
            for kx in 0..w {
                let phase = -2.0 * PI * (freq(kx, w) * dx + freq(ky, h) * dy);
                z[ky * w + kx] *= C64::from_polar(1.0, phase);
            }
        }
        fft2(&mut z, h, w, true);
        Array2::from_shape_vec((h, w), z.iter().map(|c| c.re).collect()).expect("shape")
    }

    #[test]
    fn recovers_a_subpixel_shift_of_a_real_trace_crop() {
        // Shift the whole image by Fourier phase (exact for band-limited content), then cut
        // the central 512² of both, so the frame has real content at its edges, not wrap.
        let big = trace_image();
        for &(dx, dy) in &[(2.37, -1.61), (-4.5, 3.25), (0.12, 0.0)] {
            let shifted = fourier_shift(&big, dx, dy);
            let cut = |a: &Array2<f64>| a.slice(s![256..768, 256..768]).mapv(|v| v as f32);
            let (r, f) = (cut(&big), cut(&shifted));
            let (ex, ey) =
                cc_translation(r.view(), f.view(), None).expect("structure to correlate");
            eprintln!("cc ({dx}, {dy}) error ({:.4}, {:.4})", ex - dx, ey - dy);
            assert!(
                (ex - dx).abs() < 0.05 && (ey - dy).abs() < 0.05,
                "({dx}, {dy}) → ({ex}, {ey})"
            );
            // A mask on the reference does not pull the peak to zero.
            let mask = Array2::from_shape_fn((512, 512), |(y, x)| {
                (x as f64 - 255.5).hypot(y as f64 - 255.5) < 200.0
            });
            let (mx, my) = cc_translation(r.view(), f.view(), Some(mask.view())).expect("masked");
            eprintln!("masked ({dx}, {dy}) error ({:.4}, {:.4})", mx - dx, my - dy);
            assert!(
                (mx - dx).abs() < 0.05 && (my - dy).abs() < 0.05,
                "masked ({dx}, {dy}) → ({mx}, {my})"
            );
        }
    }

    #[test]
    fn bad_inputs_give_none() {
        let a = Array2::<f32>::zeros((32, 32));
        let b = Array2::<f32>::zeros((32, 16));
        let nan = Array2::from_elem((32, 32), f32::NAN);
        let m = Array2::from_elem((16, 16), true);
        assert_eq!(cc_translation(a.view(), b.view(), None), None);
        assert_eq!(
            cc_translation(a.view(), a.view(), None),
            None,
            "flat images"
        );
        assert_eq!(cc_translation(nan.view(), nan.view(), None), None);
        assert_eq!(cc_translation(a.view(), a.view(), Some(m.view())), None);
        let tiny = Array2::<f32>::zeros((2, 2));
        assert_eq!(cc_translation(tiny.view(), tiny.view(), None), None);
    }
}
