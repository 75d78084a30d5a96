//! What a log says of its own honesty, from physics and consistency rather than from the σ it
//! reports: the model each frame was fitted with, the closure of each channel's keyframes
//! (a keyframe reached two ways), scale and roll that disagree with the headers beyond the
//! instrument's stability, and pairs of channels of one instrument whose chained pointing
//! should agree within their σ.

use super::LoggedFrame;
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use sunjitter_core::record::{ReferenceKind, Status};
use sunjitter_io::sink::ReferenceChange;

/// A fitted value this many σ from the headers' disagrees with them.
pub const HEADER_SIGMAS: f64 = 4.0;
/// A closure holds when its difference is within this many σ.
pub const CLOSURE_SIGMAS: f64 = 2.0;
/// Below this fraction of closures within [`CLOSURE_SIGMAS`] a channel's σ are too small
/// (a Gaussian error gives 95 %).
pub const CLOSURE_MIN_FRACTION: f64 = 0.8;
/// Closures needed before the fraction says anything.
pub const CLOSURE_MIN_COUNT: usize = 5;
/// Two channels agree when at least this fraction of their differences lie within the
/// combined 1σ (a Gaussian error gives 68 %); fewer means σ too small for what they show.
pub const PAIR_MIN_WITHIN: f64 = 0.4;
/// Common samples needed before a pair is compared.
pub const PAIR_MIN_SAMPLES: usize = 5;

/// One channel's consistency.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct ChannelConsistency {
    pub channel: String,
    /// Frames per fitted model (`similarity`, `rigid`, `translation`).
    pub models: BTreeMap<String, usize>,
    /// Keyframes reached two ways, and how they closed; `null` without any.
    pub closure: Option<ClosureStats>,
    /// Frames whose fitted scale or roll differs from the headers' by more than
    /// [`HEADER_SIGMAS`]: a change of the instrument, or structure evolving coherently.
    pub header_disagreements: usize,
    /// What is unphysical or inconsistent, in words.
    pub warnings: Vec<String>,
}

/// Keyframe closures of a channel: per parameter (scale, rotation, dx, dy), the fraction
/// within [`CLOSURE_SIGMAS`] and the RMS of difference / σ.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ClosureStats {
    pub keyframes: usize,
    pub within_2sigma: [f64; 4],
    pub rms_z: [f64; 4],
}

/// Two channels of one instrument (one telescope, if they share it), their chained pointing
/// compared at the second's times (the first interpolated), each offset by its mean.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct PairConsistency {
    pub channels: [String; 2],
    pub samples: usize,
    /// RMS difference of chained dx and dy, px.
    pub rms_px: [f64; 2],
    /// Fraction of differences within the combined 1σ (dx, dy).
    pub within_1sigma: [f64; 2],
    /// Median combined 1σ (dx, dy), px.
    pub median_sigma_px: [f64; 2],
    /// Each channel measured on its own; `false` when one is aligned to another channel's
    /// frames (`reference_kind` `channel`), which shares its errors and proves nothing.
    #[serde(default = "yes")]
    pub independent: bool,
    pub warnings: Vec<String>,
}

fn yes() -> bool {
    true
}

/// Everything `inspect` checks across a log's frames and reference changes.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct Consistency {
    pub channels: Vec<ChannelConsistency>,
    pub pairs: Vec<PairConsistency>,
}

/// The consistency of `frames` (any order) and `references` (the `/reference` messages).
pub fn consistency(frames: &[LoggedFrame], references: &[ReferenceChange]) -> Consistency {
    let mut by_channel: BTreeMap<&str, Vec<&LoggedFrame>> = BTreeMap::new();
    for f in frames {
        by_channel.entry(&f.record.channel).or_default().push(f);
    }
    for list in by_channel.values_mut() {
        list.sort_by_key(|f| (f.log_time_ns, f.record.sequence));
    }
    let channels = by_channel
        .iter()
        .map(|(name, list)| channel(name, list, references))
        .collect();
    let names: Vec<&str> = by_channel.keys().copied().collect();
    let mut pairs = Vec::new();
    for (i, a) in names.iter().enumerate() {
        for b in &names[i + 1..] {
            if instrument(a) == instrument(b) {
                pairs.extend(pair(a, &by_channel[a], b, &by_channel[b]));
            }
        }
    }
    Consistency { channels, pairs }
}

