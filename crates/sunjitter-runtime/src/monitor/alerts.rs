//! Alert rules: per-channel thresholds, and the state machine that turns the stream of logged
//! frames (and the passing of time) into `raised` / `resolved` alert events.
//!
//! Pure: no I/O, no clock of its own. The caller feeds every `/jitter` message with the wall
//! clock and the frame's ingest lag ([`AlertEngine::frame`]), and calls [`AlertEngine::tick`]
//! now and then for the time-based rule (`silence_s`). Each alert is keyed by (channel, kind);
//! it is raised once when its condition starts and resolved once when it ends.
//!
//! Quantities, per channel:
//! - `amplitude_*`: |(dx, dy)| of the frame's measurement against its reference;
//! - `jump_*`: |Δ position| between consecutive usable frames, the position being the chained
//!   series where the policy has one (continuous across keyframe changes), else (dx, dy);
//! - `rms_*`: RMS distance of the last `rms_window_frames` positions from their mean (the
//!   jitter about the mean pointing; evaluated once the window is full);
//! - `sigma_px`: the larger of `sigma_dx_px`, `sigma_dy_px`;
//! - `header_sigmas`: the larger of |scale − header's| / σ and |roll − header's| / σ (from
//!   `header_residual`), where the frame's model fitted them;
//! - `closure_sigmas`: the largest |difference| / σ of a keyframe's closure, fed from the
//!   `/reference` messages ([`AlertEngine::reference`]), resolved by the next keyframe that closes;
//! - `consecutive_bad`: failed or degraded frames in a row (raised at N, resolved by an ok one);
//! - `consecutive_failed`: failed frames in a row (raised at N, resolved by one with a result);
//! - `lag_s`: file taken by the daemon → alignment finished;
//! - `silence_s`: no frame of a channel for this long (armed by the channel's first frame).
//!
//! Arcsecond variants use the reference plate scale the record carries (`dx_arcsec / dx_px`).
//! A failed frame has no numbers: it leaves the numeric alerts as they are.

use crate::config::{AlertsConfig, Thresholds, DEFAULT_RMS_WINDOW};
use std::collections::{BTreeMap, VecDeque};
use sunjitter_core::record::{FrameAlignment, Status};
use sunjitter_io::sink::{Alert, ReferenceChange};

/// One alert event, with the MCAP `log_time` it is logged at.
#[derive(Debug, Clone, PartialEq)]
pub struct AlertEvent {
    pub alert: Alert,
    pub log_time_ns: i64,
}

#[derive(Debug, Clone, PartialEq)]
struct Active {
    threshold: f64,
    unit: &'static str,
}

#[derive(Debug, Default)]
struct ChannelWatch {
    thresholds: Thresholds,
    active: BTreeMap<&'static str, Active>,
    last_position: Option<(f64, f64)>,
    window: VecDeque<(f64, f64)>,
    bad_run: u32,
    failed_run: u32,
    /// arcsec per px along x and y, learned from the records.
    plate_scale: (Option<f64>, Option<f64>),
    last_frame_wall_ns: Option<i64>,
}

/// Where an event comes from: the frame that changed the state, or the wall clock.
struct At<'a> {
    channel: &'a str,
    frame: Option<&'a str>,
    time_ns: i64,
}

/// The alert state machine of every channel.
#[derive(Debug, Default)]
pub struct AlertEngine {
    config: AlertsConfig,
    channels: BTreeMap<String, ChannelWatch>,
}

/// `ChannelWatch::judge` of the threshold `$field` of `$thresholds`: the alert's kind is the
/// threshold's configuration key, its field's name.
macro_rules! judge {
    ($w:ident, $events:expr, $at:expr, $thresholds:expr => $field:ident, $value:expr, $raised:expr) => {
        $w.judge(
            $events,
            $at,
            stringify!($field),
            $thresholds.$field.map(f64::from),
            $value,
            $raised,
        )
    };
}

