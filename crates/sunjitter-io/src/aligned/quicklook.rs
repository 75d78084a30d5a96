//! The quick-look composite of a corrected frame: its panels, their rendering and the PNG.

use ndarray::{Array2, ArrayView2};
use plotters::prelude::{BitMapBackend, DrawingBackend};
use std::path::Path;
use sunjitter_core::engine::refine;
use sunjitter_core::geometry::Similarity;
use sunjitter_core::resample::HighOrderSpline;
use sunjitter_core::{Error, Result};

/// The four panels at display size: red/cyan composites (RGB, row 0 at the top) of the frame
/// through the coarse and the measured transform, and the matching differences
/// frame − reference (row 0 at the top) after matching the frame's intensities to the
/// reference's.
#[derive(Debug, Clone)]
pub(super) struct Panels {
    pub(super) width: usize,
    pub(super) height: usize,
    pub(super) composites: [Vec<u8>; 2],
    pub(super) differences: [Array2<f32>; 2],
    /// Differences in `−diff_range..diff_range` span the colour scale.
    pub(super) diff_range: f32,
}

/// An RGB picture (row 0 at the top).
#[derive(Debug, Clone)]
pub(super) struct Quicklook {
    pub(super) width: usize,
    pub(super) height: usize,
    pub(super) rgb: Vec<u8>,
}

/// What the figure says in words; header lines as (label, text that may be shortened).
pub(super) struct Captions {
    pub(super) reference: (String, String),
    pub(super) frame: (String, String),
    pub(super) measured: (String, String),
    pub(super) before: String,
    pub(super) after: String,
}

/// Largest panel side in the quick-look; larger images are block-averaged down.
pub(super) const MAX_PANEL_PX: usize = 1024;
/// Small images are enlarged (pixel replication) to at least about this size, to be seen.
pub(super) const MIN_PANEL_PX: usize = 512;
/// Display range: these percentiles of each image's finite pixels map to black and white.
pub(super) const LOW_PERCENTILE: f64 = 1.0;
pub(super) const HIGH_PERCENTILE: f64 = 99.5;
/// The difference panels' shared symmetric range: this percentile of their |values|.
pub(super) const DIFF_PERCENTILE: f64 = 99.5;
/// Grey strip between the panels, px.
pub(super) const GAP_PX: usize = 8;
/// Figure margin, header (four text lines), panel title and colour-bar strips, px.
pub(super) const MARGIN_PX: usize = 12;
pub(super) const HEADER_PX: usize = 112;
pub(super) const PANEL_TITLE_PX: usize = 30;
pub(super) const COLOUR_BAR_PX: usize = 70;
pub(super) const BACKGROUND: u8 = 255;
pub(super) const NO_DATA: [u8; 3] = [64, 64, 64];

/// The panels: frame through `coarse` and through `fine`, on the reference grid. Each image's
/// display range comes from its own pixels (1–99.5 %), the same for both composites, then a
/// square-root stretch so faint disk structure shows beside active regions. The differences
/// use the frame scaled by the least-squares gain and offset that match the `fine` rendering
/// to the reference, the same for both. `y` points up on screen (row 0 of the array at the
/// bottom), as solar images are shown. `None` when either image has no finite pixel.
pub(super) fn quicklook_panels(
    reference: ArrayView2<f32>,
    frame: ArrayView2<f32>,
    coarse: &Similarity,
    fine: &Similarity,
) -> Option<Panels> {
    let (h, w) = reference.dim();
    let ref_range = percentile_range(reference)?;
    let frame_range = percentile_range(frame)?;
    let spline = HighOrderSpline::new(frame, refine::MODEL);
    let warped = [
        spline.warp_similarity(coarse, w, h),
        spline.warp_similarity(fine, w, h),
    ];
    let red = resize(&stretch(reference, ref_range));
    let (ph, pw) = red.dim();
    let composites = [0, 1].map(|k| {
        let cyan = resize(&stretch(warped[k].view(), frame_range));
        let mut rgb = vec![0u8; pw * ph * 3];
        for y in 0..ph {
            let row = ph - 1 - y;
            for x in 0..pw {
                let i = 3 * (row * pw + x);
                let (r, c) = (to_byte(red[[y, x]]), to_byte(cyan[[y, x]]));
                rgb[i..i + 3].copy_from_slice(&[r, c, c]);
            }
        }
        rgb
    });
    let (gain, offset) = intensity_match(warped[1].view(), reference);
    let differences = [0, 1].map(|k| {
        let mut d = Array2::from_shape_fn((h, w), |(y, x)| {
            gain * warped[k][[y, x]] + offset - reference[[y, x]]
        });
        d = resize(&d);
        d.invert_axis(ndarray::Axis(0));
        d
    });
    let mut magnitudes: Vec<f32> = differences[0]
        .iter()
        .chain(differences[1].iter())
        .filter(|v| v.is_finite())
        .map(|v| v.abs())
        .collect();
    let diff_range = if magnitudes.is_empty() {
        1.0
    } else {
        let k = ((DIFF_PERCENTILE / 100.0) * (magnitudes.len() - 1) as f64).round() as usize;
        let v = *magnitudes.select_nth_unstable_by(k, f32::total_cmp).1;
        if v > 0.0 {
            v
        } else {
            1.0
        }
    };
    Some(Panels {
        width: pw,
        height: ph,
        composites,
        differences,
        diff_range,
    })
}

