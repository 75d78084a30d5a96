//! FITS ingestion: images and cube frames as `f32` arrays with their metadata, and f32 output.
//!
//! How a file is read:
//! 1. `scan` walks the HDU headers with sunjitter's own parser ([`sunjitter_core::header`]): this
//!    refuses non-FITS, truncated and absurdly sized files with a clear reason *before*
//!    anything large is allocated, and tolerates header quirks cfitsio rejects (NAXISn cards
//!    out of order, as in old IDL-written TRACE files).
//! 2. The image is the first HDU holding image data (primary, IMAGE extension, or a
//!    tile-compressed `ZIMAGE` table).
//! 3. Uncompressed pixels are decoded here (big-endian, `BSCALE`/`BZERO`, `BLANK` → NaN), reading
//!    only the requested frame. Tile-compressed pixels are decompressed by cfitsio, read with a
//!    NaN null value so blank pixels become NaN; files are opened as plain disk files so
//!    cfitsio's extended file-name syntax never applies to `[`, `]` or spaces in paths.
//! 4. Per-frame times of cubes come from the per-frame table (IRIS: HDU 1, column index in
//!    header key `TIME`, seconds after `STARTOBS`), else from the time axis, else the header.
//!    Per-frame pointing comes from the same table (`XCENIX`/`YCENIX`): one primary header
//!    describes the whole cube at its nominal pointing, while IRIS re-points between frames
//!    (it follows the Sun's rotation), so each frame's sun centre is moved by its own offset.

use ndarray::{Array2, ArrayView2};
use rayon::prelude::*;
use std::ffi::CString;
use std::fmt;
use std::fs::File;
use std::io::{Read, Seek, SeekFrom};
use std::path::{Path, PathBuf};
use std::sync::Mutex;
use sunjitter_core::engine::Image;
use sunjitter_core::header::{self, HduKind, Header, HeaderValue, ImageGeometry, BLOCK};
use sunjitter_core::meta::{self, FrameMeta, ImagePlace};
use sunjitter_core::{Error, Result};

/// Headers longer than this many blocks (28.8 MB) are treated as garbage without `END`.
const MAX_HEADER_BLOCKS: usize = 10_000;
/// More HDUs than this in one file is not an observation.
const MAX_HDUS: usize = 10_000;

/// One image to read: a file, and for a 3-D cube the frame index (`FILE.fits[N]`).
#[derive(Debug, Clone, PartialEq, Eq, Hash)]
pub struct FrameSpec {
    pub path: PathBuf,
    pub frame: Option<usize>,
}

impl FrameSpec {
    /// Parse a command-line argument: `FILE.fits[N]` for frame N of a cube, else a plain path.
    ///
    /// An argument naming an existing file is always a plain path, so file names that
    /// themselves contain `[…]` keep working.
    pub fn parse(arg: &str) -> FrameSpec {
        if !Path::new(arg).is_file() {
            if let Some((path, frame)) = split_frame_suffix(arg) {
                return FrameSpec {
                    path: PathBuf::from(path),
                    frame: Some(frame),
                };
            }
        }
        FrameSpec::file(arg)
    }

    /// A whole file (a 2-D image, or a cube of one frame).
    pub fn file(path: impl Into<PathBuf>) -> FrameSpec {
        FrameSpec {
            path: path.into(),
            frame: None,
        }
    }

    /// Frame `frame` of a cube.
    pub fn cube_frame(path: impl Into<PathBuf>, frame: usize) -> FrameSpec {
        FrameSpec {
            path: path.into(),
            frame: Some(frame),
        }
    }
}

impl fmt::Display for FrameSpec {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self.frame {
            Some(n) => write!(f, "{}[{n}]", sunjitter_core::text::path(&self.path)),
            None => write!(f, "{}", sunjitter_core::text::path(&self.path)),
        }
    }
}

/// The identity of a frame in logs: `PATH` for a 2-D image, `PATH[N]` for frame N of a cube.
pub fn frame_key(path: &std::path::Path, frame: Option<usize>) -> String {
    match frame {
        Some(n) => format!("{}[{n}]", sunjitter_core::text::path(path)),
        None => sunjitter_core::text::path(path).into_owned(),
    }
}

/// Inverse of [`frame_key`].
pub fn parse_frame_key(key: &str) -> FrameSpec {
    if let Some(stripped) = key.strip_suffix(']') {
        if let Some((path, n)) = stripped.rsplit_once('[') {
            if let Ok(n) = n.parse::<usize>() {
                return FrameSpec {
                    path: sunjitter_core::text::unescape_path(path),
                    frame: Some(n),
                };
            }
        }
    }
    FrameSpec {
        path: sunjitter_core::text::unescape_path(key),
        frame: None,
    }
}

/// `name[12]` → (`name`, 12).
fn split_frame_suffix(arg: &str) -> Option<(&str, usize)> {
    let inner = arg.strip_suffix(']')?;
    let open = inner.rfind('[')?;
    let (path, digits) = (&inner[..open], &inner[open + 1..]);
    if path.is_empty() || digits.is_empty() || !digits.bytes().all(|b| b.is_ascii_digit()) {
        return None;
    }
    Some((path, digits.parse().ok()?))
}

/// Read one image (or one frame of a cube) as f32, with its metadata.
pub fn read_frame(spec: &FrameSpec) -> Result<Image> {
    read_frame_with(spec, &ReadLimits::default())
}

/// [`read_frame`] with other limits on what the file may claim.
pub fn read_frame_with(spec: &FrameSpec, limits: &ReadLimits) -> Result<Image> {
    let plain = PlainFile::of(&spec.path, limits)?;
    let mut image = plain.read(|path| {
        read_plain_frame(
            &FrameSpec {
                path: path.to_path_buf(),
                frame: spec.frame,
            },
            limits,
        )
    })?;
    image.meta.file = spec.path.clone();
    Ok(image)
}

fn read_plain_frame(spec: &FrameSpec, limits: &ReadLimits) -> Result<Image> {
    let path = spec.path.as_path();
    let layout = scan(path)?;
    let hdu = layout.image_hdu(path)?;
    let geometry = hdu.geometry();
    limits.check(path, geometry)?;
    let frame = resolve_frame(path, geometry, spec.frame)?;
    let mut meta = layout.base_meta(path, hdu)?;
    meta.frame = frame;
    if let Some(i) = frame {
        let clock = FrameClock::of(&layout, hdu, path);
        clock.apply(&mut meta, &layout.merged_header(hdu), i, geometry.frames());
    }
    let data = read_pixels(path, hdu, frame.unwrap_or(0))?;
    Ok(Image { data, meta })
}

/// Metadata of every image (every frame of a cube) in a file.
pub fn read_meta(path: &Path) -> Result<Vec<FrameMeta>> {
    // No pixels are read: any size may be described.
    read_meta_with(
        path,
        &ReadLimits {
            max_frame_pixels: u64::MAX,
        },
    )
}

/// [`read_meta`] with other limits on what the file may claim.
pub fn read_meta_with(path: &Path, limits: &ReadLimits) -> Result<Vec<FrameMeta>> {
    let plain = PlainFile::of(path, limits)?;
    let mut metas = plain.read(|plain| read_plain_meta(plain, limits))?;
    metas.iter_mut().for_each(|m| m.file = path.to_path_buf());
    Ok(metas)
}

fn read_plain_meta(path: &Path, limits: &ReadLimits) -> Result<Vec<FrameMeta>> {
    let layout = scan(path)?;
    let hdu = layout.image_hdu(path)?;
    let geometry = hdu.geometry();
    limits.check(path, geometry)?;
    let base = layout.base_meta(path, hdu)?;
    if !geometry.is_cube() {
        return Ok(vec![base]);
    }
    let clock = FrameClock::of(&layout, hdu, path);
    clock.warn_if_resampled(path, geometry.frames());
    let header = layout.merged_header(hdu);
    Ok((0..geometry.frames())
        .map(|i| {
            let mut m = base.clone();
            m.frame = Some(i);
            clock.apply(&mut m, &header, i, geometry.frames());
            m
        })
        .collect())
}

/// The header of the HDU holding the image (with primary cards merged in when `INHERIT = T`),
/// and that HDU's index. For tools that copy a file's header (e.g. splitting a cube).
pub fn read_image_header(path: &Path) -> Result<(usize, Header)> {
    PlainFile::of(path, &ReadLimits::default())?.read(read_plain_image_header)
}

fn read_plain_image_header(path: &Path) -> Result<(usize, Header)> {
    let layout = scan(path)?;
    let hdu = layout.image_hdu(path)?;
    Ok((hdu.index, layout.merged_header(hdu)))
}

/// Which frame to read: none for a 2-D image, an index for a cube (a one-frame cube needs none).
fn resolve_frame(path: &Path, g: &ImageGeometry, asked: Option<usize>) -> Result<Option<usize>> {
    match (g.is_cube(), asked) {
        (false, None) | (false, Some(0)) => Ok(None),
        (false, Some(n)) => Err(Error::bad_input(
            path,
            format!("is a 2-D image; it has no frame {n}"),
        )),
        (true, None) if g.frames() == 1 => Ok(Some(0)),
        (true, None) => Err(Error::bad_input(
            path,
            format!("is a cube of {} frames: name one as FILE[N]", g.frames()),
        )),
        (true, Some(n)) if n < g.frames() => Ok(Some(n)),
        (true, Some(n)) => Err(Error::bad_input(
            path,
            format!(
                "frame {n} does not exist (the cube has frames 0 to {})",
                g.frames() - 1
            ),
        )),
    }
}

