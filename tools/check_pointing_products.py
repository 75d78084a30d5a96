#!/usr/bin/env python3
"""Independent check of `--aligned DIR --wcs-only` products with sunpy and astropy.

A product's header must put a solar feature at the helioprojective coordinates the chain's
origin gives it. Where the feature is seen is decided here without sunjitter's WCS code:

  --truth truth.csv   (synthetic frames from `sunjitter synth`): the feature at nominal pixel p
      is at truth_k(p) in frame k and truth_0(p) in the origin (the contract's convention,
      p' = s R(theta) (p - c) + c + (dx, dy)). sunpy's Map of the product at truth_k(p) must
      give the coordinates sunpy's Map of the origin gives at truth_0(p), within the measured
      sigma (the product's SJ_SDX, SJ_SDY, SJ_SROT) -- and the frame's own header must not.
  --image             (real data): each product is reprojected onto the origin's pixel grid
      through the two WCS (astropy), and the remaining shift against the origin image is
      measured by FFT cross-correlation; it must stay below --max-shift-px.

Prints one line per product and a closing 'N passed, N failed'; exit 1 on any failure.
"""

import argparse
import csv
import glob
import math
import os
import sys
import warnings

import numpy as np
from astropy.io import fits
from astropy.wcs import WCS, FITSFixedWarning

warnings.simplefilter("ignore", FITSFixedWarning)


def sunpy_map(path):
    import sunpy.map

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return sunpy.map.Map(path)


def hpc_arcsec(m, xy):
    """Helioprojective (Tx, Ty) in arcsec of 0-based pixel positions xy (N x 2)."""
    import astropy.units as u

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        c = m.pixel_to_world(xy[:, 0] * u.pix, xy[:, 1] * u.pix)
    return np.column_stack([c.Tx.to_value(u.arcsec), c.Ty.to_value(u.arcsec)])


def apply(t, xy, center):
    s, th, dx, dy = t
    a, b = s * math.cos(th), s * math.sin(th)
    x, y = xy[:, 0] - center[0], xy[:, 1] - center[1]
    return np.column_stack([a * x - b * y + center[0] + dx, b * x + a * y + center[1] + dy])


def products(directory):
    return sorted(glob.glob(os.path.join(directory, "**", "*.wcs.fits"), recursive=True))


def check_truth(args):
    rows = {}
    with open(args.truth) as f:
        for r in csv.DictReader(f):
            rows[os.path.basename(r["file"])] = (
                float(r["scale"]),
                math.radians(float(r["rotation_arcsec"]) / 3600.0),
                float(r["dx_px"]),
                float(r["dy_px"]),
            )
    origin = sunpy_map(args.origin)
    h, w = origin.data.shape
    center = ((w - 1) / 2, (h - 1) / 2)
    # Nominal pixels over the inner disk.
    g = np.linspace(-0.3, 0.3, 7)
    xy = np.array([(center[0] + u * w, center[1] + v * h) for u in g for v in g])
    t0 = rows[os.path.basename(args.origin)]
    reference = hpc_arcsec(origin, apply(t0, xy, center))
    passed = failed = 0
    raw_worst = 0.0
    for path in products(args.products):
        header = fits.getheader(path)
        src = os.path.basename(header["SRCFILE"])
        at = apply(rows[src], xy, center)
        corrected = hpc_arcsec(sunpy_map(path), at)
        raw = hpc_arcsec(sunpy_map(header["SRCFILE"]), at)
        plate = abs(origin.scale.axis1.value)
        err = np.abs(corrected - reference).max() / plate
        raw_err = np.abs(raw - reference).max() / plate
        raw_worst = max(raw_worst, raw_err)
        # sigma of the shift, and of the roll at the farthest point checked.
        reach = np.hypot(xy[:, 0] - center[0], xy[:, 1] - center[1]).max()
        roll = math.radians(header.get("SJ_SROT", 0.0) / 3600.0) * reach
        sigma = math.sqrt(header.get("SJ_SDX", 0.0) ** 2 + header.get("SJ_SDY", 0.0) ** 2 + roll**2)
        limit = args.sigmas * sigma + args.floor_px
        ok = err <= limit
        passed += ok
        failed += not ok
        print(
            f"{'ok  ' if ok else 'FAIL'} {os.path.relpath(path, args.products)}: "
            f"corrected {err:.4f} px (limit {limit:.4f} = {args.sigmas} sigma + "
            f"{args.floor_px}), own header {raw_err:.4f} px, status {header.get('SJ_STAT')}"
        )
    if raw_worst < args.min_raw_px:
        print(f"FAIL the frames' own headers are off by at most {raw_worst:.4f} px: "
              f"the check cannot tell a correction from none (need >= {args.min_raw_px})")
        failed += 1
    return passed, failed


