//! Instrument fill: the value a pipeline writes where it has no sky (IRIS level 2 writes
//! −200 around the field its co-registration shifted, other pipelines 0), touching the
//! image's border. Its edges are the instrument's, not the Sun's: they move with the detector
//! and, at hundreds of DN against the sky, they would outweigh every solar feature in a fit
//! (on IRIS slit-jaw cubes they pull the scale by a per cent). They are missing data.
//!
//! Fill is one value, exactly (no exposure of the sky is free of noise), held by pixels
//! connected to the border, at least as many as a row and a column (quantised images show
//! runs of one value at their borders too, but short: at most 353 pixels on the 1024² TRACE
//! image). Pixels a binning or an interpolation mixed with the fill
//! lie between it and the data: from the fill, those closer to the fill value than to the
//! data's extreme percentile are taken too, then one pixel more.

use ndarray::{Array2, ArrayView2};
use std::collections::VecDeque;

/// The border fill of an image: its value and the pixels to take as missing.
#[derive(Debug, Clone, PartialEq)]
pub struct Fill {
    /// The fill value.
    pub value: f32,
    /// The fill, the band mixed with it and a margin of one pixel.
    pub mask: Array2<bool>,
    /// Pixels of `mask` that hold a finite value.
    pub pixels: usize,
}

impl Fill {
    /// Sets the fill's pixels of `img` (the image it was found in) to NaN.
    pub fn blank(&self, img: &mut Array2<f32>) {
        ndarray::Zip::from(img).and(&self.mask).for_each(|v, &f| {
            if f {
                *v = f32::NAN;
            }
        });
    }

    /// What the record's message says of it.
    pub fn note(&self) -> String {
        format!(
            "border fill {} ({} px) taken as missing data",
            self.value, self.pixels
        )
    }
}

/// Percentile of the data (the side facing the fill) that the mixed band must stay beyond.
const DATA_PERCENTILE: f64 = 0.01;

/// The border fill of `img`; `None` when there is none.
pub fn find_fill(img: ArrayView2<f32>) -> Option<Fill> {
    let (h, w) = img.dim();
    if h < 3 || w < 3 {
        return None;
    }
    let mut fill = Array2::from_elem((h, w), false);
    let (value, found) = largest_border_region(img, &mut fill)?;
    if found < h + w {
        return None;
    }
    let data = data_quantile(img, &fill, value)?;
    // The band mixed with the fill: values on the fill's side of the midpoint.
    let threshold = 0.5 * (value as f64 + data);
    let below = (value as f64) < data;
    let mixed = |v: f32| v.is_finite() && ((v as f64) < threshold) == below;
    let mut queue: VecDeque<(usize, usize)> = fill
        .indexed_iter()
        .filter(|(_, &f)| f)
        .map(|(p, _)| p)
        .collect();
    while let Some((y, x)) = queue.pop_front() {
        for (ny, nx) in neighbours4(y, x, h, w) {
            if !fill[[ny, nx]] && mixed(img[[ny, nx]]) {
                fill[[ny, nx]] = true;
                queue.push_back((ny, nx));
            }
        }
    }
    // One pixel more: the last pixel a kernel mixed lies on the data's side of the midpoint.
    let core = fill.clone();
    for ((y, x), &f) in core.indexed_iter() {
        if f {
            for (ny, nx) in neighbours4(y, x, h, w) {
                fill[[ny, nx]] = true;
            }
        }
    }
    let pixels = ndarray::Zip::from(&img)
        .and(&fill)
        .fold(0, |n, v, &f| n + usize::from(f && v.is_finite()));
    Some(Fill {
        value,
        mask: fill,
        pixels,
    })
}

/// Marks in `fill` the largest set of pixels of one exact value connected to the border;
/// returns that value and the set's size.
fn largest_border_region(img: ArrayView2<f32>, fill: &mut Array2<bool>) -> Option<(f32, usize)> {
    let (h, w) = img.dim();
    let border = (0..w)
        .flat_map(|x| [(0, x), (h - 1, x)])
        .chain((1..h - 1).flat_map(|y| [(y, 0), (y, w - 1)]));
    let mut seen = Array2::from_elem((h, w), false);
    // Per value (by its bits): the pixels of its regions that touch the border.
    let mut regions: Vec<(u32, Vec<(usize, usize)>)> = Vec::new();
    for (y, x) in border {
        let value = img[[y, x]];
        if seen[[y, x]] || !value.is_finite() {
            continue;
        }
        seen[[y, x]] = true;
        let bits = value.to_bits();
        let mut region = vec![(y, x)];
        let mut k = 0;
        while k < region.len() {
            let (cy, cx) = region[k];
            k += 1;
            for (ny, nx) in neighbours4(cy, cx, h, w) {
                if !seen[[ny, nx]] && img[[ny, nx]].to_bits() == bits {
                    seen[[ny, nx]] = true;
                    region.push((ny, nx));
                }
            }
        }
        // A lone pixel of a value is the rule in noisy data: only runs are worth keeping.
        if region.len() < 2 {
            continue;
        }
        match regions.iter_mut().find(|(b, _)| *b == bits) {
            Some((_, r)) => r.extend(region),
            None => regions.push((bits, region)),
        }
    }
    let (bits, region) = regions.into_iter().max_by_key(|(_, r)| r.len())?;
    for &p in &region {
        fill[p] = true;
    }
    Some((f32::from_bits(bits), region.len()))
}

