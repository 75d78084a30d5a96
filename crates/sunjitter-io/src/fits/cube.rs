//! Cube frames: per-frame clocks and pointings from the per-frame table.

use super::layout::{open, read_failure, Hdu, Layout};
use super::pixels::{decode_samples, Scaling};
use std::io::{Read, Seek, SeekFrom};
use std::path::Path;
use sunjitter_core::header::{HduKind, Header};
use sunjitter_core::meta::{self, FrameMeta};
use sunjitter_core::Result;

/// Per-frame times, exposures and pointings of a cube from its per-frame table.
///
/// The table is the only per-frame record an IRIS level-2 cube has: its primary header holds
/// one time, one exposure and one pointing (`XCEN`/`YCEN`, the WCS's `CRVAL`) for all frames.
#[derive(Debug, Clone, Default)]
pub(super) struct FrameClock {
    /// Start time the table counts from (IRIS: `STARTOBS`).
    start_ns: Option<i64>,
    /// Seconds after `start_ns`, one per table row.
    seconds: Vec<f64>,
    /// Exposure per table row, when the table has one (`EXPTIMES`).
    exposures: Vec<f64>,
    /// Field-centre pointing per table row, helioprojective arcsec (`XCENIX`, `YCENIX`), when
    /// the table has both; `NaN` in rows of missing exposures (see [`pointing_columns`]).
    pointing: [Vec<f64>; 2],
}

impl FrameClock {
    /// Find an auxiliary array HDU whose header names a `TIME` column (IRIS level 2), and read
    /// its `TIME`, `EXPTIMES`, `XCENIX` and `YCENIX` columns (0-based indices in that header).
    pub(super) fn of(layout: &Layout, image: &Hdu, path: &Path) -> FrameClock {
        let start_ns = meta::time_reference_ns(&layout.merged_header(image));
        for hdu in layout
            .hdus
            .iter()
            .filter(|h| h.index != image.index && h.kind == HduKind::Image)
        {
            let Some(table) = &hdu.image else { continue };
            let Some(col) = hdu.header.i64("TIME") else {
                continue;
            };
            let (ncols, nrows) = (table.width(), table.height());
            if col < 0 || col as usize >= ncols || table.axes.len() != 2 {
                continue;
            }
            let column = |key: &str| hdu.header.i64(key).and_then(|c| usize::try_from(c).ok());
            match read_table_columns(
                path,
                hdu,
                &[
                    Some(col as usize),
                    column("EXPTIMES"),
                    column("XCENIX"),
                    column("YCENIX"),
                ],
            ) {
                Ok(mut cols) => {
                    let y = cols.pop().unwrap_or_default();
                    let x = cols.pop().unwrap_or_default();
                    let exposures = cols.pop().unwrap_or_default();
                    let seconds = cols.pop().unwrap_or_default();
                    if seconds.len() == nrows {
                        return FrameClock {
                            start_ns,
                            seconds,
                            exposures,
                            pointing: pointing_columns(x, y, nrows),
                        };
                    }
                }
                Err(e) => tracing::warn!(
                    "{}: per-frame table in HDU {} unreadable: {e}",
                    path.display(),
                    hdu.index
                ),
            }
        }
        FrameClock::default()
    }

    fn has_table(&self) -> bool {
        self.start_ns.is_some() && !self.seconds.is_empty()
    }

    /// Say so when the table and the cube disagree in length (trimmed files).
    pub(super) fn warn_if_resampled(&self, path: &Path, frames: usize) {
        if self.has_table() && self.seconds.len() != frames {
            tracing::warn!(
                "{}: per-frame table has {} rows for {frames} frames; frame times interpolated at row i·({}−1)/({frames}−1)",
                path.display(),
                self.seconds.len(),
                self.seconds.len()
            );
        }
    }

    /// Fill frame `i`'s time (table, else time axis, else the header's) and exposure, and
    /// move its sun centre to the frame's own pointing when the table gives one.
    pub(super) fn apply(&self, meta: &mut FrameMeta, header: &Header, i: usize, frames: usize) {
        self.apply_pointing(meta, header, i, frames);
        if let (true, Some(start)) = (self.has_table(), self.start_ns) {
            let p = table_position(i, frames, self.seconds.len());
            meta.obs_time_ns = offset_time(start, interpolate(&self.seconds, p));
            if !self.exposures.is_empty() {
                meta.exptime_s = Some(interpolate(&self.exposures, p));
            }
            return;
        }
        if let (Some(t), Some(reference)) = (
            meta::time_axis_seconds(header, i),
            meta::time_reference_ns(header),
        ) {
            meta.obs_time_ns = offset_time(reference, t);
        }
    }