impl AlertEngine {
    pub fn new(config: AlertsConfig) -> AlertEngine {
        AlertEngine {
            config,
            channels: BTreeMap::new(),
        }
    }

    /// Whether any threshold is set at all (nothing to evaluate otherwise).
    pub fn enabled(&self) -> bool {
        let any = |t: &Thresholds| *t != Thresholds::default();
        any(&self.config.defaults) || self.config.channels.values().any(any)
    }

    /// Alerts raised and not yet resolved.
    pub fn active(&self) -> Vec<(String, String)> {
        self.channels
            .iter()
            .flat_map(|(c, w)| w.active.keys().map(move |k| (c.clone(), k.to_string())))
            .collect()
    }

    fn watch(&mut self, channel: &str) -> &mut ChannelWatch {
        let thresholds = self.config.thresholds(channel);
        self.channels
            .entry(channel.to_string())
            .or_insert_with(|| ChannelWatch {
                thresholds,
                ..Default::default()
            })
    }

    /// One logged frame: `log_time_ns` its observation time, `wall_ns` when it was logged,
    /// `lag_s` its ingest lag if known.
    pub fn frame(
        &mut self,
        message: &FrameAlignment,
        log_time_ns: i64,
        wall_ns: i64,
        lag_s: Option<f64>,
    ) -> Vec<AlertEvent> {
        let mut events = Vec::new();
        let w = self.watch(&message.channel);
        let t = w.thresholds.clone();
        let at = At {
            channel: &message.channel,
            frame: Some(&message.align.frame),
            time_ns: log_time_ns,
        };

        // Silence ends with any frame.
        if let Some(last) = w.last_frame_wall_ns {
            let gap = (wall_ns - last) as f64 / 1e9;
            judge!(w, &mut events, &at, t => silence_s, Some(gap), |_, _| false);
        }
        w.last_frame_wall_ns = Some(wall_ns);

        let a = &message.align;
        if let Some(sx) = ratio(a.dx_arcsec, a.dx_px) {
            w.plate_scale.0 = Some(sx);
        }
        if let Some(sy) = ratio(a.dy_arcsec, a.dy_px) {
            w.plate_scale.1 = Some(sy);
        }

        let bad = matches!(a.status, Status::Failed | Status::Degraded);
        w.bad_run = if bad { w.bad_run + 1 } else { 0 };
        w.failed_run = if a.status == Status::Failed {
            w.failed_run + 1
        } else {
            0
        };
        let (bad_run, failed_run) = (w.bad_run as f64, w.failed_run as f64);
        let reached = |v: f64, thr: f64| v >= thr;
        judge!(w, &mut events, &at, t => consecutive_bad, Some(bad_run), reached);
        judge!(w, &mut events, &at, t => consecutive_failed, Some(failed_run), reached);

        judge!(w, &mut events, &at, t => lag_s, lag_s, above);

        let raw = match (a.status, a.dx_px, a.dy_px) {
            (Status::Failed, _, _) => None,
            (_, Some(dx), Some(dy)) if dx.is_finite() && dy.is_finite() => Some((dx, dy)),
            _ => None,
        };
        let Some(raw) = raw else {
            return events;
        };
        let position = match (message.chained_dx_px, message.chained_dy_px) {
            (Some(x), Some(y)) if x.is_finite() && y.is_finite() => (x, y),
            _ => raw,
        };
        let to_arcsec = |(x, y): (f64, f64), scale: (Option<f64>, Option<f64>)| {
            Some((x * scale.0?, y * scale.1?))
        };
        let scale = w.plate_scale;

        let amplitude_arcsec = match (a.dx_arcsec, a.dy_arcsec) {
            (Some(x), Some(y)) => Some(x.hypot(y)),
            _ => None,
        };
        judge!(w, &mut events, &at, t => amplitude_px, Some(raw.0.hypot(raw.1)), above);
        judge!(w, &mut events, &at, t => amplitude_arcsec, amplitude_arcsec, above);

        let sigma = match (a.sigma_dx_px, a.sigma_dy_px) {
            (Some(x), Some(y)) => Some(x.max(y)),
            _ => None,
        };
        judge!(w, &mut events, &at, t => sigma_px, sigma, above);

        let header = header_sigmas(a);
        judge!(w, &mut events, &at, t => header_sigmas, header, above);

        if let Some(last) = w.last_position {
            let d = (position.0 - last.0, position.1 - last.1);
            let jump_arcsec = to_arcsec(d, scale).map(|(x, y)| x.hypot(y));
            judge!(w, &mut events, &at, t => jump_px, Some(d.0.hypot(d.1)), above);
            judge!(w, &mut events, &at, t => jump_arcsec, jump_arcsec, above);
        }
        w.last_position = Some(position);

        let window = t.rms_window_frames.unwrap_or(DEFAULT_RMS_WINDOW).max(2);
        w.window.push_back(position);
        while w.window.len() > window {
            w.window.pop_front();
        }
        if w.window.len() == window {
            let rms_px = rms_about_mean(w.window.iter().copied());
            let rms_arcsec = w
                .window
                .iter()
                .map(|p| to_arcsec(*p, scale))
                .collect::<Option<Vec<_>>>()
                .map(|ps| rms_about_mean(ps.into_iter()));
            judge!(w, &mut events, &at, t => rms_px, Some(rms_px), above);
            judge!(w, &mut events, &at, t => rms_arcsec, rms_arcsec, above);
        }
        events
    }

