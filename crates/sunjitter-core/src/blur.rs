//! How much blurrier one image is than the other: the difference of their Gaussian blur
//! variances, from the ratio of their radial power spectra.
//!
//! A frame blurred by seeing or focus (a Gaussian of variance `v`) has the reference's
//! spectrum times `exp(−4π²·v·k²)`, whatever the scene, and the spectrum does not depend on
//! where the scene sits: so `ln(P_frame/P_reference)` is a straight line in `(2πk)²` whose
//! slope is `−v`, and its intercept takes a change of gain. The intensity refinement's model
//! (`reference ≈ α·frame∘T + β`) cannot absorb a blur difference: unmatched, one moves its
//! answer by several σ (docs/validation.md#blur-matching-and-its-band).
//!
//! Only frequencies up to [`MAX_FREQUENCY`] count, where the refinement's 0.7 px smoothing
//! leaves the structure it fits: near Nyquist, a spline-resampled frame loses power that no
//! Gaussian explains, and matching it biases the answer.

use ndarray::{s, ArrayView2};

/// Highest spatial frequency of the fit, cycles/px.
pub const MAX_FREQUENCY: f64 = 0.25;

/// Largest square analysed, px (a power of two).
const MAX_SIDE: usize = 512;
/// Smallest: below it there are too few frequency bins for a slope
/// (docs/validation.md#smallest-square-analysed).
const MIN_SIDE: usize = 128;
/// A bin counts only where its power is this many times the noise's in both images.
const SIGNAL_TO_NOISE_POWER: f64 = 10.0;

/// The estimated blur difference.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct BlurDifference {
    /// Frame's blur variance minus the reference's, px² (negative: the reference is blurrier).
    pub variance_px2: f64,
    /// Its standard error from the fit's scatter, px².
    pub sigma_px2: f64,
    /// Half the difference between the two halves of the band, px²: 0 for a Gaussian blur,
    /// more for another shape (a defocused pillbox, a seeing halo).
    pub shape_px2: f64,
    /// Frequency bins fitted.
    pub bins: usize,
}

/// Radial mean power of a Hann-windowed square, by integer frequency bin `k·n`.
#[derive(Debug, Clone)]
pub struct RadialSpectrum {
    side: usize,
    /// The square's first column and row.
    corner: [usize; 2],
    power: Vec<f64>,
    count: Vec<usize>,
    /// Power a white noise of the square's background σ would have in each bin.
    noise_power: f64,
}

impl RadialSpectrum {
    /// The spectrum of the largest square (power of two, `MIN_SIDE`–`max_side` px) centred at
    /// `centre` that lies inside `img` with every pixel finite; `None` when there is none.
    pub fn around(img: ArrayView2<f32>, centre: [f64; 2], max_side: usize) -> Option<Self> {
        let mut side = max_side.min(MAX_SIDE).next_power_of_two();
        if side > max_side.min(MAX_SIDE) {
            side /= 2;
        }
        while side >= MIN_SIDE {
            let x0 = (centre[0] - side as f64 / 2.0).round();
            let y0 = (centre[1] - side as f64 / 2.0).round();
            if x0 >= 0.0 && y0 >= 0.0 {
                let (x0, y0) = (x0 as usize, y0 as usize);
                if let Some(found) = Self::at(img, [x0, y0], side) {
                    return Some(found);
                }
            }
            side /= 2;
        }
        None
    }

    /// The spectrum of the square of `reference`'s side whose corner is `reference`'s moved by
    /// `shift` rounded to whole pixels (where a frame shows the reference's square): the same
    /// side, and for a shift of nothing the same pixels, whatever rounding a half-pixel centre
    /// would meet. `None` when it leaves `img` or holds a blank.
    pub fn moved(
        img: ArrayView2<f32>,
        reference: &RadialSpectrum,
        shift: [f64; 2],
    ) -> Option<Self> {
        let corner = |k: usize| {
            let c = reference.corner[k] as f64 + shift[k].round();
            (c >= 0.0).then_some(c as usize)
        };
        Self::at(img, [corner(0)?, corner(1)?], reference.side)
    }

    fn at(img: ArrayView2<f32>, [x0, y0]: [usize; 2], side: usize) -> Option<Self> {
        let (h, w) = img.dim();
        if x0 + side > w || y0 + side > h {
            return None;
        }
        let square = img.slice(s![y0..y0 + side, x0..x0 + side]);
        square
            .iter()
            .all(|v| v.is_finite())
            .then(|| Self::of_square(square, [x0, y0]))
    }

