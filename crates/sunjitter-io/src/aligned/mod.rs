//! Files `align` can write besides its numbers: the resampled frame and a quick-look composite.
//!
//! Both render the frame on the reference grid through the engine's transform (the
//! refinement's quintic B-spline, NaN where the frame has no data), so what a person sees is what was measured.

use crate::fits;
use ndarray::{Array2, ArrayView2};
use quicklook::{quicklook_panels, render_quicklook, write_png, Captions};
use std::path::Path;
use sunjitter_core::engine::{refine, AlignOutcome, Image, UsedGeometry};
use sunjitter_core::geometry::Similarity;
use sunjitter_core::header::{Header, HeaderValue};
use sunjitter_core::meta::FrameMeta;
use sunjitter_core::resample::HighOrderSpline;
use sunjitter_core::{Error, Result};

mod quicklook;

/// The frame resampled onto the reference grid, written as f32 FITS.
///
/// Header: the frame's own cards (time, exposure, instrument, observer…), minus whatever
/// describes its old pixel grid (WCS of axes 1–2, `XCEN`/`YCEN`, `SOLAR_R`, roll keys) and
/// the data statistics the resampling invalidates; plus the reference's grid cards (its WCS:
/// `CRPIXi`, `CDELTi`, `CRVALi`, `CTYPEi`, `CUNITi`, and the roll as `PCi_j` whether the
/// header gave it as `CROTA2`, `SC_ROLL` or a matrix; see [`Grid::of_image`]), plus `HISTORY`
/// saying what was done with which transform. `replay`/`watch --aligned` write the same WCS
/// for the same grid.
pub fn write_aligned(
    path: &Path,
    reference: &Image,
    frame: &Image,
    outcome: &AlignOutcome,
) -> Result<()> {
    require_transform(path, outcome)?;
    let (_, reference_header) = fits::read_image_header(&reference.meta.file)?;
    let (_, frame_header) = fits::read_image_header(&frame.meta.file)?;
    let (data, cards) = aligned_product(
        (&reference_header, &reference.meta, reference.data.dim()),
        (&frame_header, &frame.meta, frame.data.view()),
        outcome,
    )?;
    fits::write_image(path, data.view(), &cards)
}

/// An image's pixels and header cards, as a FITS product holds them.
pub type Product = (Array2<f32>, Vec<(String, HeaderValue)>);

/// What [`write_aligned`] writes, from the images' headers (as read: a cube's for a frame of
/// it), metadata and shape or pixels: the frame resampled onto the reference grid, and the
/// product's header cards.
pub fn aligned_product(
    reference: (&Header, &FrameMeta, (usize, usize)),
    frame: (&Header, &FrameMeta, ArrayView2<f32>),
    outcome: &AlignOutcome,
) -> Result<Product> {
    let transform = measured_transform(outcome)?;
    let grid = Grid::of_header(
        reference.0,
        reference.1,
        reference.2,
        outcome.reference_geometry,
    );
    let history = alignment_history(reference.1, frame.1, &transform, outcome, true);
    let data = resampled(&grid, frame.2, &transform);
    let cards = product_cards_of(frame.0, frame.1, &grid, history, &[], true);
    Ok((data, cards))
}

/// The frame's header with its pointing corrected from the measurement, its pixels left as
/// they are (`--wcs-only`'s product for a pair): the reference's WCS seen through the measured
/// transform, so each pixel gets the world coordinates of the matching reference pixel.
/// Returns the product's header cards.
pub fn corrected_pointing_cards(
    reference: (&Header, &FrameMeta, (usize, usize)),
    frame: (&Header, &FrameMeta, (usize, usize)),
    outcome: &AlignOutcome,
) -> Result<Vec<(String, HeaderValue)>> {
    let transform = measured_transform(outcome)?;
    let origin = Grid::of_header(
        reference.0,
        reference.1,
        reference.2,
        outcome.reference_geometry,
    );
    // The identity first: the reference's roll stated as PCi_j, however its header gave it.
    let identity = Similarity::identity(Similarity::array_center(1, 1));
    let grid = Grid {
        cards: compose_wcs(&compose_wcs(&origin.cards, &identity), &transform.inverse()),
        shape: frame.2,
        notes: origin.notes,
    };
    let history = alignment_history(reference.1, frame.1, &transform, outcome, false);
    Ok(product_cards_of(
        frame.0,
        frame.1,
        &grid,
        history,
        &[],
        false,
    ))
}

/// The measured grid-to-grid transform; an error saying why where the alignment failed.
fn measured_transform(outcome: &AlignOutcome) -> Result<Similarity> {
    outcome.transform.ok_or_else(|| {
        let why = outcome.result.message.lines().next().unwrap_or("");
        Error::AlignmentFailed(format!("{why}; no transform to apply"))
    })
}

/// A pixel grid as a header describes it: its cards (those [`is_grid_key`] names), its shape
/// `(height, width)`, and `HISTORY` lines about how the cards were made.
#[derive(Debug, Clone, PartialEq)]
pub struct Grid {
    pub cards: Vec<(String, HeaderValue)>,
    pub shape: (usize, usize),
    pub notes: Vec<String>,
}

impl Grid {
    /// The grid of `image` as its header gives it, the roll in `PCi_j` (see [`compose_wcs`]);
    /// where the alignment used a disk-checked geometry instead (`used.from_disk`), with that
    /// plate scale and Sun centre.
    pub fn of_image(image: &Image, used: Option<UsedGeometry>) -> Result<Grid> {
        let (_, header) = fits::read_image_header_as_read(&image.meta)?;
        Ok(Grid::of_header(
            &header,
            &image.meta,
            image.data.dim(),
            used,
        ))
    }

