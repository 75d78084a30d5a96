//! The configuration file (`--config FILE.toml`): engine, sink, daemon and reference settings.
//!
//! Every field has a default that works for AIA-like full-disk data; `examples/sunjitter.toml`
//! documents them all. Command-line flags override the file ([`Overrides`]). The effective
//! configuration serialises to JSON for the MCAP `sunjitter` metadata record.

use crate::reference::{ChannelPolicy, PolicySpec, ReferencePolicies};
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::path::Path;
use sunjitter_core::engine::EngineConfig;
use sunjitter_core::{Error, Result};
pub use sunjitter_io::sink::SinkConfig;

pub mod limits;

/// The whole configuration.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, Default)]
#[serde(default, deny_unknown_fields)]
pub struct Config {
    pub engine: EngineConfig,
    pub sink: SinkConfig,
    pub daemon: DaemonConfig,
    /// Reference settings for every channel not listed in `channels`.
    pub reference: ChannelPolicy,
    /// Per-channel overrides of `reference`, keyed by channel name (e.g. `SJI_2796`).
    pub channels: BTreeMap<String, ChannelConfig>,
    /// Rename channels: header-derived name → name used in topics (e.g. `AIA_304 = "EUV_304"`).
    pub channel_names: BTreeMap<String, String>,
    /// Alert thresholds and the alert command (`watch`).
    pub alerts: AlertsConfig,
    /// The health status file (`watch`).
    pub health: HealthConfig,
    /// The live view (`watch --live`).
    pub live: LiveConfig,
}

/// How files are found and taken, and how much runs at once.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct DaemonConfig {
    /// Watch (and replay) subdirectories too.
    pub recursive: bool,
    /// Follow symbolic links found in watched directories.
    pub follow_symlinks: bool,
    /// File name endings taken as frames (case-insensitive); empty = every file.
    pub extensions: Vec<String>,
    /// File name patterns never taken (`*`, `?`, `[...]`): temporary and hidden names.
    pub ignore: Vec<String>,
    /// Capacity of the bounded queues between watcher, readers and the scheduler.
    pub queue_capacity: usize,
    /// Files opened and checked at once.
    pub readers: usize,
    /// Frames aligned at once (at most one per channel; the engine itself is parallel).
    pub workers: usize,
    /// Per channel, frames held to restore observation-time order.
    pub reorder_window_frames: usize,
    /// Per channel, longest time a frame is held for reordering (seconds, wall clock).
    pub reorder_window_s: f64,
    /// A file found by a directory scan is taken only once unmodified for this long.
    pub settle_s: f64,
    /// Attempts to open a file as complete FITS before it is reported on `/log` (an
    /// incomplete one with a warning, then waited for; any other unreadable one as failed).
    pub retry_attempts: u32,
    /// First retry delay; it doubles up to `retry_max_s`.
    pub retry_initial_s: f64,
    pub retry_max_s: f64,
    /// A file that ends early (a writer stalled half-way) is waited for until it has been
    /// unchanged this long; then it is reported as failed (truncated).
    pub incomplete_wait_s: f64,
    /// Rescan the watched directories this often as a safety net (0 = only on watcher errors).
    pub rescan_interval_s: f64,
    /// When idle, flush the log (and rotate segments by time) at least this often.
    pub flush_interval_s: f64,
    /// Pixels one image (one frame of a cube) may have; larger ones are refused on `/log`
    /// before anything is allocated.
    pub max_frame_pixels: u64,
    /// Channels tracked at once; frames of further channels are named on `/log`, not measured.
    pub max_channels: usize,
}

impl Default for DaemonConfig {
    fn default() -> Self {
        DaemonConfig {
            recursive: false,
            follow_symlinks: false,
            extensions: vec![
                "fits".into(),
                "fit".into(),
                "fts".into(),
                "fits.fz".into(),
                "fits.gz".into(),
            ],
            ignore: vec![".*".into(), "*.tmp".into(), "*.part".into()],
            queue_capacity: 256,
            readers: 2,
            workers: 2,
            reorder_window_frames: 8,
            reorder_window_s: 5.0,
            settle_s: 1.0,
            retry_attempts: 6,
            retry_initial_s: 0.25,
            retry_max_s: 8.0,
            incomplete_wait_s: 300.0,
            rescan_interval_s: 300.0,
            flush_interval_s: 5.0,
            max_frame_pixels: sunjitter_io::fits::DEFAULT_MAX_FRAME_PIXELS,
            max_channels: 64,
        }
    }
}

