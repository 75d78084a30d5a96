#!/usr/bin/env python3
"""Independent oracle for sunjitter's solar differential-rotation model, computed with sunpy.

Writes tests/data/solar_rotation/oracle.json: where points of the solar surface seen in an
AIA-like 4096 x 4096 reference image appear, in the 0-based pixels of a frame taken 12 s, 600 s,
1 h and 1 day later, for sunpy's three rotation profiles (howard, snodgrass, allen), together
with the header cards of the reference and of every frame, and sunpy's `diff_rot` rates.
No number in the file comes from sunjitter.

    python3 tools/solar_rotation_oracle.py [--out PATH]

Needs sunpy (>= 5; written against 7) and astropy; run from the repository root. Nothing is
downloaded at run time: the starting header is sunpy's own test file `aia_171_level1.fits`,
shipped in the sunpy wheel, and the Earth and Sun positions come from astropy's built-in
ephemeris.

Geometry
--------
* Reference: the real AIA level-1 header with NAXIS1 = NAXIS2 = 4096, CDELT = 0.6"/px and
  CRPIX = 2048.5 (the real CRVAL, CROTA2, observer and dates are kept), so the disk centre sits
  at 0-based (2055.05, 2042.72), 7.6 px right of and 4.8 px below the array centre, where AIA's
  own master pointing puts it (X0_MP, Y0_MP of the same file).
* Frame at t0 + dt: the same pointing (CRPIX, CRVAL, CROTA2); DATE-OBS and T_OBS advanced by dt;
  the observer is SDO taken as the Earth plus the real header's offset from the Earth at t0
  (HGLN/HGLT/DSUN_OBS = real + get_earth(t1) - get_earth(t0)), CRLN_OBS = real + L0(t1) - L0(t0),
  CRLT_OBS = HGLT_OBS, RSUN_OBS = asin(RSUN_REF / DSUN_OBS).
* Both are opened as `sunpy.map.Map`s (an AIAMap: its reference time is T_OBS), so every
  coordinate frame, observer and solar radius (RSUN_REF) is the one sunpy reads from the cards
  that are written to the fixture.

Method, for each reference pixel (x0, y0) and profile
-----------------------------------------------------
    c0 = ref.wcs.pixel_to_world(x0, y0)               # HPC at t0, put on the sphere RSUN_REF
    r  = SkyCoord(RotatedSunFrame(base=c0, rotated_time=t1, rotation_model=profile))
    with transform_with_sun_center():
        c1 = r.transform_to(frame.coordinate_frame)   # HPC at t1, observer at t1
    (x1, y1) = frame.wcs.world_to_pixel(c1)

`transform_with_sun_center` keeps the point on the solar surface: without it sunpy's change of
obstime (HGS(t0) -> HCRS(t1) -> HGS(t1)) holds the point fixed relative to the solar-system
barycentre, so it lags the Sun's own barycentric motion (about 1.5 px per day here). With it,
the result equals `propagate_with_solar_surface(profile)`; the size of the barycentric lag is
recorded per case under "sun_motion_lag_px". A point is visible at t1 when its surface normal
faces the frame's observer (P . O > |P|^2, Heliocentric frame of the observer at t1); hidden
points keep null frame coordinates.
"""
import argparse
import json
import os
import warnings

import numpy as np
from astropy.utils import iers

iers.conf.auto_download = False

import astropy  # noqa: E402
import astropy.units as u  # noqa: E402
from astropy.coordinates import SkyCoord  # noqa: E402
from astropy.io import fits  # noqa: E402
from astropy.time import Time, TimeDelta  # noqa: E402

import sunpy  # noqa: E402
import sunpy.data.test  # noqa: E402
import sunpy.map  # noqa: E402
from sunpy.coordinates import (  # noqa: E402
    Heliocentric,
    HeliographicStonyhurst,
    RotatedSunFrame,
    get_earth,
    propagate_with_solar_surface,
    sun,
    transform_with_sun_center,
)

SOURCE_HEADER = "aia_171_level1.fits"
DEFAULT_OUT = os.path.join("tests", "data", "solar_rotation", "oracle.json")
DTS_S = [12.0, 600.0, 3600.0, 86400.0]
PROFILES = ["howard", "snodgrass", "allen"]
DIFF_ROT_LATITUDES_DEG = [0.0, 15.0, 30.0, 45.0, 60.0, 75.0]
SIZE = 4096
CDELT_ARCSEC = 0.6
CRPIX = 2048.5
GRID_N = 15
GRID_REACH = 0.98

