#!/usr/bin/env python3
"""Truth values for sunjitter's `info` tests, computed independently with sunpy/astropy.

Run from the repository root:  python3 tools/sunpy_truth.py  [--slit-check]
(needs sunpy 7 with its `map` extras: matplotlib, mpl-animators, reproject).
The printed numbers are hard-coded in tests/info.rs; this script is the record of how.

How each value is obtained
--------------------------
* 2-D images (AIA, EIT, HMI, TRACE) are opened with `sunpy.map.Map`:
  - sun centre: `m.wcs.world_to_pixel(SkyCoord(0", 0", frame=m.coordinate_frame))`
    (full TAN projection, 0-based pixels);
  - plate scale: `m.scale` (arcsec/pixel);
  - roll: direction of solar north in pixel space from the WCS,
    `atan2(vx, vy)` with v = pixel(CRVAL + 1" north) - pixel(CRVAL); this is the CROTA2 sense.
    EXCEPTION EIT: sunpy ignores SC_ROLL (raw SOHO files carry no CROTA); the truth for roll there
    is SC_ROLL from the FITS header itself (180 deg, SOHO flew rolled in 2004).
  - time: `m.reference_date` in UTC. For AIA and HMI sunpy uses T_OBS (mid-exposure; HMI's T_OBS is
    in TAI: '2014.03.01_00:01:25_TAI' -> 00:00:50 UTC, 22 s after DATE-OBS 00:00:27.90, which is the
    start of the first of the filtergrams combined into the observable). sunjitter reports T_OBS too.
    EIT/TRACE: DATE-OBS / DATE_OBS (start of exposure; no T_OBS).
  - rsun: `m.rsun_obs` where the header gives it (RSUN_OBS; EIT: SOLAR_R * CDELT1, the values sunpy
    reads too). TRACE gives no radius: sunpy falls back on a standard radius, sunjitter reports null.
  - exposure: `m.exposure_time`; TRACE has no EXPTIME (sunpy: None) -> header SHT_MDUR (measured
    shutter duration); HMI has none -> null.
* IRIS SJI cubes (sunpy.map does not open 3-D cubes) with astropy:
  - sun centre / roll / scale: `astropy.wcs.WCS(primary header).celestial`, same formulas as above;
  - per-frame time: irispy's rule `Time(STARTOBS) + TIME column of HDU 1` (column index = header
    key TIME).  The trimmed test files have R table rows for n frames (540/54, 720/72): the cubes
    were resampled along time (frame i = table position p = i*(R-1)/(n-1), blended between rows).
    Evidence: the slit's column in each frame follows SLTPX1IX at row round(p), and where p is
    between rows the slit shows at both rows' positions with weights (1-frac, frac); run with
    --slit-check to print the match rate (2796: 86 % exact for p-mapping vs <= 32 % for i->i or
    i->10i). So the truth time is STARTOBS + interp(p, rows, TIME); exposure likewise from EXPTIMES.
"""
import sys
import warnings

import numpy as np

warnings.simplefilter("ignore")
import astropy.units as u  # noqa: E402
from astropy.coordinates import SkyCoord  # noqa: E402
from astropy.io import fits  # noqa: E402
from astropy.time import Time, TimeDelta  # noqa: E402
from astropy.wcs import WCS  # noqa: E402

REAL = "data/real/"
IMAGES = [
    "aia_171_20110215T000000_128.fits",
    "eit_171_20040301T010016_128.fits",
    "eit_195_20040301T000010_128.fits",
    "hmi_6173_20140301T000027_100.fits",
    "trace_171_19980519T222143_1024.fits",
]
CUBES = [
    ("iris_l2_20140329_140938_3860258481_SJI_1400_t000.fits", [0, 1, 27, 53]),
    ("iris_l2_20140329_140938_3860258481_SJI_2796_t000_deconvolved.fits", [0, 35, 71]),
    ("iris_l2_20140329_140938_3860258481_SJI_2832_t000.fits", [0, 17]),
]


def roll_from_wcs(wcs2d):
    """Roll in the CROTA2 sense: angle of solar north in pixel space, from the WCS itself."""
    lon0, lat0 = wcs2d.wcs.crval  # degrees inside astropy
    p0 = np.array(wcs2d.wcs_world2pix([[lon0, lat0]], 0)[0])
    p1 = np.array(wcs2d.wcs_world2pix([[lon0, lat0 + 1.0 / 3600]], 0)[0])
    v = p1 - p0
    return np.degrees(np.arctan2(v[0], v[1]))