/// The instrument part of a channel name (`SJI` of `SJI_1400`).
fn instrument(channel: &str) -> &str {
    channel.rsplit_once('_').map_or(channel, |(head, _)| head)
}

fn channel(
    name: &str,
    frames: &[&LoggedFrame],
    references: &[ReferenceChange],
) -> ChannelConsistency {
    let mut out = ChannelConsistency {
        channel: name.to_string(),
        ..Default::default()
    };
    for f in frames {
        if let Some(m) = f.record.align.model {
            *out.models.entry(m.as_str().to_string()).or_insert(0) += 1;
        }
        let a = &f.record.align;
        if a.status == Status::Failed {
            continue;
        }
        let off = |hr: Option<f64>, sigma: Option<f64>| match (hr, sigma) {
            (Some(d), Some(s)) if s > 0.0 => d.abs() > HEADER_SIGMAS * s,
            _ => false,
        };
        let hr = a.header_residual.as_ref();
        if off(hr.map(|h| h.scale - 1.0), a.sigma_scale)
            || off(hr.map(|h| h.rotation_arcsec), a.sigma_rotation_arcsec)
        {
            out.header_disagreements += 1;
        }
    }
    if out.header_disagreements > 0 {
        out.warnings.push(format!(
            "scale or roll differs from the headers' by more than {HEADER_SIGMAS}σ on {} \
             frame(s): a change of the instrument, or structure evolving coherently",
            out.header_disagreements
        ));
    }
    let z: Vec<[f64; 4]> = references
        .iter()
        .filter(|r| r.channel == name)
        .filter_map(|r| r.closure.as_ref().map(|c| c.z()))
        .collect();
    if !z.is_empty() {
        let n = z.len() as f64;
        let stats = ClosureStats {
            keyframes: z.len(),
            within_2sigma: std::array::from_fn(|k| {
                z.iter().filter(|v| v[k].abs() <= CLOSURE_SIGMAS).count() as f64 / n
            }),
            rms_z: std::array::from_fn(|k| (z.iter().map(|v| v[k] * v[k]).sum::<f64>() / n).sqrt()),
        };
        let names = ["scale", "rotation", "dx", "dy"];
        let failing: Vec<String> = (0..4)
            .filter(|&k| stats.within_2sigma[k] < CLOSURE_MIN_FRACTION)
            .map(|k| format!("{} {:.0} %", names[k], 100.0 * stats.within_2sigma[k]))
            .collect();
        if z.len() >= CLOSURE_MIN_COUNT && !failing.is_empty() {
            out.warnings.push(format!(
                "keyframe closure fails: within {CLOSURE_SIGMAS}σ only {} of {} keyframes \
                 (σ too small for how the structure evolves)",
                failing.join(", "),
                z.len()
            ));
        }
        out.closure = Some(stats);
    }
    out
}

/// (time s, chained dx, dy, σ dx, σ dy) of the frames with a chained position.
fn chained(frames: &[&LoggedFrame]) -> Vec<(f64, [f64; 2], [f64; 2])> {
    frames
        .iter()
        .filter(|f| f.record.align.status != Status::Failed)
        .filter_map(|f| {
            let r = &f.record;
            Some((
                f.log_time_ns as f64 * 1e-9,
                [r.chained_dx_px?, r.chained_dy_px?],
                [r.sigma_chained_dx_px?, r.sigma_chained_dy_px?],
            ))
        })
        .filter(|(_, v, s)| v.iter().chain(s).all(|x| x.is_finite()))
        .collect()
}

