//! Sharded replay (`replay --shard K/N`): which frames a shard measures, which of them it
//! logs as its own, and what it records for [`crate::merge`] to stitch the chained series.
//!
//! All frames of a run are sorted by (channel, observation time, key) and cut into N
//! contiguous ranges; shard K owns range K. Before its range (per channel) a shard measures
//! an overlap that starts where a single run would have had a keyframe (predicted from the
//! frames' times by the count and age rules), so its first reference is the single run's;
//! for `channel:NAME` followers it also measures the partner frames within the tolerance of
//! its own. Frames it measures but does not own are not logged: their records are dropped by
//! [`ShardSink`], which notes where each chain of the shard starts and a few of the chained
//! values it measured on frames other shards own (the links the merge stitches with).
//!
//! The planning is pure ([`plan`]); the sink only forwards records to the MCAP sink.

use crate::config::Config;
use crate::pipeline::Input;
use crate::reference::{ChannelPolicy, PolicySpec};
use serde::{Deserialize, Serialize};
use std::collections::{BTreeMap, HashSet};
use std::str::FromStr;
use sunjitter_core::{Error, Result};
use sunjitter_io::records::{Record, RecordSink};

/// Metadata record at the start of every segment of a shard's log: which shard of what.
pub const SHARD_METADATA: &str = "sunjitter.shard";
/// Metadata record a shard writes when it has finished: where its chains start, and links.
pub const SHARD_DONE_METADATA: &str = "sunjitter.shard.done";
/// Link values kept per chain of a shard (frames other shards own, with a chained value).
const LINKS_PER_CHAIN: usize = 4;

/// Shards of one run at most (a job array larger than any cluster runs at once).
pub const MAX_SHARDS: usize = 100_000;

/// `K/N`: shard K (0-based) of N, with 1 ≤ N ≤ [`MAX_SHARDS`].
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct ShardSpec {
    pub index: usize,
    pub count: usize,
}

impl FromStr for ShardSpec {
    type Err = Error;
    fn from_str(s: &str) -> Result<ShardSpec> {
        let bad = |why: &str| Error::Usage(format!("--shard {s}: {why}"));
        let (k, n) = s
            .split_once('/')
            .ok_or_else(|| bad("expected K/N, e.g. 0/4"))?;
        let index: usize = k.trim().parse().map_err(|_| bad("K is not a number"))?;
        let count: usize = n.trim().parse().map_err(|_| bad("N is not a number"))?;
        if count == 0 {
            return Err(bad("N must be at least 1"));
        }
        if count > MAX_SHARDS {
            return Err(bad(&format!("N must be at most {MAX_SHARDS}")));
        }
        if index >= count {
            return Err(bad("K counts from 0 and must be below N"));
        }
        Ok(ShardSpec { index, count })
    }
}

impl std::fmt::Display for ShardSpec {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{}/{}", self.index, self.count)
    }
}

/// One frame of the run, as the shards sort them.
#[derive(Debug, Clone, PartialEq, Eq, PartialOrd, Ord)]
pub struct FrameEntry {
    pub channel: String,
    pub obs_time_ns: i64,
    pub key: String,
}

/// What one shard measures and owns.
#[derive(Debug, Clone)]
pub struct ShardPlan {
    pub spec: ShardSpec,
    /// Frames of the whole run (all shards).
    pub total: usize,
    /// The range of the sorted frames this shard owns: `[start, end)`.
    pub start: usize,
    pub end: usize,
    /// Frame keys this shard logs.
    pub owned: HashSet<String>,
    /// (channel, observation time) of the owned frames: a `/reference` record is logged when
    /// the frame that caused it is owned.
    pub owned_times: HashSet<(String, i64)>,
    /// Frame keys this shard measures (owned ones and the overlap).
    pub measured: HashSet<String>,
    /// Every frame key of the run.
    pub all: HashSet<String>,
    pub inputs_digest: String,
    /// Per channel, the number of its frames before the first this shard measures: the
    /// sequence number a single run gives that frame, where the shard's numbering starts.
    pub first_measured: BTreeMap<String, u64>,
}