STRING_KEYS = ["CTYPE1", "CTYPE2", "CUNIT1", "CUNIT2", "DATE-OBS", "T_OBS", "TELESCOP",
               "INSTRUME", "WAVEUNIT"]
NUMBER_KEYS = ["CRVAL1", "CRVAL2", "CROTA2", "PC1_1", "PC1_2", "PC2_1", "PC2_2", "WAVELNTH",
               "HGLN_OBS", "HGLT_OBS", "DSUN_OBS", "CRLN_OBS", "CRLT_OBS", "RSUN_REF",
               "RSUN_OBS"]
TIME_KEYS = ["DATE-OBS", "DATE_OBS", "T_OBS", "DATE-AVG", "DATE-BEG", "DATE-END"]


def real_header():
    path = os.path.join(os.path.dirname(sunpy.data.test.__file__), SOURCE_HEADER)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return fits.getheader(path)


def reference_cards(h):
    """The real header's cards that matter, with the AIA-at-4096 geometry."""
    cards = {"NAXIS": 2, "NAXIS1": SIZE, "NAXIS2": SIZE}
    for key in STRING_KEYS:
        if key in h:
            cards[key] = str(h[key]).strip()
    cards["CUNIT1"] = cards["CUNIT2"] = "arcsec"
    cards["CRPIX1"] = cards["CRPIX2"] = CRPIX
    cards["CDELT1"] = cards["CDELT2"] = CDELT_ARCSEC
    for key in NUMBER_KEYS:
        if key in h:
            cards[key] = h[key] if isinstance(h[key], int) else float(h[key])
    return cards


def parse_card_time(value):
    return Time(value.rstrip("Z"), scale="utc")


def format_card_time(t, like):
    """t in the layout of the card value `like` (same decimals, same trailing Z)."""
    body = like.rstrip("Z")
    decimals = len(body.split(".")[1]) if "." in body else 0
    s = Time(t.utc, precision=decimals).isot
    return s + ("Z" if like.endswith("Z") else "")


def open_map(cards):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        m = sunpy.map.Map(np.zeros((cards["NAXIS2"], cards["NAXIS1"]), dtype=np.uint8), dict(cards))
        _ = m.wcs, m.coordinate_frame
    return m


def frame_cards(ref, t0, dt_s):
    """Reference cards moved on by dt_s seconds: same pointing, observer recomputed."""
    cards = dict(ref)
    delta = TimeDelta(dt_s, format="sec")
    for key in TIME_KEYS:
        if key in cards:
            cards[key] = format_card_time(parse_card_time(cards[key]) + delta, cards[key])
    t1 = t0 + delta
    e0, e1 = get_earth(t0), get_earth(t1)
    cards["HGLN_OBS"] = ref["HGLN_OBS"] + (e1.lon.to_value(u.deg) - e0.lon.to_value(u.deg))
    cards["HGLT_OBS"] = ref["HGLT_OBS"] + (e1.lat.to_value(u.deg) - e0.lat.to_value(u.deg))
    cards["DSUN_OBS"] = ref["DSUN_OBS"] + (e1.radius.to_value(u.m) - e0.radius.to_value(u.m))
    if "CRLN_OBS" in ref:
        dl0 = sun.L0(t1).to_value(u.deg) - sun.L0(t0).to_value(u.deg)
        cards["CRLN_OBS"] = float((ref["CRLN_OBS"] + dl0) % 360.0)
    if "CRLT_OBS" in ref:
        cards["CRLT_OBS"] = cards["HGLT_OBS"]
    if "RSUN_OBS" in ref:
        cards["RSUN_OBS"] = float(np.degrees(np.arcsin(ref["RSUN_REF"] / cards["DSUN_OBS"])) * 3600.0)
    return cards


