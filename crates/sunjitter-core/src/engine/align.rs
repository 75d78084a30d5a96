//! One alignment of a frame to a prepared reference, stage by stage: the frame's own
//! preparation (cleaning, disk check, coarse transform, the Sun's rotation, intensities), the
//! flow or a seed for the refinement, the refinement, the flow's interpolation check, the
//! quality of the match and the verdict.

use super::config::ChannelSettings;
use super::config::EngineConfig;
use super::fine::{
    fine_alignment, flow_reach_px, max_motion_px, Crop, FineResult, FlowRegion, FlowSetup,
    PassStart, UNSETTLED_PASS_FACTOR,
};
use super::frame::{prepare_frame, FrameOwn};
use super::prepared::{made_once, FrameWork, Matched, PreparedReference, ReferenceWork};
use super::region::grown;
use super::seed::{
    binned_alignment, final_level, seed_level, seed_slack_px, Binned, BinnedRun, FINAL_ANTIALIAS,
};
use super::verdict::{verdict, Evidence, Refinement, Verdict};
use super::workspace::Workspace;
use super::{derotate, flow_check, quality};
use super::{model, refine, AlignOutcome, Image, Pixels, SigmaMethod};
use crate::flow::Roi;
use crate::geometry::{sigmas, Similarity};
use crate::meta::FrameMeta;
use crate::preprocess::{self, BlockMeans};
use crate::record::{AlignResult, SolarRotationFields, TransformFields};
use ndarray::{s, Array2, ArrayView2};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::Instant;

impl PreparedReference {
    /// Align `frame` to the prepared reference.
    pub fn align(&self, frame: &Image) -> AlignOutcome {
        self.align_with(frame, &self.cfg.channel_settings())
    }

    /// Align `frame` with its channel's own settings.
    pub fn align_with(&self, frame: &Image, settings: &ChannelSettings) -> AlignOutcome {
        self.align_inner(
            &frame.meta,
            Pixels::from(frame.data.view()),
            settings,
            false,
        )
        .0
    }

    /// As [`PreparedReference::align_with`], and the work done on `frame` that preparing it
    /// as a reference would repeat (`None` when the alignment failed).
    pub fn align_keeping(
        &self,
        frame: &Image,
        settings: &ChannelSettings,
    ) -> (AlignOutcome, Option<FrameWork>) {
        self.align_inner(&frame.meta, Pixels::from(frame.data.view()), settings, true)
    }

    fn align_inner(
        &self,
        frame_meta: &FrameMeta,
        frame_data: Pixels<'_>,
        settings: &ChannelSettings,
        keep: bool,
    ) -> (AlignOutcome, Option<FrameWork>) {
        let started = Instant::now();
        // Against an unusable reference the frame is not worth cleaning.
        let own = self
            .work
            .as_ref()
            .map_err(Clone::clone)
            .and_then(|_| FrameOwn::new(frame_meta, frame_data, self.cfg.hot_pixel_fraction));
        self.align_own(frame_meta, own, settings, keep, started)
    }

    /// [`PreparedReference::align_inner`] from the frame's own preparation, made beforehand
    /// (`Err`: the frame is unusable).
    pub(super) fn align_own(
        &self,
        frame_meta: &FrameMeta,
        own: Result<FrameOwn, String>,
        settings: &ChannelSettings,
        keep: bool,
        started: Instant,
    ) -> (AlignOutcome, Option<FrameWork>) {
        let first = self
            .aligned
            .fetch_add(1, std::sync::atomic::Ordering::Relaxed)
            == 0;
        let cfg = self.cfg.for_channel(settings);
        let result = match &self.work {
            Ok(work) => {
                own.and_then(|own| align_frame(work, frame_meta, own, &cfg, keep, &self.workspace))
            }
            Err(reason) => Err(reason.clone()),
        };
        let (result, kept) = match result {
            Ok((outcome, kept)) => (Ok(outcome), kept),
            Err(e) => (Err(e), None),
        };
        // A reference that serves many frames (a keyframe, a fixed file) keeps its own
        // self-test: its cases are handed on only along a chain.
        let kept = kept.map(|k| FrameWork {
            self_test: k.self_test.filter(|_| first),
            ..k
        });
        let mut outcome = result.unwrap_or_else(|reason| {
            AlignOutcome::failed(&self.file, &crate::text::path(&frame_meta.file), &reason)
        });
        outcome.reference_geometry = self.geometry();
        outcome.result.elapsed_ms = started.elapsed().as_secs_f64() * 1e3;
        (outcome, kept)
    }
}

