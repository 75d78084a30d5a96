#!/usr/bin/env python3
"""Independent check of `--aligned DIR --wcs-only` products with sunpy and astropy.

A product's header must put a solar feature at the helioprojective coordinates the chain's
origin gives it. Where the feature is seen is decided here without sunjitter's WCS code:

  --truth truth.csv   (synthetic frames from `sunjitter synth`): the feature at nominal pixel p
      is at truth_k(p) in frame k and truth_0(p) in the origin (the contract's convention,
      p' = s R(theta) (p - c) + c + (dx, dy)). sunpy's Map of the product at truth_k(p) must
      give the coordinates sunpy's Map of the origin gives at truth_0(p), within the measured
      sigma (the product's SJ_SDX, SJ_SDY, SJ_SROT) -- and the frame's own header must not.
  --chain             (real data): sunpy's Map of each product, at the frame pixel where the
      chained transform (SJ_* cards, the log's chained_* values) puts an origin pixel, must
      give the coordinates sunpy's Map of the origin gives that pixel.
  --disk              (a refused plate scale, EUV): the limb's radius measured in each
      product's pixels times its CDELT1 must be the header's solar radius, with the EUV limb
      between 3 % inside and 8 % above the photosphere, and the input's own CDELT1 must fail
      that test.

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


def chain_of(header):
    t = (header["SJ_SCALE"], math.radians(header["SJ_ROT"] / 3600.0), header["SJ_DX"], header["SJ_DY"])
    return t, (header["SJ_CX"], header["SJ_CY"])


def check_chain(args):
    """Real data: sunpy's Map of each product, at the frame pixel where the chained transform
    (the log's chained_*, carried in SJ_*) puts an origin pixel, gives the coordinates sunpy's
    Map of the origin gives that origin pixel."""
    origin = sunpy_map(args.origin)
    h, w = origin.data.shape
    g = np.linspace(0.1, 0.9, 5)
    xy = np.array([(u * (w - 1), v * (h - 1)) for u in g for v in g])
    reference = hpc_arcsec(origin, xy)
    plate = abs(origin.scale.axis1.value)
    passed = failed = 0
    for path in products(args.products):
        header = fits.getheader(path)
        t, center = chain_of(header)
        err = np.abs(hpc_arcsec(sunpy_map(path), apply(t, xy, center)) - reference).max() / plate
        ok = err <= args.floor_px
        passed += ok
        failed += not ok
        print(f"{'ok  ' if ok else 'FAIL'} {os.path.relpath(path, args.products)}: "
              f"{err:.2e} px from the origin's coordinates (limit {args.floor_px})")
    return passed, failed


def limb_radius_px(data):
    """The radius of an EUV image's limb brightening: the peak of the radial profile about the
    centroid of the brighter half of the pixels."""
    data = np.nan_to_num(data.astype(float))
    bright = data > np.median(data)
    y, x = np.mgrid[0 : data.shape[0], 0 : data.shape[1]]
    cx, cy = x[bright].mean(), y[bright].mean()
    r = np.hypot(x - cx, y - cy)
    bins = np.floor(r).astype(int).ravel()
    prof = np.bincount(bins, data.ravel()) / np.maximum(np.bincount(bins), 1)
    reach = int(min(cx, cy, data.shape[1] - 1 - cx, data.shape[0] - 1 - cy))
    k = 5 + int(np.argmax(prof[5:reach]))
    m, c, p = prof[k - 1], prof[k], prof[k + 1]
    d = m - 2 * c + p
    return k + 0.5 + (0.0 if d == 0 else 0.5 * (m - p) / d)


def check_disk(args):
    """The plate scale a product states against the Sun it shows: the limb's radius in pixels
    times CDELT1 must be the solar radius the input's header gives (RSUN_OBS, or SOLAR_R in
    its own pixels), the limb brightening of an EUV image peaking up to 8 % above the
    photosphere on a coarse grid (EIT 195 at 21″/px: 6 %), and the input's own CDELT1 must
    fail that test."""
    passed = failed = 0
    own = fits.getheader(args.origin)
    rsun = own.get("RSUN_OBS") or own.get("RSUN_ARC") or own["SOLAR_R"] * abs(own["CDELT1"])
    found = sorted(glob.glob(os.path.join(args.products, "**", "*.fits"), recursive=True))
    for path in [args.origin] + found:
        header = fits.getheader(path)
        r_px = limb_radius_px(fits.getdata(path))
        stated = r_px * abs(header["CDELT1"])
        ok = -0.03 <= stated / rsun - 1 <= 0.08
        if path == args.origin:
            ok = not ok
            what = "input header (must disagree)"
        else:
            what = "product"
        passed += ok
        failed += not ok
        print(f"{'ok  ' if ok else 'FAIL'} {os.path.basename(path)}: {what}: limb {r_px:.1f} px "
              f"x CDELT1 {abs(header['CDELT1']):.3f} = {stated:.0f} arcsec vs R_sun {rsun:.0f}")
    return passed, failed


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("products", help="the --aligned directory (its *.wcs.fits are checked)")
    p.add_argument("--origin", required=True, help="the chain origin's input file")
    p.add_argument("--truth", help="synth's truth.csv")
    p.add_argument("--chain", action="store_true", help="check against the chained transform")
    p.add_argument("--disk", action="store_true", help="check the plate scale against the disk")
    p.add_argument("--sigmas", type=float, default=4.0)
    p.add_argument("--floor-px", type=float, default=0.002)
    p.add_argument("--min-raw-px", type=float, default=0.5)
    p.add_argument("--expect", type=int, help="number of products expected")
    args = p.parse_args()
    if args.truth:
        passed, failed = check_truth(args)
    elif args.chain:
        passed, failed = check_chain(args)
    else:
        passed, failed = check_disk(args)
    if args.expect is not None and len(products(args.products)) != args.expect:
        print(f"FAIL {len(products(args.products))} products, expected {args.expect}")
        failed += 1
    print(f"{passed} passed, {failed} failed")
    sys.exit(1 if failed or not passed else 0)


if __name__ == "__main__":
    main()