/// One HDU as found by [`scan`].
#[derive(Debug, Clone)]
struct Hdu {
    index: usize,
    header: Header,
    kind: HduKind,
    data_offset: u64,
    image: Option<ImageGeometry>,
}

impl Hdu {
    /// Only called on HDUs picked by [`Layout::image_hdu`], which have a geometry.
    fn geometry(&self) -> &ImageGeometry {
        static NONE: ImageGeometry = ImageGeometry {
            bitpix: 8,
            axes: Vec::new(),
            compressed: false,
        };
        self.image.as_ref().unwrap_or(&NONE)
    }
}

/// All HDUs of a file, headers parsed, data located.
#[derive(Debug, Clone)]
struct Layout {
    hdus: Vec<Hdu>,
}

impl Layout {
    /// The first HDU holding image data.
    fn image_hdu(&self, path: &Path) -> Result<&Hdu> {
        let hdu = self
            .hdus
            .iter()
            .find(|h| h.image.is_some())
            .ok_or_else(|| Error::bad_input(path, "no image data in any HDU"))?;
        if let Some(problem) = header::mandatory_order_problem(&hdu.header) {
            if !hdu.geometry().compressed {
                tracing::warn!(
                    "{}: {problem}; read with a tolerant header parser",
                    path.display()
                );
            }
        }
        Ok(hdu)
    }

    /// The HDU's header, plus primary cards it lacks when it says `INHERIT = T`.
    fn merged_header(&self, hdu: &Hdu) -> Header {
        let mut merged = hdu.header.clone();
        if hdu.index > 0 && hdu.header.bool("INHERIT") == Some(true) {
            for card in self.hdus[0].header.cards() {
                if let (Some(v), false) = (&card.value, merged.contains(&card.key)) {
                    merged.push(&card.key, v.clone());
                }
            }
        }
        merged
    }

    /// Metadata from the header alone (frame-independent).
    fn base_meta(&self, path: &Path, hdu: &Hdu) -> Result<FrameMeta> {
        let g = hdu.geometry();
        let place = ImagePlace {
            file: path.to_path_buf(),
            hdu: hdu.index,
            frame: None,
            width: g.width(),
            height: g.height(),
            bitpix: g.bitpix,
        };
        meta::from_header(&self.merged_header(hdu), place)
            .map_err(|reason| Error::bad_header(path, reason))
    }
}

/// The path as UTF-8 (cfitsio writes only text names).
fn utf8_path(path: &Path) -> Result<&str> {
    path.to_str()
        .ok_or_else(|| Error::bad_input(path, "the path is not valid UTF-8"))
}

/// The path's bytes for cfitsio, which takes any name the file system does.
fn c_path(path: &Path) -> Result<CString> {
    #[cfg(unix)]
    let bytes = std::os::unix::ffi::OsStrExt::as_bytes(path.as_os_str()).to_vec();
    #[cfg(not(unix))]
    let bytes = utf8_path(path)?.as_bytes().to_vec();
    CString::new(bytes).map_err(|_| Error::bad_input(path, "the path contains a NUL byte"))
}

/// Walk every HDU header, checking the file's structure and sizes without reading pixel data.
fn scan(path: &Path) -> Result<Layout> {
    let mut file = open(path)?;
    let file_len = file
        .metadata()
        .map_err(|e| read_failure(path, e, "cannot stat"))?
        .len();
    if file_len == 0 {
        return Err(Error::bad_input(path, "empty file (0 bytes)"));
    }
    let mut hdus = Vec::new();
    let mut offset = 0u64;
    while offset < file_len && hdus.len() < MAX_HDUS {
        let is_primary = hdus.is_empty();
        let Some((header, header_len)) =
            read_header(&mut file, path, offset, file_len, is_primary)?
        else {
            break;
        };
        let kind = match header::hdu_kind(&header, is_primary) {
            Ok(kind) => kind,
            Err(e) if is_primary => return Err(Error::bad_input(path, e)),
            Err(_) => {
                tracing::debug!(
                    "{}: ignoring {} bytes after the last HDU",
                    path.display(),
                    file_len - offset
                );
                break;
            }
        };
        let index = hdus.len();
        let context = |e: String| {
            Error::bad_input(
                path,
                if index == 0 {
                    e
                } else {
                    format!("HDU {index}: {e}")
                },
            )
        };
        let image = header::image_geometry(&header, &kind).map_err(context)?;
        let data_len = header::data_size_bytes(&header).map_err(context)?;
        let data_offset = offset + header_len;
        let available = file_len.saturating_sub(data_offset);
        if data_len > available {
            return Err(context(format!(
                "truncated: the header announces {data_len} bytes of data, the file holds {available}"
            )));
        }
        hdus.push(Hdu {
            index,
            header,
            kind,
            data_offset,
            image,
        });
        offset = data_offset + data_len.div_ceil(BLOCK as u64) * BLOCK as u64;
    }
    Ok(Layout { hdus })
}

/// Largest image a gzip-compressed file may expand to: beyond it, a decompression bomb or not
/// an observation (a 4096² × 64-frame f64 cube is 8 GiB).
const MAX_GUNZIPPED_BYTES: u64 = 16 << 30;

/// What a file may claim before its pixels are read: a header is free to announce any size,
/// and a sparse file occupies nothing on disk whatever length it reports.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ReadLimits {
    /// Pixels in one image (one frame of a cube).
    pub max_frame_pixels: u64,
}

/// Admits any frame of today's solar imagers (4096² and their cubes) with margin: 8192².
pub const DEFAULT_MAX_FRAME_PIXELS: u64 = 8192 * 8192;

impl Default for ReadLimits {
    fn default() -> Self {
        ReadLimits {
            max_frame_pixels: DEFAULT_MAX_FRAME_PIXELS,
        }
    }
}

impl ReadLimits {
    fn check(&self, path: &Path, g: &ImageGeometry) -> Result<()> {
        let pixels = g.width() as u64 * g.height() as u64;
        if pixels > self.max_frame_pixels {
            return Err(Error::bad_input(
                path,
                format!(
                    "the header announces {}×{} = {pixels} pixels per image, more than the limit of {} (`[daemon] max_frame_pixels`)",
                    g.width(),
                    g.height(),
                    self.max_frame_pixels
                ),
            ));
        }
        Ok(())
    }
}

/// Prefix of the decompressed copies of gzip-compressed inputs in the temporary directory.
const GUNZIPPED_PREFIX: &str = "sunjitter-gunzipped-";

/// Remove decompressed copies left in the temporary directory by a process that was killed
/// (a copy is otherwise removed as soon as its frame is read). Copies of live processes are
/// kept: each name carries its process id.
pub fn remove_stale_gunzipped_copies() {
    let Ok(entries) = std::fs::read_dir(std::env::temp_dir()) else {
        return;
    };
    for entry in entries.flatten() {
        let name = entry.file_name();
        let Some(rest) = name.to_str().and_then(|n| n.strip_prefix(GUNZIPPED_PREFIX)) else {
            continue;
        };
        let Some(pid) = rest.split('-').next().and_then(|p| p.parse::<u32>().ok()) else {
            continue;
        };
        let alive = pid == std::process::id() || Path::new(&format!("/proc/{pid}")).exists();
        // Only plain files this user owns: never follow a link planted under the prefix.
        let ours = entry.file_type().is_ok_and(|t| t.is_file());
        if !alive && ours {
            let _ = std::fs::remove_file(entry.path());
        }
    }
}

/// A file as the readers see it: the file itself, or for a gzip-compressed one (`.fits.gz`,
/// as archives ship them) a private decompressed copy in the temporary directory, created
/// exclusively under an unpredictable name and removed when this is dropped. Errors about the
/// copy name the original file.
struct PlainFile {
    original: PathBuf,
    copy: Option<tempfile::TempPath>,
}

impl PlainFile {
    fn of(path: &Path, limits: &ReadLimits) -> Result<PlainFile> {
        let mut magic = [0u8; 2];
        let gzip = match File::open(path) {
            Ok(mut f) => f.read_exact(&mut magic).is_ok() && magic == [0x1f, 0x8b],
            Err(e) if sunjitter_core::error::transient_io(&e) => return Err(Error::io(path, e)),
            Err(_) => false,
        };
        if !gzip {
            return Ok(PlainFile {
                original: path.to_path_buf(),
                copy: None,
            });
        }
        let source = open(path)?;
        let unwritable = |e: std::io::Error| {
            Error::bad_input(
                path,
                format!("gzip-compressed; cannot write its decompressed copy: {e}"),
            )
        };
        let (file, copy) = tempfile::Builder::new()
            .prefix(&format!("{GUNZIPPED_PREFIX}{}-", std::process::id()))
            .suffix(".fits")
            .tempfile()
            .map_err(unwritable)?
            .into_parts();
        let plain = PlainFile {
            original: path.to_path_buf(),
            copy: Some(copy),
        };
        let mut out = std::io::BufWriter::new(file);
        gunzip_checked(path, source, &mut out, limits)?;
        std::io::Write::flush(&mut out).map_err(unwritable)?;
        Ok(plain)
    }

