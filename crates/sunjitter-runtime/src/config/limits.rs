//! The range of every configuration value and command-line flag, checked in one place before
//! any work.
//!
//! Each key has the range `examples/sunjitter.toml` states for it. A value outside it is
//! refused with one line naming the key, its value and the range (exit code 2): no setting
//! can make the pipeline allocate without bound, spin, overflow a duration or a time, or
//! fail every frame for a reason the configuration could have named.

use super::Config;
use crate::reference::{ChannelPolicy, PolicySpec};
use sunjitter_core::{Error, Result};

/// Longest name of a channel (topics are `/jitter/<channel>`).
pub const MAX_CHANNEL_NAME: usize = 64;

/// The configuration key of a field of a `Config` table: `AT.FIELD`, the field's Rust name,
/// which is its serde name (no field is renamed), so a key is named only by its field.
macro_rules! key {
    ($at:expr, $owner:ident . $field:ident) => {{
        let _ = &$owner.$field;
        format!("{}.{}", $at, stringify!($field))
    }};
}

/// The key of `Config`'s table `$table` (`engine`, `daemon`, …), checked to be its field.
macro_rules! table_key {
    ($table:ident) => {{
        let _ = |c: &Config| {
            let _ = &c.$table;
        };
        stringify!($table)
    }};
}

/// [`float`] on a field, by its key.
macro_rules! check_float {
    ($at:expr, $owner:ident . $field:ident $(as $t:ty)?, $($range:expr),+ $(,)?) => {
        float(&key!($at, $owner.$field), $owner.$field $(as $t)?, $($range),+)
    };
}

/// [`int`] on a field, by its key.
macro_rules! check_int {
    ($at:expr, $owner:ident . $field:ident $(as $t:ty)?, $($range:expr),+ $(,)?) => {
        int(&key!($at, $owner.$field), $owner.$field $(as $t)?, $($range),+)
    };
}

fn refuse(key: &str, value: impl std::fmt::Display, range: &str) -> Error {
    Error::Usage(format!(
        "configuration: {key} = {value} is out of range: {range}"
    ))
}

/// A float within `[lo, hi]` (`open_lo`: within `(lo, hi]`), finite.
fn float(key: &str, v: f64, lo: f64, hi: f64, open_lo: bool) -> Result<()> {
    let above = if open_lo { v > lo } else { v >= lo };
    if v.is_finite() && above && v <= hi {
        return Ok(());
    }
    let range = if open_lo {
        format!("a number > {lo} and ≤ {hi}")
    } else {
        format!("a number from {lo} to {hi}")
    };
    Err(refuse(key, v, &range))
}

/// An integer within `[lo, hi]`.
fn int(key: &str, v: u64, lo: u64, hi: u64) -> Result<()> {
    if (lo..=hi).contains(&v) {
        Ok(())
    } else {
        Err(refuse(key, v, &format!("an integer from {lo} to {hi}")))
    }
}

/// A command-line integer `--name` within `[lo, hi]` (exit 2 naming the flag otherwise).
pub fn flag_int(flag: &str, v: u64, lo: u64, hi: u64) -> Result<()> {
    if (lo..=hi).contains(&v) {
        Ok(())
    } else {
        Err(Error::Usage(format!(
            "{flag} {v} is out of range: an integer from {lo} to {hi}"
        )))
    }
}

/// A command-line number `--name` within `(lo, hi]` (`open_lo`) or `[lo, hi]`, finite.
pub fn flag_float(flag: &str, v: f64, lo: f64, hi: f64, open_lo: bool) -> Result<()> {
    float(flag, v, lo, hi, open_lo).map_err(|_| {
        let range = if open_lo {
            format!("a number > {lo} and ≤ {hi}")
        } else {
            format!("a number from {lo} to {hi}")
        };
        Error::Usage(format!("{flag} {v} is out of range: {range}"))
    })
}

/// Seconds as a wall-clock duration: from `lo` to 30 days.
const MAX_WAIT_S: f64 = 30.0 * 86_400.0;

/// A channel name as topics and configuration keys use it: 1 to 64 characters, letters,
/// digits, `_`, `-` and `.` (header-derived names are of this form).
pub fn check_channel_name(what: &str, name: &str) -> Result<()> {
    let ok = !name.is_empty()
        && name.len() <= MAX_CHANNEL_NAME
        && name
            .chars()
            .all(|c| c.is_ascii_alphanumeric() || matches!(c, '_' | '-' | '.'))
        && !matches!(name, "." | "..");
    if ok {
        Ok(())
    } else {
        Err(Error::Usage(format!(
            "configuration: {what} {:?} is not a channel name (1 to {MAX_CHANNEL_NAME} letters, digits, '_', '-', '.')",
            sunjitter_core::text::escape(name)
        )))
    }
}

