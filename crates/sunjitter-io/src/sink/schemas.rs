//! The MCAP channels' message types and their JSON Schemas (contract.md, "MCAP layout").
//!
//! Schema names are the contract: `sunjitter.FrameAlignment`, `sunjitter.ReferenceChange` and
//! Foxglove's well-known `foxglove.Log` (so the Foxglove Log panel shows `/log`). Each schema
//! is generated from its message type (fields, types, doc comments as descriptions), in the
//! dialect Foxglove's JSON Schema parser reads ([`schema_of`]).

use schemars::JsonSchema;
use serde::{Deserialize, Deserializer, Serialize, Serializer};
use serde_json::{json, Value};
use sunjitter_core::chain::Chain;
use sunjitter_core::record::{FrameAlignment, ReferenceKind, TransformFields};

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

/// One `/reference/<channel>` message: a reference was chosen or replaced for a channel, with
/// its chain where the policy knows it (a restart goes on from it).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
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
    /// The kind of reference the channel's frames are now aligned to.
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
    /// The new reference's chain (origin grid → its grid), where the policy knows it; for
    /// restarts.
    #[serde(
        default,
        with = "chain_fields",
        skip_serializing_if = "Option::is_none"
    )]
    #[schemars(with = "Option<chain_fields::Fields>")]
    pub chain: Option<Chain>,
}

/// A chain in a `/reference` message: its parameters, the centre they turn about, its plate
/// scale and its covariance as 16 numbers row by row (JSON Schema as Foxglove reads it has no
/// arrays of arrays).
mod chain_fields {
    use schemars::JsonSchema;
    use serde::{Deserialize, Deserializer, Serialize, Serializer};
    use sunjitter_core::chain::Chain;
    use sunjitter_core::geometry::Similarity;