    /// Run a reader on the plain file, naming the original in its errors.
    fn read<T>(&self, reader: impl FnOnce(&Path) -> Result<T>) -> Result<T> {
        let Some(copy) = &self.copy else {
            return reader(&self.original);
        };
        let copy: &Path = copy;
        reader(copy).map_err(|e| match e {
            Error::BadInput { path, reason } if path == copy => {
                Error::bad_input(&self.original, reason)
            }
            Error::BadHeader { path, reason } if path == copy => {
                Error::bad_header(&self.original, reason)
            }
            Error::Io { path, source } if path == copy => Error::io(&self.original, source),
            other => other,
        })
    }
}

/// Decompress `source` into `out` one HDU at a time: each header is read and checked (image
/// size against `limits`, the total against [`MAX_GUNZIPPED_BYTES`]) before the data it
/// announces is decompressed, and nothing after the last HDU is. What the headers do not
/// allow to be judged here (a missing `END`, a truncated HDU) is written as found, for the
/// plain reader to name.
fn gunzip_checked(
    path: &Path,
    source: File,
    out: &mut impl std::io::Write,
    limits: &ReadLimits,
) -> Result<()> {
    let corrupt = |e: std::io::Error| {
        if sunjitter_core::error::transient_io(&e) {
            return Error::io(path, e);
        }
        let what = if e.kind() == std::io::ErrorKind::UnexpectedEof {
            "truncated"
        } else {
            "cannot be decompressed"
        };
        Error::bad_input(path, format!("gzip-compressed, and {what}: {e}"))
    };
    let unwritable = |e: std::io::Error| {
        Error::bad_input(
            path,
            format!("gzip-compressed; cannot write its decompressed copy: {e}"),
        )
    };
    let mut decoder = flate2::read::MultiGzDecoder::new(std::io::BufReader::new(source));
    let mut block = vec![0u8; BLOCK];
    let mut written = 0u64;
    for index in 0..MAX_HDUS {
        let is_primary = index == 0;
        let mut header = Header::new();
        let mut complete = false;
        for blocks in 0..MAX_HEADER_BLOCKS {
            let n = read_up_to(&mut decoder, &mut block).map_err(corrupt)?;
            if n == 0 && !is_primary {
                return Ok(());
            }
            if blocks == 0 && !starts_like_a_header(&block[..n.max(1)], is_primary) {
                if is_primary {
                    return Err(Error::bad_input(
                        path,
                        format!("gzip-compressed, and {}", not_fits_reason(&block[..n])),
                    ));
                }
                // Whatever follows the last HDU is not needed.
                return Ok(());
            }
            out.write_all(&block[..n]).map_err(unwritable)?;
            written += n as u64;
            if n < BLOCK {
                return Ok(());
            }
            if header.push_block(&block) {
                complete = true;
                break;
            }
        }
        if !complete {
            return Ok(());
        }
        let Ok(kind) = header::hdu_kind(&header, is_primary) else {
            return Ok(());
        };
        if let Ok(Some(g)) = header::image_geometry(&header, &kind) {
            limits.check(path, &g)?;
        }
        let Ok(data_len) = header::data_size_bytes(&header) else {
            return Ok(());
        };
        let padded = data_len.div_ceil(BLOCK as u64) * BLOCK as u64;
        if written.saturating_add(padded) > MAX_GUNZIPPED_BYTES {
            return Err(Error::bad_input(
                path,
                format!(
                    "gzip-compressed, and its headers announce more than {} GiB of data",
                    MAX_GUNZIPPED_BYTES >> 30
                ),
            ));
        }
        let mut left = padded;
        while left > 0 {
            let want = left.min(BLOCK as u64) as usize;
            let n = read_up_to(&mut decoder, &mut block[..want]).map_err(corrupt)?;
            out.write_all(&block[..n]).map_err(unwritable)?;
            written += n as u64;
            left -= n as u64;
            if n < want {
                return Ok(());
            }
        }
    }
    Ok(())
}

/// Fill `buf` from `r` unless it ends first; the number of bytes read.
fn read_up_to(r: &mut impl Read, buf: &mut [u8]) -> std::io::Result<usize> {
    let mut n = 0;
    while n < buf.len() {
        match r.read(&mut buf[n..]) {
            Ok(0) => break,
            Ok(k) => n += k,
            Err(e) if e.kind() == std::io::ErrorKind::Interrupted => {}
            Err(e) => return Err(e),
        }
    }
    Ok(n)
}

/// A failed read: a transient one keeps its I/O error (so callers may retry), any other is
/// bad input, `what: error`.
fn read_failure(path: &Path, e: std::io::Error, what: &str) -> Error {
    if sunjitter_core::error::transient_io(&e) {
        Error::io(path, e)
    } else {
        Error::bad_input(path, format!("{what}: {e}"))
    }
}

/// Whether the reader refused a file only for ending early (a truncated header, data or
/// compressed stream, or no byte yet): what a file still being written looks like.
pub fn is_incomplete(e: &Error) -> bool {
    match e {
        Error::BadInput { reason, .. } => {
            reason.starts_with("empty file") || reason.contains("truncated")
        }
        _ => false,
    }
}

fn open(path: &Path) -> Result<File> {
    if path.is_dir() {
        return Err(Error::bad_input(path, "is a directory, not a FITS file"));
    }
    File::open(path).map_err(|e| {
        if sunjitter_core::error::transient_io(&e) {
            return Error::io(path, e);
        }
        let reason = match bad_frame_suffix(path) {
            Some(inner) if e.kind() == std::io::ErrorKind::NotFound => format!(
                "no such file, and '[{inner}]' is not a frame index (FILE[N] takes N = 0, 1, 2, …)"
            ),
            _ => format!("cannot open: {e}"),
        };
        Error::bad_input(path, reason)
    })
}

/// The text inside a trailing `[…]` that [`FrameSpec::parse`] did not take as a frame index.
fn bad_frame_suffix(path: &Path) -> Option<&str> {
    let name = path.file_name()?.to_str()?;
    let inner = name.strip_suffix(']')?;
    Some(&inner[inner.rfind('[')? + 1..])
}

/// Read one header starting at `offset`. `None` when an extension area holds no header
/// (trailing bytes that are not an HDU are ignored, as astropy does).
fn read_header(
    file: &mut File,
    path: &Path,
    offset: u64,
    file_len: u64,
    is_primary: bool,
) -> Result<Option<(Header, u64)>> {
    let io = |e: std::io::Error| read_failure(path, e, "read error");
    file.seek(SeekFrom::Start(offset)).map_err(io)?;
    let mut header = Header::new();
    let mut block = vec![0u8; BLOCK];
    for blocks in 1..=MAX_HEADER_BLOCKS {
        let remaining = file_len - offset - (blocks as u64 - 1) * BLOCK as u64;
        let n = (remaining.min(BLOCK as u64)) as usize;
        file.read_exact(&mut block[..n]).map_err(io)?;
        block[n..].fill(b' ');
        if blocks == 1 && !starts_like_a_header(&block[..n.max(1)], is_primary) {
            if is_primary {
                return Err(Error::bad_input(path, not_fits_reason(&block[..n])));
            }
            return Ok(None);
        }
        if header.push_block(&block) {
            return Ok(Some((header, blocks as u64 * BLOCK as u64)));
        }
        if n < BLOCK {
            let what = if is_primary {
                "header"
            } else {
                "extension header"
            };
            return Err(Error::bad_input(
                path,
                format!("truncated: the {what} ends without an END card"),
            ));
        }
    }
    Err(Error::bad_input(
        path,
        format!("no END card in the first {MAX_HEADER_BLOCKS} header blocks"),
    ))
}

fn starts_like_a_header(bytes: &[u8], is_primary: bool) -> bool {
    let key: &[u8] = if is_primary {
        b"SIMPLE  ="
    } else {
        b"XTENSION="
    };
    bytes.len() >= key.len() && &bytes[..key.len()] == key
}

/// `not a FITS file (it starts with '<!DOCTYPE HTML…', not 'SIMPLE =')`; compressed files
/// are named as such.
fn not_fits_reason(bytes: &[u8]) -> String {
    let compressions: [(&[u8], &str, &str); 4] = [
        (&[0x1f, 0x8b], "gzip", "gunzip"),
        (b"BZh", "bzip2", "bunzip2"),
        (&[0x28, 0xb5, 0x2f, 0xfd], "zstd", "unzstd"),
        (&[0xfd, b'7', b'z', b'X', b'Z', 0x00], "xz", "unxz"),
    ];
    if let Some((_, name, tool)) = compressions.iter().find(|(m, _, _)| bytes.starts_with(m)) {
        return format!(
            "a {name}-compressed file, not FITS; decompress it first ({tool}), or use FITS tile \
             compression (fpack), which is read directly"
        );
    }
    let start: String = bytes
        .iter()
        .take(24)
        .map(|&b| {
            if (b' '..=b'~').contains(&b) {
                b as char
            } else {
                '.'
            }
        })
        .collect();
    format!(
        "not a FITS file (it starts with '{}', not 'SIMPLE =')",
        start.trim_end()
    )
}

/// Pixel scaling of an uncompressed integer or float image.
#[derive(Debug, Clone, Copy)]
struct Scaling {
    scale: f64,
    zero: f64,
    /// `BLANK`, integer images only.
    blank: Option<i64>,
}