/// Check every value of `config`; the first one out of range is the error.
pub fn check(config: &Config) -> Result<()> {
    engine(table_key!(engine), &config.engine)?;
    sink(table_key!(sink), &config.sink)?;
    daemon(table_key!(daemon), &config.daemon)?;
    policy(table_key!(reference), &config.reference)?;
    let policies = config.reference_policies();
    for (name, c) in &config.channels {
        let at = format!("{}.{name}", table_key!(channels));
        check_channel_name(&format!("[{}.NAME]", table_key!(channels)), name)?;
        if let Some(PolicySpec::Channel(partner)) = &c.policy {
            if partner == name {
                return Err(Error::Usage(format!(
                    "configuration: {} = \"channel:{name}\": a channel cannot follow itself; give it keyframe, previous or fixed:FILE, or another channel",
                    key!(at, c.policy)
                )));
            }
        }
        policy(&at, policies.get(name))?;
        if let Some(v) = c.scale_stability {
            float(
                &key!(at, c.scale_stability),
                v,
                0.0,
                MAX_SCALE_STABILITY,
                true,
            )?;
        }
        if let Some(v) = c.roll_stability_arcsec {
            float(
                &key!(at, c.roll_stability_arcsec),
                v,
                0.0,
                MAX_ROLL_ARCSEC,
                true,
            )?;
        }
        if let Some(v) = c.plate_scale_arcsec {
            float(&key!(at, c.plate_scale_arcsec), v, 1e-4, 1e4, false)?;
        }
    }
    let at = table_key!(channel_names);
    for (from, to) in &config.channel_names {
        check_channel_name(&format!("[{at}] key"), from)?;
        check_channel_name(&format!("{at}.{from} ="), to)?;
    }
    alerts(&config.alerts)?;
    let (at, health) = (table_key!(health), &config.health);
    check_float!(at, health.interval_s, 0.0, 3600.0, true)?;
    if health.status_file.contains('\0') {
        return Err(Error::Usage(format!(
            "configuration: {} contains a NUL byte",
            key!(at, health.status_file)
        )));
    }
    let (at, live) = (table_key!(live), &config.live);
    check_int!(at, live.queue as u64, 1, 1_000_000)?;
    check_int!(at, live.max_clients as u64, 1, 4096)?;
    Ok(())
}

fn engine(at: &str, e: &sunjitter_core::engine::EngineConfig) -> Result<()> {
    if let Some(v) = e.window_arcsec {
        float(&key!(at, e.window_arcsec), v, 0.0, 36_000.0, true)?;
    }
    if let Some(v) = e.window_px {
        int(&key!(at, e.window_px), v as u64, 3, 4095)?;
    }
    check_int!(at, e.min_window_px as u64, 3, 4095)?;
    check_float!(at, e.window_structure_lengths, 0.0, 1000.0, true,)?;
    check_float!(at, e.mask_radius_fraction, 0.0, 1.0, true,)?;
    check_int!(at, e.sample as u64, 2, 256)?;
    check_float!(at, e.ransac_threshold_px, 0.0, 1000.0, true,)?;
    check_int!(at, e.ransac_max_trials as u64, 1, 1_000_000,)?;
    if let Some(v) = e.pyramid_levels {
        int(&key!(at, e.pyramid_levels), v as u64, 1, 8)?;
    }
    check_int!(at, e.iterations as u64, 1, 100)?;
    check_int!(at, e.poly_n as u64, 3, 15)?;
    check_float!(at, e.poly_sigma, 0.0, 10.0, true)?;
    check_int!(at, e.max_passes as u64, 1, 32)?;
    check_float!(at, e.convergence_px, 0.0, 1.0, true)?;
    check_float!(at, e.hot_pixel_fraction as f64, 0.0, 1e6, false,)?;
    check_float!(at, e.systematic_floor_px, 0.0, 1.0, false,)?;
    check_float!(at, e.min_similarity, 0.0, 1.0, false)?;
    check_float!(at, e.min_correlation, 0.0, 1.0, false)?;
    check_float!(at, e.min_inlier_fraction, 0.0, 1.0, false)?;
    check_float!(at, e.refine_smoothing_px, 0.0, 16.0, false,)?;
    check_float!(at, e.refine_gradient_smoothing_px, 0.0, 16.0, false,)?;
    check_float!(at, e.scale_stability, 0.0, MAX_SCALE_STABILITY, true)?;
    check_float!(at, e.roll_stability_arcsec, 0.0, MAX_ROLL_ARCSEC, true)?;
    check_int!(at, e.seed_extent_px as u64, 1, 65_536)?;
    check_int!(at, e.final_extent_px as u64, 0, 65_536,)?;
    Ok(())
}

