//! `inspect --csv`: one row per frame with every field of the `/jitter` record (RFC 4180).
//!
//! Columns: `log_time_ns`, then the record's fields in the order its type declares them
//! (`FrameAlignment`, the flattened `AlignResult` first; nested objects such as
//! `header_residual` flattened to `header_residual_<field>`), then any field a newer record
//! adds, by name. Empty cells are `null`. Rows are grouped by channel (sorted) and ordered by
//! time.

use super::{ChannelAnalysis, LoggedFrame};
use serde::de::{DeserializeSeed, IgnoredAny, MapAccess, SeqAccess, Visitor};
use serde_json::Value;
use std::io::Write;
use std::sync::LazyLock;
use sunjitter_core::record::FrameAlignment;

/// The record's fields as columns, read from its type.
#[derive(Debug, Clone, PartialEq)]
pub struct RecordFields {
    /// Every field, in the order the type declares them; a nested object's fields as
    /// `<object>_<field>` in its place.
    pub columns: Vec<String>,
    /// The nested objects so flattened (`header_residual`, `solar_rotation`).
    pub nested: Vec<String>,
}

/// The `/jitter` record's fields, from the order a record with every field serialises them in.
pub static RECORD_FIELDS: LazyLock<RecordFields> = LazyLock::new(|| {
    let text = serde_json::to_string(&FrameAlignment::with_every_field())
        .expect("a record serialises to JSON");
    let mut fields = RecordFields {
        columns: Vec::new(),
        nested: Vec::new(),
    };
    let mut de = serde_json::Deserializer::from_str(&text);
    FieldOrder {
        prefix: String::new(),
        fields: &mut fields,
    }
    .deserialize(&mut de)
    .expect("a record's JSON reads back");
    fields
});

/// Walks a JSON text's objects in order, naming their fields (nested ones `parent_child`).
struct FieldOrder<'a> {
    prefix: String,
    fields: &'a mut RecordFields,
}

impl<'de> DeserializeSeed<'de> for FieldOrder<'_> {
    /// Whether the value was an object.
    type Value = bool;

    fn deserialize<D: serde::Deserializer<'de>>(self, d: D) -> Result<bool, D::Error> {
        d.deserialize_any(self)
    }
}

impl<'de> Visitor<'de> for FieldOrder<'_> {
    type Value = bool;

    fn expecting(&self, f: &mut std::fmt::Formatter) -> std::fmt::Result {
        f.write_str("a JSON value")
    }

    fn visit_map<A: MapAccess<'de>>(self, mut map: A) -> Result<bool, A::Error> {
        while let Some(key) = map.next_key::<String>()? {
            let name = if self.prefix.is_empty() {
                key
            } else {
                format!("{}_{key}", self.prefix)
            };
            let object = map.next_value_seed(FieldOrder {
                prefix: name.clone(),
                fields: &mut *self.fields,
            })?;
            if object {
                self.fields.nested.push(name);
            } else {
                self.fields.columns.push(name);
            }
        }
        Ok(true)
    }

    fn visit_seq<A: SeqAccess<'de>>(self, mut seq: A) -> Result<bool, A::Error> {
        while seq.next_element::<IgnoredAny>()?.is_some() {}
        Ok(false)
    }

    fn visit_bool<E>(self, _: bool) -> Result<bool, E> {
        Ok(false)
    }

    fn visit_i64<E>(self, _: i64) -> Result<bool, E> {
        Ok(false)
    }

    fn visit_u64<E>(self, _: u64) -> Result<bool, E> {
        Ok(false)
    }

    fn visit_f64<E>(self, _: f64) -> Result<bool, E> {
        Ok(false)
    }

    fn visit_str<E>(self, _: &str) -> Result<bool, E> {
        Ok(false)
    }

    fn visit_unit<E>(self) -> Result<bool, E> {
        Ok(false)
    }
}