/// Per-channel overrides; unset fields fall back to `[reference]`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, Default)]
#[serde(default, deny_unknown_fields)]
pub struct ChannelConfig {
    pub policy: Option<PolicySpec>,
    pub keyframe_every_frames: Option<u32>,
    pub keyframe_every_s: Option<f64>,
    pub keyframe_min_frames: Option<u32>,
    pub refresh_below_similarity: Option<f64>,
    pub restart_after_failures: Option<u32>,
    pub tolerance_s: Option<f64>,
    pub hold_s: Option<f64>,
    /// The Sun's rotation profile for this channel (else `[engine] solar_rotation`).
    pub solar_rotation: Option<sunjitter_core::solar_rotation::Profile>,
    /// The model fitted and the instrument's stability for this channel (else `[engine]`'s).
    pub model: Option<sunjitter_core::engine::ModelChoice>,
    pub scale_stability: Option<f64>,
    pub roll_stability_arcsec: Option<f64>,
    /// The channel's true plate scale (arcsec/px) where its headers state another (binned
    /// data whose `CDELTi` were left at the native pixel); used in place of the header's.
    pub plate_scale_arcsec: Option<f64>,
}

impl ChannelConfig {
    /// The reference settings this channel sets, over the defaults `r`.
    fn policy_over(&self, r: &ChannelPolicy) -> ChannelPolicy {
        ChannelPolicy {
            policy: self.policy.clone().unwrap_or_else(|| r.policy.clone()),
            keyframe_every_frames: self
                .keyframe_every_frames
                .unwrap_or(r.keyframe_every_frames),
            keyframe_every_s: self.keyframe_every_s.unwrap_or(r.keyframe_every_s),
            keyframe_min_frames: self.keyframe_min_frames.unwrap_or(r.keyframe_min_frames),
            refresh_below_similarity: self
                .refresh_below_similarity
                .unwrap_or(r.refresh_below_similarity),
            restart_after_failures: self
                .restart_after_failures
                .unwrap_or(r.restart_after_failures),
            tolerance_s: self.tolerance_s.unwrap_or(r.tolerance_s),
            hold_s: self.hold_s.unwrap_or(r.hold_s),
        }
    }
}

/// Command-line settings that override the file.
#[derive(Debug, Clone, Default)]
pub struct Overrides {
    /// `--reference POLICY`: the policy of every channel.
    pub reference: Option<PolicySpec>,
    /// `--recursive`.
    pub recursive: bool,
}

/// Largest configuration file read.
const MAX_CONFIG_BYTES: u64 = 1 << 20;

impl Config {
    /// Read `path` (or the defaults when `None`), apply `overrides`, check the result.
    pub fn load(path: Option<&Path>, overrides: &Overrides) -> Result<Config> {
        let mut config = match path {
            Some(path) => {
                let text =
                    sunjitter_io::input::read_text(path, MAX_CONFIG_BYTES, "configuration file")?;
                Config::from_toml(&text).map_err(|e| Error::bad_input(path, e))?
            }
            None => Config::default(),
        };
        config.apply(overrides);
        config.validate()?;
        Ok(config)
    }

    /// Parse TOML text; the error is one line.
    pub fn from_toml(text: &str) -> std::result::Result<Config, String> {
        toml::from_str(text).map_err(|e| e.message().replace('\n', " "))
    }

    pub fn apply(&mut self, overrides: &Overrides) {
        if let Some(policy) = &overrides.reference {
            self.reference.policy = policy.clone();
            for channel in self.channels.values_mut() {
                channel.policy = None;
            }
        }
        if overrides.recursive {
            self.daemon.recursive = true;
        }
    }

    /// Reject settings that cannot work (exit code 2, one line naming the field): every value
    /// against its range ([`limits`]), channel references that form a cycle, live
    /// origins that are not origins.
    pub fn validate(&self) -> Result<()> {
        limits::check(self)?;
        let policies = self.reference_policies();
        for name in self.channels.keys() {
            policies.partner_chain(name)?;
        }
        self.live.validate()?;
        Ok(())
    }