/// An instrument's stability: a relative plate scale above 0 and up to 10 %, a roll above 0
/// and up to 180°.
const MAX_SCALE_STABILITY: f64 = 0.1;
const MAX_ROLL_ARCSEC: f64 = 648_000.0;

fn sink(at: &str, s: &sunjitter_io::sink::SinkConfig) -> Result<()> {
    check_float!(at, s.segment_minutes, 0.0, 525_600.0, false,)?;
    check_int!(at, s.flush_every_frames as u64, 1, 1_000_000,)?;
    check_int!(at, s.chunk_size as u64, 1, 256 * 1024 * 1024)?;
    Ok(())
}

fn daemon(at: &str, d: &super::DaemonConfig) -> Result<()> {
    check_int!(at, d.queue_capacity as u64, 1, 1_000_000,)?;
    check_int!(at, d.readers as u64, 1, 256)?;
    check_int!(at, d.workers as u64, 1, 256)?;
    check_int!(at, d.reorder_window_frames as u64, 0, 100_000,)?;
    check_float!(at, d.reorder_window_s, 0.0, 86_400.0, false,)?;
    check_float!(at, d.settle_s, 0.0, 86_400.0, false)?;
    check_int!(at, d.retry_attempts as u64, 0, 1000,)?;
    check_float!(at, d.retry_initial_s, 0.001, 3600.0, false,)?;
    check_float!(at, d.retry_max_s, d.retry_initial_s, 86_400.0, false,)?;
    check_float!(at, d.incomplete_wait_s, 0.0, MAX_WAIT_S, false,)?;
    check_float!(at, d.rescan_interval_s, 0.0, MAX_WAIT_S, false,)?;
    check_float!(at, d.flush_interval_s, 0.0, 3600.0, true,)?;
    check_int!(at, d.max_frame_pixels as u64, 1, 1 << 32)?;
    check_int!(at, d.max_channels as u64, 1, 4096)?;
    for ext in &d.extensions {
        if ext.trim_start_matches('.').is_empty() || ext.contains(['/', '\0']) {
            return Err(refuse(
                &key!(at, d.extensions),
                format!("{:?}", sunjitter_core::text::escape(ext)),
                "file name endings such as \"fits\"",
            ));
        }
    }
    for pattern in &d.ignore {
        if pattern.is_empty() || pattern.contains(['/', '\0']) {
            return Err(refuse(
                &key!(at, d.ignore),
                format!("{:?}", sunjitter_core::text::escape(pattern)),
                "file name patterns such as \"*.tmp\"",
            ));
        }
    }
    Ok(())
}

fn policy(at: &str, p: &ChannelPolicy) -> Result<()> {
    check_float!(at, p.keyframe_every_s, 0.0, 1e9, false)?;
    check_float!(at, p.refresh_below_similarity, 0.0, 1.0, false)?;
    check_float!(at, p.tolerance_s, 0.0, 1e9, false)?;
    check_float!(at, p.hold_s, 0.0, MAX_WAIT_S, false)?;
    if let PolicySpec::Channel(partner) = &p.policy {
        check_channel_name(&format!("{} channel:", key!(at, p.policy)), partner)?;
    }
    Ok(())
}

pub(crate) fn alerts(a: &super::AlertsConfig) -> Result<()> {
    let at = table_key!(alerts);
    check_float!(at, a.command_timeout_s, 0.0, 86_400.0, true)?;
    if a.command.first().is_some_and(|c| c.is_empty()) {
        return Err(Error::Usage(format!(
            "configuration: {}: the program (its first element) is empty",
            key!(at, a.command)
        )));
    }
    thresholds(&key!(at, a.defaults), &a.defaults)?;
    let channels = key!(at, a.channels);
    for (name, t) in &a.channels {
        check_channel_name(&format!("[{channels}.NAME]"), name)?;
        thresholds(&format!("{channels}.{name}"), t)?;
    }
    Ok(())
}

/// An optional threshold above 0, by its key.
macro_rules! check_threshold {
    ($at:expr, $t:ident . $field:ident, $lo:expr, $hi:expr) => {
        if let Some(v) = $t.$field {
            check_value(&key!($at, $t.$field), v, $lo, $hi)?;
        }
    };
}

/// A threshold's value: a number within `(lo, hi]`, or an integer within `[lo, hi]`.
trait ThresholdValue: Copy {
    fn check(self, key: &str, lo: f64, hi: f64) -> Result<()>;
}

impl ThresholdValue for f64 {
    fn check(self, key: &str, lo: f64, hi: f64) -> Result<()> {
        float(key, self, lo, hi, true)
    }
}

