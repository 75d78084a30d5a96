//! The production reader and aligner: FITS files, and the engine with a cache of prepared
//! references.

use crate::config::Config;
use crate::ports::{Aligner, FrameReader};
use std::path::Path;
use std::sync::{Arc, Mutex};
use sunjitter_core::engine::{
    AlignOutcome, EngineConfig, FrameWork, Image, PreparedReference, Workspace,
};
use sunjitter_core::meta::FrameMeta;
use sunjitter_core::Result;
use sunjitter_io::fits::FrameSpec;

/// The FITS reader, with the configured limits on what a file may claim and the plate
/// scales given for channels.
#[derive(Debug, Clone, Default)]
pub struct FitsReader {
    pub options: sunjitter_io::fits::ReadOptions,
}

impl FitsReader {
    pub fn from_config(config: &Config) -> FitsReader {
        FitsReader {
            options: sunjitter_io::fits::ReadOptions {
                limits: sunjitter_io::fits::ReadLimits {
                    max_frame_pixels: config.daemon.max_frame_pixels,
                },
                plate_scales: config.plate_scales(),
            },
        }
    }
}

impl FrameReader for FitsReader {
    fn read_meta(&self, path: &Path) -> Result<Vec<FrameMeta>> {
        sunjitter_io::fits::read_meta_with(path, &self.options)
    }
    fn read_frame(&self, spec: &FrameSpec) -> Result<Image> {
        sunjitter_io::fits::read_frame_with(spec, &self.options)
    }
}

/// The alignment engine. Keeps the prepared references (cleaned image, mask, window, …) that
/// its channels align to, so a reference used for many frames is prepared once.
pub struct EngineAligner {
    config: EngineConfig,
    channels: ChannelEngine,
    prepared: Mutex<Vec<(ReferenceKey, Arc<PreparedReference>)>>,
    /// Each channel's last aligned frame, cleaned and disk-checked: under `previous` it is the
    /// next reference.
    last_frames: Mutex<Vec<(String, ReferenceKey, FrameWork)>>,
    /// The reference each frame channel's latest alignment used. A prepared reference that no
    /// channel uses any more is dropped at once: under `previous` every frame makes a new one,
    /// and the stale ones would hold hundreds of MB at 4096².
    in_use: Mutex<Vec<(String, ReferenceKey)>>,
    /// The flow solver's memory, shared by every reference prepared here.
    workspace: Arc<Workspace>,
}

/// At most this many prepared references are kept (a 4096² one holds ≈ 150 MB): enough for
/// a few channels processed at once.
const PREPARED_REFERENCES: usize = 3;

/// Identifies a reference image in memory: the same `Image` allocation with the same pixel
/// buffer, file and a sample of its pixels (so a freed image whose addresses are reused by
/// another is not mistaken for it).
#[derive(Debug, Clone, PartialEq)]
struct ReferenceKey {
    image: usize,
    pixels: usize,
    shape: (usize, usize),
    file: std::path::PathBuf,
    sample: Vec<u32>,
}

impl ReferenceKey {
    fn of(image: &Image) -> ReferenceKey {
        let data = &image.data;
        let n = data.len();
        let step = (n / 61).max(1);
        ReferenceKey {
            image: image as *const Image as usize,
            pixels: data.as_ptr() as usize,
            shape: data.dim(),
            file: image.meta.file.clone(),
            sample: match data.as_slice_memory_order() {
                Some(all) => all.iter().step_by(step).map(|v| v.to_bits()).collect(),
                None => data.iter().step_by(step).map(|v| v.to_bits()).collect(),
            },
        }
    }
}

impl EngineAligner {
    pub fn new(config: EngineConfig) -> EngineAligner {
        EngineAligner {
            config,
            channels: Default::default(),
            prepared: Mutex::new(Vec::new()),
            last_frames: Mutex::new(Vec::new()),
            in_use: Mutex::new(Vec::new()),
            workspace: Default::default(),
        }
    }

    /// Align in `workspace` (one that keeps self-tests between runs, say) instead of one of
    /// its own.
    pub fn sharing(mut self, workspace: Workspace) -> EngineAligner {
        self.workspace = Arc::new(workspace);
        self
    }

    /// The whole configuration's engine, with each channel's own settings.
    pub fn from_config(config: &crate::config::Config) -> EngineAligner {
        EngineAligner {
            channels: ChannelEngine {
                by_channel: config.channel_settings(),
                names: config.channel_names.clone(),
                plate_scales: config.channel_plate_scales(),
            },
            ..EngineAligner::new(config.engine.clone())
        }
    }

    pub fn config(&self) -> &EngineConfig {
        &self.config
    }

    /// The prepared reference for `reference`, from the cache or made now.
    fn prepared(&self, reference: &Image) -> Arc<PreparedReference> {
        self.prepared_as(reference, ReferenceKey::of(reference), None)
    }

    /// [`Self::prepared`] with the reference's key already taken, and its position along its
    /// chain where known.
    fn prepared_as(
        &self,
        reference: &Image,
        key: ReferenceKey,
        position: Option<u64>,
    ) -> Arc<PreparedReference> {
        let lock = || match self.prepared.lock() {
            Ok(g) => g,
            Err(poisoned) => poisoned.into_inner(),
        };
        if let Some((_, p)) = lock().iter().find(|(k, _)| *k == key) {
            return p.clone();
        }
        let kept = {
            let mut last = match self.last_frames.lock() {
                Ok(g) => g,
                Err(poisoned) => poisoned.into_inner(),
            };
            let at = last.iter().position(|(_, k, _)| *k == key);
            at.map(|i| last.swap_remove(i).2)
        };
        // Prepared outside the lock: other channels keep aligning meanwhile.
        let made = match kept {
            Some(work) => PreparedReference::from_frame_work(reference, &self.config, work),
            None => PreparedReference::new(reference, &self.config),
        }
        .sharing(self.workspace.clone());
        let made = Arc::new(match position {
            Some(p) => made.at_position(p),
            None => made,
        });
        let mut cache = lock();
        if cache.len() >= PREPARED_REFERENCES {
            cache.remove(0);
        }
        cache.push((key, made.clone()));
        made
    }
}

