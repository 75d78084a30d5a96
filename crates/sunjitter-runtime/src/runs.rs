//! What a run of `watch` or `replay` is, so that an output directory holds one run only.
//!
//! A run is its command, its inputs (the watched directory; the files a replay was given) and
//! the configuration that decides its measurements (`[engine]`, `[reference]`, `[channels]`,
//! `[channel_names]`: the policy included). Every segment carries the `sunjitter.run` record
//! (command and inputs) beside the `sunjitter` record (the whole configuration). A run into an
//! `--out` that already holds a log resumes it when the log is of the same run (frames already
//! logged are not measured again) and is refused otherwise, before anything is read or
//! written, with one line saying what differs and what to do. Settings that do not change a
//! measurement (`[sink]`, `[daemon]`, `[alerts]`, `[health]`, `[live]`) may change between the
//! runs of one log.

use crate::config::Config;
use serde_json::Value;
use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};
use sunjitter_core::{Error, Result};
use sunjitter_io::sink::LogContents;

/// Metadata record of every segment of `watch` and `replay`: the command and its inputs.
pub const RUN_METADATA: &str = "sunjitter.run";

/// The configuration sections that decide the measurements.
const MEASUREMENT_SECTIONS: [&str; 4] = ["engine", "reference", "channels", "channel_names"];

/// Who a run is.
#[derive(Debug, Clone, PartialEq)]
pub struct RunIdentity {
    /// `watch` or `replay`.
    pub command: &'static str,
    /// Watch: the watched directory (canonical); replay: `N files`.
    pub inputs: String,
    /// SHA-256 (hex) of the inputs: the watched directory, or replay's sorted file keys.
    pub inputs_digest: String,
    /// Replay: the canonical input files (for logs written before the `sunjitter.run`
    /// record, whose frames are checked against them instead).
    files: BTreeSet<String>,
    /// Watch: the watched directory as frame keys spell it, ending in `/`.
    root: Option<String>,
}

fn sha256_hex(text: &str) -> String {
    use sha2::Digest;
    sha2::Sha256::digest(text.as_bytes())
        .iter()
        .map(|b| format!("{b:02x}"))
        .collect()
}

impl RunIdentity {
    /// `watch DIR` (canonical).
    pub fn watch(dir: &Path) -> RunIdentity {
        let text = sunjitter_core::text::path(dir).into_owned();
        let mut root = text.clone();
        if !root.ends_with('/') {
            root.push('/');
        }
        RunIdentity {
            command: "watch",
            inputs_digest: sha256_hex(&format!("watch\n{text}\n")),
            inputs: text,
            files: BTreeSet::new(),
            root: Some(root),
        }
    }

    /// `replay` of `files` (canonical, as [`crate::ingest::expand_inputs`] gives them).
    pub fn replay(files: &[(PathBuf, bool)]) -> RunIdentity {
        let keys: BTreeSet<String> = files
            .iter()
            .map(|(p, _)| sunjitter_io::fits::frame_key(p, None))
            .collect();
        let mut text = String::from("replay\n");
        for k in &keys {
            text.push_str(k);
            text.push('\n');
        }
        RunIdentity {
            command: "replay",
            inputs: match keys.len() {
                1 => "1 file".to_string(),
                n => format!("{n} files"),
            },
            inputs_digest: sha256_hex(&text),
            files: keys,
            root: None,
        }
    }

    /// The `sunjitter.run` record.
    pub fn metadata(&self) -> BTreeMap<String, String> {
        BTreeMap::from([
            ("command".to_string(), self.command.to_string()),
            ("inputs".to_string(), self.inputs.clone()),
            ("inputs_digest".to_string(), self.inputs_digest.clone()),
        ])
    }

    /// Whether frame `key` (`FILE` or `FILE[N]`) is one of this run's inputs.
    fn takes(&self, key: &str) -> bool {
        let file = sunjitter_io::fits::parse_frame_key(key);
        let file = sunjitter_io::fits::frame_key(&file.path, None);
        match &self.root {
            Some(root) => file.starts_with(root.as_str()),
            None => self.files.contains(&file),
        }
    }
}

/// The measurement sections of a configuration as JSON.
fn measurement(config: &Config) -> BTreeMap<&'static str, Value> {
    let json = config.to_json();
    MEASUREMENT_SECTIONS
        .iter()
        .map(|s| (*s, json.get(*s).cloned().unwrap_or(Value::Null)))
        .collect()
}

