//! `align`: one frame against one reference, from files (`FILE.fits`, `FILE.fits[N]`) or from
//! pixels held by numpy with their FITS header; and the products of a measurement.

use crate::errors::IntoPy;
use crate::wait::{self, OnInterrupt};
use ndarray::{Array2, ArrayView2};
use numpy::{IntoPyArray, PyArray2, PyArrayMethods, PyUntypedArrayMethods};
use pyo3::prelude::*;
use pyo3::types::{PyBytes, PyList, PyTuple};
use std::sync::Arc;
use sunjitter_core::engine::{self, AlignOutcome, Image};
use sunjitter_core::header::{Header, HeaderValue};
use sunjitter_core::meta::{self, FrameMeta, ImagePlace};
use sunjitter_core::{Error, Result};
use sunjitter_io::fits::{self, FrameSpec};

/// Pixels of a C-contiguous float32 numpy array, read where they lie. The array is kept alive
/// by the reference held here, so the pixels stay valid on another thread even after the
/// caller has gone on (a `KeyboardInterrupt` leaves the work to finish unseen).
struct Borrowed {
    _owner: Py<PyArray2<f32>>,
    ptr: *const f32,
    dim: (usize, usize),
}

// SAFETY: the pointer is only read, and the array it points into lives as long as `_owner`.
// A numpy array referenced elsewhere cannot be resized (numpy refuses while references exist).
unsafe impl Send for Borrowed {}

impl Borrowed {
    fn of(array: &Bound<'_, PyArray2<f32>>) -> PyResult<Borrowed> {
        if !array.is_c_contiguous() {
            return Err(pyo3::exceptions::PyValueError::new_err(
                "pixels must be C-contiguous (the Python layer makes them so)",
            ));
        }
        let dims = array.dims();
        Ok(Borrowed {
            _owner: array.clone().unbind(),
            ptr: array.data() as *const f32,
            dim: (dims[0], dims[1]),
        })
    }

    fn view(&self) -> ArrayView2<'_, f32> {
        // SAFETY: a C-contiguous array of `dim` f32 values at `ptr`, kept alive by `_owner`.
        unsafe { ArrayView2::from_shape_ptr(self.dim, self.ptr) }
    }
}

/// One side of a pair as given.
enum Source {
    Spec(String),
    Pixels {
        data: Borrowed,
        header: Vec<u8>,
        name: String,
    },
}

impl Source {
    fn from_py(value: &Bound<'_, PyAny>) -> PyResult<Source> {
        if let Ok(spec) = value.extract::<String>() {
            return Ok(Source::Spec(spec));
        }
        let tuple = value.cast::<PyTuple>()?;
        let (data, header, name): (Bound<'_, PyArray2<f32>>, Bound<'_, PyBytes>, String) =
            tuple.extract()?;
        Ok(Source::Pixels {
            data: Borrowed::of(&data)?,
            header: header.as_bytes().to_vec(),
            name,
        })
    }
}

/// A side of the pair ready for the engine: its header (as read: a cube's for a frame of
/// it), its metadata and its pixels.
struct Side {
    header: Header,
    meta: FrameMeta,
    pixels: Pixels,
}

enum Pixels {
    Owned(Array2<f32>),
    Borrowed(Borrowed),
}

impl Pixels {
    fn view(&self) -> ArrayView2<'_, f32> {
        match self {
            Pixels::Owned(a) => a.view(),
            Pixels::Borrowed(b) => b.view(),
        }
    }
}

impl Side {
    fn read(source: Source) -> Result<Side> {
        match source {
            Source::Spec(spec) => {
                let spec = FrameSpec::parse(&spec);
                let image = fits::read_frame(&spec)?;
                let (_, header) = fits::read_image_header(&spec.path)?;
                Ok(Side {
                    header,
                    meta: image.meta,
                    pixels: Pixels::Owned(image.data),
                })
            }
            Source::Pixels { data, header, name } => {
                let header = Header::parse(&header);
                let meta = meta_of(&header, data.dim, &name)?;
                Ok(Side {
                    header,
                    meta,
                    pixels: Pixels::Borrowed(data),
                })
            }
        }
    }
}

