//! The MCAP channels' message types and their JSON Schemas (contract.md, "MCAP layout").
//!
//! Schema names are the contract: `sunjitter.FrameAlignment`, `sunjitter.ReferenceChange` and
//! Foxglove's well-known `foxglove.Log` (so the Foxglove Log panel shows `/log`).

use serde::{Deserialize, Deserializer, Serialize, Serializer};
use serde_json::{json, Value};
use sunjitter_core::chain::Chain;
use sunjitter_core::record::{ReferenceKind, Status, TransformFields};

/// Schema encoding of every channel.
pub const SCHEMA_ENCODING: &str = "jsonschema";
/// Message encoding of every channel.
pub const MESSAGE_ENCODING: &str = "json";

pub const FRAME_ALIGNMENT_SCHEMA: &str = "sunjitter.FrameAlignment";
pub const REFERENCE_CHANGE_SCHEMA: &str = "sunjitter.ReferenceChange";
pub const LOG_SCHEMA: &str = "foxglove.Log";
pub const ALERT_SCHEMA: &str = "sunjitter.Alert";

/// Topic of the per-frame alignments of one channel.
pub fn jitter_topic(channel: &str) -> String {
    format!("/jitter/{channel}")
}

/// Topic of the reference changes of one channel.
pub fn reference_topic(channel: &str) -> String {
    format!("/reference/{channel}")
}

/// Topic of warnings and errors per input file.
pub const LOG_TOPIC: &str = "/log";

/// Topic of alerts raised and resolved by the daemon's monitor.
pub const ALERT_TOPIC: &str = "/alert";

/// Name of the metadata record written at the start of every segment.
pub const METADATA_NAME: &str = "sunjitter";

/// One `/reference/<channel>` message: a reference was chosen or replaced, with its chain
/// where the policy knows it (a restart goes on from it).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ReferenceChange {
    /// The channel whose reference changed.
    pub channel: String,
    /// The new reference's file.
    pub file: String,
    /// Frame index within a 3-D cube; `null` for a 2-D image. Logs that called it `frame` read
    /// as well.
    #[serde(alias = "frame")]
    pub cube_frame: Option<usize>,
    /// The new reference's observation time, ISO 8601 UTC.
    pub obs_time: String,
    /// Why: e.g. `first frame`, `refresh after 100 frames`, `match degraded`.
    pub reason: String,
    pub reference_kind: ReferenceKind,
    /// `sequence` of the first frame aligned to this reference.
    pub sequence: u64,
    /// The reference it replaces (`FILE` or `FILE[N]`), `null` for the first.
    pub replaces: Option<String>,
    /// A keyframe reached two ways (through the keyframe it replaces and through the one
    /// before that): how far the two chains are apart, and the σ of that difference.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub closure: Option<ReferenceClosure>,
    /// The covariance of the new keyframe's chain with the chain of the keyframe it replaces
    /// (16 numbers, row by row, over scale, rotation rad, dx px, dy px): with `chain`, what a
    /// restart needs to go on exactly as the run would have.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub cross_covariance: Option<Vec<f64>>,
    /// The new reference's chain (origin grid → its grid), where the policy knows it.
    #[serde(
        default,
        with = "chain_fields",
        skip_serializing_if = "Option::is_none"
    )]
    pub chain: Option<Chain>,
}

/// A chain in a `/reference` message: its parameters, the centre they turn about, its plate
/// scale and its covariance as 16 numbers row by row (JSON Schema as Foxglove reads it has no
/// arrays of arrays).
mod chain_fields {
    use serde::{Deserialize, Deserializer, Serialize, Serializer};
    use sunjitter_core::chain::Chain;
    use sunjitter_core::geometry::Similarity;

    #[derive(Serialize, Deserialize)]
    struct Fields {
        scale: f64,
        rotation_rad: f64,
        dx_px: f64,
        dy_px: f64,
        center_px: [f64; 2],
        #[serde(default)]
        covariance: Option<Vec<f64>>,
        #[serde(default)]
        plate_scale_arcsec: Option<[f64; 2]>,
    }

