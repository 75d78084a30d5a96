//! `sunjitter merge`: the logs of the N shards of one run ([`crate::shard`]) joined into one
//! log, every frame once, the chained series stitched across shard boundaries.
//!
//! A shard's chains start inside its overlap, so its chained values are relative to a frame
//! another shard owns. The link is that frame's chained value in the merged series (the
//! shard's own value there is the identity, σ 0): each of the shard's chained values `C` is
//! replaced by `C ∘ L`, σ propagated to first order as in [`crate::reference`]. Where the
//! start frame has no chained value, a later frame the shard measured and another shard
//! owns gives the link, `L = C_g⁻¹ ∘ M_g`. Chains that start on a frame the shard owns, and
//! `fixed:` references, need no link. `channel:` followers take the link of the channel at
//! the root of their partners. Sequence numbers are renumbered per channel in time order,
//! and a `/reference` message repeating the channel's current reference is dropped.
//!
//! Reading and checking the shards ([`read_shard`], [`check_set`]) and writing ([`write`](fn@write))
//! do the I/O; [`merge`] is pure.

use crate::config::Config;
use crate::reference::{PolicySpec, ReferencePolicies};
use crate::shard::{ChainStart, ShardDone, ShardSpec, SHARD_DONE_METADATA, SHARD_METADATA};
use std::collections::{BTreeMap, HashMap};
use std::path::{Path, PathBuf};
use sunjitter_core::chain::{chain_from_message, set_chain, Chain};
use sunjitter_core::geometry::{compose_with_covariance, Similarity, ARCSEC_PER_RAD};
use sunjitter_core::record::FrameAlignment;
use sunjitter_core::{Error, Result};
use sunjitter_io::sink::{LogContents, LogEntry, ReferenceChange};

/// Metadata record of a merged log: the shards it was made from.
pub const MERGE_METADATA: &str = "sunjitter.merge";

/// One shard's output, read and checked on its own.
#[derive(Debug, Clone)]
pub struct ShardLog {
    pub path: PathBuf,
    pub spec: ShardSpec,
    pub inputs_digest: String,
    pub config_digest: String,
    pub total: usize,
    pub start: usize,
    pub end: usize,
    pub done: ShardDone,
    pub config: Config,
    pub config_json: String,
    pub contents: LogContents,
}

fn refused(path: &Path, reason: impl Into<String>) -> Error {
    Error::Refused {
        path: path.to_path_buf(),
        reason: reason.into(),
    }
}