    /// One `/reference` message: a keyframe reached two ways gives `closure_sigmas`.
    pub fn reference(&mut self, change: &ReferenceChange, log_time_ns: i64) -> Vec<AlertEvent> {
        let mut events = Vec::new();
        let Some(closure) = &change.closure else {
            return events;
        };
        let key = match change.cube_frame {
            Some(n) => format!("{}[{n}]", change.file),
            None => change.file.clone(),
        };
        let w = self.watch(&change.channel);
        let z = closure.z().iter().fold(0.0f64, |m, z| m.max(z.abs()));
        let at = At {
            channel: &change.channel,
            frame: Some(&key),
            time_ns: log_time_ns,
        };
        judge!(w, &mut events, &at, w.thresholds => closure_sigmas, Some(z), above);
        events
    }

    /// The passing of time (call every second or so): `silence_s`.
    pub fn tick(&mut self, wall_ns: i64) -> Vec<AlertEvent> {
        let mut events = Vec::new();
        for (channel, w) in self.channels.iter_mut() {
            let Some(last) = w.last_frame_wall_ns else {
                continue;
            };
            let gap = (wall_ns - last) as f64 / 1e9;
            let at = At {
                channel,
                frame: None,
                time_ns: wall_ns,
            };
            judge!(w, &mut events, &at, w.thresholds => silence_s, Some(gap), above);
        }
        events
    }
}

fn above(value: f64, threshold: f64) -> bool {
    value > threshold
}

/// How many σ the fitted scale or roll is from the headers' (`None` where neither was fitted
/// with a σ).
fn header_sigmas(a: &sunjitter_core::record::AlignResult) -> Option<f64> {
    let h = a.header_residual.as_ref()?;
    let z = |d: f64, s: Option<f64>| s.filter(|s| *s > 0.0).map(|s| d.abs() / s);
    match (
        z(h.scale - 1.0, a.sigma_scale),
        z(h.rotation_arcsec, a.sigma_rotation_arcsec),
    ) {
        (Some(a), Some(b)) => Some(a.max(b)),
        (a, b) => a.or(b),
    }
}

fn ratio(arcsec: Option<f64>, px: Option<f64>) -> Option<f64> {
    let (a, p) = (arcsec?, px?);
    let r = a / p;
    (p.abs() > 1e-9 && r.is_finite() && r > 0.0).then_some(r)
}