def image_truth(name):
    import sunpy.map

    m = sunpy.map.Map(REAL + name)
    hdr = fits.getheader(REAL + name)
    c = m.wcs.world_to_pixel(SkyCoord(0 * u.arcsec, 0 * u.arcsec, frame=m.coordinate_frame))
    roll = roll_from_wcs(m.wcs)
    if "SC_ROLL" in hdr and "CROTA2" not in hdr and "PC1_1" not in hdr:
        roll = hdr["SC_ROLL"]  # EIT: sunpy ignores it; the header is the truth
    exp = m.exposure_time.to_value(u.s) if m.exposure_time is not None else hdr.get("SHT_MDUR")
    has_rsun = any(k in hdr for k in ("RSUN_OBS", "SOLAR_R")) or (
        "RSUN_REF" in hdr and "DSUN_OBS" in hdr
    )
    return dict(
        file=name,
        frame=None,
        sun_center_px=(float(c[0]), float(c[1])),
        plate_scale=(m.scale.axis1.to_value(u.arcsec / u.pix), m.scale.axis2.to_value(u.arcsec / u.pix)),
        rotation_deg=float(roll),
        obs_time=m.reference_date.utc.isot + "Z",
        exptime_s=exp,
        rsun_arcsec=m.rsun_obs.to_value(u.arcsec) if has_rsun else None,
        wavelength=m.wavelength.value if m.wavelength is not None else float(hdr["WAVE_LEN"]),
    )


def frame_positions(n, rows):
    """Table position of each frame: identity when the table matches, else resampled."""
    if rows == n or n == 1:
        return np.arange(n, dtype=float)
    return np.arange(n) * (rows - 1) / (n - 1)


def cube_truth(name, frames):
    with fits.open(REAL + name) as h:
        hdr = h[0].header
        w = WCS(hdr).celestial
        c = w.wcs_world2pix([[0.0, 0.0]], 0)[0]
        aux, ah = h[1].data, h[1].header
        n, rows = hdr["NAXIS3"], aux.shape[0]
        p = frame_positions(n, rows)
        t = np.interp(p, np.arange(rows), aux[:, ah["TIME"]])
        e = np.interp(p, np.arange(rows), aux[:, ah["EXPTIMES"]])
        start = Time(hdr["STARTOBS"], scale="utc")
        out = []
        for i in frames:
            out.append(
                dict(
                    file=name,
                    frame=i,
                    sun_center_px=(float(c[0]), float(c[1])),
                    plate_scale=tuple(np.array(w.wcs.cdelt) * 3600.0),
                    rotation_deg=float(roll_from_wcs(w)),
                    obs_time=(start + TimeDelta(t[i], format="sec")).utc.isot + "Z",
                    exptime_s=float(e[i]),
                    rsun_arcsec=None,
                    wavelength=hdr["TWAVE1"],
                )
            )
        return out


def slit_check(name):
    """Where is the slit (dark column) in each frame, versus SLTPX1IX at the mapped table row?"""
    with fits.open(REAL + name) as h:
        d, aux, ah = h[0].data.astype(float), h[1].data, h[1].header
        n, rows = d.shape[0], aux.shape[0]
        sx = aux[:, ah["SLTPX1IX"]] / 10.0  # cube was rebinned 10x in space too
        meas = []
        for f in d:
            prof = np.nanmedian(f[10:100], axis=0)
            dip = prof - 0.5 * (np.roll(prof, 2) + np.roll(prof, -2))
            meas.append(np.argmin(dip[45:65]) + 45)
        meas = np.array(meas)
        for label, idx in [
            ("frame i -> row i", np.arange(n)),
            ("frame i -> row 10 i", np.minimum(np.arange(n) * 10, rows - 1)),
            ("frame i -> row round(i(R-1)/(n-1))", np.round(frame_positions(n, rows)).astype(int)),
        ]:
            best = max((np.abs(meas - (sx[idx] + o)) < 1.0).mean() for o in np.arange(-3, 3.01, 0.1))
            print(f"  {name[-40:]}: {label}: {best:.0%} of frames match")


def main():
    if "--slit-check" in sys.argv:
        for name, _ in CUBES[:2]:
            slit_check(name)
        return
    rows = [image_truth(n) for n in IMAGES]
    for name, frames in CUBES:
        rows.extend(cube_truth(name, frames))
    for r in rows:
        print(r)


if __name__ == "__main__":
    main()
