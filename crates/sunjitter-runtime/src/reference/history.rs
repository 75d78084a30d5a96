//! What an existing log says: which frames are finished, and each channel's state to continue
//! from (restart).

use super::RestoredChannel;
use std::collections::{BTreeMap, HashSet};
use sunjitter_io::records::Record;
use sunjitter_io::sink::LogLevel;

/// What earlier runs logged in the output: which frames are finished, and each channel's
/// state to continue from. Built from the sink's reader with [`History::add`].
#[derive(Debug, Clone, Default)]
pub struct History {
    /// Frame keys (and file keys) already logged as a measurement or a terminal `/log` entry.
    pub done: HashSet<String>,
    pub channels: BTreeMap<String, RestoredChannel>,
}

/// Frame messages kept per channel for restoring its state.
const RESTORE_TAIL: usize = 256;

impl History {
    pub fn add(&mut self, record: &Record) {
        match record {
            Record::Frame {
                message,
                log_time_ns,
            } => {
                self.done.insert(message.align.frame.clone());
                let ch = self.channels.entry(message.channel.clone()).or_default();
                ch.next_sequence = ch.next_sequence.max(message.sequence + 1);
                ch.last_obs_time_ns = ch.last_obs_time_ns.max(Some(*log_time_ns));
                let at = ch
                    .recent
                    .partition_point(|(m, _)| m.sequence < message.sequence);
                if ch
                    .recent
                    .get(at)
                    .is_none_or(|(m, _)| m.sequence != message.sequence)
                {
                    ch.recent.insert(at, ((**message).clone(), *log_time_ns));
                }
                if ch.recent.len() > RESTORE_TAIL {
                    let excess = ch.recent.len() - RESTORE_TAIL;
                    ch.recent.drain(..excess);
                }
            }
            Record::Reference {
                change,
                log_time_ns,
            } => {
                let ch = self.channels.entry(change.channel.clone()).or_default();
                let newer = ch
                    .last_reference
                    .as_ref()
                    .is_none_or(|(c, t)| (change.sequence, *log_time_ns) >= (c.sequence, *t));
                if newer {
                    let older = ch
                        .last_reference
                        .replace(((**change).clone(), *log_time_ns));
                    if older.as_ref().is_some_and(|(c, _)| c.key() != change.key()) {
                        ch.previous_reference = older;
                    }
                } else {
                    let older_than_previous = ch
                        .previous_reference
                        .as_ref()
                        .is_none_or(|(c, t)| (change.sequence, *log_time_ns) >= (c.sequence, *t));
                    let is_last = ch
                        .last_reference
                        .as_ref()
                        .is_some_and(|(c, _)| c.key() == change.key());
                    if older_than_previous && !is_last {
                        ch.previous_reference = Some(((**change).clone(), *log_time_ns));
                    }
                }
            }
            Record::Log { level, file, .. } => {
                if *level >= LogLevel::Error && !file.is_empty() {
                    self.done.insert(file.clone());
                }
            }
        }
    }

    pub fn is_done(&self, key: &str) -> bool {
        self.done.contains(key)
    }
}
