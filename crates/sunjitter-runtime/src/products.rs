//! The per-frame FITS products of `watch` and `replay` (`--aligned DIR`, `--wcs-only`).
//!
//! A product gives a frame the pointing its channel's chain measured: the chain's origin (the
//! frame that started the chain, or a `fixed:` reference) keeps its header's pointing (with the
//! disk-checked plate scale and Sun centre where the engine refused the header's), and every
//! later frame is put on it through its chained transform (origin grid → frame grid).
//!
//! - Resampled (`--aligned DIR`): the frame resampled onto the origin's pixel grid, with the
//!   origin's WCS, as `align --aligned` writes a pair.
//! - Header only (`--wcs-only`): the frame's own pixels, its WCS recomputed through the
//!   chained transform so that a pixel's world coordinates are those of the matching origin
//!   pixel.
//!
//! The origin's grid is found without keeping state between runs: a frame's reference already
//! has its product in `DIR` (written when it was measured, in this run or an earlier one), and
//! a product records its chained transform (`SJ_*` cards), so the origin's grid is that
//! product's grid taken back through its transform. A frame whose reference has no product
//! (products asked for only after its chain began) keeps its own header's pointing, and the
//! frames after it are put on it. Names mirror the inputs below a root (the
//! watched directory, or the deepest directory holding every input of a replay): `DIR/REL`
//! without its FITS extension (`.fits`, `.fit`, `.fts`, also gzip- or fpack-compressed), plus
//! `[N]` for frame N of a cube, plus `.aligned.fits` or `.wcs.fits` (`a/x.fits[3]` →
//! `DIR/a/x[3].aligned.fits`), with `REL` spelled as frame keys are (see
//! [`sunjitter_core::text::path`]). Two inputs that differ only in their extension (`x.fits`,
//! `x.fits.gz`) would share a name: the product belongs to the first frame written there
//! (its `SRCFILE`/`SRCFRAME` cards say which), and the other frame gets a `/log` note instead.

use crate::reference::{StepContext, StepOutput};
use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex};
use sunjitter_core::chain::Chain;
use sunjitter_core::engine::Image;
use sunjitter_core::geometry::{Similarity, ARCSEC_PER_RAD};
use sunjitter_core::header::HeaderValue;
use sunjitter_core::record::{FrameAlignment, ReferenceKind, Status};
use sunjitter_core::{Error, Result};
use sunjitter_io::aligned::{compose_wcs, is_grid_key, Grid};
use sunjitter_io::fits::parse_frame_key;
use sunjitter_io::records::Record;

/// What a product holds.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Mode {
    /// The frame resampled onto the origin's grid (`.aligned.fits`).
    Resampled,
    /// The frame's own pixels with its pointing corrected (`.wcs.fits`).
    WcsOnly,
}

impl Mode {
    fn suffix(self) -> &'static str {
        match self {
            Mode::Resampled => ".aligned.fits",
            Mode::WcsOnly => ".wcs.fits",
        }
    }
}

/// Writes products into one directory.
#[derive(Debug)]
pub struct Products {
    dir: PathBuf,
    /// The root's frame-key spelling, ending in `/`.
    root: String,
    mode: Mode,
    /// Grids of `fixed:` references that are not inputs (they have no product to start from).
    fixed: Mutex<HashMap<String, Arc<Grid>>>,
    /// Product paths written in this run, and the frame each belongs to.
    claimed: Mutex<HashMap<PathBuf, String>>,
}

/// The chained-transform cards: scale, rotation (arcsec), dx, dy (px), centre (0-based px).
const CHAIN_KEYS: [&str; 6] = ["SJ_SCALE", "SJ_ROT", "SJ_DX", "SJ_DY", "SJ_CX", "SJ_CY"];

