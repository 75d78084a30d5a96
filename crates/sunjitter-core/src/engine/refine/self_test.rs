//! The method's systematic error on a reference, measured on synthetic frames made from it.

use super::pixels::{lattice_pixels, pixel_box, CellGrid};
use super::reference::RefineReference;
use super::solve::{refine_fitted, FitPixels};
use super::window::{mapped_window, window_margin, FrameWindow, WindowTile};
use super::{RefineSettings, MAX_PIXELS, MODEL};
use crate::geometry::Similarity;
use crate::resample::{HighOrderSpline, SplineImage};
use ndarray::{s, Array2, ArrayView2};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

/// What the self-test measured on a reference.
#[derive(Debug, Clone, Copy)]
pub struct SelfTest {
    /// The systematic floor per parameter (scale, rotation rad, dx, dy).
    pub floor: [f64; 4],
    /// RMS over the cases of the residuals' robust σ at the flattest pixels: the level the
    /// model's misfit alone leaves there, without noise.
    pub flat_sigma: Option<f64>,
}

/// One self-test case: the error it made, and the (cluster-robust) variance it reported.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub(super) struct SelfTestCase {
    pub(super) bias: [f64; 4],
    pub(super) variance: [f64; 4],
    /// Robust σ of its residuals at the flattest pixels: the model's misfit alone.
    pub(super) flat_sigma: Option<f64>,
}

/// A reference's self-test cases, one per transform, and what they depend on. Along a chain
/// (`previous`, where every frame becomes the next reference) a reference hands them on: the
/// next one runs only a quarter of the transforms afresh and keeps the others, as long as its
/// pixels, lever arm, settings and structure length match. No case is then older than three
/// references (docs/validation.md#self-test-along-a-chain).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SelfTestCases {
    key: CaseKey,
    /// One result per transform, in the transforms' order.
    cases: Vec<SelfTestCase>,
    /// The quarter the next reference renews when it has no position of its own.
    next_quarter: usize,
}

/// Cases handed on to a reference, and the reference's position along its chain (its
/// sequence number in the log), which picks the quarter it renews: position `q` renews
/// quarter `q mod 4`, so a chain that starts four references earlier (a shard's overlap)
/// holds the same cases as a single run's from then on. Without a position the quarters
/// are renewed in turn.
#[derive(Debug, Clone, Copy)]
pub struct HandedOn<'a> {
    pub cases: &'a SelfTestCases,
    pub position: Option<u64>,
}

/// References whose cases make up one reference's self-test along a chain: each renews a
/// quarter of the transforms (rounded up).
pub const SELF_TEST_QUARTERS: usize = 4;

/// The transforms in quarter `quarter` of `cases`.
fn quarter(cases: usize, quarter: usize) -> std::ops::Range<usize> {
    let size = cases.div_ceil(SELF_TEST_QUARTERS);
    (quarter * size).min(cases)..((quarter + 1) * size).min(cases)
}

/// What a self-test case's error depends on, besides the reference's content near the
/// Nyquist frequency (which the structure length stands in for).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
struct CaseKey {
    shape: (usize, usize),
    tiles: usize,
    pixels: usize,
    lever: f64,
    /// NaN when the reference has none (kept as `null`).
    #[serde(with = "finite_or_null")]
    structure_px: f64,
    settings: RefineSettings,
}

/// An `f64` that may be NaN, as JSON has no NaN: `null` for it.
mod finite_or_null {
    use serde::{Deserialize, Deserializer, Serialize, Serializer};

    pub fn serialize<S: Serializer>(v: &f64, s: S) -> Result<S::Ok, S::Error> {
        v.is_finite().then_some(*v).serialize(s)
    }

    pub fn deserialize<'de, D: Deserializer<'de>>(d: D) -> Result<f64, D::Error> {
        Ok(Option::<f64>::deserialize(d)?.unwrap_or(f64::NAN))
    }
}

