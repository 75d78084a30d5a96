#!/usr/bin/env python3
"""Truth values for tests/iris_pointing.rs: each IRIS SJI frame's sun centre from its own pointing.

Run from the repository root:  python3 tools/iris_pointing_truth.py
(needs astropy; written against astropy 8.0.2). The printed numbers are hard-coded in
tests/iris_pointing.rs; this script is the record of how they were obtained.

How each value is obtained
--------------------------
* An IRIS level-2 SJI cube has one primary header for all frames; its WCS (CRPIX/CRVAL/CDELT/
  PCi_j, HPLN-TAN/HPLT-TAN) describes the nominal pointing XCEN/YCEN (= CRVAL1/CRVAL2).
  HDU 1 is a 2-D array, one row per exposure, whose header names column indices: XCENIX and
  YCENIX are each exposure's field-centre pointing in arcsec (as irispy-lmsal reads them).
* Frame i reads the table at fractional row p = i*(R-1)/(n-1) when the table has R != n rows
  (the trimmed test files: 540 rows for the 54-frame 1400 cube, resampled along time; see
  tools/sunpy_truth.py --slit-check), else row i; values are interpolated linearly between rows.
* The frame's pointing offset d = (XCENIX(p) - XCEN, YCENIX(p) - YCEN) arcsec moves the
  reference value: a copy of the primary header gets CRVAL1 += d_x, CRVAL2 += d_y, and the sun
  centre is astropy's `WCS(copy).celestial.wcs_world2pix([[0, 0]], 0)` (full TAN projection,
  0-based pixels), i.e. where helioprojective (0", 0") falls in that frame.
* Rows of missing exposures carry XCENIX = YCENIX = 0 (with EXPTIMES = 0): 1400 rows 198-221
  (not all), which frames 20 and 21 straddle. Such a frame has no pointing of its own: its truth
  is the header's centre (printed below as a check of that rule).
* Also printed: the linear approximation -M^-1 d of the move (M = diag(CDELT) PC), which is what
  sunjitter applies, and its difference from the exact TAN answer (well under 0.01 px here).
"""
import warnings

import numpy as np

warnings.simplefilter("ignore")
from astropy.io import fits  # noqa: E402
from astropy.wcs import WCS  # noqa: E402

REAL = "data/real/"
# tests/iris_pointing.rs uses 1400 frames 0, 27, 53 (and 20, 21: fill rows) and 2832 frames
# 0, 9, 17; the others are the frames tests/info.rs checks.
CUBES = [
    ("iris_l2_20140329_140938_3860258481_SJI_1400_t000.fits", [0, 27, 53, 20, 21, 1]),
    ("iris_l2_20140329_140938_3860258481_SJI_2832_t000.fits", [0, 9, 17]),
    ("iris_l2_20140329_140938_3860258481_SJI_2796_t000_deconvolved.fits", [0, 35, 71]),
]


def frame_positions(n, rows):
    """Table position of each frame: identity when the table matches, else resampled."""
    if rows == n or n <= 1 or rows <= 1:
        return np.minimum(np.arange(n), rows - 1).astype(float)
    return np.arange(n) * (rows - 1) / (n - 1)


def interp_rows(values, p):
    """Linear interpolation at fractional row p; a row of zero weight does not contribute."""
    lo = int(np.floor(p))
    if p == lo:
        return values[lo]
    return values[lo] + (values[lo + 1] - values[lo]) * (p - lo)


def sun_centre(header):
    c = WCS(header).celestial.wcs_world2pix([[0.0, 0.0]], 0)[0]
    return float(c[0]), float(c[1])


def main():
    import argparse

    parser = argparse.ArgumentParser()
    parser.add_argument(
        "--cdelt",
        type=float,
        help="give every cube this plate scale (arcsec/px) in place of its CDELT1/CDELT2, as "
        "`[channels.X] plate_scale_arcsec` does for binned data (tests/plate_scale.rs)",
    )
    args = parser.parse_args()
    for name, frames in CUBES:
        with fits.open(REAL + name) as hdul:
            hdr, aux, ah = hdul[0].header, hdul[1].data, hdul[1].header
            if args.cdelt is not None:
                hdr["CDELT1"] = args.cdelt
                hdr["CDELT2"] = args.cdelt
            n, rows = hdr["NAXIS3"], aux.shape[0]
            xcen = hdr.get("XCEN", hdr["CRVAL1"])
            ycen = hdr.get("YCEN", hdr["CRVAL2"])
            xs = aux[:, ah["XCENIX"]].astype(float).copy()
            ys = aux[:, ah["YCENIX"]].astype(float).copy()
            fill = (xs == 0) & (ys == 0)
            xs[fill] = np.nan
            ys[fill] = np.nan
            nominal = sun_centre(hdr)
            cdelt = np.array([hdr["CDELT1"], hdr["CDELT2"]])
            pc = np.array([[hdr["PC1_1"], hdr["PC1_2"]], [hdr["PC2_1"], hdr["PC2_2"]]])
            m = cdelt[:, None] * pc
            p = frame_positions(n, rows)
            print(f"{name}: {n} frames, {rows} table rows, XCEN {xcen}, YCEN {ycen}, "
                  f"header centre {nominal!r}")
            for i in frames:
                x, y = float(interp_rows(xs, p[i])), float(interp_rows(ys, p[i]))
                row = float(p[i])
                if not (np.isfinite(x) and np.isfinite(y)):
                    print(f"  frame {i}: row {row!r}: pointing missing (fill rows) -> header "
                          f"centre {nominal!r}")
                    continue
                d = np.array([x - xcen, y - ycen])
                moved = hdr.copy()
                moved["CRVAL1"] = hdr["CRVAL1"] + d[0]
                moved["CRVAL2"] = hdr["CRVAL2"] + d[1]
                c = sun_centre(moved)
                linear = [float(v) for v in np.array(nominal) - np.linalg.solve(m, d)]
                print(f"  frame {i}: row {row!r}: XCENIX {x!r} YCENIX {y!r} "
                      f"sun_center_px ({c[0]!r}, {c[1]!r}) "
                      f"[linear -M^-1 d: ({linear[0]!r}, {linear[1]!r}), "
                      f"differs by {np.hypot(linear[0] - c[0], linear[1] - c[1]):.2e} px]")


if __name__ == "__main__":
    main()