impl Scaling {
    fn of(header: &Header, bitpix: i32) -> Scaling {
        Scaling {
            scale: header.f64("BSCALE").unwrap_or(1.0),
            zero: header.f64("BZERO").unwrap_or(0.0),
            // BLANK means nothing for float data (NaN is the null there); AIA/HMI carry one anyway.
            blank: if bitpix > 0 {
                header.i64("BLANK")
            } else {
                None
            },
        }
    }
}

/// Read frame `frame` (0 for a 2-D image) of an image HDU.
fn read_pixels(path: &Path, hdu: &Hdu, frame: usize) -> Result<Array2<f32>> {
    let g = hdu.geometry();
    let values = if g.compressed {
        read_compressed(path, hdu.index, g, frame)?
    } else {
        read_uncompressed(path, hdu, frame)?
    };
    Array2::from_shape_vec((g.height(), g.width()), values)
        .map_err(|e| Error::bad_input(path, format!("image shape: {e}")))
}

/// Seek to the frame and decode exactly its bytes.
fn read_uncompressed(path: &Path, hdu: &Hdu, frame: usize) -> Result<Vec<f32>> {
    let g = hdu.geometry();
    let frame_bytes = (g.pixels_per_frame() * g.bytes_per_pixel()) as u64;
    let mut file = open(path)?;
    file.seek(SeekFrom::Start(
        hdu.data_offset + frame as u64 * frame_bytes,
    ))
    .map_err(|e| read_failure(path, e, "read error"))?;
    let mut bytes = vec![0u8; frame_bytes as usize];
    file.read_exact(&mut bytes)
        .map_err(|e| read_failure(path, e, "truncated while reading pixels"))?;
    // Decoded in parallel chunks: at 4096² this is tens of ms that would otherwise be serial.
    const CHUNK: usize = 1 << 16;
    let scaling = Scaling::of(&hdu.header, g.bitpix);
    let mut out = vec![0f32; g.pixels_per_frame()];
    out.par_chunks_mut(CHUNK)
        .zip(bytes.par_chunks(CHUNK * g.bytes_per_pixel()))
        .for_each(|(out, bytes)| {
            let mut slots = out.iter_mut();
            decode_samples(bytes, g.bitpix, scaling, |v| {
                if let Some(slot) = slots.next() {
                    *slot = v as f32;
                }
            });
        });
    Ok(out)
}

/// Decode big-endian FITS samples, applying `BZERO + BSCALE·raw`; `BLANK` and NaN give NaN.
fn decode_samples(bytes: &[u8], bitpix: i32, s: Scaling, mut emit: impl FnMut(f64)) {
    let int = |raw: i64| {
        if s.blank == Some(raw) {
            f64::NAN
        } else {
            s.zero + s.scale * raw as f64
        }
    };
    let float = |raw: f64| s.zero + s.scale * raw;
    match bitpix {
        8 => bytes.iter().for_each(|&b| emit(int(i64::from(b)))),
        16 => {
            for c in bytes.chunks_exact(2) {
                emit(int(i64::from(i16::from_be_bytes([c[0], c[1]]))));
            }
        }
        32 => {
            for c in bytes.chunks_exact(4) {
                emit(int(i64::from(i32::from_be_bytes([c[0], c[1], c[2], c[3]]))));
            }
        }
        64 => {
            for c in bytes.chunks_exact(8) {
                emit(int(i64::from_be_bytes(eight(c))));
            }
        }
        -32 => {
            for c in bytes.chunks_exact(4) {
                emit(float(f64::from(f32::from_be_bytes([
                    c[0], c[1], c[2], c[3],
                ]))));
            }
        }
        _ => {
            for c in bytes.chunks_exact(8) {
                emit(float(f64::from_be_bytes(eight(c))));
            }
        }
    }
}

/// The first eight bytes of a chunk of eight.
fn eight(c: &[u8]) -> [u8; 8] {
    let mut a = [0u8; 8];
    a.copy_from_slice(&c[..8]);
    a
}

/// cfitsio is not guaranteed re-entrant as bundled: one call at a time.
static CFITSIO: Mutex<()> = Mutex::new(());

/// cfitsio's text for a status code.
fn cfitsio_error(status: i32) -> String {
    let mut buf = [0 as std::os::raw::c_char; 32];
    // SAFETY: ffgerr writes at most 31 characters plus NUL into a 31+ byte buffer.
    unsafe { fitsio::sys::ffgerr(status, buf.as_mut_ptr()) };
    let bytes: Vec<u8> = buf
        .iter()
        .take_while(|&&c| c != 0)
        .map(|&c| c as u8)
        .collect();
    format!(
        "cfitsio: {} (status {status})",
        String::from_utf8_lossy(&bytes)
    )
}

/// Decompress one frame of a tile-compressed image with cfitsio, blanks as NaN.
fn read_compressed(
    path: &Path,
    hdu_index: usize,
    g: &ImageGeometry,
    frame: usize,
) -> Result<Vec<f32>> {
    let cpath = c_path(path)?;
    let n = g.pixels_per_frame();
    let mut out = vec![0f32; n];
    let _guard = CFITSIO
        .lock()
        .unwrap_or_else(|poisoned| poisoned.into_inner());
    let mut status = 0;
    let mut fptr: *mut fitsio::sys::fitsfile = std::ptr::null_mut();
    // SAFETY: plain cfitsio calls on a pointer it returned; `out` holds exactly `n` floats and
    // the file is closed on every path below.
    unsafe {
        // ffdkopn: a disk file, no extended file-name syntax.
        fitsio::sys::ffdkopn(&mut fptr, cpath.as_ptr(), 0, &mut status);
        if status == 0 {
            let mut hdu_type = 0;
            fitsio::sys::ffmahd(fptr, hdu_index as i32 + 1, &mut hdu_type, &mut status);
        }
        if status == 0 {
            let mut any_null = 0;
            let first = (frame * n + 1) as i64;
            fitsio::sys::ffgpve(
                fptr,
                1,
                first,
                n as i64,
                f32::NAN,
                out.as_mut_ptr(),
                &mut any_null,
                &mut status,
            );
        }
        let read_status = status;
        if !fptr.is_null() {
            let mut close_status = 0;
            fitsio::sys::ffclos(fptr, &mut close_status);
        }
        if read_status != 0 {
            return Err(Error::bad_input(
                path,
                format!("compressed image: {}", cfitsio_error(read_status)),
            ));
        }
    }
    Ok(out)
}

/// Per-frame times, exposures and pointings of a cube from its per-frame table.
///
/// The table is the only per-frame record an IRIS level-2 cube has: its primary header holds
/// one time, one exposure and one pointing (`XCEN`/`YCEN`, the WCS's `CRVAL`) for all frames.
#[derive(Debug, Clone, Default)]
struct FrameClock {
    /// Start time the table counts from (IRIS: `STARTOBS`).
    start_ns: Option<i64>,
    /// Seconds after `start_ns`, one per table row.
    seconds: Vec<f64>,
    /// Exposure per table row, when the table has one (`EXPTIMES`).
    exposures: Vec<f64>,
    /// Field-centre pointing per table row, helioprojective arcsec (`XCENIX`, `YCENIX`), when
    /// the table has both; `NaN` in rows of missing exposures (see [`pointing_columns`]).
    pointing: [Vec<f64>; 2],
}

impl FrameClock {
    /// Find an auxiliary array HDU whose header names a `TIME` column (IRIS level 2), and read
    /// its `TIME`, `EXPTIMES`, `XCENIX` and `YCENIX` columns (0-based indices in that header).
    fn of(layout: &Layout, image: &Hdu, path: &Path) -> FrameClock {
        let start_ns = meta::time_reference_ns(&layout.merged_header(image));
        for hdu in layout
            .hdus
            .iter()
            .filter(|h| h.index != image.index && h.kind == HduKind::Image)
        {
            let Some(table) = &hdu.image else { continue };
            let Some(col) = hdu.header.i64("TIME") else {
                continue;
            };
            let (ncols, nrows) = (table.width(), table.height());
            if col < 0 || col as usize >= ncols || table.axes.len() != 2 {
                continue;
            }
            let column = |key: &str| hdu.header.i64(key).and_then(|c| usize::try_from(c).ok());
            match read_table_columns(
                path,
                hdu,
                &[
                    Some(col as usize),
                    column("EXPTIMES"),
                    column("XCENIX"),
                    column("YCENIX"),
                ],
            ) {
                Ok(mut cols) => {
                    let y = cols.pop().unwrap_or_default();
                    let x = cols.pop().unwrap_or_default();
                    let exposures = cols.pop().unwrap_or_default();
                    let seconds = cols.pop().unwrap_or_default();
                    if seconds.len() == nrows {
                        return FrameClock {
                            start_ns,
                            seconds,
                            exposures,
                            pointing: pointing_columns(x, y, nrows),
                        };
                    }
                }
                Err(e) => tracing::warn!(
                    "{}: per-frame table in HDU {} unreadable: {e}",
                    path.display(),
                    hdu.index
                ),
            }
        }
        FrameClock::default()
    }

    fn has_table(&self) -> bool {
        self.start_ns.is_some() && !self.seconds.is_empty()
    }

    /// Say so when the table and the cube disagree in length (trimmed files).
    fn warn_if_resampled(&self, path: &Path, frames: usize) {
        if self.has_table() && self.seconds.len() != frames {
            tracing::warn!(
                "{}: per-frame table has {} rows for {frames} frames; frame times interpolated at row i·({}−1)/({frames}−1)",
                path.display(),
                self.seconds.len(),
                self.seconds.len()
            );
        }
    }

