//! Reference policies: which image each frame of a channel is aligned to, and the chained
//! ("absolute") pointing series built from those alignments.
//!
//! Everything here is deterministic given the frames of a channel in observation-time order
//! (and, for `channel:NAME`, the partner frame the scheduler picked), which is what makes
//! `replay` write the same messages as the daemon.

use std::sync::Arc;
use sunjitter_core::chain::IDENTITY;
use sunjitter_core::chain::{
    carried, chain_after, chain_after_carrying, chain_from_message, combine, combined_cross,
    set_chain, Chain,
};
use sunjitter_core::engine::{AlignOutcome, Image};
use sunjitter_core::geometry::{Matrix4, Similarity};
use sunjitter_core::record::{AlignResult, FrameAlignment, ReferenceKind, Status, TransformFields};
use sunjitter_core::time::format_iso_utc as iso8601_utc;
use sunjitter_io::fits::FrameSpec;
use sunjitter_io::fits::{frame_key, parse_frame_key};
use sunjitter_io::records::Record;
use sunjitter_io::sink::LogLevel;
use sunjitter_io::sink::{ReferenceChange, ReferenceClosure};

/// Covariance of (scale, rotation_rad, dx_px, dy_px).
pub type Cov4 = sunjitter_core::geometry::Covariance4;

mod history;
mod policy;

pub use history::History;
pub use policy::{ChannelPolicy, KeyframeDue, PolicySpec, ReferencePolicies};

// ---------------------------------------------------------------------------------------------
// What the state machine is given and gives back

/// What a policy step needs from the outside world: the engine and image reading.
pub trait StepContext {
    fn align(&self, reference: &Image, frame: &Image) -> AlignOutcome;
    /// As [`StepContext::align`], to a reference at `position` along its chain (its
    /// sequence number in the log).
    fn align_at(&self, reference: &Image, _position: u64, frame: &Image) -> AlignOutcome {
        self.align(reference, frame)
    }
    fn load(&self, spec: &FrameSpec) -> sunjitter_core::Result<Image>;
    /// Why `image` cannot start a reference, if it cannot (the aligner's requirements).
    fn usable_as_reference(&self, _image: &Image) -> Result<(), String> {
        Ok(())
    }
    /// The plate scale alignments to `image` use (arcsec/px; by default the header's).
    fn plate_scale_used(&self, image: &Image) -> Option<[f64; 2]> {
        Some(image.meta.plate_scale_arcsec)
    }
    /// The geometry alignments to `image` use, where it is not the header's.
    fn geometry_used(&self, _image: &Image) -> Option<sunjitter_core::engine::UsedGeometry> {
        None
    }
}

/// A frame ready to be aligned.
#[derive(Debug, Clone)]
pub struct LoadedFrame {
    pub key: String,
    pub spec: FrameSpec,
    pub obs_time_ns: i64,
    pub image: Arc<Image>,
}

/// A processed frame of a partner channel, as a candidate reference for `channel:NAME`.
#[derive(Debug, Clone, PartialEq)]
pub struct PartnerFrame {
    pub channel: String,
    pub key: String,
    pub spec: FrameSpec,
    pub obs_time_ns: i64,
    /// The partner frame's own chained pointing, if it has one.
    pub chain: Option<Chain>,
}

/// A reference slot: the image is loaded lazily (it may come from a restored log).
#[derive(Debug, Clone)]
struct RefSlot {
    key: String,
    spec: FrameSpec,
    obs_time_ns: i64,
    chain: Option<Chain>,
    image: Option<Arc<Image>>,
    /// Restart: the chain as the reference's own message logged it (σ only); completed with
    /// the image centre when the image is loaded.
    chain_hint: Option<FrameAlignment>,
    /// The reference frame's sequence number, where this run logged it.
    position: Option<u64>,
}

impl RefSlot {
    fn from_frame(frame: &LoadedFrame, chain: Option<Chain>) -> RefSlot {
        RefSlot {
            key: frame.key.clone(),
            spec: frame.spec.clone(),
            obs_time_ns: frame.obs_time_ns,
            chain,
            image: Some(frame.image.clone()),
            chain_hint: None,
            position: None,
        }
    }

    /// The slot of a frame this run logged at `sequence`.
    fn logged_at(mut self, sequence: u64) -> RefSlot {
        self.position = Some(sequence);
        self
    }

    /// A reference known only by name (restart, partner, fixed file): read when needed.
    fn named(key: &str, obs_time_ns: i64, chain: Option<Chain>) -> RefSlot {
        RefSlot {
            key: key.to_string(),
            spec: parse_frame_key(key),
            obs_time_ns,
            chain,
            image: None,
            chain_hint: None,
            position: None,
        }
    }

    /// The image (read on first use). Always called before `chain` is used.
    fn image(&mut self, ctx: &dyn StepContext) -> sunjitter_core::Result<Arc<Image>> {
        if let Some(image) = &self.image {
            return Ok(image.clone());
        }
        let image = Arc::new(ctx.load(&self.spec)?);
        if self.chain.is_none() {
            if let Some(m) = self.chain_hint.take() {
                self.chain = chain_from_message(&m, Some(image_center(&image)));
            }
        }
        self.image = Some(image.clone());
        Ok(image)
    }
}

/// What the state of a channel looked like in an existing log (for restart).
#[derive(Debug, Clone, Default)]
pub struct RestoredChannel {
    pub next_sequence: u64,
    pub last_obs_time_ns: Option<i64>,
    /// The last reference change and its log time.
    pub last_reference: Option<(ReferenceChange, i64)>,
    /// The one before it (the keyframe a new one is also reached through).
    pub previous_reference: Option<(ReferenceChange, i64)>,
    /// The most recent frame messages (ascending sequence) with their log times.
    pub recent: Vec<(FrameAlignment, i64)>,
}

// ---------------------------------------------------------------------------------------------
// The per-channel state machine

/// The reference state of one channel. Frames must be given in observation-time order.
#[derive(Debug)]
pub struct ChannelState {
    pub name: String,
    policy: ChannelPolicy,
    next_sequence: u64,
    last_obs_time_ns: Option<i64>,
    reference: Option<RefSlot>,
    /// Keyframe: the latest frame aligned well to the keyframe (promoted when the match
    /// degrades), with the Jacobian of its chain with respect to the keyframe's.
    candidate: Option<(RefSlot, Matrix4)>,
    /// Keyframe: the keyframe before the current one, and the covariance of the current
    /// keyframe's chain error with its (`Cov(e_current, e_previous)`, where known). A new
    /// keyframe is reached through both, so that one link's error does not stay in the
    /// chain for good, and the two ways' agreement is its closure.
    previous_keyframe: Option<(RefSlot, Option<Cov4>)>,
    frames_on_reference: u32,
    consecutive_failures: u32,
    /// Why the next frame starts a new chain (None: first frame).
    restart_reason: Option<String>,
    /// The last reference announced (for `replaces`).
    announced: Option<String>,
}

/// A processed frame as the scheduler sees it afterwards.
#[derive(Debug, Clone)]
pub struct StepOutput {
    pub records: Vec<Record>,
    /// The frame as a reference for `channel:` followers (every frame that was read).
    pub partner: Option<PartnerFrame>,
}

/// A new keyframe with its chain, the closure of its two ways (where it was reached two
/// ways), and the covariance of its chain's error with the keyframe it replaces'.
struct Linked {
    slot: RefSlot,
    closure: Option<ReferenceClosure>,
    cross: Option<Cov4>,
}

/// The reference a frame was aligned to: the policy's kind and the reference's frame key.
#[derive(Clone, Copy)]
struct AlignedTo<'a> {
    kind: ReferenceKind,
    key: &'a str,
}

/// One emitted frame message and the chain it reported.
struct Emitted {
    message: FrameAlignment,
    chain: Option<Chain>,
}

impl ChannelState {
    pub fn new(name: impl Into<String>, policy: ChannelPolicy) -> ChannelState {
        ChannelState {
            name: name.into(),
            policy,
            next_sequence: 0,
            last_obs_time_ns: None,
            reference: None,
            candidate: None,
            previous_keyframe: None,
            frames_on_reference: 0,
            consecutive_failures: 0,
            restart_reason: None,
            announced: None,
        }
    }