    fn of_square(square: ArrayView2<f32>, corner: [usize; 2]) -> Self {
        let n = square.nrows();
        let mean = square.iter().map(|&v| v as f64).sum::<f64>() / (n * n) as f64;
        let hann: Vec<f64> = (0..n)
            .map(|i| 0.5 - 0.5 * (2.0 * std::f64::consts::PI * i as f64 / (n - 1) as f64).cos())
            .collect();
        let mut data: Vec<Complex> = square
            .indexed_iter()
            .map(|((y, x), &v)| Complex::new((v as f64 - mean) * hann[x] * hann[y], 0.0))
            .collect();
        fft_2d(&mut data, n);
        let bins = n / 2 + 1;
        let (mut power, mut count) = (vec![0.0; bins], vec![0usize; bins]);
        let freq = |i: usize| {
            if i <= n / 2 {
                i as f64
            } else {
                i as f64 - n as f64
            }
        };
        for y in 0..n {
            for x in 0..n {
                let bin = freq(x).hypot(freq(y)).round() as usize;
                if bin < bins {
                    power[bin] += data[y * n + x].norm_sqr();
                    count[bin] += 1;
                }
            }
        }
        for (p, &c) in power.iter_mut().zip(&count) {
            *p /= c.max(1) as f64;
        }
        let window_energy: f64 = hann.iter().map(|h| h * h).sum();
        let sigma = crate::simulate::background_noise(square).unwrap_or(0.0);
        RadialSpectrum {
            side: n,
            corner,
            power,
            count,
            noise_power: sigma * sigma * window_energy * window_energy,
        }
    }

    /// Power at `k` cycles/px, interpolated linearly in log power between bins.
    fn log_power_at(&self, k: f64) -> Option<f64> {
        let pos = k * self.side as f64;
        let i = pos.floor() as usize;
        let (a, b) = (*self.power.get(i)?, *self.power.get(i + 1)?);
        let (a, b) = (a - self.noise_power, b - self.noise_power);
        (a > 0.0 && b > 0.0).then(|| {
            let t = pos - i as f64;
            (1.0 - t) * a.ln() + t * b.ln()
        })
    }
}

/// The frame's blur variance minus the reference's, px², fitted over the bins below
/// [`MAX_FREQUENCY`] where both spectra are well above their noise. `scale` is the frame's
/// scale relative to the reference (a frame frequency `k` is the reference's `scale·k`).
/// `None` when fewer than 4 bins qualify.
pub fn blur_difference(
    reference: &RadialSpectrum,
    frame: &RadialSpectrum,
    scale: f64,
) -> Option<BlurDifference> {
    let n = frame.side as f64;
    let mut points = Vec::new();
    for bin in 2..frame.power.len() {
        let k = bin as f64 / n;
        if k > MAX_FREQUENCY {
            break;
        }
        let pf = frame.power[bin];
        let pr_bin = (scale * k * reference.side as f64).round() as usize;
        let Some(&pr) = reference.power.get(pr_bin) else {
            break;
        };
        if pf < SIGNAL_TO_NOISE_POWER * frame.noise_power
            || pr < SIGNAL_TO_NOISE_POWER * reference.noise_power
        {
            continue;
        }
        let (Some(lr), true) = (reference.log_power_at(scale * k), pf > frame.noise_power) else {
            continue;
        };
        let x = (2.0 * std::f64::consts::PI * k).powi(2);
        let y = (pf - frame.noise_power).ln() - lr;
        // Each bin's log power is the mean of `count` periodogram values.
        points.push((x, y, frame.count[bin] as f64));
    }
    if points.len() < 4 {
        return None;
    }
    let (slope, sigma) = fit_line(&points)?;
    // A blur of another shape than a Gaussian's bends the line: the two halves of the band
    // then disagree, and a Gaussian match is good only to about half their difference.
    let half = (2.0 * std::f64::consts::PI * MAX_FREQUENCY / 2.0).powi(2);
    let (low, high): (Vec<_>, Vec<_>) = points.iter().partition(|p| p.0 <= half);
    let shape = match (fit_line(&low), fit_line(&high)) {
        (Some((a, _)), Some((b, _))) if low.len() >= 3 && high.len() >= 3 => (a - b).abs() / 2.0,
        _ => 0.0,
    };
    Some(BlurDifference {
        variance_px2: -slope,
        sigma_px2: sigma,
        shape_px2: shape,
        bins: points.len(),
    })
}