def reference_points(m):
    """0-based (x, y): disk centre, a grid over the disk, limb and high-latitude points."""
    cx, cy = (float(v) for v in m.wcs.world_to_pixel(
        SkyCoord(0 * u.arcsec, 0 * u.arcsec, frame=m.coordinate_frame)))
    rho = m.rsun_obs.to_value(u.arcsec) / CDELT_ARCSEC
    pts = [(cx, cy), (float(round(cx)), float(round(cy)))]
    steps = np.linspace(-GRID_REACH, GRID_REACH, GRID_N)
    for fy in steps:
        for fx in steps:
            x, y = round(cx + fx * rho), round(cy + fy * rho)
            if np.hypot(x - cx, y - cy) <= GRID_REACH * rho and (float(x), float(y)) not in pts:
                pts.append((float(x), float(y)))
    for frac in (0.99, 0.995):
        for pa_deg in (0.0, 30.0, -30.0):
            for side in (-1.0, 1.0):
                a = np.radians(pa_deg)
                pts.append((cx + side * frac * rho * np.cos(a), cy + frac * rho * np.sin(a)))
    for frac in (0.8, 0.9, 0.95, 0.98, 0.99):
        for side in (-1.0, 1.0):
            pts.append((cx, cy + side * frac * rho))
    for side_y in (-1.0, 1.0):
        for side_x in (-1.0, 1.0):
            pts.append((cx + side_x * 0.3 * rho, cy + side_y * 0.9 * rho))
    return np.array([p[0] for p in pts]), np.array([p[1] for p in pts]), (cx, cy), rho


def rotate(ref_map, frame_map, x0, y0, profile, follow_sun=True):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        c0 = ref_map.wcs.pixel_to_world(x0, y0)
        rotated = SkyCoord(RotatedSunFrame(base=c0, rotated_time=frame_map.reference_date,
                                           rotation_model=profile))
        if follow_sun:
            with transform_with_sun_center():
                c1 = rotated.transform_to(frame_map.coordinate_frame)
                hcc = rotated.transform_to(Heliocentric(observer=frame_map.observer_coordinate,
                                                        obstime=frame_map.reference_date))
        else:
            c1 = rotated.transform_to(frame_map.coordinate_frame)
            hcc = None
        x1, y1 = (np.asarray(v, dtype=float) for v in frame_map.wcs.world_to_pixel(c1))
    if hcc is None:
        return x1, y1, None
    p = hcc.cartesian.xyz.to_value(u.m)
    d = frame_map.observer_coordinate.radius.to_value(u.m)
    visible = (p[2] * d > np.sum(p * p, axis=0)) & np.isfinite(x1) & np.isfinite(y1)
    return x1, y1, visible


def propagate_check(ref_map, frame_map, x0, y0, profile):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        c0 = ref_map.wcs.pixel_to_world(x0, y0)
        with propagate_with_solar_surface(profile):
            c1 = c0.transform_to(frame_map.coordinate_frame)
        return (np.asarray(v, dtype=float) for v in frame_map.wcs.world_to_pixel(c1))


def hgs_frame_drift_deg(t0, t1):
    """Change of HGS longitude of a Sun-centred direction fixed in inertial space, t0 -> t1."""
    p = SkyCoord(0 * u.deg, 0 * u.deg, 1 * u.AU, frame=HeliographicStonyhurst(obstime=t0))
    with transform_with_sun_center():
        q = p.transform_to(HeliographicStonyhurst(obstime=t1))
    return float(q.lon.wrap_at(180 * u.deg).to_value(u.deg))


def diff_rot_table():
    from sunpy.physics.differential_rotation import diff_rot
    lat = np.array(DIFF_ROT_LATITUDES_DEG) * u.deg
    out = {}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        for profile in PROFILES:
            out[profile] = {ft: [float(v) for v in diff_rot(1 * u.day, lat, rot_type=profile,
                                                            frame_time=ft).to_value(u.deg)]
                            for ft in ("sidereal", "synodic")}
    return out