    /// [`Grid::of_image`] from the image's header (as read), metadata and shape.
    pub fn of_header(
        header: &Header,
        meta: &FrameMeta,
        shape: (usize, usize),
        used: Option<UsedGeometry>,
    ) -> Grid {
        let mut cards: Vec<(String, HeaderValue)> = fits::frame_header_cards(header, meta)
            .into_iter()
            .filter(|(k, _)| is_grid_key(k))
            .map(|(k, v)| {
                // `frame_header_cards` removed the third axis; a cube's WCSAXES = 3 no longer holds.
                let v = if k.starts_with("WCSAXES") {
                    HeaderValue::Int(2)
                } else {
                    v
                };
                (k, v)
            })
            .collect();
        let notes = match used.filter(|g| g.from_disk) {
            Some(used) => use_checked_geometry(&mut cards, meta, &used),
            None => Vec::new(),
        };
        // The roll as the alignment read it, stated in `PCi_j` whichever card gave it
        // (`CROTA2`, SOHO's `SC_ROLL`): astropy and sunpy read no instrument keys.
        let cards = compose_wcs(&cards, &Similarity::identity([0.0, 0.0]));
        Grid {
            cards,
            shape,
            notes,
        }
    }
}

/// `frame` resampled onto `grid` through `transform` (grid pixel → frame pixel; the identity
/// copies the pixels as they are), written as f32 FITS with the frame's cards, the grid's, the
/// frame's `HISTORY` followed by `history` and the grid's notes, and `extra` cards.
pub fn write_resampled(
    path: &Path,
    grid: &Grid,
    frame: &Image,
    transform: &Similarity,
    history: Vec<String>,
    extra: &[(String, HeaderValue)],
) -> Result<()> {
    let data = resampled(grid, frame.data.view(), transform);
    let cards = product_cards(grid, frame, history, extra, true)?;
    fits::write_image(path, data.view(), &cards)
}

/// `frame` resampled onto `grid` through `transform`.
fn resampled(grid: &Grid, frame: ArrayView2<f32>, transform: &Similarity) -> Array2<f32> {
    let (h, w) = grid.shape;
    let identity = transform.scale == 1.0
        && transform.rotation_rad == 0.0
        && transform.dx == 0.0
        && transform.dy == 0.0
        && frame.dim() == grid.shape;
    if identity {
        frame.to_owned()
    } else {
        HighOrderSpline::new(frame, refine::MODEL).warp_similarity(transform, w, h)
    }
}

/// The frame's own pixels with `grid`'s cards in place of its own: a header-only correction.
pub fn write_regridded_header(
    path: &Path,
    grid: &Grid,
    frame: &Image,
    history: Vec<String>,
    extra: &[(String, HeaderValue)],
) -> Result<()> {
    let cards = product_cards(grid, frame, history, extra, false)?;
    fits::write_image(path, frame.data.view(), &cards)
}

fn product_cards(
    grid: &Grid,
    frame: &Image,
    history: Vec<String>,
    extra: &[(String, HeaderValue)],
    resampled: bool,
) -> Result<Vec<(String, HeaderValue)>> {
    let (_, frame_header) = fits::read_image_header_as_read(&frame.meta)?;
    Ok(product_cards_of(
        &frame_header,
        &frame.meta,
        grid,
        history,
        extra,
        resampled,
    ))
}

/// [`product_cards`] from the frame's header (as read) and metadata.
fn product_cards_of(
    frame_header: &Header,
    frame: &FrameMeta,
    grid: &Grid,
    history: Vec<String>,
    extra: &[(String, HeaderValue)],
    resampled: bool,
) -> Vec<(String, HeaderValue)> {
    let mut frame_cards = fits::frame_header_cards(frame_header, frame);
    frame_cards.retain(|(k, _)| !extra.iter().any(|(e, _)| e == k));
    let mut all_history = commentary(frame_header, "HISTORY");
    all_history.extend(history);
    all_history.extend(grid.notes.iter().cloned());
    let comments = commentary(frame_header, "COMMENT");
    let mut cards = aligned_header_cards(&grid.cards, &frame_cards, &comments, &[], !resampled);
    cards.extend(extra.iter().cloned());
    cards.extend(
        all_history
            .into_iter()
            .map(|t| ("HISTORY".to_string(), HeaderValue::Str(t))),
    );
    cards
}

