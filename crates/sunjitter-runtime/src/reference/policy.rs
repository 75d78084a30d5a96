//! Reference policies as written in the configuration or on the command line, a channel's
//! policy with its settings, and every channel's settings resolved once for a run.

use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::fmt;
use std::str::FromStr;
use sunjitter_core::error::Error;
use sunjitter_core::record::ReferenceKind;

/// A reference policy as written in the configuration or on the command line.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum PolicySpec {
    /// Each frame aligned to the previous (good) frame of its channel.
    Previous,
    /// A keyframe refreshed every N frames / T seconds / when the match degrades.
    Keyframe,
    /// One fixed image (`FILE` or `FILE[N]` for frame N of a cube).
    Fixed(String),
    /// The nearest-in-time frame of another channel.
    Channel(String),
}

impl PolicySpec {
    /// The `reference_kind` written in messages for frames aligned under this policy.
    pub fn kind(&self) -> ReferenceKind {
        match self {
            PolicySpec::Previous => ReferenceKind::Previous,
            PolicySpec::Keyframe => ReferenceKind::Keyframe,
            PolicySpec::Fixed(_) => ReferenceKind::Fixed,
            PolicySpec::Channel(_) => ReferenceKind::Channel,
        }
    }
}

impl FromStr for PolicySpec {
    type Err = sunjitter_core::Error;
    fn from_str(s: &str) -> sunjitter_core::Result<Self> {
        let bad = || {
            sunjitter_core::Error::Usage(format!(
                "reference policy `{s}`: expected previous, keyframe, fixed:FILE or channel:NAME"
            ))
        };
        match s.trim() {
            "previous" => Ok(PolicySpec::Previous),
            "keyframe" => Ok(PolicySpec::Keyframe),
            other => match other.split_once(':') {
                Some(("fixed", file)) if !file.is_empty() => Ok(PolicySpec::Fixed(file.into())),
                Some(("channel", name)) if !name.is_empty() => Ok(PolicySpec::Channel(name.into())),
                _ => Err(bad()),
            },
        }
    }
}

impl fmt::Display for PolicySpec {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            PolicySpec::Previous => f.write_str("previous"),
            PolicySpec::Keyframe => f.write_str("keyframe"),
            PolicySpec::Fixed(file) => write!(f, "fixed:{file}"),
            PolicySpec::Channel(name) => write!(f, "channel:{name}"),
        }
    }
}

impl Serialize for PolicySpec {
    fn serialize<S: serde::Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        s.collect_str(self)
    }
}

impl<'de> Deserialize<'de> for PolicySpec {
    fn deserialize<D: serde::Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        let s = String::deserialize(d)?;
        s.parse().map_err(serde::de::Error::custom)
    }
}

/// A channel's reference settings: the `[reference]` table of the configuration (every
/// channel's defaults), and the settings one channel resolves to with its own overrides
/// ([`ReferencePolicies`]).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct ChannelPolicy {
    /// `keyframe`, `previous`, `fixed:FILE` (or `fixed:FILE[N]`) or `channel:NAME`.
    pub policy: PolicySpec,
    /// Keyframe: refresh after this many frames aligned to it (0 = never by count).
    pub keyframe_every_frames: u32,
    /// Keyframe: refresh when the frame is this much later than the keyframe (0 = never).
    pub keyframe_every_s: f64,
    /// Keyframe: frames a keyframe serves before its age can refresh it, so that at a
    /// cadence sparser than `keyframe_every_s` frames are still measured against a keyframe.
    pub keyframe_min_frames: u32,
    /// Keyframe: a match with a similarity below this counts as degraded (0 = engine status only).
    pub refresh_below_similarity: f64,
    /// After this many consecutive failed frames the next frame starts a new chain.
    pub restart_after_failures: u32,
    /// `channel:NAME`: largest |Δt| between a frame and its partner.
    pub tolerance_s: f64,
    /// `channel:NAME`: how long (wall clock, daemon only) a frame waits for a partner.
    pub hold_s: f64,
}

/// Why a keyframe is due by the policy's count and age rules.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum KeyframeDue {
    /// `keyframe_every_frames` frames were measured against it.
    Count,
    /// The frame is `keyframe_every_s` later, after `keyframe_min_frames` frames.
    Age,
}

impl ChannelPolicy {
    /// Whether the frame that comes `age_s` after the keyframe, `on_reference` frames having
    /// been measured against it, is due to become the next keyframe: the one rule of the
    /// pipeline and of the shards' prediction of it.
    pub fn keyframe_due(&self, on_reference: u32, age_s: f64) -> Option<KeyframeDue> {
        let due_count =
            self.keyframe_every_frames > 0 && on_reference + 1 >= self.keyframe_every_frames;
        let due_time = self.keyframe_every_s > 0.0
            && age_s >= self.keyframe_every_s
            && on_reference >= self.keyframe_min_frames;
        if due_count {
            Some(KeyframeDue::Count)
        } else if due_time {
            Some(KeyframeDue::Age)
        } else {
            None
        }
    }
}

impl Default for ChannelPolicy {
    fn default() -> Self {
        ChannelPolicy {
            policy: PolicySpec::Keyframe,
            keyframe_every_frames: 50,
            keyframe_every_s: 600.0,
            keyframe_min_frames: 4,
            refresh_below_similarity: 0.0,
            restart_after_failures: 5,
            tolerance_s: 30.0,
            hold_s: 120.0,
        }
    }
}

/// Every channel's reference settings, resolved once from the configuration
/// (`Config::reference_policies`): the channels `[channels.NAME]` sets, and `[reference]` for
/// any other channel a run meets.
#[derive(Debug, Clone, PartialEq)]
pub struct ReferencePolicies {
    default: ChannelPolicy,
    channels: BTreeMap<String, ChannelPolicy>,
}

impl ReferencePolicies {
    /// `default` for channels not in `channels`. A channel told to follow itself (`--reference
    /// channel:X` reaches X too) takes `keyframe`.
    pub fn new(default: ChannelPolicy, mut channels: BTreeMap<String, ChannelPolicy>) -> Self {
        if let PolicySpec::Channel(partner) = &default.policy {
            if !channels.contains_key(partner) {
                channels.insert(partner.clone(), default.clone());
            }
        }
        for (name, p) in channels.iter_mut() {
            if matches!(&p.policy, PolicySpec::Channel(partner) if partner == name) {
                p.policy = PolicySpec::Keyframe;
            }
        }
        ReferencePolicies { default, channels }
    }

    /// The settings of `channel`.
    pub fn get(&self, channel: &str) -> &ChannelPolicy {
        self.channels.get(channel).unwrap_or(&self.default)
    }

    /// Follow `channel:NAME` links from `channel`; a cycle would make frames wait forever.
    pub fn partner_chain(&self, channel: &str) -> sunjitter_core::Result<Vec<String>> {
        let mut seen = vec![channel.to_string()];
        let mut current = channel.to_string();
        while let PolicySpec::Channel(next) = self.get(&current).policy.clone() {
            if seen.contains(&next) {
                seen.push(next);
                return Err(Error::Usage(format!(
                    "configuration: channel references form a cycle: {}",
                    seen.join(" → ")
                )));
            }
            seen.push(next.clone());
            current = next;
        }
        Ok(seen)
    }

    /// Whether `channel`'s policy follows `partner` (`channel:PARTNER`).
    pub fn follows(&self, channel: &str, partner: &str) -> bool {
        matches!(&self.get(channel).policy, PolicySpec::Channel(p) if p == partner)
    }
}