    /// The channel name used in topics for a header-derived name.
    pub fn channel_name(&self, header_channel: &str) -> String {
        self.channel_names
            .get(header_channel)
            .cloned()
            .unwrap_or_else(|| header_channel.to_string())
    }

    /// Every channel's reference settings: `[channels.NAME]` over `[reference]`, resolved
    /// once (a run holds the result).
    pub fn reference_policies(&self) -> ReferencePolicies {
        let channels = self
            .channels
            .iter()
            .map(|(name, c)| (name.clone(), c.policy_over(&self.reference)))
            .collect();
        ReferencePolicies::new(self.reference.clone(), channels)
    }

    /// The engine settings of each channel that sets any of its own, by topic name.
    pub fn channel_settings(
        &self,
    ) -> std::collections::BTreeMap<String, sunjitter_core::engine::ChannelSettings> {
        let base = self.engine.channel_settings();
        self.channels
            .iter()
            .filter(|(_, c)| {
                c.solar_rotation.is_some()
                    || c.model.is_some()
                    || c.scale_stability.is_some()
                    || c.roll_stability_arcsec.is_some()
            })
            .map(|(name, c)| {
                let mut s = base;
                s.solar_rotation = c.solar_rotation.unwrap_or(s.solar_rotation);
                s.model.model = c.model.unwrap_or(s.model.model);
                s.model.scale_stability = c.scale_stability.unwrap_or(s.model.scale_stability);
                s.model.roll_stability_arcsec = c
                    .roll_stability_arcsec
                    .unwrap_or(s.model.roll_stability_arcsec);
                (name.clone(), s)
            })
            .collect()
    }

    /// `[channels.X] plate_scale_arcsec`, by channel (topic) name.
    pub fn channel_plate_scales(&self) -> BTreeMap<String, f64> {
        self.channels
            .iter()
            .filter_map(|(name, c)| Some((name.clone(), c.plate_scale_arcsec?)))
            .collect()
    }

    /// The plate scales `[channels.X] plate_scale_arcsec` gives, by the channel name headers
    /// give (`[channel_names]` undone), for the reader.
    pub fn plate_scales(&self) -> sunjitter_io::fits::PlateScales {
        let mut by_header = BTreeMap::new();
        for (name, v) in self.channel_plate_scales() {
            if !self.channel_names.contains_key(&name) {
                by_header.insert(name.clone(), v);
            }
            for (header, topic) in &self.channel_names {
                if *topic == name {
                    by_header.insert(header.clone(), v);
                }
            }
        }
        sunjitter_io::fits::PlateScales(by_header)
    }

    /// The effective configuration as JSON (for the MCAP metadata record).
    pub fn to_json(&self) -> serde_json::Value {
        serde_json::to_value(self).unwrap_or(serde_json::Value::Null)
    }

    /// The files `fixed:` policies name (the cube itself for `fixed:FILE[N]`): inputs that no
    /// output may overwrite.
    pub fn reference_files(&self) -> Vec<std::path::PathBuf> {
        std::iter::once(&self.reference.policy)
            .chain(self.channels.values().filter_map(|c| c.policy.as_ref()))
            .filter_map(|p| match p {
                PolicySpec::Fixed(file) => Some(sunjitter_io::fits::parse_frame_key(file).path),
                _ => None,
            })
            .collect()
    }

    /// Make `fixed:FILE` paths absolute and canonical, so they match frame keys in logs.
    pub fn canonicalize_fixed_paths(&mut self) -> Result<()> {
        let fix = |p: &mut PolicySpec| -> Result<()> {
            if let PolicySpec::Fixed(file) = p {
                let spec = sunjitter_io::fits::parse_frame_key(file);
                let path = canonical_file_path(&spec.path)?;
                *file = sunjitter_io::fits::frame_key(&path, spec.frame);
            }
            Ok(())
        };
        fix(&mut self.reference.policy)?;
        for c in self.channels.values_mut() {
            if let Some(p) = c.policy.as_mut() {
                fix(p)?;
            }
        }
        Ok(())
    }
}