/// Read one shard's output directory and check that it is a finished shard.
pub fn read_shard(path: &Path) -> Result<ShardLog> {
    if !path.is_dir() {
        return Err(refused(path, "not a directory of a shard's log"));
    }
    let contents = sunjitter_io::sink::read_logs(&[path.to_path_buf()])
        .map_err(|e| refused(path, format!("unreadable: {e}")))?;
    if contents.segments.is_empty() {
        return Err(refused(path, "holds no log segment (shard not run?)"));
    }
    let shard = contents
        .metadata
        .iter()
        .find(|m| m.name == SHARD_METADATA)
        .ok_or_else(|| {
            refused(
                path,
                "not a shard's log (no `sunjitter.shard` metadata: made without --shard?)",
            )
        })?;
    let m = &shard.metadata;
    let get = |k: &str| {
        m.get(k)
            .cloned()
            .ok_or_else(|| refused(path, format!("shard metadata without `{k}`")))
    };
    let number = |k: &str| -> Result<usize> {
        get(k)?
            .parse()
            .map_err(|_| refused(path, format!("shard metadata `{k}` is not a number")))
    };
    let spec: ShardSpec = get("shard")?
        .parse()
        .map_err(|_| refused(path, "shard metadata `shard` is not K/N"))?;
    for other in contents
        .metadata
        .iter()
        .filter(|o| o.name == SHARD_METADATA)
    {
        if other.metadata != *m {
            return Err(refused(
                path,
                "segments of different shards or runs in one directory",
            ));
        }
    }
    if let Some(s) = contents.segments.iter().find(|s| !s.complete) {
        return Err(refused(
            path,
            format!(
                "shard {spec} is unfinished ({} has no summary): run it again",
                sunjitter_core::text::path(&s.path)
            ),
        ));
    }
    let done = contents
        .metadata
        .iter()
        .find(|m| m.name == SHARD_DONE_METADATA)
        .ok_or_else(|| refused(path, format!("shard {spec} did not finish: run it again")))?;
    let done = ShardDone::from_metadata(&done.metadata)
        .map_err(|e| refused(path, format!("shard {spec}: completion record: {e}")))?;
    if done.messages != contents.jitter.len() as u64 {
        // Fewer (or more) messages than it logged: a segment damaged since.
        let damaged = contents
            .segments
            .iter()
            .find(|s| s.skipped > 0 || !s.notes.is_empty());
        let why = match damaged {
            Some(s) => format!(
                "{} is damaged ({}); {} of the {} frame messages the shard logged are readable",
                sunjitter_core::text::path(&s.path),
                s.notes
                    .first()
                    .cloned()
                    .unwrap_or_else(|| format!("{} messages unreadable", s.skipped)),
                contents.jitter.len(),
                done.messages
            ),
            None => format!(
                "holds {} frame messages where it logged {} (a segment missing or added)",
                contents.jitter.len(),
                done.messages
            ),
        };
        return Err(refused(path, format!("shard {spec}: {why}: run it again")));
    }
    let config_json = contents
        .metadata
        .iter()
        .find(|m| m.name == sunjitter_io::sink::METADATA_NAME)
        .and_then(|m| m.metadata.get("config").cloned())
        .ok_or_else(|| refused(path, "no `sunjitter` metadata with the configuration"))?;
    let config: Config = serde_json::from_str(&config_json).map_err(|e| {
        refused(
            path,
            format!("configuration not readable by this version: {e}"),
        )
    })?;
    config
        .validate()
        .map_err(|e| refused(path, format!("its {e}")))?;
    Ok(ShardLog {
        path: path.to_path_buf(),
        spec,
        inputs_digest: get("inputs_digest")?,
        config_digest: get("config_digest")?,
        total: number("total_frames")?,
        start: number("start")?,
        end: number("end")?,
        done,
        config,
        config_json,
        contents,
    })
}

/// Check that `shards` are all N shards of one run, once each, their ranges tiling the
/// run's frames, no frame logged twice. Sorts them by shard index.
pub fn check_set(shards: &mut [ShardLog]) -> Result<()> {
    let Some(first) = shards.first().cloned() else {
        return Err(Error::Usage("merge: no shard output given".into()));
    };
    let name = |s: &ShardLog| sunjitter_core::text::path(&s.path).into_owned();
    for s in shards.iter() {
        if s.spec.count != first.spec.count {
            return Err(refused(
                &s.path,
                format!(
                    "shard {} is one of {}, but {} is shard {}",
                    s.spec,
                    s.spec.count,
                    name(&first),
                    first.spec
                ),
            ));
        }
        if s.inputs_digest != first.inputs_digest {
            return Err(refused(
                &s.path,
                format!(
                    "shard {} was made from other inputs than {} (inputs digest {} ≠ {})",
                    s.spec,
                    name(&first),
                    &s.inputs_digest[..12.min(s.inputs_digest.len())],
                    &first.inputs_digest[..12.min(first.inputs_digest.len())]
                ),
            ));
        }
        if s.config_digest != first.config_digest {
            return Err(refused(
                &s.path,
                format!(
                    "shard {} was made with another configuration or version than {}",
                    s.spec,
                    name(&first)
                ),
            ));
        }
    }
    shards.sort_by_key(|s| s.spec.index);
    for pair in shards.windows(2) {
        if pair[0].spec.index == pair[1].spec.index {
            return Err(refused(
                &pair[1].path,
                format!(
                    "shard {} is given twice (also {})",
                    pair[1].spec,
                    name(&pair[0])
                ),
            ));
        }
    }
    let n = first.spec.count;
    for k in 0..n {
        if !shards.iter().any(|s| s.spec.index == k) {
            return Err(Error::Usage(format!(
                "merge: shard {k}/{n} is missing (none of the {} outputs given holds it)",
                shards.len()
            )));
        }
    }
    let mut expected_start = 0;
    for s in shards.iter() {
        if s.total != first.total || s.start != expected_start || s.end < s.start {
            return Err(refused(
                &s.path,
                format!(
                    "shard {} covers frames {}..{} of {}, where the shards before it end at {} of {}: overlapping or apart",
                    s.spec, s.start, s.end, s.total, expected_start, first.total
                ),
            ));
        }
        expected_start = s.end;
    }
    if expected_start != first.total {
        let last = &shards[shards.len() - 1];
        return Err(refused(
            &last.path,
            format!(
                "shard {} ends at frame {} of {}",
                last.spec, last.end, first.total
            ),
        ));
    }
    let mut seen: HashMap<&str, usize> = HashMap::new();
    for (i, s) in shards.iter().enumerate() {
        for m in &s.contents.jitter {
            if let Some(j) = seen.insert(&m.record.align.frame, i) {
                return Err(refused(
                    &s.path,
                    format!(
                        "frame {} is logged by shard {} and by {} ({})",
                        m.record.align.frame,
                        s.spec,
                        shards[j].spec,
                        name(&shards[j])
                    ),
                ));
            }
        }
    }
    Ok(())
}