/// Gain and offset of the least-squares fit reference ≈ gain · frame + offset over the
/// pixels where both are finite (exposure and calibration differ between frames).
pub(super) fn intensity_match(frame: ArrayView2<f32>, reference: ArrayView2<f32>) -> (f32, f32) {
    let (mut n, mut sf, mut sr, mut sff, mut sfr) = (0.0f64, 0.0, 0.0, 0.0, 0.0);
    for (&f, &r) in frame.iter().zip(reference.iter()) {
        if f.is_finite() && r.is_finite() {
            let (f, r) = (f as f64, r as f64);
            n += 1.0;
            sf += f;
            sr += r;
            sff += f * f;
            sfr += f * r;
        }
    }
    if n < 2.0 {
        return (1.0, 0.0);
    }
    let var = sff - sf * sf / n;
    let gain = if var > 0.0 {
        (sfr - sf * sr / n) / var
    } else {
        1.0
    };
    (gain as f32, ((sr - gain * sf) / n) as f32)
}

/// Blue (negative) – white (0) – red (positive), `v` in −1..1; NaN is dark grey.
pub(super) fn diverging(v: f32) -> [u8; 3] {
    if !v.is_finite() {
        return NO_DATA;
    }
    const NEG: [f32; 3] = [33.0, 102.0, 172.0];
    const MID: [f32; 3] = [247.0, 247.0, 247.0];
    const POS: [f32; 3] = [178.0, 24.0, 43.0];
    let t = v.clamp(-1.0, 1.0);
    let end = if t < 0.0 { NEG } else { POS };
    let a = t.abs();
    [0, 1, 2].map(|i| (MID[i] + a * (end[i] - MID[i])).round() as u8)
}

/// Figure size for panels of `pw × ph` px.
pub(super) fn quicklook_size(pw: usize, ph: usize) -> (usize, usize) {
    (
        2 * pw + GAP_PX + 2 * MARGIN_PX,
        HEADER_PX + 2 * (PANEL_TITLE_PX + ph) + GAP_PX + COLOUR_BAR_PX,
    )
}

/// Top-left corner of panel (`row`, `col`).
pub(super) fn panel_origin(p: &Panels, row: usize, col: usize) -> (usize, usize) {
    (
        MARGIN_PX + col * (p.width + GAP_PX),
        HEADER_PX + PANEL_TITLE_PX + row * (p.height + PANEL_TITLE_PX + GAP_PX),
    )
}