    pub fn serialize<S: Serializer>(chain: &Option<Chain>, s: S) -> Result<S::Ok, S::Error> {
        chain
            .as_ref()
            .map(|c| Fields {
                scale: c.transform.scale,
                rotation_rad: c.transform.rotation_rad,
                dx_px: c.transform.dx,
                dy_px: c.transform.dy,
                center_px: c.transform.center,
                covariance: c.covariance.map(|m| m.iter().flatten().copied().collect()),
                plate_scale_arcsec: c.plate_scale_arcsec,
            })
            .serialize(s)
    }

    pub fn deserialize<'de, D: Deserializer<'de>>(d: D) -> Result<Option<Chain>, D::Error> {
        Ok(Option::<Fields>::deserialize(d)?.map(|f| Chain {
            transform: Similarity {
                scale: f.scale,
                rotation_rad: f.rotation_rad,
                dx: f.dx_px,
                dy: f.dy_px,
                center: f.center_px,
            },
            covariance: f
                .covariance
                .filter(|v| v.len() == 16)
                .map(|v| std::array::from_fn(|r| std::array::from_fn(|c| v[4 * r + c]))),
            plate_scale_arcsec: f.plate_scale_arcsec,
        }))
    }
}

/// The closure of a keyframe's two chains (`/reference` messages' `closure`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ReferenceClosure {
    /// The keyframe before the one replaced, through which the second chain runs.
    pub through: String,
    /// Second chain minus first, per parameter.
    pub difference: TransformFields,
    /// 1-σ of that difference.
    pub sigma: TransformFields,
}

impl ReferenceClosure {
    /// The differences in units of their σ (scale, rotation, dx, dy); 0 where a σ is 0.
    pub fn z(&self) -> [f64; 4] {
        let (d, s) = (&self.difference, &self.sigma);
        let ratio = |a: f64, b: f64| if b > 0.0 { a / b } else { 0.0 };
        [
            ratio(d.scale, s.scale),
            ratio(d.rotation_arcsec, s.rotation_arcsec),
            ratio(d.dx_px, s.dx_px),
            ratio(d.dy_px, s.dy_px),
        ]
    }
}

impl ReferenceChange {
    /// The new reference as a frame key (`FILE` or `FILE[N]`).
    pub fn key(&self) -> String {
        crate::fits::frame_key(std::path::Path::new(&self.file), self.cube_frame)
    }
}

/// One `/alert` message: a monitored condition of a channel started (`raised`) or ended
/// (`resolved`). A `resolved` message repeats the `channel`, `kind` and `threshold` of the
/// `raised` one it ends; `value` is the value that ended it.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Alert {
    pub channel: String,
    /// The configuration key of the threshold, e.g. `jump_px`, `silence_s`.
    pub kind: String,
    /// `raised` or `resolved`.
    pub state: String,
    /// `warning` or `error`.
    pub severity: String,
    pub value: f64,
    pub threshold: f64,
    /// Unit of `value` and `threshold`: `px`, `arcsec`, `s` or `frames`.
    pub unit: String,
    /// The frame (`FILE` or `FILE[N]`) that changed the state; `null` for time-based changes.
    pub frame: Option<String>,
    /// When: the frame's observation time, or the wall clock for time-based changes (ISO 8601 UTC).
    pub time: String,
    /// One line for people.
    pub message: String,
}

/// Foxglove log levels (`foxglove.LogLevel`), serialised as their numbers.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub enum LogLevel {
    Unknown = 0,
    Debug = 1,
    Info = 2,
    Warning = 3,
    Error = 4,
    Fatal = 5,
}

impl LogLevel {
    pub fn from_number(n: u8) -> Option<LogLevel> {
        Some(match n {
            0 => LogLevel::Unknown,
            1 => LogLevel::Debug,
            2 => LogLevel::Info,
            3 => LogLevel::Warning,
            4 => LogLevel::Error,
            5 => LogLevel::Fatal,
            _ => return None,
        })
    }
}

impl Serialize for LogLevel {
    fn serialize<S: Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        s.serialize_u8(*self as u8)
    }
}

impl<'de> Deserialize<'de> for LogLevel {
    fn deserialize<D: Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        let n = u8::deserialize(d)?;
        LogLevel::from_number(n)
            .ok_or_else(|| serde::de::Error::custom(format!("log level {n} is not 0..=5")))
    }
}