// ---------------------------------------------------------------------------------------------
// The merge itself (no I/O)

/// One message of the merged log.
#[derive(Debug, Clone, PartialEq)]
pub enum Item {
    Frame(Box<FrameAlignment>),
    Reference(Box<ReferenceChange>),
    Log(LogEntry),
}

/// A message with its times, in the order the merged log writes them.
#[derive(Debug, Clone, PartialEq)]
pub struct MergedMessage {
    pub log_time_ns: u64,
    pub publish_time_ns: u64,
    pub item: Item,
}

/// The merged log, before writing.
#[derive(Debug, Clone, Default)]
pub struct Merged {
    pub messages: Vec<MergedMessage>,
    /// `/jitter` messages per channel.
    pub frames: BTreeMap<String, u64>,
    /// Frames whose chained values were carried across a shard boundary.
    pub stitched: u64,
    /// Frames whose chain could not be linked to the run's (chained values left null).
    pub unlinked: u64,
}

/// How one chain of one shard joins the run's series.
#[derive(Debug, Clone)]
enum LinkState {
    /// Already the run's: the chain starts where the run's does.
    Identity,
    Link(Box<Chain>),
    Unresolved,
}

/// The channel at the root of `channel`'s `channel:` partners.
fn root_channel(policies: &ReferencePolicies, channel: &str) -> String {
    policies
        .partner_chain(channel)
        .ok()
        .and_then(|c| c.last().cloned())
        .unwrap_or_else(|| channel.to_string())
}

/// The chain (index into the shard's starts of `root`) a frame at `t` belongs to.
fn chain_at(starts: &[ChainStart], t: i64) -> Option<usize> {
    let at = starts.partition_point(|s| s.obs_time_ns <= t);
    at.checked_sub(1)
}

/// A message's chained value as a chain about `center` (σ only: messages carry no
/// correlations).
fn message_chain(m: &FrameAlignment, center: [f64; 2]) -> Option<Chain> {
    chain_from_message(m, Some(center))
}

/// The link through a frame `g` measured by the shard (`c_g`, on the shard's chain) and
/// merged (`m_g`, on the run's): `L = c_g⁻¹ ∘ m_g`. The inverse's covariance is taken as
/// `c_g`'s (first order, near the identity).
fn link_through(c_g: &Chain, m_g: &Chain) -> Chain {
    let inverse = c_g.transform.inverse();
    match (c_g.covariance, m_g.covariance) {
        (Some(cc), Some(mc)) => {
            let (transform, cov) = compose_with_covariance(&inverse, &cc, &m_g.transform, &mc);
            Chain {
                transform,
                covariance: Some(cov),
                plate_scale_arcsec: m_g.plate_scale_arcsec,
            }
        }
        _ => Chain {
            transform: inverse.after(&m_g.transform),
            covariance: None,
            plate_scale_arcsec: m_g.plate_scale_arcsec,
        },
    }
}

fn chain_value(v: &crate::shard::ChainValue, center: [f64; 2]) -> Chain {
    let s = v.sigma;
    let mut cov = [[0.0; 4]; 4];
    cov[0][0] = s[0] * s[0];
    cov[1][1] = (s[1] / ARCSEC_PER_RAD).powi(2);
    cov[2][2] = s[2] * s[2];
    cov[3][3] = s[3] * s[3];
    Chain {
        transform: Similarity {
            scale: v.scale,
            rotation_rad: v.rotation_arcsec / ARCSEC_PER_RAD,
            dx: v.dx_px,
            dy: v.dy_px,
            center,
        },
        covariance: Some(cov),
        plate_scale_arcsec: None,
    }
}

