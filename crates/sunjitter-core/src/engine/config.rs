//! The engine's settings (the configuration file's `[engine]` table).

use super::model::{ModelChoice, ModelPrior, ROLL_STABILITY_ARCSEC, SCALE_STABILITY};
use super::sigma::SigmaMethod;
use serde::{Deserialize, Serialize};

/// Engine settings (from the configuration file's `[engine]` table). Every default is meant
/// to work on any solar imager; sizes are derived from the plate scale and the image itself.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct EngineConfig {
    /// Farneback averaging window in arcsec (the paper uses about 63″), converted with the
    /// reference plate scale. `None` (the default): sized for the image's structure,
    /// `window_structure_lengths` texture correlation lengths (measured in the reference).
    /// Either way kept within `min_window_px` and a third of the disk radius (a quarter of the
    /// image without a disk).
    pub window_arcsec: Option<f64>,
    /// Explicit window in pixels (overrides everything else).
    pub window_px: Option<usize>,
    pub min_window_px: usize,
    pub window_structure_lengths: f64,
    /// Fraction of the solar radius kept in the disk mask (excludes the limb).
    pub mask_radius_fraction: f64,
    /// `sample × sample` grid of median vectors.
    pub sample: usize,
    /// RANSAC inlier threshold, px.
    pub ransac_threshold_px: f64,
    pub ransac_max_trials: usize,
    pub seed: u64,
    /// Pyramid levels of the first pass (`None`: as many as keep the coarsest level ≥ 64 px,
    /// at most 4). Later passes measure a small residual and use one level.
    pub pyramid_levels: Option<usize>,
    pub iterations: usize,
    /// Polynomial expansion neighbourhood (Farneback `poly_n`) and its Gaussian σ.
    pub poly_n: usize,
    pub poly_sigma: f64,
    /// Fine passes at most; stop when the update moves no point of the mask by more than
    /// `convergence_px`.
    pub max_passes: usize,
    pub convergence_px: f64,
    /// Replace pixels deviating from their 3×3 median by more than this fraction of it
    /// (cosmic rays, hot pixels); 0 disables.
    pub hot_pixel_fraction: f32,
    /// Systematic floor of the method, px (resampling and f32 arithmetic; measured with
    /// `simulate` as the bias left when the random error vanishes). Added in quadrature to the
    /// translation σ, and as `floor / rms radius of the vectors` to scale and rotation.
    pub systematic_floor_px: f64,
    /// Which σ is reported as `sigma_*` (the paper's plain UABJM is always reported too).
    pub sigma: SigmaMethod,
    /// Below this Bhattacharyya coefficient the result is `degraded`.
    pub min_similarity: f64,
    /// Below this structural correlation after alignment the result is `degraded`; below a
    /// third of it, `failed`.
    pub min_correlation: f64,
    /// Below this fraction of RANSAC inliers the result is `degraded`.
    pub min_inlier_fraction: f64,
    /// Final direct intensity refinement (Gauss–Newton on the RANSAC-inlier cells).
    pub refine: RefineMode,
    /// Gaussian σ applied to both images before the refinement, px: it takes the
    /// interpolation error of sharp structure out of the match
    /// (docs/validation.md#refinement-smoothing).
    pub refine_smoothing_px: f64,
    /// Further Gaussian σ of the reference whose gradient weighs the refinement's residuals, px.
    pub refine_gradient_smoothing_px: f64,
    /// When the refinement follows, the flow seeds it on copies binned to the pyramid level
    /// where the mask spans at least this many pixels (full resolution below twice that).
    pub seed_extent_px: usize,
    /// When the flow's answer is final (between channels, or with the refinement off), it is
    /// measured on copies binned to the pyramid level where the mask spans at least this many
    /// pixels, from a seed on a coarser level; 0 measures at full resolution.
    pub final_extent_px: usize,
    /// The Sun's differential rotation taken out between the reference's and the frame's
    /// times (`howard`, `snodgrass`, `allen`, or `none` to keep it in the answer).
    pub solar_rotation: crate::solar_rotation::Profile,
    /// Which transform to fit: `auto` fits scale and roll only where the images measure them
    /// better than the instrument holds them (`scale_stability`, `roll_stability_arcsec`);
    /// `similarity`, `rigid` or `translation` always.
    pub model: ModelChoice,
    /// How well the instrument holds its plate scale between two frames (relative, 1-σ).
    pub scale_stability: f64,
    /// How well the instrument holds its roll between two frames, arcsec (1-σ).
    pub roll_stability_arcsec: f64,
}