/// The cut points of `total` sorted frames into `count` ranges: `count + 1` indices. A cut
/// never falls between frames of one channel with the same observation time.
pub fn cuts(frames: &[FrameEntry], count: usize) -> Vec<usize> {
    let total = frames.len();
    let mut cuts: Vec<usize> = (0..=count).map(|k| k * total / count.max(1)).collect();
    for cut in cuts.iter_mut() {
        while *cut > 0
            && *cut < total
            && frames[*cut - 1].channel == frames[*cut].channel
            && frames[*cut - 1].obs_time_ns == frames[*cut].obs_time_ns
        {
            *cut += 1;
        }
    }
    for k in 1..cuts.len() {
        cuts[k] = cuts[k].max(cuts[k - 1]);
    }
    cuts
}

/// Indices (within one channel's frames) where a single run's keyframes fall when no match
/// degrades and no frame fails: the count and age rules of the keyframe policy.
pub fn predicted_keyframes(times_ns: &[i64], p: &ChannelPolicy) -> Vec<usize> {
    let mut keyframes = Vec::new();
    let Some(&first) = times_ns.first() else {
        return keyframes;
    };
    keyframes.push(0);
    let (mut key_time, mut on_reference) = (first, 0u32);
    for (i, &t) in times_ns.iter().enumerate().skip(1) {
        let age_s = (t - key_time) as f64 * 1e-9;
        if p.keyframe_due(on_reference, age_s).is_some() {
            keyframes.push(i);
            key_time = t;
            on_reference = 0;
        } else {
            on_reference += 1;
        }
    }
    keyframes
}

/// `previous`: frames measured before a shard's range by default.
const PREVIOUS_OVERLAP: usize = sunjitter_core::engine::refine::SELF_TEST_QUARTERS;

/// The frames of a channel measured before frame `a` (an index within the channel) so that
/// the shard's reference at `a` is the single run's. `overlap`: at least this many frames
/// (`None`: the policy's default, one keyframe interval for `keyframe`).
fn overlap_start(a: usize, p: &ChannelPolicy, times: &[i64], overlap: Option<usize>) -> usize {
    if a == 0 {
        return 0;
    }
    match &p.policy {
        // Back to the single run's keyframe before the range, and one more: a keyframe is
        // reached through the one it replaces and the one before that.
        PolicySpec::Keyframe => {
            let want = overlap.unwrap_or(p.keyframe_every_frames as usize).max(1);
            let s = a.saturating_sub(want);
            let keyframes = predicted_keyframes(times, p);
            let at = keyframes.partition_point(|&k| k <= s);
            keyframes[at.saturating_sub(2)]
        }
        // Each reference along the chain renews a quarter of the self-test cases it is handed:
        // after as many references the shard's chain holds the single run's cases.
        PolicySpec::Previous => a.saturating_sub(overlap.unwrap_or(PREVIOUS_OVERLAP).max(1)),
        PolicySpec::Channel(_) => a.saturating_sub(overlap.unwrap_or(1)),
        PolicySpec::Fixed(_) => a.saturating_sub(overlap.unwrap_or(0)),
    }
}

impl ShardPlan {
    /// Where the shard's channels start: each numbers its frames from its first measured
    /// frame's place in the whole run, as a single run numbers them (the self-test cases a
    /// `previous` chain renews follow these numbers).
    pub fn history(&self) -> crate::reference::History {
        crate::reference::History {
            done: HashSet::new(),
            channels: self
                .first_measured
                .iter()
                .map(|(c, &n)| {
                    let start = crate::reference::RestoredChannel {
                        next_sequence: n,
                        ..Default::default()
                    };
                    (c.clone(), start)
                })
                .collect(),
        }
    }
}

