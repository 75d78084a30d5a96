"""``read_map``, ``correct_pointing`` and ``register`` against astropy/sunpy's reading of the
files and WCS, and against the command line's ``--aligned`` product."""

from __future__ import annotations

import numpy as np
import pytest
import sunpy.map
from astropy.io import fits
from astropy.wcs import WCS

import sunjitter
from conftest import AIA_171, EIT_171, EIT_195, IRIS_1400


def _transform(r):
    """The measured map reference pixel → frame pixel (the contract's convention)."""
    h, w = r._alignment.shapes[0]
    c = np.array([(w - 1) / 2, (h - 1) / 2])
    theta = np.deg2rad(r.rotation_arcsec / 3600)
    rot = np.array([[np.cos(theta), -np.sin(theta)], [np.sin(theta), np.cos(theta)]])

    def apply(p):
        return (r.scale * (rot @ (np.asarray(p, float) - c[:, None])) + c[:, None]
                + np.array([[r.dx_px], [r.dy_px]]))

    return apply


def test_a_2d_file_reads_as_astropy_reads_it():
    m = sunjitter.read_map(EIT_195)
    with fits.open(EIT_195) as hdul:
        data, header = hdul[0].data, hdul[0].header
    assert m.data.dtype == np.float32
    np.testing.assert_array_equal(m.data, data.astype(np.float32))
    for key in ("CRPIX1", "CRPIX2", "CDELT1", "CDELT2", "CRVAL1", "CRVAL2"):
        assert m.fits_header[key] == header[key]


def test_a_cube_frame_has_its_own_time():
    first, later = (sunjitter.read_map(f"{IRIS_1400}[{n}]") for n in (0, 20))
    with fits.open(IRIS_1400) as hdul:
        np.testing.assert_array_equal(later.data, hdul[0].data[20].astype(np.float32))
    assert later.date > first.date
    assert later.meta["srcframe"] == 20


def test_register_is_the_command_lines_aligned_product(cli, tmp_path):
    """The same code as ``align --aligned``: the same pixels and cards. (EIT's headers give a
    disk that disagrees with the image: the product's WCS carries the geometry used.)"""
    out = tmp_path / "aligned.fits"
    cli.run("align", EIT_171, EIT_195, "--aligned", out)
    r = sunjitter.align(EIT_171, EIT_195)
    registered = sunjitter.register(sunpy.map.Map(EIT_195), r)
    with fits.open(out) as hdul:
        written, header = hdul[0].data, hdul[0].header
    # The same resampling, to the last bit (NaN where the frame has no data).
    np.testing.assert_array_equal(registered.data, written)
    # The cards as written (cfitsio writes 15 significant digits).
    for key in ("CRPIX1", "CRPIX2", "CDELT1", "CDELT2", "CRVAL1", "CRVAL2"):
        assert registered.fits_header[key] == pytest.approx(header[key], rel=1e-14, abs=1e-300), key
    for key in ("CTYPE1", "CTYPE2", "DATE-OBS", "TELESCOP"):
        assert registered.fits_header[key] == header[key], key
    assert registered.fits_header["HISTORY"][:] == header["HISTORY"][:]


IRIS_PAIR = (0, 7)


@pytest.fixture(scope="module")
def iris_pair():
    ref_map, frame_map = (sunjitter.read_map(f"{IRIS_1400}[{n}]") for n in IRIS_PAIR)
    return ref_map, frame_map, sunjitter.align(ref_map, frame_map)


def test_registered_frames_are_on_the_references_grid(iris_pair):
    ref_map, frame_map, r = iris_pair
    registered = sunjitter.register(frame_map, r)
    assert registered.data.shape == ref_map.data.shape
    pixels = np.array([[10.5, 54.0, 100.0], [7.0, 54.0, 99.25]])
    np.testing.assert_allclose(
        registered.wcs.pixel_to_world_values(*pixels), ref_map.wcs.pixel_to_world_values(*pixels),
        rtol=0, atol=1e-9,
    )
    assert any("resampled onto the reference" in h for h in registered.fits_header["HISTORY"])


def test_corrected_pointing_gives_features_the_references_coordinates(iris_pair):
    ref_map, frame_map, r = iris_pair
    corrected = sunjitter.correct_pointing(frame_map, r)
    assert corrected.data is frame_map.data  # not resampled, not copied
    p_ref = np.array([[20.0, 54.0, 100.0, 33.5], [90.0, 54.5, 30.0, 70.25]])
    p_frame = _transform(r)(p_ref)
    # A feature at p_ref in the reference is at p_frame in the frame: the corrected WCS (as
    # astropy reads it) gives it the reference's coordinates, the frame's own header did not.
    got = np.array(corrected.wcs.pixel_to_world_values(*p_frame))
    want = np.array(ref_map.wcs.pixel_to_world_values(*p_ref))
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-9)
    before = np.array(frame_map.wcs.pixel_to_world_values(*p_frame))
    assert np.abs(before - want).max() > 1e-6  # the correction is not nothing
    assert "XCEN" not in corrected.fits_header


def test_a_known_shift_is_corrected_within_its_sigma():
    """The truth: the reference's pixels moved by a whole number of pixels, same header."""
    ref_map = sunpy.map.Map(AIA_171)
    shift = (3, -2)  # (x, y) px: reference content appears at p + shift in the frame
    moved = np.full_like(ref_map.data, np.nan, dtype=np.float32)
    moved[max(shift[1], 0):moved.shape[0] + min(shift[1], 0),
          max(shift[0], 0):moved.shape[1] + min(shift[0], 0)] = ref_map.data[
        max(-shift[1], 0):moved.shape[0] - max(shift[1], 0),
        max(-shift[0], 0):moved.shape[1] - max(shift[0], 0)]
    frame_map = sunpy.map.Map(moved, ref_map.fits_header)
    r = sunjitter.align(ref_map, frame_map)
    assert r.ok
    assert abs(r.dx_px - shift[0]) < 4 * r.sigma_dx_px + 0.01
    assert abs(r.dy_px - shift[1]) < 4 * r.sigma_dy_px + 0.01
    corrected = sunjitter.correct_pointing(frame_map, r)
    # Frame pixel p + shift holds the reference's pixel p: their coordinates agree to the
    # measurement's error (arcsec = px × plate scale).
    p = np.array([[40.0, 64.0], [50.0, 80.0]])
    got = np.array(corrected.wcs.pixel_to_world_values(p[0] + shift[0], p[1] + shift[1]))
    want = np.array(ref_map.wcs.pixel_to_world_values(*p))
    scale_deg = abs(ref_map.fits_header["CDELT1"]) / 3600
    tolerance = 4 * max(r.sigma_dx_px, r.sigma_dy_px) * scale_deg + 0.02 * scale_deg
    assert np.all(np.abs(got - want) < tolerance)


def test_products_of_a_failed_alignment_are_refused():
    ref_map = sunpy.map.Map(EIT_171)
    flat = sunpy.map.Map(np.full((128, 128), 3.0, dtype=np.float32), ref_map.fits_header)
    r = sunjitter.align(ref_map, flat)
    assert r.status == "failed"
    with pytest.raises(sunjitter.AlignmentFailedError, match="no transform"):
        sunjitter.correct_pointing(flat, r)
    with pytest.raises(sunjitter.AlignmentFailedError):
        sunjitter.register(flat, r)