/// Align `frame` to the prepared reference `work`; with `keep`, also the work on the frame
/// that preparing it as a reference would repeat.
pub(super) fn align_frame(
    work: &ReferenceWork,
    frame: &FrameMeta,
    own: FrameOwn,
    cfg: &EngineConfig,
    keep: bool,
    workspace: &Workspace,
) -> Result<(AlignOutcome, Option<FrameWork>), String> {
    let started = Instant::now();
    let side = prepare_frame(work, frame, own, cfg, keep, started)?;
    let (h, w) = work.cleaned.dim();
    let partial = !derotate::holds_the_disk(work.reference_check.disk_px, w, h);
    let pair = Pair {
        work,
        frame,
        frame_meta: &side.meta,
        frame_data: &side.data,
        frame_means: side.block_means.as_deref(),
        cfg,
        workspace,
        started,
    };
    let coarse = side.coarse;
    let first = measure(
        &pair,
        Start {
            coarse,
            carried: side.carried.as_ref(),
            solar_rotation: side.solar_rotation,
        },
        side.notes.clone(),
    );
    // A partial field has no disk to check its header pointing against: where that pointing
    // leads to no match, the frame is measured from the reference's pointing instead.
    let moved = max_motion_px(&coarse.recentered(Similarity::array_center(w, h)), 0.0);
    let outcome = match first {
        Err(why) if partial && moved > 1.0 => {
            let still = Similarity {
                dx: 0.0,
                dy: 0.0,
                ..coarse.recentered(Similarity::array_center(w, h))
            };
            let mut notes = side.notes.clone();
            notes.push(format!(
                "the header pointing ({moved:.1} px from the reference's) led to no match ({why}); \
                 measured from the reference's pointing, the Sun's rotation not removed"
            ));
            let start = Start {
                coarse: still,
                carried: None,
                solar_rotation: None,
            };
            measure(&pair, start, notes).map_err(|_| why)
        }
        other => other,
    }?;
    let Measured { outcome, self_test } = outcome;
    let kept = side.kept_check.map(|(check, notes)| FrameWork {
        cleaned: side.kept_cleaned.unwrap_or(side.data),
        fill: side.fill,
        check,
        notes,
        hot_pixel_fraction: cfg.hot_pixel_fraction,
        self_test,
    });
    Ok((outcome, kept))
}

/// What every measurement of one frame against the reference reads.
struct Pair<'a> {
    work: &'a ReferenceWork,
    /// The frame's header as read.
    frame: &'a FrameMeta,
    frame_meta: &'a FrameMeta,
    frame_data: &'a Array2<f32>,
    /// `frame_data` binned already by some factor.
    frame_means: Option<&'a BlockMeans>,
    cfg: &'a EngineConfig,
    workspace: &'a Workspace,
    started: Instant,
}

/// Where a measurement starts from.
struct Start<'a> {
    coarse: Similarity,
    carried: Option<&'a derotate::Carried>,
    solar_rotation: Option<SolarRotationFields>,
}

