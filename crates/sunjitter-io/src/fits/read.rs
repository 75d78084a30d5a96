//! The reading entry points and the limits on what a file may claim.

use super::cube::FrameClock;
use super::gzip::PlainFile;
use super::layout::scan;
use super::options::{ReadLimits, ReadOptions};
use super::pixels::read_pixels;
use super::spec::FrameSpec;
use std::path::Path;
use sunjitter_core::engine::Image;
use sunjitter_core::header::{Header, ImageGeometry};
use sunjitter_core::meta::{self, FrameMeta};
use sunjitter_core::{Error, Result};

/// Read one image (or one frame of a cube) as f32, with its metadata.
pub fn read_frame(spec: &FrameSpec) -> Result<Image> {
    read_frame_with(spec, &ReadOptions::default())
}

/// [`read_frame`] with other limits on what the file may claim, or plate scales of its own.
pub fn read_frame_with(spec: &FrameSpec, options: &ReadOptions) -> Result<Image> {
    let plain = PlainFile::of(&spec.path, &options.limits)?;
    let mut image = plain.read(|path| {
        read_plain_frame(
            &FrameSpec {
                path: path.to_path_buf(),
                frame: spec.frame,
            },
            options,
        )
    })?;
    image.meta.file = spec.path.clone();
    Ok(image)
}

fn read_plain_frame(spec: &FrameSpec, options: &ReadOptions) -> Result<Image> {
    let path = spec.path.as_path();
    let mut layout = scan(path)?;
    layout.plate_scales = options.plate_scales.clone();
    let hdu = layout.image_hdu(path)?;
    let geometry = hdu.geometry();
    options.limits.check(path, geometry)?;
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
        &ReadOptions {
            limits: ReadLimits {
                max_frame_pixels: u64::MAX,
            },
            ..Default::default()
        },
    )
}

/// [`read_meta`] with other limits on what the file may claim, or plate scales of its own.
pub fn read_meta_with(path: &Path, options: &ReadOptions) -> Result<Vec<FrameMeta>> {
    let plain = PlainFile::of(path, &options.limits)?;
    let mut metas = plain.read(|plain| read_plain_meta(plain, options))?;
    metas.iter_mut().for_each(|m| m.file = path.to_path_buf());
    Ok(metas)
}

fn read_plain_meta(path: &Path, options: &ReadOptions) -> Result<Vec<FrameMeta>> {
    let mut layout = scan(path)?;
    layout.plate_scales = options.plate_scales.clone();
    let hdu = layout.image_hdu(path)?;
    let geometry = hdu.geometry();
    options.limits.check(path, geometry)?;
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

/// [`read_image_header`] of the file `meta` was read from, its plate scale the one `meta`
/// has (a plate scale the reading was given for the channel, see [`PlateScales`](super::PlateScales)), so that
/// cards copied from it describe the grid the frame was measured on.
pub fn read_image_header_as_read(meta: &FrameMeta) -> Result<(usize, Header)> {
    let (index, mut header) = read_image_header(&meta.file)?;
    let own = meta::CelestialWcs::from_header(&header).map(|w| w.plate_scale_arcsec());
    let used = meta.plate_scale_arcsec.map(f64::abs);
    if let Ok(own) = own {
        let differs = (0..2).any(|j| (own[j].abs() - used[j]).abs() > 1e-12 * used[j]);
        if differs {
            meta::set_plate_scale(&mut header, used)
                .map_err(|reason| Error::bad_header(&meta.file, reason))?;
        }
    }
    Ok((index, header))
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
