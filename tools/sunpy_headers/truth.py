#!/usr/bin/env python3
"""sunpy truths for every file in manifest.json + the real .fits/.fts/.fits.gz images.

Same recipe as tools/sunpy_truth.py: sunpy.map.Map(file) read from disk (so sunpy's
io fixes apply), sun centre = m.wcs.world_to_pixel(SkyCoord(0",0", frame=m.coordinate_frame)),
roll = atan2(vx, vy) of pixel(CRVAL + 1" north) - pixel(CRVAL), time = m.reference_date.utc,
rsun = m.rsun_obs, scale = m.scale, exposure = m.exposure_time, wavelength = m.wavelength.
3-D files: sunpy.map.Map of each 2-D slice with the same header (NAXIS3 dropped).
For non-helioprojective maps also the pixel of HPC (0",0") transformed via the observer.
Writes truth.json.
"""
import json, os, sys, warnings, traceback
from pathlib import Path
import numpy as np
warnings.simplefilter("ignore")
import astropy.units as u
from astropy.coordinates import SkyCoord
from astropy.io import fits
import sunpy, sunpy.map
from sunpy.coordinates import Helioprojective
import logging
import os

# Where the built FITS files and the JSON results go.
WORK = os.environ.get("SUNPY_HEADERS_WORK", "sunpy_headers_work")
os.makedirs(WORK, exist_ok=True)
logging.getLogger("sunpy").setLevel(logging.ERROR)
sunpy.log.setLevel("ERROR")

ROOT = Path(os.path.dirname(sunpy.__file__)) / "data" / "test"


def hpc_center(m):
    c = m.wcs.world_to_pixel(SkyCoord(0 * u.arcsec, 0 * u.arcsec, frame=m.coordinate_frame))
    return [float(c[0]), float(c[1])]


def roll(m):
    f = m.coordinate_frame
    ref = m.reference_coordinate
    lon, lat = ref.spherical.lon, ref.spherical.lat
    p0 = np.array(m.wcs.world_to_pixel(SkyCoord(lon, lat, frame=f)), float)
    p1 = np.array(m.wcs.world_to_pixel(SkyCoord(lon, lat + 1 * u.arcsec, frame=f)), float)
    v = p1 - p0
    return float(np.degrees(np.arctan2(v[0], v[1])))


def truth_for_map(m, hdr):
    t = {}
    t["map_class"] = type(m).__name__
    t["instrument"] = m.instrument
    t["detector"] = m.detector
    t["nickname"] = m.nickname
    t["observatory"] = m.observatory
    w = m.wavelength
    t["wavelength"] = None if w is None else (float(w.value) if np.ndim(w.value) == 0 else np.asarray(w.value).tolist())
    t["waveunit"] = None if w is None else str(w.unit)
    t["coord_frame"] = type(m.coordinate_frame).__name__
    t["ctype"] = list(m.coordinate_system)
    for k, f in [("sun_center_px", lambda: hpc_center(m)), ("rotation_deg", lambda: roll(m))]:
        try:
            t[k] = f()
        except Exception as e:
            t[k + "_err"] = f"{type(e).__name__}: {e}"
    if t["coord_frame"] != "Helioprojective":
        try:
            obs = m.observer_coordinate
            c = SkyCoord(0 * u.arcsec, 0 * u.arcsec, frame=Helioprojective(observer=obs, obstime=m.reference_date))
            cc = c.transform_to(m.coordinate_frame)
            p = m.wcs.world_to_pixel(cc)
            t["sun_center_px_via_observer"] = [float(p[0]), float(p[1])]
        except Exception as e:
            t["sun_center_px_via_observer_err"] = f"{type(e).__name__}: {e}"
    try:
        t["plate_scale_arcsec"] = [float(m.scale.axis1.to_value(u.arcsec / u.pix)), float(m.scale.axis2.to_value(u.arcsec / u.pix))]
    except Exception as e:
        t["plate_scale_err"] = str(e)
    try:
        t["obs_time"] = m.reference_date.utc.isot + "Z"
    except Exception as e:
        t["obs_time_err"] = str(e)
    try:
        t["date"] = m.date.utc.isot + "Z"
    except Exception as e:
        t["date_err"] = str(e)
    e = m.exposure_time
    t["exptime_s"] = None if e is None else float(e.to_value(u.s))
    try:
        t["rsun_arcsec"] = float(m.rsun_obs.to_value(u.arcsec))
    except Exception as ex:
        t["rsun_err"] = str(ex)
    keys = {k.upper() for k in m.meta}
    t["rsun_given"] = bool(keys & {"RSUN_OBS", "SOLAR_R", "RADIUS", "RSUN_ARC", "RSUN"}) or {"RSUN_REF", "DSUN_OBS"} <= keys or type(m).__name__ in ("GONGHalphaMap",)
    return t