/// The grid `cards` describe, seen through `m` (new pixel → old pixel, 0-based): the WCS whose
/// world coordinates at pixel `q` are the old WCS's at `m(q)`. Exact for any projection: only
/// the linear part changes. `CRPIXi` moves, `CDi_j` becomes `CD·L` (L = s R(θ)); otherwise
/// `CDELTi` is multiplied by `s` and `PCi_j` (from `CROTA2`, or `SC_ROLL`, where the header has
/// no matrix) becomes `PC·R(θ)`, with `CROTAi` removed. `CRVALi`, `CTYPEi`, `CUNITi` stay. Cards that
/// would describe the old grid otherwise (alternate WCS, `XCEN`/`YCEN`, `FOVX`/`FOVY`, `*_MP`,
/// roll and spacecraft-pointing keys) go.
pub fn compose_wcs(cards: &[(String, HeaderValue)], m: &Similarity) -> Vec<(String, HeaderValue)> {
    let get = |k: &str| {
        cards
            .iter()
            .find(|(c, _)| c == k)
            .and_then(|(_, v)| v.as_f64())
    };
    let ij = [(1, 1), (1, 2), (2, 1), (2, 2)];
    let (a, b) = m.ab();
    let l = [[a, -b], [b, a]];
    let matmul = |x: [[f64; 2]; 2], y: [[f64; 2]; 2]| {
        let mut z = [[0.0; 2]; 2];
        for (r, row) in z.iter_mut().enumerate() {
            for (c, v) in row.iter_mut().enumerate() {
                *v = x[r][0] * y[0][c] + x[r][1] * y[1][c];
            }
        }
        z
    };
    let crpix = [get("CRPIX1").unwrap_or(0.0), get("CRPIX2").unwrap_or(0.0)];
    // FITS pixels are 1-based: m(q) = L (q − c) + c + d holds with c + 1 for c.
    let c1 = [m.center[0] + 1.0, m.center[1] + 1.0];
    let v = [c1[0] + m.dx - crpix[0], c1[1] + m.dy - crpix[1]];
    let det = a * a + b * b;
    let new_crpix = if (a, b, m.dx, m.dy) == (1.0, 0.0, 0.0, 0.0) {
        crpix
    } else {
        [
            c1[0] - (a * v[0] + b * v[1]) / det,
            c1[1] - (-b * v[0] + a * v[1]) / det,
        ]
    };
    let has_cd = ij.iter().any(|(i, j)| get(&format!("CD{i}_{j}")).is_some());
    let mut linear: Vec<(String, f64)> = Vec::new();
    if has_cd {
        let cd = [
            [get("CD1_1").unwrap_or(0.0), get("CD1_2").unwrap_or(0.0)],
            [get("CD2_1").unwrap_or(0.0), get("CD2_2").unwrap_or(0.0)],
        ];
        let new = matmul(cd, l);
        linear.extend(ij.map(|(i, j)| (format!("CD{i}_{j}"), new[i - 1][j - 1])));
    } else {
        let cdelt = [get("CDELT1").unwrap_or(1.0), get("CDELT2").unwrap_or(1.0)];
        let has_pc = ij.iter().any(|(i, j)| get(&format!("PC{i}_{j}")).is_some());
        let has_old_pc = ij
            .iter()
            .any(|(i, j)| get(&format!("PC00{i}00{j}")).is_some());
        let pc = if has_pc || has_old_pc {
            let at = |i: usize, j: usize| {
                get(&format!("PC{i}_{j}"))
                    .or_else(|| get(&format!("PC00{i}00{j}")))
                    .unwrap_or(if i == j { 1.0 } else { 0.0 })
            };
            [[at(1, 1), at(1, 2)], [at(2, 1), at(2, 2)]]
        } else {
            // FITS WCS Paper II, the CROTA2 convention; SOHO's SC_ROLL where nothing else
            // gives the roll, as the headers are read for alignment.
            let rho = get("CROTA2")
                .or_else(|| get("CROTA1"))
                .or_else(|| get("CROTA"))
                .or_else(|| get("SC_ROLL"))
                .unwrap_or(0.0);
            let (s, c) = sin_cos_deg(rho);
            let ratio = if cdelt[0] != 0.0 {
                cdelt[1] / cdelt[0]
            } else {
                1.0
            };
            [[c, -s * ratio], [s / ratio, c]]
        };
        let (sin, cos) = m.rotation_rad.sin_cos();
        let new = matmul(pc, [[cos, -sin], [sin, cos]]);
        linear.push(("CDELT1".into(), cdelt[0] * m.scale));
        linear.push(("CDELT2".into(), cdelt[1] * m.scale));
        linear.extend(ij.map(|(i, j)| (format!("PC{i}_{j}"), new[i - 1][j - 1])));
    }
    const STALE: [&str; 12] = [
        "XCEN", "YCEN", "FOVX", "FOVY", "X0_MP", "Y0_MP", "IMSCL_MP", "SC_ROLL", "SC_X0", "SC_Y0",
        "SAT_ROT", "INST_ROT",
    ];
    let replaced = |k: &str| {
        matches!(
            k,
            "CRPIX1" | "CRPIX2" | "CDELT1" | "CDELT2" | "CROTA" | "CROTA1" | "CROTA2"
        ) || ["PC", "CD"].iter().any(|p| {
            k.strip_prefix(p)
                .and_then(|r| r.split_once('_'))
                .is_some_and(|(i, j)| matches!(i, "1" | "2") && matches!(j, "1" | "2"))
        }) || k.strip_prefix("PC00").is_some_and(|r| r.len() == 4)
    };
    let mut out: Vec<(String, HeaderValue)> = cards
        .iter()
        .filter(|(k, _)| !replaced(k) && !is_alternate_grid_key(k) && !STALE.contains(&k.as_str()))
        .cloned()
        .collect();
    out.push(("CRPIX1".into(), HeaderValue::Float(new_crpix[0])));
    out.push(("CRPIX2".into(), HeaderValue::Float(new_crpix[1])));
    out.extend(linear.into_iter().map(|(k, v)| (k, HeaderValue::Float(v))));
    out
}

/// sin and cos of an angle in degrees, exact at multiples of 90° (a roll of 180° gives
/// `PC1_2 = 0`, not 1.2e-16).
fn sin_cos_deg(deg: f64) -> (f64, f64) {
    let quarter = deg / 90.0;
    if quarter == quarter.round() && quarter.abs() < 1e9 {
        match (quarter as i64).rem_euclid(4) {
            0 => (0.0, 1.0),
            1 => (1.0, 0.0),
            2 => (0.0, -1.0),
            _ => (-1.0, 0.0),
        }
    } else {
        deg.to_radians().sin_cos()
    }
}

