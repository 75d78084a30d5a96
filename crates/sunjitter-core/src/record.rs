//! The records sunjitter reports: `align --json` and the MCAP `/jitter/<channel>` messages.
//! Field names are the external contract (`docs/contract.md`); do not rename.

use schemars::JsonSchema;
use serde::{Deserialize, Serialize};

/// A frame's verdict (`status`), written as [`Status::as_str`] gives it: in the records, the
/// schema, the CSV, the log and every message that names it.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Status {
    Ok,
    Degraded,
    Failed,
}

impl Status {
    pub const ALL: [Status; 3] = [Status::Ok, Status::Degraded, Status::Failed];
    /// [`Status::ALL`] written.
    pub const NAMES: [&'static str; 3] = [
        Status::Ok.as_str(),
        Status::Degraded.as_str(),
        Status::Failed.as_str(),
    ];

    /// Its one written form.
    pub const fn as_str(self) -> &'static str {
        match self {
            Status::Ok => "ok",
            Status::Degraded => "degraded",
            Status::Failed => "failed",
        }
    }
}

impl std::fmt::Display for Status {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.as_str())
    }
}

impl Serialize for Status {
    fn serialize<S: serde::Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        s.serialize_str(self.as_str())
    }
}

impl JsonSchema for Status {
    fn schema_name() -> std::borrow::Cow<'static, str> {
        "Status".into()
    }

    fn json_schema(_: &mut schemars::SchemaGenerator) -> schemars::Schema {
        schemars::json_schema!({ "type": "string", "enum": Status::NAMES })
    }
}

impl<'de> Deserialize<'de> for Status {
    fn deserialize<D: serde::Deserializer<'de>>(d: D) -> Result<Status, D::Error> {
        let text = std::borrow::Cow::<'de, str>::deserialize(d)?;
        Status::ALL
            .into_iter()
            .find(|s| s.as_str() == text)
            .ok_or_else(|| serde::de::Error::unknown_variant(&text, &Status::NAMES))
    }
}

/// The transform a record's numbers come from (`model`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, JsonSchema)]
#[serde(rename_all = "lowercase")]
pub enum Model {
    /// Scale, rotation and shift fitted.
    Similarity,
    /// Rotation and shift fitted; scale from the headers.
    Rigid,
    /// Shift fitted; scale and rotation from the headers.
    Translation,
}

impl Model {
    pub fn as_str(self) -> &'static str {
        match self {
            Model::Similarity => "similarity",
            Model::Rigid => "rigid",
            Model::Translation => "translation",
        }
    }
}

/// Which reference a frame was aligned to (`reference_kind`): itself, or what its channel's
/// policy chose.
#[derive(
    Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash, Serialize, Deserialize, JsonSchema,
)]
#[serde(rename_all = "lowercase")]
pub enum ReferenceKind {
    /// The frame is its own reference: a chain's origin, or a frame no reference could take.
    #[serde(rename = "self")]
    Itself,
    Previous,
    Keyframe,
    Fixed,
    Channel,
}

impl ReferenceKind {
    /// The name in messages and logs.
    pub fn as_str(self) -> &'static str {
        match self {
            ReferenceKind::Itself => "self",
            ReferenceKind::Previous => "previous",
            ReferenceKind::Keyframe => "keyframe",
            ReferenceKind::Fixed => "fixed",
            ReferenceKind::Channel => "channel",
        }
    }
}

impl std::fmt::Display for ReferenceKind {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.as_str())
    }
}

/// A transform in the contract's units (the `header_residual` object).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize, JsonSchema)]
pub struct TransformFields {
    pub scale: f64,
    pub rotation_arcsec: f64,
    pub dx_px: f64,
    pub dy_px: f64,
}

/// The Sun's differential rotation taken out between the two times.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize, JsonSchema)]
pub struct SolarRotationFields {
    /// The rotation law: howard, snodgrass, allen or none.
    pub profile: crate::solar_rotation::Profile,
    /// Frame time minus reference time, s.
    pub dt_s: f64,
    /// Motion removed at the centre of the measured region (the disk centre for full-disk
    /// images), x, reference pixels.
    pub dx_px: f64,
    /// The same, y.
    pub dy_px: f64,
    /// The field was taken to follow the Sun (a partial field): the motion of its centre was
    /// left to the pointing.
    pub tracked: bool,
}