impl ThresholdValue for u32 {
    fn check(self, key: &str, lo: f64, hi: f64) -> Result<()> {
        int(key, u64::from(self), lo as u64, hi as u64)
    }
}

impl ThresholdValue for usize {
    fn check(self, key: &str, lo: f64, hi: f64) -> Result<()> {
        int(key, self as u64, lo as u64, hi as u64)
    }
}

fn check_value(key: &str, v: impl ThresholdValue, lo: f64, hi: f64) -> Result<()> {
    v.check(key, lo, hi)
}

fn thresholds(at: &str, t: &super::Thresholds) -> Result<()> {
    check_threshold!(at, t.amplitude_px, 0.0, 1e9);
    check_threshold!(at, t.amplitude_arcsec, 0.0, 1e9);
    check_threshold!(at, t.rms_px, 0.0, 1e9);
    check_threshold!(at, t.rms_arcsec, 0.0, 1e9);
    check_threshold!(at, t.rms_window_frames, 2.0, 100_000.0);
    check_threshold!(at, t.jump_px, 0.0, 1e9);
    check_threshold!(at, t.jump_arcsec, 0.0, 1e9);
    check_threshold!(at, t.sigma_px, 0.0, 1e9);
    check_threshold!(at, t.header_sigmas, 0.0, 1e9);
    check_threshold!(at, t.closure_sigmas, 0.0, 1e9);
    check_threshold!(at, t.consecutive_bad, 1.0, 1_000_000.0);
    check_threshold!(at, t.consecutive_failed, 1.0, 1_000_000.0);
    check_threshold!(at, t.lag_s, 0.0, 1e9);
    check_threshold!(at, t.silence_s, 0.0, 1e9);
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn refused(toml: &str) -> String {
        let config = Config::from_toml(toml).expect("parses");
        let err = config.validate().expect_err(toml);
        assert_eq!(
            err.exit_code(),
            sunjitter_core::error::ExitCode::BadInput,
            "{toml}: {err}"
        );
        let text = err.to_string();
        assert!(!text.contains('\n'), "{text}");
        text
    }

    #[test]
    fn the_defaults_and_the_example_are_in_range() {
        Config::default().validate().unwrap();
        let text = include_str!("../../../../examples/sunjitter.toml");
        Config::from_toml(text).unwrap().validate().unwrap();
    }

    #[test]
    fn values_that_would_allocate_spin_or_panic_are_refused_naming_the_key() {
        for (toml, key) in [
            ("[engine]\nsample = 100000", "engine.sample"),
            (
                "[engine]\nrefine_smoothing_px = 1e308",
                "engine.refine_smoothing_px",
            ),
            (
                "[engine]\nrefine_smoothing_px = nan",
                "engine.refine_smoothing_px",
            ),
            ("[engine]\nmin_similarity = -1", "engine.min_similarity"),
            ("[engine]\nsample = 0", "engine.sample"),
            ("[engine]\npoly_sigma = 0", "engine.poly_sigma"),
            ("[engine]\nwindow_px = 100000", "engine.window_px"),
            ("[engine]\nconvergence_px = inf", "engine.convergence_px"),
            (
                "[sink]\nchunk_size = 18446744073709551615",
                "sink.chunk_size",
            ),
            ("[daemon]\nsettle_s = 1e300", "daemon.settle_s"),
            ("[daemon]\nqueue_capacity = 0", "daemon.queue_capacity"),
            ("[daemon]\nretry_max_s = 0.01", "daemon.retry_max_s"),
            ("[health]\ninterval_s = 1e308", "health.interval_s"),
            ("[reference]\nhold_s = 1e300", "reference.hold_s"),
            ("[channels.A]\ntolerance_s = -1", "channels.A.tolerance_s"),
            (
                "[alerts]\ncommand_timeout_s = 1e300",
                "alerts.command_timeout_s",
            ),
            ("[live]\nmax_clients = 100000", "live.max_clients"),
        ] {
            let text = refused(toml);
            assert!(text.contains(key), "{toml}: {text}");
        }
    }

    #[test]
    fn channel_names_are_names_and_no_channel_follows_itself() {
        for toml in [
            "[channel_names]\nAIA_171 = \"\"",
            "[channel_names]\nAIA_171 = \"a/b\"",
            "[channel_names]\nAIA_171 = \"x\\ny\"",
            "[channel_names]\n\"\" = \"X\"",
        ] {
            assert!(refused(toml).contains("channel name"), "{toml}");
        }
        let text = refused("[channels.A]\npolicy = \"channel:A\"");
        assert!(text.contains("cannot follow itself"), "{text}");
        let ok = Config::from_toml("[channel_names]\nAIA_171 = \"EUV-171.a\"").unwrap();
        ok.validate().unwrap();
    }
}