/// Where the reference's header was refused for the disk its image shows, the alignment used
/// the disk-checked plate scale and Sun centre: the aligned image's WCS says so too.
/// `CDELTi` (or the columns of `CDi_j`) are scaled to the plate scale used, the reference point
/// moves to the Sun centre used (`CRPIXi` there, `CRVALi` = 0, exact for any zenithal
/// projection), radii in pixels (`SOLAR_R`, `R_SUN`) follow the plate scale, and cards that
/// describe the old grid otherwise (alternate WCS, `XCEN`/`YCEN`, `FOVX`/`FOVY`, `*_MP`) go.
/// Returns the HISTORY lines that say what was done.
pub(crate) fn use_checked_geometry(
    cards: &mut Vec<(String, HeaderValue)>,
    header: &FrameMeta,
    used: &UsedGeometry,
) -> Vec<String> {
    let factor = [0, 1].map(|j| {
        let old = header.plate_scale_arcsec[j].abs();
        if old > 0.0 {
            used.plate_scale_arcsec[j].abs() / old
        } else {
            1.0
        }
    });
    let has = |cards: &[(String, HeaderValue)], k: &str| cards.iter().any(|(c, _)| c == k);
    let uses_cd = ["CD1_1", "CD1_2", "CD2_1", "CD2_2"]
        .iter()
        .any(|k| has(cards, k));
    const OLD_GRID: [&str; 7] = ["XCEN", "YCEN", "FOVX", "FOVY", "X0_MP", "Y0_MP", "IMSCL_MP"];
    cards.retain(|(k, _)| !(OLD_GRID.contains(&k.as_str()) || is_alternate_grid_key(k)));
    let rsun = header.rsun_arcsec;
    let old_plate = header.plate_scale_arcsec[0].abs();
    for (key, value) in cards.iter_mut() {
        let scaled = |v: &HeaderValue, f: f64| v.as_f64().map(|x| HeaderValue::Float(x * f));
        let new = match key.as_str() {
            "CDELT1" if !uses_cd => scaled(value, factor[0]),
            "CDELT2" if !uses_cd => scaled(value, factor[1]),
            "CD1_1" | "CD2_1" => scaled(value, factor[0]),
            "CD1_2" | "CD2_2" => scaled(value, factor[1]),
            "CRPIX1" => Some(HeaderValue::Float(used.sun_center_px[0] + 1.0)),
            "CRPIX2" => Some(HeaderValue::Float(used.sun_center_px[1] + 1.0)),
            "CRVAL1" | "CRVAL2" => Some(HeaderValue::Float(0.0)),
            // A radius in pixels of the header's grid (its product with that plate scale is
            // the Sun's radius in arcsec), now in pixels of the grid used.
            "SOLAR_R" | "R_SUN" => value.as_f64().and_then(|r| {
                let in_pixels = rsun.is_some_and(|a| (r * old_plate / a - 1.0).abs() < 0.01);
                in_pixels.then(|| HeaderValue::Float(r / factor[0]))
            }),
            _ => None,
        };
        if let Some(new) = new {
            *value = new;
        }
    }
    for (key, value) in [
        ("CRPIX1", used.sun_center_px[0] + 1.0),
        ("CRPIX2", used.sun_center_px[1] + 1.0),
        ("CRVAL1", 0.0),
        ("CRVAL2", 0.0),
    ] {
        if !has(cards, key) {
            cards.push((key.to_string(), HeaderValue::Float(value)));
        }
    }
    for (j, key) in ["CDELT1", "CDELT2"].into_iter().enumerate() {
        if !uses_cd && !has(cards, key) {
            cards.push((key.to_string(), HeaderValue::Float(factor[j])));
        }
    }
    let p = used.plate_scale_arcsec;
    let c = used.sun_center_px;
    vec![
        "the reference header's disk disagreed with its image: the alignment".to_string(),
        format!(
            "used {:.6}, {:.6} arcsec/px (header: {:.6}, {:.6})",
            p[0].abs(),
            p[1].abs(),
            header.plate_scale_arcsec[0].abs(),
            header.plate_scale_arcsec[1].abs()
        ),
        format!(
            "and Sun centre ({:.3}, {:.3}) px, 0-based (header: ({:.3}, {:.3}))",
            c[0], c[1], header.sun_center_px[0], header.sun_center_px[1]
        ),
        "WCS written with these: CDELT, CRPIX at the Sun centre, CRVAL = 0".to_string(),
    ]
}

/// An alternate description (`…A`–`…Z`) of axes 1–2.
fn is_alternate_grid_key(key: &str) -> bool {
    is_grid_key(key)
        && key
            .as_bytes()
            .last()
            .is_some_and(|b| b.is_ascii_uppercase())
        && key.len() > 1
        && {
            let stem = &key[..key.len() - 1];
            stem.bytes().last().is_some_and(|b| b.is_ascii_digit())
                || ["WCSAXES", "WCSNAME", "LONPOLE", "LATPOLE", "RADESYS"].contains(&stem)
        }
}

/// Red = reference, green + blue = frame; the frame through the coarse (header) transform on
/// the left, through the measured one on the right (the paper's figure 6). Where the two
/// agree the picture is grey; misregistered structure shows red/cyan fringes. Below, the
/// difference frame − reference of each, on a blue–white–red scale shared by both, so a
/// residual sub-pixel motion shows as paired blue/red edges.
pub fn write_quicklook(
    path: &Path,
    reference: &Image,
    frame: &Image,
    outcome: &AlignOutcome,
) -> Result<()> {
    let transform = require_transform(path, outcome)?;
    let (h, w) = reference.data.dim();
    let coarse = outcome
        .coarse
        .unwrap_or_else(|| Similarity::identity(Similarity::array_center(w, h)));
    let panels = quicklook_panels(
        reference.data.view(),
        frame.data.view(),
        &coarse,
        &transform,
    )
    .ok_or_else(|| {
        Error::output(
            path,
            "no finite pixels to show; nothing written".to_string(),
        )
    })?;
    let when = |m: &FrameMeta| m.obs_time_iso().unwrap_or_else(|| "time unknown".into());
    let r = &outcome.result;
    // No "-0.0000": a sign only on a non-zero digit.
    let num = |v: Option<f64>, d: usize| {
        v.map_or("?".to_string(), |v| {
            let s = format!("{v:.d$}");
            if s.bytes().all(|b| matches!(b, b'-' | b'0' | b'.')) {
                s.trim_start_matches('-').to_string()
            } else {
                s
            }
        })
    };
    let captions = Captions {
        reference: (
            "reference (red): ".into(),
            format!("{}   {}", describe(&reference.meta), when(&reference.meta)),
        ),
        frame: (
            "frame (cyan): ".into(),
            format!("{}   {}", describe(&frame.meta), when(&frame.meta)),
        ),
        measured: (
            "measured: ".into(),
            format!(
                "dx {} ± {} px, dy {} ± {} px, rotation {}″, scale {}",
                num(r.dx_px, 4),
                num(r.sigma_dx_px, 4),
                num(r.dy_px, 4),
                num(r.sigma_dy_px, 4),
                num(r.rotation_arcsec, 1),
                num(r.scale, 5)
            ),
        ),
        before: format!(
            "before: header (coarse) transform, dx {:.2} dy {:.2} px",
            coarse.dx, coarse.dy
        ),
        after: format!(
            "after: measured transform, dx {:.3} dy {:.3} px",
            transform.dx, transform.dy
        ),
    };
    let look = render_quicklook(&panels, &captions)
        .map_err(|e| Error::output(path, format!("cannot draw the quick-look: {e}")))?;
    write_png(path, &look)
}