/// The first place two JSON values differ: (dotted key, value in `a`, value in `b`).
fn first_difference(at: &str, a: &Value, b: &Value) -> Option<(String, String, String)> {
    if a == b {
        return None;
    }
    if let (Value::Object(x), Value::Object(y)) = (a, b) {
        let keys: BTreeSet<&String> = x.keys().chain(y.keys()).collect();
        for k in keys {
            let (va, vb) = (
                x.get(k).unwrap_or(&Value::Null),
                y.get(k).unwrap_or(&Value::Null),
            );
            if let Some(d) = first_difference(&format!("{at}.{k}"), va, vb) {
                return Some(d);
            }
        }
    }
    let show = |v: &Value| {
        let text = match v {
            Value::Null => "unset".to_string(),
            other => other.to_string(),
        };
        let mut short: String = text.chars().take(60).collect();
        if short.len() < text.len() {
            short.push('…');
        }
        short
    };
    Some((at.to_string(), show(a), show(b)))
}

/// What to do about a log that is not this run's.
const ELSEWHERE: &str =
    "give this run a new --out, or move that directory's segments away to start afresh";

fn refused(out: &Path, why: String) -> Error {
    Error::Refused {
        path: out.to_path_buf(),
        reason: format!("holds another run's log: {why}; {ELSEWHERE}"),
    }
}

/// Check the log already in `out` (`contents`, as read) against this run: `Ok` when there is
/// none or it is this run's (same command, inputs and measuring configuration); otherwise
/// the refusal, one line naming what differs.
pub fn check_resume(
    out: &Path,
    contents: &LogContents,
    identity: &RunIdentity,
    config: &Config,
) -> Result<()> {
    if contents.segments.is_empty() {
        return Ok(());
    }
    let name_of = |i: usize| {
        contents
            .segments
            .get(i)
            .map(|s| {
                s.path
                    .file_name()
                    .map(|n| n.to_string_lossy().into_owned())
                    .unwrap_or_default()
            })
            .unwrap_or_default()
    };
    if let Some(m) = contents
        .metadata
        .iter()
        .find(|m| m.name == crate::shard::SHARD_METADATA)
    {
        let spec = m.metadata.get("shard").map_or("?", String::as_str);
        return Err(Error::Refused {
            path: out.to_path_buf(),
            reason: format!(
                "holds shard {spec}'s log (replay --shard {spec}; {}): run that shard with --shard {spec}, or give this run a new --out",
                name_of(m.segment)
            ),
        });
    }
    if let Some(m) = contents
        .metadata
        .iter()
        .find(|m| m.name == crate::merge::MERGE_METADATA)
    {
        return Err(Error::Refused {
            path: out.to_path_buf(),
            reason: format!(
                "holds a merged log (sunjitter merge; {}): a merge is run again with merge; give this run a new --out",
                name_of(m.segment)
            ),
        });
    }
    let ours = measurement(config);
    for m in contents
        .metadata
        .iter()
        .filter(|m| m.name == sunjitter_io::sink::METADATA_NAME)
    {
        let Some(json) = m.metadata.get("config") else {
            return Err(refused(
                out,
                format!("{} has no configuration record", name_of(m.segment)),
            ));
        };
        // Read as this version reads a configuration, so keys added since take their defaults.
        let theirs: Config = serde_json::from_str(json).map_err(|e| {
            refused(
                out,
                format!(
                    "{} was written by another version of sunjitter, whose configuration this one cannot read ({e})",
                    name_of(m.segment)
                ),
            )
        })?;
        let theirs = measurement(&theirs);
        for section in MEASUREMENT_SECTIONS {
            if let Some((key, there, here)) =
                first_difference(section, &theirs[section], &ours[section])
            {
                return Err(refused(
                    out,
                    format!("it was measured with {key} = {there}, this run has {here}"),
                ));
            }
        }
    }
    let mut described = false;
    for m in contents.metadata.iter().filter(|m| m.name == RUN_METADATA) {
        described = true;
        let get = |k: &str| m.metadata.get(k).map_or("?", String::as_str);
        if get("command") != identity.command {
            return Err(refused(
                out,
                format!(
                    "it is a {} of {}, this is a {} of {}",
                    get("command"),
                    get("inputs"),
                    identity.command,
                    identity.inputs
                ),
            ));
        }
        if get("inputs_digest") != identity.inputs_digest {
            return Err(refused(
                out,
                format!(
                    "it is a {} of other inputs ({} there, {} here)",
                    identity.command,
                    get("inputs"),
                    identity.inputs
                ),
            ));
        }
    }
    // A log without the record (an older version's): its frames must be this run's inputs.
    if !described {
        let foreign = contents
            .jitter
            .iter()
            .map(|m| m.record.align.frame.as_str())
            .chain(
                contents
                    .logs
                    .iter()
                    .map(|m| m.entry.file.as_str())
                    .filter(|f| !f.is_empty() && f.starts_with('/')),
            )
            .find(|key| !identity.takes(key));
        if let Some(key) = foreign {
            return Err(refused(
                out,
                format!(
                    "it logged {}, which is not an input of this {}",
                    sunjitter_core::text::escape(key),
                    identity.command
                ),
            ));
        }
    }
    Ok(())
}