/// One measurement: flow (or seed), refinement, interpolation check, quality, verdict.
fn measure(pair: &Pair, start: Start, mut notes: Vec<String>) -> Result<Measured, String> {
    let cfg = pair.cfg;
    let stage = Stages::new(pair, start.coarse, start.carried);
    let flow_and_run = || -> Result<(FineResult, Option<FirstRun>), String> {
        let mut fine = stage.flow_or_seed()?;
        let run = stage.refining.then(|| stage.run_refinement(&mut fine));
        Ok((fine, run))
    };
    // The reference's self-test needs nothing of the frame: it runs beside the flow and the
    // refinement's run, on the cores their serial parts leave idle, and the refinement's σ
    // that needs it comes after both.
    let (mut fine, run) = match stage.self_test_ahead {
        true => rayon::join(flow_and_run, || stage.self_test_cases()).0?,
        false => flow_and_run()?,
    };
    let refinement = match run {
        Some(run) => stage.refine(&mut fine, run)?,
        None => Refinement::default(),
    };
    // The flow's answer is final: its σ must cover its own interpolation bias, which the
    // scatter of its vectors does not show (see `flow_check`). The check and the quality
    // checks read the same answer, side by side.
    let fine_at = pair.started.elapsed();
    let (similarity, correlation) = if !stage.refining && cfg.sigma == SigmaMethod::Calibrated {
        let (term, quality) = rayon::join(
            || stage.flow_interpolation_term(&fine),
            || stage.quality(&fine),
        );
        notes.push(widened_by_flow_check(term, &mut fine));
        quality
    } else {
        stage.quality(&fine)
    };
    tracing::debug!(?fine_at, quality_at = ?pair.started.elapsed(), "frame aligned");
    let evidence = Evidence {
        correlation,
        similarity,
        inliers: fine.fit.n_inliers,
        points: fine.points,
        passes: fine.passes,
        converged: fine.converged,
        unsettled_px: fine.unsettled_px,
        seed_level: fine.seed_level,
        seeded_from: fine.seeded_from,
        winsize: pair.work.winsize,
        refinement,
    };
    // Scale and roll where the images measure them worse than the instrument holds them:
    // the headers' values.
    let prior = cfg.model_prior();
    let (model, why) = model::choose(&fine.transform, &fine.covariance, &start.coarse, &prior);
    model::constrain(
        &mut fine.transform,
        &mut fine.covariance,
        model,
        &start.coarse,
        &prior,
    );
    notes.extend(why);
    let verdict = verdict(&evidence, notes, cfg)?;
    let outcome = outcome(
        pair,
        &fine,
        start.coarse,
        start.solar_rotation,
        similarity,
        model,
        verdict,
    );
    // A frame that matched well hands the reference's self-test on, should it become the
    // next reference: cases run ahead once the refinement has used them, as on demand.
    let self_test = (outcome.result.status == crate::record::Status::Ok
        && (!stage.self_test_ahead || stage.self_test_used.load(Ordering::Relaxed)))
    .then(|| stage.matched.self_test_to_hand_on())
    .flatten();
    Ok(Measured { outcome, self_test })
}

/// The refinement's first run from the flow's answer, before its σ, and the blur difference
/// it matched.
struct FirstRun {
    blur: Option<crate::blur::BlurDifference>,
    run: Result<refine::RefinementRun, refine::Rejected>,
}

/// The flow's answer as the refinement reads and replaces it.
fn flow_answer(fine: &mut FineResult) -> refine::FlowAnswer<'_> {
    refine::FlowAnswer {
        transform: &mut fine.transform,
        covariance: &mut fine.covariance,
        sample_box: fine.sample_box,
        inliers: &fine.inliers,
        slack_px: fine.seed_level.map_or(0.0, seed_slack_px),
    }
}

/// One measurement's outcome, and the reference's self-test cases it leaves to hand on.
struct Measured {
    outcome: AlignOutcome,
    self_test: Option<(f64, refine::SelfTestCases)>,
}

/// The stages of one measurement and what they share: the reference matched to the frame's
/// resolution, the frame's smoothing, where the flow samples, where it starts.
struct Stages<'a> {
    pair: &'a Pair<'a>,
    matched: Arc<Matched>,
    /// Gaussian σ that brings the frame to the reference's resolution, px.
    sig_frame: f64,
    /// Between channels: the reference's disk (centre, radius px), whose limb the flow's
    /// windows must stay clear of.
    limb: Option<([f64; 2], f64)>,
    refining: bool,
    coarse: Similarity,
    carried: Option<&'a derotate::Carried>,
    /// The refinement's σ will need the reference's self-test, and it has not run yet.
    self_test_ahead: bool,
    /// The refinement has read the self-test's floor.
    self_test_used: AtomicBool,
}