fn require_transform(path: &Path, outcome: &AlignOutcome) -> Result<Similarity> {
    outcome.transform.ok_or_else(|| {
        let why = outcome.result.message.lines().next().unwrap_or("");
        Error::output(path, format!("alignment failed ({why}); nothing written"))
    })
}

// ---------------------------------------------------------------------------------------------
// Aligned FITS header
// ---------------------------------------------------------------------------------------------

/// Frame cards without its grid description (and without the data statistics unless the
/// pixels are the frame's own), then the reference's grid cards, then the frame's comments and
/// the history.
fn aligned_header_cards(
    reference_cards: &[(String, HeaderValue)],
    frame_cards: &[(String, HeaderValue)],
    comments: &[String],
    history: &[String],
    keep_statistics: bool,
) -> Vec<(String, HeaderValue)> {
    let mut cards: Vec<(String, HeaderValue)> = frame_cards
        .iter()
        .filter(|(k, _)| {
            !is_grid_key(k) && (keep_statistics || !is_data_statistic(k)) && !is_container_key(k)
        })
        .cloned()
        .collect();
    for (key, value) in reference_cards.iter().filter(|(k, _)| is_grid_key(k)) {
        // `frame_header_cards` removed the third axis; a cube's WCSAXES = 3 no longer holds.
        let value = if key.starts_with("WCSAXES") {
            HeaderValue::Int(2)
        } else {
            value.clone()
        };
        cards.push((key.clone(), value));
    }
    let commentary_cards = |key: &str, lines: &[String]| {
        lines
            .iter()
            .map(|t| (key.to_string(), HeaderValue::Str(t.clone())))
            .collect::<Vec<_>>()
    };
    cards.extend(commentary_cards("COMMENT", comments));
    cards.extend(commentary_cards("HISTORY", history));
    cards
}

/// Cards that describe the pixel grid of axes 1–2 (the WCS, with alternates `…A`–`…Z`) or the
/// instrument's pointing in grid terms. On the aligned image these are the reference's.
pub fn is_grid_key(key: &str) -> bool {
    const INSTRUMENT_GRID: [&str; 14] = [
        "XCEN", "YCEN", "FOVX", "FOVY", "SOLAR_R", "R_SUN", "X0_MP", "Y0_MP", "IMSCL_MP",
        "SC_ROLL", "SC_X0", "SC_Y0", "SAT_ROT", "INST_ROT",
    ];
    const AXIS_KEYS: [&str; 9] = [
        "CTYPE", "CUNIT", "CRPIX", "CRVAL", "CDELT", "CROTA", "CNAME", "CRDER", "CSYER",
    ];
    if INSTRUMENT_GRID.contains(&key) || key == "CROTA" {
        return true;
    }
    // Alternate WCS descriptions carry one trailing letter.
    let base = match key.as_bytes().last() {
        Some(b) if b.is_ascii_uppercase() && key.len() > 1 => {
            let stem = &key[..key.len() - 1];
            if stem.bytes().last().is_some_and(|b| b.is_ascii_digit())
                || ["WCSAXES", "WCSNAME", "LONPOLE", "LATPOLE", "RADESYS"].contains(&stem)
            {
                stem
            } else {
                key
            }
        }
        _ => key,
    };
    if [
        "WCSAXES", "WCSNAME", "LONPOLE", "LATPOLE", "RADESYS", "EQUINOX",
    ]
    .contains(&base)
    {
        return true;
    }
    let axis12 = |n: &str| n == "1" || n == "2";
    if AXIS_KEYS
        .iter()
        .any(|p| base.strip_prefix(p).is_some_and(axis12))
    {
        return true;
    }
    // PCi_j, CDi_j, PVi_m, PSi_m, and the old PC00i00j.
    let matrix = ["PC", "CD", "PV", "PS"].iter().any(|p| {
        base.strip_prefix(p)
            .and_then(|ij| ij.split_once('_'))
            .is_some_and(|(i, j)| axis12(i) && j.parse::<u32>().is_ok())
    });
    let old_pc = base
        .strip_prefix("PC00")
        .is_some_and(|r| r.len() == 4 && axis12(&r[..1]) && &r[1..3] == "00" && axis12(&r[3..]));
    matrix || old_pc
}

/// Cards of the HDU that held the frame rather than of the image: extension and binary-table
/// structure, and the tile compression of `ZIMAGE` files (whose header is a table's). The
/// output is a plain primary image.
fn is_container_key(key: &str) -> bool {
    const EXACT: [&str; 24] = [
        "EXTNAME", "EXTVER", "EXTLEVEL", "INHERIT", "TFIELDS", "THEAP", "ZIMAGE", "ZSIMPLE",
        "ZBITPIX", "ZNAXIS", "ZCMPTYPE", "ZMASKCMP", "ZQUANTIZ", "ZDITHER0", "ZBLANK", "ZSCALE",
        "ZZERO", "ZHECKSUM", "ZDATASUM", "ZEXTEND", "ZPCOUNT", "ZGCOUNT", "ZTENSION", "ZBLOCKED",
    ];
    const NUMBERED: [&str; 13] = [
        "TTYPE", "TFORM", "TUNIT", "TDIM", "TZERO", "TSCAL", "TNULL", "TDISP", "TBCOL", "ZNAXIS",
        "ZTILE", "ZNAME", "ZVAL",
    ];
    EXACT.contains(&key)
        || NUMBERED.iter().any(|p| {
            key.strip_prefix(p)
                .is_some_and(|n| !n.is_empty() && n.bytes().all(|b| b.is_ascii_digit()))
        })
}

