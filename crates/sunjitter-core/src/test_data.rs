//! Test-only reading of the bundled real images (`data/real`, plain primary HDUs), through
//! fitsio for the pixels and this crate's own header parser for the metadata; and a seeded
//! source of test values.
use ndarray::Array2;

use crate::header::{Header, BLOCK};
use crate::meta::{self, ImagePlace};

pub fn real_path(name: &str) -> std::path::PathBuf {
    std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../../data/real")
        .join(name)
}

/// The primary image (first plane of a cube) as f32, shape (height, width).
pub fn read_real(name: &str) -> Array2<f32> {
    let mut f = fitsio::FitsFile::open(real_path(name)).expect("open bundled FITS");
    let hdu = f.primary_hdu().expect("primary HDU");
    let (h, w) = match &hdu.info {
        fitsio::hdu::HduInfo::ImageInfo { shape, .. } => {
            let n = shape.len();
            (shape[n - 2], shape[n - 1])
        }
        _ => panic!("not an image"),
    };
    let data: Vec<f32> = hdu.read_image(&mut f).expect("read image");
    Array2::from_shape_vec((h, w), data[..h * w].to_vec()).expect("shape")
}

/// The primary image with the metadata its header gives.
pub fn read_real_image(name: &str) -> (Array2<f32>, crate::meta::FrameMeta) {
    let path = real_path(name);
    let bytes = std::fs::read(&path).expect("read bundled FITS");
    let mut header = Header::new();
    let complete = bytes.chunks(BLOCK).any(|block| header.push_block(block));
    assert!(complete, "{name}: no END card");
    let data = read_real(name);
    let (height, width) = data.dim();
    let bitpix = header
        .get("BITPIX")
        .and_then(|v| v.as_i64())
        .expect("BITPIX") as i32;
    let place = ImagePlace {
        file: path,
        hdu: 0,
        frame: None,
        width,
        height,
        bitpix,
    };
    let meta = meta::from_header(&header, place).expect("bundled header");
    (data, meta)
}

/// Uniform values in [0, 1) from `seed`: a 64-bit linear congruential generator (Knuth's
/// MMIX constants), its top 53 bits. The same sequence on every machine.
pub fn uniform(seed: u64) -> impl FnMut() -> f64 {
    let mut state = seed;
    move || {
        state = state
            .wrapping_mul(6_364_136_223_846_793_005)
            .wrapping_add(1_442_695_040_888_963_407);
        (state >> 11) as f64 / (1u64 << 53) as f64
    }
}