/// The result of aligning one frame to one reference (`align --json`).
/// Numbers are `None` (JSON `null`) when `status` is `failed`.
///
/// The doc comments of the fields are the MCAP schema's descriptions (contract.md).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
pub struct AlignResult {
    /// Reference image (FILE or FILE[N]).
    pub reference: String,
    /// Aligned frame (FILE or FILE[N]).
    pub frame: String,
    /// Scale s (unitless).
    pub scale: Option<f64>,
    /// Rotation θ, counter-clockwise, arcsec.
    pub rotation_arcsec: Option<f64>,
    /// Shift along x (columns), reference pixels.
    pub dx_px: Option<f64>,
    /// Shift along y (rows), reference pixels.
    pub dy_px: Option<f64>,
    /// dx_px times the plate scale used (the header's, or the disk-checked one).
    pub dx_arcsec: Option<f64>,
    /// dy_px times the plate scale used (the header's, or the disk-checked one).
    pub dy_arcsec: Option<f64>,
    /// Calibrated 1-σ standard error of scale.
    pub sigma_scale: Option<f64>,
    /// Calibrated 1-σ standard error of rotation_arcsec.
    pub sigma_rotation_arcsec: Option<f64>,
    /// Calibrated 1-σ standard error of dx_px.
    pub sigma_dx_px: Option<f64>,
    /// Calibrated 1-σ standard error of dy_px.
    pub sigma_dy_px: Option<f64>,
    /// sigma_dx_px times the plate scale used, arcsec.
    #[serde(default)]
    pub sigma_dx_arcsec: Option<f64>,
    /// sigma_dy_px times the plate scale used, arcsec.
    #[serde(default)]
    pub sigma_dy_arcsec: Option<f64>,
    /// Plain UABJM 1-σ of scale, (JᵀJ)⁻¹σ².
    pub uabjm_sigma_scale: Option<f64>,
    /// Plain UABJM 1-σ of rotation_arcsec, (JᵀJ)⁻¹σ².
    pub uabjm_sigma_rotation_arcsec: Option<f64>,
    /// Plain UABJM 1-σ of dx_px, (JᵀJ)⁻¹σ².
    pub uabjm_sigma_dx_px: Option<f64>,
    /// Plain UABJM 1-σ of dy_px, (JᵀJ)⁻¹σ².
    pub uabjm_sigma_dy_px: Option<f64>,
    /// The part of the transform the FITS headers did not predict.
    pub header_residual: Option<TransformFields>,
    /// The Sun's differential rotation taken out between the two times (null when nothing
    /// was).
    #[serde(default)]
    pub solar_rotation: Option<SolarRotationFields>,
    /// Flow sample points.
    pub points: usize,
    /// RANSAC inliers.
    pub inliers: usize,
    /// RMS residual of the inliers, px.
    pub residual_rms_px: Option<f64>,
    /// Bhattacharyya coefficient of the histograms.
    pub similarity: Option<f64>,
    /// The transform fitted: similarity, rigid or translation; scale and rotation not fitted
    /// are the headers' values, with the instrument's stability as σ (null: nothing fitted, a
    /// failed frame or one that starts a reference).
    #[serde(default)]
    pub model: Option<Model>,
    /// ok, degraded or failed.
    pub status: Status,
    /// Why degraded or failed.
    pub message: String,
    /// Processing time, ms.
    pub elapsed_ms: f64,
}

impl AlignResult {
    /// The identity, with zero σ, of `frame` measured against `reference` (a frame aligned to
    /// itself); `status` ok, no model fitted, no rotation taken out.
    pub fn identity(reference: String, frame: String, message: &str) -> AlignResult {
        AlignResult {
            reference,
            frame,
            scale: Some(1.0),
            rotation_arcsec: Some(0.0),
            dx_px: Some(0.0),
            dy_px: Some(0.0),
            dx_arcsec: Some(0.0),
            dy_arcsec: Some(0.0),
            sigma_scale: Some(0.0),
            sigma_rotation_arcsec: Some(0.0),
            sigma_dx_px: Some(0.0),
            sigma_dy_px: Some(0.0),
            sigma_dx_arcsec: Some(0.0),
            sigma_dy_arcsec: Some(0.0),
            uabjm_sigma_scale: Some(0.0),
            uabjm_sigma_rotation_arcsec: Some(0.0),
            uabjm_sigma_dx_px: Some(0.0),
            uabjm_sigma_dy_px: Some(0.0),
            header_residual: Some(TransformFields {
                scale: 1.0,
                rotation_arcsec: 0.0,
                dx_px: 0.0,
                dy_px: 0.0,
            }),
            solar_rotation: None,
            points: 0,
            inliers: 0,
            residual_rms_px: Some(0.0),
            similarity: Some(1.0),
            model: None,
            status: Status::Ok,
            message: message.into(),
            elapsed_ms: 0.0,
        }
    }
}