/// Weighted least-squares line through (x, y, weight): its slope and the slope's standard
/// error (the weights are inverse variances up to a common factor, which the scatter
/// estimates).
fn fit_line(points: &[(f64, f64, f64)]) -> Option<(f64, f64)> {
    if points.len() < 3 {
        return None;
    }
    let (mut sw, mut sx, mut sy, mut sxx, mut sxy) = (0.0, 0.0, 0.0, 0.0, 0.0);
    for &(x, y, w) in points {
        sw += w;
        sx += w * x;
        sy += w * y;
        sxx += w * x * x;
        sxy += w * x * y;
    }
    let det = sw * sxx - sx * sx;
    if det <= 0.0 {
        return None;
    }
    let slope = (sw * sxy - sx * sy) / det;
    let intercept = (sy - slope * sx) / sw;
    let rss: f64 = points
        .iter()
        .map(|&(x, y, w)| w * (y - intercept - slope * x).powi(2))
        .sum();
    Some((slope, (rss / (points.len() - 2) as f64 * sw / det).sqrt()))
}

#[derive(Debug, Clone, Copy, PartialEq)]
struct Complex {
    re: f64,
    im: f64,
}

impl Complex {
    fn new(re: f64, im: f64) -> Self {
        Complex { re, im }
    }
    fn norm_sqr(self) -> f64 {
        self.re * self.re + self.im * self.im
    }
    fn mul(self, o: Complex) -> Complex {
        Complex::new(
            self.re * o.re - self.im * o.im,
            self.re * o.im + self.im * o.re,
        )
    }
}

/// In-place radix-2 FFT (forward, unnormalised) of a power-of-two length.
fn fft(data: &mut [Complex]) {
    let n = data.len();
    debug_assert!(n.is_power_of_two());
    let mut j = 0;
    for i in 1..n {
        let mut bit = n >> 1;
        while j & bit != 0 {
            j ^= bit;
            bit >>= 1;
        }
        j |= bit;
        if i < j {
            data.swap(i, j);
        }
    }
    let mut len = 2;
    while len <= n {
        let angle = -2.0 * std::f64::consts::PI / len as f64;
        let twiddles: Vec<Complex> = (0..len / 2)
            .map(|k| Complex::new((angle * k as f64).cos(), (angle * k as f64).sin()))
            .collect();
        for start in (0..n).step_by(len) {
            for (k, &twiddle) in twiddles.iter().enumerate() {
                let (a, b) = (data[start + k], data[start + k + len / 2].mul(twiddle));
                data[start + k] = Complex::new(a.re + b.re, a.im + b.im);
                data[start + k + len / 2] = Complex::new(a.re - b.re, a.im - b.im);
            }
        }
        len <<= 1;
    }
}

