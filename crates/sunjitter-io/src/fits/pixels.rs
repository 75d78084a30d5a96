//! Pixels: uncompressed ones decoded here, tile-compressed ones by cfitsio.

use super::layout::{c_path, open, read_failure, Hdu};
use ndarray::Array2;
use rayon::prelude::*;
use std::path::Path;
use std::sync::Mutex;
use sunjitter_core::header::{Header, ImageGeometry};
use sunjitter_core::{Error, Result};

/// Pixel scaling of an uncompressed integer or float image.
#[derive(Debug, Clone, Copy)]
pub(super) struct Scaling {
    scale: f64,
    zero: f64,
    /// `BLANK`, integer images only.
    blank: Option<i64>,
}

impl Scaling {
    pub(super) fn of(header: &Header, bitpix: i32) -> Scaling {
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
pub(super) fn read_pixels(path: &Path, hdu: &Hdu, frame: usize) -> Result<Array2<f32>> {
    let g = hdu.geometry();
    let values = if g.compressed {
        read_compressed(path, hdu.index, g, frame)?
    } else {
        read_uncompressed(path, hdu, frame)?
    };
    Array2::from_shape_vec((g.height(), g.width()), values)
        .map_err(|e| Error::bad_input(path, format!("image shape: {e}")))
}

/// Read the frame's bytes in chunks side by side, each decoded while it is in cache: no copy
/// of the whole frame's bytes is made, and the kernel's copying runs on every thread.
fn read_uncompressed(path: &Path, hdu: &Hdu, frame: usize) -> Result<Vec<f32>> {
    use std::os::unix::fs::FileExt;
    const CHUNK: usize = 1 << 16;
    let g = hdu.geometry();
    let bpp = g.bytes_per_pixel();
    let start = hdu.data_offset + (frame * g.pixels_per_frame() * bpp) as u64;
    let file = open(path)?;
    let scaling = Scaling::of(&hdu.header, g.bitpix);
    let n = g.pixels_per_frame();
    // Each chunk is cleared by the thread that decodes into it, just before: a buffer the
    // allocator hands back from an earlier frame would otherwise be cleared whole, serially.
    let mut out: Vec<f32> = Vec::with_capacity(n);
    out.spare_capacity_mut()[..n]
        .par_chunks_mut(CHUNK)
        .enumerate()
        .try_for_each_init(
            || vec![0u8; CHUNK * bpp],
            |bytes, (i, out)| {
                out.fill(std::mem::MaybeUninit::new(0.0));
                // SAFETY: every value of `out` was just initialised.
                let out = unsafe { &mut *(out as *mut [std::mem::MaybeUninit<f32>] as *mut [f32]) };
                let bytes = &mut bytes[..out.len() * bpp];
                file.read_exact_at(bytes, start + (i * CHUNK * bpp) as u64)
                    .map_err(|e| read_failure(path, e, "truncated while reading pixels"))?;
                decode_into(bytes, g.bitpix, scaling, out);
                Ok::<_, Error>(())
            },
        )?;
    // SAFETY: every chunk of the first `n` values was initialised (an error returned above).
    unsafe { out.set_len(n) };
    Ok(out)
}

/// [`decode_samples`] into `out`, as `f32`. The common layouts have loops of their own that
/// the compiler vectorises; they give the same values.
fn decode_into(bytes: &[u8], bitpix: i32, s: Scaling, out: &mut [f32]) {
    match bitpix {
        16 if s.blank.is_none() => {
            for (o, c) in out.iter_mut().zip(bytes.chunks_exact(2)) {
                let raw = f64::from(i16::from_be_bytes([c[0], c[1]]));
                *o = (s.zero + s.scale * raw) as f32;
            }
        }
        -32 => {
            for (o, c) in out.iter_mut().zip(bytes.chunks_exact(4)) {
                let raw = f64::from(f32::from_be_bytes([c[0], c[1], c[2], c[3]]));
                *o = (s.zero + s.scale * raw) as f32;
            }
        }
        _ => {
            let mut slots = out.iter_mut();
            decode_samples(bytes, bitpix, s, |v| {
                if let Some(slot) = slots.next() {
                    *slot = v as f32;
                }
            });
        }
    }
}

/// Decode big-endian FITS samples, applying `BZERO + BSCALE·raw`; `BLANK` and NaN give NaN.
pub(super) fn decode_samples(bytes: &[u8], bitpix: i32, s: Scaling, mut emit: impl FnMut(f64)) {
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
pub(super) static CFITSIO: Mutex<()> = Mutex::new(());

/// cfitsio's text for a status code.
pub(super) fn cfitsio_error(status: i32) -> String {
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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::fits::layout::scan;
    use crate::fits::{read_frame, FrameSpec};
    use std::path::PathBuf;
    use sunjitter_core::header::BLOCK;

    const REAL: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/../../data/real/");

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
            if bitpix > 0 {
                // Without BLANK, the raw −1 (255 for unsigned bytes) is a value like any other.
                let path = fixture(&dir, &format!("n{bitpix}.fits"), &cards, &data);
                let img = read_frame(&FrameSpec::file(&path)).unwrap();
                let first = if bitpix == 8 { 227.5 } else { 99.5 };
                assert_eq!(img.data[[0, 0]], first, "BITPIX {bitpix} without BLANK");
                // BLANK is the raw value −1 (255 for unsigned bytes); floats use NaN instead.
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

    /// Every pixel of an image larger than one read lands in its place (row-major, FITS
    /// standard §3.3.2), at physical = BZERO + BSCALE·raw, for the layouts most instruments
    /// write; the unsigned 16-bit convention (BZERO = 32768) among them.
    #[test]
    fn every_pixel_of_a_large_image_in_place() {
        let dir = tempfile::tempdir().unwrap();
        let card = |k: &str, v: &str| format!("{k:<8}= {v:>20}");
        let (w, h) = (301usize, 419usize);
        let raw = |i: usize| ((i * 7919) % 65536) as i64 - 32768;
        for (bitpix, zero) in [(16i32, "32768.0"), (16, "0.0"), (-32, "-3.0"), (32, "1.0")] {
            let mut data = Vec::new();
            for i in 0..w * h {
                match bitpix {
                    16 => data.extend((raw(i) as i16).to_be_bytes()),
                    32 => data.extend((raw(i) as i32 * 3).to_be_bytes()),
                    _ => data.extend((raw(i) as f32 * 0.25).to_be_bytes()),
                }
            }
            let cards = vec![
                card("SIMPLE", "T"),
                card("BITPIX", &bitpix.to_string()),
                card("NAXIS", "2"),
                card("NAXIS1", &w.to_string()),
                card("NAXIS2", &h.to_string()),
                card("BZERO", zero),
                card("CDELT1", "1.0"),
                card("CDELT2", "1.0"),
                card("CRPIX1", "1.0"),
                card("CRPIX2", "1.0"),
            ];
            let path = fixture(&dir, &format!("l{bitpix}_{zero}.fits"), &cards, &data);
            let img = read_frame(&FrameSpec::file(&path)).unwrap();
            let zero: f64 = zero.parse().unwrap();
            for (i, &v) in img.data.iter().enumerate() {
                let expected = match bitpix {
                    16 => zero + raw(i) as f64,
                    32 => zero + (raw(i) * 3) as f64,
                    _ => zero + raw(i) as f64 * 0.25,
                };
                assert_eq!(v, expected as f32, "BITPIX {bitpix}, pixel {i}");
            }
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
}