/// Plan shard `spec` of `frames` (any order; frames are sorted here). `overlap`: the
/// `--shard-overlap` frames, `None` for the policies' defaults.
pub fn plan(
    frames: &[FrameEntry],
    other_inputs: &[String],
    config: &Config,
    spec: ShardSpec,
    overlap: Option<usize>,
) -> ShardPlan {
    let mut sorted = frames.to_vec();
    sorted.sort();
    let cuts = cuts(&sorted, spec.count);
    let (start, end) = (cuts[spec.index], cuts[spec.index + 1]);

    // Per channel: its frames' global indices, in order.
    let mut by_channel: BTreeMap<&str, Vec<usize>> = BTreeMap::new();
    for (i, f) in sorted.iter().enumerate() {
        by_channel.entry(&f.channel).or_default().push(i);
    }
    let times = |c: &str| -> Vec<i64> {
        by_channel
            .get(c)
            .map(|ix| ix.iter().map(|&i| sorted[i].obs_time_ns).collect())
            .unwrap_or_default()
    };
    // Measured range per channel, as indices within the channel: [lo, hi).
    let policies = config.reference_policies();
    let mut need: BTreeMap<String, (usize, usize)> = BTreeMap::new();
    for (c, ix) in &by_channel {
        let a = ix.partition_point(|&i| i < start);
        let b = ix.partition_point(|&i| i < end);
        if a < b {
            let p = policies.get(c);
            need.insert(c.to_string(), (overlap_start(a, p, &times(c), overlap), b));
        }
    }
    // Partner frames of `channel:` followers, within the tolerance of the frames they
    // measure, with the partner's own overlap; repeated along chains of followers.
    for _ in 0..=by_channel.len() {
        let mut changed = false;
        let snapshot = need.clone();
        for (c, &(lo, hi)) in &snapshot {
            let p = policies.get(c);
            let PolicySpec::Channel(partner) = &p.policy else {
                continue;
            };
            let t = times(c);
            let partner_times = times(partner);
            if partner_times.is_empty() || lo >= hi {
                continue;
            }
            let tol = (p.tolerance_s * 1e9) as i64;
            let (t_lo, t_hi) = (t[lo].saturating_sub(tol), t[hi - 1].saturating_add(tol));
            let i0 = partner_times.partition_point(|&x| x < t_lo);
            let i1 = partner_times.partition_point(|&x| x <= t_hi);
            if i0 >= i1 {
                continue;
            }
            let s = overlap_start(i0, policies.get(partner), &partner_times, overlap);
            let entry = need.entry(partner.clone()).or_insert((s, i1));
            let merged = (entry.0.min(s), entry.1.max(i1));
            if merged != *entry {
                *entry = merged;
                changed = true;
            } else if !snapshot.contains_key(partner) {
                changed = true;
            }
        }
        if !changed {
            break;
        }
    }

    let owned: HashSet<String> = sorted[start..end].iter().map(|f| f.key.clone()).collect();
    let owned_times = sorted[start..end]
        .iter()
        .map(|f| (f.channel.clone(), f.obs_time_ns))
        .collect();
    let mut measured = HashSet::new();
    for (c, (lo, hi)) in &need {
        if let Some(ix) = by_channel.get(c.as_str()) {
            measured.extend(ix[*lo..*hi].iter().map(|&i| sorted[i].key.clone()));
        }
    }
    ShardPlan {
        spec,
        total: sorted.len(),
        start,
        end,
        owned,
        owned_times,
        measured,
        all: sorted.iter().map(|f| f.key.clone()).collect(),
        inputs_digest: inputs_digest(&sorted, other_inputs),
        first_measured: need
            .iter()
            .map(|(c, &(lo, _))| (c.clone(), lo as u64))
            .collect(),
    }
}

/// SHA-256 (hex) of the sorted frames (channel, time, key) and the inputs that gave no frame.
pub fn inputs_digest(sorted: &[FrameEntry], other_inputs: &[String]) -> String {
    use sha2::Digest;
    let mut h = sha2::Sha256::new();
    for f in sorted {
        h.update(format!("{}\t{}\t{}\n", f.channel, f.obs_time_ns, f.key).as_bytes());
    }
    let mut others = other_inputs.to_vec();
    others.sort();
    for o in others {
        h.update(format!("-\t{o}\n").as_bytes());
    }
    hex(&h.finalize())
}

/// SHA-256 (hex) of the program version and the effective configuration: shards measured
/// with different settings or versions do not merge.
pub fn config_digest(config: &Config) -> String {
    use sha2::Digest;
    let mut h = sha2::Sha256::new();
    h.update(env!("CARGO_PKG_VERSION").as_bytes());
    h.update(b"\n");
    h.update(config.to_json().to_string().as_bytes());
    hex(&h.finalize())
}

fn hex(bytes: &[u8]) -> String {
    bytes.iter().map(|b| format!("{b:02x}")).collect()
}

