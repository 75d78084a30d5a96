//! Reading logs back: finished segments and unfinished ones (a crash leaves no summary and
//! maybe a truncated record at the end), read linearly up to the last complete record.

use super::schemas::{
    Alert, LogEntry, LogLevel, ReferenceChange, ALERT_SCHEMA, FRAME_ALIGNMENT_SCHEMA, LOG_SCHEMA,
    MESSAGE_ENCODING, REFERENCE_CHANGE_SCHEMA,
};
use crate::fits::FrameSpec;
use mcap::records::{op, Channel, MessageHeader, Metadata, Record};
use std::collections::{BTreeMap, HashSet};
use std::fs::File;
use std::path::{Path, PathBuf};
use sunjitter_core::record::FrameAlignment;
use sunjitter_core::{Error, Result};

/// One `/jitter/<channel>` message.
#[derive(Debug, Clone, PartialEq)]
pub struct JitterMessage {
    /// Index into [`LogContents::segments`].
    pub segment: usize,
    pub topic: String,
    pub log_time_ns: u64,
    pub publish_time_ns: u64,
    pub record: FrameAlignment,
}

/// One `/reference/<channel>` message.
#[derive(Debug, Clone, PartialEq)]
pub struct ReferenceMessage {
    pub segment: usize,
    pub topic: String,
    pub log_time_ns: u64,
    pub publish_time_ns: u64,
    pub change: ReferenceChange,
}

/// One `/log` message.
#[derive(Debug, Clone, PartialEq)]
pub struct LogMessage {
    pub segment: usize,
    pub log_time_ns: u64,
    pub publish_time_ns: u64,
    pub entry: LogEntry,
}

/// One `/alert` message.
#[derive(Debug, Clone, PartialEq)]
pub struct AlertMessage {
    pub segment: usize,
    pub log_time_ns: u64,
    pub publish_time_ns: u64,
    pub alert: Alert,
}

/// One metadata record (sunjitter writes `sunjitter` with `version` and `config`).
#[derive(Debug, Clone, PartialEq)]
pub struct MetadataRecord {
    pub segment: usize,
    pub name: String,
    pub metadata: BTreeMap<String, String>,
}

/// What was read from one file.
#[derive(Debug, Clone, PartialEq)]
pub struct SegmentReport {
    pub path: PathBuf,
    pub file_len: u64,
    /// Bytes up to the end of the last complete record read.
    pub readable_len: u64,
    /// Data section, summary and footer all present (a cleanly finished segment).
    pub complete: bool,
    /// Messages decoded from this file.
    pub messages: usize,
    /// Messages not decoded (unknown schema, or not valid for their schema).
    pub skipped: usize,
    /// Human-readable notes, e.g. on an unfinished segment and what was recovered.
    pub notes: Vec<String>,
}

/// The typed contents of one or more segments, in file order then write order.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct LogContents {
    pub jitter: Vec<JitterMessage>,
    pub references: Vec<ReferenceMessage>,
    pub logs: Vec<LogMessage>,
    pub alerts: Vec<AlertMessage>,
    pub metadata: Vec<MetadataRecord>,
    pub segments: Vec<SegmentReport>,
}

impl LogContents {
    /// Frames already accounted for in the log: every `/jitter` message's `frame`, and the
    /// `file` of every `/log` entry at level ERROR or above (a frame that failed for good).
    /// Warnings (degraded, retrying) do not count. `FILE[N]` is frame N of a cube.
    pub fn logged_frames(&self) -> HashSet<FrameSpec> {
        let jitter = self.jitter.iter().map(|m| m.record.align.frame.as_str());
        let failed = self
            .logs
            .iter()
            .filter(|m| m.entry.level >= LogLevel::Error && !m.entry.file.is_empty())
            .map(|m| m.entry.file.as_str());
        jitter.chain(failed).map(parse_frame_id).collect()
    }