impl<'a> Stages<'a> {
    fn new(
        pair: &'a Pair<'a>,
        coarse: Similarity,
        carried: Option<&'a derotate::Carried>,
    ) -> Stages<'a> {
        let (work, frame, cfg) = (pair.work, pair.frame, pair.cfg);
        // Resolution matching: degrade the sharper image to the other's resolution.
        let plate = work.reference_check.meta.plate_scale_arcsec[0].abs();
        let grid_plate = plate;
        let frame_plate_on_grid = pair.frame_meta.plate_scale_arcsec[0].abs();
        let (sig_ref, sig_frame) = preprocess::resolution_matching_sigmas(
            preprocess::nyquist_fwhm_arcsec(plate),
            preprocess::nyquist_fwhm_arcsec(frame_plate_on_grid),
            grid_plate,
        );
        let matched = work.matched(sig_ref);
        let refining = refine::wanted(cfg.refine, &work.meta, frame);
        // Between channels the limb is no common structure: each channel brightens towards it
        // by its own amount and shows it at its own height, even on one telescope. Windows
        // that reach it read that as a scale change
        // (docs/validation.md#between-channels-windows-clear-of-the-limb).
        let limb = work
            .reference_check
            .disk_px
            .filter(|_| work.meta.channel != frame.channel);
        let self_test_ahead =
            refining && cfg.sigma == SigmaMethod::Calibrated && matched.self_test.get().is_none();
        Stages {
            pair,
            matched,
            sig_frame,
            limb,
            refining,
            coarse,
            carried,
            self_test_ahead,
            self_test_used: AtomicBool::new(false),
        }
    }

    /// The reference at the frame's resolution.
    fn reference(&self) -> ArrayView2<'_, f32> {
        self.matched.view(self.pair.work)
    }

    fn region(&self) -> FlowRegion<'_> {
        FlowRegion {
            mask: &self.pair.work.mask,
            // The circle inside the limb the flow's vectors must lie in.
            sample_within: self.limb.map(|(centre, radius)| {
                let reach = flow_reach_px(self.pair.work.winsize, self.pair.cfg.poly_n);
                (centre, radius - reach)
            }),
        }
    }

    /// What the flow runs of this measurement share.
    fn flow_setup(&self) -> FlowSetup<'a> {
        FlowSetup {
            winsize: self.pair.work.winsize,
            frame_smoothing_px: self.sig_frame,
            carried: self.carried,
            cfg: self.pair.cfg,
            workspace: self.pair.workspace,
        }
    }

    /// The fine stage at full resolution from `start`.
    fn flow_from(&self, start: PassStart, max_passes: usize) -> Result<FineResult, String> {
        fine_alignment(
            self.reference(),
            self.pair.frame_data,
            self.region(),
            start,
            max_passes,
            self.flow_setup(),
        )
        .map_err(|e| e.to_string())
    }

    fn full_flow(&self) -> Result<FineResult, String> {
        self.flow_from(PassStart::Coarse(self.coarse), self.pair.cfg.max_passes)
    }

    /// On a large frame the flow starts on binned copies. When the refinement follows, that
    /// seed is all it needs (should the refinement not be taken, the flow runs at full
    /// resolution after all). When the flow's answer is final, passes carry on from the seed,
    /// in place of a first pass with the whole pyramid over the full grid: the seed costs less
    /// and the passes converge to the same answer
    /// (docs/validation.md#between-channels-full-resolution-passes-from-a-seed). They run on
    /// copies binned to the level where the mask still spans `final_extent_px`, full
    /// resolution on smaller frames
    /// (docs/validation.md#between-channels-the-answer-on-binned-copies).
    fn flow_or_seed(&self) -> Result<FineResult, String> {
        let (work, cfg) = (self.pair.work, self.pair.cfg);
        let seed_level = seed_level(work.mask_box, cfg);
        if seed_level == 0 {
            return self.full_flow();
        }
        let binned = made_once(&self.matched.binned, || {
            Binned::new(
                self.reference(),
                self.matched.block_means(work),
                &work.mask,
                seed_level,
                work.trend_px(),
                0.0,
            )
        });
        let final_level = final_level(work.mask_box, cfg).min(seed_level - 1);
        let binned_final = || {
            made_once(&self.matched.binned_final, || {
                let antialias_px = FINAL_ANTIALIAS * (1usize << final_level) as f64;
                Binned::new(
                    self.reference(),
                    None,
                    &work.mask,
                    final_level,
                    work.trend_px(),
                    antialias_px,
                )
            })
        };
        let seeded = || self.on_binned(binned, BinnedRun::Seed(self.coarse));
        // The reference's copies for the final passes need nothing of the seed: made beside it.
        let seed = match !self.refining && final_level > 0 {
            true => rayon::join(seeded, binned_final).0,
            false => seeded(),
        };
        // Binned copies can lack what the full frame has (too few vectors, say).
        let Ok(seed) = seed else {
            return self.full_flow();
        };
        if self.refining {
            return Ok(seed);
        }
        let mut fine = if final_level == 0 {
            self.flow_from(PassStart::Seed(seed.transform), cfg.max_passes)?
        } else {
            match self.on_binned(binned_final(), BinnedRun::Final(seed.transform)) {
                Ok(fine) => fine,
                Err(_) => return self.full_flow(),
            }
        };
        // A seed that the passes moved further than a seed on its level can be off misled
        // them (binned copies can, on weak structure): the whole pyramid from the coarse start
        // after all. Passes that only wander, as they would from any start, are kept.
        let moved = motion_within(&seed.transform, &fine.transform, work.mask_box);
        if fine.converged || moved <= seed_slack_px(seed_level) {
            fine.seeded_from = Some(seed_level);
            Ok(fine)
        } else {
            self.full_flow()
        }
    }

    /// The flow on `binned` copies of the reference and the frame.
    fn on_binned(&self, binned: &Binned, run: BinnedRun) -> Result<FineResult, String> {
        let pair = self.pair;
        binned_alignment(
            binned,
            pair.work.cleaned.dim(),
            (pair.frame_data, pair.frame_means),
            run,
            self.limb,
            self.flow_setup(),
        )
    }

    /// The blur difference between the reference and the frame around the mask's centre.
    fn blur_of(&self, fine: &FineResult) -> Option<crate::blur::BlurDifference> {
        let mask_box = self.pair.work.mask_box;
        let centre = [
            mask_box.x as f64 + (mask_box.width as f64 - 1.0) / 2.0,
            mask_box.y as f64 + (mask_box.height as f64 - 1.0) / 2.0,
        ];
        let side = mask_box.width.min(mask_box.height);
        let reference = made_once(&self.matched.spectrum, || {
            crate::blur::RadialSpectrum::around(self.reference(), centre, side)
        })
        .as_ref()?;
        let at = match self.carried {
            Some(c) => {
                let (x, y) = c.then(&fine.transform)(centre[0], centre[1]);
                [x, y]
            }
            None => fine.transform.apply(centre),
        };
        let frame = crate::blur::RadialSpectrum::moved(
            self.pair.frame_data.view(),
            reference,
            [at[0] - centre[0], at[1] - centre[1]],
        )?;
        crate::blur::blur_difference(reference, &frame, fine.transform.scale)
    }

    /// The intensity refinement from the flow's answer; it replaces that answer when taken.
    fn try_refine(&self, fine: &mut FineResult) -> Result<String, refine::Rejected> {
        let run = self.run_refinement(fine);
        self.settle_refinement(fine, run)
    }

    /// The refinement from the flow's answer up to its σ, with the blur difference it
    /// matched: what needs nothing of the reference's self-test.
    fn run_refinement(&self, fine: &mut FineResult) -> FirstRun {
        let measured = Instant::now();
        let blur = self.blur_of(fine);
        tracing::debug!(?blur, took = ?measured.elapsed(), "blur difference");
        let run = refine::run_refinement(&flow_answer(fine), &self.refine_inputs(blur));
        FirstRun { blur, run }
    }

    /// The refinement's σ, with the reference's self-test, and its answer taken or refused.
    fn settle_refinement(
        &self,
        fine: &mut FineResult,
        first: FirstRun,
    ) -> Result<String, refine::Rejected> {
        refine::settle(
            first.run?,
            flow_answer(fine),
            &self.refine_inputs(first.blur),
            |settings| {
                debug_assert_eq!(*settings, self.refine_settings());
                self.self_test_used.store(true, Ordering::Relaxed);
                self.self_test_cases().map(refine::SelfTestCases::floor)
            },
        )
    }

    /// The pair as the refinement reads it.
    fn refine_inputs(&self, blur: Option<crate::blur::BlurDifference>) -> refine::RefineInputs<'_> {
        let (work, cfg) = (self.pair.work, self.pair.cfg);
        refine::RefineInputs {
            reference: self.reference(),
            prepared: self.refine_reference(),
            frame: self.pair.frame_data.view(),
            mask: &work.mask,
            mask_box: work.mask_box,
            frame_smoothing_px: self.sig_frame,
            blur,
            carried: self.carried,
            cfg,
        }
    }

    /// The settings the refinement of this pair starts from (before any blur matching).
    fn refine_settings(&self) -> refine::RefineSettings {
        refine::settings(self.pair.cfg, self.sig_frame)
    }

    /// The reference as the refinement reads it (made on first use).
    fn refine_reference(&self) -> &refine::RefineReference {
        made_once(&self.matched.refine_reference, || {
            // Every pixel the refinement, its self-test and its checks fit lies in the mask.
            let m = self.pair.work.mask_box;
            let bbox = (m.x, m.y, m.x + m.width - 1, m.y + m.height - 1);
            let settings = refine::settings(self.pair.cfg, 0.0);
            refine::RefineReference::within(self.reference(), &settings, bbox)
        })
    }

    /// The reference's self-test cases (run on first use).
    fn self_test_cases(&self) -> Option<&refine::SelfTestCases> {
        made_once(&self.matched.self_test, || {
            self.self_test(self.refine_reference(), &self.refine_settings())
        })
        .as_ref()
    }

    /// The reference's self-test cases: from the cases handed on along a chain, or kept by
    /// the caller's store from an earlier run on this same reference, or run afresh.
    fn self_test(
        &self,
        prepared: &refine::RefineReference,
        settings: &refine::RefineSettings,
    ) -> Option<refine::SelfTestCases> {
        let (work, cfg) = (self.pair.work, self.pair.cfg);
        let handed_on = self.matched.handed_on(work);
        let run = || {
            refine::self_test_floor(
                self.reference(),
                prepared,
                &work.mask,
                cfg.sample,
                settings,
                work.structure_px,
                handed_on,
            )
        };
        // Cases handed on depend on the chain before this reference: not kept.
        let store = self.pair.workspace.self_tests();
        let Some(store) = store.filter(|_| handed_on.is_none()) else {
            return run();
        };
        let key = refine::SelfTestKey::new(
            self.reference(),
            &work.mask,
            cfg.sample,
            settings,
            work.structure_px,
            &format!("{cfg:?}"),
        );
        if let Some(kept) = store.load(&key).filter(refine::SelfTestCases::is_sound) {
            tracing::debug!(key = key.hex(), "self-test cases kept from an earlier run");
            return Some(kept);
        }
        let cases = run();
        if let Some(cases) = &cases {
            store.save(&key, cases);
        }
        cases
    }

    /// The refinement from its first run, retried from a full-resolution or longer flow when
    /// refused; what the verdict needs to know of it.
    fn refine(&self, fine: &mut FineResult, first: FirstRun) -> Result<Refinement, String> {
        let cfg = self.pair.cfg;
        let mut outcome = self.settle_refinement(fine, first);
        if outcome.is_err() {
            if fine.seed_level.is_some() {
                *fine = self.full_flow()?;
            }
            // A flow still moving by more than its σ when its passes ran out is mostly
            // converging slowly: weak or noisy structure lowers its gain, and each pass
            // recovers only part of what is left. More passes, then the refinement again.
            // Only here: on real frames that the refinement accepts after the first passes,
            // more passes can wander off where the structure changes
            // (docs/validation.md#extra-passes-for-an-unsettled-flow).
            if fine.unsettled_px.is_some() {
                let mut more = self.flow_from(
                    PassStart::Coarse(fine.transform),
                    cfg.max_passes.max(1) * (UNSETTLED_PASS_FACTOR - 1),
                )?;
                more.passes += fine.passes;
                *fine = more;
                outcome = self.try_refine(fine);
            }
        }
        Ok(match outcome {
            Ok(note) => {
                fine.unsettled_px = None;
                Refinement {
                    note: Some(note),
                    accepted: true,
                    ..Refinement::default()
                }
            }
            Err(rejected) => {
                // Two measurements of one motion that disagree beyond their σ: the flow's
                // answer stays, and its σ grow to cover the refinement's (either may be the
                // wrong one; docs/validation.md#a-disagreement-keeps-the-flows-answer).
                let disagrees = rejected.disagreeing.is_some();
                if let Some(refined) = rejected.disagreeing {
                    let (a, b) = (fine.transform.params(), refined.params());
                    for k in 0..4 {
                        fine.covariance[k][k] += (a[k] - b[k]).powi(2);
                    }
                }
                Refinement {
                    note: Some(rejected.note),
                    accepted: false,
                    ran_off: rejected.ran_off,
                    disagrees,
                }
            }
        })
    }

    /// The flow's interpolation check: the σ its answer must cover beyond the scatter of its
    /// vectors. An answer measured on binned copies is checked on them.
    fn flow_interpolation_term(&self, fine: &FineResult) -> Option<[f64; 4]> {
        let checked = Instant::now();
        let (work, cfg) = (self.pair.work, self.pair.cfg);
        let binned = fine
            .seed_level
            .filter(|&level| level > 0)
            .and_then(|level| self.matched.binned_at(level));
        let region = match binned {
            Some(binned) => binned.region(self.limb, work.winsize, cfg),
            None => self.region(),
        };
        let term = flow_check::flow_interpolation_check(
            self.reference(),
            binned,
            region,
            (&fine.transform, &self.coarse),
            self.flow_setup(),
        );
        tracing::debug!(took = ?checked.elapsed(), "flow interpolation check");
        term
    }

    /// Quality of the final match: on the full grid, or for a seed on binned copies on theirs
    /// (the refinement moves the seed's answer by a small fraction of a binned pixel).
    fn quality(&self, fine: &FineResult) -> (Option<f64>, Option<f64>) {
        let work = self.pair.work;
        match fine
            .seed_level
            .and_then(|level| self.matched.binned_at(level))
        {
            Some(binned) => quality_of(
                &QualityGrid {
                    reference: binned.reference.view(),
                    mask: &binned.mask,
                    mask_box: binned.mask_box,
                    high_pass: &binned.high_pass,
                    quality_crop: &binned.quality_crop,
                    trend_px: work.trend_px(),
                },
                fine,
            ),
            _ => {
                let (high_pass, quality_crop) = self.matched.high_pass(work);
                quality_of(
                    &QualityGrid {
                        reference: work.cleaned.view(),
                        mask: &work.mask,
                        mask_box: work.mask_box,
                        high_pass,
                        quality_crop,
                        trend_px: work.trend_px(),
                    },
                    fine,
                )
            }
        }
    }
}