/// The labelled figure: the header (files, times, measured transform, colour legend), the
/// composites above the differences, and the differences' colour bar.
pub(super) fn render_quicklook(
    p: &Panels,
    captions: &Captions,
) -> std::result::Result<Quicklook, String> {
    use plotters::prelude::*;
    use plotters::style::text_anchor::{HPos, Pos, VPos};
    let (width, height) = quicklook_size(p.width, p.height);
    let mut rgb = vec![BACKGROUND; width * height * 3];
    let mut put = |x: usize, y: usize, c: [u8; 3]| {
        let i = 3 * (y * width + x);
        rgb[i..i + 3].copy_from_slice(&c);
    };
    for col in 0..2 {
        let (x0, y0) = panel_origin(p, 0, col);
        for y in 0..p.height {
            for x in 0..p.width {
                let i = 3 * (y * p.width + x);
                let c = &p.composites[col][i..i + 3];
                put(x0 + x, y0 + y, [c[0], c[1], c[2]]);
            }
        }
        let (x0, y0) = panel_origin(p, 1, col);
        for y in 0..p.height {
            for x in 0..p.width {
                put(
                    x0 + x,
                    y0 + y,
                    diverging(p.differences[col][[y, x]] / p.diff_range),
                );
            }
        }
    }
    // Colour bar on the right, its caption to its left.
    let bar_w = width * 2 / 5;
    let bar_x = width - MARGIN_PX - 40 - bar_w;
    let bar_y = height - COLOUR_BAR_PX + 10;
    for x in 0..bar_w {
        let c = diverging(2.0 * x as f32 / (bar_w - 1).max(1) as f32 - 1.0);
        for y in bar_y..bar_y + 16 {
            put(bar_x + x, y, c);
        }
    }

    crate::font::register();
    let family = crate::font::FAMILY;
    {
        let root =
            BitMapBackend::with_buffer(&mut rgb, (width as u32, height as u32)).into_drawing_area();
        let e = |err: DrawingAreaErrorKind<_>| format!("{err}");
        let left = TextStyle::from((family, 18).into_font()).pos(Pos::new(HPos::Left, VPos::Top));
        let centre =
            TextStyle::from((family, 17).into_font()).pos(Pos::new(HPos::Center, VPos::Top));
        let max_w = (width - 2 * MARGIN_PX) as u32;
        // Long paths lose their beginning (the file name stays); the label is kept whole.
        let fit = |(label, body): &(String, String), style: &TextStyle| {
            let fits = |s: &str| {
                root.estimate_text_size(s, style)
                    .map_or(true, |(w, _)| w <= max_w)
            };
            let chars: Vec<char> = body.chars().collect();
            (0..chars.len())
                .map(|k| {
                    let cut: String = chars[k..].iter().collect();
                    if k == 0 {
                        format!("{label}{cut}")
                    } else {
                        format!("{label}…{cut}")
                    }
                })
                .find(|s| fits(s))
                .unwrap_or_else(|| label.clone())
        };
        let m = MARGIN_PX as i32;
        for (k, line) in [&captions.reference, &captions.frame, &captions.measured]
            .into_iter()
            .enumerate()
        {
            root.draw_text(&fit(line, &left), &left, (m, 8 + 25 * k as i32))
                .map_err(e)?;
        }
        // Colour legend of the composites.
        let mut x = m;
        let y = 8 + 25 * 3;
        for (colour, text) in [
            (RGBColor(255, 0, 0), "reference only"),
            (RGBColor(0, 255, 255), "frame only"),
            (RGBColor(200, 200, 200), "both (in register)"),
        ] {
            root.draw(&Rectangle::new(
                [(x, y + 2), (x + 16, y + 18)],
                colour.filled(),
            ))
            .map_err(e)?;
            root.draw(&Rectangle::new([(x, y + 2), (x + 16, y + 18)], BLACK))
                .map_err(e)?;
            root.draw_text(text, &left, (x + 22, y)).map_err(e)?;
            x += 22 + root.estimate_text_size(text, &left).map_err(e)?.0 as i32 + 30;
        }
        let titles = [
            [captions.before.clone(), captions.after.clone()],
            [
                "difference before: frame − reference (intensity-matched)".to_string(),
                "difference after: frame − reference (intensity-matched)".to_string(),
            ],
        ];
        let panel_max = p.width as u32 - 4;
        for (row, pair) in titles.iter().enumerate() {
            for (col, title) in pair.iter().enumerate() {
                let (x0, y0) = panel_origin(p, row, col);
                let shown = {
                    let fits = |s: &str| {
                        root.estimate_text_size(s, &centre)
                            .map_or(true, |(w, _)| w <= panel_max)
                    };
                    if fits(title) {
                        title.clone()
                    } else {
                        // Narrow panels: the part before the colon says which panel it is.
                        title.split(':').next().unwrap_or(title).to_string()
                    }
                };
                root.draw_text(
                    &shown,
                    &centre,
                    ((x0 + p.width / 2) as i32, (y0 - PANEL_TITLE_PX + 6) as i32),
                )
                .map_err(e)?;
            }
        }
        let r = p.diff_range;
        let label_y = (bar_y + 20) as i32;
        for (frac, text) in [
            (0.0, format!("−{}", significant(r))),
            (0.5, "0".to_string()),
            (1.0, format!("+{}", significant(r))),
        ] {
            let x = bar_x as i32 + (frac * (bar_w - 1) as f64) as i32;
            root.draw_text(&text, &centre, (x, label_y)).map_err(e)?;
        }
        let note = TextStyle::from((family, 16).into_font()).pos(Pos::new(HPos::Right, VPos::Top));
        root.draw_text(
            "frame − reference, reference units",
            &note,
            (bar_x as i32 - 50, bar_y as i32),
        )
        .map_err(e)?;
        root.present().map_err(e)?;
    }
    Ok(Quicklook { width, height, rgb })
}

