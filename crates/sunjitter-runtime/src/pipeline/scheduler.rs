//! Scheduler: per-channel order, reorder window, partner choice.

use super::frames::FrameItem;
use super::job::{Job, JobDone};
use crate::config::Config;
use crate::reference::History;
use crate::reference::{
    ChannelState, PartnerFrame, PolicySpec, ReferencePolicies, RestoredChannel,
};
use std::collections::{BTreeMap, VecDeque};
use std::sync::Arc;
use std::time::{Duration, Instant};
use sunjitter_io::records::Record;
use sunjitter_io::sink::LogLevel;

/// What the scheduler wants done.
#[derive(Debug)]
pub enum Action {
    Run(Box<Job>),
    Emit(Record),
}

#[derive(Debug, Default)]
struct Lane {
    state: Option<ChannelState>,
    buffer: BTreeMap<(i64, String), FrameItem>,
    in_flight: bool,
    /// Observation time of the frame being processed.
    in_flight_ns: Option<i64>,
    last_dispatched_ns: Option<i64>,
    /// Processed, usable frames of this channel (candidates for `channel:` followers).
    history: VecDeque<PartnerFrame>,
    /// Last time a frame of this channel arrived or finished (wall clock).
    last_activity: Option<Instant>,
}

enum PartnerChoice {
    Wait,
    Unmatched(String),
    Use(Box<PartnerFrame>),
}

/// Scheduling settings.
#[derive(Debug, Clone)]
pub struct SchedulerSettings {
    /// Daemon (wall-clock reorder window and partner hold) or replay (all input known at EOF).
    pub live: bool,
    pub workers: usize,
    pub reorder_window_frames: usize,
    pub reorder_window: Duration,
    /// Longest a frame is held while files are still in the pipe (window + settle time).
    pub reorder_cap: Duration,
}

impl SchedulerSettings {
    pub fn from_config(config: &Config, live: bool) -> SchedulerSettings {
        SchedulerSettings {
            live,
            workers: config.daemon.workers.max(1),
            reorder_window_frames: config.daemon.reorder_window_frames,
            reorder_window: Duration::from_secs_f64(config.daemon.reorder_window_s),
            reorder_cap: Duration::from_secs_f64(
                config.daemon.reorder_window_s + config.daemon.settle_s,
            ),
        }
    }
}

/// Decides which frame of which channel runs next. Pure state, no I/O, no clock of its own.
pub struct Scheduler {
    config: Arc<Config>,
    /// Every channel's reference settings, resolved once for the run.
    policies: ReferencePolicies,
    settings: SchedulerSettings,
    restored: BTreeMap<String, RestoredChannel>,
    lanes: BTreeMap<String, Lane>,
    running: usize,
    eof: bool,
    /// The front end has no file in hand that could still yield frames.
    pipe_empty: bool,
}

/// Partner history kept per channel beyond what waiting followers need.
const PARTNER_HISTORY_MIN: usize = 4;

impl Scheduler {
    pub fn new(config: Arc<Config>, settings: SchedulerSettings, history: &History) -> Scheduler {
        Scheduler {
            policies: config.reference_policies(),
            config,
            settings,
            restored: history.channels.clone(),
            lanes: BTreeMap::new(),
            running: 0,
            eof: false,
            pipe_empty: true,
        }
    }

    /// Whether the front end still has files in hand (see
    /// [`run_pipeline`](super::run_pipeline)).
    pub fn set_pipe_empty(&mut self, empty: bool) {
        self.pipe_empty = empty;
    }

    /// Take a frame; a frame of one channel more than `[daemon] max_channels` is not taken,
    /// and the `/log` record naming it comes back instead.
    pub fn offer(&mut self, item: FrameItem) -> Option<Record> {
        let cap = self.config.daemon.max_channels;
        if !self.lanes.contains_key(&item.channel) && self.lanes.len() >= cap {
            return Some(Record::log(
                LogLevel::Error,
                &item.key,
                format!(
                    "channel {}: {cap} channels are tracked already (`[daemon] max_channels`); not measured",
                    item.channel
                ),
                item.obs_time_ns,
            ));
        }
        let lane = self.lanes.entry(item.channel.clone()).or_default();
        lane.buffer
            .insert((item.obs_time_ns, item.key.clone()), item);
        None
    }

    /// No more input will come (replay: everything is known; frames are released).
    pub fn set_eof(&mut self) {
        self.eof = true;
    }

    pub fn is_eof(&self) -> bool {
        self.eof
    }