fn rms_about_mean(points: impl Iterator<Item = (f64, f64)> + Clone) -> f64 {
    let n = points.clone().count() as f64;
    let (sx, sy) = points
        .clone()
        .fold((0.0, 0.0), |(a, b), (x, y)| (a + x, b + y));
    let (mx, my) = (sx / n, sy / n);
    let ss: f64 = points
        .map(|(x, y)| (x - mx).powi(2) + (y - my).powi(2))
        .sum();
    (ss / n).sqrt()
}

fn unit_of(kind: &str) -> &'static str {
    if kind.ends_with("_px") {
        "px"
    } else if kind.ends_with("_arcsec") {
        "arcsec"
    } else if kind.ends_with("_sigmas") {
        "σ"
    } else if kind.ends_with("_s") {
        "s"
    } else {
        "frames"
    }
}

fn severity_of(kind: &str) -> &'static str {
    match kind {
        "consecutive_bad" | "consecutive_failed" | "silence_s" => "error",
        _ => "warning",
    }
}

fn describe(kind: &str) -> &'static str {
    match kind {
        "amplitude_px" | "amplitude_arcsec" => "jitter amplitude",
        "rms_px" | "rms_arcsec" => "jitter RMS",
        "jump_px" | "jump_arcsec" => "jump between frames",
        "sigma_px" => "1-σ error",
        "header_sigmas" => "scale or roll against the headers'",
        "closure_sigmas" => "keyframe closure",
        "consecutive_bad" => "failed or degraded frames in a row",
        "consecutive_failed" => "failed frames in a row",
        "lag_s" => "ingest lag",
        "silence_s" => "time without a frame",
        _ => "value",
    }
}