/// What the header says of an image of `dim` pixels (height, width) named `name`; the
/// header's own `NAXISn`, where it has them, must agree.
pub fn meta_of(header: &Header, dim: (usize, usize), name: &str) -> Result<FrameMeta> {
    let (height, width) = dim;
    for (key, n) in [("NAXIS1", width), ("NAXIS2", height)] {
        if let Some(v) = header.i64(key) {
            if v != n as i64 {
                return Err(Error::bad_header(
                    name,
                    format!(
                        "{key} = {v}, but the array is {width}×{height} px (NAXIS1 is the number of columns)"
                    ),
                ));
            }
        }
    }
    let place = ImagePlace {
        file: name.into(),
        hdu: 0,
        frame: None,
        width,
        height,
        bitpix: -32,
    };
    meta::from_header(header, place).map_err(|reason| Error::bad_header(name, reason))
}

/// A measurement, with what its products need of the pair.
#[pyclass(module = "sunjitter._sunjitter", frozen)]
pub struct Alignment {
    outcome: AlignOutcome,
    reference_header: Header,
    reference_meta: FrameMeta,
    reference_shape: (usize, usize),
    frame_meta: FrameMeta,
    frame_shape: (usize, usize),
}

#[pymethods]
impl Alignment {
    /// The record, as `sunjitter align --json` prints it (compact JSON).
    fn record_json(&self) -> PyResult<String> {
        serde_json::to_string(&self.outcome.result)
            .map_err(|e| pyo3::exceptions::PyValueError::new_err(e.to_string()))
    }

    /// (height, width) of the reference and of the frame.
    #[getter]
    fn shapes(&self) -> ((usize, usize), (usize, usize)) {
        (self.reference_shape, self.frame_shape)
    }

    /// The frame's pixels resampled onto the reference grid and the product's header cards,
    /// as `align --aligned` writes them; `frame_header` is the frame's header (FITS cards).
    fn registered<'py>(
        &self,
        py: Python<'py>,
        frame: &Bound<'py, PyArray2<f32>>,
        frame_header: &[u8],
        name: &str,
    ) -> PyResult<(Bound<'py, PyArray2<f32>>, Bound<'py, PyList>)> {
        let pixels = Borrowed::of(frame)?;
        let header = Header::parse(frame_header);
        let meta = self.frame_side(&header, pixels.dim, name).py_err()?;
        let reference = (
            &self.reference_header,
            &self.reference_meta,
            self.reference_shape,
        );
        let view = pixels.view();
        let (data, cards) = wait::detached(py, "register", || {
            sunjitter_io::aligned::aligned_product(reference, (&header, &meta, view), &self.outcome)
        })?
        .py_err()?;
        Ok((data.into_pyarray(py), cards_to_py(py, &cards)?))
    }

    /// The frame's header cards with its pointing corrected from the measurement (its pixels
    /// unchanged): `--wcs-only`'s product for this pair.
    fn corrected_pointing<'py>(
        &self,
        py: Python<'py>,
        frame_header: &[u8],
        shape: (usize, usize),
        name: &str,
    ) -> PyResult<Bound<'py, PyList>> {
        let header = Header::parse(frame_header);
        let meta = self.frame_side(&header, shape, name).py_err()?;
        let reference = (
            &self.reference_header,
            &self.reference_meta,
            self.reference_shape,
        );
        let cards = wait::detached(py, "correct_pointing", || {
            sunjitter_io::aligned::corrected_pointing_cards(
                reference,
                (&header, &meta, shape),
                &self.outcome,
            )
        })?
        .py_err()?;
        cards_to_py(py, &cards)
    }
}

impl Alignment {
    /// The frame's metadata from its header; it must be the frame that was measured.
    fn frame_side(&self, header: &Header, shape: (usize, usize), name: &str) -> Result<FrameMeta> {
        if shape != self.frame_shape {
            return Err(Error::bad_input(
                name,
                format!(
                    "is {}×{} px, but the frame measured was {}×{} px",
                    shape.1, shape.0, self.frame_shape.1, self.frame_shape.0
                ),
            ));
        }
        let mut meta = meta_of(header, shape, name)?;
        meta.file = self.frame_meta.file.clone();
        meta.frame = self.frame_meta.frame;
        Ok(meta)
    }
}