impl ShardPlan {
    /// The inputs of the shard's run: the frames it measures, and (shard 0 only) the records
    /// of inputs that gave no frame.
    pub fn select(&self, inputs: Vec<Input>) -> Vec<Input> {
        inputs
            .into_iter()
            .filter(|i| match i {
                Input::Frame(f) => self.measured.contains(&f.key),
                Input::Record(_) => self.spec.index == 0,
            })
            .collect()
    }

    /// Whether the shard logs `record`.
    pub fn owns(&self, record: &Record) -> bool {
        match record {
            Record::Frame { message, .. } => self.owned.contains(&message.align.frame),
            Record::Reference {
                change,
                log_time_ns,
            } => self
                .owned_times
                .contains(&(change.channel.clone(), *log_time_ns)),
            Record::Log { file, .. } => {
                self.owned.contains(file) || (self.spec.index == 0 && !self.all.contains(file))
            }
        }
    }

    /// The `sunjitter.shard` metadata record.
    pub fn metadata(&self, config_digest: &str) -> BTreeMap<String, String> {
        let mut m = BTreeMap::new();
        m.insert("shard".into(), self.spec.to_string());
        m.insert("index".into(), self.spec.index.to_string());
        m.insert("count".into(), self.spec.count.to_string());
        m.insert("inputs_digest".into(), self.inputs_digest.clone());
        m.insert("config_digest".into(), config_digest.to_string());
        m.insert("total_frames".into(), self.total.to_string());
        m.insert("start".into(), self.start.to_string());
        m.insert("end".into(), self.end.to_string());
        m
    }
}

/// Frames of a run from [`crate::pipeline::replay_inputs`]: the frames, and the keys of the
/// inputs that gave no frame.
pub fn entries(inputs: &[Input]) -> (Vec<FrameEntry>, Vec<String>) {
    let mut frames = Vec::new();
    let mut others = Vec::new();
    for input in inputs {
        match input {
            Input::Frame(f) => frames.push(FrameEntry {
                channel: f.channel.clone(),
                obs_time_ns: f.obs_time_ns,
                key: f.key.clone(),
            }),
            Input::Record(Record::Log { file, .. }) => others.push(file.clone()),
            Input::Record(_) => {}
        }
    }
    (frames, others)
}

// ---------------------------------------------------------------------------------------------
// What a shard records for the merge

/// A chain value measured by a shard (σ only, as messages carry them).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct ChainValue {
    pub scale: f64,
    pub rotation_arcsec: f64,
    pub dx_px: f64,
    pub dy_px: f64,
    pub sigma: [f64; 4],
}

/// A frame another shard owns, with the chained value this shard measured for it.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Link {
    pub frame: String,
    pub chain: ChainValue,
}

/// Where one chain of a shard starts (the frame that became its origin).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ChainStart {
    pub frame: String,
    pub obs_time_ns: i64,
    /// The start is one of the shard's own frames (then a single run started a chain there).
    pub owned: bool,
    /// Centre the chain's transforms are expressed about (the origin's array centre).
    pub center_px: [f64; 2],
    pub plate_scale_arcsec: Option<[f64; 2]>,
    /// Chained values of frames other shards own, measured on this chain.
    pub links: Vec<Link>,
}

/// What a finished shard records at its end (`sunjitter.shard.done`).
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct ShardDone {
    /// `/jitter` messages the shard logged.
    pub messages: u64,
    /// Frames measured but not logged (overlap and partner frames).
    pub overlap_frames: u64,
    /// Per channel, its chains in the order they started.
    pub chains: BTreeMap<String, Vec<ChainStart>>,
}

impl ShardDone {
    pub fn to_metadata(&self) -> BTreeMap<String, String> {
        let mut m = BTreeMap::new();
        m.insert("messages".into(), self.messages.to_string());
        m.insert("overlap_frames".into(), self.overlap_frames.to_string());
        m.insert(
            "chains".into(),
            serde_json::to_string(&self.chains).unwrap_or_else(|_| "{}".into()),
        );
        m
    }

    pub fn from_metadata(m: &BTreeMap<String, String>) -> std::result::Result<ShardDone, String> {
        let number = |k: &str| -> std::result::Result<u64, String> {
            m.get(k)
                .and_then(|v| v.parse().ok())
                .ok_or_else(|| format!("`{k}` missing or not a number"))
        };
        let chains = m.get("chains").ok_or("`chains` missing")?;
        Ok(ShardDone {
            messages: number("messages")?,
            overlap_frames: number("overlap_frames")?,
            chains: serde_json::from_str(chains).map_err(|e| format!("`chains`: {e}"))?,
        })
    }
}