/// Statistics of the original pixel values (and checksums) that resampling makes false.
fn is_data_statistic(key: &str) -> bool {
    matches!(
        key,
        "CHECKSUM"
            | "DATASUM"
            | "DATAMIN"
            | "DATAMAX"
            | "DATAMEAN"
            | "DATAMEDN"
            | "DATARMS"
            | "DATASKEW"
            | "DATAKURT"
            | "DATAVALS"
            | "MISSVALS"
            | "TOTVALS"
            | "PERCENTD"
    ) || key
        .strip_prefix("DATAP")
        .is_some_and(|p| p.len() == 2 && p.bytes().all(|b| b.is_ascii_digit()))
}

/// The text of a header's commentary cards named `key` (`HISTORY`, `COMMENT`).
fn commentary(header: &Header, key: &str) -> Vec<String> {
    header
        .cards()
        .iter()
        .filter(|c| c.key == key && c.value.is_none())
        .map(|c| c.comment.trim().to_string())
        .filter(|t| !t.is_empty())
        .collect()
}

fn describe(meta: &FrameMeta) -> String {
    match meta.frame {
        Some(n) => format!("{}[{n}]", meta.file.display()),
        None => meta.file.display().to_string(),
    }
}

fn alignment_history(
    reference: &FrameMeta,
    frame: &FrameMeta,
    t: &Similarity,
    outcome: &AlignOutcome,
    resampled: bool,
) -> Vec<String> {
    let r = &outcome.result;
    let status = serde_json::to_value(r.status)
        .ok()
        .and_then(|v| v.as_str().map(str::to_string))
        .unwrap_or_default();
    let sig = |v: Option<f64>| v.map_or("?".to_string(), |v| format!("{v:.3e}"));
    // Short lines: each fits one 72-character HISTORY card (paths may still wrap).
    let (what, how) = if resampled {
        (
            "frame resampled onto the reference's pixel grid",
            "quintic B-spline; NaN where the frame has no data; WCS = reference's",
        )
    } else {
        (
            "frame's pointing corrected, pixels as they were",
            "WCS = reference's, seen through the transform below",
        )
    };
    vec![
        format!("sunjitter {}: {what}", env!("CARGO_PKG_VERSION")),
        format!("reference: {}", describe(reference)),
        format!("frame: {}", describe(frame)),
        how.to_string(),
        format!(
            "p_frame = s R(theta) (p_ref - c) + c + (dx, dy), c = ({}, {}) px",
            t.center[0], t.center[1]
        ),
        format!(
            "scale = {:.9}, rotation = {:.6} arcsec",
            t.scale,
            t.rotation_arcsec()
        ),
        format!("dx = {:.6} px, dy = {:.6} px (0-based pixels)", t.dx, t.dy),
        format!(
            "sigma: scale {}, rotation {} arcsec",
            sig(r.sigma_scale),
            sig(r.sigma_rotation_arcsec)
        ),
        format!(
            "sigma: dx {} px, dy {} px; status {status}",
            sig(r.sigma_dx_px),
            sig(r.sigma_dy_px)
        ),
    ]
}

#[cfg(test)]
mod tests {
    use super::quicklook::{resize, Panels, GAP_PX};
    use super::*;
    /// A bundled real image's pixels.
    fn read_real(name: &str) -> Array2<f32> {
        let path = format!("{}/../../data/real/{name}", env!("CARGO_MANIFEST_DIR"));
        fits::read_frame(&fits::FrameSpec::parse(&path))
            .expect("bundled image")
            .data
    }
    use sunjitter_core::resample::SplineImage;

    #[test]
    fn grid_keys_are_the_wcs_of_axes_one_and_two_and_pointing() {
        for k in [
            "CRPIX1", "CRPIX2", "CDELT1", "CDELT2", "CRVAL1", "CTYPE2", "CUNIT1", "CROTA2",
            "CROTA", "PC1_1", "PC2_1", "CD1_2", "PV2_1", "PC001001", "PC002001", "CRPIX1A",
            "WCSAXES", "WCSNAME", "LONPOLE", "XCEN", "SOLAR_R", "SC_ROLL",
        ] {
            assert!(is_grid_key(k), "{k}");
        }
        for k in [
            "CRPIX3", "PC3_1", "DATE-OBS", "EXPTIME", "INSTRUME", "WAVELNTH", "RSUN_OBS",
            "DSUN_OBS", "CDELT12", "PCOUNT", "CROTAX", "TELESCOP",
        ] {
            assert!(!is_grid_key(k), "{k}");
        }
        // Tile-compressed AIA/HMI files: the header is a binary table's.
        for k in [
            "ZIMAGE", "ZNAXIS1", "ZTILE2", "ZCMPTYPE", "TFORM1", "TTYPE1", "EXTNAME",
        ] {
            assert!(is_container_key(k), "{k}");
        }
        // IRIS slit-jaw per-window keys are not table structure.
        for k in ["TDESC1", "TWAVE1", "TDET1", "TDMEAN1", "TSR1", "ZNAXIS_X"] {
            assert!(!is_container_key(k), "{k}");
        }
        assert!(is_data_statistic("DATAP99") && is_data_statistic("CHECKSUM"));
        assert!(!is_data_statistic("DATAP1") && !is_data_statistic("DATE"));
    }