    /// Notes of every segment, prefixed with its path.
    pub fn notes(&self) -> Vec<String> {
        self.segments
            .iter()
            .flat_map(|s| {
                s.notes
                    .iter()
                    .map(move |n| format!("{}: {n}", s.path.display()))
            })
            .collect()
    }
}

/// `FILE[N]` → frame N of FILE; anything else is a plain file.
fn parse_frame_id(id: &str) -> FrameSpec {
    if let Some(inner) = id.strip_suffix(']') {
        if let Some((path, index)) = inner.rsplit_once('[') {
            if let Ok(n) = index.parse::<usize>() {
                return FrameSpec {
                    path: PathBuf::from(path),
                    frame: Some(n),
                };
            }
        }
    }
    FrameSpec {
        path: PathBuf::from(id),
        frame: None,
    }
}

/// Frames already logged in the segments under `paths` (see [`LogContents::logged_frames`]),
/// for a restarted daemon. An output directory without segments gives an empty set.
pub fn logged_frames(paths: &[PathBuf]) -> Result<HashSet<FrameSpec>> {
    Ok(read_logs(paths)?.logged_frames())
}

/// Reads files and directories (every `*.mcap` in a directory, not recursive) as one series:
/// files sorted by name (segment names sort in time order), messages in write order.
/// Unfinished segments are read up to their last complete record; see the segment notes.
pub fn read_logs(paths: &[PathBuf]) -> Result<LogContents> {
    let mut contents = LogContents::default();
    for path in segment_files(paths)? {
        let bytes = read_segment_bytes(&path)?;
        let raw = parse_segment(&path, &bytes)?;
        decode_segment(raw, &mut contents);
    }
    Ok(contents)
}

/// A segment's bytes; only a regular file is read (a FIFO or a device would block or never
/// end).
fn read_segment_bytes(path: &Path) -> Result<Vec<u8>> {
    use std::io::Read;
    let mut file = crate::input::open_regular(path).map_err(|e| match e.kind() {
        std::io::ErrorKind::InvalidInput => Error::bad_input(path, e.to_string()),
        _ => Error::io(path, e),
    })?;
    let mut bytes = Vec::new();
    file.read_to_end(&mut bytes)
        .map_err(|e| Error::io(path, e))?;
    Ok(bytes)
}

fn segment_files(paths: &[PathBuf]) -> Result<Vec<PathBuf>> {
    let mut files = Vec::new();
    for path in paths {
        let meta = std::fs::metadata(path).map_err(|e| Error::io(path, e))?;
        if meta.is_dir() {
            let entries = std::fs::read_dir(path).map_err(|e| Error::io(path, e))?;
            for entry in entries {
                let entry = entry.map_err(|e| Error::io(path, e))?;
                let p = entry.path();
                if p.extension().is_some_and(|e| e == "mcap") && p.is_file() {
                    files.push(p);
                }
            }
        } else {
            files.push(path.clone());
        }
    }
    files.sort_by(|a, b| a.file_name().cmp(&b.file_name()).then_with(|| a.cmp(b)));
    files.dedup();
    Ok(files)
}

/// The records of one file that survived, before decoding.
struct RawSegment {
    report: SegmentReport,
    schemas: BTreeMap<u16, (String, String, Vec<u8>)>,
    channels: BTreeMap<u16, Channel>,
    metadata: Vec<Metadata>,
    messages: Vec<(MessageHeader, Vec<u8>)>,
}

