//! How a blur difference between the images is matched before the refinement.

/// Smallest blur difference matched, as a fraction of the refinement's smoothing variance:
/// below it, what a difference does is within the noise-free σ
/// (docs/validation.md#smallest-blur-difference-matched).
pub(super) const MIN_MATCHED_BLUR_FRACTION: f64 = 0.02;

/// Standard errors a blur difference must exceed to be matched. Not 3: the Hann window
/// correlates neighbouring frequency bins, so the fit's scatter understates its error.
pub(super) const MIN_BLUR_SIGNIFICANCE: f64 = 5.0;

/// How the sharper image is blurred to the other's, and how uncertain that is. A difference
/// (the frame's resolution-matching smoothing included) is matched when it is beyond
/// [`MIN_BLUR_SIGNIFICANCE`] standard errors and [`MIN_MATCHED_BLUR_FRACTION`] of the
/// smoothing variance.
pub(super) fn blur_matching(
    blur: Option<crate::blur::BlurDifference>,
    frame_smoothing_px: f64,
    smoothing_px: f64,
) -> BlurMatch {
    let unmatched = BlurMatch {
        reference_extra: 0.0,
        frame_smoothing_px,
        uncertainty_px2: None,
    };
    let Some(b) = blur else {
        return unmatched;
    };
    // The frame's resolution-matching smoothing is part of its blur.
    let excess = b.variance_px2 + frame_smoothing_px * frame_smoothing_px;
    let significant = excess.abs() > MIN_BLUR_SIGNIFICANCE * b.sigma_px2
        && excess.abs() > MIN_MATCHED_BLUR_FRACTION * smoothing_px * smoothing_px;
    if !significant || !excess.is_finite() {
        return unmatched;
    }
    let uncertainty_px2 = Some(
        (BLUR_SIGMA_UNDERSTATEMENT * b.sigma_px2)
            .hypot(BLUR_SYSTEMATIC_FRACTION * excess)
            .hypot(b.shape_px2),
    );
    if excess > 0.0 {
        BlurMatch {
            reference_extra: excess.sqrt(),
            frame_smoothing_px,
            uncertainty_px2,
        }
    } else {
        BlurMatch {
            reference_extra: 0.0,
            frame_smoothing_px: (-b.variance_px2).max(0.0).sqrt(),
            uncertainty_px2,
        }
    }
}

/// How a blur difference is matched.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(super) struct BlurMatch {
    /// σ of the Gaussian added to the reference, px (0: none).
    pub(super) reference_extra: f64,
    /// The frame's smoothing σ, px.
    pub(super) frame_smoothing_px: f64,
    /// 1-σ error of the matched difference, px² (`None`: nothing matched).
    pub(super) uncertainty_px2: Option<f64>,
}

/// The fit's standard error understates the blur difference's: neighbouring frequency bins
/// are correlated through the window.
pub(super) const BLUR_SIGMA_UNDERSTATEMENT: f64 = 2.0;

/// And the spectra carry errors proportional to it: a known Gaussian blur reads a few percent
/// off (docs/validation.md#systematic-error-of-a-matched-blur).
pub(super) const BLUR_SYSTEMATIC_FRACTION: f64 = 0.03;

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn only_a_significant_blur_difference_is_matched_on_the_blurrier_side() {
        let blur = |v: f64, sd: f64| {
            Some(crate::blur::BlurDifference {
                variance_px2: v,
                sigma_px2: sd,
                shape_px2: 0.0,
                bins: 50,
            })
        };
        // Frame blurrier by 0.64 px²: the reference gets a Gaussian of that variance.
        let m = blur_matching(blur(0.64, 0.005), 0.0, 0.7);
        assert!((m.reference_extra - 0.8).abs() < 1e-12 && m.frame_smoothing_px == 0.0);
        assert!(m.uncertainty_px2.is_some());
        // Reference blurrier by 0.25 px²: the frame is smoothed by 0.5 px.
        let m = blur_matching(blur(-0.25, 0.005), 0.0, 0.7);
        assert!(m.reference_extra == 0.0 && (m.frame_smoothing_px - 0.5).abs() < 1e-12);
        // The frame's resolution-matching smoothing (0.3 px) is part of its blur.
        let m = blur_matching(blur(-0.25, 0.005), 0.3, 0.7);
        assert!((m.frame_smoothing_px - 0.5).abs() < 1e-12);
        // Within 5 standard errors, or under 2 % of the smoothing variance: nothing.
        for (v, sd) in [(0.04, 0.01), (0.009, 0.0001)] {
            let m = blur_matching(blur(v, sd), 0.0, 0.7);
            assert_eq!((m.reference_extra, m.frame_smoothing_px), (0.0, 0.0));
            assert!(m.uncertainty_px2.is_none());
        }
    }
}