/// A record as flat `name → value` (nested objects become `parent_child`).
fn flatten(prefix: &str, v: &Value, out: &mut Vec<(String, Value)>) {
    match v {
        Value::Object(map) => {
            for (k, child) in map {
                let name = if prefix.is_empty() {
                    k.clone()
                } else {
                    format!("{prefix}_{k}")
                };
                match child {
                    Value::Object(_) => flatten(&name, child, out),
                    // `header_residual: null` still yields its (empty) columns: they are known.
                    _ => out.push((name, child.clone())),
                }
            }
        }
        other => out.push((prefix.to_string(), other.clone())),
    }
}

fn cell(v: &Value) -> String {
    match v {
        Value::Null => String::new(),
        Value::String(s) => quote(s),
        Value::Number(n) => n.to_string(),
        Value::Bool(b) => b.to_string(),
        other => quote(&other.to_string()),
    }
}

fn quote(s: &str) -> String {
    if s.contains([',', '"', '\n', '\r']) {
        format!("\"{}\"", s.replace('"', "\"\""))
    } else {
        s.to_string()
    }
}

/// The time series of every channel as a table: what `--csv` writes, and what other front
/// ends (the Python package) show, so the columns are the same everywhere.
#[derive(Debug, Clone, PartialEq)]
pub struct Table {
    /// `log_time_ns`, then the record's fields ([`RECORD_FIELDS`]), then the fields a newer
    /// record adds, by name.
    pub columns: Vec<String>,
    /// One row per frame, one value per column (`null` where the record has none).
    pub rows: Vec<Vec<Value>>,
}

/// The table of every channel's frames.
pub fn table(analyses: &[ChannelAnalysis]) -> Result<Table, serde_json::Error> {
    let known = &*RECORD_FIELDS;
    let mut rows = Vec::new();
    let mut extra: Vec<String> = Vec::new();
    for a in analyses {
        for f in &a.frames {
            let v = serde_json::to_value(&f.record)?;
            let mut flat = Vec::new();
            flatten("", &v, &mut flat);
            for (k, _) in &flat {
                if !known.columns.contains(k) && !known.nested.contains(k) && !extra.contains(k) {
                    extra.push(k.clone());
                }
            }
            rows.push((f.log_time_ns, flat));
        }
    }
    extra.sort();
    let columns: Vec<String> = std::iter::once("log_time_ns")
        .chain(known.columns.iter().map(String::as_str))
        .chain(extra.iter().map(|s| s.as_str()))
        .map(str::to_string)
        .collect();
    let rows = rows
        .into_iter()
        .map(|(t, flat)| {
            let lookup = |name: &str| flat.iter().find(|(k, _)| k == name).map(|(_, v)| v);
            std::iter::once(Value::from(t))
                .chain(
                    columns[1..]
                        .iter()
                        .map(|name| lookup(name).cloned().unwrap_or(Value::Null)),
                )
                .collect()
        })
        .collect();
    Ok(Table { columns, rows })
}

/// A row of a [`Table`] (named by `columns`) as the frame it was made from: nested objects
/// gathered again (`null` where all their cells are), `log_time_ns` apart.
pub fn frame_from_row(
    columns: &[String],
    row: impl IntoIterator<Item = Value>,
) -> Result<LoggedFrame, String> {
    let mut record = serde_json::Map::new();
    let mut log_time_ns = None;
    for (name, value) in columns.iter().zip(row) {
        if name == "log_time_ns" {
            log_time_ns = value.as_i64();
            continue;
        }
        let nested = RECORD_FIELDS.nested.iter().find_map(|n| {
            name.strip_prefix(n.as_str())
                .and_then(|r| r.strip_prefix('_'))
                .map(|field| (n.as_str(), field))
        });
        match nested {
            Some((object, field)) => {
                let entry = record
                    .entry(object)
                    .or_insert_with(|| Value::Object(Default::default()));
                if let Value::Object(fields) = entry {
                    fields.insert(field.to_string(), value);
                }
            }
            None => {
                record.insert(name.clone(), value);
            }
        }
    }
    for object in &RECORD_FIELDS.nested {
        if let Some(Value::Object(fields)) = record.get(object) {
            if fields.values().all(Value::is_null) {
                record.insert(object.to_string(), Value::Null);
            }
        }
    }
    let log_time_ns = log_time_ns.ok_or("the row has no log_time_ns")?;
    let record = serde_json::from_value(Value::Object(record)).map_err(|e| e.to_string())?;
    Ok(LoggedFrame {
        log_time_ns,
        record,
    })
}