/// A processed frame, as its product is written from: its key, its image, the pipeline's step
/// for it and the alignment that step logged.
#[derive(Clone, Copy)]
struct Processed<'a> {
    key: &'a str,
    image: &'a Arc<Image>,
    message: &'a FrameAlignment,
    step: &'a StepOutput,
}

impl Products {
    /// Products of frames found below `root` (canonical), written into `dir` (created).
    pub fn new(dir: &Path, root: &Path, wcs_only: bool) -> Result<Products> {
        std::fs::create_dir_all(dir).map_err(|e| Error::unwritable(dir, e))?;
        let dir = dir.canonicalize().map_err(|e| Error::io(dir, e))?;
        let mut root = sunjitter_core::text::path(root).into_owned();
        if !root.ends_with('/') {
            root.push('/');
        }
        Ok(Products {
            dir,
            root,
            mode: if wcs_only {
                Mode::WcsOnly
            } else {
                Mode::Resampled
            },
            fixed: Mutex::new(HashMap::new()),
            claimed: Mutex::new(HashMap::new()),
        })
    }

    pub fn mode(&self) -> Mode {
        self.mode
    }

    /// The directory products are written into (canonical).
    pub fn dir(&self) -> &Path {
        &self.dir
    }

    /// The product of frame `key` (`None` for a frame outside the root).
    pub fn path_for(&self, key: &str) -> Option<PathBuf> {
        let rel = key.strip_prefix(&self.root)?;
        if rel.is_empty() {
            return None;
        }
        let (file, frame) = match rel.strip_suffix(']').and_then(|r| r.rsplit_once('[')) {
            Some((file, n)) if !n.is_empty() && n.bytes().all(|b| b.is_ascii_digit()) => {
                (file, format!("[{n}]"))
            }
            _ => (rel, String::new()),
        };
        let stem = without_fits_extension(file);
        Some(
            self.dir
                .join(format!("{stem}{frame}{}", self.mode.suffix())),
        )
    }

    /// Whether the product at `path` is frame `key`'s (by its `SRCFILE` name and `SRCFRAME`);
    /// `None` when it cannot be read or does not say.
    fn belongs_to(path: &Path, key: &str) -> Option<bool> {
        let (_, header) = sunjitter_io::fits::read_image_header(path).ok()?;
        let source = header.get("SRCFILE")?.as_str()?.to_string();
        let frame = header.get("SRCFRAME").and_then(HeaderValue::as_i64);
        let spec = parse_frame_key(key);
        let name = |p: &Path| p.file_name().map(|n| n.to_string_lossy().into_owned());
        let own = spec.path.display().to_string();
        Some(
            name(Path::new(&source)) == name(Path::new(&own))
                && frame == spec.frame.map(|f| f as i64),
        )
    }

    /// Take `path` for frame `key` in this run. `Err` names the frame that holds it: another
    /// input of this run, or of an earlier one, whose name differs only in its extension.
    /// With `take` false, only check (a failed frame writes nothing, so holds no name).
    fn claim(&self, path: &Path, key: &str, take: bool) -> std::result::Result<(), String> {
        let mut claimed = self.claimed.lock().unwrap_or_else(|p| p.into_inner());
        if let Some(owner) = claimed.get(path) {
            return if owner == key {
                Ok(())
            } else {
                Err(sunjitter_core::text::escape(owner).into_owned())
            };
        }
        if path.is_file() && Self::belongs_to(path, key) == Some(false) {
            return Err("another input of an earlier run".to_string());
        }
        if take {
            claimed.insert(path.to_path_buf(), key.to_string());
        }
        Ok(())
    }

