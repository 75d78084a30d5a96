#!/usr/bin/env python3
"""What a rigid similarity fit should measure between two full-disk images of a rotating Sun.

Independent of sunjitter: the motion of each point of the disk between the two observation
times from the Sun's differential rotation (Snodgrass & Ulrich 1990, sidereal rate of
magnetic features, made synodic by the Earth's 0.9856 °/day) about an axis tilted by B0
towards the observer (Meeus, Astronomical Algorithms, ch. 29), projected on the sky, then
the least-squares similarity (contract convention: rotation about the array centre, y up)
of that displacement field over the disk of radius RHO px about the disk centre, every
pixel weighted alike.

    python3 tools/solar_rotation_expectation.py REF.fits FRAME.fits --centre X Y --radius R
        --rho RHO [--roll DEG]

Defaults are the bundled EIT 195 -> 171 pair: the true plate scale 21.04"/px (8 x 2.63,
the headers were not updated when the images were rebinned), the photospheric radius
979.07" (the header's SOLAR_R x CDELT), SOHO rolled 180 deg, the disk centre sunjitter's
limb fit finds in the reference (62.8, 64.2) and the region its flow samples between
channels (the disk less the flow's reach, 48.5 - 19 = 29.5 px).
"""
import argparse
import math

import numpy as np
from astropy.io import fits
from astropy.time import Time


def obs_time(path):
    h = fits.getheader(path)
    for key in ("DATE_OBS", "DATE-OBS", "T_OBS"):
        if key in h:
            return Time(h[key].replace("Z", ""), scale="utc")
    raise SystemExit(f"{path}: no DATE_OBS/DATE-OBS/T_OBS")


def b0_deg(t):
    """Heliographic latitude of the disk centre (Meeus ch. 29)."""
    jd = t.jd
    tc = (jd - 2451545.0) / 36525.0
    l0 = 280.46646 + 36000.76983 * tc
    m = math.radians(357.52911 + 35999.05029 * tc)
    c = 1.914602 * math.sin(m) + 0.019993 * math.sin(2 * m)
    lam = math.radians(l0 + c)
    node = math.radians(73.6667 + 1.3958333 * (jd - 2396758.0) / 36525.0)
    return math.degrees(math.asin(math.sin(lam - node) * math.sin(math.radians(7.25))))


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("reference", nargs="?", default="data/real/eit_195_20040301T000010_128.fits")
    ap.add_argument("frame", nargs="?", default="data/real/eit_171_20040301T010016_128.fits")
    ap.add_argument("--plate", type=float, default=21.04, help="true plate scale, arcsec/px")
    ap.add_argument("--rsun", type=float, default=979.07, help="photospheric radius, arcsec")
    ap.add_argument("--centre", type=float, nargs=2, default=(62.8, 64.2))
    ap.add_argument("--rho", type=float, default=29.5, help="radius of the fitted region, px")
    ap.add_argument("--roll", type=float, default=180.0, help="image roll, deg (solar north from +y)")
    a = ap.parse_args()

    t0, t1 = obs_time(a.reference), obs_time(a.frame)
    dt_days = (t1 - t0).to_value("day")
    b0 = math.radians(b0_deg(t0))
    h, w = fits.getdata(a.reference).shape
    r_px = a.rsun / a.plate
    ys, xs = np.mgrid[0:h, 0:w].astype(float)
    ex, ey = xs - a.centre[0], ys - a.centre[1]
    inside = ex**2 + ey**2 <= a.rho**2
    # Image to solar (north up, west +x) by undoing the roll.
    cr, sr = math.cos(math.radians(a.roll)), math.sin(math.radians(a.roll))
    sx = (cr * ex[inside] + sr * ey[inside]) / r_px
    sy = (-sr * ex[inside] + cr * ey[inside]) / r_px
    sz = np.sqrt(np.clip(1 - sx**2 - sy**2, 0, None))
    sin_lat = sy * math.cos(b0) + sz * math.sin(b0)
    rate = 14.71 - 2.39 * sin_lat**2 - 1.78 * sin_lat**4 - 0.9856  # synodic, deg/day
    turn = np.radians(rate) * dt_days
    # v = Ω × r, Ω = turn · (0, cos B0, sin B0): the projected motion on the sky.
    u = turn * (math.cos(b0) * sz - math.sin(b0) * sy) * r_px
    v = turn * math.sin(b0) * sx * r_px
    # Back to image axes (the roll again).
    du, dv = cr * u - sr * v, sr * u + cr * v
    x = xs[inside] - (w - 1) / 2
    y = ys[inside] - (h - 1) / 2
    design = np.zeros((2 * x.size, 4))
    design[0::2] = np.c_[x, -y, np.ones_like(x), np.zeros_like(x)]
    design[1::2] = np.c_[y, x, np.zeros_like(x), np.ones_like(x)]
    p, *_ = np.linalg.lstsq(design, np.c_[du, dv].ravel(), rcond=None)
    print(f"{a.reference} -> {a.frame}: {dt_days * 24:.3f} h apart, B0 {math.degrees(b0):.2f} deg")
    print(f"disk-centre motion {turn.max() * r_px:.3f} px west; fitted over {inside.sum()} px within {a.rho} px:")
    print(f"scale {1 + p[0]:.7f}  rotation {math.degrees(p[1]) * 3600:.0f} arcsec  dx {p[2]:.3f} px  dy {p[3]:.3f} px")


if __name__ == "__main__":
    main()