/// `foxglove.Log` `timestamp` (`time`: seconds and nanoseconds since the Unix epoch).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct FoxgloveTime {
    pub sec: u64,
    pub nsec: u32,
}

impl FoxgloveTime {
    pub fn from_ns(ns: u64) -> Self {
        FoxgloveTime {
            sec: ns / 1_000_000_000,
            nsec: (ns % 1_000_000_000) as u32,
        }
    }

    pub fn to_ns(self) -> u64 {
        self.sec
            .saturating_mul(1_000_000_000)
            .saturating_add(self.nsec as u64)
    }
}

/// One `/log` message (`foxglove.Log`). `file` names the input file (`FILE` or `FILE[N]`) the
/// entry is about, `name` is always `sunjitter`, `line` is 0 (not a source location).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct LogEntry {
    pub timestamp: FoxgloveTime,
    pub level: LogLevel,
    pub message: String,
    pub name: String,
    pub file: String,
    pub line: u32,
}

/// A number that is `null` when there is no value (e.g. a failed frame). Foxglove's JSON
/// Schema parser takes one `type` per field and rejects `["number", "null"]`, so nullability
/// is marked with OpenAPI's `nullable` keyword, which JSON Schema validators ignore.
fn number_or_null(description: &str) -> Value {
    json!({ "type": "number", "nullable": true, "description": description })
}

/// JSON Schema of a transform's fields (`TransformFields`).
fn transform_fields_schema(description: &str) -> Value {
    json!({
        "type": "object",
        "description": description,
        "properties": {
            "scale": { "type": "number" },
            "rotation_arcsec": { "type": "number" },
            "dx_px": { "type": "number" },
            "dy_px": { "type": "number" }
        },
        "required": ["scale", "rotation_arcsec", "dx_px", "dy_px"]
    })
}