impl CaseKey {
    /// Whether cases measured under `self` stand for a reference under `other`: the same
    /// image size, tiling and settings; the pixel count within 2 %, the lever arm within 1 %
    /// (the disk moving by the pointing jitter, or its radius by the Earth's orbit), and the
    /// structure length within 5 % (seeing, or a changed exposure, changes it by more).
    fn matches(&self, other: &CaseKey) -> bool {
        let near = |a: f64, b: f64, tol: f64| (a - b).abs() <= tol * a.abs().max(b.abs());
        self.shape == other.shape
            && self.tiles == other.tiles
            && self.settings == other.settings
            && near(self.pixels as f64, other.pixels as f64, 0.02)
            && near(self.lever, other.lever, 0.01)
            && near(self.structure_px, other.structure_px, 0.05)
    }
}

impl SelfTestCases {
    /// The systematic floor over all the cases, summed in the transforms' order.
    pub fn floor(&self) -> SelfTest {
        let (mut sum, mut seen) = ([0.0; 4], [0.0; 4]);
        let mut flat = Vec::with_capacity(self.cases.len());
        for test in &self.cases {
            for k in 0..4 {
                sum[k] += test.bias[k] * test.bias[k];
                seen[k] += test.variance[k];
            }
            flat.extend(test.flat_sigma);
        }
        let n = self.cases.len() as f64;
        // Only the error the residuals do not already show: without noise the cluster
        // covariance is made of these same interpolation residuals, and counting both
        // overstates the σ (docs/validation.md#self-test-floor).
        SelfTest {
            floor: std::array::from_fn(|k| ((sum[k] - seen[k]) / n).max(0.0).sqrt()),
            flat_sigma: (!flat.is_empty())
                .then(|| (flat.iter().map(|s| s * s).sum::<f64>() / flat.len() as f64).sqrt()),
        }
    }
}

impl SelfTestCases {
    /// Whether these cases could have come from [`self_test_floor`]: between 4 and 16 of
    /// them, every figure finite. What a store hands back is checked against this first.
    pub fn is_sound(&self) -> bool {
        (4..=16).contains(&self.cases.len())
            && self.next_quarter < SELF_TEST_QUARTERS
            && self.cases.iter().all(|c| {
                c.bias.iter().chain(&c.variance).all(|v| v.is_finite())
                    && c.variance.iter().all(|&v| v >= 0.0)
                    && c.flat_sigma.is_none_or(|s| s.is_finite() && s >= 0.0)
            })
    }
}

/// A fingerprint of everything a reference's self-test cases depend on: the code that
/// computes them and the instruction set it runs on, the reference as the refinement reads
/// it, its mask, the sampling step, the refinement's settings, the structure length and the
/// engine's configuration. Equal keys give equal cases, so a [`SelfTestStore`] may hand back
/// the cases it kept under a key instead of their being run again (128 bits of XXH3: no two
/// references meet by chance).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub struct SelfTestKey(u128);

impl SelfTestKey {
    /// `config` describes the engine's configuration (any text that changes with it).
    pub fn new(
        reference: ArrayView2<f32>,
        mask: &Array2<bool>,
        sample: usize,
        settings: &RefineSettings,
        structure_px: Option<f64>,
        config: &str,
    ) -> SelfTestKey {
        let mut digest = xxhash_rust::xxh3::Xxh3::new();
        let mut text = |t: &str| {
            digest.update(&(t.len() as u64).to_le_bytes());
            digest.update(t.as_bytes());
        };
        text(env!("SUNJITTER_CORE_CODE"));
        // The instruction set the samplers pick at run time moves the last digits.
        text(&format!(
            "{} {}",
            std::env::consts::ARCH,
            crate::flow::simd::has_avx2_fma()
        ));
        text(&format!(
            "{:?} {:?} {sample} {settings:?} {:?}",
            reference.dim(),
            mask.dim(),
            structure_px.map(f64::to_bits)
        ));
        text(config);
        for row in reference.rows() {
            match row.as_slice() {
                Some(values) => digest.update(bytemuck::cast_slice(values)),
                None => row.iter().for_each(|v| digest.update(&v.to_le_bytes())),
            }
        }
        let mut bytes = Vec::with_capacity(mask.ncols());
        for row in mask.rows() {
            bytes.clear();
            bytes.extend(row.iter().map(|&m| m as u8));
            digest.update(&bytes);
        }
        SelfTestKey(digest.digest128())
    }