/// The data's extreme percentile on the side that faces `value`, over the central half of
/// the image (away from the border, where the mixed band lies) outside `fill`; `None` when
/// it does not lie beyond the fill value.
fn data_quantile(img: ArrayView2<f32>, fill: &Array2<bool>, value: f32) -> Option<f64> {
    let (h, w) = img.dim();
    let (rows, cols) = (h / 4..h - h / 4, w / 4..w - w / 4);
    let centre = img.slice(ndarray::s![rows.clone(), cols.clone()]);
    let centre_fill = fill.slice(ndarray::s![rows, cols]);
    // A regular sample of at most `SAMPLE` pixels: percentiles, not every pixel, are needed.
    let stride = (centre.len() / SAMPLE).max(1);
    let mut data: Vec<f32> = centre
        .iter()
        .zip(centre_fill.iter())
        .step_by(stride)
        .filter(|(x, &f)| !f && x.is_finite())
        .map(|(&x, _)| x)
        .collect();
    if data.is_empty() {
        return None;
    }
    data.sort_unstable_by(f32::total_cmp);
    let at = |q: f64| data[((data.len() - 1) as f64 * q).round() as usize] as f64;
    let median = at(0.5);
    let v = value as f64;
    let q = if v < median {
        at(DATA_PERCENTILE)
    } else {
        at(1.0 - DATA_PERCENTILE)
    };
    ((v < median && q > v) || (v > median && q < v)).then_some(q)
}

/// Pixels sampled for the data's percentiles at most.
const SAMPLE: usize = 1 << 18;

fn neighbours4(y: usize, x: usize, h: usize, w: usize) -> impl Iterator<Item = (usize, usize)> {
    [
        (y.wrapping_sub(1), x),
        (y + 1, x),
        (y, x.wrapping_sub(1)),
        (y, x + 1),
    ]
    .into_iter()
    .filter(move |&(ny, nx)| ny < h && nx < w)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::stats::SplitMix64;

    /// A noisy scene whose left 3 columns and bottom 2 rows hold the fill value, with a
    /// column mixed between them and the scene.
    fn padded(fill: f32, level: f32) -> Array2<f32> {
        let mut rng = SplitMix64::new(5);
        Array2::from_shape_fn((40, 50), |(y, x)| {
            let sky = level + 10.0 * rng.gaussian() as f32 + 30.0 * ((x as f32) * 0.3).sin();
            match (y, x) {
                (_, 0..=2) | (0..=1, _) => fill,
                (_, 3) => 0.7 * fill + 0.3 * sky,
                _ => sky,
            }
        })
    }

    #[test]
    fn border_fill_and_the_pixels_mixed_with_it_become_missing() {
        for (fill, level) in [(-200.0, 800.0), (0.0, 500.0), (4095.0, 1000.0)] {
            let mut img = padded(fill, level);
            let found = find_fill(img.view()).expect("fill found");
            found.blank(&mut img);
            assert_eq!(found.value, fill);
            for ((y, x), v) in img.indexed_iter() {
                // The fill, the mixed column and one pixel beyond are missing; the rest kept.
                let missing = x <= 4 || y <= 2;
                assert_eq!(v.is_nan(), missing, "fill {fill}: pixel ({x}, {y}) = {v}");
            }
            assert_eq!(found.pixels, 40 * 50 - 37 * 45);
        }
    }

    #[test]
    fn noise_and_small_flat_patches_are_data() {
        // A quantised sky: flat 3 × 3 patches of real values at the border, and no fill.
        let mut rng = SplitMix64::new(8);
        let mut img = Array2::from_shape_fn((64, 64), |_| (85.0 + rng.gaussian()).round() as f32);
        for y in 0..5 {
            for x in 0..6 {
                img[[y, x]] = 84.0;
            }
        }
        assert_eq!(find_fill(img.view()), None);
    }

    #[test]
    fn real_iris_fill_is_found_on_every_side_it_touches() {
        let cube =
            crate::test_data::read_real("iris_l2_20140329_140938_3860258481_SJI_2832_t000.fits");
        let mut img = cube;
        let found = find_fill(img.view()).expect("IRIS level-2 fill");
        found.blank(&mut img);
        assert_eq!(found.value, -200.0);
        // No pixel at the fill value, or below the data's range, is left.
        let least = img
            .iter()
            .filter(|v| v.is_finite())
            .fold(f32::INFINITY, |a, &b| a.min(b));
        assert!(least > -150.0, "darkest pixel kept: {least}");
    }
}