/// The link state of every chain of a root channel, per (shard, channel): identity for a
/// chain its shard owns (or a fixed reference), else a link through frames the run's
/// resolved chains reach.
fn link_states(
    shards: &[ShardLog],
    policies: &ReferencePolicies,
) -> BTreeMap<(usize, String), Vec<LinkState>> {
    // Chains of root channels per (shard, channel): their link states.
    let mut links: BTreeMap<(usize, String), Vec<LinkState>> = BTreeMap::new();
    for (i, s) in shards.iter().enumerate() {
        for (channel, starts) in &s.done.chains {
            let fixed = matches!(policies.get(channel).policy, PolicySpec::Fixed(_));
            let states = starts
                .iter()
                .map(|st| {
                    if fixed || st.owned {
                        LinkState::Identity
                    } else {
                        LinkState::Unresolved
                    }
                })
                .collect();
            links.insert((i, channel.clone()), states);
        }
    }
    // The run's chained value of every frame of a root channel, as it becomes known.
    let mut merged: HashMap<String, Chain> = HashMap::new();
    let resolve_frames = |i: usize,
                          channel: &str,
                          j: usize,
                          state: LinkState,
                          merged: &mut HashMap<String, Chain>| {
        let s = &shards[i];
        let starts = &s.done.chains[channel];
        for jm in &s.contents.jitter {
            let m = &jm.record;
            if m.channel != channel || chain_at(starts, jm.log_time_ns as i64) != Some(j) {
                continue;
            }
            let Some(own) = message_chain(m, starts[j].center_px) else {
                continue;
            };
            let value = match &state {
                LinkState::Identity => own,
                LinkState::Link(l) => l.then(&own.transform, own.covariance.as_ref()),
                LinkState::Unresolved => continue,
            };
            merged.insert(m.align.frame.clone(), value);
        }
    };
    // Identity chains first, then links as the frames they go through become known.
    for ((i, channel), states) in &links {
        for (j, state) in states.iter().enumerate() {
            if let LinkState::Identity = state {
                resolve_frames(*i, channel, j, state.clone(), &mut merged);
            }
        }
    }
    loop {
        let mut progressed = false;
        let keys: Vec<(usize, String)> = links.keys().cloned().collect();
        for (i, channel) in keys {
            for j in 0..links[&(i, channel.clone())].len() {
                if !matches!(links[&(i, channel.clone())][j], LinkState::Unresolved) {
                    continue;
                }
                let start = &shards[i].done.chains[&channel][j];
                let link = merged.get(&start.frame).copied().or_else(|| {
                    start.links.iter().find_map(|g| {
                        let m_g = merged.get(&g.frame)?;
                        Some(link_through(&chain_value(&g.chain, start.center_px), m_g))
                    })
                });
                if let Some(l) = link {
                    let state = LinkState::Link(Box::new(l));
                    if let Some(v) = links.get_mut(&(i, channel.clone())) {
                        v[j] = state.clone();
                    }
                    resolve_frames(i, &channel, j, state, &mut merged);
                    progressed = true;
                }
            }
        }
        if !progressed {
            break;
        }
    }
    links
}

/// The shards' /reference messages in time order, renumbered by `offsets` (per shard and
/// channel), without one that repeats the channel's current reference.
fn references_renumbered(
    shards: &[ShardLog],
    offsets: &HashMap<(usize, String), i64>,
) -> Vec<MergedMessage> {
    let mut references: Vec<MergedMessage> = Vec::new();
    for (i, s) in shards.iter().enumerate() {
        for r in &s.contents.references {
            let mut change = r.change.clone();
            if let Some(offset) = offsets.get(&(i, change.channel.clone())) {
                change.sequence = (change.sequence as i64 + offset).max(0) as u64;
            }
            references.push(MergedMessage {
                log_time_ns: r.log_time_ns,
                publish_time_ns: r.publish_time_ns,
                item: Item::Reference(Box::new(change)),
            });
        }
    }
    references.sort_by_key(|r| r.log_time_ns);
    let mut current: HashMap<String, (String, Option<usize>)> = HashMap::new();
    references.retain(|r| {
        let Item::Reference(c) = &r.item else {
            return true;
        };
        let key = (c.file.clone(), c.cube_frame);
        current.insert(c.channel.clone(), key.clone()) != Some(key)
    });
    references
}