    /// Fill frame `i`'s time (table, else time axis, else the header's) and exposure, and
    /// move its sun centre to the frame's own pointing when the table gives one.
    fn apply(&self, meta: &mut FrameMeta, header: &Header, i: usize, frames: usize) {
        self.apply_pointing(meta, header, i, frames);
        if let (true, Some(start)) = (self.has_table(), self.start_ns) {
            let p = table_position(i, frames, self.seconds.len());
            meta.obs_time_ns = offset_time(start, interpolate(&self.seconds, p));
            if !self.exposures.is_empty() {
                meta.exptime_s = Some(interpolate(&self.exposures, p));
            }
            return;
        }
        if let (Some(t), Some(reference)) = (
            meta::time_axis_seconds(header, i),
            meta::time_reference_ns(header),
        ) {
            meta.obs_time_ns = offset_time(reference, t);
        }
    }

    /// Frame `i`'s sun centre at the frame's pointing (`XCENIX`/`YCENIX` at the frame's table
    /// position) rather than the header's nominal one: the header's WCS places the Sun for
    /// the nominal pointing only (see [`pointing_shift_px`]). Frames without a usable
    /// pointing keep the header's centre.
    fn apply_pointing(&self, meta: &mut FrameMeta, header: &Header, i: usize, frames: usize) {
        let [xs, ys] = &self.pointing;
        if xs.is_empty() || xs.len() != ys.len() {
            return;
        }
        let p = table_position(i, frames, xs.len());
        let at = [interpolate_rows(xs, p), interpolate_rows(ys, p)];
        if let Some([dx, dy]) = pointing_shift_px(header, at) {
            meta.sun_center_px[0] += dx;
            meta.sun_center_px[1] += dy;
        }
    }
}

/// The `XCENIX`/`YCENIX` columns as the pointing per table row, or empty columns when the
/// table lacks either. IRIS writes `XCENIX = YCENIX = 0` (with `EXPTIMES = 0`) in the rows of
/// exposures that are missing (rows 198–221 of the trimmed 1400 Å test cube): that is no
/// pointing at all, so those rows become `NaN` and frames read from them keep the header's.
fn pointing_columns(x: Vec<f64>, y: Vec<f64>, rows: usize) -> [Vec<f64>; 2] {
    if x.len() != rows || y.len() != rows {
        return [Vec::new(), Vec::new()];
    }
    let (x, y) = x
        .iter()
        .zip(&y)
        .map(|(&x, &y)| {
            if x == 0.0 && y == 0.0 {
                (f64::NAN, f64::NAN)
            } else {
                (x, y)
            }
        })
        .unzip();
    [x, y]
}

/// Pixel move of the sun centre for a frame pointed at `at` (helioprojective arcsec) when the
/// header's WCS describes the nominal pointing `XCEN`/`YCEN` (else `CRVAL1`/`CRVAL2` in arcsec).
///
/// A telescope pointed `d = at − nominal` further sees every sky point, the disk centre
/// included, `−M⁻¹·d` pixels from where the header puts it (`M`: the header's
/// arcsec-per-pixel matrix, world axis i × pixel axis j). This is the linear part of
/// moving `CRVAL` by `d`; for IRIS fields (≲ 30″ moves, ~10′ from disk centre) the projection
/// adds < 0.001 px (tools/iris_pointing_truth.py). `None` when the header gives no nominal
/// pointing, no usable WCS, or the values are not finite.
fn pointing_shift_px(header: &Header, at: [f64; 2]) -> Option<[f64; 2]> {
    let wcs = meta::CelestialWcs::from_header(header).ok()?;
    let nominal = match (header.f64("XCEN"), header.f64("YCEN")) {
        (Some(x), Some(y)) => [x, y],
        _ if header.contains("CRVAL1") && header.contains("CRVAL2") => wcs.crval_arcsec,
        _ => return None,
    };
    let d = [at[0] - nominal[0], at[1] - nominal[1]];
    let [[a, b], [c, e]] = wcs.matrix;
    let det = a * e - b * c;
    if !det.is_finite() || det.abs() < 1e-300 {
        return None;
    }
    let shift = [-(e * d[0] - b * d[1]) / det, -(a * d[1] - c * d[0]) / det];
    shift.iter().all(|v| v.is_finite()).then_some(shift)
}

/// `start` plus `seconds`, in ns; `None` when the sum is not a representable time (an absurd
/// table or time axis: the frame is then reported as having no observation time).
fn offset_time(start: i64, seconds: f64) -> Option<i64> {
    let ns = seconds * 1e9;
    if !ns.is_finite() || ns.abs() >= 9.0e18 {
        return None;
    }
    start.checked_add(ns.round() as i64)
}

/// Table row (fractional) of frame `i`. Equal lengths map one to one; a cube resampled along
/// time (the trimmed IRIS test files: 540 rows, 54 frames) spans the table end to end, which
/// is where each frame's slit position shows it was taken from (see tools/sunpy_truth.py).
fn table_position(i: usize, frames: usize, rows: usize) -> f64 {
    if rows == frames || frames <= 1 || rows <= 1 {
        return i.min(rows.saturating_sub(1)) as f64;
    }
    i as f64 * (rows - 1) as f64 / (frames - 1) as f64
}

/// Linear interpolation of `values` at fractional index `p` (clamped to the ends).
fn interpolate(values: &[f64], p: f64) -> f64 {
    let last = values.len() - 1;
    let p = p.clamp(0.0, last as f64);
    let lo = p.floor() as usize;
    let hi = (lo + 1).min(last);
    values[lo] + (values[hi] - values[lo]) * (p - lo as f64)
}

/// [`interpolate`], except that a row of zero weight plays no part: a frame read exactly at a
/// row is that row's value even when its neighbour is `NaN` (a missing exposure's pointing).
fn interpolate_rows(values: &[f64], p: f64) -> f64 {
    let p = p.clamp(0.0, (values.len() - 1) as f64);
    if p.fract() == 0.0 {
        return values[p as usize];
    }
    interpolate(values, p)
}

/// Read columns of a 2-D array HDU (NAXIS1 = columns, NAXIS2 = rows), as f64.
fn read_table_columns(path: &Path, hdu: &Hdu, columns: &[Option<usize>]) -> Result<Vec<Vec<f64>>> {
    let g = hdu.geometry();
    let bytes_len = g.pixels_per_frame() * g.bytes_per_pixel();
    let mut file = open(path)?;
    file.seek(SeekFrom::Start(hdu.data_offset))
        .map_err(|e| read_failure(path, e, "read error"))?;
    let mut bytes = vec![0u8; bytes_len];
    file.read_exact(&mut bytes)
        .map_err(|e| read_failure(path, e, "truncated table"))?;
    let mut all = Vec::with_capacity(g.pixels_per_frame());
    decode_samples(&bytes, g.bitpix, Scaling::of(&hdu.header, g.bitpix), |v| {
        all.push(v)
    });
    let ncols = g.width();
    Ok(columns
        .iter()
        .map(|c| match c {
            Some(c) if *c < ncols => all.chunks_exact(ncols).map(|row| row[*c]).collect(),
            _ => Vec::new(),
        })
        .collect())
}

/// Cards `write_image` sets itself (structure and scaling of the f32 array it writes).
const STRUCTURAL_KEYS: [&str; 11] = [
    "SIMPLE", "BITPIX", "NAXIS", "EXTEND", "BSCALE", "BZERO", "BLANK", "XTENSION", "PCOUNT",
    "GCOUNT", "END",
];

fn is_structural(key: &str) -> bool {
    STRUCTURAL_KEYS.contains(&key)
        || (key.starts_with("NAXIS") && key[5..].bytes().all(|b| b.is_ascii_digit()))
}

/// Write a 2-D f32 image (shape `(height, width)`) as a FITS primary HDU with header cards.
///
/// Structural cards in `cards` (`BITPIX`, `NAXISn`, `BSCALE`, …) are skipped: the file holds the
/// f32 values as given. Keys must be standard FITS keywords (≤ 8 characters). The file is
/// written under a temporary name and renamed into place, so a directory watcher never sees a
/// half-written file.
pub fn write_image(
    path: &Path,
    data: ArrayView2<f32>,
    cards: &[(String, HeaderValue)],
) -> Result<()> {
    let out_err = |reason: String| Error::output(path, reason);
    let file_name = path
        .file_name()
        .and_then(|n| n.to_str())
        .ok_or_else(|| out_err("not a UTF-8 file name".into()))?;
    let tmp = path.with_file_name(format!(".{file_name}.{}.tmp", std::process::id()));
    let ctmp = CString::new(utf8_path(&tmp).map_err(|_| out_err("not a UTF-8 path".into()))?)
        .map_err(|_| out_err("the path contains a NUL byte".into()))?;
    for (key, _) in cards {
        if key.is_empty()
            || key.len() > 8
            || !key
                .bytes()
                .all(|b| b.is_ascii_uppercase() || b.is_ascii_digit() || b == b'_' || b == b'-')
        {
            return Err(out_err(format!("{key:?} is not a FITS keyword")));
        }
    }
    let pixels: Vec<f32> = data.iter().copied().collect();
    let (height, width) = data.dim();
    let _ = std::fs::remove_file(&tmp);
    {
        let _guard = CFITSIO
            .lock()
            .unwrap_or_else(|poisoned| poisoned.into_inner());
        write_with_cfitsio(&ctmp, width, height, pixels, cards).map_err(out_err)?;
    }
    std::fs::rename(&tmp, path).map_err(|e| {
        let _ = std::fs::remove_file(&tmp);
        out_err(format!("cannot move the written file into place: {e}"))
    })
}