    /// A chain: origin grid → the reference's grid.
    #[derive(Serialize, Deserialize, JsonSchema)]
    pub struct Fields {
        scale: f64,
        rotation_rad: f64,
        dx_px: f64,
        dy_px: f64,
        /// The centre the rotation and scale turn about, px.
        center_px: [f64; 2],
        /// 4 × 4, row by row: scale, rotation rad, dx px, dy px.
        #[serde(default)]
        covariance: Option<Vec<f64>>,
        /// The plate scale of the chain's origin, arcsec/px (x, y).
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

/// A keyframe reached through the keyframe it replaces and through the one before: second
/// chain minus first, and the σ of that difference (absent for other references).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
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
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
pub struct Alert {
    /// The channel the condition is about.
    pub channel: String,
    /// The configuration key of the threshold, e.g. `jump_px`, `silence_s`.
    pub kind: String,
    /// `raised` or `resolved`.
    #[schemars(extend("enum" = ["raised", "resolved"]))]
    pub state: String,
    /// `warning` or `error`.
    #[schemars(extend("enum" = ["warning", "error"]))]
    pub severity: String,
    /// The value that changed the state.
    pub value: f64,
    /// The configured threshold.
    pub threshold: f64,
    /// Unit of `value` and `threshold`: `px`, `arcsec`, `σ`, `s` or `frames`.
    #[schemars(extend("enum" = ["px", "arcsec", "σ", "s", "frames"]))]
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

/// The JSON Schema of message type `T`, titled `title`, in the dialect Foxglove's parser reads:
/// every subschema inline, one `type` per field (a value that may be `null` is marked with
/// OpenAPI's `nullable`, which JSON Schema validators ignore, since Foxglove rejects
/// `["number", "null"]`), string choices as `enum`. Fields a message always carries are
/// `required`.
pub fn schema_of<T: JsonSchema>(title: &str) -> Value {
    let generator = schemars::generate::SchemaSettings::draft07()
        .with(|s| {
            s.inline_subschemas = true;
            s.meta_schema = None;
        })
        .for_serialize()
        .into_generator();
    let mut schema = generator.into_root_schema_for::<T>().to_value();
    foxglove_dialect(&mut schema);
    if let Some(root) = schema.as_object_mut() {
        root.insert("title".into(), json!(title));
    }
    schema
}

/// Rewrite a generated schema (and its subschemas) into the dialect of [`schema_of`].
fn foxglove_dialect(schema: &mut Value) {
    let Some(map) = schema.as_object_mut() else {
        return;
    };
    // `Option<T>` of a struct or enum: one alternative and `null`.
    for key in ["anyOf", "oneOf"] {
        let Some(Value::Array(alternatives)) = map.get(key) else {
            continue;
        };
        let is_null = |a: &Value| a["type"] == "null" || a.get("const") == Some(&Value::Null);
        let others: Vec<&Value> = alternatives.iter().filter(|a| !is_null(a)).collect();
        if others.len() == 1 && others.len() < alternatives.len() {
            let inner = others[0].clone();
            map.remove(key);
            if let Value::Object(inner) = inner {
                for (k, v) in inner {
                    map.entry(k).or_insert(v);
                }
            }
            map.insert("nullable".into(), json!(true));
        }
    }
    // A unit enum some of whose variants carry doc comments: `oneOf` of string constants.
    if let Some(Value::Array(alternatives)) = map.get("oneOf") {
        let names: Option<Vec<Vec<Value>>> = alternatives
            .iter()
            .map(|a| match (&a["const"], &a["enum"]) {
                (Value::String(s), _) => Some(vec![json!(s)]),
                (_, Value::Array(e)) if e.iter().all(Value::is_string) => Some(e.clone()),
                _ => None,
            })
            .collect();
        if let Some(names) = names.map(|n| n.concat()) {
            map.remove("oneOf");
            map.insert("type".into(), json!("string"));
            map.insert("enum".into(), Value::Array(names));
        }
    }
    if let Some(Value::Array(types)) = map.get("type") {
        if types.iter().any(|t| t == "null") {
            let rest: Vec<Value> = types.iter().filter(|t| *t != "null").cloned().collect();
            if rest.len() == 1 {
                map.insert("type".into(), rest[0].clone());
                map.insert("nullable".into(), json!(true));
            }
        }
    }
    // A nullable choice lists null among its values (OpenAPI's rule for `nullable` enums), so
    // validators that read `enum` take a null.
    if map.get("nullable") == Some(&json!(true)) {
        if let Some(Value::Array(values)) = map.get_mut("enum") {
            if !values.contains(&Value::Null) {
                values.push(Value::Null);
            }
        }
    }
    // Integer widths are Rust's business, and defaults the reader's, not the contract's.
    map.remove("format");
    map.remove("default");
    // Doc comments wrap at the source's width; a description is one paragraph per line.
    if let Some(Value::String(text)) = map.get_mut("description") {
        *text = text
            .split("\n\n")
            .map(|paragraph| paragraph.split_whitespace().collect::<Vec<_>>().join(" "))
            .collect::<Vec<_>>()
            .join("\n");
    }
    if let Some(Value::Object(properties)) = map.get_mut("properties") {
        for field in properties.values_mut() {
            foxglove_dialect(field);
        }
    }
    if let Some(items) = map.get_mut("items") {
        foxglove_dialect(items);
    }
}

/// JSON Schema of `sunjitter.FrameAlignment` (`sunjitter_core::record::FrameAlignment`).
pub fn frame_alignment_schema() -> Value {
    schema_of::<FrameAlignment>(FRAME_ALIGNMENT_SCHEMA)
}

/// JSON Schema of `sunjitter.ReferenceChange` ([`ReferenceChange`]).
pub fn reference_change_schema() -> Value {
    schema_of::<ReferenceChange>(REFERENCE_CHANGE_SCHEMA)
}

/// JSON Schema of `sunjitter.Alert` ([`Alert`]).
pub fn alert_schema() -> Value {
    schema_of::<Alert>(ALERT_SCHEMA)
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
    fn frame_alignment_schema_is_the_record_with_a_description_per_field() {
        let record = serde_json::to_value(FrameAlignment::with_every_field()).unwrap();
        let schema = frame_alignment_schema();
        let keys = |v: &Value| {
            let mut k: Vec<String> = v.as_object().unwrap().keys().cloned().collect();
            k.sort();
            k
        };
        assert_eq!(keys(&schema["properties"]), keys(&record));
        for nested in ["header_residual", "solar_rotation"] {
            assert_eq!(
                keys(&schema["properties"][nested]["properties"]),
                keys(&record[nested]),
                "{nested}"
            );
            assert_eq!(schema["properties"][nested]["nullable"], true, "{nested}");
        }
        for (name, field) in schema["properties"].as_object().unwrap() {
            let d = field["description"].as_str().unwrap_or_default();
            assert!(!d.is_empty() && !d.contains('\n'), "{name}: {d:?}");
        }
        // Present in every message, null or not; the checksum only where it was taken.
        let required: Vec<&str> = schema["required"]
            .as_array()
            .unwrap()
            .iter()
            .map(|v| v.as_str().unwrap())
            .collect();
        assert!(required.contains(&"dx_px") && required.contains(&"header_residual"));
        assert!(!required.contains(&"pixel_checksum"));
        assert_eq!(schema["properties"]["dx_px"]["type"], "number");
        assert_eq!(schema["properties"]["dx_px"]["nullable"], true);
        assert_eq!(
            schema["properties"]["status"]["enum"],
            json!(["ok", "degraded", "failed"])
        );
        // A choice that may be null lists null (OpenAPI 3.0's rule for `nullable` enums).
        let model = &schema["properties"]["model"];
        assert_eq!(model["nullable"], true);
        assert!(model["enum"].as_array().unwrap().contains(&Value::Null));
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