/// Three significant digits, no exponent for everyday magnitudes.
pub(super) fn significant(v: f32) -> String {
    let v = v as f64;
    if v == 0.0 || !(1e-3..1e6).contains(&v.abs()) {
        return format!("{v:.2e}");
    }
    let decimals = (2 - v.abs().log10().floor() as i32).max(0) as usize;
    format!("{v:.decimals$}")
}

/// The `LOW_PERCENTILE`/`HIGH_PERCENTILE` values of the finite pixels (at most ~1M sampled).
pub(super) fn percentile_range(img: ArrayView2<f32>) -> Option<(f32, f32)> {
    let step = (img.len() / 1_000_000).max(1);
    let mut values: Vec<f32> = img
        .iter()
        .step_by(step)
        .copied()
        .filter(|v| v.is_finite())
        .collect();
    if values.is_empty() {
        return None;
    }
    let mut at = |pct: f64| {
        let k = ((pct / 100.0) * (values.len() - 1) as f64).round() as usize;
        *values.select_nth_unstable_by(k, f32::total_cmp).1
    };
    let lo = at(LOW_PERCENTILE);
    let hi = at(HIGH_PERCENTILE);
    // A flat image still shows (as black) rather than dividing by zero.
    Some((lo, if hi > lo { hi } else { lo + 1.0 }))
}

/// Clip to `range`, map to 0–1, square root. NaN stays NaN.
pub(super) fn stretch(img: ArrayView2<f32>, (lo, hi): (f32, f32)) -> Array2<f32> {
    img.mapv(|v| ((v - lo) / (hi - lo)).clamp(0.0, 1.0).sqrt())
}

pub(super) fn to_byte(v: f32) -> u8 {
    if v.is_finite() {
        (v * 255.0).round().clamp(0.0, 255.0) as u8
    } else {
        0
    }
}

/// Block-average big images down to at most `MAX_PANEL_PX`, replicate small ones up to about
/// `MIN_PANEL_PX` (integer factors, so every output pixel is a whole input block).
pub(super) fn resize(img: &Array2<f32>) -> Array2<f32> {
    let (h, w) = img.dim();
    let side = w.max(h).max(1);
    if side > MAX_PANEL_PX {
        let k = side.div_ceil(MAX_PANEL_PX);
        let (oh, ow) = (h.div_ceil(k), w.div_ceil(k));
        Array2::from_shape_fn((oh, ow), |(y, x)| {
            let (mut sum, mut n) = (0.0f64, 0usize);
            for yy in y * k..((y + 1) * k).min(h) {
                for xx in x * k..((x + 1) * k).min(w) {
                    let v = img[[yy, xx]];
                    if v.is_finite() {
                        sum += v as f64;
                        n += 1;
                    }
                }
            }
            if n == 0 {
                f32::NAN
            } else {
                (sum / n as f64) as f32
            }
        })
    } else {
        let u = (MIN_PANEL_PX / side).max(1);
        Array2::from_shape_fn((h * u, w * u), |(y, x)| img[[y / u, x / u]])
    }
}

/// Encode with plotters' bitmap backend (PNG chosen by the `.png` name of a temporary file,
/// renamed into place so a half-written picture is never seen under `path`).
pub(super) fn write_png(path: &Path, look: &Quicklook) -> Result<()> {
    let size = (look.width as u32, look.height as u32);
    crate::outputs::write_atomically(path, |tmp| {
        let mut backend = BitMapBackend::new(tmp, size);
        backend
            .blit_bitmap((0, 0), size, &look.rgb)
            .and_then(|_| backend.present())
            .map_err(|e| Error::output(path, format!("cannot write the PNG: {e}")))
    })
}