/// Write the time series of every channel.
pub fn write_csv<W: Write>(out: &mut W, analyses: &[ChannelAnalysis]) -> std::io::Result<()> {
    let table = table(analyses).map_err(std::io::Error::other)?;
    writeln!(out, "{}", table.columns.join(","))?;
    for row in &table.rows {
        let cells: Vec<String> = row.iter().map(cell).collect();
        writeln!(out, "{}", cells.join(","))?;
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::super::testdata::frame;
    use super::super::{analyse, InspectOptions};
    use super::*;
    use sunjitter_core::record::{Status, TransformFields};

    #[test]
    fn one_row_per_frame_with_every_field() {
        let mut frames = vec![
            frame("SYNTH_171", 0, 0.0, 0.25, -0.5, Status::Ok),
            frame("SYNTH_171", 1, 12.0, 0.0, 0.0, Status::Failed),
        ];
        frames[0].record.align.message = "few inliers, \"low\" similarity".into();
        frames[0].record.align.header_residual = Some(TransformFields {
            scale: 1.0,
            rotation_arcsec: 0.5,
            dx_px: 0.125,
            dy_px: -0.25,
        });
        let a = analyse(&frames, &InspectOptions::default());
        let mut buf = Vec::new();
        write_csv(&mut buf, &a).unwrap();
        let text = String::from_utf8(buf).unwrap();
        let lines: Vec<&str> = text.lines().collect();
        assert_eq!(lines.len(), 3);
        let header: Vec<&str> = lines[0].split(',').collect();
        assert_eq!(header.len(), 1 + RECORD_FIELDS.columns.len());
        // Every serialised field of the record has a column.
        let v = serde_json::to_value(&frames[0].record).unwrap();
        for k in v.as_object().unwrap().keys() {
            assert!(
                header
                    .iter()
                    .any(|h| h == k || h.starts_with(&format!("{k}_"))),
                "no column for {k}"
            );
        }
        let col = |name: &str| header.iter().position(|h| *h == name).unwrap();
        // The quoted message holds a comma, so compare the leading, unquoted cells only.
        let row0: Vec<&str> = lines[1].split(',').collect();
        assert_eq!(row0[col("dx_px")], "0.25");
        assert_eq!(row0[col("header_residual_dx_px")], "0.125");
        assert_eq!(row0[col("status")], "ok");
        assert!(lines[1].contains("\"few inliers, \"\"low\"\" similarity\""));
        let row1: Vec<&str> = lines[2].split(',').collect();
        assert_eq!(row1[col("status")], "failed");
        assert_eq!(row1[col("dx_px")], "");
        assert_eq!(row1[0], "1714564812000000000");
    }

    /// Each row of the table gives back the record it was made from (nested objects, null
    /// ones included, and the log time).
    #[test]
    fn rows_give_back_their_records() {
        let mut frames = vec![
            frame("SYNTH_171", 0, 0.0, 0.25, -0.5, Status::Ok),
            frame("SYNTH_171", 1, 12.0, 0.0, 0.0, Status::Failed),
            frame("SYNTH_195", 0, 3.0, 1.5, 2.5, Status::Degraded),
        ];
        frames[0].record.align.header_residual = Some(TransformFields {
            scale: 1.0,
            rotation_arcsec: 0.5,
            dx_px: 0.125,
            dy_px: -0.25,
        });
        frames[2].record.pixel_checksum = Some("xxh3_64:0123456789abcdef".into());
        let t = table(&analyse(&frames, &InspectOptions::default())).unwrap();
        assert!(t.columns.iter().any(|c| c == "pixel_checksum"));
        let back: Vec<LoggedFrame> = t
            .rows
            .iter()
            .map(|row| frame_from_row(&t.columns, row.iter().cloned()).unwrap())
            .collect();
        assert_eq!(back, frames);
    }
}