    #[test]
    fn aligned_header_takes_the_grid_from_the_reference_and_the_rest_from_the_frame() {
        let s = |k: &str, v: HeaderValue| (k.to_string(), v);
        let reference = vec![
            s("CRPIX1", HeaderValue::Float(512.5)),
            s("CDELT1", HeaderValue::Float(0.5)),
            s("PC1_2", HeaderValue::Float(0.01)),
            s("WCSAXES", HeaderValue::Int(3)),
            s("DATE-OBS", HeaderValue::Str("2000-01-01T00:00:00".into())),
        ];
        let frame = vec![
            s("CRPIX1", HeaderValue::Float(64.5)),
            s("CROTA2", HeaderValue::Float(180.0)),
            s("DATE-OBS", HeaderValue::Str("2011-02-15T00:00:01".into())),
            s("DATAMAX", HeaderValue::Float(9.0)),
            s("EXPTIME", HeaderValue::Float(2.0)),
        ];
        let cards = aligned_header_cards(&reference, &frame, &[], &["did it".to_string()], false);
        let get = |k: &str| {
            let v: Vec<_> = cards.iter().filter(|(c, _)| c == k).collect();
            assert!(v.len() <= 1, "{k} twice");
            v.first().map(|(_, v)| v.clone())
        };
        assert_eq!(get("CRPIX1"), Some(HeaderValue::Float(512.5)));
        assert_eq!(get("CDELT1"), Some(HeaderValue::Float(0.5)));
        assert_eq!(get("PC1_2"), Some(HeaderValue::Float(0.01)));
        assert_eq!(get("WCSAXES"), Some(HeaderValue::Int(2)));
        assert_eq!(get("CROTA2"), None, "the frame's roll must not survive");
        assert_eq!(get("DATAMAX"), None);
        assert_eq!(
            get("DATE-OBS"),
            Some(HeaderValue::Str("2011-02-15T00:00:01".into()))
        );
        assert_eq!(get("EXPTIME"), Some(HeaderValue::Float(2.0)));
        assert_eq!(get("HISTORY"), Some(HeaderValue::Str("did it".into())));
    }

    /// Intermediate world coordinates (CD · (p − CRPIX), 0-based p) of a header's cards,
    /// evaluated the way FITS WCS Paper I/II define them, independently of `compose_wcs`.
    fn intermediate(cards: &[(String, HeaderValue)], p: [f64; 2]) -> [f64; 2] {
        let get = |k: &str| {
            cards
                .iter()
                .find(|(c, _)| c == k)
                .and_then(|(_, v)| v.as_f64())
        };
        let d = [
            p[0] + 1.0 - get("CRPIX1").unwrap(),
            p[1] + 1.0 - get("CRPIX2").unwrap(),
        ];
        let m = if get("CD1_1").is_some() {
            [
                [get("CD1_1").unwrap(), get("CD1_2").unwrap()],
                [get("CD2_1").unwrap(), get("CD2_2").unwrap()],
            ]
        } else {
            let c = [get("CDELT1").unwrap(), get("CDELT2").unwrap()];
            let (pc11, pc12, pc21, pc22) = match get("PC1_1") {
                Some(_) => (
                    get("PC1_1").unwrap(),
                    get("PC1_2").unwrap(),
                    get("PC2_1").unwrap(),
                    get("PC2_2").unwrap(),
                ),
                None => {
                    let r = get("CROTA2").unwrap_or(0.0).to_radians();
                    (
                        r.cos(),
                        -r.sin() * c[1] / c[0],
                        r.sin() * c[0] / c[1],
                        r.cos(),
                    )
                }
            };
            [[c[0] * pc11, c[0] * pc12], [c[1] * pc21, c[1] * pc22]]
        };
        [
            m[0][0] * d[0] + m[0][1] * d[1],
            m[1][0] * d[0] + m[1][1] * d[1],
        ]
    }

    /// Truth: the definition. The composed WCS at q equals the original at m(q), for the
    /// three ways a header states its linear part.
    #[test]
    fn a_composed_wcs_at_q_is_the_original_at_m_of_q() {
        let f = |k: &str, v: f64| (k.to_string(), HeaderValue::Float(v));
        let common = vec![
            f("CRPIX1", 512.5),
            f("CRPIX2", 498.25),
            f("CRVAL1", -120.0),
            f("CRVAL2", 35.0),
            ("CTYPE1".to_string(), HeaderValue::Str("HPLN-TAN".into())),
            f("XCEN", 3.0),
        ];
        let crota = [f("CDELT1", 0.6), f("CDELT2", 0.61), f("CROTA2", 12.5)];
        let pc = [
            f("CDELT1", -0.6),
            f("CDELT2", 0.6),
            f("PC1_1", 0.99),
            f("PC1_2", -0.02),
            f("PC2_1", 0.03),
            f("PC2_2", 0.98),
        ];
        let cd = [
            f("CD1_1", 2.6),
            f("CD1_2", 0.01),
            f("CD2_1", -0.02),
            f("CD2_2", 2.63),
        ];
        let m = Similarity {
            scale: 1.003,
            rotation_rad: 0.021,
            dx: 2.7,
            dy: -1.4,
            center: [511.5, 511.5],
        };
        for linear in [&crota[..], &pc[..], &cd[..]] {
            let mut cards = common.clone();
            cards.extend(linear.iter().cloned());
            let composed = compose_wcs(&cards, &m);
            for q in [[0.0, 0.0], [1023.0, 17.0], [300.5, 800.25]] {
                let want = intermediate(&cards, m.apply(q));
                let got = intermediate(&composed, q);
                for k in 0..2 {
                    assert!(
                        (want[k] - got[k]).abs() < 1e-9,
                        "{linear:?} {q:?}: {got:?} vs {want:?}"
                    );
                }
            }
            let keys: Vec<&str> = composed.iter().map(|(k, _)| k.as_str()).collect();
            assert!(
                !keys.contains(&"CROTA2") && !keys.contains(&"XCEN"),
                "{keys:?}"
            );
            assert!(keys.contains(&"CRVAL1") && keys.contains(&"CTYPE1"));
            // Through m and back: the original grid.
            let back = compose_wcs(&composed, &m.inverse());
            for q in [[10.0, 20.0], [900.0, 5.0]] {
                let (a, b) = (intermediate(&cards, q), intermediate(&back, q));
                assert!((a[0] - b[0]).abs() < 1e-9 && (a[1] - b[1]).abs() < 1e-9);
            }
        }
    }