/// The cfitsio part of [`write_image`] (caller holds the lock).
fn write_with_cfitsio(
    cpath: &CString,
    width: usize,
    height: usize,
    mut pixels: Vec<f32>,
    cards: &[(String, HeaderValue)],
) -> std::result::Result<(), String> {
    use fitsio::sys;
    let mut status = 0;
    let mut fptr: *mut sys::fitsfile = std::ptr::null_mut();
    // SAFETY: cfitsio calls on the pointer it returned; strings are NUL-terminated CStrings that
    // outlive the calls; `pixels` holds width·height floats; the file is closed on every path.
    unsafe {
        sys::ffdkinit(&mut fptr, cpath.as_ptr(), &mut status);
        if status != 0 {
            return Err(cfitsio_error(status));
        }
        let mut naxes = [
            width as std::os::raw::c_long,
            height as std::os::raw::c_long,
        ];
        sys::ffcrim(fptr, -32, 2, naxes.as_mut_ptr(), &mut status);
        for (key, value) in cards.iter().filter(|(k, _)| !is_structural(k)) {
            if status != 0 {
                break;
            }
            let ckey = CString::new(key.as_str()).unwrap_or_default();
            let empty = CString::default();
            match value {
                HeaderValue::Bool(b) => sys::ffpkyl(
                    fptr,
                    ckey.as_ptr(),
                    i32::from(*b),
                    empty.as_ptr(),
                    &mut status,
                ),
                HeaderValue::Int(i) => {
                    sys::ffpkyj(fptr, ckey.as_ptr(), *i, empty.as_ptr(), &mut status)
                }
                // G format, 15 significant digits.
                HeaderValue::Float(f) if f.is_finite() => {
                    sys::ffpkyd(fptr, ckey.as_ptr(), *f, -15, empty.as_ptr(), &mut status)
                }
                HeaderValue::Float(_) => 0,
                // Commentary cards: no value indicator (cfitsio splits long text over cards).
                HeaderValue::Str(s) if key == "HISTORY" || key == "COMMENT" => {
                    let printable: String = s
                        .chars()
                        .map(|c| if (' '..='~').contains(&c) { c } else { '?' })
                        .collect();
                    let text = CString::new(printable).unwrap_or_default();
                    if key == "HISTORY" {
                        sys::ffphis(fptr, text.as_ptr(), &mut status)
                    } else {
                        sys::ffpcom(fptr, text.as_ptr(), &mut status)
                    }
                }
                HeaderValue::Str(s) => {
                    let printable: String = s
                        .chars()
                        .map(|c| if (' '..='~').contains(&c) { c } else { '?' })
                        .collect();
                    let cval = CString::new(printable).unwrap_or_default();
                    sys::ffpkls(
                        fptr,
                        ckey.as_ptr(),
                        cval.as_ptr(),
                        empty.as_ptr(),
                        &mut status,
                    )
                }
            };
        }
        if status == 0 {
            sys::ffppre(
                fptr,
                1,
                1,
                pixels.len() as i64,
                pixels.as_mut_ptr(),
                &mut status,
            );
        }
        let write_status = status;
        let mut close_status = 0;
        sys::ffclos(fptr, &mut close_status);
        match (write_status, close_status) {
            (0, 0) => Ok(()),
            (0, s) | (s, _) => Err(cfitsio_error(s)),
        }
    }
}

/// Header cards for frame `meta` of a cube written as a 2-D image: the cube's cards minus
/// structure, the third (time) axis and per-cube time keys, plus the frame's own `DATE-OBS`
/// (UTC), `EXPTIME`, and where it came from (`SRCFILE`, `SRCFRAME`). Keys that are not
/// standard 8-character keywords (HIERARCH) are dropped. A frame read at its own pointing
/// (per-frame table) gets `CRPIX1`/`CRPIX2` moved by its sun centre's move, and `XCEN`/`YCEN`
/// set to that pointing: the 2-D file has no table, so its header must carry the pointing.
pub fn frame_header_cards(cube_header: &Header, meta: &FrameMeta) -> Vec<(String, HeaderValue)> {
    let mut cards: Vec<(String, HeaderValue)> = cube_header
        .cards()
        .iter()
        .filter(|c| {
            is_standard_keyword(&c.key) && !is_structural(&c.key) && !is_per_cube_key(&c.key)
        })
        .filter_map(|c| Some((c.key.clone(), c.value.clone()?)))
        .collect();
    cards.retain(|(k, _)| {
        !matches!(
            k.as_str(),
            "DATE-OBS" | "EXPTIME" | "TIMESYS" | "SRCFILE" | "SRCFRAME"
        )
    });
    if let Some(t) = meta.obs_time_iso() {
        cards.push((
            "DATE-OBS".into(),
            HeaderValue::Str(t.trim_end_matches('Z').to_string()),
        ));
        cards.push(("TIMESYS".into(), HeaderValue::Str("UTC".into())));
    }
    if let Some(e) = meta.exptime_s {
        cards.push(("EXPTIME".into(), HeaderValue::Float(e)));
    }
    if let Some((crpix, offset)) = frame_pointing(cube_header, meta) {
        for (key, value) in cards.iter_mut() {
            let moved = match key.as_str() {
                "CRPIX1" => Some(crpix[0]),
                "CRPIX2" => Some(crpix[1]),
                "XCEN" => value.as_f64().map(|v| v + offset[0]),
                "YCEN" => value.as_f64().map(|v| v + offset[1]),
                _ => None,
            };
            if let Some(v) = moved {
                *value = HeaderValue::Float(v);
            }
        }
    }
    cards.push((
        "SRCFILE".into(),
        HeaderValue::Str(meta.file.display().to_string()),
    ));
    if let Some(f) = meta.frame {
        cards.push(("SRCFRAME".into(), HeaderValue::Int(f as i64)));
    }
    cards
}

/// For a cube frame whose sun centre the per-frame table moved ([`FrameClock::apply`]): the
/// frame's reference pixel (1-based `CRPIX1`, `CRPIX2`, moved with the sun centre, which is
/// exact whatever the projection) and its pointing offset from the header's, arcsec
/// (`d = −M·move`, the inverse of [`pointing_shift_px`]). `None` at the header's pointing.
fn frame_pointing(cube_header: &Header, meta: &FrameMeta) -> Option<([f64; 2], [f64; 2])> {
    meta.frame?;
    let wcs = meta::CelestialWcs::from_header(cube_header).ok()?;
    let nominal = wcs.sun_center_px().ok()?;
    let moved = [
        meta.sun_center_px[0] - nominal[0],
        meta.sun_center_px[1] - nominal[1],
    ];
    if moved == [0.0, 0.0] || !moved.iter().all(|v| v.is_finite()) {
        return None;
    }
    let m = wcs.matrix;
    let offset = [
        -(m[0][0] * moved[0] + m[0][1] * moved[1]),
        -(m[1][0] * moved[0] + m[1][1] * moved[1]),
    ];
    Some(([wcs.crpix[0] + moved[0], wcs.crpix[1] + moved[1]], offset))
}

/// 1–8 characters of `A–Z 0–9 _ -`.
fn is_standard_keyword(key: &str) -> bool {
    !key.is_empty()
        && key.len() <= 8
        && key
            .bytes()
            .all(|b| b.is_ascii_uppercase() || b.is_ascii_digit() || b == b'_' || b == b'-')
}

/// Keys that describe the cube as a whole and would mislead on a single frame: the third WCS
/// axis (`CTYPE3`, `PC3_1`, `PC1_3`…), and the times that outrank `DATE-OBS` (`T_OBS`, `DATE_OBS`).
fn is_per_cube_key(key: &str) -> bool {
    const AXIS_KEYS: [&str; 9] = [
        "CTYPE", "CUNIT", "CRPIX", "CRVAL", "CDELT", "CROTA", "CNAME", "CRDER", "CSYSER",
    ];
    let third_axis = AXIS_KEYS.iter().any(|p| {
        key.strip_prefix(p)
            .is_some_and(|n| n.parse::<u32>().is_ok_and(|n| n >= 3))
    });
    let matrix = ["PC", "CD"].iter().any(|p| {
        key.strip_prefix(p)
            .and_then(|ij| ij.split_once('_'))
            .is_some_and(|(i, j)| {
                i.parse::<u32>().is_ok_and(|i| i >= 3) || j.parse::<u32>().is_ok_and(|j| j >= 3)
            })
    });
    third_axis
        || matrix
        || matches!(
            key,
            "T_OBS" | "DATE_OBS" | "TIME-OBS" | "TIME_OBS" | "DATE_END" | "DATEREF" | "MJDREF"
        )
}

#[cfg(test)]
mod tests {
    use super::*;

    const REAL: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/../../data/real/");

