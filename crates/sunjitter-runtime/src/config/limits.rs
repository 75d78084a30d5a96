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
    engine(&config.engine)?;
    sink(&config.sink)?;
    daemon(&config.daemon)?;
    policy("reference", &config.reference)?;
    let policies = config.reference_policies();
    for (name, c) in &config.channels {
        check_channel_name("[channels.NAME]", name)?;
        if let Some(PolicySpec::Channel(partner)) = &c.policy {
            if partner == name {
                return Err(Error::Usage(format!(
                    "configuration: channels.{name}.policy = \"channel:{name}\": a channel cannot follow itself; give it keyframe, previous or fixed:FILE, or another channel"
                )));
            }
        }
        policy(&format!("channels.{name}"), policies.get(name))?;
        stability(
            &format!("channels.{name}"),
            c.scale_stability,
            c.roll_stability_arcsec,
        )?;
        if let Some(v) = c.plate_scale_arcsec {
            float(
                &format!("channels.{name}.plate_scale_arcsec"),
                v,
                1e-4,
                1e4,
                false,
            )?;
        }
    }
    for (from, to) in &config.channel_names {
        check_channel_name("[channel_names] key", from)?;
        check_channel_name(&format!("channel_names.{from} ="), to)?;
    }
    alerts(&config.alerts)?;
    float(
        "health.interval_s",
        config.health.interval_s,
        0.0,
        3600.0,
        true,
    )?;
    if config.health.status_file.contains('\0') {
        return Err(Error::Usage(
            "configuration: health.status_file contains a NUL byte".into(),
        ));
    }
    int("live.queue", config.live.queue as u64, 1, 1_000_000)?;
    int("live.max_clients", config.live.max_clients as u64, 1, 4096)?;
    Ok(())
}

fn engine(e: &sunjitter_core::engine::EngineConfig) -> Result<()> {
    if let Some(v) = e.window_arcsec {
        float("engine.window_arcsec", v, 0.0, 36_000.0, true)?;
    }
    if let Some(v) = e.window_px {
        int("engine.window_px", v as u64, 3, 4095)?;
    }
    int("engine.min_window_px", e.min_window_px as u64, 3, 4095)?;
    float(
        "engine.window_structure_lengths",
        e.window_structure_lengths,
        0.0,
        1000.0,
        true,
    )?;
    float(
        "engine.mask_radius_fraction",
        e.mask_radius_fraction,
        0.0,
        1.0,
        true,
    )?;
    int("engine.sample", e.sample as u64, 2, 256)?;
    float(
        "engine.ransac_threshold_px",
        e.ransac_threshold_px,
        0.0,
        1000.0,
        true,
    )?;
    int(
        "engine.ransac_max_trials",
        e.ransac_max_trials as u64,
        1,
        1_000_000,
    )?;
    if let Some(v) = e.pyramid_levels {
        int("engine.pyramid_levels", v as u64, 1, 8)?;
    }
    int("engine.iterations", e.iterations as u64, 1, 100)?;
    int("engine.poly_n", e.poly_n as u64, 3, 15)?;
    float("engine.poly_sigma", e.poly_sigma, 0.0, 10.0, true)?;
    int("engine.max_passes", e.max_passes as u64, 1, 32)?;
    float("engine.convergence_px", e.convergence_px, 0.0, 1.0, true)?;
    float(
        "engine.hot_pixel_fraction",
        f64::from(e.hot_pixel_fraction),
        0.0,
        1e6,
        false,
    )?;
    float(
        "engine.systematic_floor_px",
        e.systematic_floor_px,
        0.0,
        1.0,
        false,
    )?;
    for (key, v) in [
        ("engine.min_similarity", e.min_similarity),
        ("engine.min_correlation", e.min_correlation),
        ("engine.min_inlier_fraction", e.min_inlier_fraction),
    ] {
        float(key, v, 0.0, 1.0, false)?;
    }
    float(
        "engine.refine_smoothing_px",
        e.refine_smoothing_px,
        0.0,
        16.0,
        false,
    )?;
    float(
        "engine.refine_gradient_smoothing_px",
        e.refine_gradient_smoothing_px,
        0.0,
        16.0,
        false,
    )?;
    stability(
        "engine",
        Some(e.scale_stability),
        Some(e.roll_stability_arcsec),
    )?;
    int("engine.seed_extent_px", e.seed_extent_px as u64, 1, 65_536)?;
    int(
        "engine.final_extent_px",
        e.final_extent_px as u64,
        0,
        65_536,
    )?;
    Ok(())
}

/// An instrument's stability: a relative plate scale above 0 and up to 10 %, a roll above 0
/// and up to 180°.
fn stability(at: &str, scale: Option<f64>, roll_arcsec: Option<f64>) -> Result<()> {
    if let Some(v) = scale {
        float(&format!("{at}.scale_stability"), v, 0.0, 0.1, true)?;
    }
    if let Some(v) = roll_arcsec {
        float(
            &format!("{at}.roll_stability_arcsec"),
            v,
            0.0,
            648_000.0,
            true,
        )?;
    }
    Ok(())
}

