//! Plain and gzip-compressed files: a `.fits.gz` is read from a private decompressed copy.

use super::layout::{not_fits_reason, open, starts_like_a_header, MAX_HDUS, MAX_HEADER_BLOCKS};
use super::options::ReadLimits;
use std::fs::File;
use std::io::Read;
use std::path::{Path, PathBuf};
use sunjitter_core::header::{self, Header, BLOCK};
use sunjitter_core::{Error, Result};

/// Largest image a gzip-compressed file may expand to: beyond it, a decompression bomb or not
/// an observation (a 4096² × 64-frame f64 cube is 8 GiB).
const MAX_GUNZIPPED_BYTES: u64 = 16 << 30;

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
pub(super) struct PlainFile {
    original: PathBuf,
    copy: Option<tempfile::TempPath>,
}

impl PlainFile {
    pub(super) fn of(path: &Path, limits: &ReadLimits) -> Result<PlainFile> {
        let mut magic = [0u8; 2];
        let gzip = match crate::input::open_regular(path) {
            Ok(mut f) => f.read_exact(&mut magic).is_ok() && magic == [0x1f, 0x8b],
            Err(e) if sunjitter_core::error::transient_io(&e) => return Err(Error::io(path, e)),
            // Not a regular file (a FIFO would block the readers): said by `open`.
            Err(e) if e.kind() == std::io::ErrorKind::InvalidInput => {
                return Err(Error::bad_input(path, e.to_string()))
            }
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
    pub(super) fn read<T>(&self, reader: impl FnOnce(&Path) -> Result<T>) -> Result<T> {
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

#[cfg(test)]
mod tests {
    use super::*;

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
}