/// What a record's message says when the frame's or the reference's plate scale came from
/// the configuration (`given`, by topic name) rather than its header; channels as headers name
/// them, `names` the `[channel_names]` renames.
pub fn plate_scale_note(
    given: &BTreeMap<String, f64>,
    names: &BTreeMap<String, String>,
    reference_channel: &str,
    frame_channel: &str,
) -> Option<String> {
    let mut said: Vec<String> = Vec::new();
    for channel in [frame_channel, reference_channel] {
        let name = names.get(channel).map_or(channel, String::as_str);
        if let Some(v) = given.get(name) {
            let text = format!("{v}″/px for {name}");
            if !said.contains(&text) {
                said.push(text);
            }
        }
    }
    (!said.is_empty()).then(|| {
        format!(
            "plate scale from the configuration, not the header: {} (plate_scale_arcsec)",
            said.join(", ")
        )
    })
}

/// `path` with its directory made canonical (the file name itself is kept, so a symbolic
/// link keeps its own name): the identity of a file in logs.
pub fn canonical_file_path(path: &Path) -> Result<std::path::PathBuf> {
    let name = path
        .file_name()
        .ok_or_else(|| Error::bad_input(path, "not a file path"))?;
    let parent = match path.parent() {
        Some(p) if !p.as_os_str().is_empty() => p.to_path_buf(),
        _ => std::path::PathBuf::from("."),
    };
    let parent = parent.canonicalize().map_err(|e| Error::io(&parent, e))?;
    Ok(parent.join(name))
}

// ---------------------------------------------------------------------------------------------
// Monitoring: [alerts], [health], [live]

/// `[alerts]` in the configuration file.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct AlertsConfig {
    /// Program and arguments run for every alert event with the alert JSON on stdin
    /// (empty: none). Runs off the pipeline, one at a time, in its own process group; killed
    /// with the whole group after `command_timeout_s`.
    pub command: Vec<String>,
    pub command_timeout_s: f64,
    /// Thresholds for every channel.
    pub defaults: Thresholds,
    /// Per-channel thresholds; unset fields fall back to `defaults`.
    pub channels: BTreeMap<String, Thresholds>,
}

impl Default for AlertsConfig {
    fn default() -> Self {
        AlertsConfig {
            command: Vec::new(),
            command_timeout_s: 10.0,
            defaults: Thresholds::default(),
            channels: BTreeMap::new(),
        }
    }
}

/// Alert thresholds; an unset one is off. Values above a threshold raise its alert.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct Thresholds {
    pub amplitude_px: Option<f64>,
    pub amplitude_arcsec: Option<f64>,
    pub rms_px: Option<f64>,
    pub rms_arcsec: Option<f64>,
    /// Frames in the RMS window (default 20).
    pub rms_window_frames: Option<usize>,
    pub jump_px: Option<f64>,
    pub jump_arcsec: Option<f64>,
    pub sigma_px: Option<f64>,
    /// A frame's fitted scale or roll this many σ from what its headers say (a telescope's
    /// plate scale and roll hold: a change is the instrument's, or structure evolving).
    pub header_sigmas: Option<f64>,
    /// A keyframe reached two ways whose two chains are this many σ apart in any parameter
    /// (`/reference` `closure`): the channel's σ do not hold.
    pub closure_sigmas: Option<f64>,
    /// Raised when this many frames in a row are failed or degraded.
    pub consecutive_bad: Option<u32>,
    /// Raised when this many frames in a row are failed (no result at all).
    pub consecutive_failed: Option<u32>,
    pub lag_s: Option<f64>,
    pub silence_s: Option<f64>,
}

/// Frames in an RMS window when `rms_window_frames` is unset.
pub const DEFAULT_RMS_WINDOW: usize = 20;

impl Thresholds {
    /// `self` with unset fields taken from `fallback`.
    pub fn or(&self, fallback: &Thresholds) -> Thresholds {
        Thresholds {
            amplitude_px: self.amplitude_px.or(fallback.amplitude_px),
            amplitude_arcsec: self.amplitude_arcsec.or(fallback.amplitude_arcsec),
            rms_px: self.rms_px.or(fallback.rms_px),
            rms_arcsec: self.rms_arcsec.or(fallback.rms_arcsec),
            rms_window_frames: self.rms_window_frames.or(fallback.rms_window_frames),
            jump_px: self.jump_px.or(fallback.jump_px),
            jump_arcsec: self.jump_arcsec.or(fallback.jump_arcsec),
            sigma_px: self.sigma_px.or(fallback.sigma_px),
            header_sigmas: self.header_sigmas.or(fallback.header_sigmas),
            closure_sigmas: self.closure_sigmas.or(fallback.closure_sigmas),
            consecutive_bad: self.consecutive_bad.or(fallback.consecutive_bad),
            consecutive_failed: self.consecutive_failed.or(fallback.consecutive_failed),
            lag_s: self.lag_s.or(fallback.lag_s),
            silence_s: self.silence_s.or(fallback.silence_s),
        }
    }
}