    /// Frame `i`'s sun centre at the frame's pointing (`XCENIX`/`YCENIX` at the frame's table
    /// position) rather than the header's nominal one: the header's WCS places the Sun for
    /// the nominal pointing only (see [`pointing_shift_px`]). Frames without a usable
    /// pointing keep the header's centre.
    fn apply_pointing(&self, meta: &mut FrameMeta, header: &Header, i: usize, frames: usize) {
        let [xs, ys] = &self.pointing;
        if xs.is_empty() || xs.len() != ys.len() {
            return;
        }
        let p = table_position(i, frames, xs.len());
        let at = [interpolate_rows(xs, p), interpolate_rows(ys, p)];
        if let Some([dx, dy]) = pointing_shift_px(header, at) {
            meta.sun_center_px[0] += dx;
            meta.sun_center_px[1] += dy;
        }
    }
}

/// The `XCENIX`/`YCENIX` columns as the pointing per table row, or empty columns when the
/// table lacks either. IRIS writes `XCENIX = YCENIX = 0` (with `EXPTIMES = 0`) in the rows of
/// exposures that are missing (rows 198–221 of the trimmed 1400 Å test cube): that is no
/// pointing at all, so those rows become `NaN` and frames read from them keep the header's.
fn pointing_columns(x: Vec<f64>, y: Vec<f64>, rows: usize) -> [Vec<f64>; 2] {
    if x.len() != rows || y.len() != rows {
        return [Vec::new(), Vec::new()];
    }
    let (x, y) = x
        .iter()
        .zip(&y)
        .map(|(&x, &y)| {
            if x == 0.0 && y == 0.0 {
                (f64::NAN, f64::NAN)
            } else {
                (x, y)
            }
        })
        .unzip();
    [x, y]
}

/// Pixel move of the sun centre for a frame pointed at `at` (helioprojective arcsec) when the
/// header's WCS describes the nominal pointing `XCEN`/`YCEN` (else `CRVAL1`/`CRVAL2` in arcsec).
///
/// A telescope pointed `d = at − nominal` further sees every sky point, the disk centre
/// included, `−M⁻¹·d` pixels from where the header puts it (`M`: the header's
/// arcsec-per-pixel matrix, world axis i × pixel axis j). This is the linear part of
/// moving `CRVAL` by `d`; for small re-pointings of a field near disk centre the projection
/// adds a negligible part (docs/validation.md#cube-pointing-linear-part-only). `None` when the
/// header gives no nominal pointing, no usable WCS, or the values are not finite.
fn pointing_shift_px(header: &Header, at: [f64; 2]) -> Option<[f64; 2]> {
    let wcs = meta::CelestialWcs::from_header(header).ok()?;
    let nominal = match (header.f64("XCEN"), header.f64("YCEN")) {
        (Some(x), Some(y)) => [x, y],
        _ if header.contains("CRVAL1") && header.contains("CRVAL2") => wcs.crval_arcsec,
        _ => return None,
    };
    let d = [at[0] - nominal[0], at[1] - nominal[1]];
    let [[a, b], [c, e]] = wcs.matrix;
    let det = a * e - b * c;
    if !det.is_finite() || det.abs() < 1e-300 {
        return None;
    }
    let shift = [-(e * d[0] - b * d[1]) / det, -(a * d[1] - c * d[0]) / det];
    shift.iter().all(|v| v.is_finite()).then_some(shift)
}

/// `start` plus `seconds`, in ns; `None` when the sum is not a representable time (an absurd
/// table or time axis: the frame is then reported as having no observation time).
fn offset_time(start: i64, seconds: f64) -> Option<i64> {
    let ns = seconds * 1e9;
    if !ns.is_finite() || ns.abs() >= 9.0e18 {
        return None;
    }
    start.checked_add(ns.round() as i64)
}

/// Table row (fractional) of frame `i`. Equal lengths map one to one; a cube resampled along
/// time (the trimmed IRIS test files: 540 rows, 54 frames) spans the table end to end, which
/// is where each frame's slit position shows it was taken from (see tools/sunpy_truth.py).
fn table_position(i: usize, frames: usize, rows: usize) -> f64 {
    if rows == frames || frames <= 1 || rows <= 1 {
        return i.min(rows.saturating_sub(1)) as f64;
    }
    i as f64 * (rows - 1) as f64 / (frames - 1) as f64
}

/// Linear interpolation of `values` at fractional index `p` (clamped to the ends).
fn interpolate(values: &[f64], p: f64) -> f64 {
    let last = values.len() - 1;
    let p = p.clamp(0.0, last as f64);
    let lo = p.floor() as usize;
    let hi = (lo + 1).min(last);
    values[lo] + (values[hi] - values[lo]) * (p - lo as f64)
}

/// [`interpolate`], except that a row of zero weight plays no part: a frame read exactly at a
/// row is that row's value even when its neighbour is `NaN` (a missing exposure's pointing).
fn interpolate_rows(values: &[f64], p: f64) -> f64 {
    let p = p.clamp(0.0, (values.len() - 1) as f64);
    if p.fract() == 0.0 {
        return values[p as usize];
    }
    interpolate(values, p)
}