impl ChannelWatch {
    /// Raise `kind` when `raised(value, threshold)` starts to hold, resolve it when it stops.
    /// No threshold or no value: no change.
    fn judge(
        &mut self,
        events: &mut Vec<AlertEvent>,
        at: &At,
        kind: &'static str,
        threshold: Option<f64>,
        value: Option<f64>,
        raised: impl Fn(f64, f64) -> bool,
    ) {
        let (Some(threshold), Some(value)) = (threshold, value) else {
            return;
        };
        if !value.is_finite() {
            return;
        }
        let unit = unit_of(kind);
        let is_active = self.active.contains_key(kind);
        let now = raised(value, threshold);
        let state = match (is_active, now) {
            (false, true) => {
                self.active.insert(kind, Active { threshold, unit });
                "raised"
            }
            (true, false) => {
                self.active.remove(kind);
                "resolved"
            }
            _ => return,
        };
        let what = describe(kind);
        let message = if state == "raised" {
            format!(
                "{}: {what} {value:.3} {unit} above {threshold} {unit}",
                at.channel
            )
        } else {
            format!(
                "{}: {what} back to {value:.3} {unit} (threshold {threshold} {unit})",
                at.channel
            )
        };
        events.push(AlertEvent {
            alert: Alert {
                channel: at.channel.to_string(),
                kind: kind.to_string(),
                state: state.to_string(),
                severity: severity_of(kind).to_string(),
                value,
                threshold,
                unit: unit.to_string(),
                frame: at.frame.map(str::to_string),
                time: sunjitter_core::time::format_iso_utc(at.time_ns),
                message,
            },
            log_time_ns: at.time_ns,
        });
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use sunjitter_core::record::AlignResult;

    #[test]
    fn every_threshold_key_is_a_described_kind() {
        // The keys `[alerts.defaults]` reads, from the configuration's own parser.
        let t: Thresholds = toml::from_str(
            "amplitude_px = 1\namplitude_arcsec = 1\nrms_px = 1\nrms_arcsec = 1\n\
             rms_window_frames = 5\njump_px = 1\njump_arcsec = 1\nsigma_px = 1\n\
             header_sigmas = 1\nclosure_sigmas = 1\nconsecutive_bad = 1\n\
             consecutive_failed = 1\nlag_s = 1\nsilence_s = 1",
        )
        .unwrap();
        let keys = serde_json::to_value(&t).unwrap();
        let keys: Vec<&String> = keys.as_object().unwrap().keys().collect();
        assert_eq!(keys.len(), 14, "{keys:?}");
        for key in keys {
            if key == "rms_window_frames" {
                continue; // the window of rms_*, not a threshold of its own
            }
            assert_ne!(describe(key), "value", "{key}");
        }
    }

    const S: i64 = 1_000_000_000;
    /// Plate scale of the records below (IRIS SJI: CDELT1 = CDELT2 = 0.16635″).
    const PLATE: f64 = 0.16635;

    fn record(seq: u64, status: Status, dx: f64, dy: f64, sigma: f64) -> FrameAlignment {
        let failed = status == Status::Failed;
        let num = |v: f64| (!failed).then_some(v);
        FrameAlignment::unchained(
            AlignResult {
                reference: "ref.fits".into(),
                frame: format!("f{seq:03}.fits"),
                scale: num(1.0),
                rotation_arcsec: num(0.0),
                dx_px: num(dx),
                dy_px: num(dy),
                dx_arcsec: num(dx * PLATE),
                dy_arcsec: num(dy * PLATE),
                sigma_scale: num(0.0),
                sigma_rotation_arcsec: num(0.0),
                sigma_dx_px: num(sigma),
                sigma_dy_px: num(sigma / 2.0),
                sigma_dx_arcsec: num(sigma),
                sigma_dy_arcsec: num(sigma / 2.0),
                uabjm_sigma_scale: None,
                uabjm_sigma_rotation_arcsec: None,
                uabjm_sigma_dx_px: None,
                uabjm_sigma_dy_px: None,
                header_residual: None,
                solar_rotation: None,
                points: 100,
                inliers: 90,
                residual_rms_px: num(0.1),
                model: None,
                similarity: num(0.9),
                status,
                message: String::new(),
                elapsed_ms: 1.0,
            },
            "A".into(),
            String::new(),
            seq,
            sunjitter_core::record::ReferenceKind::Previous,
        )
    }

    fn engine(t: Thresholds) -> AlertEngine {
        AlertEngine::new(AlertsConfig {
            defaults: t,
            ..Default::default()
        })
    }

    /// (frame index, kind, state) of every event.
    type Seen = Vec<(u64, String, String)>;

    fn feed(engine: &mut AlertEngine, frames: &[FrameAlignment]) -> Seen {
        let mut seen = Vec::new();
        for (i, f) in frames.iter().enumerate() {
            let t = i as i64 * 12 * S;
            for e in engine.frame(f, t, t, Some(0.5)) {
                seen.push((f.sequence, e.alert.kind.clone(), e.alert.state.clone()));
            }
        }
        seen
    }

    fn ev(seq: u64, kind: &str, state: &str) -> (u64, String, String) {
        (seq, kind.into(), state.into())
    }

    #[test]
    fn a_single_displaced_frame_raises_amplitude_and_jump_once_each() {
        // Frame 3 is displaced by (3, 4) px: amplitude 5 px; jumps +5 then −5.
        let mut e = engine(Thresholds {
            amplitude_px: Some(2.0),
            jump_px: Some(2.0),
            ..Default::default()
        });
        let frames: Vec<_> = (0..6)
            .map(|i| {
                let (dx, dy) = if i == 3 { (3.0, 4.0) } else { (0.1, 0.0) };
                record(i, Status::Ok, dx, dy, 0.01)
            })
            .collect();
        assert_eq!(
            feed(&mut e, &frames),
            vec![
                ev(3, "amplitude_px", "raised"),
                ev(3, "jump_px", "raised"),
                ev(4, "amplitude_px", "resolved"),
                // Frame 4 jumps back by 5 px: the jump alert holds until frame 5.
                ev(5, "jump_px", "resolved"),
            ]
        );
        assert!(e.active().is_empty());
    }

    #[test]
    fn alert_messages_carry_value_threshold_frame_time_and_severity() {
        let mut e = engine(Thresholds {
            amplitude_arcsec: Some(0.5),
            ..Default::default()
        });
        let f = record(7, Status::Ok, 3.0, 4.0, 0.01);
        let events = e.frame(&f, 1_396_102_178 * S, 0, None);
        assert_eq!(events.len(), 1);
        let a = &events[0].alert;
        assert_eq!(
            (a.channel.as_str(), a.kind.as_str(), a.state.as_str()),
            ("A", "amplitude_arcsec", "raised")
        );
        assert!((a.value - 5.0 * PLATE).abs() < 1e-12, "{}", a.value);
        assert_eq!((a.threshold, a.unit.as_str()), (0.5, "arcsec"));
        assert_eq!(a.frame.as_deref(), Some("f007.fits"));
        // 1396102178 s = 2014-03-29T14:09:38Z (`date -u -d @1396102178`).
        assert!(a.time.starts_with("2014-03-29T14:09:38"), "{}", a.time);
        assert_eq!(a.severity, "warning");
        assert_eq!(events[0].log_time_ns, 1_396_102_178 * S);
    }

    #[test]
    fn rms_over_a_window_waits_for_a_full_window() {
        // Window 4, positions x = 0,0,0,3: mean 0.75, RMS = sqrt((3·0.5625 + 5.0625)/4) = 1.299.
        let mut e = engine(Thresholds {
            rms_px: Some(1.0),
            rms_window_frames: Some(4),
            ..Default::default()
        });
        let xs = [0.0, 0.0, 0.0, 3.0, 0.0, 0.0, 0.0, 0.0, 0.0];
        let frames: Vec<_> = xs
            .iter()
            .enumerate()
            .map(|(i, x)| record(i as u64, Status::Ok, *x, 0.0, 0.01))
            .collect();
        let mut values = Vec::new();
        for (i, f) in frames.iter().enumerate() {
            for ev in e.frame(f, i as i64, i as i64, None) {
                values.push((f.sequence, ev.alert.state.clone(), ev.alert.value));
            }
        }
        // Raised at frame 3; the outlier leaves the window at frame 7.
        assert_eq!(values.len(), 2, "{values:?}");
        assert_eq!((values[0].0, values[0].1.as_str()), (3, "raised"));
        assert!((values[0].2 - (6.75f64 / 4.0).sqrt()).abs() < 1e-12);
        assert_eq!(
            (values[1].0, values[1].1.as_str(), values[1].2),
            (7, "resolved", 0.0)
        );
    }

    #[test]
    fn consecutive_bad_frames_raise_at_n_and_a_good_frame_resolves() {
        let mut e = engine(Thresholds {
            consecutive_bad: Some(2),
            consecutive_failed: Some(2),
            ..Default::default()
        });
        let statuses = [
            Status::Ok,
            Status::Failed,
            Status::Ok,
            Status::Degraded,
            Status::Failed,
            Status::Failed,
            Status::Ok,
        ];
        let frames: Vec<_> = statuses
            .iter()
            .enumerate()
            .map(|(i, s)| record(i as u64, *s, 0.0, 0.0, 0.01))
            .collect();
        assert_eq!(
            feed(&mut e, &frames),
            vec![
                ev(4, "consecutive_bad", "raised"),
                // Failed frames 4 and 5 are in a row; 1 and 4 are not.
                ev(5, "consecutive_failed", "raised"),
                ev(6, "consecutive_bad", "resolved"),
                ev(6, "consecutive_failed", "resolved"),
            ]
        );
    }

    #[test]
    fn failed_frames_leave_numeric_alerts_unchanged() {
        let mut e = engine(Thresholds {
            amplitude_px: Some(1.0),
            sigma_px: Some(0.5),
            ..Default::default()
        });
        let frames = [
            record(0, Status::Ok, 2.0, 0.0, 0.01),
            record(1, Status::Failed, 0.0, 0.0, 0.0),
            record(2, Status::Ok, 0.0, 0.0, 0.8),
            record(3, Status::Ok, 0.0, 0.0, 0.1),
        ];
        assert_eq!(
            feed(&mut e, &frames),
            vec![
                ev(0, "amplitude_px", "raised"),
                ev(2, "amplitude_px", "resolved"),
                ev(2, "sigma_px", "raised"),
                ev(3, "sigma_px", "resolved"),
            ]
        );
    }

    #[test]
    fn silence_is_raised_by_the_clock_and_resolved_by_the_next_frame() {
        let mut e = engine(Thresholds {
            silence_s: Some(30.0),
            ..Default::default()
        });
        assert!(e.tick(100 * S).is_empty(), "not armed before a first frame");
        let f = record(0, Status::Ok, 0.0, 0.0, 0.01);
        assert!(e.frame(&f, 0, 100 * S, None).is_empty());
        assert!(e.tick(130 * S).is_empty(), "exactly 30 s is not above 30 s");
        let raised = e.tick(131 * S);
        assert_eq!(raised.len(), 1);
        assert_eq!(
            (raised[0].alert.state.as_str(), raised[0].alert.value),
            ("raised", 31.0)
        );
        assert_eq!(raised[0].alert.frame, None);
        assert_eq!(raised[0].alert.severity, "error");
        assert!(e.tick(200 * S).is_empty(), "raised once");
        let resolved = e.frame(&record(1, Status::Ok, 0.0, 0.0, 0.01), 0, 205 * S, None);
        assert_eq!(resolved.len(), 1);
        assert_eq!(
            (resolved[0].alert.state.as_str(), resolved[0].alert.value),
            ("resolved", 105.0)
        );
    }

    #[test]
    fn lag_above_its_bound_raises_and_resolves() {
        let mut e = engine(Thresholds {
            lag_s: Some(10.0),
            ..Default::default()
        });
        let lags = [1.0, 12.0, 30.0, 9.0, 2.0];
        let mut seen = Vec::new();
        for (i, lag) in lags.iter().enumerate() {
            let f = record(i as u64, Status::Ok, 0.0, 0.0, 0.01);
            for ev in e.frame(&f, 0, 0, Some(*lag)) {
                seen.push((i, ev.alert.state, ev.alert.value));
            }
        }
        assert_eq!(
            seen,
            vec![(1, "raised".into(), 12.0), (3, "resolved".into(), 9.0)]
        );
    }

    #[test]
    fn jumps_follow_the_chained_series_across_reference_changes() {
        // A keyframe change resets the raw offsets but not the chained series: no jump.
        let mut e = engine(Thresholds {
            jump_px: Some(1.0),
            ..Default::default()
        });
        let mut a = record(0, Status::Ok, 2.0, 0.0, 0.01);
        a.chained_dx_px = Some(2.0);
        a.chained_dy_px = Some(0.0);
        let mut b = record(1, Status::Ok, 0.0, 0.0, 0.01);
        b.chained_dx_px = Some(2.1);
        b.chained_dy_px = Some(0.0);
        assert!(feed(&mut e, &[a, b]).is_empty());
    }

    #[test]
    fn per_channel_thresholds_fall_back_to_defaults_and_bad_values_are_refused() {
        let config = AlertsConfig {
            defaults: Thresholds {
                jump_px: Some(1.0),
                silence_s: Some(60.0),
                ..Default::default()
            },
            channels: [(
                "B".to_string(),
                Thresholds {
                    jump_px: Some(3.0),
                    ..Default::default()
                },
            )]
            .into(),
            ..Default::default()
        };
        let b = config.thresholds("B");
        assert_eq!((b.jump_px, b.silence_s), (Some(3.0), Some(60.0)));
        assert_eq!(config.thresholds("A").jump_px, Some(1.0));
        config.validate().unwrap();
        let mut bad = config.clone();
        bad.defaults.lag_s = Some(-1.0);
        let err = bad.validate().unwrap_err();
        assert_eq!(err.exit_code(), sunjitter_core::error::ExitCode::BadInput);
        assert!(err.to_string().contains("alerts.defaults.lag_s"), "{err}");
    }

    #[test]
    fn scale_off_the_headers_and_a_keyframe_that_does_not_close_raise_alerts() {
        use sunjitter_core::record::TransformFields;
        use sunjitter_io::sink::ReferenceClosure;
        let mut engine = engine(Thresholds {
            header_sigmas: Some(4.0),
            closure_sigmas: Some(3.0),
            ..Default::default()
        });
        // Scale 5e-4 from the headers' with σ 1e-4 (5σ), then 2e-4 (2σ).
        let frames: Vec<FrameAlignment> = [5e-4, 2e-4]
            .iter()
            .enumerate()
            .map(|(i, off)| {
                let mut f = record(i as u64, Status::Ok, 0.1, 0.1, 0.05);
                f.align.sigma_scale = Some(1e-4);
                f.align.sigma_rotation_arcsec = Some(10.0);
                f.align.header_residual = Some(TransformFields {
                    scale: 1.0 + off,
                    rotation_arcsec: 5.0,
                    dx_px: 0.0,
                    dy_px: 0.0,
                });
                f
            })
            .collect();
        let seen = feed(&mut engine, &frames);
        let header = |state: &str| {
            (0..2).find(|&i| seen.contains(&(i, "header_sigmas".into(), state.into())))
        };
        assert_eq!(
            (header("raised"), header("resolved")),
            (Some(0), Some(1)),
            "{seen:?}"
        );

        // A keyframe 0.5 px from its second chain with σ 0.1 px (5σ), then one 0.1 px off.
        let change = |dx: f64| ReferenceChange {
            channel: "A".into(),
            file: "k.fits".into(),
            cube_frame: Some(7),
            obs_time: "2014-03-29T14:09:38Z".into(),
            reason: "refresh".into(),
            reference_kind: sunjitter_core::record::ReferenceKind::Keyframe,
            sequence: 3,
            replaces: Some("j.fits".into()),
            closure: Some(ReferenceClosure {
                through: "i.fits".into(),
                difference: TransformFields {
                    scale: 0.0,
                    rotation_arcsec: 0.0,
                    dx_px: dx,
                    dy_px: 0.0,
                },
                sigma: TransformFields {
                    scale: 1e-4,
                    rotation_arcsec: 60.0,
                    dx_px: 0.1,
                    dy_px: 0.1,
                },
            }),
            cross_covariance: None,
            chain: None,
        };
        let raised = engine.reference(&change(0.5), 100 * S);
        assert_eq!(raised.len(), 1, "{raised:?}");
        let a = &raised[0].alert;
        assert_eq!(
            (a.kind.as_str(), a.state.as_str()),
            ("closure_sigmas", "raised")
        );
        assert!((a.value - 5.0).abs() < 1e-9, "{a:?}");
        assert_eq!(
            (a.unit.as_str(), a.frame.as_deref()),
            ("σ", Some("k.fits[7]"))
        );
        let resolved = engine.reference(&change(0.1), 200 * S);
        assert_eq!(resolved.len(), 1);
        assert_eq!(resolved[0].alert.state, "resolved");
        // A new keyframe with no second chain leaves the alert as it is.
        let mut none = change(0.5);
        none.closure = None;
        assert!(engine.reference(&none, 300 * S).is_empty());
    }
}