    #[test]
    fn frame_spec_parsing() {
        assert_eq!(
            FrameSpec::parse("cube.fits[3]"),
            FrameSpec::cube_frame("cube.fits", 3)
        );
        assert_eq!(
            FrameSpec::parse("a b/c[1].fits"),
            FrameSpec::file("a b/c[1].fits")
        );
        assert_eq!(FrameSpec::parse("x.fits[]"), FrameSpec::file("x.fits[]"));
        assert_eq!(
            FrameSpec::parse("x.fits[-1]"),
            FrameSpec::file("x.fits[-1]")
        );
        assert_eq!(FrameSpec::parse("[2]"), FrameSpec::file("[2]"));
        assert_eq!(FrameSpec::cube_frame("c.fits", 7).to_string(), "c.fits[7]");
        // An existing file whose name ends in [N] is a plain path.
        let dir = tempfile::tempdir().unwrap();
        let odd = dir.path().join("frame[2]");
        std::fs::write(&odd, b"x").unwrap();
        assert_eq!(
            FrameSpec::parse(odd.to_str().unwrap()),
            FrameSpec::file(&odd)
        );
    }

    /// Absurd table/time-axis times that overflow the ns count.
    #[test]
    fn offset_times_that_do_not_fit_are_none() {
        assert_eq!(offset_time(1_000, 2.5), Some(2_500_001_000));
        assert_eq!(offset_time(i64::MAX - 10, 1.0), None);
        assert_eq!(offset_time(0, f64::NAN), None);
        assert_eq!(offset_time(0, 1e300), None);
    }

    #[test]
    fn table_positions_span_the_table() {
        assert_eq!(table_position(5, 10, 10), 5.0);
        assert_eq!(table_position(0, 54, 540), 0.0);
        assert_eq!(table_position(53, 54, 540), 539.0);
        assert!((table_position(1, 54, 540) - 539.0 / 53.0).abs() < 1e-12);
        assert_eq!(interpolate(&[0.0, 10.0, 20.0], 1.5), 15.0);
        assert_eq!(interpolate(&[0.0, 10.0], 7.0), 10.0);
    }

    /// The pointing move is −M⁻¹·d. With a 90° roll, M = [[0, −2], [2, 0]] arcsec/px, a frame
    /// pointed 4″ west and 2″ north of XCEN/YCEN sees the disk centre 1 px left, 2 px up.
    #[test]
    fn pointing_moves_the_centre_and_fill_rows_are_no_pointing() {
        let header = |cards: &[(&str, &str)]| {
            let text: String = cards
                .iter()
                .map(|(k, v)| format!("{:<80}", format!("{k:<8}= {v:>20}")))
                .collect();
            Header::parse(text.as_bytes())
        };
        let mut cards = vec![
            ("CRPIX1", "1.0"),
            ("CRPIX2", "1.0"),
            ("CDELT1", "2.0"),
            ("CDELT2", "2.0"),
            ("PC1_1", "0.0"),
            ("PC1_2", "-1.0"),
            ("PC2_1", "1.0"),
            ("PC2_2", "0.0"),
            ("CRVAL1", "100.0"),
            ("CRVAL2", "50.0"),
        ];
        // CRVAL stands in for a missing XCEN/YCEN.
        assert_eq!(
            pointing_shift_px(&header(&cards), [104.0, 52.0]),
            Some([-1.0, 2.0])
        );
        cards.extend([("XCEN", "90.0"), ("YCEN", "40.0")]);
        assert_eq!(
            pointing_shift_px(&header(&cards), [94.0, 42.0]),
            Some([-1.0, 2.0])
        );
        assert_eq!(pointing_shift_px(&header(&cards), [f64::NAN, 42.0]), None);
        let no_nominal: Vec<_> = cards
            .iter()
            .copied()
            .filter(|(k, _)| !matches!(*k, "XCEN" | "YCEN" | "CRVAL1" | "CRVAL2"))
            .collect();
        assert_eq!(pointing_shift_px(&header(&no_nominal), [94.0, 42.0]), None);

        let [x, y] = pointing_columns(vec![1.0, 0.0, 0.0], vec![2.0, 0.0, 5.0], 3);
        assert_eq!((x[0], y[0]), (1.0, 2.0));
        assert!(x[1].is_nan() && y[1].is_nan());
        assert_eq!((x[2], y[2]), (0.0, 5.0));
        assert!(pointing_columns(vec![1.0], Vec::new(), 1)[0].is_empty());
        assert_eq!(interpolate_rows(&x, 0.0), 1.0);
        assert!(interpolate_rows(&x, 0.5).is_nan());
    }

    /// Pixel values against astropy (`fits.getdata`, which applies BZERO/BSCALE and BLANK):
    /// python3 -c "from astropy.io import fits; d=fits.getdata('data/real/trace_171_19980519T222143_1024.fits'); print(d[0,0], d[500,600], d[1023,1023], d.astype(float).sum())"
    /// → 85 344 93 153957404.0
    #[test]
    fn trace_int16_pixels_match_astropy() {
        let img = read_frame(&FrameSpec::file(format!(
            "{REAL}trace_171_19980519T222143_1024.fits"
        )))
        .unwrap();
        assert_eq!(img.data.dim(), (1024, 1024));
        assert_eq!(
            (
                img.data[[0, 0]],
                img.data[[500, 600]],
                img.data[[1023, 1023]]
            ),
            (85.0, 344.0, 93.0)
        );
        assert_eq!(
            img.data.iter().map(|&v| f64::from(v)).sum::<f64>(),
            153_957_404.0
        );
    }

    /// python3 -c "from astropy.io import fits; d=fits.getdata('data/real/iris_l2_20140329_140938_3860258481_SJI_1400_t000.fits'); print(d[7,50,60], d[53,60,40], d[53,108,109])"
    /// → 173.60815 22.341318 -200.0
    #[test]
    fn iris_cube_frame_pixels_match_astropy() {
        let path = format!("{REAL}iris_l2_20140329_140938_3860258481_SJI_1400_t000.fits");
        let img = read_frame(&FrameSpec::cube_frame(&path, 7)).unwrap();
        assert_eq!(img.data.dim(), (109, 110));
        assert_eq!(img.meta.frame, Some(7));
        let last = read_frame(&FrameSpec::cube_frame(&path, 53)).unwrap();
        assert_eq!(img.data[[50, 60]], 173.60815);
        assert_eq!(last.data[[60, 40]], 22.341318);
        assert_eq!(last.data[[108, 109]], -200.0);
        assert!(read_frame(&FrameSpec::cube_frame(&path, 54))
            .unwrap_err()
            .to_string()
            .contains("frames 0 to 53"));
        assert!(read_frame(&FrameSpec::file(&path))
            .unwrap_err()
            .to_string()
            .contains("54 frames"));
    }

    /// FITS standard §5.3: physical = BZERO + BSCALE·raw; raw == BLANK is undefined (NaN).
    #[test]
    fn integer_scaling_and_blank() {
        let s = Scaling {
            scale: 2.0,
            zero: 10.0,
            blank: Some(-1),
        };
        let mut out = Vec::new();
        decode_samples(&[0x00, 0x05, 0xFF, 0xFF, 0x80, 0x00], 16, s, |v| {
            out.push(v)
        });
        assert_eq!(out[0], 20.0);
        assert!(out[1].is_nan());
        assert_eq!(out[2], 10.0 + 2.0 * -32768.0);
        out.clear();
        // Unsigned 16-bit convention: BZERO = 32768.
        decode_samples(
            &[0x80, 0x00, 0x7F, 0xFF],
            16,
            Scaling {
                scale: 1.0,
                zero: 32768.0,
                blank: None,
            },
            |v| out.push(v),
        );
        assert_eq!(out, vec![0.0, 65535.0]);
    }

    /// A primary image from header cards and raw big-endian data (test fixture).
    fn fixture(dir: &tempfile::TempDir, name: &str, cards: &[String], data: &[u8]) -> PathBuf {
        let mut bytes: Vec<u8> = cards
            .iter()
            .map(String::as_str)
            .chain(["END"])
            .flat_map(|c| format!("{c:<80}").into_bytes())
            .collect();
        bytes.resize(bytes.len().div_ceil(BLOCK) * BLOCK, b' ');
        bytes.extend_from_slice(data);
        bytes.resize(bytes.len().div_ceil(BLOCK) * BLOCK, 0);
        let path = dir.path().join(name);
        std::fs::write(&path, bytes).unwrap();
        path
    }

    /// Every BITPIX end to end, with BSCALE/BZERO and BLANK (FITS standard §5.3:
    /// physical = BZERO + BSCALE·raw, raw = BLANK → undefined; float NaN stays NaN).
    #[test]
    fn every_bitpix_with_scaling_and_blank() {
        let dir = tempfile::tempdir().unwrap();
        let card = |k: &str, v: &str| format!("{k:<8}= {v:>20}");
        let raws: [i64; 4] = [-1, 0, 2, 7];
        for bitpix in [8i32, 16, 32, 64, -32, -64] {
            let mut data = Vec::new();
            for &r in &raws {
                match bitpix {
                    8 => data.push(r as u8),
                    16 => data.extend((r as i16).to_be_bytes()),
                    32 => data.extend((r as i32).to_be_bytes()),
                    64 => data.extend(r.to_be_bytes()),
                    -32 => data.extend((if r == -1 { f32::NAN } else { r as f32 }).to_be_bytes()),
                    _ => data.extend((if r == -1 { f64::NAN } else { r as f64 }).to_be_bytes()),
                }
            }
            let mut cards = vec![
                card("SIMPLE", "T"),
                card("BITPIX", &bitpix.to_string()),
                card("NAXIS", "2"),
                card("NAXIS1", "2"),
                card("NAXIS2", "2"),
                card("BSCALE", "0.5"),
                card("BZERO", "100.0"),
                card("CDELT1", "1.0"),
                card("CDELT2", "1.0"),
                card("CRPIX1", "1.0"),
                card("CRPIX2", "1.0"),
            ];
            // BLANK is the raw value −1 (255 for unsigned bytes); floats use NaN instead.
            if bitpix > 0 {
                cards.push(card("BLANK", if bitpix == 8 { "255" } else { "-1" }));
            }
            let path = fixture(&dir, &format!("b{bitpix}.fits"), &cards, &data);
            let img = read_frame(&FrameSpec::file(&path)).unwrap();
            assert!(img.data[[0, 0]].is_nan(), "BITPIX {bitpix}");
            assert_eq!(
                (img.data[[0, 1]], img.data[[1, 0]], img.data[[1, 1]]),
                (100.0, 101.0, 103.5),
                "BITPIX {bitpix}"
            );
            assert_eq!(img.meta.bitpix, bitpix);
        }
    }