/// Walks the records of one file; stops cleanly at the first incomplete or unreadable one.
/// A chunk is taken whole or not at all (its CRC is checked), so no partial message leaks out.
fn parse_segment(path: &Path, bytes: &[u8]) -> Result<RawSegment> {
    let mut raw = RawSegment {
        report: SegmentReport {
            path: path.to_path_buf(),
            file_len: bytes.len() as u64,
            readable_len: 0,
            complete: false,
            messages: 0,
            skipped: 0,
            notes: Vec::new(),
        },
        schemas: BTreeMap::new(),
        channels: BTreeMap::new(),
        metadata: Vec::new(),
        messages: Vec::new(),
    };
    let magic = mcap::MAGIC;
    if bytes.len() < magic.len() && magic.starts_with(bytes) {
        raw.report.notes.push(format!(
            "empty segment ({} bytes): the writer stopped before its header",
            bytes.len()
        ));
        return Ok(raw);
    }
    if !bytes.starts_with(magic) {
        return Err(Error::bad_input(path, "not an MCAP file (bad magic bytes)"));
    }
    let mut pos = magic.len();
    let mut data_end: Option<usize> = None;
    let mut stopped: Option<String> = None;
    while pos < bytes.len() {
        let rest = &bytes[pos..];
        if rest.len() < 9 {
            stopped = Some(format!("truncated record header at byte {pos}"));
            break;
        }
        let opcode = rest[0];
        let mut len_bytes = [0u8; 8];
        len_bytes.copy_from_slice(&rest[1..9]);
        let len = u64::from_le_bytes(len_bytes);
        if len > (rest.len() - 9) as u64 {
            stopped = Some(format!(
                "truncated record (opcode 0x{opcode:02x}) at byte {pos}: {len} bytes announced, {} present",
                rest.len() - 9
            ));
            break;
        }
        let next = pos + 9 + len as usize;
        let body = &rest[9..9 + len as usize];
        match opcode {
            op::CHUNK => match chunk_records(&bytes[pos..next]) {
                Ok(records) => {
                    for r in records {
                        take_record(&mut raw, r);
                    }
                }
                // The framing around it is sound (its length fits): skip just this chunk.
                Err(e) => raw.report.notes.push(format!(
                    "damaged chunk at byte {pos} ({len} bytes) skipped with its messages: {e}"
                )),
            },
            op::SCHEMA | op::CHANNEL | op::MESSAGE | op::METADATA => {
                match mcap::parse_record(opcode, body) {
                    Ok(record) => take_record(&mut raw, record),
                    Err(e) => {
                        stopped = Some(format!(
                            "unreadable record (opcode 0x{opcode:02x}) at byte {pos}: {e}"
                        ));
                        break;
                    }
                }
            }
            op::DATA_END => {
                data_end = Some(next);
                raw.report.readable_len = next as u64;
                break;
            }
            op::FOOTER => break,
            // Header, indexes, statistics, attachments, unknown records: not needed for the
            // series, and not parsed (less parsing of possibly damaged bytes).
            _ => {}
        }
        pos = next;
        raw.report.readable_len = pos as u64;
    }
    raw.report.complete = data_end.is_some_and(|end| has_summary_and_footer(bytes, end));
    if !raw.report.complete {
        let n = raw.messages.len();
        let (read, total) = (raw.report.readable_len, raw.report.file_len);
        let what = match &stopped {
            Some(why) => format!("; stopped at a {why}"),
            None if data_end.is_some() => "; summary or footer missing or damaged".to_string(),
            None => "; ends at a record boundary".to_string(),
        };
        raw.report.notes.push(format!(
            "unfinished segment (no summary/footer): recovered {n} messages from the first \
             {read} of {total} bytes{what}"
        ));
    }
    Ok(raw)
}

/// A footer record right before the end magic, pointing at a summary section that starts
/// after the data section (which ends at `data_end`).
fn has_summary_and_footer(bytes: &[u8], data_end: usize) -> bool {
    const FOOTER_LEN: usize = 1 + 8 + 20;
    let magic = mcap::MAGIC;
    let n = bytes.len();
    if n < data_end + FOOTER_LEN + magic.len() || !bytes.ends_with(magic) {
        return false;
    }
    let footer = &bytes[n - magic.len() - FOOTER_LEN..n - magic.len()];
    let u64_at = |i: usize| {
        let mut b = [0u8; 8];
        b.copy_from_slice(&footer[i..i + 8]);
        u64::from_le_bytes(b)
    };
    let summary_start = u64_at(9);
    footer[0] == op::FOOTER
        && u64_at(1) == 20
        && summary_start >= data_end as u64
        && summary_start < (n - magic.len() - FOOTER_LEN) as u64
}