    /// Pearson correlation of the red and green channels of one composite, inside a circle.
    fn panel_rg_correlation(p: &Panels, panel: usize, center: [f64; 2], r: f64) -> f64 {
        let rgb = &p.composites[panel];
        let (mut n, mut sr, mut sg, mut srr, mut sgg, mut srg) = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0);
        for y in 0..p.height {
            for x in 0..p.width {
                if (x as f64 - center[0]).hypot(y as f64 - center[1]) > r {
                    continue;
                }
                let i = 3 * (y * p.width + x);
                let (a, b) = (rgb[i] as f64, rgb[i + 1] as f64);
                n += 1.0;
                sr += a;
                sg += b;
                srr += a * a;
                sgg += b * b;
                srg += a * b;
            }
        }
        let cov = srg / n - sr * sg / n / n;
        cov / ((srr / n - (sr / n).powi(2)) * (sgg / n - (sg / n).powi(2))).sqrt()
    }

    /// RMS of a difference panel's finite pixels inside a circle.
    fn panel_rms(d: &Array2<f32>, center: [f64; 2], r: f64) -> f64 {
        let (mut n, mut s) = (0.0, 0.0);
        for ((y, x), v) in d.indexed_iter() {
            if v.is_finite() && (x as f64 - center[0]).hypot(y as f64 - center[1]) <= r {
                n += 1.0;
                s += (*v as f64).powi(2);
            }
        }
        (s / n).sqrt()
    }

    /// Truth: a real full-disk AIA image and a copy moved by a known similarity. The fine panel
    /// renders the frame through that very transform, the coarse panel through the identity:
    /// the fine panel must show the two images in register (red = cyan), the coarse one not.
    #[test]
    fn fine_panel_registers_a_known_misaligned_pair_better_than_the_coarse_panel() {
        let reference = read_real("aia_171_20110215T000000_128.fits");
        let (h, w) = reference.dim();
        let center = Similarity::array_center(w, h);
        let truth = Similarity {
            scale: 1.003,
            rotation_rad: 0.02,
            dx: 2.6,
            dy: -1.7,
            center,
        };
        let frame = SplineImage::new(reference.view()).warp_similarity(&truth.inverse(), w, h);
        let identity = Similarity::identity(center);
        let p = quicklook_panels(reference.view(), frame.view(), &identity, &truth).unwrap();

        // 128 px → replicated 4× to 512 px panels.
        assert_eq!((p.width, p.height), (512, 512));
        // Green and blue carry the same frame.
        assert!(p
            .composites
            .iter()
            .all(|c| c.chunks(3).all(|q| q[1] == q[2])));

        // Inside the disk (AIA: 19.2″/px, R☉ ≈ 975″ → ~50 px; use 40 px, ×4 on screen).
        let disk = [255.5, 255.5];
        let coarse = panel_rg_correlation(&p, 0, disk, 160.0);
        let fine = panel_rg_correlation(&p, 1, disk, 160.0);
        // Measured: coarse 0.51, fine 0.990 (not 1: the frame went through two spline
        // resamplings, which smooth pixel-scale structure, and 8-bit quantisation).
        assert!(fine > 0.97, "fine panel correlation {fine}");
        assert!(fine > coarse + 0.3, "fine {fine} vs coarse {coarse}");
    }

    /// Truth: the frame is the reference moved by 0.25 px in x and scaled ×3 plus 50 (another
    /// exposure). Through the identity the difference shows the motion; through the truth,
    /// after intensity matching, little is left.
    #[test]
    fn difference_panels_show_a_quarter_pixel_motion_and_its_removal() {
        let reference = read_real("aia_171_20110215T000000_128.fits");
        let (h, w) = reference.dim();
        let center = Similarity::array_center(w, h);
        let truth = Similarity {
            dx: 0.25,
            ..Similarity::identity(center)
        };
        let frame = SplineImage::new(reference.view())
            .warp_similarity(&truth.inverse(), w, h)
            .mapv(|v| 3.0 * v + 50.0);
        let identity = Similarity::identity(center);
        let p = quicklook_panels(reference.view(), frame.view(), &identity, &truth).unwrap();
        let disk = [255.5, 255.5];
        let before = panel_rms(&p.differences[0], disk, 160.0);
        let after = panel_rms(&p.differences[1], disk, 160.0);
        assert!(after < 0.5 * before, "after {after} vs before {before}");
        // The motion is visible: the before panel's structure is a sizeable part of the scale.
        assert!(
            before > 0.1 * p.diff_range as f64,
            "{before} of {}",
            p.diff_range
        );

        // The labelled figure: two panel columns and two rows of 512 px, plus text strips.
        let captions = Captions {
            reference: ("reference (red): ".into(), "ref.fits".into()),
            frame: ("frame (cyan): ".into(), "frame.fits".into()),
            measured: ("measured: ".into(), "dx 0.25 px".into()),
            before: "before".into(),
            after: "after".into(),
        };
        let look = render_quicklook(&p, &captions).unwrap();
        assert!(look.width >= 2 * 512 + GAP_PX && look.height >= 2 * 512);
        assert_eq!(look.rgb.len(), look.width * look.height * 3);
    }

    #[test]
    fn big_images_are_block_averaged_small_ones_replicated() {
        let big = Array2::from_shape_fn((3000, 2100), |(y, _)| y as f32);
        let small = resize(&big);
        // ⌈3000 / 1024⌉ = 3: 1000 × 700, each pixel the mean of a 3×3 block.
        assert_eq!(small.dim(), (1000, 700));
        assert_eq!(small[[10, 5]], 31.0);
        let tiny = Array2::from_shape_fn((100, 110), |(y, x)| (y * 1000 + x) as f32);
        let up = resize(&tiny);
        assert_eq!(up.dim(), (400, 440));
        assert_eq!(up[[7, 9]], tiny[[1, 2]]);
    }
}