/// JSON Schema of `sunjitter.FrameAlignment` (fields of `sunjitter_core::record::FrameAlignment`).
pub fn frame_alignment_schema() -> Value {
    let mut transform =
        transform_fields_schema("The part of the transform the FITS headers did not predict");
    transform["nullable"] = json!(true);
    let mut properties = serde_json::Map::new();
    let mut put = |name: &str, v: Value| {
        properties.insert(name.to_string(), v);
    };
    put(
        "reference",
        json!({ "type": "string", "description": "Reference image (FILE or FILE[N])" }),
    );
    put(
        "frame",
        json!({ "type": "string", "description": "Aligned frame (FILE or FILE[N])" }),
    );
    put("scale", number_or_null("Scale s (unitless)"));
    put(
        "rotation_arcsec",
        number_or_null("Rotation θ, counter-clockwise, arcsec"),
    );
    put(
        "dx_px",
        number_or_null("Shift along x (columns), reference pixels"),
    );
    put(
        "dy_px",
        number_or_null("Shift along y (rows), reference pixels"),
    );
    put(
        "dx_arcsec",
        number_or_null("dx_px times the plate scale used (the header's, or the disk-checked one)"),
    );
    put(
        "dy_arcsec",
        number_or_null("dy_px times the plate scale used (the header's, or the disk-checked one)"),
    );
    for p in [
        "scale",
        "rotation_arcsec",
        "dx_px",
        "dy_px",
        "dx_arcsec",
        "dy_arcsec",
    ] {
        put(
            &format!("sigma_{p}"),
            number_or_null("Calibrated 1-σ standard error"),
        );
    }
    for p in ["scale", "rotation_arcsec", "dx_px", "dy_px"] {
        put(
            &format!("uabjm_sigma_{p}"),
            number_or_null("Plain UABJM 1-σ, (JᵀJ)⁻¹σ²"),
        );
    }
    put("header_residual", transform);
    put(
        "solar_rotation",
        json!({
            "type": "object",
            "nullable": true,
            "description": "The Sun's differential rotation taken out between the two times",
            "properties": {
                "profile": { "type": "string", "enum": ["howard", "snodgrass", "allen", "none"] },
                "dt_s": { "type": "number", "description": "Frame time minus reference time, s" },
                "dx_px": { "type": "number", "description": "Motion removed at the disk (or tracked field's) centre, x, px" },
                "dy_px": { "type": "number", "description": "Motion removed at the disk (or tracked field's) centre, y, px" },
                "tracked": { "type": "boolean", "description": "Partial field taken to follow the Sun at its centre" }
            },
            "required": ["profile", "dt_s", "dx_px", "dy_px", "tracked"]
        }),
    );
    put(
        "points",
        json!({ "type": "integer", "minimum": 0, "description": "Flow sample points" }),
    );
    put(
        "inliers",
        json!({ "type": "integer", "minimum": 0, "description": "RANSAC inliers" }),
    );
    put(
        "residual_rms_px",
        number_or_null("RMS residual of the inliers, px"),
    );
    put(
        "similarity",
        number_or_null("Bhattacharyya coefficient of the histograms"),
    );
    put(
        "model",
        json!({
            "type": "string",
            "nullable": true,
            "description": "The transform fitted: similarity, rigid or translation; scale and rotation not fitted are the headers' values, with the instrument's stability as σ (null: nothing fitted)"
        }),
    );
    put("status", json!({ "type": "string", "enum": Status::NAMES }));
    put(
        "message",
        json!({ "type": "string", "description": "Why degraded or failed" }),
    );
    put(
        "elapsed_ms",
        json!({ "type": "number", "description": "Processing time, ms" }),
    );
    put("channel", json!({ "type": "string" }));
    put(
        "obs_time",
        json!({ "type": "string", "description": "Observation time, ISO 8601 UTC" }),
    );
    put("sequence", json!({ "type": "integer", "minimum": 0 }));
    put(
        "reference_kind",
        json!({ "type": "string", "enum": ["self", "previous", "keyframe", "fixed", "channel"] }),
    );
    for p in ["dx_px", "dy_px", "rotation_arcsec", "scale"] {
        put(
            &format!("chained_{p}"),
            number_or_null("Relative to the chain's origin (the channel's first reference)"),
        );
    }
    for p in ["dx", "dy"] {
        put(
            &format!("chained_{p}_arcsec"),
            number_or_null(&format!(
                "chained_{p}_px times the plate scale the alignments to the chain's origin used"
            )),
        );
    }
    for p in [
        "dx_px",
        "dy_px",
        "dx_arcsec",
        "dy_arcsec",
        "rotation_arcsec",
        "scale",
    ] {
        put(
            &format!("sigma_chained_{p}"),
            number_or_null("1-σ of the chained value"),
        );
    }
    let required: Vec<&String> = properties.keys().collect();
    let required = json!(required);
    // Beyond the contract, optional (additive): absent from logs written before it existed.
    properties.insert(
        "pixel_checksum".to_string(),
        json!({ "type": "string",
                "description": "xxh3_64:HEX of the aligned pixels as read (width, height, f32 bits)" }),
    );
    json!({
        "title": FRAME_ALIGNMENT_SCHEMA,
        "description": "Alignment of one frame to its reference (sunjitter contract.md)",
        "type": "object",
        "properties": properties,
        "required": required
    })
}

/// JSON Schema of `sunjitter.ReferenceChange`.
pub fn reference_change_schema() -> Value {
    json!({
        "title": REFERENCE_CHANGE_SCHEMA,
        "description": "A reference was chosen or replaced for a channel",
        "type": "object",
        "properties": {
            "channel": { "type": "string" },
            "file": { "type": "string", "description": "The new reference's file" },
            "cube_frame": { "type": "integer", "nullable": true, "minimum": 0,
                            "description": "Frame index in a 3-D cube (null for a 2-D image)" },
            "obs_time": { "type": "string", "description": "ISO 8601 UTC" },
            "reason": { "type": "string" },
            "reference_kind": { "type": "string",
                                "enum": ["self", "previous", "keyframe", "fixed", "channel"] },
            "sequence": { "type": "integer", "minimum": 0,
                          "description": "sequence of the first frame aligned to it" },
            "replaces": { "type": "string", "nullable": true,
                          "description": "The previous reference" },
            "closure": {
                "type": "object",
                "description": "A keyframe reached through the keyframe it replaces and through the one before: second chain minus first, and the σ of that difference (absent for other references)",
                "properties": {
                    "through": { "type": "string", "description": "The keyframe before the one replaced" },
                    "difference": transform_fields_schema("Second chain minus first"),
                    "sigma": transform_fields_schema("1-σ of the difference")
                },
                "required": ["through", "difference", "sigma"]
            },
            "chain": {
                "type": "object",
                "description": "The reference's chain (origin grid → its grid), for restarts",
                "properties": {
                    "scale": { "type": "number" },
                    "rotation_rad": { "type": "number" },
                    "dx_px": { "type": "number" },
                    "dy_px": { "type": "number" },
                    "center_px": { "type": "array", "items": { "type": "number" } },
                    "covariance": { "type": "array", "items": { "type": "number" },
                                    "description": "4 × 4, row by row: scale, rotation rad, dx px, dy px" },
                    "plate_scale_arcsec": { "type": "array", "items": { "type": "number" } }
                },
                "required": ["scale", "rotation_rad", "dx_px", "dy_px", "center_px"]
            },
            "cross_covariance": { "type": "array", "items": { "type": "number" },
                "description": "The chain's covariance with that of the keyframe it replaces, 4 × 4 row by row; for restarts" }
        },
        "required": ["channel", "file", "cube_frame", "obs_time", "reason", "reference_kind",
                     "sequence", "replaces"]
    })
}

