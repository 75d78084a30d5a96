//! The HDU scan: headers parsed before anything large is allocated, and the image HDU.

use std::ffi::CString;
use std::fs::File;
use std::io::{Read, Seek, SeekFrom};
use std::path::Path;
use sunjitter_core::header::{self, HduKind, Header, ImageGeometry, BLOCK};
use sunjitter_core::meta::{self, FrameMeta, ImagePlace};
use sunjitter_core::{Error, Result};

/// Headers longer than this many blocks (28.8 MB) are treated as garbage without `END`.
pub(super) const MAX_HEADER_BLOCKS: usize = 10_000;
/// More HDUs than this in one file is not an observation.
pub(super) const MAX_HDUS: usize = 10_000;

/// One HDU as found by [`scan`].
#[derive(Debug, Clone)]
pub(super) struct Hdu {
    pub(super) index: usize,
    pub(super) header: Header,
    pub(super) kind: HduKind,
    pub(super) data_offset: u64,
    pub(super) image: Option<ImageGeometry>,
}

impl Hdu {
    /// Only called on HDUs picked by [`Layout::image_hdu`], which have a geometry.
    pub(super) fn geometry(&self) -> &ImageGeometry {
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
pub(super) struct Layout {
    pub(super) hdus: Vec<Hdu>,
    /// Plate scales given for channels, applied to the image's header where it is merged.
    pub(super) plate_scales: super::options::PlateScales,
}

impl Layout {
    /// The first HDU holding image data.
    pub(super) fn image_hdu(&self, path: &Path) -> Result<&Hdu> {
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
    pub(super) fn merged_header(&self, hdu: &Hdu) -> Header {
        let mut merged = hdu.header.clone();
        if hdu.index > 0 && hdu.header.bool("INHERIT") == Some(true) {
            for card in self.hdus[0].header.cards() {
                if let (Some(v), false) = (&card.value, merged.contains(&card.key)) {
                    merged.push(&card.key, v.clone());
                }
            }
        }
        self.plate_scales.apply(&mut merged);
        merged
    }

    /// Metadata from the header alone (frame-independent).
    pub(super) fn base_meta(&self, path: &Path, hdu: &Hdu) -> Result<FrameMeta> {
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
pub(super) fn utf8_path(path: &Path) -> Result<&str> {
    path.to_str()
        .ok_or_else(|| Error::bad_input(path, "the path is not valid UTF-8"))
}

/// The path's bytes for cfitsio, which takes any name the file system does.
pub(super) fn c_path(path: &Path) -> Result<CString> {
    #[cfg(unix)]
    let bytes = std::os::unix::ffi::OsStrExt::as_bytes(path.as_os_str()).to_vec();
    #[cfg(not(unix))]
    let bytes = utf8_path(path)?.as_bytes().to_vec();
    CString::new(bytes).map_err(|_| Error::bad_input(path, "the path contains a NUL byte"))
}

/// Walk every HDU header, checking the file's structure and sizes without reading pixel data.
pub(super) fn scan(path: &Path) -> Result<Layout> {
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
    Ok(Layout {
        hdus,
        plate_scales: Default::default(),
    })
}

/// A failed read: a transient one keeps its I/O error (so callers may retry), any other is
/// bad input, `what: error`.
pub(super) fn read_failure(path: &Path, e: std::io::Error, what: &str) -> Error {
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

pub(super) fn open(path: &Path) -> Result<File> {
    if path.is_dir() {
        return Err(Error::bad_input(path, "is a directory, not a FITS file"));
    }
    crate::input::open_regular(path).map_err(|e| {
        if sunjitter_core::error::transient_io(&e) {
            return Error::io(path, e);
        }
        let reason = match bad_frame_suffix(path) {
            _ if e.kind() == std::io::ErrorKind::InvalidInput => e.to_string(),
            Some(inner) if e.kind() == std::io::ErrorKind::NotFound => format!(
                "no such file, and '[{inner}]' is not a frame index (FILE[N] takes N = 0, 1, 2, …)"
            ),
            _ => format!("cannot open: {e}"),
        };
        Error::bad_input(path, reason)
    })
}

/// The text inside a trailing `[…]` that [`FrameSpec::parse`](super::FrameSpec::parse) did
/// not take as a frame index.
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

pub(super) fn starts_like_a_header(bytes: &[u8], is_primary: bool) -> bool {
    let key: &[u8] = if is_primary {
        b"SIMPLE  ="
    } else {
        b"XTENSION="
    };
    bytes.len() >= key.len() && &bytes[..key.len()] == key
}

/// `not a FITS file (it starts with '<!DOCTYPE HTML…', not 'SIMPLE =')`; compressed files
/// are named as such.
pub(super) fn not_fits_reason(bytes: &[u8]) -> String {
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