fn pair(
    a_name: &str,
    a: &[&LoggedFrame],
    b_name: &str,
    b: &[&LoggedFrame],
) -> Option<PairConsistency> {
    let follows = |frames: &[&LoggedFrame]| {
        frames
            .iter()
            .any(|f| f.record.reference_kind == ReferenceKind::Channel)
    };
    let independent = !follows(a) && !follows(b);
    let (a, b) = (chained(a), chained(b));
    let (t0, t1) = (a.first()?.0, a.last()?.0);
    // Each sample of b inside a's span, with a interpolated linearly to its time.
    let at = |t: f64| -> Option<([f64; 2], [f64; 2])> {
        let i = a.partition_point(|x| x.0 < t);
        let (lo, hi) = (a.get(i.checked_sub(1)?)?, a.get(i)?);
        let w = if hi.0 > lo.0 {
            (t - lo.0) / (hi.0 - lo.0)
        } else {
            0.0
        };
        let mix = |p: [f64; 2], q: [f64; 2]| [p[0] + w * (q[0] - p[0]), p[1] + w * (q[1] - p[1])];
        Some((mix(lo.1, hi.1), mix(lo.2, hi.2)))
    };
    let samples: Vec<([f64; 2], [f64; 2])> = b
        .iter()
        .filter(|x| x.0 >= t0 && x.0 <= t1)
        .filter_map(|x| {
            let (va, sa) = if x.0 == t0 {
                (a[0].1, a[0].2)
            } else {
                at(x.0)?
            };
            Some((
                [x.1[0] - va[0], x.1[1] - va[1]],
                [x.2[0].hypot(sa[0]), x.2[1].hypot(sa[1])],
            ))
        })
        .collect();
    if samples.len() < PAIR_MIN_SAMPLES {
        return None;
    }
    let n = samples.len() as f64;
    let mean: [f64; 2] = std::array::from_fn(|k| samples.iter().map(|s| s.0[k]).sum::<f64>() / n);
    let rms_px = std::array::from_fn(|k| {
        (samples
            .iter()
            .map(|s| (s.0[k] - mean[k]).powi(2))
            .sum::<f64>()
            / n)
            .sqrt()
    });
    let within_1sigma = std::array::from_fn(|k| {
        samples
            .iter()
            .filter(|s| (s.0[k] - mean[k]).abs() <= s.1[k])
            .count() as f64
            / n
    });
    let median_sigma_px = std::array::from_fn(|k| {
        let mut v: Vec<f64> = samples.iter().map(|s| s.1[k]).collect();
        v.sort_by(f64::total_cmp);
        v[v.len() / 2]
    });
    let mut warnings = Vec::new();
    let axes = ["dx", "dy"];
    for k in 0..2 {
        if independent && within_1sigma[k] < PAIR_MIN_WITHIN {
            warnings.push(format!(
                "{} and {b_name} disagree in chained {}: {:.3} px RMS with {:.0} % within \
                 their combined 1σ (median {:.3} px); through one telescope their σ are too \
                 small, or one channel's evolving structure misleads it",
                a_name,
                axes[k],
                rms_px[k],
                100.0 * within_1sigma[k],
                median_sigma_px[k]
            ));
        }
    }
    Some(PairConsistency {
        channels: [a_name.to_string(), b_name.to_string()],
        samples: samples.len(),
        rms_px,
        within_1sigma,
        median_sigma_px,
        independent,
        warnings,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use sunjitter_core::record::{AlignResult, FrameAlignment};

    fn frame(channel: &str, t_s: f64, dx: f64, dy: f64, sigma: f64) -> LoggedFrame {
        let align: AlignResult = serde_json::from_value(serde_json::json!({
            "reference": "r", "frame": format!("{channel}{t_s}"),
            "scale": 1.0, "rotation_arcsec": 0.0, "dx_px": 0.0, "dy_px": 0.0,
            "dx_arcsec": 0.0, "dy_arcsec": 0.0,
            "sigma_scale": 1e-4, "sigma_rotation_arcsec": 60.0, "sigma_dx_px": sigma,
            "sigma_dy_px": sigma, "uabjm_sigma_scale": null, "uabjm_sigma_rotation_arcsec": null,
            "uabjm_sigma_dx_px": null, "uabjm_sigma_dy_px": null,
            "header_residual": {"scale": 1.0, "rotation_arcsec": 0.0, "dx_px": 0.0, "dy_px": 0.0},
            "points": 400, "inliers": 400, "residual_rms_px": 0.0, "similarity": 1.0,
            "model": "translation", "status": "ok", "message": "", "elapsed_ms": 0.0
        }))
        .expect("record");
        let mut record = FrameAlignment::unchained(
            align,
            channel.into(),
            String::new(),
            0,
            ReferenceKind::Keyframe,
        );
        record.chained_dx_px = Some(dx);
        record.chained_dy_px = Some(dy);
        record.sigma_chained_dx_px = Some(sigma);
        record.sigma_chained_dy_px = Some(sigma);
        LoggedFrame {
            log_time_ns: (t_s * 1e9) as i64,
            record,
        }
    }

    #[test]
    fn two_channels_that_share_a_pointing_agree_and_an_offset_in_time_does_not() {
        // One pointing, sampled by two channels at interleaved times, each with its own
        // origin (a constant offset) and known independent errors of σ = 0.05 px.
        let pointing = |t: f64| [0.3 * (t / 500.0).sin(), 0.2 * (t / 700.0).cos()];
        let mut rng = sunjitter_core::stats::SplitMix64::new(4);
        let mut frames = Vec::new();
        for i in 0..200 {
            let t = i as f64 * 20.0;
            let p = pointing(t);
            let (ch, off) = if i % 2 == 0 {
                ("SJI_1400", 1.0)
            } else {
                ("SJI_2796", -2.0)
            };
            let e = [0.05 * rng.gaussian(), 0.05 * rng.gaussian()];
            frames.push(frame(ch, t, p[0] + off + e[0], p[1] + e[1], 0.05));
        }
        let c = consistency(&frames, &[]);
        let p = &c.pairs[0];
        assert_eq!(p.channels, ["SJI_1400".to_string(), "SJI_2796".to_string()]);
        for k in 0..2 {
            // The difference of two errors of 0.05 (plus the interpolation's, which is
            // smaller) is about 0.05·√2.
            assert!(
                (p.rms_px[k] / (0.05 * 2f64.sqrt()) - 1.0).abs() < 0.2,
                "{:?}",
                p.rms_px
            );
            assert!(
                (0.55..0.85).contains(&p.within_1sigma[k]),
                "{:?}",
                p.within_1sigma
            );
        }
        assert!(p.warnings.is_empty());

        // The same pointing, claimed at σ ten times too small: flagged.
        for f in &mut frames {
            f.record.sigma_chained_dx_px = Some(0.005);
            f.record.sigma_chained_dy_px = Some(0.005);
        }
        let c = consistency(&frames, &[]);
        assert_eq!(c.pairs[0].warnings.len(), 2, "{:?}", c.pairs[0]);
        assert!(c.pairs[0].independent);

        // One channel aligned to the other's frames: no independent check, no warning.
        for f in frames.iter_mut().filter(|f| f.record.channel == "SJI_2796") {
            f.record.reference_kind = ReferenceKind::Channel;
        }
        let c = consistency(&frames, &[]);
        assert!(!c.pairs[0].independent);
        assert!(c.pairs[0].warnings.is_empty(), "{:?}", c.pairs[0]);
    }

    #[test]
    fn keyframe_closures_beyond_their_sigma_are_flagged() {
        use sunjitter_core::record::TransformFields;
        use sunjitter_io::sink::ReferenceClosure;
        let change = |dx: f64| ReferenceChange {
            channel: "SJI_1400".into(),
            file: "a.fits".into(),
            cube_frame: None,
            obs_time: String::new(),
            reason: String::new(),
            reference_kind: ReferenceKind::Keyframe,
            sequence: 0,
            replaces: None,
            cross_covariance: None,
            closure: Some(ReferenceClosure {
                through: "b.fits".into(),
                difference: TransformFields {
                    scale: 0.0,
                    rotation_arcsec: 0.0,
                    dx_px: dx,
                    dy_px: 0.0,
                },
                sigma: TransformFields {
                    scale: 1e-4,
                    rotation_arcsec: 60.0,
                    dx_px: 0.01,
                    dy_px: 0.01,
                },
            }),
            chain: None,
        };
        let frames = [frame("SJI_1400", 0.0, 0.0, 0.0, 0.01)];
        // Four of six closures 5σ off in dx: flagged; all within 1σ: not.
        let bad: Vec<ReferenceChange> = [0.05, -0.05, 0.05, 0.005, 0.05, -0.005]
            .into_iter()
            .map(change)
            .collect();
        let c = consistency(&frames, &bad);
        let stats = c.channels[0].closure.as_ref().expect("closures");
        assert_eq!(stats.keyframes, 6);
        assert!((stats.within_2sigma[2] - 2.0 / 6.0).abs() < 1e-12);
        assert_eq!(
            c.channels[0].warnings.len(),
            1,
            "{:?}",
            c.channels[0].warnings
        );
        let good: Vec<ReferenceChange> = [0.005; 6].into_iter().map(change).collect();
        assert!(consistency(&frames, &good).channels[0].warnings.is_empty());
    }
}