    /// Continue a channel found in an existing log: sequence numbers go on, and the chain
    /// continues from the last recorded reference (its image is re-read when first needed).
    /// Only the σ of the keyframe candidate (not its correlations) survive a restart.
    pub fn restore(
        name: impl Into<String>,
        policy: ChannelPolicy,
        restored: &RestoredChannel,
    ) -> ChannelState {
        let mut state = ChannelState::new(name, policy);
        state.next_sequence = restored.next_sequence;
        state.last_obs_time_ns = restored.last_obs_time_ns;
        let Some((change, change_time)) = &restored.last_reference else {
            return state;
        };
        let key = change.key();
        state.announced = Some(key.clone());
        if change.reference_kind != state.policy.policy.kind() {
            state.restart_reason = Some(format!(
                "policy changed from {} to {}: new chain",
                change.reference_kind,
                state.policy.policy.kind()
            ));
            return state;
        }
        if let PolicySpec::Fixed(_) | PolicySpec::Channel(_) = state.policy.policy {
            // Nothing to continue: the reference is re-read (and re-announced if it changes).
            return state;
        }
        let own_message = |k: &str| {
            restored
                .recent
                .iter()
                .rev()
                .find(|(m, _)| m.align.frame == k)
                .map(|(m, _)| m.clone())
        };
        let after: Vec<&(FrameAlignment, i64)> = restored
            .recent
            .iter()
            .filter(|(m, _)| m.sequence >= change.sequence)
            .collect();
        state.frames_on_reference = after
            .iter()
            .filter(|(m, _)| m.align.reference == key && m.reference_kind != ReferenceKind::Itself)
            .count() as u32;
        state.consecutive_failures = restored
            .recent
            .iter()
            .rev()
            .take_while(|(m, _)| m.align.status == Status::Failed)
            .count() as u32;
        let ref_time = restored
            .recent
            .iter()
            .find(|(m, _)| m.align.frame == key)
            .map_or(*change_time, |(_, t)| *t);
        let mut slot = RefSlot::named(&key, ref_time, change.chain);
        if slot.chain.is_none() {
            slot.chain_hint = own_message(&key);
        }
        state.reference = Some(slot);
        // The keyframe before it, through which the next one is reached too.
        if state.policy.policy == PolicySpec::Keyframe {
            state.previous_keyframe = restored.previous_reference.as_ref().map(|(p, t)| {
                let key = p.key();
                let mut slot = RefSlot::named(&key, *t, p.chain);
                if slot.chain.is_none() {
                    slot.chain_hint = own_message(&key);
                }
                let cross = change.cross_covariance.as_deref().and_then(unflat);
                (slot, cross)
            });
        }
        if state.policy.policy == PolicySpec::Keyframe {
            state.candidate = after
                .iter()
                .rev()
                .find(|(m, _)| {
                    m.align.reference == key
                        && m.align.status == Status::Ok
                        && m.reference_kind != ReferenceKind::Itself
                })
                .map(|(m, t)| {
                    let mut slot = RefSlot::named(&m.align.frame, *t, None);
                    slot.chain_hint = Some(m.clone());
                    // A step between two images of one grid carries the chain unchanged,
                    // to first order.
                    (slot, IDENTITY)
                });
        }
        state
    }

    pub fn policy(&self) -> &ChannelPolicy {
        &self.policy
    }

    pub fn last_obs_time_ns(&self) -> Option<i64> {
        self.last_obs_time_ns
    }

    pub fn next_sequence(&self) -> u64 {
        self.next_sequence
    }

    /// Align one frame according to the policy; returns the records to log, in order.
    /// `partner` is required for `channel:NAME` (the scheduler logs unmatched frames itself).
    pub fn process(
        &mut self,
        frame: &LoadedFrame,
        partner: Option<&PartnerFrame>,
        ctx: &dyn StepContext,
    ) -> StepOutput {
        let mut records = Vec::new();
        let sequence = self.next_sequence;
        let emitted = match self.policy.policy.clone() {
            PolicySpec::Previous => self.step_previous(frame, sequence, ctx, &mut records),
            PolicySpec::Keyframe => self.step_keyframe(frame, sequence, ctx, &mut records),
            PolicySpec::Fixed(file) => self.step_fixed(&file, frame, sequence, ctx, &mut records),
            PolicySpec::Channel(name) => match partner {
                Some(p) => self.step_channel(p, frame, sequence, ctx, &mut records),
                None => {
                    // The scheduler logs unmatched frames itself; never lose one anyway.
                    records.push(Record::log(
                        LogLevel::Error,
                        &frame.key,
                        format!("unmatched: no {name} frame to align to"),
                        frame.obs_time_ns,
                    ));
                    return StepOutput {
                        records,
                        partner: None,
                    };
                }
            },
        };
        self.next_sequence += 1;
        self.last_obs_time_ns = Some(
            self.last_obs_time_ns
                .map_or(frame.obs_time_ns, |t| t.max(frame.obs_time_ns)),
        );
        // Any frame that was read can serve as a partner's reference image; its chain is
        // absent when its own alignment failed.
        let partner = Some(PartnerFrame {
            channel: self.name.clone(),
            key: frame.key.clone(),
            spec: frame.spec.clone(),
            obs_time_ns: frame.obs_time_ns,
            chain: emitted.chain,
        });
        StepOutput { records, partner }
    }

    // -- policies ---------------------------------------------------------------------------

    /// `frame` becomes the origin of a new chain.
    fn start_chain(
        &mut self,
        frame: &LoadedFrame,
        sequence: u64,
        ctx: &dyn StepContext,
        records: &mut Vec<Record>,
    ) -> Emitted {
        // A frame without usable pixels would fail every frame after it.
        if let Err(why) = ctx.usable_as_reference(&frame.image) {
            let why = format!("cannot start a reference: {why}");
            let outcome = AlignOutcome::failed(&frame.key, &frame.key, &why);
            return self.emit(
                frame,
                sequence,
                AlignedTo {
                    kind: ReferenceKind::Itself,
                    key: &frame.key,
                },
                outcome,
                None,
                records,
            );
        }
        let reason = self
            .restart_reason
            .take()
            .unwrap_or_else(|| "first frame".into());
        let chain = Chain::origin(
            image_center(&frame.image),
            ctx.plate_scale_used(&frame.image),
        );
        let slot = RefSlot::from_frame(frame, Some(chain)).logged_at(sequence);
        self.install(slot, frame, sequence, reason, records);
        self.candidate = None;
        self.previous_keyframe = None;
        self.frames_on_reference = 0;
        self.consecutive_failures = 0;
        self.emit_self(frame, sequence, Some(chain), records)
    }

    /// The current reference and its image, taken out of the state; or what the frame gets
    /// instead: the start of a chain (no reference, or one that cannot be read, named `what`
    /// in the reason), or itself when it is the reference.
    fn take_reference(
        &mut self,
        frame: &LoadedFrame,
        sequence: u64,
        ctx: &dyn StepContext,
        records: &mut Vec<Record>,
        what: &str,
    ) -> std::result::Result<(RefSlot, Arc<Image>), Box<Emitted>> {
        let Some(mut reference) = self.reference.take() else {
            return Err(Box::new(self.start_chain(frame, sequence, ctx, records)));
        };
        if reference.key == frame.key {
            let chain = reference.chain;
            self.reference = Some(reference);
            return Err(Box::new(self.emit_self(frame, sequence, chain, records)));
        }
        match reference.image(ctx) {
            Ok(image) => Ok((reference, image)),
            Err(e) => {
                self.restart_reason = Some(format!("{what} unreadable ({e}): new chain"));
                Err(Box::new(self.start_chain(frame, sequence, ctx, records)))
            }
        }
    }

    fn step_previous(
        &mut self,
        frame: &LoadedFrame,
        sequence: u64,
        ctx: &dyn StepContext,
        records: &mut Vec<Record>,
    ) -> Emitted {
        let (reference, ref_image) =
            match self.take_reference(frame, sequence, ctx, records, "previous reference") {
                Ok(taken) => taken,
                Err(emitted) => return *emitted,
            };
        let outcome = match reference.position {
            Some(position) => ctx.align_at(&ref_image, position, &frame.image),
            None => ctx.align(&ref_image, &frame.image),
        };
        let chain = chain_after(reference.chain.as_ref(), &outcome);
        let emitted = self.emit(
            frame,
            sequence,
            AlignedTo {
                kind: ReferenceKind::Previous,
                key: &reference.key,
            },
            outcome,
            chain,
            records,
        );
        if emitted.message.align.status == Status::Failed {
            self.reference = Some(reference);
            self.note_failure();
        } else {
            self.consecutive_failures = 0;
            let slot = RefSlot::from_frame(frame, chain).logged_at(sequence);
            // The first frame aligned to it is the next one.
            self.install(slot, frame, sequence + 1, "previous frame".into(), records);
        }
        emitted
    }