impl EngineAligner {
    /// Record that `channel` now aligns to `key`; drop the prepared reference it used before
    /// when no other channel uses it (an alignment still running on it keeps its own `Arc`).
    fn used_by(&self, channel: &str, key: ReferenceKey) {
        let mut in_use = self.in_use.lock().unwrap_or_else(|p| p.into_inner());
        let before = in_use
            .iter()
            .position(|(c, _)| c == channel)
            .map(|i| in_use.swap_remove(i).1);
        in_use.push((channel.to_string(), key));
        if let Some(old) = before.filter(|old| in_use.iter().all(|(_, k)| k != old)) {
            let mut cache = self.prepared.lock().unwrap_or_else(|p| p.into_inner());
            cache.retain(|(k, _)| *k != old);
        }
    }
}

impl Default for EngineAligner {
    fn default() -> Self {
        EngineAligner::new(EngineConfig::default())
    }
}

impl std::fmt::Debug for EngineAligner {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("EngineAligner")
            .field("config", &self.config)
            .finish_non_exhaustive()
    }
}

impl EngineAligner {
    /// Align `frame` to `reference` (at `position` along its chain, where known), keeping
    /// the work on `frame` for when it becomes the next reference.
    fn align_to(&self, reference: &Image, position: Option<u64>, frame: &Image) -> AlignOutcome {
        let channel = &frame.meta.channel;
        let name = self.channels.names.get(channel).unwrap_or(channel);
        let settings = self.channels.by_channel.get(name).copied();
        let key = ReferenceKey::of(reference);
        let prepared = self.prepared_as(reference, key.clone(), position);
        self.used_by(channel, key);
        let (mut outcome, kept) =
            prepared.align_keeping(frame, &settings.unwrap_or(self.config.channel_settings()));
        if let Some(note) = self.channels.plate_scale_note(&reference.meta, &frame.meta) {
            let message = &mut outcome.result.message;
            if !message.is_empty() {
                message.push_str("; ");
            }
            message.push_str(&note);
        }
        if let Some(work) = kept {
            let mut last = match self.last_frames.lock() {
                Ok(g) => g,
                Err(poisoned) => poisoned.into_inner(),
            };
            last.retain(|(c, _, _)| c != channel);
            last.push((channel.clone(), ReferenceKey::of(frame), work));
        }
        outcome
    }
}

impl Aligner for EngineAligner {
    fn align(&self, reference: &Image, frame: &Image) -> AlignOutcome {
        self.align_to(reference, None, frame)
    }

    fn align_at(&self, reference: &Image, position: u64, frame: &Image) -> AlignOutcome {
        self.align_to(reference, Some(position), frame)
    }

    fn usable_as_reference(&self, image: &Image) -> std::result::Result<(), String> {
        sunjitter_core::engine::usable_as_reference(image)
    }

    fn plate_scale_used(&self, image: &Image) -> Option<[f64; 2]> {
        self.prepared(image)
            .geometry()
            .map(|g| g.plate_scale_arcsec)
            .or(Some(image.meta.plate_scale_arcsec))
    }

    fn geometry_used(&self, image: &Image) -> Option<sunjitter_core::engine::UsedGeometry> {
        self.prepared(image).geometry()
    }
}

/// Channels whose engine settings or plate scale are their own, by topic name, and the
/// header channel → topic name map that finds them.
#[derive(Debug, Default)]
struct ChannelEngine {
    by_channel: std::collections::BTreeMap<String, sunjitter_core::engine::ChannelSettings>,
    names: std::collections::BTreeMap<String, String>,
    /// `[channels.X] plate_scale_arcsec` (the reader applied them; the message says so).
    plate_scales: std::collections::BTreeMap<String, f64>,
}

impl ChannelEngine {
    fn plate_scale_note(&self, reference: &FrameMeta, frame: &FrameMeta) -> Option<String> {
        crate::config::plate_scale_note(
            &self.plate_scales,
            &self.names,
            &reference.channel,
            &frame.channel,
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_prepared_reference_no_channel_aligns_to_is_dropped() {
        let path = Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("../../data/real/aia_171_20110215T000000_128.fits");
        let spec = FrameSpec { path, frame: None };
        let real = FitsReader::default()
            .read_frame(&spec)
            .expect("bundled AIA image");
        let image = |offset: f32, channel: &str| Image {
            data: real.data.mapv(|v| v + offset),
            meta: FrameMeta {
                channel: channel.into(),
                ..real.meta.clone()
            },
        };
        let (a, b, c, other) = (
            image(0.0, "A"),
            image(1.0, "A"),
            image(2.0, "A"),
            image(0.0, "B"),
        );
        let aligner = EngineAligner::default();
        let cached = |img: &Image| {
            let key = ReferenceKey::of(img);
            aligner
                .prepared
                .lock()
                .unwrap()
                .iter()
                .any(|(k, _)| *k == key)
        };
        aligner.align(&a, &b);
        aligner.align(&a, &other);
        // Channel A moves on to `b`; channel B still aligns to `a`.
        aligner.align(&b, &c);
        assert!(cached(&a) && cached(&b));
        // Now no channel aligns to `a`.
        aligner.align(&b, &other);
        assert!(!cached(&a) && cached(&b));
    }
}