    /// After frame `key` was processed: write its product, or remove a stale one when the frame
    /// failed. Returns the `/log` note when a product could not be written.
    pub fn write(
        &self,
        key: &str,
        image: &Arc<Image>,
        step: &StepOutput,
        ctx: &dyn StepContext,
    ) -> Option<Record> {
        let message = step.records.iter().find_map(|r| match r {
            Record::Frame { message, .. } if message.align.frame == key => Some(message),
            _ => None,
        })?;
        let note = |why: String| {
            tracing::warn!(frame = %sunjitter_core::text::escape(key), "product not written: {why}");
            Some(Record::note(
                key,
                format!("product not written: {why}"),
                image.meta.obs_time_ns.unwrap_or_default(),
            ))
        };
        let Some(path) = self.path_for(key) else {
            return note(format!(
                "outside {}, the tree the products mirror",
                self.root.trim_end_matches('/')
            ));
        };
        let failed = message.align.status == Status::Failed;
        if let Err(owner) = self.claim(&path, key, !failed) {
            if failed {
                return None;
            }
            return note(format!(
                "{} holds the product of {owner}, whose name differs only in its extension",
                sunjitter_core::text::path(&path)
            ));
        }
        if failed {
            // A product left by a run stopped before it logged this frame must not outlive it.
            let _ = std::fs::remove_file(&path);
            return None;
        }
        let chain = step.partner.as_ref().and_then(|p| p.chain);
        let written = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
            let chain = chain.ok_or_else(|| "its reference has no chained pointing".to_string())?;
            let frame = Processed {
                key,
                image,
                message,
                step,
            };
            self.write_product(&path, &frame, &chain, ctx)
        }));
        match written {
            Ok(Ok(())) => None,
            Ok(Err(why)) => {
                let _ = std::fs::remove_file(&path);
                note(why)
            }
            Err(_) => {
                let _ = std::fs::remove_file(&path);
                note("internal error".into())
            }
        }
    }

    fn write_product(
        &self,
        path: &Path,
        frame: &Processed,
        chain: &Chain,
        ctx: &dyn StepContext,
    ) -> std::result::Result<(), String> {
        let Processed {
            key,
            image,
            message,
            step,
        } = *frame;
        let reason = |e: Error| e.reason();
        let t = chain.transform;
        let is_self = message.reference_kind == ReferenceKind::Itself;
        let anchored = if is_self && is_identity(&t) {
            None
        } else {
            self.anchor_grid(key, message, step)
        };
        let mut history = history(self.mode, message, &t);
        let origin = match anchored {
            Some(grid) => grid,
            None if message.reference_kind == ReferenceKind::Fixed => {
                self.fixed_grid(&message.align.reference, ctx)?
            }
            None => {
                // The chain's origin, or the first frame of its chain to get a product: its
                // header's pointing is kept, expressed on the chain's origin grid.
                if !is_identity(&t) {
                    history.push("its reference has no product: the frame's own".to_string());
                    history.push("pointing is kept, and later frames are put on it".to_string());
                }
                let mut grid = Grid::of_image(image, ctx.geometry_used(image)).map_err(reason)?;
                grid.cards = compose_wcs(&grid.cards, &t);
                Arc::new(grid)
            }
        };
        let extra = self.cards(message, chain);
        if let Some(parent) = path.parent() {
            std::fs::create_dir_all(parent).map_err(|e| format!("cannot create {e}"))?;
        }
        match self.mode {
            Mode::Resampled => {
                sunjitter_io::aligned::write_resampled(path, &origin, image, &t, history, &extra)
                    .map_err(reason)
            }
            Mode::WcsOnly => {
                let grid = Grid {
                    cards: compose_wcs(&origin.cards, &t.inverse()),
                    shape: image.data.dim(),
                    notes: origin.notes.clone(),
                };
                sunjitter_io::aligned::write_regridded_header(path, &grid, image, history, &extra)
                    .map_err(reason)
            }
        }
    }

    /// The origin's grid from the product of the frame's reference (for a keyframe that
    /// replaced another, of the one it replaced; for a frame logged again as its own
    /// reference, of itself), if there is one.
    fn anchor_grid(
        &self,
        key: &str,
        message: &FrameAlignment,
        step: &StepOutput,
    ) -> Option<Arc<Grid>> {
        let reference = message.align.reference.as_str();
        let mut anchors: Vec<&str> = Vec::new();
        if reference != key {
            anchors.push(reference);
        }
        if message.reference_kind == ReferenceKind::Itself {
            for r in &step.records {
                if let Record::Reference { change, .. } = r {
                    if let Some(replaced) = change.replaces.as_deref() {
                        if replaced != key {
                            anchors.push(replaced);
                        }
                    }
                }
            }
            anchors.push(key);
        }
        anchors.iter().find_map(|anchor| {
            let path = self.path_for(anchor).filter(|p| p.is_file())?;
            if Self::belongs_to(&path, anchor) == Some(false) {
                return None;
            }
            self.grid_of_product(&path).ok().map(Arc::new)
        })
    }

    /// The origin's grid from a product: a resampled product is on it; a header-only one holds
    /// it seen through its chained transform, which is undone.
    fn grid_of_product(&self, path: &Path) -> Result<Grid> {
        let (_, header) = sunjitter_io::fits::read_image_header(path)?;
        let get = |k: &str| header.get(k).and_then(HeaderValue::as_f64);
        let dim = |k: &str| header.get(k).and_then(HeaderValue::as_i64).unwrap_or(0) as usize;
        let cards: Vec<(String, HeaderValue)> = header
            .cards()
            .iter()
            .filter(|c| is_grid_key(&c.key))
            .filter_map(|c| Some((c.key.clone(), c.value.clone()?)))
            .collect();
        let shape = (dim("NAXIS2"), dim("NAXIS1"));
        let cards = match self.mode {
            Mode::Resampled => cards,
            Mode::WcsOnly => {
                let v = CHAIN_KEYS.map(get);
                let [Some(scale), Some(rot), Some(dx), Some(dy), Some(cx), Some(cy)] = v else {
                    return Err(Error::bad_input(path, "no SJ_* chained-transform cards"));
                };
                let t = Similarity {
                    scale,
                    rotation_rad: rot / ARCSEC_PER_RAD,
                    dx,
                    dy,
                    center: [cx, cy],
                };
                compose_wcs(&cards, &t)
            }
        };
        Ok(Grid {
            cards,
            shape,
            notes: Vec::new(),
        })
    }

    /// A `fixed:` reference is its chain's origin: its own grid (read once).
    fn fixed_grid(
        &self,
        key: &str,
        ctx: &dyn StepContext,
    ) -> std::result::Result<Arc<Grid>, String> {
        let lock = || self.fixed.lock().unwrap_or_else(|p| p.into_inner());
        if let Some(grid) = lock().get(key) {
            return Ok(grid.clone());
        }
        let reason = |e: Error| e.reason();
        let image = ctx.load(&parse_frame_key(key)).map_err(reason)?;
        let grid = Arc::new(Grid::of_image(&image, ctx.geometry_used(&image)).map_err(reason)?);
        lock().insert(key.to_string(), grid.clone());
        Ok(grid)
    }

    /// The cards that say what the product applied.
    fn cards(&self, m: &FrameAlignment, chain: &Chain) -> Vec<(String, HeaderValue)> {
        let t = chain.transform;
        let f = HeaderValue::Float;
        let mut cards = vec![
            ("SJ_STAT".to_string(), HeaderValue::Str(status_text(m))),
            (
                "SJ_REF".to_string(),
                HeaderValue::Str(m.align.reference.clone()),
            ),
        ];
        let values = [
            t.scale,
            t.rotation_arcsec(),
            t.dx,
            t.dy,
            t.center[0],
            t.center[1],
        ];
        cards.extend(
            CHAIN_KEYS
                .iter()
                .zip(values)
                .map(|(k, v)| (k.to_string(), f(v))),
        );
        if let (Some(sx), Some(sy)) = (m.sigma_chained_dx_px, m.sigma_chained_dy_px) {
            cards.push(("SJ_SDX".into(), f(sx)));
            cards.push(("SJ_SDY".into(), f(sy)));
        }
        if let Some(sr) = m.sigma_chained_rotation_arcsec {
            cards.push(("SJ_SROT".into(), f(sr)));
        }
        if let Some(p) = chain.plate_scale_arcsec {
            cards.push(("SJ_PLATX".into(), f(p[0].abs())));
            cards.push(("SJ_PLATY".into(), f(p[1].abs())));
        }
        cards
    }
}