    fn step_keyframe(
        &mut self,
        frame: &LoadedFrame,
        sequence: u64,
        ctx: &dyn StepContext,
        records: &mut Vec<Record>,
    ) -> Emitted {
        let (keyframe, key_image) =
            match self.take_reference(frame, sequence, ctx, records, "keyframe") {
                Ok(taken) => taken,
                Err(emitted) => return *emitted,
            };
        let outcome = ctx.align(&key_image, &frame.image);

        let degraded = self.degraded(&outcome);
        // Hand over to the latest frame that still matched well, then try again. Without
        // one (no frame matched this keyframe well since it was chosen: weak common structure
        // throughout, say), a hand-over to this frame would only add a link to the chain:
        // the frame is measured against the keyframe, which the usual rules refresh.
        let candidate = match degraded {
            Some(_) => self.candidate.take(),
            None => None,
        };
        if let (Some(why), Some((mut candidate, j_candidate))) = (degraded, candidate) {
            let Ok(cand_image) = candidate.image(ctx) else {
                self.reference = Some(keyframe);
                return self.keyframe_result(frame, sequence, outcome, records);
            };
            let reason = format!("match degraded ({why}): promoted the last good frame");
            let outcome = ctx.align(&cand_image, &frame.image);
            let linked = self.linked(&keyframe, candidate, j_candidate, ctx);
            self.install_linked(keyframe, linked, frame, sequence, reason, records);
            return self.keyframe_result(frame, sequence, outcome, records);
        }

        let age_s = (frame.obs_time_ns - keyframe.obs_time_ns) as f64 * 1e-9;
        let due = self.policy.keyframe_due(self.frames_on_reference, age_s);
        if let (Some(due), false) = (due, outcome.result.status == Status::Failed) {
            // This frame becomes the keyframe: logged aligned to itself, its chain goes on.
            let reason = match due {
                KeyframeDue::Count => {
                    format!("refresh every {} frames", self.policy.keyframe_every_frames)
                }
                KeyframeDue::Age => format!("refresh every {} s", self.policy.keyframe_every_s),
            };
            let (chain, j_current) = chain_after_carrying(keyframe.chain.as_ref(), &outcome)
                .map_or((None, IDENTITY), |(c, j)| (Some(c), j));
            let slot = RefSlot::from_frame(frame, chain);
            let linked = self.linked(&keyframe, slot, j_current, ctx);
            let chain = linked.slot.chain;
            self.install_linked(keyframe, linked, frame, sequence, reason, records);
            self.consecutive_failures = 0;
            return self.emit_self(frame, sequence, chain, records);
        }
        self.reference = Some(keyframe);
        self.keyframe_result(frame, sequence, outcome, records)
    }

    /// A new keyframe `slot`, whose chain runs through `keyframe` (`j_current`: its Jacobian
    /// with respect to the keyframe's chain): where the keyframe before that is known, also
    /// reached through that one, the two combined (their agreement is the closure the
    /// `/reference` message reports).
    fn linked(
        &mut self,
        keyframe: &RefSlot,
        mut slot: RefSlot,
        j_current: Matrix4,
        ctx: &dyn StepContext,
    ) -> Linked {
        // Cov(e_new, e_current) for a chain through the current keyframe alone.
        let cross = slot
            .chain
            .and(keyframe.chain)
            .and_then(|c| c.covariance)
            .map(|c| carried(&j_current, &c, &IDENTITY));
        match self.second_way(&mut slot, j_current, cross, ctx) {
            Some((chain, closure, cross)) => Linked {
                slot: RefSlot {
                    chain: Some(chain),
                    ..slot
                },
                closure: Some(closure),
                cross: Some(cross),
            },
            None => Linked {
                slot,
                closure: None,
                cross,
            },
        }
    }

    /// `slot`'s chain through the keyframe before the current one, combined with the one
    /// through the current keyframe (`slot.chain`, `cross_one` = Cov(e_new, e_current)); the
    /// closure of the two ways and Cov(e_combined, e_current). `None` where there is no
    /// second way.
    fn second_way(
        &mut self,
        slot: &mut RefSlot,
        j_current: Matrix4,
        cross_one: Option<Cov4>,
        ctx: &dyn StepContext,
    ) -> Option<(Chain, ReferenceClosure, Cov4)> {
        let (through_current, cross_one) = (slot.chain?, cross_one?);
        let (previous, cross_cp) = self.previous_keyframe.as_mut()?;
        let cross_cp = (*cross_cp)?;
        let (prev_image, image) = (previous.image(ctx).ok()?, slot.image(ctx).ok()?);
        let second = ctx.align(&prev_image, &image);
        let (through_previous, j_previous) =
            chain_after_carrying(previous.chain.as_ref(), &second)?;
        // The two ways' errors share the keyframes' chains: Cov(e_a, e_b) = J_c Cov(e_c, e_p) J_pᵀ.
        let both = combine(
            &through_current,
            &through_previous,
            &carried(&j_current, &cross_cp, &j_previous),
        )?;
        // Cov(e_b, e_current) = J_p Cov(e_p, e_c).
        let cross_pc: Cov4 = std::array::from_fn(|r| std::array::from_fn(|s| cross_cp[s][r]));
        let cov_b_current = carried(&j_previous, &cross_pc, &IDENTITY);
        tracing::debug!(
            channel = %self.name,
            frame = %slot.key,
            z = ?both.closure.z(),
            "keyframe closure"
        );
        let fields = |p: [f64; 4]| TransformFields {
            scale: p[0],
            rotation_arcsec: p[1] * sunjitter_core::geometry::ARCSEC_PER_RAD,
            dx_px: p[2],
            dy_px: p[3],
        };
        let closure = ReferenceClosure {
            through: previous.key.clone(),
            difference: fields(both.closure.difference),
            sigma: fields(both.closure.sigma),
        };
        let cross = combined_cross(&both.gain, &cross_one, &cov_b_current);
        Some((both.chain, closure, cross))
    }

    /// Install the keyframe `linked` in place of `keyframe`, which becomes the one before.
    fn install_linked(
        &mut self,
        keyframe: RefSlot,
        linked: Linked,
        frame: &LoadedFrame,
        first_sequence: u64,
        reason: String,
        records: &mut Vec<Record>,
    ) {
        let Linked {
            slot,
            closure,
            cross,
        } = linked;
        let mut change = self.change_record(&slot, frame, first_sequence, reason);
        if let Record::Reference { change, .. } = &mut change {
            change.closure = closure;
            change.cross_covariance = cross.map(|c| flat(&c));
        }
        records.push(change);
        self.reference = Some(slot);
        self.previous_keyframe = Some((keyframe, cross));
        self.candidate = None;
        self.frames_on_reference = 0;
    }

    /// Log a frame aligned to the current keyframe and update the hand-over state.
    fn keyframe_result(
        &mut self,
        frame: &LoadedFrame,
        sequence: u64,
        outcome: AlignOutcome,
        records: &mut Vec<Record>,
    ) -> Emitted {
        let good = self.degraded(&outcome).is_none();
        let (key, ref_chain) = match &self.reference {
            Some(r) => (r.key.clone(), r.chain),
            None => (String::new(), None),
        };
        let (chain, j_chain) = chain_after_carrying(ref_chain.as_ref(), &outcome)
            .map_or((None, IDENTITY), |(c, j)| (Some(c), j));
        self.frames_on_reference += 1;
        let emitted = self.emit(
            frame,
            sequence,
            AlignedTo {
                kind: ReferenceKind::Keyframe,
                key: &key,
            },
            outcome,
            chain,
            records,
        );
        if good {
            self.consecutive_failures = 0;
            self.candidate = Some((RefSlot::from_frame(frame, chain), j_chain));
        } else if emitted.message.align.status == Status::Failed {
            self.note_failure();
        }
        emitted
    }