/// Widens the flow's σ by its interpolation check `term`; the note says by how much.
fn widened_by_flow_check(term: Option<[f64; 4]>, fine: &mut FineResult) -> String {
    let Some(term) = term else {
        return "flow interpolation check could not run".to_string();
    };
    for (k, t) in term.iter().enumerate() {
        fine.covariance[k][k] += t * t;
    }
    format!(
        "flow interpolation check {:.1e} / {:.3}″ / {:.1e} / {:.1e} px",
        term[0],
        term[1] * crate::geometry::ARCSEC_PER_RAD,
        term[2],
        term[3]
    )
}

/// The engine's answer from the fine stage's result and the verdict on it.
fn outcome(
    pair: &Pair,
    fine: &FineResult,
    coarse: Similarity,
    solar_rotation: Option<SolarRotationFields>,
    similarity: Option<f64>,
    model: model::Model,
    verdict: Verdict,
) -> AlignOutcome {
    let work = pair.work;
    let t = fine.transform;
    let sig = sigmas(&fine.covariance);
    let usig = sigmas(&fine.uabjm_covariance);
    let header_residual = coarse.inverse().after(&t);
    // The plate scale the alignment used: the header's, or the disk-checked one where the
    // header's was refused.
    let ps = work.reference_check.meta.plate_scale_arcsec;
    let result = AlignResult {
        reference: crate::text::path(&work.meta.file).into_owned(),
        frame: crate::text::path(&pair.frame.file).into_owned(),
        scale: Some(t.scale),
        rotation_arcsec: Some(t.rotation_arcsec()),
        dx_px: Some(t.dx),
        dy_px: Some(t.dy),
        dx_arcsec: Some(t.dx * ps[0]),
        dy_arcsec: Some(t.dy * ps[1]),
        sigma_scale: Some(sig[0]),
        sigma_rotation_arcsec: Some(sig[1] * crate::geometry::ARCSEC_PER_RAD),
        sigma_dx_px: Some(sig[2]),
        sigma_dy_px: Some(sig[3]),
        sigma_dx_arcsec: Some(sig[2] * ps[0].abs()),
        sigma_dy_arcsec: Some(sig[3] * ps[1].abs()),
        uabjm_sigma_scale: Some(usig[0]),
        uabjm_sigma_rotation_arcsec: Some(usig[1] * crate::geometry::ARCSEC_PER_RAD),
        uabjm_sigma_dx_px: Some(usig[2]),
        uabjm_sigma_dy_px: Some(usig[3]),
        header_residual: Some(TransformFields {
            scale: header_residual.scale,
            rotation_arcsec: header_residual.rotation_arcsec(),
            dx_px: header_residual.dx,
            dy_px: header_residual.dy,
        }),
        solar_rotation,
        points: fine.points,
        inliers: fine.fit.n_inliers,
        residual_rms_px: Some(fine.fit.residual_rms_px),
        similarity,
        model: Some(model),
        status: verdict.status,
        message: verdict.message,
        elapsed_ms: 0.0,
    };
    AlignOutcome {
        result,
        transform: Some(t),
        coarse: Some(coarse),
        covariance: Some(fine.covariance),
        uabjm_covariance: Some(fine.uabjm_covariance),
        mask: Some(work.mask.clone()),
        reference_geometry: Some(work.geometry()),
    }
}