/// Is this `/reference` record the start of a new chain (its origin)?
fn starts_chain(reason: &str) -> bool {
    reason == "first frame" || reason.ends_with("new chain")
}

/// The sink of a shard: logs the records of owned frames, keeps note of chain starts and
/// links, and at the end writes `sunjitter.shard.done` (a shard without it did not finish).
pub struct ShardSink {
    inner: sunjitter_io::sink::McapSink,
    plan: ShardPlan,
    done: ShardDone,
    measured: HashSet<String>,
}

impl ShardSink {
    pub fn new(inner: sunjitter_io::sink::McapSink, plan: ShardPlan) -> ShardSink {
        ShardSink {
            inner,
            plan,
            done: ShardDone::default(),
            measured: HashSet::new(),
        }
    }

    fn note(&mut self, record: &Record, owned: bool) {
        match record {
            Record::Reference {
                change,
                log_time_ns,
            } if starts_chain(&change.reason) => {
                let Some(chain) = change.chain else {
                    return;
                };
                let frame = change.key();
                self.done
                    .chains
                    .entry(change.channel.clone())
                    .or_default()
                    .push(ChainStart {
                        owned: self.plan.owned.contains(&frame),
                        frame,
                        obs_time_ns: *log_time_ns,
                        center_px: chain.transform.center,
                        plate_scale_arcsec: chain.plate_scale_arcsec,
                        links: Vec::new(),
                    });
            }
            Record::Frame { message, .. } if !owned => {
                self.measured.insert(message.align.frame.clone());
                let m = message;
                let chain = (|| {
                    Some(ChainValue {
                        scale: m.chained_scale?,
                        rotation_arcsec: m.chained_rotation_arcsec?,
                        dx_px: m.chained_dx_px?,
                        dy_px: m.chained_dy_px?,
                        sigma: [
                            m.sigma_chained_scale?,
                            m.sigma_chained_rotation_arcsec?,
                            m.sigma_chained_dx_px?,
                            m.sigma_chained_dy_px?,
                        ],
                    })
                })();
                let Some(chain) = chain else {
                    return;
                };
                if let Some(start) = self
                    .done
                    .chains
                    .get_mut(&m.channel)
                    .and_then(|c| c.last_mut())
                {
                    if start.links.len() < LINKS_PER_CHAIN && start.frame != m.align.frame {
                        start.links.push(Link {
                            frame: m.align.frame.clone(),
                            chain,
                        });
                    }
                }
            }
            _ => {}
        }
    }
}

impl RecordSink for ShardSink {
    fn write(&mut self, record: &Record, publish_time_ns: i64) -> Result<()> {
        let owned = self.plan.owns(record);
        self.note(record, owned);
        if !owned {
            return Ok(());
        }
        if matches!(record, Record::Frame { .. }) {
            self.done.messages += 1;
        }
        sunjitter_io::records::McapRecordSink::write_to(&mut self.inner, record, publish_time_ns)
    }

    fn flush(&mut self) -> Result<()> {
        self.inner.tick(sunjitter_io::records::mcap_ns(
            sunjitter_io::records::now_ns(),
        ))
    }

    fn finish(mut self: Box<Self>) -> Result<()> {
        self.done.overlap_frames = self.measured.len() as u64;
        let now = sunjitter_io::records::mcap_ns(sunjitter_io::records::now_ns());
        let metadata = self.done.to_metadata();
        self.inner
            .write_metadata(SHARD_DONE_METADATA, metadata, now)?;
        self.inner.finish()
    }
}

// ---------------------------------------------------------------------------------------------
// The shard's output directory