    fn step_fixed(
        &mut self,
        file: &str,
        frame: &LoadedFrame,
        sequence: u64,
        ctx: &dyn StepContext,
        records: &mut Vec<Record>,
    ) -> Emitted {
        let mut reference = match self.reference.take() {
            Some(slot) => slot,
            None => {
                let spec = parse_frame_key(file);
                let mut slot =
                    RefSlot::named(&frame_key(&spec.path, spec.frame), frame.obs_time_ns, None);
                match slot.image(ctx) {
                    Ok(image) => {
                        slot.obs_time_ns = image.meta.obs_time_ns.unwrap_or(frame.obs_time_ns);
                        slot.chain = Some(Chain::origin(
                            image_center(&image),
                            ctx.plate_scale_used(&image),
                        ));
                        records.push(self.change_record(
                            &slot,
                            frame,
                            sequence,
                            "fixed reference".into(),
                        ));
                        slot
                    }
                    Err(e) => {
                        // Tried again with the next frame.
                        let why = format!("fixed reference unreadable: {e}");
                        let outcome = AlignOutcome::failed(file, &frame.key, &why);
                        return self.emit(
                            frame,
                            sequence,
                            AlignedTo {
                                kind: ReferenceKind::Fixed,
                                key: file,
                            },
                            outcome,
                            None,
                            records,
                        );
                    }
                }
            }
        };
        let emitted = if reference.key == frame.key {
            self.emit_self(frame, sequence, reference.chain, records)
        } else {
            let outcome = match reference.image(ctx) {
                Ok(image) => ctx.align(&image, &frame.image),
                Err(e) => {
                    let why = format!("fixed reference unreadable: {e}");
                    AlignOutcome::failed(&reference.key, &frame.key, &why)
                }
            };
            let chain = chain_after(reference.chain.as_ref(), &outcome);
            self.emit(
                frame,
                sequence,
                AlignedTo {
                    kind: ReferenceKind::Fixed,
                    key: &reference.key,
                },
                outcome,
                chain,
                records,
            )
        };
        self.reference = Some(reference);
        emitted
    }

    fn step_channel(
        &mut self,
        partner: &PartnerFrame,
        frame: &LoadedFrame,
        sequence: u64,
        ctx: &dyn StepContext,
        records: &mut Vec<Record>,
    ) -> Emitted {
        let mut reference = match self.reference.take() {
            Some(slot) if slot.key == partner.key => slot,
            _ => {
                let mut slot = RefSlot::named(&partner.key, partner.obs_time_ns, partner.chain);
                slot.spec = partner.spec.clone();
                let dt = (frame.obs_time_ns - partner.obs_time_ns) as f64 * 1e-9;
                let reason = format!(
                    "nearest {} frame (frame − reference = {dt:+.3} s)",
                    partner.channel
                );
                records.push(self.change_record(&slot, frame, sequence, reason));
                slot
            }
        };
        let outcome = match reference.image(ctx) {
            Ok(image) => ctx.align(&image, &frame.image),
            Err(e) => {
                let why = format!("{} frame unreadable: {e}", partner.channel);
                AlignOutcome::failed(&partner.key, &frame.key, &why)
            }
        };
        let chain = chain_after(reference.chain.as_ref(), &outcome);
        let emitted = self.emit(
            frame,
            sequence,
            AlignedTo {
                kind: ReferenceKind::Channel,
                key: &reference.key,
            },
            outcome,
            chain,
            records,
        );
        self.reference = Some(reference);
        emitted
    }

    // -- helpers ----------------------------------------------------------------------------

    /// Why `outcome` counts as a degraded match for the keyframe policy, if it does.
    fn degraded(&self, outcome: &AlignOutcome) -> Option<String> {
        match outcome.result.status {
            Status::Failed => return Some(format!("failed: {}", outcome.result.message)),
            Status::Degraded => return Some(format!("degraded: {}", outcome.result.message)),
            Status::Ok => {}
        }
        if outcome.transform.is_none() {
            return Some("no transform".into());
        }
        match outcome.result.similarity {
            Some(s) if s < self.policy.refresh_below_similarity => Some(format!(
                "similarity {s:.4} < {}",
                self.policy.refresh_below_similarity
            )),
            _ => None,
        }
    }

    /// Count a failed frame; after too many in a row the next frame starts a new chain.
    fn note_failure(&mut self) {
        self.consecutive_failures += 1;
        let limit = self.policy.restart_after_failures;
        if limit > 0 && self.consecutive_failures >= limit {
            self.reference = None;
            self.candidate = None;
            self.previous_keyframe = None;
            self.consecutive_failures = 0;
            self.restart_reason = Some(format!("{limit} consecutive failed frames: new chain"));
        }
    }

    /// The `/reference` record for `slot`; `first_sequence` is the first frame aligned to it.
    fn change_record(
        &mut self,
        slot: &RefSlot,
        frame: &LoadedFrame,
        first_sequence: u64,
        reason: String,
    ) -> Record {
        let chain = slot.chain;
        let change = ReferenceChange {
            channel: self.name.clone(),
            file: sunjitter_core::text::path(&slot.spec.path).into_owned(),
            cube_frame: slot.spec.frame,
            obs_time: iso8601_utc(slot.obs_time_ns),
            reason,
            reference_kind: self.policy.policy.kind(),
            sequence: first_sequence,
            replaces: self.announced.replace(slot.key.clone()),
            closure: None,
            cross_covariance: None,
            chain,
        };
        Record::Reference {
            change: Box::new(change),
            log_time_ns: frame.obs_time_ns,
        }
    }

    /// Announce `slot` on `/reference/<channel>` and make it the current reference.
    fn install(
        &mut self,
        slot: RefSlot,
        frame: &LoadedFrame,
        sequence: u64,
        reason: String,
        records: &mut Vec<Record>,
    ) {
        records.push(self.change_record(&slot, frame, sequence, reason));
        self.reference = Some(slot);
    }

    fn emit_self(
        &mut self,
        frame: &LoadedFrame,
        sequence: u64,
        chain: Option<Chain>,
        records: &mut Vec<Record>,
    ) -> Emitted {
        let align = AlignResult::identity(
            frame.key.clone(),
            frame.key.clone(),
            "starts a reference: aligned to itself",
        );
        self.push_message(
            frame,
            sequence,
            ReferenceKind::Itself,
            align,
            chain,
            records,
        )
    }

    fn emit(
        &mut self,
        frame: &LoadedFrame,
        sequence: u64,
        to: AlignedTo,
        outcome: AlignOutcome,
        chain: Option<Chain>,
        records: &mut Vec<Record>,
    ) -> Emitted {
        let mut align = outcome.result;
        align.reference = to.key.into();
        align.frame = frame.key.clone();
        self.push_message(frame, sequence, to.kind, align, chain, records)
    }

    fn push_message(
        &mut self,
        frame: &LoadedFrame,
        sequence: u64,
        kind: ReferenceKind,
        align: AlignResult,
        chain: Option<Chain>,
        records: &mut Vec<Record>,
    ) -> Emitted {
        let mut message = FrameAlignment::unchained(
            align,
            self.name.clone(),
            iso8601_utc(frame.obs_time_ns),
            sequence,
            kind,
        );
        set_chain(&mut message, chain.as_ref());
        records.push(Record::Frame {
            message: Box::new(message.clone()),
            log_time_ns: frame.obs_time_ns,
        });
        Emitted { message, chain }
    }
}

/// A 4 × 4 covariance as 16 numbers, row by row (the `/reference` message's form).
fn flat(c: &Cov4) -> Vec<f64> {
    c.iter().flatten().copied().collect()
}

/// A covariance from its 16 numbers, row by row.
fn unflat(v: &[f64]) -> Option<Cov4> {
    (v.len() == 16 && v.iter().all(|x| x.is_finite()))
        .then(|| std::array::from_fn(|r| std::array::from_fn(|s| v[4 * r + s])))
}