/// Join checked shards (sorted by index, see [`check_set`]) into one series.
pub fn merge(shards: &[ShardLog]) -> Merged {
    let Some(first) = shards.first() else {
        return Merged::default();
    };
    let policies = first.config.reference_policies();
    let links = link_states(shards, &policies);

    // Frame times of the whole run, for followers' partner frames.
    let times: HashMap<&str, i64> = shards
        .iter()
        .flat_map(|s| s.contents.jitter.iter())
        .map(|m| (m.record.align.frame.as_str(), m.log_time_ns as i64))
        .collect();

    let mut out = Merged::default();
    let mut unlinked_notes: BTreeMap<(usize, String, usize), (u64, String)> = BTreeMap::new();
    // Frames with their shard, log and publish times.
    let mut frames_of: Vec<(usize, FrameAlignment, u64, u64)> = Vec::new();
    for (i, s) in shards.iter().enumerate() {
        for jm in &s.contents.jitter {
            let mut m = jm.record.clone();
            let root = root_channel(&policies, &m.channel);
            let at = if root == m.channel {
                jm.log_time_ns as i64
            } else {
                times
                    .get(m.align.reference.as_str())
                    .copied()
                    .unwrap_or(jm.log_time_ns as i64)
            };
            let starts = s.done.chains.get(&root);
            let chain = starts.and_then(|st| chain_at(st, at).map(|j| (j, &st[j])));
            if let (Some((j, start)), true) = (chain, m.chained_dx_px.is_some()) {
                match links.get(&(i, root.clone())).map(|v| v[j].clone()) {
                    Some(LinkState::Link(l)) => {
                        let own = message_chain(&m, start.center_px);
                        let value = own.map(|c| l.then(&c.transform, c.covariance.as_ref()));
                        set_chain(&mut m, value.as_ref());
                        out.stitched += 1;
                    }
                    Some(LinkState::Unresolved) => {
                        set_chain(&mut m, None);
                        out.unlinked += 1;
                        let note = unlinked_notes
                            .entry((i, root.clone(), j))
                            .or_insert((jm.log_time_ns, start.frame.clone()));
                        note.0 = note.0.min(jm.log_time_ns);
                    }
                    _ => {}
                }
            }
            frames_of.push((i, m, jm.log_time_ns, jm.publish_time_ns));
        }
    }

    // Sequence numbers: per channel, in (time, frame) order, as one run numbers them; the
    // offset of each shard's numbers carries over to its /reference messages.
    frames_of.sort_by(|a, b| {
        (&a.1.channel, a.2, &a.1.align.frame).cmp(&(&b.1.channel, b.2, &b.1.align.frame))
    });
    let mut offsets: HashMap<(usize, String), i64> = HashMap::new();
    let mut next: HashMap<String, u64> = HashMap::new();
    for (shard, m, _, _) in frames_of.iter_mut() {
        let n = next.entry(m.channel.clone()).or_insert(0);
        offsets
            .entry((*shard, m.channel.clone()))
            .or_insert(*n as i64 - m.sequence as i64);
        m.sequence = *n;
        *n += 1;
        *out.frames.entry(m.channel.clone()).or_default() += 1;
    }

    let references = references_renumbered(shards, &offsets);

    let mut messages: Vec<MergedMessage> = frames_of
        .into_iter()
        .map(|(_, m, log_time_ns, publish_time_ns)| MergedMessage {
            log_time_ns,
            publish_time_ns,
            item: Item::Frame(Box::new(m)),
        })
        .collect();
    messages.extend(references);
    for s in shards {
        messages.extend(s.contents.logs.iter().map(|l| MergedMessage {
            log_time_ns: l.log_time_ns,
            publish_time_ns: l.publish_time_ns,
            item: Item::Log(l.entry.clone()),
        }));
    }
    for ((i, channel, _), (t, start)) in unlinked_notes {
        messages.push(MergedMessage {
            log_time_ns: t,
            publish_time_ns: t,
            item: Item::Log(LogEntry {
                timestamp: sunjitter_io::sink::FoxgloveTime::from_ns(t),
                level: sunjitter_io::sink::LogLevel::Warning,
                message: format!(
                    "{channel}: chained values left out: shard {}'s chain from {start} could not be linked to the run's",
                    shards[i].spec
                ),
                name: "sunjitter".into(),
                file: start,
                line: 0,
            }),
        });
    }
    messages.sort_by_key(|m| m.log_time_ns);
    out.messages = messages;
    out
}