/// `name` without its FITS extension (case-insensitive; kept when nothing would be left).
fn without_fits_extension(name: &str) -> &str {
    const EXTENSIONS: [&str; 7] = [
        ".fits.fz", ".fits.gz", ".fit.gz", ".fts.gz", ".fits", ".fit", ".fts",
    ];
    let base_start = name.rfind('/').map_or(0, |i| i + 1);
    for ext in EXTENSIONS {
        let cut = name.len().saturating_sub(ext.len());
        if cut > base_start && name.is_char_boundary(cut) && name[cut..].eq_ignore_ascii_case(ext) {
            return &name[..cut];
        }
    }
    name
}

fn is_identity(t: &Similarity) -> bool {
    t.scale == 1.0 && t.rotation_rad == 0.0 && t.dx == 0.0 && t.dy == 0.0
}

fn status_text(m: &FrameAlignment) -> String {
    m.align.status.as_str().to_string()
}

/// `HISTORY` lines: what was applied, from which measurement. Short lines (one card each).
fn history(mode: Mode, m: &FrameAlignment, t: &Similarity) -> Vec<String> {
    let what = match mode {
        Mode::Resampled => "frame resampled onto its chain origin's grid (quintic B-spline)",
        Mode::WcsOnly => "pointing corrected; pixel values as read",
    };
    let sig = |v: Option<f64>| v.map_or("?".to_string(), |v| format!("{v:.3e}"));
    let mut lines = vec![
        format!("sunjitter {}: {what}", env!("CARGO_PKG_VERSION")),
        format!(
            "channel {}, sequence {}, reference_kind {}",
            m.channel, m.sequence, m.reference_kind
        ),
        format!("reference: {}", m.align.reference),
        format!("status {}", status_text(m)),
    ];
    if m.align.status != Status::Ok && !m.align.message.is_empty() {
        lines.push(format!(
            "({})",
            sunjitter_core::text::escape(&m.align.message)
        ));
    }
    lines.extend([
        "chained transform, chain origin grid to this frame (0-based px):".to_string(),
        format!(
            "p_frame = s R(theta) (p_origin - c) + c + (dx, dy), c = ({}, {})",
            t.center[0], t.center[1]
        ),
        format!(
            "scale = {:.9}, rotation = {:.6} arcsec",
            t.scale,
            t.rotation_arcsec()
        ),
        format!("dx = {:.6} px, dy = {:.6} px", t.dx, t.dy),
        format!(
            "sigma: dx {} px, dy {} px",
            sig(m.sigma_chained_dx_px),
            sig(m.sigma_chained_dy_px)
        ),
    ]);
    lines.push(match mode {
        Mode::Resampled => "WCS = the chain origin's".to_string(),
        Mode::WcsOnly => "WCS = the chain origin's through the inverse transform:".to_string(),
    });
    if mode == Mode::WcsOnly {
        lines.push("CRPIXi moved, CDELTi and PCi_j (or CDi_j) turned and scaled".to_string());
    }
    lines
}