def shift_by_correlation(a, b):
    """Shift (x, y) of b relative to a: FFT cross-correlation, parabolic peak."""
    a = np.nan_to_num(a - np.nanmean(a))
    b = np.nan_to_num(b - np.nanmean(b))
    win = np.outer(np.hanning(a.shape[0]), np.hanning(a.shape[1]))
    f = np.fft.fft2(a * win).conj() * np.fft.fft2(b * win)
    cc = np.fft.fftshift(np.real(np.fft.ifft2(f)))
    iy, ix = np.unravel_index(np.argmax(cc), cc.shape)

    def para(m, c, p):
        d = m - 2 * c + p
        return 0.0 if d == 0 else 0.5 * (m - p) / d

    dy = para(cc[iy - 1, ix], cc[iy, ix], cc[iy + 1, ix])
    dx = para(cc[iy, ix - 1], cc[iy, ix], cc[iy, ix + 1])
    return ix + dx - cc.shape[1] // 2, iy + dy - cc.shape[0] // 2


def reproject(data, wcs_from, wcs_to, shape):
    from scipy.ndimage import map_coordinates

    h, w = shape
    y, x = np.mgrid[0:h, 0:w].astype(float)
    lon, lat = wcs_to.celestial.wcs_pix2world(x, y, 0)
    px, py = wcs_from.celestial.wcs_world2pix(lon, lat, 0)
    return map_coordinates(data.astype(float), [py, px], order=3, mode="constant", cval=np.nan)


def check_image(args):
    ref_hdu = fits.getheader(args.origin)
    ref = fits.getdata(args.origin).astype(float)
    ref_wcs = WCS(ref_hdu).celestial
    h, w = ref.shape
    crop = (slice(h // 4, 3 * h // 4), slice(w // 4, 3 * w // 4))
    passed = failed = 0
    for path in products(args.products):
        hdr = fits.getheader(path)
        data = fits.getdata(path)
        on_ref = reproject(data, WCS(hdr).celestial, ref_wcs, ref.shape)
        sx, sy = shift_by_correlation(ref[crop], on_ref[crop])
        err = math.hypot(sx, sy)
        ok = err <= args.max_shift_px
        passed += ok
        failed += not ok
        print(f"{'ok  ' if ok else 'FAIL'} {os.path.relpath(path, args.products)}: "
              f"remaining shift ({sx:+.4f}, {sy:+.4f}) px (limit {args.max_shift_px})")
    return passed, failed


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("products", help="the --aligned directory (its *.wcs.fits are checked)")
    p.add_argument("--origin", required=True, help="the chain origin's input file")
    p.add_argument("--truth", help="synth's truth.csv")
    p.add_argument("--image", action="store_true", help="check by image correlation")
    p.add_argument("--sigmas", type=float, default=4.0)
    p.add_argument("--floor-px", type=float, default=0.002)
    p.add_argument("--min-raw-px", type=float, default=0.5)
    p.add_argument("--max-shift-px", type=float, default=0.2)
    p.add_argument("--expect", type=int, help="number of products expected")
    args = p.parse_args()
    passed, failed = check_truth(args) if args.truth else check_image(args)
    if args.expect is not None and len(products(args.products)) != args.expect:
        print(f"FAIL {len(products(args.products))} products, expected {args.expect}")
        failed += 1
    print(f"{passed} passed, {failed} failed")
    sys.exit(1 if failed or not passed else 0)


if __name__ == "__main__":
    main()