/// The grid the quality checks compare on: the reference's, or binned copies of it.
struct QualityGrid<'a> {
    reference: ArrayView2<'a, f32>,
    mask: &'a Array2<bool>,
    mask_box: Roi,
    high_pass: &'a Array2<f32>,
    quality_crop: &'a Crop,
    trend_px: f64,
}

/// Bhattacharyya similarity of the histograms and rank correlation of the structure between
/// the reference and the frame as aligned (`fine.warped`, on the same grid).
fn quality_of(q: &QualityGrid, fine: &FineResult) -> (Option<f64>, Option<f64>) {
    let (h, w) = q.reference.dim();
    let (rows, cols) = grown(q.mask_box, 0.0, w, h);
    let similarity = || {
        fine.warped_at(rows.clone(), cols.clone())
            .and_then(|warped| {
                quality::bhattacharyya(
                    q.reference.slice(s![rows.clone(), cols.clone()]),
                    warped,
                    q.mask.slice(s![rows.clone(), cols.clone()]),
                )
            })
    };
    let crop = &q.quality_crop;
    let correlation = || {
        fine.warped_at(crop.rows.clone(), crop.cols.clone())
            .and_then(|warped| {
                quality::rank_correlation(
                    q.high_pass.view(),
                    quality::high_pass(warped, q.trend_px).view(),
                    q.mask.slice(s![crop.rows.clone(), crop.cols.clone()]),
                )
            })
    };
    // Independent, and each partly serial: side by side.
    rayon::join(similarity, correlation)
}

/// The farthest any point of `roi` lands apart under `a` and `b`, px: at one of its corners, a
/// similarity's displacement field being affine.
fn motion_within(a: &Similarity, b: &Similarity, roi: Roi) -> f64 {
    let (x0, y0) = (roi.x as f64, roi.y as f64);
    let (x1, y1) = (x0 + roi.width as f64 - 1.0, y0 + roi.height as f64 - 1.0);
    [[x0, y0], [x1, y0], [x0, y1], [x1, y1]]
        .iter()
        .map(|&p| {
            let (pa, pb) = (a.apply(p), b.apply(p));
            (pa[0] - pb[0]).hypot(pa[1] - pb[1])
        })
        .fold(0.0, f64::max)
}