// ---------------------------------------------------------------------------------------------
// Where products may go

/// Refuse (exit 2, one line) a product directory that the run would read from or that holds
/// its log: `dir` must not be inside (or be) a directory the run takes frames from
/// (`input_dirs`: the watched directory, replay's directory arguments and the directories of
/// its files), must not hold an input file, and must be apart from `out` (neither inside the
/// other).
pub fn check_dir(
    dir: &Path,
    out: &Path,
    input_dirs: &[PathBuf],
    input_files: &[PathBuf],
) -> Result<()> {
    let refuse = |reason: String| {
        Err(Error::Refused {
            path: dir.to_path_buf(),
            reason,
        })
    };
    if dir.exists() && !dir.is_dir() {
        return refuse("is not a directory".into());
    }
    let d = absolute(dir);
    for input in input_dirs {
        let input = absolute(input);
        if d.starts_with(&input) {
            return refuse(format!(
                "is inside {}, where frames are taken from: the run would take its own products; write them elsewhere",
                sunjitter_core::text::path(&input)
            ));
        }
        if input.starts_with(&d) {
            return refuse(format!(
                "holds {}, where frames are taken from; write the products elsewhere",
                sunjitter_core::text::path(&input)
            ));
        }
    }
    if let Some(f) = input_files.iter().find(|f| absolute(f).starts_with(&d)) {
        return refuse(format!(
            "holds the input {}; write the products elsewhere",
            sunjitter_core::text::path(f)
        ));
    }
    let o = absolute(out);
    let relation = if d == o {
        Some("is")
    } else if d.starts_with(&o) {
        Some("is inside")
    } else if o.starts_with(&d) {
        Some("holds")
    } else {
        None
    };
    if let Some(relation) = relation {
        return refuse(format!(
            "{relation} the log directory {} (--out); write the products elsewhere",
            sunjitter_core::text::path(out)
        ));
    }
    Ok(())
}