// ---------------------------------------------------------------------------------------------
// Writing

/// The `sunjitter.merge` metadata of a merged log.
pub fn merge_metadata(shards: &[ShardLog], merged: &Merged) -> BTreeMap<String, String> {
    let mut m = BTreeMap::new();
    let paths: Vec<String> = shards
        .iter()
        .map(|s| sunjitter_core::text::path(&s.path).into_owned())
        .collect();
    if let Some(first) = shards.first() {
        m.insert("count".into(), first.spec.count.to_string());
        m.insert("inputs_digest".into(), first.inputs_digest.clone());
        m.insert("config_digest".into(), first.config_digest.clone());
    }
    m.insert(
        "shards".into(),
        serde_json::to_string(&paths).unwrap_or_default(),
    );
    m.insert(
        "frames".into(),
        merged.frames.values().sum::<u64>().to_string(),
    );
    m
}

/// What a merge may write into: a new directory, an empty one, or one holding only an
/// earlier merge of the same run (same inputs and configuration), which is replaced. Not a
/// shard's output, nor a directory holding anything else. Checked before any work and again
/// under the lock just before writing.
pub fn check_output(out: &Path, shards: &[ShardLog]) -> Result<()> {
    use sunjitter_io::outputs::file_id;
    if let Some(o) = file_id(out) {
        if let Some(s) = shards.iter().find(|s| file_id(&s.path) == Some(o)) {
            return Err(refused(
                out,
                format!(
                    "is shard {}'s output: refusing to write the merge over it",
                    s.spec
                ),
            ));
        }
    }
    if !out.exists() {
        return Ok(());
    }
    if !out.is_dir() {
        return Err(refused(out, "exists and is not a directory"));
    }
    let mut others = Vec::new();
    for entry in std::fs::read_dir(out).map_err(|e| Error::io(out, e))? {
        let entry = entry.map_err(|e| Error::io(out, e))?;
        let name = entry.file_name().to_string_lossy().into_owned();
        let segment = name.ends_with(".mcap") && entry.file_type().is_ok_and(|t| t.is_file());
        if name != sunjitter_io::outputs::LOCK_FILE && !segment {
            others.push(name);
        }
    }
    if !others.is_empty() {
        others.sort();
        let shown: Vec<String> = others
            .iter()
            .take(3)
            .map(|n| sunjitter_core::text::escape(n).into_owned())
            .collect();
        return Err(refused(
            out,
            format!(
                "holds {} other file(s) ({}{}): merge writes only into a new or empty directory, or over its own earlier merge",
                others.len(),
                shown.join(", "),
                if others.len() > 3 { ", …" } else { "" }
            ),
        ));
    }
    let contents = sunjitter_io::sink::read_logs(&[out.to_path_buf()]).map_err(|e| {
        refused(
            out,
            format!("holds a log that cannot be read ({e}); refusing to write over it"),
        )
    })?;
    let first = &shards[0];
    let same_run = |i: usize| {
        contents.metadata.iter().any(|m| {
            m.segment == i
                && m.name == MERGE_METADATA
                && m.metadata.get("inputs_digest") == Some(&first.inputs_digest)
                && m.metadata.get("config_digest") == Some(&first.config_digest)
        })
    };
    for (i, s) in contents.segments.iter().enumerate() {
        if !same_run(i) {
            return Err(refused(
                out,
                format!(
                    "holds a log ({}) that is not a merge of these shards: refusing to write over it",
                    sunjitter_core::text::path(&s.path)
                ),
            ));
        }
    }
    Ok(())
}