impl Default for EngineConfig {
    fn default() -> Self {
        EngineConfig {
            window_arcsec: None,
            window_px: None,
            min_window_px: 15,
            window_structure_lengths: 10.0,
            mask_radius_fraction: 0.9,
            sample: 20,
            ransac_threshold_px: 1.0,
            ransac_max_trials: 2000,
            seed: 0,
            pyramid_levels: None,
            iterations: 10,
            poly_n: 5,
            poly_sigma: 1.1,
            max_passes: 4,
            convergence_px: 2e-4,
            hot_pixel_fraction: 1.0,
            systematic_floor_px: 3e-5,
            sigma: SigmaMethod::default(),
            min_similarity: 0.3,
            min_correlation: 0.3,
            min_inlier_fraction: 0.5,
            refine: RefineMode::default(),
            refine_smoothing_px: 0.7,
            refine_gradient_smoothing_px: 0.0,
            seed_extent_px: SEED_EXTENT_PX,
            final_extent_px: FINAL_EXTENT_PX,
            solar_rotation: crate::solar_rotation::Profile::default(),
            model: ModelChoice::default(),
            scale_stability: SCALE_STABILITY,
            roll_stability_arcsec: ROLL_STABILITY_ARCSEC,
        }
    }
}

impl EngineConfig {
    /// The model settings, as the fit reads them.
    pub fn model_prior(&self) -> ModelPrior {
        ModelPrior {
            model: self.model,
            scale_stability: self.scale_stability,
            roll_stability_arcsec: self.roll_stability_arcsec,
        }
    }

    /// The settings a channel may have of its own, as this configuration gives them.
    pub fn channel_settings(&self) -> ChannelSettings {
        ChannelSettings {
            solar_rotation: self.solar_rotation,
            model: self.model_prior(),
        }
    }

    /// This configuration with a channel's own settings.
    pub fn for_channel(&self, settings: &ChannelSettings) -> EngineConfig {
        EngineConfig {
            solar_rotation: settings.solar_rotation,
            model: settings.model.model,
            scale_stability: settings.model.scale_stability,
            roll_stability_arcsec: settings.model.roll_stability_arcsec,
            ..self.clone()
        }
    }
}

/// When the intensity refinement runs.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum RefineMode {
    /// When both images are of the same channel (default): there the intensities are the
    /// same physical quantity up to gain and offset. Between channels the flow's answer stays.
    #[default]
    SameChannel,
    /// Always (also between channels).
    Always,
    /// Never: the flow's answer is final.
    Off,
}

/// What a channel may set for the frames it measures, beside the engine's settings (the
/// configuration's `[channels.NAME]` table): what the instrument and its target do.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ChannelSettings {
    /// The Sun's rotation profile taken out.
    pub solar_rotation: crate::solar_rotation::Profile,
    /// The model fitted and the instrument's stability.
    pub model: ModelPrior,
}

/// Default mask extent, px, at the pyramid level a seed flow works on. The flow's cost and
/// memory grow with the pixel count while the refinement only needs a start near its answer,
/// and a seed this size gives the same refined answer as one at full resolution. Not less: the
/// refinement's reweighting settles on slightly different weights from a coarser start. And a
/// seed that converged on its level, not one pass: on undersampled images the refinement's
/// answer depends on its start (docs/validation.md#seed-flow-on-binned-copies-converged).
pub(super) const SEED_EXTENT_PX: usize = 700;

/// Default mask extent, px, at the pyramid level where a final flow answer is measured
/// (between channels, or with the refinement off). Twice the seed's: the flow's own σ there are
/// far below its interpolation term, and the cost stays that of a 2048² frame on larger ones
/// (docs/validation.md#between-channels-the-answer-on-binned-copies).
pub(super) const FINAL_EXTENT_PX: usize = 1400;