/// Make `out` ready for shard `spec`: a log already there must be an earlier attempt of the
/// same shard of the same inputs and configuration (a requeued job), and is removed; any
/// other log is refused. Call with `out`'s lock held.
pub fn replace_earlier_attempt(
    out: &std::path::Path,
    plan: &ShardPlan,
    config_digest: &str,
) -> Result<usize> {
    if !out.is_dir() {
        return Ok(0);
    }
    let contents = sunjitter_io::sink::read_logs(&[out.to_path_buf()])?;
    if contents.segments.is_empty() {
        return Ok(0);
    }
    let refuse = |why: String| Error::Refused {
        path: out.to_path_buf(),
        reason: why,
    };
    let ours = plan.metadata(config_digest);
    let same = |m: &BTreeMap<String, String>| {
        ["shard", "inputs_digest", "config_digest"]
            .iter()
            .all(|k| m.get(*k) == ours.get(*k))
    };
    for (i, segment) in contents.segments.iter().enumerate() {
        let shard = contents
            .metadata
            .iter()
            .find(|m| m.segment == i && m.name == SHARD_METADATA);
        match shard {
            None => {
                return Err(refuse(format!(
                    "holds a log that is not a shard's ({}); refusing to replace it",
                    sunjitter_core::text::path(&segment.path)
                )))
            }
            Some(m) if !same(&m.metadata) => {
                return Err(refuse(format!(
                    "holds shard {} of a run, not shard {} of these inputs and configuration ({}); refusing to replace it",
                    m.metadata.get("shard").map_or("?", |s| s.as_str()),
                    plan.spec,
                    sunjitter_core::text::path(&segment.path)
                )))
            }
            Some(_) => {}
        }
    }
    for segment in &contents.segments {
        std::fs::remove_file(&segment.path).map_err(|e| Error::io(&segment.path, e))?;
    }
    Ok(contents.segments.len())
}