/// What `--aligned DIR [--wcs-only]` asks for, beside the log directory `--out`.
#[derive(Debug, Clone, Copy)]
pub struct Request<'a> {
    /// `--aligned`: where products go (`None`: no products).
    pub dir: Option<&'a Path>,
    /// `--wcs-only`: corrected headers on the frame's own pixels.
    pub wcs_only: bool,
    /// `--out`: the log directory, which products must stay out of.
    pub out: &'a Path,
}

/// The product writer `request` asks for, after [`check_dir`]; frames are named below `root`.
pub fn open(
    request: Request<'_>,
    input_dirs: &[PathBuf],
    input_files: &[PathBuf],
    root: &Path,
) -> Result<Option<Arc<Products>>> {
    let Some(dir) = request.dir else {
        return Ok(None);
    };
    check_dir(dir, request.out, input_dirs, input_files)?;
    Ok(Some(Arc::new(Products::new(dir, root, request.wcs_only)?)))
}

/// [`open`] for `replay PATH…` over `files` (as [`crate::ingest::expand_inputs`] gives them):
/// the directories given and those holding the files are input directories; names are below
/// the deepest directory holding every file. `protected` (references, the configuration) are
/// inputs too: the product directory must not hold them.
pub fn for_replay(
    request: Request<'_>,
    paths: &[String],
    files: &[(PathBuf, bool)],
    protected: &[PathBuf],
) -> Result<Option<Arc<Products>>> {
    let files: Vec<PathBuf> = files.iter().map(|(p, _)| p.clone()).collect();
    let mut dirs: Vec<PathBuf> = paths
        .iter()
        .map(PathBuf::from)
        .filter(|p| p.is_dir())
        .collect();
    dirs.extend(
        files
            .iter()
            .filter_map(|p| p.parent().map(Path::to_path_buf)),
    );
    let mut inputs = files.clone();
    inputs.extend(protected.iter().cloned());
    open(request, &dirs, &inputs, &common_root(&files))
}

/// The deepest directory holding every file (`/` at worst).
pub fn common_root(files: &[PathBuf]) -> PathBuf {
    let mut root: Option<PathBuf> = None;
    for f in files {
        let parent = f.parent().unwrap_or(Path::new("/")).to_path_buf();
        root = Some(match root {
            None => parent,
            Some(r) => {
                let mut r = r;
                while !parent.starts_with(&r) {
                    if !r.pop() {
                        break;
                    }
                }
                r
            }
        });
    }
    root.unwrap_or_else(|| PathBuf::from("/"))
}