    /// The key as 32 hexadecimal digits (a file name).
    pub fn hex(&self) -> String {
        format!("{:032x}", self.0)
    }
}

/// Where a caller keeps references' self-test cases between runs (the engine does no I/O):
/// a reference whose key was seen before skips its self-test. `load` returns what `save`
/// stored under the same key, or nothing; neither may fail the alignment.
pub trait SelfTestStore: Send + Sync {
    fn load(&self, key: &SelfTestKey) -> Option<SelfTestCases>;
    fn save(&self, key: &SelfTestKey, cases: &SelfTestCases);
}

/// The method's systematic floor for a reference ([`SelfTestCases::floor`]): per parameter,
/// the RMS of the self-test errors (`self_test_bias`) over the cases of `self_test_case`, on
/// the lattice of the whole `mask`, beyond the σ those refinements reported themselves
/// (quadratic excess). The error depends on the sub-pixel positions the pixels land on, so
/// the cases spread the shift over the unit square and rotate and scale the lever arm by a
/// fraction of a pixel (which varies the positions across the image); their RMS is the
/// typical error of a frame, whatever its own transform. `structure_px` is the reference's
/// structure length; `handed_on`, the cases of the previous reference along a chain, of which
/// a quarter are run again when they still apply, all of them otherwise. `None` when a case
/// fails.
pub fn self_test_floor(
    reference: ArrayView2<f32>,
    prepared: &RefineReference,
    mask: &Array2<bool>,
    sample: usize,
    settings: &RefineSettings,
    structure_px: Option<f64>,
    handed_on: Option<HandedOn>,
) -> Option<SelfTestCases> {
    let (h, w) = reference.dim();
    let grid = CellGrid::new(mask.view(), sample)?;
    let usable = |x: usize, y: usize| mask[[y, x]] && reference[[y, x]].is_finite();
    let tiles = self_test_tiles(mask);
    let (pixels, boxes) = if tiles.is_empty() {
        let pixels = lattice_pixels((h, w), usable, &grid, MAX_PIXELS, |_| true);
        let whole = pixel_box(&pixels)?;
        (pixels, vec![whole])
    } else {
        // Every pixel of every tile, tile by tile (the order the sampling reads them in).
        let pixels = tiles
            .par_iter()
            .flat_map_iter(|&(x0, y0, x1, y1)| {
                let (usable, grid) = (&usable, &grid);
                (y0..=y1).flat_map(move |y| {
                    (x0..=x1).filter_map(move |x| {
                        usable(x, y)
                            .then(|| grid.cell_of(x, y).map(|c| (x, y, c)))
                            .flatten()
                    })
                })
            })
            .collect();
        (pixels, tiles)
    };
    if pixels.is_empty() {
        return None;
    }
    let center = Similarity::array_center(w, h);
    let lever = (pixels
        .iter()
        .map(|&(x, y, _)| (x as f64 - center[0]).powi(2) + (y as f64 - center[1]).powi(2))
        .sum::<f64>()
        / pixels.len() as f64)
        .sqrt()
        .max(1.0);
    let settings = RefineSettings {
        frame_smoothing_px: 0.0,
        ..*settings
    };
    // More cases where they are cheap: the RMS of four is uncertain by about ±35 %, and on
    // small undersampled images the error varies strongly with the sub-pixel position.
    let cases = (SELF_TEST_PIXEL_BUDGET / pixels.len().max(1)).clamp(4, 16);
    let cases = if boxes.len() > 1 { 4 } else { cases };
    // Without a structure length the key matches nothing: every case runs afresh.
    let key = CaseKey {
        shape: (h, w),
        tiles: boxes.len(),
        pixels: pixels.len(),
        lever,
        structure_px: structure_px.unwrap_or(f64::NAN),
        settings,
    };
    // The cases to run: a quarter of those handed on where they still apply, else all.
    let kept = handed_on.filter(|h| h.cases.cases.len() == cases && h.cases.key.matches(&key));
    let (mut results, run, renewed): (Vec<Option<SelfTestCase>>, Vec<usize>, usize) = match kept {
        Some(HandedOn {
            cases: old,
            position,
        }) => {
            let renewed = position.map_or(old.next_quarter, |q| {
                (q % SELF_TEST_QUARTERS as u64) as usize
            });
            let run = quarter(cases, renewed).collect();
            (old.cases.iter().copied().map(Some).collect(), run, renewed)
        }
        None => (
            vec![None; cases],
            (0..cases).collect(),
            SELF_TEST_QUARTERS - 1,
        ),
    };
    // Every case refines the same pixels about the same centre: their instruments once.
    let fit = FitPixels::new(prepared, &pixels, center).ok()?;
    // The cases side by side: each one's own work leaves a core idle in its serial parts
    // (a case's frame is made tile by tile, on a whole mask as one).
    let tests = run
        .par_iter()
        .map(|&case| {
            let (dx, dy, turn_px, stretch_px) = self_test_case(case);
            let t = Similarity {
                scale: 1.0 + stretch_px / lever,
                rotation_rad: turn_px / lever,
                dx,
                dy,
                center,
            };
            let test = self_test_bias(
                reference,
                &fit,
                &boxes,
                &grid,
                &t,
                &settings,
                FrameMaker::Model,
            )?;
            tracing::trace!(case, bias = ?test.bias, "self-test case");
            Some(test)
        })
        .collect::<Option<Vec<_>>>()?;
    for (&case, test) in run.iter().zip(tests) {
        results[case] = Some(test);
    }
    tracing::debug!(cases, fresh = run.len(), "self-test cases");
    Some(SelfTestCases {
        key,
        cases: results.into_iter().collect::<Option<Vec<_>>>()?,
        next_quarter: (renewed + 1) % SELF_TEST_QUARTERS,
    })
}