def truth_for_file(path):
    out = []
    with fits.open(path) as hl:
        for i, hdu in enumerate(hl):
            if hdu.data is None or getattr(hdu, "is_image", False) is False or hdu.data.ndim < 2:
                continue
            hdr = hdu.header
            data = hdu.data
            if data.ndim == 2:
                slices = [(None, data)]
            else:
                flat = data.reshape((-1,) + data.shape[-2:])
                slices = list(enumerate(flat))
            for fr, d in slices:
                rec = dict(hdu=i, frame=fr)
                try:
                    if fr is None and i == 0:
                        m = sunpy.map.Map(path)
                        if isinstance(m, list):
                            m = m[0]
                    else:
                        h2 = hdr.copy()
                        for k in list(h2.keys()):
                            pass
                        h2["NAXIS"] = 2
                        for k in ("NAXIS3", "NAXIS4"):
                            h2.pop(k, None)
                        m = sunpy.map.Map(np.asarray(d), h2)
                    rec.update(truth_for_map(m, hdr))
                except Exception as e:
                    rec["map_error"] = f"{type(e).__name__}: {e}".splitlines()[0]
                    if "coordinate units" in str(e) and "CRPIX1" in hdr:
                        # retry with CUNIT = arcsec added (what sunjitter assumes for a missing CUNIT)
                        h2 = hdr.copy()
                        h2["NAXIS"] = 2
                        h2.pop("NAXIS3", None)
                        h2.setdefault("CUNIT1", "arcsec"); h2.setdefault("CUNIT2", "arcsec")
                        try:
                            m = sunpy.map.Map(np.asarray(d), h2)
                            rec.update(truth_for_map(m, hdr))
                            rec["note"] = "sunpy needed CUNIT1/2='arcsec' added; " + rec.pop("map_error")
                        except Exception as e2:
                            rec["map_error"] += f" | retry with CUNIT arcsec: {type(e2).__name__}: {e2}".splitlines()[0]
                out.append(rec)
    return out


def main():
    manifest = json.load(open(os.path.join(WORK, "manifest.json")))
    files = [(r["source"], r["fits"]) for r in manifest if "error" not in r]
    for ext in ("*.fits", "*.fts", "*.fits.gz", "*.fit.gz", "*.fts.gz"):
        for p in sorted(ROOT.rglob(ext)):
            files.append((p.relative_to(ROOT).as_posix(), str(p)))
    # gunzipped copies of the .gz files (made by build.py), so sunjitter can be checked on them too
    for p in sorted(Path(WORK, "fits").glob("gunzip__*")):
        files.append((p.name, str(p)))
    res = {}
    for src, f in files:
        try:
            res[f] = dict(source=src, frames=truth_for_file(f))
        except Exception as e:
            res[f] = dict(source=src, error=f"{type(e).__name__}: {e}".splitlines()[0])
        print(src, json.dumps(res[f])[:300], flush=True)
    json.dump(res, open(os.path.join(WORK, "truth.json"), "w"), indent=1)


if __name__ == "__main__":
    main()