/// The sink, history and inputs of `replay --shard`: plans the shard, replaces an earlier
/// attempt's log in `out`, and opens the MCAP sink with the shard's metadata.
pub fn open_shard(
    out: &std::path::Path,
    config: &Config,
    spec: ShardSpec,
    overlap: Option<usize>,
    inputs: Vec<Input>,
) -> Result<(Box<dyn RecordSink>, Vec<Input>, ShardPlan)> {
    let (frames, others) = entries(&inputs);
    let plan = plan(&frames, &others, config, spec, overlap);
    let digest = config_digest(config);
    let lock = sunjitter_io::outputs::OutputLock::acquire(out)?;
    let replaced = replace_earlier_attempt(out, &plan, &digest)?;
    if replaced > 0 {
        tracing::warn!(
            "{}: replaced {replaced} segment(s) of an earlier attempt of shard {spec}",
            sunjitter_core::text::path(out)
        );
    }
    let sink =
        sunjitter_io::sink::McapSink::new(out, config.sink.clone(), config.to_json().to_string())?
            .with_segment_metadata(SHARD_METADATA, plan.metadata(&digest))
            .holding(lock);
    let selected = plan.select(inputs);
    Ok((Box::new(ShardSink::new(sink, plan.clone())), selected, plan))
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::collections::HashMap;

    fn frames(channel: &str, n: usize, cadence_s: i64) -> Vec<FrameEntry> {
        (0..n)
            .map(|i| FrameEntry {
                channel: channel.into(),
                obs_time_ns: i as i64 * cadence_s * 1_000_000_000,
                key: format!("{channel}-{i:04}.fits"),
            })
            .collect()
    }

    #[test]
    fn shard_spec_parses_k_of_n_and_refuses_the_rest() {
        assert_eq!(
            "3/4".parse::<ShardSpec>().unwrap(),
            ShardSpec { index: 3, count: 4 }
        );
        for bad in [
            "4/4",
            "1/0",
            "a/2",
            "2",
            "-1/3",
            "0/4294967296",
            "0/18446744073709551615",
            "0/18446744073709551616",
            "0/100001",
        ] {
            let e = bad.parse::<ShardSpec>().unwrap_err();
            assert_eq!(
                e.exit_code(),
                sunjitter_core::error::ExitCode::BadInput,
                "{bad}"
            );
        }
    }

    #[test]
    fn every_frame_belongs_to_exactly_one_shard() {
        let mut all = frames("B", 37, 12);
        all.extend(frames("A", 20, 10));
        let config = Config::default();
        for n in [1, 2, 3, 7, 60] {
            let mut seen: HashMap<String, usize> = HashMap::new();
            for k in 0..n {
                let p = plan(&all, &[], &config, ShardSpec { index: k, count: n }, None);
                for key in &p.owned {
                    *seen.entry(key.clone()).or_default() += 1;
                }
                assert!(p.owned.is_subset(&p.measured));
            }
            assert_eq!(seen.len(), all.len(), "N = {n}");
            assert!(seen.values().all(|&c| c == 1), "N = {n}");
        }
    }

    #[test]
    fn shards_of_one_channel_are_contiguous_time_ranges() {
        let all = frames("A", 100, 12);
        let config = Config::default();
        let mut last_end = 0;
        for k in 0..4 {
            let p = plan(&all, &[], &config, ShardSpec { index: k, count: 4 }, None);
            assert_eq!(p.start, last_end);
            let mut idx: Vec<usize> = p
                .owned
                .iter()
                .map(|key| all.iter().position(|f| &f.key == key).unwrap())
                .collect();
            idx.sort();
            assert_eq!(idx, (p.start..p.end).collect::<Vec<_>>());
            last_end = p.end;
        }
        assert_eq!(last_end, 100);
    }

    #[test]
    fn a_cut_never_splits_frames_of_one_time() {
        let mut all = frames("A", 10, 12);
        // Frames 4 and 5 at the same time: the cut at 5 moves past both.
        for f in all.iter_mut().skip(4).take(2) {
            f.obs_time_ns = 60_000_000_000;
        }
        assert_eq!(cuts(&all, 2), vec![0, 6, 10]);
    }

    #[test]
    fn keyframe_overlap_starts_at_the_single_runs_keyframe() {
        // Refresh every 50 frames (the age rule off): keyframes at 0, 50, 100, …
        let mut config = Config::default();
        config.reference.keyframe_every_s = 0.0;
        let p = config.reference_policies().get("A").clone();
        let times: Vec<i64> = (0..200).map(|i| i * 12_000_000_000).collect();
        assert_eq!(predicted_keyframes(&times, &p), vec![0, 50, 100, 150]);
        // Own frames from 120: at least 50 frames before (70), back to the keyframe at 50,
        // and to the one before it (0), through which the keyframe at 100 is reached too.
        assert_eq!(overlap_start(120, &p, &times, None), 0);
        assert_eq!(overlap_start(170, &p, &times, None), 50);
        // Own frames from 100 (a keyframe itself): reached from the keyframes at 50 and 0.
        assert_eq!(overlap_start(100, &p, &times, Some(1)), 0);
        assert_eq!(overlap_start(0, &p, &times, None), 0);
    }

    #[test]
    fn keyframes_by_age_follow_the_policy_rule() {
        let mut config = Config::default();
        config.reference.keyframe_every_frames = 0;
        config.reference.keyframe_every_s = 60.0;
        config.reference.keyframe_min_frames = 2;
        let p = config.reference_policies().get("A").clone();
        // 20 s cadence: age 60 s at frame 3 (on-reference 2 ≥ 2).
        let times: Vec<i64> = (0..10).map(|i| i * 20_000_000_000).collect();
        assert_eq!(predicted_keyframes(&times, &p), vec![0, 3, 6, 9]);
    }

    #[test]
    fn followers_measure_their_partner_frames_within_tolerance() {
        let mut all = frames("A", 40, 10);
        all.extend(frames("B", 40, 10));
        let mut config = Config::default();
        config.channels.insert(
            "B".into(),
            crate::config::ChannelConfig {
                policy: Some(PolicySpec::Channel("A".into())),
                tolerance_s: Some(15.0),
                ..Default::default()
            },
        );
        // Shard 1 of 2 owns B (frames 40..80 of the sorted list): it measures A too.
        let p = plan(&all, &[], &config, ShardSpec { index: 1, count: 2 }, None);
        assert!(p.owned.iter().all(|k| k.starts_with("B-")));
        assert!(p.measured.contains("A-0000.fits"));
        assert!(p.measured.contains("A-0039.fits"));
        assert!(!p.owned.contains("A-0000.fits"));
    }

    #[test]
    fn digests_change_with_the_inputs() {
        let all = frames("A", 5, 10);
        let mut sorted = all.clone();
        sorted.sort();
        let d = inputs_digest(&sorted, &[]);
        assert_eq!(d.len(), 64);
        assert_ne!(d, inputs_digest(&sorted[1..], &[]));
        assert_ne!(d, inputs_digest(&sorted, &["bad.fits".into()]));
    }
}