/// Tiles (inclusive boxes) of the self-test on a large mask: a 5 × 5 layout over the mask's
/// bounding box, the tiles wholly inside the mask kept, [`SELF_TEST_TILE_PIXELS`] in all.
/// Tiles keep the lever arm of the whole mask and every sub-pixel position while the
/// synthetic frames are made only where the refinement reads them. Empty when the mask is
/// small enough to be tested whole.
pub(super) fn self_test_tiles(mask: &Array2<bool>) -> Vec<(usize, usize, usize, usize)> {
    const LAYOUT: usize = 5;
    let Some(roi) = crate::sampling::mask_bounding_box(mask.view()) else {
        return Vec::new();
    };
    let (x0, y0, x1, y1) = roi;
    let (bw, bh) = (x1 - x0 + 1, y1 - y0 + 1);
    if bw * bh <= SELF_TEST_TILED_ABOVE {
        return Vec::new();
    }
    let side = ((SELF_TEST_TILE_PIXELS / (LAYOUT * LAYOUT - 4)) as f64).sqrt() as usize;
    let side = side.min(bw / LAYOUT).min(bh / LAYOUT);
    let tiles: Vec<_> = (0..LAYOUT * LAYOUT)
        .map(|k| {
            let centre = |i: usize, n: usize, at: usize| at + ((2 * i + 1) * n) / (2 * LAYOUT);
            let (cx, cy) = (centre(k % LAYOUT, bw, x0), centre(k / LAYOUT, bh, y0));
            (
                cx - side / 2,
                cy - side / 2,
                cx - side / 2 + side - 1,
                cy - side / 2 + side - 1,
            )
        })
        .filter(|&(tx0, ty0, tx1, ty1)| mask.slice(s![ty0..=ty1, tx0..=tx1]).iter().all(|&m| m))
        .collect();
    // Too few tiles inside (a ring-shaped or ragged mask): test the whole mask.
    if tiles.len() < LAYOUT * LAYOUT / 2 {
        return Vec::new();
    }
    tiles
}