/// JSON Schema of `sunjitter.Alert`.
pub fn alert_schema() -> Value {
    json!({
        "title": ALERT_SCHEMA,
        "description": "A monitored condition of a channel was raised or resolved",
        "type": "object",
        "properties": {
            "channel": { "type": "string" },
            "kind": { "type": "string", "description": "Threshold key, e.g. jump_px" },
            "state": { "type": "string", "enum": ["raised", "resolved"] },
            "severity": { "type": "string", "enum": ["warning", "error"] },
            "value": { "type": "number" },
            "threshold": { "type": "number" },
            "unit": { "type": "string", "enum": ["px", "arcsec", "s", "frames"] },
            "frame": { "type": "string", "nullable": true,
                       "description": "The frame that changed the state" },
            "time": { "type": "string", "description": "ISO 8601 UTC" },
            "message": { "type": "string" }
        },
        "required": ["channel", "kind", "state", "severity", "value", "threshold", "unit",
                     "frame", "time", "message"]
    })
}

/// JSON Schema of Foxglove's `foxglove.Log`, as the Foxglove SDK publishes it.
pub fn log_schema() -> Value {
    let level =
        |title: &str, n: u8, d: &str| json!({ "title": title, "const": n, "description": d });
    json!({
        "title": LOG_SCHEMA,
        "description": "A log message",
        "type": "object",
        "properties": {
            "timestamp": {
                "type": "object",
                "title": "time",
                "properties": {
                    "sec": { "type": "integer", "minimum": 0 },
                    "nsec": { "type": "integer", "minimum": 0, "maximum": 999_999_999 }
                },
                "description": "Timestamp of log message"
            },
            "level": {
                "title": "foxglove.LogLevel",
                "description": "Log level",
                "oneOf": [
                    level("UNKNOWN", 0, "Unknown log level"),
                    level("DEBUG", 1, "Debug log level"),
                    level("INFO", 2, "Info log level"),
                    level("WARNING", 3, "Warning log level"),
                    level("ERROR", 4, "Error log level"),
                    level("FATAL", 5, "Fatal log level")
                ]
            },
            "message": { "type": "string", "description": "Log message" },
            "name": { "type": "string", "description": "Process or node name" },
            "file": { "type": "string", "description": "Filename" },
            "line": { "type": "integer", "minimum": 0, "description": "Line number in the file" }
        },
        "required": ["timestamp", "level", "message", "name", "file", "line"]
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Foxglove's JSON Schema parser (foxglove studio `parseJsonSchema.ts`) accepts per field
    /// either a `oneOf` of numeric `const`s or one `type` among boolean, string, number,
    /// integer, object (recursively) and array (of those); anything else fails the channel.
    fn foxglove_parsable(schema: &Value, path: &str) -> Result<(), String> {
        if schema["type"] != "object" {
            return Err(format!("{path}: root/nested type must be \"object\""));
        }
        let props = schema["properties"]
            .as_object()
            .ok_or(format!("{path}: no properties"))?;
        for (name, field) in props {
            let here = format!("{path}.{name}");
            if let Some(alternatives) = field["oneOf"].as_array() {
                if alternatives.iter().all(|a| a["const"].is_number()) {
                    continue;
                }
                return Err(format!("{here}: oneOf alternatives must be numeric consts"));
            }
            match field["type"].as_str() {
                Some("boolean" | "number" | "integer") => {}
                Some("string") if field.get("contentEncoding").is_none() => {}
                Some("object") => foxglove_parsable(field, &here)?,
                Some("array") => match field["items"]["type"].as_str() {
                    Some("boolean" | "string" | "number" | "integer") => {}
                    Some("object") => foxglove_parsable(&field["items"], &here)?,
                    other => return Err(format!("{here}: array items of type {other:?}")),
                },
                _ => return Err(format!("{here}: unsupported type {}", field["type"])),
            }
        }
        Ok(())
    }

    #[test]
    fn schemas_load_in_foxglove() {
        for (name, schema) in [
            (FRAME_ALIGNMENT_SCHEMA, frame_alignment_schema()),
            (REFERENCE_CHANGE_SCHEMA, reference_change_schema()),
            (LOG_SCHEMA, log_schema()),
            (ALERT_SCHEMA, alert_schema()),
        ] {
            foxglove_parsable(&schema, name).unwrap();
        }
        // The check itself rejects what Foxglove rejects.
        let nullable_union =
            json!({"type": "object", "properties": {"x": {"type": ["number", "null"]}}});
        assert!(foxglove_parsable(&nullable_union, "t").is_err());
    }

    #[test]
    fn log_levels_are_foxglove_numbers() {
        // foxglove.LogLevel: UNKNOWN 0, DEBUG 1, INFO 2, WARNING 3, ERROR 4, FATAL 5
        // (docs.foxglove.dev/docs/sdk/schemas/log).
        let levels = [
            (LogLevel::Unknown, 0),
            (LogLevel::Debug, 1),
            (LogLevel::Info, 2),
            (LogLevel::Warning, 3),
            (LogLevel::Error, 4),
            (LogLevel::Fatal, 5),
        ];
        for (level, n) in levels {
            assert_eq!(serde_json::to_string(&level).unwrap(), n.to_string());
            assert_eq!(
                serde_json::from_str::<LogLevel>(&n.to_string()).unwrap(),
                level
            );
        }
        assert!(serde_json::from_str::<LogLevel>("6").is_err());
    }

    #[test]
    fn foxglove_time_splits_nanoseconds() {
        let t = FoxgloveTime::from_ns(1_396_102_178_123_456_789);
        assert_eq!(
            t,
            FoxgloveTime {
                sec: 1_396_102_178,
                nsec: 123_456_789
            }
        );
        assert_eq!(t.to_ns(), 1_396_102_178_123_456_789);
    }

    #[test]
    fn reference_change_json_has_the_schema_fields() {
        let change = ReferenceChange {
            channel: "SJI_1400".into(),
            file: "a.fits".into(),
            cube_frame: Some(3),
            obs_time: "2014-03-29T14:09:38Z".into(),
            reason: "first frame".into(),
            reference_kind: ReferenceKind::Keyframe,
            sequence: 0,
            replaces: None,
            closure: Some(ReferenceClosure {
                through: "b.fits".into(),
                difference: TransformFields {
                    scale: 0.0,
                    rotation_arcsec: 0.0,
                    dx_px: 0.01,
                    dy_px: -0.02,
                },
                sigma: TransformFields {
                    scale: 1e-4,
                    rotation_arcsec: 60.0,
                    dx_px: 0.03,
                    dy_px: 0.03,
                },
            }),
            cross_covariance: Some(vec![0.0; 16]),
            chain: Some(Chain::origin([64.0, 64.0], Some([0.6, 0.6]))),
        };
        let v = serde_json::to_value(&change).unwrap();
        let schema = reference_change_schema();
        let props: Vec<&String> = schema["properties"].as_object().unwrap().keys().collect();
        let keys: Vec<&String> = v.as_object().unwrap().keys().collect();
        let mut props_sorted = props.clone();
        props_sorted.sort();
        let mut keys_sorted = keys.clone();
        keys_sorted.sort();
        assert_eq!(props_sorted, keys_sorted);
    }
}