/// Largest decompressed chunk accepted (a damaged size field must not exhaust memory).
const CHUNK_LIMIT: usize = 1 << 30;

/// The schema, channel and message records of one chunk record (`opcode..end`), or an error
/// if any part of it is unreadable: its CRC is checked before any record is taken.
fn chunk_records(record: &[u8]) -> mcap::McapResult<Vec<Record<'static>>> {
    let options = mcap::sans_io::LinearReaderOptions::default()
        .with_skip_start_magic(true)
        .with_skip_end_magic(true)
        .with_emit_chunks(false)
        .with_prevalidate_chunk_crcs(true)
        .with_record_length_limit(CHUNK_LIMIT);
    let mut reader = mcap::sans_io::LinearReader::new_with_options(options);
    let mut input = record;
    let mut out = Vec::new();
    while let Some(event) = reader.next_event() {
        match event? {
            mcap::sans_io::LinearReadEvent::ReadRequest(n) => {
                let k = n.min(input.len());
                reader.insert(k).copy_from_slice(&input[..k]);
                reader.notify_read(k);
                input = &input[k..];
            }
            mcap::sans_io::LinearReadEvent::Record { opcode, data } => {
                if matches!(opcode, op::SCHEMA | op::CHANNEL | op::MESSAGE) {
                    out.push(mcap::parse_record(opcode, data)?.into_owned());
                }
            }
        }
    }
    Ok(out)
}

fn take_record(raw: &mut RawSegment, record: Record<'_>) {
    match record {
        Record::Schema { header, data } => {
            raw.schemas
                .insert(header.id, (header.name, header.encoding, data.into_owned()));
        }
        Record::Channel(channel) => {
            raw.channels.insert(channel.id, channel);
        }
        Record::Message { header, data } => raw.messages.push((header, data.into_owned())),
        Record::Metadata(m) => raw.metadata.push(m),
        // Indexes, statistics, attachments, unknown records: not needed to read the series.
        _ => {}
    }
}

fn decode_segment(raw: RawSegment, contents: &mut LogContents) {
    let segment = contents.segments.len();
    let mut report = raw.report;
    for m in raw.metadata {
        contents.metadata.push(MetadataRecord {
            segment,
            name: m.name,
            metadata: m.metadata,
        });
    }
    let mut first_error: Option<String> = None;
    for (header, data) in &raw.messages {
        let channel = raw.channels.get(&header.channel_id);
        let schema = channel.and_then(|c| raw.schemas.get(&c.schema_id));
        let (Some(channel), Some((schema_name, _, _))) = (channel, schema) else {
            report.skipped += 1;
            first_error.get_or_insert_with(|| {
                format!("message on unknown channel id {}", header.channel_id)
            });
            continue;
        };
        if channel.message_encoding != MESSAGE_ENCODING {
            report.skipped += 1;
            first_error.get_or_insert_with(|| {
                format!(
                    "{}: message encoding {:?}",
                    channel.topic, channel.message_encoding
                )
            });
            continue;
        }
        let (log_time_ns, publish_time_ns) = (header.log_time, header.publish_time);
        let decoded = match schema_name.as_str() {
            FRAME_ALIGNMENT_SCHEMA => serde_json::from_slice(data).map(|record| {
                contents.jitter.push(JitterMessage {
                    segment,
                    topic: channel.topic.clone(),
                    log_time_ns,
                    publish_time_ns,
                    record,
                })
            }),
            REFERENCE_CHANGE_SCHEMA => serde_json::from_slice(data).map(|change| {
                contents.references.push(ReferenceMessage {
                    segment,
                    topic: channel.topic.clone(),
                    log_time_ns,
                    publish_time_ns,
                    change,
                })
            }),
            LOG_SCHEMA => serde_json::from_slice(data).map(|entry| {
                contents.logs.push(LogMessage {
                    segment,
                    log_time_ns,
                    publish_time_ns,
                    entry,
                })
            }),
            ALERT_SCHEMA => serde_json::from_slice(data).map(|alert| {
                contents.alerts.push(AlertMessage {
                    segment,
                    log_time_ns,
                    publish_time_ns,
                    alert,
                })
            }),
            other => {
                report.skipped += 1;
                first_error.get_or_insert_with(|| format!("{}: schema {other:?}", channel.topic));
                continue;
            }
        };
        match decoded {
            Ok(()) => report.messages += 1,
            Err(e) => {
                report.skipped += 1;
                first_error.get_or_insert_with(|| format!("{}: {e}", channel.topic));
            }
        }
    }
    if let Some(first) = first_error {
        report.notes.push(format!(
            "{} messages not decoded (first: {first})",
            report.skipped
        ));
    }
    contents.segments.push(report);
}