fn sink(s: &sunjitter_io::sink::SinkConfig) -> Result<()> {
    float(
        "sink.segment_minutes",
        s.segment_minutes,
        0.0,
        525_600.0,
        false,
    )?;
    int(
        "sink.flush_every_frames",
        s.flush_every_frames,
        1,
        1_000_000,
    )?;
    int("sink.chunk_size", s.chunk_size, 1, 256 * 1024 * 1024)?;
    Ok(())
}

fn daemon(d: &super::DaemonConfig) -> Result<()> {
    int(
        "daemon.queue_capacity",
        d.queue_capacity as u64,
        1,
        1_000_000,
    )?;
    int("daemon.readers", d.readers as u64, 1, 256)?;
    int("daemon.workers", d.workers as u64, 1, 256)?;
    int(
        "daemon.reorder_window_frames",
        d.reorder_window_frames as u64,
        0,
        100_000,
    )?;
    float(
        "daemon.reorder_window_s",
        d.reorder_window_s,
        0.0,
        86_400.0,
        false,
    )?;
    float("daemon.settle_s", d.settle_s, 0.0, 86_400.0, false)?;
    int(
        "daemon.retry_attempts",
        u64::from(d.retry_attempts),
        0,
        1000,
    )?;
    float(
        "daemon.retry_initial_s",
        d.retry_initial_s,
        0.001,
        3600.0,
        false,
    )?;
    float(
        "daemon.retry_max_s",
        d.retry_max_s,
        d.retry_initial_s,
        86_400.0,
        false,
    )?;
    float(
        "daemon.incomplete_wait_s",
        d.incomplete_wait_s,
        0.0,
        MAX_WAIT_S,
        false,
    )?;
    float(
        "daemon.rescan_interval_s",
        d.rescan_interval_s,
        0.0,
        MAX_WAIT_S,
        false,
    )?;
    float(
        "daemon.flush_interval_s",
        d.flush_interval_s,
        0.0,
        3600.0,
        true,
    )?;
    int("daemon.max_frame_pixels", d.max_frame_pixels, 1, 1 << 32)?;
    int("daemon.max_channels", d.max_channels as u64, 1, 4096)?;
    for ext in &d.extensions {
        if ext.trim_start_matches('.').is_empty() || ext.contains(['/', '\0']) {
            return Err(refuse(
                "daemon.extensions",
                format!("{:?}", sunjitter_core::text::escape(ext)),
                "file name endings such as \"fits\"",
            ));
        }
    }
    for pattern in &d.ignore {
        if pattern.is_empty() || pattern.contains(['/', '\0']) {
            return Err(refuse(
                "daemon.ignore",
                format!("{:?}", sunjitter_core::text::escape(pattern)),
                "file name patterns such as \"*.tmp\"",
            ));
        }
    }
    Ok(())
}

fn policy(at: &str, p: &ChannelPolicy) -> Result<()> {
    let key = |k: &str| format!("{at}.{k}");
    float(
        &key("keyframe_every_s"),
        p.keyframe_every_s,
        0.0,
        1e9,
        false,
    )?;
    float(
        &key("refresh_below_similarity"),
        p.refresh_below_similarity,
        0.0,
        1.0,
        false,
    )?;
    float(&key("tolerance_s"), p.tolerance_s, 0.0, 1e9, false)?;
    float(&key("hold_s"), p.hold_s, 0.0, MAX_WAIT_S, false)?;
    if let PolicySpec::Channel(partner) = &p.policy {
        check_channel_name(&format!("{at}.policy channel:"), partner)?;
    }
    Ok(())
}

pub(crate) fn alerts(a: &super::AlertsConfig) -> Result<()> {
    float(
        "alerts.command_timeout_s",
        a.command_timeout_s,
        0.0,
        86_400.0,
        true,
    )?;
    if a.command.first().is_some_and(|c| c.is_empty()) {
        return Err(Error::Usage(
            "configuration: alerts.command: the program (its first element) is empty".into(),
        ));
    }
    thresholds("alerts.defaults", &a.defaults)?;
    for (name, t) in &a.channels {
        check_channel_name("[alerts.channels.NAME]", name)?;
        thresholds(&format!("alerts.channels.{name}"), t)?;
    }
    Ok(())
}

fn thresholds(at: &str, t: &super::Thresholds) -> Result<()> {
    for (name, v) in [
        ("amplitude_px", t.amplitude_px),
        ("amplitude_arcsec", t.amplitude_arcsec),
        ("rms_px", t.rms_px),
        ("rms_arcsec", t.rms_arcsec),
        ("jump_px", t.jump_px),
        ("jump_arcsec", t.jump_arcsec),
        ("sigma_px", t.sigma_px),
        ("header_sigmas", t.header_sigmas),
        ("closure_sigmas", t.closure_sigmas),
        ("lag_s", t.lag_s),
        ("silence_s", t.silence_s),
    ] {
        if let Some(v) = v {
            float(&format!("{at}.{name}"), v, 0.0, 1e9, true)?;
        }
    }
    if let Some(w) = t.rms_window_frames {
        int(&format!("{at}.rms_window_frames"), w as u64, 2, 100_000)?;
    }
    for (name, v) in [
        ("consecutive_bad", t.consecutive_bad),
        ("consecutive_failed", t.consecutive_failed),
    ] {
        if let Some(v) = v {
            int(&format!("{at}.{name}"), u64::from(v), 1, 1_000_000)?;
        }
    }
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