/// Mask bounding-box area above which the self-test runs on tiles, px: the refinement's pixel
/// budget, above which the whole-mask test would refine a thinned lattice anyway. Tiles give
/// the same Monte Carlo figures there at a fraction of the cost
/// (docs/validation.md#self-test-on-tiles).
pub(super) const SELF_TEST_TILED_ABOVE: usize = MAX_PIXELS;

/// Pixels in all the self-test's tiles.
pub(super) const SELF_TEST_TILE_PIXELS: usize = 1 << 18;

/// Pixels (summed over the cases) the self-test may refine on a whole mask: 4 cases at 2²⁰
/// pixels, up to 16 on smaller images (on tiles, always 4).
pub(super) const SELF_TEST_PIXEL_BUDGET: usize = 4 << 20;

/// The `k`-th self-test transform: (dx, dy, rotation and scale change as a motion of the
/// lever arm), px. Shifts follow the R2 low-discrepancy sequence over the unit square; the
/// turn and stretch are ±0.3–0.5 px with alternating signs.
pub(super) fn self_test_case(k: usize) -> (f64, f64, f64, f64) {
    // R2: fractional parts of k·(1/g, 1/g²), g the plastic number.
    const G: f64 = 1.324_717_957_244_746;
    let n = k as f64 + 1.0;
    let (dx, dy) = ((0.5 + n / G).fract(), (0.5 + n / (G * G)).fract());
    let sign = |b: bool| if b { 1.0 } else { -1.0 };
    let turn = sign(k.is_multiple_of(2)) * (0.3 + 0.2 * ((k / 2) % 2) as f64);
    let stretch = sign(k % 4 < 2) * (0.5 - 0.2 * ((k / 2) % 2) as f64);
    (dx, dy, turn, stretch)
}

/// How a self-test makes its synthetic frame from the reference.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) enum FrameMaker {
    /// The refinement's own interpolator: what is left is the method's error on frames it
    /// can model exactly (double interpolation, f32, the weights).
    Model,
    /// A cubic spline, one order below the model: a real frame is a new sampling of the sky,
    /// not the model's resampling of the reference, and the two differ in how they move
    /// structure near the Nyquist frequency. Band-limited frames sit on the model's other
    /// side, nearer, so the cubic frame's error bounds theirs; and frames that were made by
    /// cubic resampling (scipy's default) are covered exactly
    /// (docs/validation.md#check-frames-made-by-a-cubic-spline).
    CubicSpline,
}

/// The method's systematic error for this image and transform, measured: a frame made from
/// the reference itself through `transform` (by `maker`) is refined from the exact answer,
/// and what the refinement reports instead is its bias (interpolation of sharp or
/// undersampled structure, mostly), with the variance it reported.
pub(super) fn self_test_bias(
    reference: ArrayView2<f32>,
    fit: &FitPixels,
    boxes: &[(usize, usize, usize, usize)],
    grid: &CellGrid,
    transform: &Similarity,
    settings: &RefineSettings,
    maker: FrameMaker,
) -> Option<SelfTestCase> {
    let tiles = boxes
        .par_iter()
        .map(|&bbox| synthetic_tile(reference, bbox, transform, settings, maker))
        .collect::<Option<Vec<_>>>()?;
    let window = FrameWindow {
        tiles,
        carried: None,
    };
    let test = refine_fitted(fit, &window, grid, *transform, settings).ok()?;
    let (a, b) = (transform.params(), test.transform.params());
    let bias = [0, 1, 2, 3].map(|k| b[k] - a[k]);
    let variance = [0, 1, 2, 3].map(|k| test.covariance[k][k]);
    let flat_sigma = test.flat_residual_sigma;
    (bias.iter().chain(&variance).all(|v| v.is_finite())).then_some(SelfTestCase {
        bias,
        variance,
        flat_sigma,
    })
}