/// `path` made absolute with symbolic links resolved as far as it exists (the rest appended).
fn absolute(path: &Path) -> PathBuf {
    let path = if path.is_absolute() {
        path.to_path_buf()
    } else {
        std::env::current_dir().unwrap_or_default().join(path)
    };
    let mut existing = path.as_path();
    let mut rest = Vec::new();
    loop {
        if let Ok(c) = existing.canonicalize() {
            let mut out = c;
            for part in rest.iter().rev() {
                out.push(part);
            }
            return out;
        }
        match (existing.parent(), existing.file_name()) {
            (Some(parent), Some(name)) => {
                rest.push(name.to_os_string());
                existing = parent;
            }
            _ => return path,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn names_mirror_the_tree_and_never_collide() {
        let dir = tempfile::tempdir().unwrap();
        let root = Path::new("/data/in");
        let p = Products::new(&dir.path().join("p"), root, true).unwrap();
        let a = p.path_for("/data/in/a/x.fits").unwrap();
        let b = p.path_for("/data/in/b/x.fits").unwrap();
        let c = p.path_for("/data/in/a/x.fits[3]").unwrap();
        assert!(a.ends_with("a/x.wcs.fits"), "{a:?}");
        assert!(b.ends_with("b/x.wcs.fits"), "{b:?}");
        assert!(c.ends_with("a/x[3].wcs.fits"), "{c:?}");
        assert_ne!(a, b);
        for (input, product) in [
            ("/data/in/y.FITS", "y.wcs.fits"),
            ("/data/in/y.fits.gz", "y.wcs.fits"),
            ("/data/in/y.fts", "y.wcs.fits"),
            ("/data/in/y.fits.fz[2]", "y[2].wcs.fits"),
            ("/data/in/y.dat", "y.dat.wcs.fits"),
            ("/data/in/.fits", ".fits.wcs.fits"),
            ("/data/in/d.fits/z", "d.fits/z.wcs.fits"),
        ] {
            let got = p.path_for(input).unwrap();
            assert_eq!(got, p.dir.join(product), "{input}");
        }
        assert!(p.path_for("/data/other/x.fits").is_none());
        assert!(p.path_for("/data/input/x.fits").is_none());
    }

    #[test]
    fn the_deepest_common_directory_is_the_root() {
        let files = [
            PathBuf::from("/a/b/c/x.fits"),
            PathBuf::from("/a/b/d/y.fits"),
            PathBuf::from("/a/b/c/z.fits"),
        ];
        assert_eq!(common_root(&files), PathBuf::from("/a/b"));
        assert_eq!(common_root(&files[..1]), PathBuf::from("/a/b/c"));
        assert_eq!(
            common_root(&[PathBuf::from("/a/x"), PathBuf::from("/b/y")]),
            PathBuf::from("/")
        );
    }

    #[test]
    fn a_directory_inside_the_input_tree_or_the_log_is_refused() {
        let t = tempfile::tempdir().unwrap();
        let watched = t.path().join("in");
        let out = t.path().join("out");
        std::fs::create_dir_all(&watched).unwrap();
        let inputs = [watched.clone()];
        for bad in [
            watched.clone(),
            watched.join("products"),
            t.path().to_path_buf(),
            out.clone(),
            out.join("p"),
        ] {
            let err = check_dir(&bad, &out, &inputs, &[]).unwrap_err();
            assert_eq!(
                err.exit_code(),
                sunjitter_core::error::ExitCode::BadInput,
                "{err}"
            );
            assert_eq!(err.to_string().lines().count(), 1, "{err}");
        }
        check_dir(&t.path().join("products"), &out, &inputs, &[]).unwrap();
        let file = t.path().join("products/x.fits");
        assert!(check_dir(&t.path().join("products"), &out, &[], &[file]).is_err());
    }
}
