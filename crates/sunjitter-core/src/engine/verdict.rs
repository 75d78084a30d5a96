//! The verdict on one measurement: `ok`, `degraded` with its reasons, or no answer at all,
//! from what the stages found.

use super::config::EngineConfig;
use crate::record::Status;

/// What the intensity refinement said of the flow's answer.
#[derive(Debug, Clone, Default, PartialEq)]
pub(super) struct Refinement {
    /// Its note (the answer taken, or why not), when it ran.
    pub note: Option<String>,
    /// Its answer replaced the flow's.
    pub accepted: bool,
    /// It ran from the flow's answer and found no consistent solution near it.
    pub ran_off: bool,
    /// It converged beyond the flow's σ from the flow's answer.
    pub disagrees: bool,
}

/// What the stages of one measurement found.
#[derive(Debug, Clone, PartialEq)]
pub(super) struct Evidence {
    /// Rank correlation of the structure after alignment.
    pub correlation: Option<f64>,
    /// Bhattacharyya similarity of the histograms after alignment.
    pub similarity: Option<f64>,
    /// RANSAC inliers of the flow's vectors, and the vectors.
    pub inliers: usize,
    pub points: usize,
    pub passes: usize,
    pub converged: bool,
    /// The flow's last motion when it was still moving beyond its σ (cleared when the
    /// refinement's answer was taken).
    pub unsettled_px: Option<f64>,
    /// The pyramid level of a seed on binned copies.
    pub seed_level: Option<usize>,
    /// The pyramid level of the seed that full-resolution passes started from.
    pub seeded_from: Option<usize>,
    pub winsize: usize,
    pub refinement: Refinement,
}

/// The status and the message of a measurement that gave an answer.
#[derive(Debug, Clone, PartialEq)]
pub(super) struct Verdict {
    pub status: Status,
    pub message: String,
}

/// The verdict on `evidence`; `notes` (what the earlier stages said) follow the reasons in
/// the message. `Err`: the measurement gives no answer, and why.
pub(super) fn verdict(
    evidence: &Evidence,
    mut notes: Vec<String>,
    cfg: &EngineConfig,
) -> Result<Verdict, String> {
    let e = evidence;
    let refinement = &e.refinement;
    // Once the refinement has the last word, the flow only seeded it: its convergence is
    // no news to the user.
    if !e.converged && !refinement.accepted {
        notes.push(format!(
            "fine alignment did not converge to {} px in {} passes",
            cfg.convergence_px, e.passes
        ));
    }
    notes.extend(refinement.note.clone());

    let inlier_fraction = e.inliers as f64 / e.points.max(1) as f64;
    let mut status = Status::Ok;
    let mut reasons: Vec<String> = Vec::new();
    if let Some(c) = e.correlation {
        if c < cfg.min_correlation / 3.0 {
            return Err(format!(
                "no common structure: correlation {c:.3} after alignment (frame unrelated to the reference?)"
            ));
        }
        if c < cfg.min_correlation {
            status = Status::Degraded;
            reasons.push(format!("weak common structure (correlation {c:.3})"));
        }
    }
    if let Some(s) = e.similarity {
        if s < cfg.min_similarity {
            status = Status::Degraded;
            reasons.push(format!("low histogram similarity {s:.3}"));
        }
    }
    if let Some(why) = unconfirmed(e, inlier_fraction, cfg) {
        return Err(why);
    }
    if let Some(moved) = e.unsettled_px {
        status = Status::Degraded;
        reasons.push(format!(
            "the fine alignment was still moving ({moved:.3} px in its last pass); σ include \
             that step"
        ));
    }
    if refinement.disagrees {
        status = Status::Degraded;
        reasons.push(
            "the flow and the intensity refinement disagree; σ include their difference".into(),
        );
    }
    if inlier_fraction < cfg.min_inlier_fraction {
        status = Status::Degraded;
        reasons.push(format!(
            "only {}/{} flow vectors agree with one similarity",
            e.inliers, e.points
        ));
    }
    reasons.extend(notes);
    reasons.push(match (e.seed_level, e.seeded_from) {
        (Some(level), Some(from)) if level > 0 => format!(
            "window {} px, {} passes on pyramid level {level} from a seed on level {from}",
            e.winsize, e.passes
        ),
        (Some(level), _) if level > 0 => format!(
            "window {} px, {} passes finished on pyramid level {level}",
            e.winsize, e.passes
        ),
        (_, Some(level)) => format!(
            "window {} px, {} passes from a seed on pyramid level {level}",
            e.winsize, e.passes
        ),
        _ => format!("window {} px, {} passes", e.winsize, e.passes),
    });
    Ok(Verdict {
        status,
        message: reasons.join("; "),
    })
}