/// Header cards as a list of `(key, value)`; `HISTORY` and `COMMENT` values are their text.
pub fn cards_to_py<'py>(
    py: Python<'py>,
    cards: &[(String, HeaderValue)],
) -> PyResult<Bound<'py, PyList>> {
    let list = PyList::empty(py);
    for (key, value) in cards {
        let value: Bound<'py, PyAny> = match value {
            HeaderValue::Bool(b) => b.into_pyobject(py)?.to_owned().into_any(),
            HeaderValue::Int(i) => i.into_pyobject(py)?.into_any(),
            HeaderValue::Float(f) => f.into_pyobject(py)?.into_any(),
            HeaderValue::Str(s) => s.into_pyobject(py)?.into_any(),
        };
        list.append((key, value))?;
    }
    Ok(list)
}

/// Align `frame` to `reference`. Each is a path spec (`FILE.fits`, `FILE.fits[N]`) or a tuple
/// `(pixels, header_cards, name)`: a C-contiguous float32 array and its FITS header as bytes
/// (80-character cards). The record's `reference` and `frame` are `names`.
#[pyfunction]
#[pyo3(signature = (reference, frame, names, config_path=None, config_table=None))]
pub fn align(
    py: Python<'_>,
    reference: &Bound<'_, PyAny>,
    frame: &Bound<'_, PyAny>,
    names: (String, String),
    config_path: Option<std::path::PathBuf>,
    config_table: Option<String>,
) -> PyResult<Alignment> {
    let reference = Source::from_py(reference)?;
    let frame = Source::from_py(frame)?;
    let config = crate::config::Source::new(config_path, config_table);
    let work = move || -> Result<Alignment> {
        let cfg = config.load(&Default::default())?.engine;
        // Read side by side, as the command line does.
        let (reference, frame) = std::thread::scope(|scope| {
            let reference = scope.spawn(|| Side::read(reference));
            let frame = Side::read(frame);
            let reference = reference
                .join()
                .unwrap_or_else(|panic| std::panic::resume_unwind(panic));
            (reference, frame)
        });
        let (reference, frame) = (reference?, frame?);
        let workspace = Arc::new(sunjitter_io::self_tests::SelfTestCache::workspace_from_env());
        let reference_shape = reference.pixels.view().dim();
        let frame_shape = frame.pixels.view().dim();
        let frame_meta = frame.meta.clone();
        let (reference_header, reference_meta) = (reference.header, reference.meta.clone());
        let mut outcome = match (reference.pixels, frame.pixels) {
            // Both read from files: the command line's own call, each image cleaned in place.
            (Pixels::Owned(r), Pixels::Owned(f)) => engine::align_images_owned_in(
                Image {
                    data: r,
                    meta: reference.meta,
                },
                Image {
                    data: f,
                    meta: frame.meta,
                },
                &cfg,
                workspace,
            ),
            (r, f) => engine::align_views_in(
                (&reference_meta, r.view()),
                (&frame_meta, f.view()),
                &cfg,
                workspace,
            ),
        };
        outcome.result.reference = names.0;
        outcome.result.frame = names.1;
        Ok(Alignment {
            outcome,
            reference_header,
            reference_meta,
            reference_shape,
            frame_meta,
            frame_shape,
        })
    };
    wait::run(py, "align", work, OnInterrupt::Abandon, |_| Ok(()))?.py_err()
}

/// One image (or frame of a cube) as the engine reads it: its pixels (float32) and the header
/// cards of a 2-D file of it (a cube frame's own time, exposure and pointing).
#[pyfunction]
pub fn read_frame<'py>(
    py: Python<'py>,
    spec: String,
) -> PyResult<(Bound<'py, PyArray2<f32>>, Bound<'py, PyList>)> {
    let work = move || -> Result<sunjitter_io::aligned::Product> {
        let spec = FrameSpec::parse(&spec);
        let image = fits::read_frame(&spec)?;
        let (_, header) = fits::read_image_header(&spec.path)?;
        let mut cards = fits::frame_header_cards(&header, &image.meta);
        // The cube's `WCSAXES = 3` no longer holds for one frame.
        for (key, value) in cards.iter_mut() {
            if key == "WCSAXES" {
                *value = HeaderValue::Int(2);
            }
        }
        Ok((image.data, cards))
    };
    let (data, cards) =
        wait::run(py, "read_frame", work, OnInterrupt::Abandon, |_| Ok(()))?.py_err()?;
    Ok((data.into_pyarray(py), cards_to_py(py, &cards)?))
}