fn image_center(image: &Image) -> [f64; 2] {
    let (h, w) = image.data.dim();
    Similarity::array_center(w, h)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::fake::{FakeFrame, TruthAligner, HEIGHT, WIDTH};
    use crate::ports::Aligner;
    use std::collections::HashMap;
    use std::path::{Path, PathBuf};
    use sunjitter_core::geometry::ARCSEC_PER_RAD;

    const SX: f64 = 0.05; // σ of dx, dy per alignment (px)

    fn diag(s: f64, r: f64, x: f64, y: f64) -> Cov4 {
        let mut c = [[0.0; 4]; 4];
        c[0][0] = s * s;
        c[1][1] = r * r;
        c[2][2] = x * x;
        c[3][3] = y * y;
        c
    }

    /// Frames in memory; the aligner answers the true relative transform.
    struct World {
        frames: HashMap<PathBuf, FakeFrame>,
        aligner: TruthAligner,
        calls: std::cell::RefCell<Vec<(String, String)>>,
    }

    impl World {
        fn new(frames: &[(String, FakeFrame)], cov: Cov4) -> World {
            let map: HashMap<PathBuf, FakeFrame> = frames
                .iter()
                .map(|(k, f)| (PathBuf::from(k), f.clone()))
                .collect();
            let lookup = map.clone();
            World {
                frames: map,
                aligner: TruthAligner {
                    cov,
                    truth: Box::new(move |p: &Path| lookup.get(p).cloned()),
                },
                calls: Default::default(),
            }
        }
        fn loaded(&self, key: &str) -> LoadedFrame {
            let f = &self.frames[Path::new(key)];
            LoadedFrame {
                key: key.into(),
                spec: parse_frame_key(key),
                obs_time_ns: f.obs_time_ns.unwrap(),
                image: Arc::new(f.image(Path::new(key))),
            }
        }
    }

    impl StepContext for World {
        fn align(&self, reference: &Image, frame: &Image) -> AlignOutcome {
            self.calls.borrow_mut().push((
                reference.meta.file.display().to_string(),
                frame.meta.file.display().to_string(),
            ));
            self.aligner.align(reference, frame)
        }
        fn load(&self, spec: &FrameSpec) -> sunjitter_core::Result<Image> {
            self.frames
                .get(&spec.path)
                .map(|f| f.image(&spec.path))
                .ok_or_else(|| sunjitter_core::Error::bad_input(&spec.path, "no such fake"))
        }
    }

    fn policy(spec: PolicySpec) -> ChannelPolicy {
        ChannelPolicy {
            policy: spec,
            keyframe_every_frames: 0,
            keyframe_every_s: 0.0,
            keyframe_min_frames: 0,
            refresh_below_similarity: 0.0,
            restart_after_failures: 3,
            tolerance_s: 30.0,
            hold_s: 60.0,
        }
    }

    /// A drifting, rotating, breathing pointing series: frame i at 10 s cadence.
    fn series(n: usize) -> Vec<(String, FakeFrame)> {
        (0..n)
            .map(|i| {
                let x = i as f64;
                let f = if i == 0 {
                    FakeFrame::new("C", 0, 1.0, 0.0, 0.0, 0.0)
                } else {
                    FakeFrame::new(
                        "C",
                        i as i64 * 10_000_000_000,
                        1.0 + 1e-4 * x.sin(),
                        2e-4 * x,
                        0.7 * x.cos() + 0.1 * x,
                        -0.4 * (0.5 * x).sin(),
                    )
                };
                (format!("/d/f{i:02}.fits"), f)
            })
            .collect()
    }

    /// The history a restart reads back from `records`, with `strip` applied to every
    /// reference change (fields an older log or the MCAP schema lacks).
    fn history_stripped(records: &[Record], strip: impl Fn(&mut ReferenceChange)) -> History {
        let mut history = History::default();
        for r in records {
            match r {
                Record::Reference {
                    change,
                    log_time_ns,
                } => {
                    let mut c = (**change).clone();
                    strip(&mut c);
                    history.add(&Record::Reference {
                        change: Box::new(c),
                        log_time_ns: *log_time_ns,
                    });
                }
                other => history.add(other),
            }
        }
        history
    }

    fn run(state: &mut ChannelState, world: &World, keys: &[String]) -> Vec<Record> {
        let mut out = Vec::new();
        for key in keys {
            out.extend(state.process(&world.loaded(key), None, world).records);
        }
        out
    }

    fn messages(records: &[Record]) -> Vec<&FrameAlignment> {
        records
            .iter()
            .filter_map(|r| match r {
                Record::Frame { message, .. } => Some(message.as_ref()),
                _ => None,
            })
            .collect()
    }

    fn changes(records: &[Record]) -> Vec<&ReferenceChange> {
        records
            .iter()
            .filter_map(|r| match r {
                Record::Reference { change, .. } => Some(change.as_ref()),
                _ => None,
            })
            .collect()
    }

    fn assert_chained_is_truth(m: &FrameAlignment, truth: &Similarity) {
        let tol = 1e-9;
        assert!(
            (m.chained_scale.unwrap() - truth.scale).abs() < tol,
            "{m:?}"
        );
        let rot = m.chained_rotation_arcsec.unwrap() / ARCSEC_PER_RAD;
        assert!((rot - truth.rotation_rad).abs() < tol, "{m:?}");
        assert!(
            (m.chained_dx_px.unwrap() - truth.dx).abs() < tol,
            "{} vs {}",
            m.chained_dx_px.unwrap(),
            truth.dx
        );
        assert!((m.chained_dy_px.unwrap() - truth.dy).abs() < tol, "{m:?}");
    }

    #[test]
    fn policy_names_parse_and_print() {
        for s in [
            "previous",
            "keyframe",
            "fixed:/a/b.fits[2]",
            "channel:SJI_1400",
        ] {
            assert_eq!(s.parse::<PolicySpec>().unwrap().to_string(), s);
        }
        assert_eq!(
            "fixed:x.fits".parse::<PolicySpec>().unwrap(),
            PolicySpec::Fixed("x.fits".into())
        );
        for bad in ["", "fixed:", "channel:", "nearest"] {
            assert_eq!(
                bad.parse::<PolicySpec>().unwrap_err().exit_code(),
                sunjitter_core::error::ExitCode::BadInput
            );
        }
        assert_eq!(parse_frame_key("/a/cube.fits[12]").frame, Some(12));
        assert_eq!(parse_frame_key("/a/odd[name].fits").frame, None);
        assert_eq!(frame_key(Path::new("/a/c.fits"), Some(3)), "/a/c.fits[3]");
    }

    #[test]
    fn first_frame_is_logged_aligned_to_itself() {
        let frames = series(1);
        let world = World::new(&frames, diag(0.0, 0.0, SX, SX));
        let mut state = ChannelState::new("C", policy(PolicySpec::Keyframe));
        let records = run(&mut state, &world, &[frames[0].0.clone()]);
        // One reference change, then the frame message.
        assert!(matches!(records[0], Record::Reference { .. }));
        let m = messages(&records)[0];
        assert_eq!((m.reference_kind, m.sequence), (ReferenceKind::Itself, 0));
        assert_eq!(m.align.status, Status::Ok);
        assert_eq!(
            (m.align.scale, m.align.dx_px, m.align.dy_px),
            (Some(1.0), Some(0.0), Some(0.0))
        );
        assert_eq!(
            (m.align.sigma_dx_px, m.sigma_chained_dx_px),
            (Some(0.0), Some(0.0))
        );
        assert_eq!((m.chained_scale, m.chained_dx_px), (Some(1.0), Some(0.0)));
        assert_eq!(m.align.reference, m.align.frame);
        assert_eq!(changes(&records)[0].reason, "first frame");
        assert!(
            world.calls.borrow().is_empty(),
            "no engine call for the self frame"
        );
    }

    #[test]
    fn keyframe_chain_reproduces_the_true_pointing() {
        // Keyframes every 4 frames: hand-overs at 4, 8, 12; chained values must equal the
        // injected pointing of each frame relative to frame 0 throughout.
        let frames = series(14);
        let keys: Vec<String> = frames.iter().map(|(k, _)| k.clone()).collect();
        let world = World::new(&frames, diag(0.0, 0.0, SX, SX));
        let mut p = policy(PolicySpec::Keyframe);
        p.keyframe_every_frames = 4;
        let mut state = ChannelState::new("C", p);
        let records = run(&mut state, &world, &keys);
        let msgs = messages(&records);
        assert_eq!(msgs.len(), 14);
        for (i, m) in msgs.iter().enumerate() {
            assert_eq!(m.sequence, i as u64);
            assert_eq!(m.align.frame, keys[i]);
            assert_chained_is_truth(m, &frames[i].1.truth);
            let expect_self = i % 4 == 0;
            assert_eq!(
                m.reference_kind == ReferenceKind::Itself,
                expect_self,
                "frame {i}"
            );
            if !expect_self {
                assert_eq!(m.align.reference, keys[i / 4 * 4], "frame {i}");
                assert_eq!(m.reference_kind, ReferenceKind::Keyframe);
            }
        }
        let ch = changes(&records);
        assert_eq!(ch.len(), 4);
        assert_eq!(
            ch.iter().map(|c| c.file.as_str()).collect::<Vec<_>>(),
            [&keys[0], &keys[4], &keys[8], &keys[12]]
        );
        assert!(ch[1].reason.contains("every 4 frames"), "{}", ch[1].reason);
        // Each change carries the keyframe's chain (what a restart continues from).
        let c8 = ch[2].chain.unwrap();
        assert!((c8.transform.dx - frames[8].1.truth.dx).abs() < 1e-9);
    }

    #[test]
    fn at_a_cadence_sparser_than_the_refresh_age_a_keyframe_still_serves_frames() {
        // Frames 800 s apart, refresh by age after 600 s: each keyframe serves 4 frames before
        // its age counts, so frames 0, 5, 10 are keyframes and the rest are measured against
        // them; without the minimum, every frame would start its own reference.
        let frames: Vec<(String, FakeFrame)> = series(12)
            .into_iter()
            .enumerate()
            .map(|(i, (key, f))| {
                let t = f.truth;
                let f = FakeFrame::new(
                    "C",
                    i as i64 * 800_000_000_000,
                    t.scale,
                    t.rotation_rad,
                    t.dx,
                    t.dy,
                );
                (key, f)
            })
            .collect();
        let keys: Vec<String> = frames.iter().map(|(k, _)| k.clone()).collect();
        let world = World::new(&frames, diag(0.0, 0.0, SX, SX));
        for (min_frames, keyframes) in [(4, vec![0, 5, 10]), (0, (0..12).collect())] {
            let mut p = policy(PolicySpec::Keyframe);
            p.keyframe_every_s = 600.0;
            p.keyframe_min_frames = min_frames;
            let mut state = ChannelState::new("C", p);
            let records = run(&mut state, &world, &keys);
            let msgs = messages(&records);
            let selves: Vec<usize> = msgs
                .iter()
                .enumerate()
                .filter(|(_, m)| m.reference_kind == ReferenceKind::Itself)
                .map(|(i, _)| i)
                .collect();
            assert_eq!(selves, keyframes, "minimum {min_frames}");
            for (i, m) in msgs.iter().enumerate() {
                assert_chained_is_truth(m, &frames[i].1.truth);
                if !keyframes.contains(&i) {
                    let keyframe = keyframes.iter().rev().find(|&&k| k < i).unwrap();
                    assert_eq!(m.align.reference, keys[*keyframe], "frame {i}");
                }
            }
        }
    }

    #[test]
    fn chained_sigma_is_the_spread_of_chained_errors_with_keyframes_reached_two_ways() {
        // Known truth: every alignment is the true relative transform plus Gaussian noise of
        // the covariance it reports (independent per pair, as for different image pairs).
        // Over many such runs, each frame's chained error must spread as its reported σ,
        // for keyframes reached two ways as much as for the frames between them; and the
        // two ways' closure must scatter as its σ.
        use std::cell::RefCell;
        struct Noisy<'a> {
            world: &'a World,
            rng: RefCell<sunjitter_core::stats::SplitMix64>,
            sigma: [f64; 4],
        }
        impl StepContext for Noisy<'_> {
            fn align(&self, r: &Image, f: &Image) -> AlignOutcome {
                let mut o = self.world.align(r, f);
                if let Some(t) = o.transform.as_mut() {
                    let mut rng = self.rng.borrow_mut();
                    let mut p = t.params();
                    for (v, s) in p.iter_mut().zip(self.sigma) {
                        *v += s * rng.gaussian();
                    }
                    *t = Similarity::from_params(p, t.center);
                }
                o
            }
            fn load(&self, spec: &FrameSpec) -> sunjitter_core::Result<Image> {
                self.world.load(spec)
            }
        }
        let frames = series(13);
        let keys: Vec<String> = frames.iter().map(|(k, _)| k.clone()).collect();
        let sigma = [2e-5, 3e-5, SX, 1.5 * SX];
        let cov = diag(sigma[0], sigma[1], sigma[2], sigma[3]);
        let world = World::new(&frames, cov);
        let ctx = Noisy {
            world: &world,
            rng: RefCell::new(sunjitter_core::stats::SplitMix64::new(11)),
            sigma,
        };
        let mut p = policy(PolicySpec::Keyframe);
        p.keyframe_every_frames = 3;
        let runs = 600;
        let (mut err2, mut var) = (vec![[0.0; 2]; keys.len()], vec![[0.0; 2]; keys.len()]);
        let mut closure_z = Vec::new();
        for _ in 0..runs {
            let mut state = ChannelState::new("C", p.clone());
            let mut records = Vec::new();
            for k in &keys {
                records.extend(state.process(&world.loaded(k), None, &ctx).records);
            }
            for (i, m) in messages(&records).iter().enumerate() {
                let truth = &frames[i].1.truth;
                let e = [
                    m.chained_dx_px.unwrap() - truth.dx,
                    m.chained_dy_px.unwrap() - truth.dy,
                ];
                let s = [
                    m.sigma_chained_dx_px.unwrap(),
                    m.sigma_chained_dy_px.unwrap(),
                ];
                for k in 0..2 {
                    err2[i][k] += e[k] * e[k];
                    var[i][k] += s[k] * s[k];
                }
            }
            closure_z.extend(
                changes(&records)
                    .iter()
                    .filter_map(|c| c.closure.as_ref().map(|c| c.z())),
            );
        }
        // Keyframes at 0, 3, 6, 9, 12; from the one at 6 on they are reached two ways.
        let two_ways = [6, 9, 12];
        assert_eq!(closure_z.len(), runs * two_ways.len());
        for i in 1..keys.len() {
            for k in 0..2 {
                // The ratio of two variance estimates over 600 runs: within 15 %.
                let ratio = err2[i][k] / var[i][k];
                assert!((ratio - 1.0).abs() < 0.15, "frame {i}, axis {k}: {ratio}");
            }
        }
        // Two ways make a keyframe surer than one way would: frame 12, four hand-overs from
        // the origin, would have 4·σ² one way.
        let mean_var = var[12][0] / runs as f64;
        assert!(mean_var < 0.8 * 4.0 * SX * SX, "{:?}", var[12]);
        for k in 2..4 {
            let rms = (closure_z.iter().map(|z| z[k] * z[k]).sum::<f64>() / closure_z.len() as f64)
                .sqrt();
            assert!(
                (rms - 1.0).abs() < 0.1,
                "closure z of parameter {k}: rms {rms}"
            );
        }
    }

    #[test]
    fn chained_covariance_matches_monte_carlo_composition() {
        // Independent truth: perturb both factors with their covariances (correlated, via
        // Cholesky), compose with Similarity::after, and measure the spread of the result.
        let a = Similarity {
            scale: 1.003,
            rotation_rad: 0.02,
            dx: 1.5,
            dy: -2.0,
            center: [40.0, 30.0],
        };
        let t = Similarity {
            scale: 0.998,
            rotation_rad: -0.01,
            dx: -3.0,
            dy: 0.7,
            center: [50.5, 20.5],
        };
        let ca = [
            [1e-6, 2e-8, 1e-5, 0.0],
            [2e-8, 4e-8, 0.0, 3e-6],
            [1e-5, 0.0, 0.01, 0.002],
            [0.0, 3e-6, 0.002, 0.02],
        ];
        let ct = diag(2e-4, 3e-4, 0.05, 0.08);
        let chain = Chain {
            transform: t,
            covariance: Some(ct),
            plate_scale_arcsec: None,
        }
        .then(&a, Some(&ca));
        let cov = chain.covariance.unwrap();
        let la = cholesky(&ca);
        let lt = cholesky(&ct);
        let mut rng = sunjitter_core::stats::SplitMix64::new(7);
        let n = 40_000;
        let mut samples = Vec::with_capacity(n);
        for _ in 0..n {
            let za: [f64; 4] = std::array::from_fn(|_| rng.gaussian());
            let zt: [f64; 4] = std::array::from_fn(|_| rng.gaussian());
            let pa = perturb(&a, &la, &za);
            let pt = perturb(&t, &lt, &zt);
            let c = pa.after(&pt);
            samples.push([c.scale, c.rotation_rad, c.dx, c.dy]);
        }
        let mean: [f64; 4] =
            std::array::from_fn(|k| samples.iter().map(|s| s[k]).sum::<f64>() / n as f64);
        for r in 0..4 {
            for k in 0..4 {
                let emp = samples
                    .iter()
                    .map(|s| (s[r] - mean[r]) * (s[k] - mean[k]))
                    .sum::<f64>()
                    / (n - 1) as f64;
                // Sampling error of a covariance ≈ sqrt((σ_r²σ_k² + c_rk²)/n) ≤ 1.5 % here.
                let scale = (cov[r][r] * cov[k][k]).sqrt();
                assert!(
                    (emp - cov[r][k]).abs() < 0.03 * scale,
                    "[{r}][{k}] empirical {emp} vs {}",
                    cov[r][k]
                );
            }
        }
    }

    fn cholesky(c: &Cov4) -> Cov4 {
        let mut l = [[0.0; 4]; 4];
        for i in 0..4 {
            for j in 0..=i {
                let sum: f64 = (0..j).map(|k| l[i][k] * l[j][k]).sum();
                l[i][j] = if i == j {
                    (c[i][i] - sum).sqrt()
                } else {
                    (c[i][j] - sum) / l[j][j]
                };
            }
        }
        l
    }

    fn perturb(s: &Similarity, l: &Cov4, z: &[f64; 4]) -> Similarity {
        let d: [f64; 4] = std::array::from_fn(|i| (0..4).map(|k| l[i][k] * z[k]).sum());
        Similarity {
            scale: s.scale + d[0],
            rotation_rad: s.rotation_rad + d[1],
            dx: s.dx + d[2],
            dy: s.dy + d[3],
            center: s.center,
        }
    }

    #[test]
    fn degraded_match_hands_over_to_the_last_good_frame() {
        let mut frames = series(6);
        frames[4].1.degraded = true; // degraded against keyframe 0 … and against frame 3 too
        let keys: Vec<String> = frames.iter().map(|(k, _)| k.clone()).collect();
        // Make only the pair (f00, f04) degraded: frame 4 is fine against frame 3.
        let lookup: HashMap<PathBuf, FakeFrame> = frames
            .iter()
            .map(|(k, f)| (PathBuf::from(k), f.clone()))
            .collect();
        let mut world = World::new(&frames, diag(0.0, 0.0, SX, SX));
        let k0 = PathBuf::from(&keys[0]);
        world.aligner = TruthAligner {
            cov: diag(0.0, 0.0, SX, SX),
            truth: Box::new(move |p: &Path| lookup.get(p).cloned()),
        };
        struct PairDegraded<'a>(&'a World, PathBuf, PathBuf);
        impl StepContext for PairDegraded<'_> {
            fn align(&self, r: &Image, f: &Image) -> AlignOutcome {
                let mut o = self.0.align(r, f);
                let pair = r.meta.file == self.1 && f.meta.file == self.2;
                o.result.status = if pair { Status::Degraded } else { Status::Ok };
                o
            }
            fn load(&self, spec: &FrameSpec) -> sunjitter_core::Result<Image> {
                self.0.load(spec)
            }
        }
        let ctx = PairDegraded(&world, k0, PathBuf::from(&keys[4]));
        let mut state = ChannelState::new("C", policy(PolicySpec::Keyframe));
        let mut records = Vec::new();
        for k in &keys {
            records.extend(state.process(&world.loaded(k), None, &ctx).records);
        }
        let msgs = messages(&records);
        assert_eq!(msgs.len(), 6);
        assert_eq!(
            msgs[4].align.reference, keys[3],
            "frame 4 re-aligned to frame 3"
        );
        assert_eq!(msgs[4].align.status, Status::Ok);
        assert_eq!(msgs[5].align.reference, keys[3]);
        for (i, m) in msgs.iter().enumerate() {
            assert_chained_is_truth(m, &frames[i].1.truth);
        }
        let ch = changes(&records);
        assert_eq!(ch.len(), 2);
        assert_eq!(ch[1].file, keys[3]);
        assert!(
            ch[1].reason.starts_with("match degraded"),
            "{}",
            ch[1].reason
        );
        // Frame 3 was logged once (aligned to frame 0), never as `self`.
        assert_eq!(msgs.iter().filter(|m| m.align.frame == keys[3]).count(), 1);
    }

    #[test]
    fn a_degraded_match_without_a_good_frame_keeps_the_keyframe() {
        // Frame 1 matches keyframe 0 only `degraded`, and no frame matched it well before:
        // the match is as good as the keyframe allows, and a hand-over would only add a link
        // to the chain. Frame 1 is measured against keyframe 0, as are the frames after it.
        let frames = series(4);
        let keys: Vec<String> = frames.iter().map(|(k, _)| k.clone()).collect();
        let world = World::new(&frames, diag(0.0, 0.0, SX, SX));
        struct Degrade<'a>(&'a World, String);
        impl StepContext for Degrade<'_> {
            fn align(&self, r: &Image, f: &Image) -> AlignOutcome {
                let mut o = self.0.align(r, f);
                if f.meta.file == Path::new(&self.1) {
                    o.result.status = Status::Degraded;
                }
                o
            }
            fn load(&self, spec: &FrameSpec) -> sunjitter_core::Result<Image> {
                self.0.load(spec)
            }
        }
        let ctx = Degrade(&world, keys[1].clone());
        let mut state = ChannelState::new("C", policy(PolicySpec::Keyframe));
        let mut records = Vec::new();
        for k in &keys {
            records.extend(state.process(&world.loaded(k), None, &ctx).records);
        }
        let msgs = messages(&records);
        assert_eq!(msgs[1].align.status, Status::Degraded);
        for m in &msgs[1..] {
            assert_eq!(m.align.reference, keys[0]);
        }
        for (i, m) in msgs.iter().enumerate() {
            assert_chained_is_truth(m, &frames[i].1.truth);
        }
        assert_eq!(changes(&records).len(), 1);
        // A failed frame is never handed over to.
        let mut bad = series(3);
        bad[1].1.bad = true;
        let bad_keys: Vec<String> = bad.iter().map(|(k, _)| k.clone()).collect();
        let world = World::new(&bad, diag(0.0, 0.0, SX, SX));
        let mut state = ChannelState::new("C", policy(PolicySpec::Keyframe));
        let records = run(&mut state, &world, &bad_keys);
        assert_eq!(messages(&records)[2].align.reference, bad_keys[0]);
        assert_eq!(changes(&records).len(), 1);
    }

    #[test]
    fn repeated_failures_start_a_new_chain() {
        let mut frames = series(8);
        for f in &mut frames[2..5] {
            f.1.bad = true;
        }
        let keys: Vec<String> = frames.iter().map(|(k, _)| k.clone()).collect();
        let world = World::new(&frames, diag(0.0, 0.0, SX, SX));
        let mut state = ChannelState::new("C", policy(PolicySpec::Previous));
        let records = run(&mut state, &world, &keys);
        let msgs = messages(&records);
        assert_eq!(msgs.len(), 8, "every frame gets exactly one message");
        for m in &msgs[2..5] {
            assert_eq!(m.align.status, Status::Failed);
            assert_eq!((m.chained_dx_px, m.align.dx_px), (None, None));
            // A failed frame never becomes the reference: all three tried against frame 1.
            assert_eq!(m.align.reference, keys[1]);
        }
        // Three failures in a row (restart_after_failures = 3): frame 5 starts a new chain.
        assert_eq!(msgs[5].reference_kind, ReferenceKind::Itself);
        assert_eq!(msgs[5].chained_dx_px, Some(0.0));
        let last = changes(&records)
            .into_iter()
            .find(|c| c.file == keys[5])
            .unwrap();
        assert!(
            last.reason.contains("3 consecutive failed"),
            "{}",
            last.reason
        );
        // Frames 6, 7 continue the new chain: pointing relative to frame 5.
        let rel = frames[7].1.truth.after(&frames[5].1.truth.inverse());
        assert_chained_is_truth(msgs[7], &rel);
        assert_eq!(
            msgs.iter().map(|m| m.sequence).collect::<Vec<_>>(),
            (0..8).collect::<Vec<_>>()
        );
    }

    #[test]
    fn previous_policy_chains_frame_to_frame() {
        let frames = series(6);
        let keys: Vec<String> = frames.iter().map(|(k, _)| k.clone()).collect();
        let world = World::new(&frames, diag(0.0, 0.0, SX, SX));
        let mut state = ChannelState::new("C", policy(PolicySpec::Previous));
        let records = run(&mut state, &world, &keys);
        let msgs = messages(&records);
        // Isotropic translation errors stay isotropic through a similarity; each link adds
        // SX² and scales what came before by the link's s²: var_i = SX² + s_i² var_(i−1).
        let mut var = 0.0;
        for (i, m) in msgs.iter().enumerate().skip(1) {
            assert_eq!(m.align.reference, keys[i - 1]);
            assert_eq!(m.reference_kind, ReferenceKind::Previous);
            assert_chained_is_truth(m, &frames[i].1.truth);
            let s = frames[i].1.truth.scale / frames[i - 1].1.truth.scale;
            var = SX * SX + s * s * var;
            // (geometry's Jacobian is numerical: agreement to 1e-8 relative)
            assert!((m.sigma_chained_dx_px.unwrap() - var.sqrt()).abs() <= 1e-8 * var.sqrt());
            assert!((m.sigma_chained_dy_px.unwrap() - var.sqrt()).abs() <= 1e-8 * var.sqrt());
        }
        // Every frame becomes the next one's reference: one change per frame.
        assert_eq!(changes(&records).len(), 6);
    }

    #[test]
    fn fixed_reference_reports_pointing_relative_to_the_file() {
        let mut frames = series(4);
        let fixed = FakeFrame::new("REF", 5, 1.001, 0.003, 2.0, -1.0);
        frames.push(("/d/ref.fits".into(), fixed.clone()));
        let world = World::new(&frames, diag(1e-5, 1e-5, SX, SX));
        let keys: Vec<String> = frames[..4].iter().map(|(k, _)| k.clone()).collect();
        let mut state = ChannelState::new("C", policy(PolicySpec::Fixed("/d/ref.fits".into())));
        let records = run(&mut state, &world, &keys);
        let msgs = messages(&records);
        for (i, m) in msgs.iter().enumerate() {
            assert_eq!(
                (m.reference_kind, m.align.reference.as_str()),
                (ReferenceKind::Fixed, "/d/ref.fits")
            );
            let rel = frames[i].1.truth.after(&fixed.truth.inverse());
            assert_chained_is_truth(m, &rel);
            assert!((m.align.dx_px.unwrap() - rel.dx).abs() < 1e-9);
        }
        assert_eq!(changes(&records).len(), 1);
    }

    #[test]
    fn channel_policy_aligns_to_the_partner_and_chains_through_it() {
        let frames = series(3);
        let keys: Vec<String> = frames.iter().map(|(k, _)| k.clone()).collect();
        let partner_frame = FakeFrame::new("P", 12_000_000_000, 0.999, -0.002, 1.0, 3.0);
        let mut all = frames.clone();
        all.push(("/d/p.fits".into(), partner_frame.clone()));
        let world = World::new(&all, diag(0.0, 0.0, SX, SX));
        // The partner frame's own chain (e.g. its keyframe series): origin → partner.
        let partner_chain = Chain::origin(Similarity::array_center(WIDTH, HEIGHT), None)
            .then(&partner_frame.truth, Some(&diag(0.0, 0.0, SX, SX)));
        let partner = PartnerFrame {
            channel: "P".into(),
            key: "/d/p.fits".into(),
            spec: parse_frame_key("/d/p.fits"),
            obs_time_ns: 12_000_000_000,
            chain: Some(partner_chain),
        };
        let mut state = ChannelState::new("C", policy(PolicySpec::Channel("P".into())));
        let mut records = Vec::new();
        for k in &keys[1..3] {
            records.extend(
                state
                    .process(&world.loaded(k), Some(&partner), &world)
                    .records,
            );
        }
        let msgs = messages(&records);
        for (m, i) in msgs.iter().zip(1..) {
            assert_eq!(
                (m.reference_kind, m.align.reference.as_str()),
                (ReferenceKind::Channel, "/d/p.fits")
            );
            // Partner chain then partner→frame = the frame's true pointing.
            assert_chained_is_truth(m, &frames[i].1.truth);
            // One link (partner → frame) after the partner's own: SX² + s² SX².
            let s = frames[i].1.truth.scale / partner_frame.truth.scale;
            let expect = (SX * SX * (1.0 + s * s)).sqrt();
            assert!((m.sigma_chained_dx_px.unwrap() - expect).abs() <= 1e-8 * expect);
        }
        let ch = changes(&records);
        assert_eq!(ch.len(), 1, "same partner twice: one change");
        assert!(ch[0].reason.contains("nearest P frame"), "{}", ch[0].reason);
    }

    #[test]
    fn restored_state_continues_exactly_where_the_log_stopped() {
        // Run 11 frames straight, and 6 + restart + 5: the second half must be identical
        // (pure translations: diagonal covariances, so nothing is lost by the log's σ).
        let frames: Vec<(String, FakeFrame)> = (0..11)
            .map(|i| {
                let f = FakeFrame::new(
                    "C",
                    i * 1_000_000_000,
                    1.0,
                    0.0,
                    (i as f64).sin(),
                    0.1 * i as f64,
                );
                (format!("/d/r{i:02}.fits"), f)
            })
            .collect();
        let keys: Vec<String> = frames.iter().map(|(k, _)| k.clone()).collect();
        let world = World::new(&frames, diag(0.0, 0.0, SX, SX));
        let mut p = policy(PolicySpec::Keyframe);
        p.keyframe_every_frames = 4;
        let mut straight = ChannelState::new("C", p.clone());
        let all = run(&mut straight, &world, &keys);

        let mut first = ChannelState::new("C", p.clone());
        let before = run(&mut first, &world, &keys[..6]);
        let n_before = before.len();
        let mut history = History::default();
        for r in &before {
            history.add(r);
        }
        let mut resumed = ChannelState::restore("C", p.clone(), &history.channels["C"]);
        let after = run(&mut resumed, &world, &keys[6..]);
        assert_eq!(&all[n_before..], &after[..]);

        // The MCAP schema keeps no chain in /reference messages: the restart then takes the
        // chain from the reference frame's own message (σ only), which for these diagonal
        // covariances is the same to rounding.
        let bare = history_stripped(&before, |c| {
            c.chain = None;
        });
        let mut resumed = ChannelState::restore("C", p, &bare.channels["C"]);
        let after = run(&mut resumed, &world, &keys[6..]);
        let expect = messages(&all[n_before..]);
        let got = messages(&after);
        assert_eq!(expect.len(), got.len());
        for (e, g) in expect.iter().zip(&got) {
            assert_eq!(
                (&e.align.frame, &e.align.reference, e.sequence),
                (&g.align.frame, &g.align.reference, g.sequence)
            );
            assert_chained_is_truth(g, &frames[g.sequence as usize].1.truth);
            let (es, gs) = (
                e.sigma_chained_dx_px.unwrap(),
                g.sigma_chained_dx_px.unwrap(),
            );
            assert!((es - gs).abs() <= 1e-9 * es, "{es} vs {gs}");
        }
    }

    /// Injected: alignments to the origin use 0.6″/px along x and −0.6 along y (a flipped
    /// axis), while every outcome claims 7″/px for its own reference. The chained series in
    /// arcsec is the chained one in px times the origin's, through keyframe hand-overs and a
    /// restart from a log whose `/reference` messages keep no chain.
    #[test]
    fn chained_arcsec_use_the_plate_scale_of_the_chains_origin() {
        const ORIGIN: [f64; 2] = [0.6, -0.6];
        struct Plated<'a>(&'a World);
        impl StepContext for Plated<'_> {
            fn align(&self, reference: &Image, frame: &Image) -> AlignOutcome {
                let mut outcome = self.0.align(reference, frame);
                if let Some(g) = outcome.reference_geometry.as_mut() {
                    g.plate_scale_arcsec = [7.0, 7.0];
                }
                outcome
            }
            fn load(&self, spec: &FrameSpec) -> sunjitter_core::Result<Image> {
                self.0.load(spec)
            }
            fn plate_scale_used(&self, _image: &Image) -> Option<[f64; 2]> {
                Some(ORIGIN)
            }
        }
        let frames = series(11);
        let keys: Vec<String> = frames.iter().map(|(k, _)| k.clone()).collect();
        let world = World::new(&frames, diag(0.0, 0.0, SX, SX));
        let ctx = Plated(&world);
        let mut p = policy(PolicySpec::Keyframe);
        p.keyframe_every_frames = 3;
        let run_on = |state: &mut ChannelState, keys: &[String]| {
            let mut out = Vec::new();
            for key in keys {
                out.extend(state.process(&world.loaded(key), None, &ctx).records);
            }
            out
        };
        let check = |m: &FrameAlignment| {
            let pairs = [
                (m.chained_dx_arcsec, m.chained_dx_px, ORIGIN[0]),
                (m.chained_dy_arcsec, m.chained_dy_px, ORIGIN[1]),
                (
                    m.sigma_chained_dx_arcsec,
                    m.sigma_chained_dx_px,
                    ORIGIN[0].abs(),
                ),
                (
                    m.sigma_chained_dy_arcsec,
                    m.sigma_chained_dy_px,
                    ORIGIN[1].abs(),
                ),
            ];
            for (arcsec, px, plate) in pairs {
                let (a, p) = (arcsec.unwrap(), px.unwrap());
                assert!((a - p * plate).abs() <= 1e-12 * (1.0 + a.abs()), "{m:?}");
            }
        };
        let mut straight = ChannelState::new("C", p.clone());
        let all = run_on(&mut straight, &keys);
        let msgs = messages(&all);
        assert!(changes(&all).len() >= 3, "keyframes handed over");
        assert!(msgs.iter().any(|m| m.chained_dx_px.unwrap().abs() > 0.1));
        msgs.iter().for_each(|m| check(m));

        let mut first = ChannelState::new("C", p.clone());
        let before = run_on(&mut first, &keys[..5]);
        let bare = history_stripped(&before, |c| {
            c.chain = None;
        });
        let mut resumed = ChannelState::restore("C", p, &bare.channels["C"]);
        let after = run_on(&mut resumed, &keys[5..]);
        assert_eq!(messages(&after).len(), 6);
        messages(&after).iter().for_each(|m| check(m));
    }
}