    /// Nothing buffered and nothing running.
    pub fn idle(&self) -> bool {
        self.running == 0 && self.lanes.values().all(|l| l.buffer.is_empty())
    }

    pub fn running(&self) -> usize {
        self.running
    }

    pub fn buffered(&self) -> usize {
        self.lanes.values().map(|l| l.buffer.len()).sum()
    }

    /// Frames buffered or being aligned, per channel.
    pub fn queued_by_channel(&self) -> BTreeMap<String, u64> {
        self.lanes
            .iter()
            .map(|(name, l)| (name.clone(), l.buffer.len() as u64 + u64::from(l.in_flight)))
            .collect()
    }

    /// Everything that can start now.
    pub fn poll(&mut self, now: Instant) -> Vec<Action> {
        let mut actions = Vec::new();
        loop {
            let mut progressed = false;
            let names: Vec<String> = self.lanes.keys().cloned().collect();
            for name in names {
                if self.running >= self.settings.workers {
                    return actions;
                }
                if let Some(action) = self.poll_lane(&name, now) {
                    progressed = true;
                    actions.push(action);
                }
            }
            if !progressed {
                return actions;
            }
        }
    }

    fn released(&self, lane: &Lane, now: Instant) -> bool {
        let Some(((t, _), _)) = lane.buffer.first_key_value() else {
            return false;
        };
        if self.eof {
            return true;
        }
        if !self.settings.live {
            return false;
        }
        if lane.last_dispatched_ns.is_some_and(|last| *t < last)
            || lane.buffer.len() > self.settings.reorder_window_frames
        {
            return true;
        }
        let oldest = lane.buffer.values().map(|i| i.arrived).min();
        let age = oldest.map_or(Duration::ZERO, |a| now.saturating_duration_since(a));
        // Files still in the pipe may hold earlier frames: wait for them, within the cap.
        (age >= self.settings.reorder_window && self.pipe_empty) || age >= self.settings.reorder_cap
    }

    fn poll_lane(&mut self, name: &str, now: Instant) -> Option<Action> {
        let lane = self.lanes.get(name)?;
        if lane.in_flight || !self.released(lane, now) {
            return None;
        }
        let (_, head) = lane.buffer.first_key_value()?;
        let policy = self.policies.get(name);
        let partner = match &policy.policy {
            PolicySpec::Channel(partner_name) => {
                match self.choose_partner(
                    partner_name,
                    head,
                    policy.tolerance_s,
                    policy.hold_s,
                    now,
                ) {
                    PartnerChoice::Wait => return None,
                    PartnerChoice::Unmatched(why) => {
                        let lane = self.lanes.get_mut(name)?;
                        let (_, item) = lane.buffer.pop_first()?;
                        return Some(Action::Emit(Record::log(
                            LogLevel::Error,
                            &item.key,
                            why,
                            item.obs_time_ns,
                        )));
                    }
                    PartnerChoice::Use(p) => Some(*p),
                }
            }
            _ => None,
        };
        let restored = self.restored.remove(name);
        let lane = self.lanes.get_mut(name)?;
        let (_, item) = lane.buffer.pop_first()?;
        let late = lane
            .last_dispatched_ns
            .is_some_and(|t| item.obs_time_ns < t);
        lane.last_dispatched_ns = lane.last_dispatched_ns.max(Some(item.obs_time_ns));
        let state = lane.state.take().unwrap_or_else(|| match restored {
            Some(r) => ChannelState::restore(name, policy.clone(), &r),
            None => ChannelState::new(name, policy.clone()),
        });
        lane.in_flight = true;
        self.running += 1;
        Some(Action::Run(Box::new(Job {
            channel: name.to_string(),
            state,
            item,
            partner,
            late,
        })))
    }