/// The hidden directory beside `out` a merge is written into before it takes `out`'s place.
fn staging_dir(parent: &Path, name: &std::ffi::OsStr, pid: u32) -> PathBuf {
    parent.join(format!(".{}.merge-{pid}", name.to_string_lossy()))
}

/// Remove what a merge put in `dir` (segments, their recovery copies, the lock file, a
/// write check's probe), then the directory if that leaves it empty. Anything else is left; a
/// link is never followed.
fn remove_merge_dir(dir: &Path) {
    let is_dir = std::fs::symlink_metadata(dir).is_ok_and(|m| m.is_dir());
    if !is_dir {
        return;
    }
    if let Ok(entries) = std::fs::read_dir(dir) {
        for entry in entries.flatten() {
            let name = entry.file_name().to_string_lossy().into_owned();
            let ours = name == sunjitter_io::outputs::LOCK_FILE
                || name.ends_with(".mcap")
                || name.ends_with(".mcap.recovering")
                || name.starts_with(sunjitter_core::error::WRITE_PROBE_PREFIX);
            if ours && entry.file_type().is_ok_and(|t| t.is_file()) {
                let _ = std::fs::remove_file(entry.path());
            }
        }
    }
    let _ = std::fs::remove_dir(dir);
}

/// Staging directories of merges into `name` that were killed (nobody holds their lock).
fn remove_stale_staging(parent: &Path, name: &std::ffi::OsStr) {
    let prefix = format!(".{}.merge-", name.to_string_lossy());
    let Ok(entries) = std::fs::read_dir(parent) else {
        return;
    };
    for entry in entries.flatten() {
        let n = entry.file_name().to_string_lossy().into_owned();
        if !n.starts_with(&prefix) || !entry.file_type().is_ok_and(|t| t.is_dir()) {
            continue;
        }
        if let Ok(lock) = sunjitter_io::outputs::OutputLock::acquire(&entry.path()) {
            drop(lock);
            remove_merge_dir(&entry.path());
        }
    }
}