/// The synthetic frame (the reference moved by `transform`, by `maker`) on the window that
/// the reference pixels in `bbox` map into.
pub(super) fn synthetic_tile(
    reference: ArrayView2<f32>,
    bbox: (usize, usize, usize, usize),
    transform: &Similarity,
    settings: &RefineSettings,
    maker: FrameMaker,
) -> Option<WindowTile> {
    let (h, w) = reference.dim();
    // The synthetic frame is only needed on the window the refinement reads; it is made
    // there from the spline of the part of the reference that the window maps back to.
    let sigma = settings.smoothing_px;
    // The synthetic frame's own smoothing: a blur mismatch, for the blur check.
    let frame_sigma = sigma.hypot(settings.frame_smoothing_px);
    let (wx0, wy0, wx1, wy1) = mapped_window(bbox, transform, window_margin(frame_sigma), w, h)?;
    let back = mapped_window(
        (wx0, wy0, wx1, wy1),
        &transform.inverse(),
        // The model's support (3 px) and border transient (0.431^17 < 1e-6).
        window_margin(0.0),
        w,
        h,
    )?;
    let (sx0, sy0, sx1, sy1) = back;
    let source = reference.slice(s![sy0..=sy1, sx0..=sx1]);
    let inverse = transform.inverse();
    let to_source = Similarity {
        dx: inverse.dx - sx0 as f64,
        dy: inverse.dy - sy0 as f64,
        ..inverse
    };
    let (ww, wh) = (wx1 - wx0 + 1, wy1 - wy0 + 1);
    let synthetic = match maker {
        FrameMaker::Model => {
            HighOrderSpline::new(source, MODEL).warp_similarity_window(&to_source, wx0, wy0, ww, wh)
        }
        FrameMaker::CubicSpline => {
            SplineImage::new(source).warp_similarity_window(&to_source, wx0, wy0, ww, wh)
        }
    };
    Some(WindowTile {
        spline: HighOrderSpline::new(
            crate::preprocess::gaussian_smooth(synthetic.view(), frame_sigma).view(),
            MODEL,
        ),
        origin: [wx0 as f64, wy0 as f64],
        end: [wx1 as f64, wy1 as f64],
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// AIA 171 128² (undersampled: the floor is most of its σ), its whole field, and the
    /// engine's default refinement settings.
    fn aia() -> (Array2<f32>, Array2<bool>, RefineSettings) {
        let image = crate::test_data::read_real("aia_171_20110215T000000_128.fits");
        let mask = Array2::from_elem(image.dim(), true);
        let settings = super::super::settings(&crate::engine::EngineConfig::default(), 0.0);
        (image, mask, settings)
    }

    /// The key tells apart every input the cases depend on: one pixel's last bit, one mask
    /// pixel, the sampling step, a setting, the structure length, the configuration; and is
    /// the same for equal inputs (a copy, not the same array).
    #[test]
    fn the_self_test_key_changes_with_every_input_it_stands_for() {
        let (image, mask, settings) = aia();
        let key = |image: &Array2<f32>, mask: &Array2<bool>, sample, settings, structure, cfg| {
            SelfTestKey::new(image.view(), mask, sample, settings, structure, cfg)
        };
        let base = key(&image, &mask, 4, &settings, Some(3.5), "cfg");
        assert_eq!(
            key(
                &image.clone(),
                &mask.clone(),
                4,
                &settings,
                Some(3.5),
                "cfg"
            ),
            base
        );
        let mut pixel = image.clone();
        pixel[[64, 64]] = f32::from_bits(pixel[[64, 64]].to_bits() ^ 1);
        let mut masked = mask.clone();
        masked[[0, 127]] = false;
        let smoother = RefineSettings {
            smoothing_px: settings.smoothing_px + 0.1,
            ..settings
        };
        let others = [
            key(&pixel, &mask, 4, &settings, Some(3.5), "cfg"),
            key(&image, &masked, 4, &settings, Some(3.5), "cfg"),
            key(&image, &mask, 5, &settings, Some(3.5), "cfg"),
            key(&image, &mask, 4, &smoother, Some(3.5), "cfg"),
            key(&image, &mask, 4, &settings, Some(3.6), "cfg"),
            key(&image, &mask, 4, &settings, None, "cfg"),
            key(&image, &mask, 4, &settings, Some(3.5), "cfg2"),
            // The same pixels in another shape.
            key(
                &image.clone().into_shape_with_order((64, 256)).unwrap(),
                &mask.clone().into_shape_with_order((64, 256)).unwrap(),
                4,
                &settings,
                Some(3.5),
                "cfg",
            ),
        ];
        for (i, other) in others.iter().enumerate() {
            assert_ne!(*other, base, "input {i}");
        }
    }

    /// Cases run on a real reference survive a JSON round trip bit for bit (NaN structure
    /// length included) and are sound; cases with a non-finite figure are not.
    #[test]
    fn self_test_cases_round_trip_and_are_checked_for_soundness() {
        let (image, mask, settings) = aia();
        let prepared = RefineReference::new(image.view(), &settings);
        let cases = self_test_floor(image.view(), &prepared, &mask, 4, &settings, None, None)
            .expect("self-test on AIA 171");
        assert!(cases.is_sound());
        let text = serde_json::to_string(&cases).unwrap();
        let back: SelfTestCases = serde_json::from_str(&text).unwrap();
        assert_eq!(format!("{back:?}"), format!("{cases:?}"));
        assert!(back.key.structure_px.is_nan());
        let mut bad = back.clone();
        bad.cases[1].variance[2] = f64::INFINITY;
        assert!(!bad.is_sound());
        let mut few = back;
        few.cases.truncate(3);
        assert!(!few.is_sound());
    }

    fn floor_of(
        image: &Array2<f32>,
        mask: &Array2<bool>,
        settings: &RefineSettings,
        structure_px: f64,
        handed_on: Option<&SelfTestCases>,
    ) -> SelfTestCases {
        let handed_on = handed_on.map(|cases| HandedOn {
            cases,
            position: None,
        });
        let prepared = RefineReference::new(image.view(), settings);
        self_test_floor(
            image.view(),
            &prepared,
            mask,
            20,
            settings,
            Some(structure_px),
            handed_on,
        )
        .expect("self-test runs")
    }

    #[test]
    fn cases_are_not_handed_on_to_a_reference_whose_structure_changed() {
        let (sharp, mask, settings) = aia();
        let blurred = crate::preprocess::gaussian_smooth(sharp.view(), 1.0);
        let before = floor_of(&sharp, &mask, &settings, 2.0, None);
        let fresh = floor_of(&blurred, &mask, &settings, 2.2, None);
        // Blurring takes out the structure near the Nyquist frequency that the model
        // interpolates worst: the sharp reference's cases do not stand for the blurred one.
        let (a, b) = (before.floor().floor, fresh.floor().floor);
        assert!(
            a[2] > 2.0 * b[2] && a[3] > 2.0 * b[3],
            "{a:?} against {b:?}"
        );
        // A structure length 10 % longer: every case is run again on the blurred reference.
        let handed = floor_of(&blurred, &mask, &settings, 2.2, Some(&before));
        assert_eq!(handed.floor().floor, b);
    }

    #[test]
    fn along_a_chain_a_reference_runs_a_quarter_of_the_cases_and_keeps_the_rest() {
        let (sharp, mask, settings) = aia();
        let blurred = crate::preprocess::gaussian_smooth(sharp.view(), 1.0);
        // Cases measured on the blurred image, handed on under a matching key.
        let before = floor_of(&blurred, &mask, &settings, 2.0, None);
        let fresh = floor_of(&sharp, &mask, &settings, 2.0, None);
        let handed = floor_of(&sharp, &mask, &settings, 2.0, Some(&before));
        let n = fresh.cases.len();
        assert_eq!(n, 16, "a 128² field runs 16 transforms");
        for k in 0..n {
            let expected = if k < n / 4 { &fresh } else { &before };
            assert_eq!(
                handed.cases[k].bias, expected.cases[k].bias,
                "transform {k}"
            );
        }
        // The next reference along renews the next quarter.
        let after = floor_of(&sharp, &mask, &settings, 2.0, Some(&handed));
        for k in 0..n {
            let expected = if k < n / 2 { &fresh } else { &before };
            assert_eq!(after.cases[k].bias, expected.cases[k].bias, "transform {k}");
        }
    }
}