    fn choose_partner(
        &self,
        partner: &str,
        item: &FrameItem,
        tolerance_s: f64,
        hold_s: f64,
        now: Instant,
    ) -> PartnerChoice {
        let lane = self.lanes.get(partner);
        let history = lane.map(|l| &l.history);
        let t = item.obs_time_ns;
        let tolerance_ns = (tolerance_s * 1e9) as i64;
        // A partner frame still to be processed may be nearer than any processed one.
        let nearer_pending = lane.is_some_and(|l| {
            l.buffer
                .keys()
                .next()
                .is_some_and(|(pt, _)| *pt <= t + tolerance_ns)
                || (l.in_flight && l.in_flight_ns.is_some_and(|pt| pt <= t + tolerance_ns))
        });
        if nearer_pending {
            return PartnerChoice::Wait;
        }
        let before = history.and_then(|h| h.iter().rev().find(|p| p.obs_time_ns <= t));
        let after = history.and_then(|h| h.iter().find(|p| p.obs_time_ns >= t));
        let idle = lane.is_none_or(|l| l.buffer.is_empty() && !l.in_flight);
        let exhausted = self.eof && idle;
        // Live: give up only once the partner has nothing pending, no file is in the pipe,
        // and the partner has been quiet for `hold_s` (a busy partner is waited for).
        let expired = self.settings.live
            && idle
            && self.pipe_empty
            && now.saturating_duration_since(self.hold_start(partner, item))
                >= Duration::from_secs_f64(hold_s);
        if after.is_none() && !exhausted && !expired {
            return PartnerChoice::Wait;
        }
        let mut best: Option<&PartnerFrame> = None;
        for p in [before, after].into_iter().flatten() {
            let dt = (p.obs_time_ns - t).abs();
            if dt <= tolerance_ns && best.is_none_or(|b| dt < (b.obs_time_ns - t).abs()) {
                best = Some(p);
            }
        }
        match best {
            Some(p) => PartnerChoice::Use(Box::new(p.clone())),
            None => PartnerChoice::Unmatched(format!(
                "unmatched: no {partner} frame within ±{tolerance_s} s"
            )),
        }
    }

    /// When a frame's wait for a partner began counting: its arrival or the partner's last
    /// activity, whichever is later.
    fn hold_start(&self, partner: &str, item: &FrameItem) -> Instant {
        let activity = self.lanes.get(partner).and_then(|l| l.last_activity);
        activity.map_or(item.arrived, |a| a.max(item.arrived))
    }

    /// A job finished: take its state back and record the frame for followers.
    pub fn complete(&mut self, done: JobDone) {
        self.running = self.running.saturating_sub(1);
        let lane = self.lanes.entry(done.channel.clone()).or_default();
        lane.in_flight = false;
        lane.in_flight_ns = None;
        lane.last_activity = Some(Instant::now());
        lane.state = Some(done.state);
        if let Some(p) = done.partner {
            let at = lane
                .history
                .partition_point(|q| q.obs_time_ns <= p.obs_time_ns);
            lane.history.insert(at, p);
        }
        self.prune_history(&done.channel);
    }

    /// Drop partner frames no waiting follower can still choose.
    fn prune_history(&mut self, channel: &str) {
        let mut oldest_needed: Option<i64> = None;
        let mut has_followers = false;
        for (name, lane) in &self.lanes {
            if !self.policies.follows(name, channel) {
                continue;
            }
            let p = self.policies.get(name);
            has_followers = true;
            let tol = (p.tolerance_s * 1e9) as i64;
            let pending = lane
                .buffer
                .keys()
                .next()
                .map(|(t, _)| *t)
                .or(lane.last_dispatched_ns);
            if let Some(t) = pending {
                let need = t.saturating_sub(tol);
                oldest_needed = Some(oldest_needed.map_or(need, |o| o.min(need)));
            }
        }
        let Some(lane) = self.lanes.get_mut(channel) else {
            return;
        };
        if !has_followers {
            while lane.history.len() > PARTNER_HISTORY_MIN {
                lane.history.pop_front();
            }
            return;
        }
        if let Some(oldest) = oldest_needed {
            // Keep one frame before `oldest` (it may still be the nearest).
            while lane.history.len() > PARTNER_HISTORY_MIN
                && lane.history.get(1).is_some_and(|p| p.obs_time_ns < oldest)
            {
                lane.history.pop_front();
            }
        }
    }

    /// When the scheduler next needs a look without new input (daemon only).
    pub fn next_deadline(&self) -> Option<Instant> {
        if !self.settings.live || self.eof {
            return None;
        }
        let mut next: Option<Instant> = None;
        let mut consider = |t: Instant| next = Some(next.map_or(t, |n: Instant| n.min(t)));
        for (name, lane) in &self.lanes {
            if lane.in_flight {
                continue;
            }
            if let Some(first) = lane.buffer.values().map(|i| i.arrived).min() {
                consider(first + self.settings.reorder_window);
                consider(first + self.settings.reorder_cap);
            }
            let policy = self.policies.get(name);
            if let PolicySpec::Channel(partner) = &policy.policy {
                if let Some((_, head)) = lane.buffer.first_key_value() {
                    let start = self.hold_start(partner, head);
                    consider(start + Duration::from_secs_f64(policy.hold_s));
                }
            }
        }
        next
    }
}