/// Why an answer that nothing confirms is no answer, if it is not.
///
/// A flow that needs more than `max_passes`, or is still moving when its passes run out,
/// has a low gain. With weak common structure, or a flow field most of which fits no one
/// similarity, it may also settle on a wrong match far outside its σ, or stop short of the
/// right one. Without the refinement's confirmation there is no reliable answer. Nor when the
/// flow settles but the refinement from its answer runs off: then both checks of that answer
/// fail (docs/validation.md#an-unconfirmed-answer-is-no-answer).
fn unconfirmed(e: &Evidence, inlier_fraction: f64, cfg: &EngineConfig) -> Option<String> {
    if e.refinement.accepted {
        return None;
    }
    let slow_flow = e.unsettled_px.is_some() || e.passes > cfg.max_passes.max(1);
    let weak = e
        .correlation
        .filter(|&c| c < cfg.min_correlation)
        .map(|c| format!("the common structure is weak (correlation {c:.3})"));
    let incoherent = (inlier_fraction < cfg.min_inlier_fraction).then(|| {
        format!(
            "only {}/{} flow vectors agree with one similarity",
            e.inliers, e.points
        )
    });
    let why = weak.or(incoherent)?;
    let unconfirmed = match e.unsettled_px {
        Some(moved) => format!(
            "the fine alignment was still moving after {} passes ({moved:.3} px in the last)",
            e.passes
        ),
        None if slow_flow => format!("the fine alignment needed {} passes to settle", e.passes),
        None if e.refinement.ran_off => {
            "the intensity refinement from the flow's answer ran off".to_string()
        }
        None => return None,
    };
    Some(format!("no reliable answer: {why}, and {unconfirmed}"))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn settled() -> Evidence {
        Evidence {
            correlation: Some(0.9),
            similarity: Some(0.9),
            inliers: 90,
            points: 100,
            passes: 2,
            converged: true,
            unsettled_px: None,
            seed_level: None,
            seeded_from: None,
            winsize: 31,
            refinement: Refinement::default(),
        }
    }

    #[test]
    fn a_settled_coherent_match_is_ok_and_names_its_window() {
        let v = verdict(&settled(), vec!["a note".into()], &EngineConfig::default()).unwrap();
        assert_eq!(v.status, Status::Ok);
        assert_eq!(v.message, "a note; window 31 px, 2 passes");
        // The level the passes ran on, and the seed's, as docs/method.md names them.
        let binned = Evidence {
            seed_level: Some(1),
            seeded_from: Some(2),
            ..settled()
        };
        let v = verdict(&binned, Vec::new(), &EngineConfig::default()).unwrap();
        assert_eq!(
            v.message,
            "window 31 px, 2 passes on pyramid level 1 from a seed on level 2"
        );
        let full = Evidence {
            seeded_from: Some(2),
            ..settled()
        };
        let v = verdict(&full, Vec::new(), &EngineConfig::default()).unwrap();
        assert_eq!(
            v.message,
            "window 31 px, 2 passes from a seed on pyramid level 2"
        );
    }

    #[test]
    fn unrelated_structure_gives_no_answer() {
        let e = Evidence {
            correlation: Some(0.05),
            ..settled()
        };
        let why = verdict(&e, Vec::new(), &EngineConfig::default()).unwrap_err();
        assert!(why.starts_with("no common structure"), "{why}");
    }

    #[test]
    fn weak_structure_and_a_slow_flow_unconfirmed_give_no_answer() {
        let e = Evidence {
            correlation: Some(0.2),
            passes: 12,
            converged: false,
            ..settled()
        };
        let why = verdict(&e, Vec::new(), &EngineConfig::default()).unwrap_err();
        assert_eq!(
            why,
            "no reliable answer: the common structure is weak (correlation 0.200), and the fine \
             alignment needed 12 passes to settle"
        );
        // The refinement's confirmation makes it an answer, degraded for the structure.
        let confirmed = Evidence {
            refinement: Refinement {
                note: Some("refined".into()),
                accepted: true,
                ..Refinement::default()
            },
            ..e
        };
        let v = verdict(&confirmed, Vec::new(), &EngineConfig::default()).unwrap();
        assert_eq!(v.status, Status::Degraded);
        assert_eq!(
            v.message,
            "weak common structure (correlation 0.200); refined; window 31 px, 12 passes"
        );
    }

    #[test]
    fn each_degraded_condition_gives_its_reason_in_order() {
        let e = Evidence {
            similarity: Some(0.1),
            unsettled_px: Some(0.25),
            converged: false,
            passes: 4,
            seed_level: Some(2),
            seeded_from: None,
            refinement: Refinement {
                note: Some("refinement refused".into()),
                disagrees: true,
                ..Refinement::default()
            },
            ..settled()
        };
        let v = verdict(&e, vec!["a note".into()], &EngineConfig::default()).unwrap();
        assert_eq!(v.status, Status::Degraded);
        let reasons: Vec<&str> = v.message.split("; ").collect();
        assert_eq!(
            reasons,
            [
                "low histogram similarity 0.100",
                "the fine alignment was still moving (0.250 px in its last pass)",
                "σ include that step",
                "the flow and the intensity refinement disagree",
                "σ include their difference",
                "a note",
                "fine alignment did not converge to 0.0002 px in 4 passes",
                "refinement refused",
                "window 31 px, 4 passes finished on pyramid level 2",
            ]
        );
    }

    #[test]
    fn incoherent_vectors_degrade_a_settled_flow_and_fail_an_unsettled_one() {
        let e = Evidence {
            inliers: 40,
            ..settled()
        };
        let v = verdict(&e, Vec::new(), &EngineConfig::default()).unwrap();
        assert_eq!(v.status, Status::Degraded);
        assert_eq!(
            v.message,
            "only 40/100 flow vectors agree with one similarity; window 31 px, 2 passes"
        );
        let unsettled = Evidence {
            unsettled_px: Some(0.5),
            converged: false,
            ..e
        };
        let why = verdict(&unsettled, Vec::new(), &EngineConfig::default()).unwrap_err();
        assert_eq!(
            why,
            "no reliable answer: only 40/100 flow vectors agree with one similarity, and the \
             fine alignment was still moving after 2 passes (0.500 px in the last)"
        );
    }
}