/// One `/jitter/<channel>` MCAP message: the align fields plus the stream context.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
pub struct FrameAlignment {
    #[serde(flatten)]
    pub align: AlignResult,
    /// The channel (topic name).
    pub channel: String,
    /// Observation time, ISO 8601 UTC.
    pub obs_time: String,
    /// The frame's number within its channel, from 0.
    pub sequence: u64,
    /// Which reference the frame was aligned to: itself, or what its channel's policy chose.
    pub reference_kind: ReferenceKind,
    /// dx_px relative to the chain's origin (the channel's first reference).
    pub chained_dx_px: Option<f64>,
    /// dy_px relative to the chain's origin (the channel's first reference).
    pub chained_dy_px: Option<f64>,
    /// chained_dx_px times the plate scale the alignments to the chain's origin used.
    #[serde(default)]
    pub chained_dx_arcsec: Option<f64>,
    /// chained_dy_px times the plate scale the alignments to the chain's origin used.
    #[serde(default)]
    pub chained_dy_arcsec: Option<f64>,
    /// rotation_arcsec relative to the chain's origin.
    pub chained_rotation_arcsec: Option<f64>,
    /// scale relative to the chain's origin.
    pub chained_scale: Option<f64>,
    /// 1-σ of chained_dx_px.
    pub sigma_chained_dx_px: Option<f64>,
    /// 1-σ of chained_dy_px.
    pub sigma_chained_dy_px: Option<f64>,
    /// 1-σ of chained_dx_arcsec.
    #[serde(default)]
    pub sigma_chained_dx_arcsec: Option<f64>,
    /// 1-σ of chained_dy_arcsec.
    #[serde(default)]
    pub sigma_chained_dy_arcsec: Option<f64>,
    /// 1-σ of chained_rotation_arcsec.
    pub sigma_chained_rotation_arcsec: Option<f64>,
    /// 1-σ of chained_scale.
    pub sigma_chained_scale: Option<f64>,
    /// Beyond the contract (additive): xxh3_64:HEX of the aligned pixels as read (width,
    /// height, f32 bits), so a log can prove no frame was read half-written.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub pixel_checksum: Option<String>,
}

impl FrameAlignment {
    /// A message with every field present (no `null`, every nested object), from which lists
    /// of the fields in the order the type declares them are read (the CSV's columns).
    pub fn with_every_field() -> FrameAlignment {
        let align = AlignResult {
            solar_rotation: Some(SolarRotationFields {
                profile: crate::solar_rotation::Profile::Howard,
                dt_s: 0.0,
                dx_px: 0.0,
                dy_px: 0.0,
                tracked: false,
            }),
            model: Some(Model::Similarity),
            ..AlignResult::identity(String::new(), String::new(), "")
        };
        FrameAlignment {
            align,
            channel: String::new(),
            obs_time: String::new(),
            sequence: 0,
            reference_kind: ReferenceKind::Keyframe,
            chained_dx_px: Some(0.0),
            chained_dy_px: Some(0.0),
            chained_dx_arcsec: Some(0.0),
            chained_dy_arcsec: Some(0.0),
            chained_rotation_arcsec: Some(0.0),
            chained_scale: Some(1.0),
            sigma_chained_dx_px: Some(0.0),
            sigma_chained_dy_px: Some(0.0),
            sigma_chained_dx_arcsec: Some(0.0),
            sigma_chained_dy_arcsec: Some(0.0),
            sigma_chained_rotation_arcsec: Some(0.0),
            sigma_chained_scale: Some(0.0),
            pixel_checksum: Some(String::new()),
        }
    }

    /// A message for `align` with no chained values (a chain fills them in) and no checksum.
    pub fn unchained(
        align: AlignResult,
        channel: String,
        obs_time: String,
        sequence: u64,
        reference_kind: ReferenceKind,
    ) -> Self {
        Self {
            align,
            channel,
            obs_time,
            sequence,
            reference_kind,
            chained_dx_px: None,
            chained_dy_px: None,
            chained_dx_arcsec: None,
            chained_dy_arcsec: None,
            chained_rotation_arcsec: None,
            chained_scale: None,
            sigma_chained_dx_px: None,
            sigma_chained_dy_px: None,
            sigma_chained_dx_arcsec: None,
            sigma_chained_dy_arcsec: None,
            sigma_chained_rotation_arcsec: None,
            sigma_chained_scale: None,
            pixel_checksum: None,
        }
    }
}

/// `xxh3_64:<16 hex digits>`: 64-bit XXH3 (seed 0) over the width and height (u64,
/// little-endian) then every pixel's f32 bit pattern (little-endian), row by row. XXH3 reads
/// memory at its bandwidth; a byte-serial hash would cost a 4096² frame about 0.1 s of a core.
pub fn pixel_checksum(pixels: ndarray::ArrayView2<f32>) -> String {
    let mut digest = xxhash_rust::xxh3::Xxh3::new();
    let (height, width) = pixels.dim();
    digest.update(&(width as u64).to_le_bytes());
    digest.update(&(height as u64).to_le_bytes());
    for row in pixels.rows() {
        match row.as_slice() {
            Some(values) if cfg!(target_endian = "little") => {
                digest.update(bytemuck::cast_slice(values))
            }
            _ => row
                .iter()
                .for_each(|v| digest.update(&v.to_bits().to_le_bytes())),
        }
    }
    format!("xxh3_64:{:016x}", digest.digest())
}

#[cfg(test)]
mod tests {
    use super::Status;

    #[test]
    fn a_status_reads_back_from_its_one_written_form() {
        for status in Status::ALL {
            let text = serde_json::to_string(&status).unwrap();
            assert_eq!(text, format!("\"{}\"", status.as_str()));
            assert_eq!(serde_json::from_str::<Status>(&text).unwrap(), status);
            assert_eq!(status.to_string(), status.as_str());
        }
        let refused = serde_json::from_str::<Status>("\"Ok\"").unwrap_err();
        assert!(refused.to_string().contains("`degraded`"), "{refused}");
    }
}