/// What [`recover_segment`] did.
#[derive(Debug, Clone, PartialEq)]
pub enum RecoveryOutcome {
    /// The segment was finished cleanly; left untouched.
    AlreadyComplete,
    /// Rewritten as a finished segment with every message that could be read.
    Recovered {
        messages: usize,
        /// Bytes of the old file that could not be used (the truncated tail).
        dropped_bytes: u64,
    },
    /// Unfinished and without a single message (killed between creating it and its first
    /// flush): removed, rather than rewritten as an empty file readers would have to skip.
    RemovedEmpty,
}

/// Turns an unfinished segment (a crash) into a finished one that every MCAP reader opens:
/// its readable records are rewritten with summary and indexes to `<name>.recovering`, which
/// then replaces the segment atomically (rename). A crash during recovery leaves the original.
pub fn recover_segment(path: &Path) -> Result<RecoveryOutcome> {
    recover_segment_with(path, true)
}

/// [`recover_segment`], with `fsync` of the new file and its directory only if `sync`.
pub(super) fn recover_segment_with(path: &Path, sync: bool) -> Result<RecoveryOutcome> {
    let bytes = read_segment_bytes(path)?;
    let raw = parse_segment(path, &bytes)?;
    if raw.report.complete {
        return Ok(RecoveryOutcome::AlreadyComplete);
    }
    if raw.messages.is_empty() {
        std::fs::remove_file(path)
            .map_err(|e| Error::output(path, format!("cannot remove empty segment: {e}")))?;
        return Ok(RecoveryOutcome::RemovedEmpty);
    }
    let mut tmp_name = path.as_os_str().to_os_string();
    tmp_name.push(".recovering");
    let tmp = PathBuf::from(tmp_name);
    let fail = |e: &dyn std::fmt::Display| Error::output(path, format!("recovery failed: {e}"));
    let file = File::create(&tmp).map_err(|e| fail(&e))?;
    let written = (|| -> mcap::McapResult<File> {
        let options = mcap::WriteOptions::new()
            .compression(Some(mcap::Compression::Zstd))
            .compression_threads(0)
            .library(format!(
                "sunjitter {} (recovered)",
                env!("CARGO_PKG_VERSION")
            ));
        let mut writer = options.create(std::io::BufWriter::new(file))?;
        for m in &raw.metadata {
            writer.write_metadata(m)?;
        }
        for (id, (name, encoding, data)) in &raw.schemas {
            writer.add_schema_with_id(*id, name, encoding, data)?;
        }
        for (id, c) in &raw.channels {
            let schema_id = if raw.schemas.contains_key(&c.schema_id) {
                c.schema_id
            } else {
                0
            };
            writer.add_channel_with_id(
                *id,
                schema_id,
                &c.topic,
                &c.message_encoding,
                &c.metadata,
            )?;
        }
        for (header, data) in &raw.messages {
            if raw.channels.contains_key(&header.channel_id) {
                writer.write_to_known_channel(header, data)?;
            }
        }
        writer.finish()?;
        let file = writer
            .into_inner()
            .into_inner()
            .map_err(|e| e.into_error())?;
        if sync {
            file.sync_all()?;
        }
        Ok(file)
    })();
    if let Err(e) = written {
        let _ = std::fs::remove_file(&tmp);
        return Err(fail(&e));
    }
    std::fs::rename(&tmp, path).map_err(|e| fail(&e))?;
    if let Some(dir) = path.parent().filter(|d| sync && !d.as_os_str().is_empty()) {
        // Make the rename itself durable where the platform allows it.
        if let Ok(d) = File::open(dir) {
            let _ = d.sync_all();
        }
    }
    Ok(RecoveryOutcome::Recovered {
        messages: raw.messages.len(),
        dropped_bytes: raw.report.file_len - raw.report.readable_len,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Found by the crash test: a daemon killed right after creating a segment left one with
    /// only its header and metadata, "recovered" into a file with no chunks at all.
    #[test]
    fn unfinished_segments_without_messages_are_removed() {
        let dir = tempfile::tempdir().unwrap();
        let empty = dir.path().join("sunjitter-20260101T000000Z-0000.mcap");
        std::fs::write(&empty, b"").unwrap();
        let header_only = dir.path().join("sunjitter-20260101T000000Z-0001.mcap");
        {
            let file = std::fs::File::create(&header_only).unwrap();
            let mut w = mcap::WriteOptions::new()
                .create(std::io::BufWriter::new(file))
                .unwrap();
            w.write_metadata(&mcap::records::Metadata {
                name: "sunjitter".into(),
                metadata: BTreeMap::from([("version".to_string(), "0".to_string())]),
            })
            .unwrap();
            w.flush().unwrap();
            std::mem::forget(w); // killed: no summary, no footer
        }
        for path in [&empty, &header_only] {
            assert_eq!(
                recover_segment(path).unwrap(),
                RecoveryOutcome::RemovedEmpty
            );
            assert!(!path.exists());
        }
    }

    /// `/reference` messages written when the cube index was named `frame` still read (a
    /// restart on such a log continues it).
    #[test]
    fn reference_changes_with_the_cube_index_named_frame_read() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("sunjitter-20260101T000000Z-0000.mcap");
        let old = br#"{"channel":"SJI_1400","file":"/d/sji.fits","frame":7,"obs_time":"2014-03-29T14:09:38Z","reason":"first frame","reference_kind":"keyframe","sequence":0,"replaces":null}"#;
        {
            let file = std::fs::File::create(&path).unwrap();
            let mut w = mcap::WriteOptions::new()
                .create(std::io::BufWriter::new(file))
                .unwrap();
            let schema = w
                .add_schema(REFERENCE_CHANGE_SCHEMA, "jsonschema", b"{}")
                .unwrap();
            let channel = w
                .add_channel(
                    schema,
                    "/reference/SJI_1400",
                    MESSAGE_ENCODING,
                    &BTreeMap::new(),
                )
                .unwrap();
            let header = MessageHeader {
                channel_id: channel,
                sequence: 0,
                log_time: 1,
                publish_time: 1,
            };
            w.write_to_known_channel(&header, old).unwrap();
            w.finish().unwrap();
        }
        let contents = read_logs(&[dir.path().to_path_buf()]).unwrap();
        assert_eq!(contents.references.len(), 1);
        assert_eq!(contents.references[0].change.cube_frame, Some(7));
        // Written again, it carries the new name only.
        let again = serde_json::to_value(&contents.references[0].change).unwrap();
        assert_eq!(again["cube_frame"], 7);
        assert!(again.get("frame").is_none());
    }

    #[test]
    fn frame_ids_parse_cube_indexes() {
        let cube = parse_frame_id("data/sji.fits[12]");
        assert_eq!(cube.path, PathBuf::from("data/sji.fits"));
        assert_eq!(cube.frame, Some(12));
        let plain = parse_frame_id("data/a[b].fits");
        assert_eq!(plain.path, PathBuf::from("data/a[b].fits"));
        assert_eq!(plain.frame, None);
        assert_eq!(parse_frame_id("x.fits[]").frame, None);
        assert_eq!(parse_frame_id("x.fits[-1]").frame, None);
    }
}