    /// astropy: `(fits.getdata(out_of_order) == fits.getdata(reordered)).all()` is True.
    #[test]
    fn out_of_order_idl_file_has_the_same_pixels() {
        let tolerant = read_frame(&FrameSpec::file(concat!(
            env!("CARGO_MANIFEST_DIR"),
            "/../../data/malformed/trace_171_naxis_cards_out_of_order.fits"
        )))
        .unwrap();
        let reordered = read_frame(&FrameSpec::file(format!(
            "{REAL}trace_171_19980519T222143_1024.fits"
        )))
        .unwrap();
        assert_eq!(tolerant.data, reordered.data);
        assert_eq!(tolerant.meta.sun_center_px, reordered.meta.sun_center_px);
    }

    /// A Rice tile-compressed copy written by cfitsio (`[compress R]`) reads back identical.
    #[test]
    fn rice_compressed_copy_reads_back_identical() {
        let source = format!("{REAL}trace_171_19980519T222143_1024.fits");
        let original = read_frame(&FrameSpec::file(&source)).unwrap();
        let dir = tempfile::tempdir().unwrap();
        let packed = dir.path().join("rice.fits");
        write_rice_i16(&packed, &original.data);
        // cfitsio reads it as a plain disk file even when the name has brackets and spaces.
        let packed_odd = dir.path().join("rice [compress R] 1.fits");
        std::fs::rename(&packed, &packed_odd).unwrap();
        let packed = packed_odd;
        let layout = scan(&packed).unwrap();
        let hdu = layout.image_hdu(&packed).unwrap();
        assert!(
            hdu.geometry().compressed
                && hdu.index == 1
                && hdu.header.str("ZCMPTYPE") == Some("RICE_1")
        );
        let round = read_frame(&FrameSpec::file(&packed)).unwrap();
        assert_eq!(round.data, original.data);
        assert_eq!(round.meta.bitpix, 16);
        assert!(
            std::fs::metadata(&packed).unwrap().len() < std::fs::metadata(&source).unwrap().len()
        );
    }

    /// Write `data` (integral values) as a Rice-compressed int16 image via cfitsio's
    /// extended file-name syntax, with the TRACE WCS cards needed for metadata.
    fn write_rice_i16(path: &Path, data: &Array2<f32>) {
        use fitsio::images::{ImageDescription, ImageType};
        let spec = format!("{}[compress R]", path.display());
        let values: Vec<i16> = data.iter().map(|&v| v as i16).collect();
        let _guard = CFITSIO.lock().unwrap_or_else(|p| p.into_inner());
        let mut f = fitsio::FitsFile::create(&spec).open().unwrap();
        let desc = ImageDescription {
            data_type: ImageType::Short,
            dimensions: &[data.nrows(), data.ncols()],
        };
        let hdu = f.create_image("RICE", &desc).unwrap();
        for (k, v) in [
            ("CDELT1", 0.5),
            ("CDELT2", 0.5),
            ("CRPIX1", -331.555),
            ("CRPIX2", -289.793),
            ("CRVAL1", 0.0),
            ("CRVAL2", 0.0),
        ] {
            hdu.write_key(&mut f, k, v).unwrap();
        }
        hdu.write_image(&mut f, &values).unwrap();
    }

    /// A cube frame written as a 2-D file with `frame_header_cards` reads back with the same
    /// metadata as the frame had in the cube (truth: the cube's values, checked against sunpy
    /// in tests/info.rs).
    #[test]
    fn cube_frame_round_trips_through_a_2d_file() {
        let cube = format!("{REAL}iris_l2_20140329_140938_3860258481_SJI_1400_t000.fits");
        let frame = read_frame(&FrameSpec::cube_frame(&cube, 27)).unwrap();
        let (_, header) = read_image_header(Path::new(&cube)).unwrap();
        let cards = frame_header_cards(&header, &frame.meta);
        assert!(!cards
            .iter()
            .any(|(k, _)| k == "CTYPE3" || k == "PC3_1" || k == "NAXIS3" || k == "DATE_OBS"));
        let dir = tempfile::tempdir().unwrap();
        let out = dir.path().join("f27.fits");
        write_image(&out, frame.data.view(), &cards).unwrap();
        let back = read_frame(&FrameSpec::file(&out)).unwrap();
        assert_eq!(back.data, frame.data);
        let m = &back.meta;
        assert_eq!((m.frame, m.bitpix, m.hdu), (None, -32, 0));
        assert_eq!(m.obs_time_iso(), frame.meta.obs_time_iso());
        assert_eq!(
            (m.channel.as_str(), m.instrument.as_deref(), m.wavelength),
            ("SJI_1400", Some("SJI"), Some(1400.0))
        );
        assert_eq!(m.plate_scale_arcsec, frame.meta.plate_scale_arcsec);
        for k in 0..2 {
            assert!((m.sun_center_px[k] - frame.meta.sun_center_px[k]).abs() < 1e-9);
        }
        assert!((m.rotation_deg - frame.meta.rotation_deg).abs() < 1e-12);
        assert!((m.exptime_s.unwrap() - frame.meta.exptime_s.unwrap()).abs() < 1e-12);
    }

    /// Only what the headers announce is decompressed (FITS standard: header blocks, then
    /// |BITPIX|/8 · ΠNAXISn bytes padded to 2880), not the 20 MB that follow in the stream.
    #[test]
    fn a_gzip_stream_is_decompressed_only_as_far_as_its_headers_announce() {
        use std::io::Write;
        let mut header: Vec<u8> = [
            "SIMPLE  =                    T",
            "BITPIX  =                  -32",
            "NAXIS   =                    2",
            "NAXIS1  =                  100",
            "NAXIS2  =                  100",
            "END",
        ]
        .iter()
        .flat_map(|c| format!("{c:<80}").into_bytes())
        .collect();
        header.resize(BLOCK, b' ');
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("bomb.fits.gz");
        let mut gz = flate2::write::GzEncoder::new(
            File::create(&path).unwrap(),
            flate2::Compression::fast(),
        );
        gz.write_all(&header).unwrap();
        gz.write_all(&vec![0u8; 20 << 20]).unwrap();
        gz.finish().unwrap();
        let mut out = Vec::new();
        gunzip_checked(
            &path,
            File::open(&path).unwrap(),
            &mut out,
            &ReadLimits::default(),
        )
        .unwrap();
        assert_eq!(
            out.len(),
            BLOCK + (100 * 100 * 4usize).div_ceil(BLOCK) * BLOCK
        );
    }

    #[test]
    fn write_image_round_trips_values_and_cards() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("out [1].fits");
        let data = Array2::from_shape_fn((3, 4), |(y, x)| {
            if (y, x) == (1, 2) {
                f32::NAN
            } else {
                (y * 10 + x) as f32 + 0.25
            }
        });
        let cards = vec![
            ("CDELT1".to_string(), HeaderValue::Float(0.6)),
            ("CDELT2".to_string(), HeaderValue::Float(0.6)),
            ("CRPIX1".to_string(), HeaderValue::Float(2.5)),
            ("CRPIX2".to_string(), HeaderValue::Float(2.0)),
            ("BITPIX".to_string(), HeaderValue::Int(16)),
            ("BZERO".to_string(), HeaderValue::Float(32768.0)),
            (
                "DATE-OBS".to_string(),
                HeaderValue::Str("2020-01-02T03:04:05.678".into()),
            ),
            ("INSTRUME".to_string(), HeaderValue::Str("SYNTH".into())),
            ("WAVELNTH".to_string(), HeaderValue::Int(171)),
        ];
        write_image(&path, data.view(), &cards).unwrap();
        let back = read_frame(&FrameSpec::parse(path.to_str().unwrap())).unwrap();
        assert_eq!(back.data.dim(), (3, 4));
        assert!(back.data[[1, 2]].is_nan());
        assert_eq!(back.data[[2, 3]], 23.25);
        assert_eq!(back.meta.bitpix, -32);
        assert_eq!(back.meta.channel, "SYNTH_171");
        assert_eq!(
            back.meta.obs_time_iso().unwrap(),
            "2020-01-02T03:04:05.678Z"
        );
        assert_eq!(back.meta.sun_center_px, [1.5, 1.0]);
        assert!(write_image(&path, data.view(), &[("lower".into(), HeaderValue::Int(1))]).is_err());
        // No temporary file left behind.
        assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 1);
    }
}