impl AlertsConfig {
    /// The ranges of `[alerts]` ([`limits`]).
    pub fn validate(&self) -> Result<()> {
        limits::alerts(self)
    }

    /// The thresholds in force for a channel.
    pub fn thresholds(&self, channel: &str) -> Thresholds {
        match self.channels.get(channel) {
            Some(t) => t.or(&self.defaults),
            None => self.defaults.clone(),
        }
    }
}

/// `[health]` in the configuration file.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct HealthConfig {
    /// Where the status file goes; empty: `status.json` in the output directory.
    pub status_file: String,
    /// Seconds between rewrites of the status file.
    pub interval_s: f64,
}

impl Default for HealthConfig {
    fn default() -> Self {
        HealthConfig {
            status_file: String::new(),
            interval_s: 2.0,
        }
    }
}

/// `[live]` in the configuration file.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct LiveConfig {
    /// Messages waiting for the live view at most; more are dropped for the live view only.
    pub queue: usize,
    /// Clients connected at once at most; more connections are refused (HTTP 503).
    pub max_clients: usize,
    /// Web origins (`https://host[:port]`) whose pages may connect. A handshake with another
    /// `Origin` is refused (HTTP 403); one without (not a browser) is allowed.
    pub allowed_origins: Vec<String>,
}

impl Default for LiveConfig {
    fn default() -> Self {
        LiveConfig {
            queue: 1024,
            max_clients: 32,
            allowed_origins: Vec::new(),
        }
    }
}

impl LiveConfig {
    /// Origins are origins (the numbers are checked with the rest, [`crate::limits`]).
    pub fn validate(&self) -> Result<()> {
        let bad = |m: String| Err(Error::Usage(format!("configuration: {m}")));
        for origin in &self.allowed_origins {
            if !is_origin(origin) {
                return bad(format!(
                    "live.allowed_origins: {origin:?} is not an origin \
                     (scheme://host[:port], e.g. \"https://app.foxglove.dev\")"
                ));
            }
        }
        Ok(())
    }
}