/// 2-D FFT of an `n`×`n` row-major array: rows, then columns.
fn fft_2d(data: &mut [Complex], n: usize) {
    use rayon::prelude::*;
    data.par_chunks_mut(n).for_each(fft);
    let mut columns: Vec<Complex> = (0..n * n).map(|i| data[(i % n) * n + i / n]).collect();
    columns.par_chunks_mut(n).for_each(fft);
    for (i, v) in columns.into_iter().enumerate() {
        data[(i % n) * n + i / n] = v;
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use ndarray::Array2;

    #[test]
    fn the_fft_is_the_discrete_fourier_transform() {
        // The DFT's definition, summed directly.
        let n = 16;
        let input: Vec<Complex> = (0..n)
            .map(|i| Complex::new((i as f64 * 0.7).sin() + 0.1 * i as f64, (i * i % 5) as f64))
            .collect();
        let mut fast = input.clone();
        fft(&mut fast);
        for (k, f) in fast.iter().enumerate() {
            let (mut re, mut im) = (0.0, 0.0);
            for (t, x) in input.iter().enumerate() {
                let a = -2.0 * std::f64::consts::PI * (k * t) as f64 / n as f64;
                re += x.re * a.cos() - x.im * a.sin();
                im += x.re * a.sin() + x.im * a.cos();
            }
            assert!(
                (f.re - re).abs() < 1e-9 && (f.im - im).abs() < 1e-9,
                "bin {k}"
            );
        }
    }

    /// The central 512² of the bundled TRACE image.
    fn trace_centre_512() -> Array2<f32> {
        let image = crate::test_data::read_real("trace_171_19980519T222143_1024.fits");
        image.slice(ndarray::s![256..768, 256..768]).to_owned()
    }

    /// Variance of the sampled Gaussian kernel that `preprocess::gaussian_smooth` applies.
    fn kernel_variance(sigma: f64) -> f64 {
        let radius = (4.0 * sigma + 0.5) as i64;
        let weights: Vec<(f64, f64)> = (-radius..=radius)
            .map(|d| (d as f64, (-0.5 * (d * d) as f64 / (sigma * sigma)).exp()))
            .collect();
        let total: f64 = weights.iter().map(|w| w.1).sum();
        weights.iter().map(|(d, w)| d * d * w).sum::<f64>() / total
    }

    #[test]
    fn an_injected_gaussian_blur_is_measured_on_a_real_image() {
        let sharp = trace_centre_512();
        let centre = [255.5, 255.5];
        for sigma in [0.5, 0.8, 1.2] {
            let injected = kernel_variance(sigma);
            let blurred = crate::preprocess::gaussian_smooth(sharp.view(), sigma);
            let r = RadialSpectrum::around(sharp.view(), centre, 512).unwrap();
            let f = RadialSpectrum::around(blurred.view(), centre, 512).unwrap();
            let d = blur_difference(&r, &f, 1.0).unwrap();
            // Here the image's own noise is blurred too, where a detector's is added after the
            // seeing; the noise floor, modelled as white, is then too high at high frequency
            // in the blurred copy, which reads 2–3 % blurrier.
            let tolerance = 0.01 + 0.03 * injected;
            assert!(
                (d.variance_px2 - injected).abs() < tolerance,
                "{injected}: {d:?}"
            );
            // And the other way round.
            let d = blur_difference(&f, &r, 1.0).unwrap();
            assert!(
                (d.variance_px2 + injected).abs() < tolerance,
                "{injected}: {d:?}"
            );
        }
    }

    /// The frame's square follows the reference's by the motion rounded as a whole: for a
    /// motion of almost nothing it is the same square, also where the centre falls on a
    /// half pixel and rounding each centre alone could take the neighbouring one (an image
    /// aligned to itself would then read 0.028 px² blurrier than itself, and be "matched"). One
    /// image has no blur difference with itself.
    #[test]
    fn a_frame_that_did_not_move_is_measured_on_the_reference_square() {
        let img = trace_centre_512();
        let centre = [255.5, 127.5];
        let r = RadialSpectrum::around(img.view(), centre, 256).unwrap();
        for tiny in [-1e-9, 0.0, 1e-9] {
            let f = RadialSpectrum::moved(img.view(), &r, [tiny, -tiny]).unwrap();
            assert_eq!((f.corner, f.side), (r.corner, r.side));
            let d = blur_difference(&r, &f, 1.0).unwrap();
            assert_eq!(d.variance_px2, 0.0, "{d:?}");
        }
        // A real motion moves the square by whole pixels, and off the image there is none.
        let f = RadialSpectrum::moved(img.view(), &r, [3.4, -2.6]).unwrap();
        assert_eq!(f.corner, [r.corner[0] + 3, r.corner[1] - 3]);
        assert!(RadialSpectrum::moved(img.view(), &r, [0.0, -200.0]).is_none());
    }

    #[test]
    fn a_box_blur_is_measured_by_its_variance_and_flagged_as_not_gaussian() {
        let sharp = trace_centre_512();
        // A 3×3 mean: variance 2/3 px² per axis, and an MTF (sinc²) that is no Gaussian's.
        let boxed = Array2::from_shape_fn((512, 512), |(y, x)| {
            let (y0, x0) = (y.clamp(1, 510), x.clamp(1, 510));
            sharp
                .slice(ndarray::s![y0 - 1..=y0 + 1, x0 - 1..=x0 + 1])
                .sum()
                / 9.0
        });
        let gaussian = crate::preprocess::gaussian_smooth(sharp.view(), (2.0f64 / 3.0).sqrt());
        let centre = [255.5, 255.5];
        let r = RadialSpectrum::around(sharp.view(), centre, 512).unwrap();
        let of = |img: &Array2<f32>| {
            let f = RadialSpectrum::around(img.view(), centre, 512).unwrap();
            blur_difference(&r, &f, 1.0).unwrap()
        };
        let (b, g) = (of(&boxed), of(&gaussian));
        // The Gaussian line through a sinc² reads 0.82 px²: the shape term says how far off a
        // Gaussian reading of this blur may be.
        assert!(
            (b.variance_px2 - 2.0 / 3.0).abs() < 2.0 * b.shape_px2,
            "{b:?}"
        );
        assert!(b.shape_px2 > 3.0 * g.shape_px2, "{b:?} against {g:?}");
    }

    #[test]
    fn no_square_without_finite_pixels() {
        let mut img = Array2::<f32>::zeros((100, 100));
        img.fill(f32::NAN);
        assert!(RadialSpectrum::around(img.view(), [50.0, 50.0], 100).is_none());
    }
}