/// The output directory of a run, locked and ready: the sink (holding the lock), what earlier
/// runs of this run logged there, and how many frames that is.
pub struct OpenedOutput {
    pub sink: sunjitter_io::sink::McapSink,
    pub history: crate::reference::History,
    /// `/jitter` messages already in the log.
    pub earlier_frames: u64,
}

/// Open the MCAP output in `out` for `identity`: lock it first (nothing is recovered or
/// written while another process holds it), refuse a log of another run ([`check_resume`]),
/// then rewrite unfinished segments (a crash) as finished files so every MCAP reader opens
/// them; what they held counts as logged. Every segment the sink starts records the run.
pub fn open_run(out: &Path, config: &Config, identity: &RunIdentity) -> Result<OpenedOutput> {
    let lock = sunjitter_io::outputs::OutputLock::acquire(out)?;
    let contents = sunjitter_io::sink::read_logs(&[out.to_path_buf()])?;
    check_resume(out, &contents, identity, config)?;
    let history = crate::pipeline::history_of(&contents);
    let sink =
        sunjitter_io::sink::McapSink::new(out, config.sink.clone(), config.to_json().to_string())?
            .with_segment_metadata(RUN_METADATA, identity.metadata())
            .holding(lock);
    Ok(OpenedOutput {
        sink,
        history,
        earlier_frames: contents.jitter.len() as u64,
    })
}

/// Refuse (exit 2) an `--out` that would put the log among the inputs: inside one of
/// `trees` (the watched directory; replay's directory arguments, whole when `recursive`,
/// else only the directory itself), or a directory that holds one of `files`. Compared by
/// identity, so links and other spellings count.
pub fn check_out_dir(
    out: &Path,
    trees: &[(&Path, &str)],
    recursive: bool,
    files: &[PathBuf],
) -> Result<()> {
    use sunjitter_io::outputs::{file_id, is_within};
    let refuse = |reason: String| {
        Err(Error::Refused {
            path: out.to_path_buf(),
            reason,
        })
    };
    let out_id = file_id(out);
    for (tree, what) in trees {
        let Some(id) = file_id(tree) else { continue };
        let inside = if recursive {
            is_within(out, id)
        } else {
            out_id == Some(id)
        };
        if inside {
            return refuse(format!(
                "is inside {what} {}: the log is never written among the inputs; choose another --out",
                sunjitter_core::text::path(tree)
            ));
        }
    }
    if let Some(out_id) = out_id {
        if let Some(f) = files
            .iter()
            .find(|f| f.parent().and_then(file_id) == Some(out_id))
        {
            return refuse(format!(
                "holds the input {}: the log is never written among the inputs; choose another --out",
                sunjitter_core::text::path(f)
            ));
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn differences_are_named_by_their_key() {
        let a = serde_json::json!({"policy": "keyframe", "hold_s": 1.0});
        let b = serde_json::json!({"policy": "previous", "hold_s": 1.0});
        let (key, x, y) = first_difference("reference", &a, &b).unwrap();
        assert_eq!(key, "reference.policy");
        assert_eq!((x.as_str(), y.as_str()), ("\"keyframe\"", "\"previous\""));
        let c = serde_json::json!({"X": {"tolerance_s": 2.0}});
        let (key, x, y) = first_difference("channels", &c, &serde_json::json!({})).unwrap();
        assert_eq!(
            (key.as_str(), x.as_str(), y.as_str()),
            ("channels.X", "{\"tolerance_s\":2.0}", "unset")
        );
        assert!(first_difference("engine", &a, &a).is_none());
    }

    #[test]
    fn replay_identity_is_the_set_of_files_in_any_order() {
        let f = |names: &[&str]| -> Vec<(PathBuf, bool)> {
            names.iter().map(|n| (PathBuf::from(n), true)).collect()
        };
        let a = RunIdentity::replay(&f(&["/d/a.fits", "/d/b.fits"]));
        let b = RunIdentity::replay(&f(&["/d/b.fits", "/d/a.fits"]));
        let c = RunIdentity::replay(&f(&["/d/a.fits", "/d/c.fits"]));
        assert_eq!(a.inputs_digest, b.inputs_digest);
        assert_ne!(a.inputs_digest, c.inputs_digest);
        assert!(a.takes("/d/a.fits[3]") && !a.takes("/d/c.fits"));
        let w = RunIdentity::watch(Path::new("/data/in"));
        assert!(w.takes("/data/in/x/y.fits") && !w.takes("/data/inbox/y.fits"));
    }
}