/// `scheme://host[:port]` and nothing after it (a path would never match). Not `null`: any
/// sandboxed page sends that.
fn is_origin(text: &str) -> bool {
    let Some((scheme, rest)) = text.split_once("://") else {
        return false;
    };
    let host = rest.strip_suffix('/').unwrap_or(rest);
    let web = matches!(scheme, "http" | "https");
    scheme.starts_with(|c: char| c.is_ascii_alphabetic())
        && scheme
            .chars()
            .all(|c| c.is_ascii_alphanumeric() || "+-.".contains(c))
        && !(web && host.is_empty())
        && !host.contains(['/', '?', '#', ' ', '*'])
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn example_file_parses_to_the_defaults() {
        // The documented example must stay in step with the defaults it describes.
        let text = include_str!("../../../examples/sunjitter.toml");
        let parsed = Config::from_toml(text).expect("example parses");
        let mut expected = Config::default();
        expected.channels.insert(
            "SJI_2796".into(),
            ChannelConfig {
                policy: Some(PolicySpec::Channel("SJI_1400".into())),
                tolerance_s: Some(150.0),
                ..Default::default()
            },
        );
        assert_eq!(parsed, expected);
    }

    #[test]
    fn channel_overrides_fall_back_to_reference_defaults() {
        let config = Config::from_toml(
            r#"
            [reference]
            policy = "previous"
            hold_s = 10
            [channels.B]
            policy = "channel:A"
            tolerance_s = 2.5
            "#,
        )
        .unwrap();
        let b = config.reference_policies().get("B").clone();
        assert_eq!(b.policy, PolicySpec::Channel("A".into()));
        assert_eq!((b.tolerance_s, b.hold_s), (2.5, 10.0));
        assert_eq!(
            config.reference_policies().get("A").policy,
            PolicySpec::Previous
        );
    }

    #[test]
    fn command_line_policy_overrides_every_channel_and_not_itself() {
        let mut config = Config::from_toml("[channels.B]\npolicy = \"previous\"").unwrap();
        config.apply(&Overrides {
            reference: Some(PolicySpec::Channel("A".into())),
            recursive: true,
        });
        assert_eq!(
            config.reference_policies().get("B").policy,
            PolicySpec::Channel("A".into())
        );
        // A cannot follow itself: it keeps a keyframe series the others follow.
        assert_eq!(
            config.reference_policies().get("A").policy,
            PolicySpec::Keyframe
        );
        assert!(config.daemon.recursive);
        config.validate().unwrap();
    }

    #[test]
    fn cycles_unknown_fields_and_bad_policies_are_usage_errors() {
        let cyclic = Config::from_toml(
            "[channels.A]\npolicy = \"channel:B\"\n[channels.B]\npolicy = \"channel:A\"",
        )
        .unwrap();
        let err = cyclic.validate().unwrap_err();
        assert_eq!(err.exit_code(), sunjitter_core::error::ExitCode::BadInput);
        assert!(err.to_string().contains("cycle"), "{err}");

        let typo = Config::from_toml("[daemon]\nworkerz = 3").unwrap_err();
        assert!(typo.contains("workerz"), "{typo}");
        let policy = Config::from_toml("[reference]\npolicy = \"sometimes\"").unwrap_err();
        assert!(policy.contains("sometimes"), "{policy}");
    }

    #[test]
    fn a_channels_plate_scale_is_checked_and_found_under_its_header_name() {
        let config = Config::from_toml(
            "[channel_names]\nAIA_304 = \"EUV_304\"\n\
             [channels.SJI_1400]\nplate_scale_arcsec = 1.6635\n\
             [channels.EUV_304]\nplate_scale_arcsec = 0.6",
        )
        .unwrap();
        config.validate().unwrap();
        let scales = config.plate_scales().0;
        assert_eq!(scales.get("SJI_1400"), Some(&1.6635));
        assert_eq!(scales.get("AIA_304"), Some(&0.6));
        // A header naming EUV_304 itself (not renamed) is that channel too.
        assert_eq!(scales.get("EUV_304"), Some(&0.6));
        assert_eq!(scales.len(), 3);
        for bad in ["0", "-1.5", "nan", "1e9"] {
            let err = Config::from_toml(&format!("[channels.X]\nplate_scale_arcsec = {bad}"))
                .unwrap()
                .validate()
                .unwrap_err();
            assert_eq!(err.exit_code(), sunjitter_core::error::ExitCode::BadInput);
            assert!(
                err.to_string().contains("channels.X.plate_scale_arcsec"),
                "{err}"
            );
        }
    }

    #[test]
    fn live_origins_are_origins_and_the_client_cap_is_positive() {
        let live = |text: &str| {
            Config::from_toml(&format!("[live]\n{text}"))
                .unwrap()
                .validate()
        };
        assert!(live(
            "allowed_origins = [\"https://app.foxglove.dev\", \"http://localhost:8080/\"]"
        )
        .is_ok());
        assert!(live("allowed_origins = [\"file://\", \"app://foxglove\"]").is_ok());
        for bad in [
            "app.foxglove.dev",
            "https://app.foxglove.dev/studio",
            "*",
            "https://",
            "null",
        ] {
            let err = live(&format!("allowed_origins = [\"{bad}\"]")).unwrap_err();
            assert!(
                err.to_string().contains("live.allowed_origins"),
                "{bad}: {err}"
            );
        }
        let err = live("max_clients = 0").unwrap_err();
        assert!(err.to_string().contains("live.max_clients"), "{err}");
    }

    #[test]
    fn effective_configuration_round_trips_through_json() {
        let mut config = Config::default();
        config.channels.insert(
            "X".into(),
            ChannelConfig {
                policy: Some(PolicySpec::Fixed("/data/ref.fits[3]".into())),
                ..Default::default()
            },
        );
        let json = config.to_json();
        assert_eq!(json["reference"]["policy"], "keyframe");
        assert_eq!(json["channels"]["X"]["policy"], "fixed:/data/ref.fits[3]");
        let back: Config = serde_json::from_value(json).unwrap();
        assert_eq!(back, config);
    }
}