/// Read columns of a 2-D array HDU (NAXIS1 = columns, NAXIS2 = rows), as f64.
fn read_table_columns(path: &Path, hdu: &Hdu, columns: &[Option<usize>]) -> Result<Vec<Vec<f64>>> {
    let g = hdu.geometry();
    let bytes_len = g.pixels_per_frame() * g.bytes_per_pixel();
    let mut file = open(path)?;
    file.seek(SeekFrom::Start(hdu.data_offset))
        .map_err(|e| read_failure(path, e, "read error"))?;
    let mut bytes = vec![0u8; bytes_len];
    file.read_exact(&mut bytes)
        .map_err(|e| read_failure(path, e, "truncated table"))?;
    let mut all = Vec::with_capacity(g.pixels_per_frame());
    decode_samples(&bytes, g.bitpix, Scaling::of(&hdu.header, g.bitpix), |v| {
        all.push(v)
    });
    let ncols = g.width();
    Ok(columns
        .iter()
        .map(|c| match c {
            Some(c) if *c < ncols => all.chunks_exact(ncols).map(|row| row[*c]).collect(),
            _ => Vec::new(),
        })
        .collect())
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Absurd table/time-axis times that overflow the ns count.
    #[test]
    fn offset_times_that_do_not_fit_are_none() {
        assert_eq!(offset_time(1_000, 2.5), Some(2_500_001_000));
        assert_eq!(offset_time(i64::MAX - 10, 1.0), None);
        assert_eq!(offset_time(0, f64::NAN), None);
        assert_eq!(offset_time(0, 1e300), None);
    }

    #[test]
    fn table_positions_span_the_table() {
        assert_eq!(table_position(5, 10, 10), 5.0);
        assert_eq!(table_position(0, 54, 540), 0.0);
        assert_eq!(table_position(53, 54, 540), 539.0);
        assert!((table_position(1, 54, 540) - 539.0 / 53.0).abs() < 1e-12);
        assert_eq!(interpolate(&[0.0, 10.0, 20.0], 1.5), 15.0);
        assert_eq!(interpolate(&[0.0, 10.0], 7.0), 10.0);
    }

    /// The pointing move is −M⁻¹·d. With a 90° roll, M = [[0, −2], [2, 0]] arcsec/px, a frame
    /// pointed 4″ west and 2″ north of XCEN/YCEN sees the disk centre 1 px left, 2 px up.
    #[test]
    fn pointing_moves_the_centre_and_fill_rows_are_no_pointing() {
        let header = |cards: &[(&str, &str)]| {
            let text: String = cards
                .iter()
                .map(|(k, v)| format!("{:<80}", format!("{k:<8}= {v:>20}")))
                .collect();
            Header::parse(text.as_bytes())
        };
        let mut cards = vec![
            ("CRPIX1", "1.0"),
            ("CRPIX2", "1.0"),
            ("CDELT1", "2.0"),
            ("CDELT2", "2.0"),
            ("PC1_1", "0.0"),
            ("PC1_2", "-1.0"),
            ("PC2_1", "1.0"),
            ("PC2_2", "0.0"),
            ("CRVAL1", "100.0"),
            ("CRVAL2", "50.0"),
        ];
        // CRVAL stands in for a missing XCEN/YCEN.
        assert_eq!(
            pointing_shift_px(&header(&cards), [104.0, 52.0]),
            Some([-1.0, 2.0])
        );
        cards.extend([("XCEN", "90.0"), ("YCEN", "40.0")]);
        assert_eq!(
            pointing_shift_px(&header(&cards), [94.0, 42.0]),
            Some([-1.0, 2.0])
        );
        assert_eq!(pointing_shift_px(&header(&cards), [f64::NAN, 42.0]), None);
        let no_nominal: Vec<_> = cards
            .iter()
            .copied()
            .filter(|(k, _)| !matches!(*k, "XCEN" | "YCEN" | "CRVAL1" | "CRVAL2"))
            .collect();
        assert_eq!(pointing_shift_px(&header(&no_nominal), [94.0, 42.0]), None);

        let [x, y] = pointing_columns(vec![1.0, 0.0, 0.0], vec![2.0, 0.0, 5.0], 3);
        assert_eq!((x[0], y[0]), (1.0, 2.0));
        assert!(x[1].is_nan() && y[1].is_nan());
        assert_eq!((x[2], y[2]), (0.0, 5.0));
        assert!(pointing_columns(vec![1.0], Vec::new(), 1)[0].is_empty());
        assert_eq!(interpolate_rows(&x, 0.0), 1.0);
        assert!(interpolate_rows(&x, 0.5).is_nan());
    }
}