/// Write the merged log as `out`: into a hidden directory beside it first, then put in
/// `out`'s place in one rename (the old and the new directory exchanged where the system
/// can, Linux), and the old merge removed. A merge stopped at any moment leaves `out` as
/// it was (the hidden directory is removed by the next merge). Returns the segments.
pub fn write(out: &Path, shards: &[ShardLog], merged: &Merged) -> Result<Vec<PathBuf>> {
    let out = match out.canonicalize() {
        Ok(real) => real,
        Err(_) => std::path::absolute(out).map_err(|e| Error::io(out, e))?,
    };
    let (Some(parent), Some(name)) = (out.parent(), out.file_name()) else {
        return Err(refused(
            &out,
            "is not a directory a merge can be written as",
        ));
    };
    std::fs::create_dir_all(parent).map_err(|e| Error::unwritable(parent, e))?;
    // Held until the new log is in place: no other merge or run writes here meanwhile.
    let out_lock = if out.exists() {
        Some(sunjitter_io::outputs::OutputLock::acquire(&out)?)
    } else {
        None
    };
    check_output(&out, shards)?;
    remove_stale_staging(parent, name);
    let stage = staging_dir(parent, name, std::process::id());
    remove_merge_dir(&stage);
    let stage_lock = sunjitter_io::outputs::OutputLock::acquire(&stage)?;
    let first = &shards[0];
    let mut sink_config = first.config.sink.clone();
    // One pass over finished logs: segments by frame count only, not by the clock.
    sink_config.segment_minutes = 0.0;
    let written = (|| -> Result<sunjitter_io::sink::McapSink> {
        let mut sink =
            sunjitter_io::sink::McapSink::new(&stage, sink_config, first.config_json.clone())?
                .with_segment_metadata(MERGE_METADATA, merge_metadata(shards, merged))
                .holding(stage_lock);
        for m in &merged.messages {
            match &m.item {
                Item::Frame(f) => sink.write_frame(f, m.log_time_ns, m.publish_time_ns)?,
                Item::Reference(c) => {
                    sink.write_reference_change(c, m.log_time_ns, m.publish_time_ns)?
                }
                Item::Log(e) => sink.write_log(
                    e.level,
                    &e.file,
                    &e.message,
                    m.log_time_ns,
                    m.publish_time_ns,
                )?,
            }
        }
        if merged.messages.is_empty() {
            sink.write_metadata(
                MERGE_METADATA,
                merge_metadata(shards, merged),
                sunjitter_io::records::mcap_ns(sunjitter_io::records::now_ns()),
            )?;
        }
        sink.finish()?;
        // On disk before it replaces anything.
        for p in sink.segment_paths() {
            std::fs::File::open(p)
                .and_then(|f| f.sync_all())
                .map_err(|e| Error::io(p, e))?;
        }
        Ok(sink)
    })();
    let sink = match written {
        Ok(sink) => sink,
        Err(e) => {
            remove_merge_dir(&stage);
            return Err(e);
        }
    };
    let names: Vec<PathBuf> = sink
        .segment_paths()
        .iter()
        .filter_map(|p| p.file_name().map(|n| out.join(n)))
        .collect();
    let replaced = sunjitter_io::outputs::put_dir_in_place(&stage, &out)?;
    drop(sink);
    drop(out_lock);
    // The stage now holds the old merge (or nothing).
    if replaced {
        remove_merge_dir(&stage);
    }
    Ok(names)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn chain(dx: f64, dy: f64, sigma: f64) -> Chain {
        let mut cov = [[0.0; 4]; 4];
        cov[0][0] = 1e-10;
        cov[1][1] = 1e-10;
        cov[2][2] = sigma * sigma;
        cov[3][3] = sigma * sigma;
        Chain {
            transform: Similarity {
                scale: 1.0,
                rotation_rad: 0.0,
                dx,
                dy,
                center: [10.0, 10.0],
            },
            covariance: Some(cov),
            plate_scale_arcsec: Some([0.5, 0.5]),
        }
    }

    #[test]
    fn a_link_through_the_chain_start_reproduces_the_single_run() {
        // Single run: origin → keyframe K (chain k), keyframe → frame F (step a).
        let k = chain(1.5, -0.5, 0.1);
        let a = chain(0.25, 0.75, 0.05);
        let single = k.then(&a.transform, a.covariance.as_ref());
        // The shard starts its chain at K: F's chained value there is `a` itself.
        let shard_f =
            Chain::origin([10.0, 10.0], Some([0.5, 0.5])).then(&a.transform, a.covariance.as_ref());
        let stitched = k.then(&shard_f.transform, shard_f.covariance.as_ref());
        assert!((stitched.transform.dx - single.transform.dx).abs() < 1e-12);
        assert!((stitched.transform.dy - single.transform.dy).abs() < 1e-12);
        let (s1, s2) = (single.sigmas().unwrap(), stitched.sigmas().unwrap());
        assert!((s1[2] - s2[2]).abs() < 1e-9, "{s1:?} {s2:?}");
        // σ adds in quadrature: √(0.1² + 0.05²).
        assert!((s2[2] - (0.1f64.powi(2) + 0.05f64.powi(2)).sqrt()).abs() < 1e-6);
    }

    #[test]
    fn a_link_through_a_later_frame_gives_the_same_transform() {
        let k = chain(1.5, -0.5, 0.1);
        let g = chain(0.2, 0.1, 0.05);
        let merged_g = k.then(&g.transform, g.covariance.as_ref());
        let shard_g = Chain::origin([10.0, 10.0], None).then(&g.transform, g.covariance.as_ref());
        let l = link_through(&shard_g, &merged_g);
        assert!((l.transform.dx - 1.5).abs() < 1e-9 && (l.transform.dy + 0.5).abs() < 1e-9);
        // The link's σ holds both frames' (the start's own chain, and g's step twice).
        assert!(l.sigmas().unwrap()[2] > 0.1);
    }

    #[test]
    fn chains_are_found_by_start_time() {
        let start = |t: i64| ChainStart {
            frame: format!("f{t}"),
            obs_time_ns: t,
            owned: false,
            center_px: [0.0, 0.0],
            plate_scale_arcsec: None,
            links: Vec::new(),
        };
        let starts = vec![start(10), start(50)];
        assert_eq!(chain_at(&starts, 5), None);
        assert_eq!(chain_at(&starts, 10), Some(0));
        assert_eq!(chain_at(&starts, 49), Some(0));
        assert_eq!(chain_at(&starts, 60), Some(1));
    }
}