def dump(obj, level=0):
    """JSON with one line per point row and per short list, indented elsewhere."""
    pad, inner = "  " * level, "  " * (level + 1)
    if isinstance(obj, dict):
        if not obj:
            return "{}"
        items = [f"{inner}{json.dumps(k)}: {dump(v, level + 1)}" for k, v in obj.items()]
        return "{\n" + ",\n".join(items) + "\n" + pad + "}"
    if isinstance(obj, list) and obj and isinstance(obj[0], (list, dict)):
        return "[\n" + ",\n".join(inner + dump(v, level + 1) for v in obj) + "\n" + pad + "]"
    return json.dumps(obj, allow_nan=False)


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--out", default=DEFAULT_OUT, help=f"fixture path (default {DEFAULT_OUT})")
    args = ap.parse_args()

    ref_cards = reference_cards(real_header())
    ref_map = open_map(ref_cards)
    t0 = ref_map.reference_date
    x0, y0, centre, rho = reference_points(ref_map)
    print(f"sunpy {sunpy.__version__}, astropy {astropy.__version__}; {SOURCE_HEADER}; "
          f"t0 = {t0.isot} (T_OBS); disk centre ({centre[0]:.4f}, {centre[1]:.4f}) px, "
          f"radius {rho:.3f} px; {len(x0)} points")

    cases = []
    for dt_s in DTS_S:
        fcards = frame_cards(ref_cards, t0, dt_s)
        frame_map = open_map(fcards)
        profiles, lag = {}, {}
        for profile in PROFILES:
            x1, y1, vis = rotate(ref_map, frame_map, x0, y0, profile)
            px, py = propagate_check(ref_map, frame_map, x0, y0, profile)
            agree = float(np.nanmax(np.hypot(px - x1, py - y1)))
            if agree > 1e-6:
                raise SystemExit(f"dt {dt_s}: RotatedSunFrame and propagate_with_solar_surface "
                                 f"differ by {agree} px")
            nx, ny, _ = rotate(ref_map, frame_map, x0, y0, profile, follow_sun=False)
            lag[profile] = float(np.max(np.hypot(nx - x1, ny - y1)[vis]))
            disp = np.hypot(x1 - x0, y1 - y0)
            print(f"dt {dt_s:8.0f} s {profile:9s}: visible {int(vis.sum()):3d}/{len(vis)}, "
                  f"|d| median {np.median(disp[vis]):.6g} px, max {np.max(disp[vis]):.6g} px, "
                  f"centre ({x1[0] - x0[0]:+.6g}, {y1[0] - y0[0]:+.6g}) = {disp[0]:.6g} px; "
                  f"barycentric lag {lag[profile]:.3g} px")
            profiles[profile] = [
                [float(a), float(b), float(c) if v else None, float(d) if v else None, bool(v)]
                for a, b, c, d, v in zip(x0, y0, x1, y1, vis)]
        cases.append({
            "dt_s": dt_s,
            "frame": {"cards": fcards},
            "hgs_frame_drift_deg": hgs_frame_drift_deg(t0, frame_map.reference_date),
            "sun_motion_lag_px": lag,
            "profiles": profiles,
        })

    out = {
        "generator": "tools/solar_rotation_oracle.py",
        "sunpy_version": sunpy.__version__,
        "astropy_version": astropy.__version__,
        "source_header": SOURCE_HEADER,
        "method": ("sunpy.map.Map of each card set; c0 = ref.wcs.pixel_to_world(x, y); "
                   "SkyCoord(RotatedSunFrame(base=c0, rotated_time=frame T_OBS, "
                   "rotation_model=profile)).transform_to(frame.coordinate_frame) under "
                   "transform_with_sun_center(); frame.wcs.world_to_pixel. Pixels 0-based, "
                   "x = FITS axis 1. Frame time = T_OBS (sunpy's AIA reference date). "
                   "visible: surface normal faces the frame's observer."),
        "reference": {"cards": ref_cards, "disk_centre_px": list(centre),
                      "apparent_radius_px": rho},
        "cases": cases,
        "diff_rot_deg_per_day": diff_rot_table(),
        "diff_rot_latitudes_deg": DIFF_ROT_LATITUDES_DEG,
    }
    for profile, table in out["diff_rot_deg_per_day"].items():
        print(f"diff_rot 1 day {profile:9s} sidereal "
              + " ".join(f"{v:.6f}" for v in table["sidereal"])
              + " | synodic " + " ".join(f"{v:.6f}" for v in table["synodic"]))
    for case in cases:
        print(f"dt {case['dt_s']:8.0f} s: HGS frame drift {case['hgs_frame_drift_deg']:+.9f} deg "
              f"({case['hgs_frame_drift_deg'] * 86400.0 / case['dt_s']:+.6f} deg/day)")

    os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
    with open(args.out, "w") as f:
        f.write(dump(out) + "\n")
    print(f"wrote {args.out} ({os.path.getsize(args.out)} bytes)")


if __name__ == "__main__":
    main()
