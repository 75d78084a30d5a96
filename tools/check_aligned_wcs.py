#!/usr/bin/env python3
"""Independent check that aligned products state one WCS, with the roll astropy and sunpy read.

    check_aligned_wcs.py --input REFERENCE.fits PRODUCT.fits...

The products (`align --aligned`, `replay --aligned`, `watch --aligned` on the same reference
grid) must:

  - carry no instrument roll keys (`SC_ROLL`, `CROTAn`) and a `PCi_j` matrix;
  - give every pixel the same helioprojective coordinates (astropy), to 1e-6 arcsec;
  - give the coordinates astropy computes itself from the product's header with the matrix
    removed and `CROTA2` set to the input's roll (its `CROTA2`, or `SC_ROLL` where it has
    none): the FITS convention, applied by astropy, not by sunjitter;
  - be read by sunpy with that roll (`Map.rotation_matrix`), giving the coordinates sunpy
    gives the header with `CROTA2` (sunpy reads `Solar-X` as `HPLN-TAN`, astropy as linear,
    so each tool is compared with itself).

Where the input's roll is not 0, the products' header with roll 0 (what astropy makes of an
input that gives its roll only as `SC_ROLL`) must disagree: the check tells a roll from none.
Prints one line per product and a closing 'N passed, N failed'; exit 1 on any failure.
"""

import argparse
import math
import sys
import warnings

import numpy as np
from astropy.io import fits
from astropy.wcs import WCS, FITSFixedWarning

warnings.simplefilter("ignore", FITSFixedWarning)


def celestial(header):
    """astropy's WCS of axes 1-2. Old solar headers' `Solar-X`/`Solar-Y` (no `CUNIT`) are read
    as sunpy reads them, `HPLN-TAN`/`HPLT-TAN` in arcsec: wcslib honours `CROTA2` only on a
    celestial pair."""
    h = header.copy()
    if str(h.get("CTYPE1", "")).lower().startswith("solar"):
        h["CTYPE1"], h["CTYPE2"] = "HPLN-TAN", "HPLT-TAN"
        h.setdefault("CUNIT1", "arcsec")
        h.setdefault("CUNIT2", "arcsec")
    return WCS(h, naxis=2)


def world(wcs, xy):
    """Coordinates in arcsec of 0-based pixels: helioprojective angles where astropy knows the
    axis type, else the header's own values (arcsec for `Solar-X` without `CUNIT`)."""
    import astropy.units as u

    values = wcs.pixel_to_world_values(xy[:, 0], xy[:, 1])
    out = []
    for i, v in enumerate(values):
        v = np.asarray(v, dtype=float)
        unit = wcs.wcs.cunit[i]
        if str(unit) in ("", "None"):
            out.append(v)
            continue
        v = (v * unit).to_value(u.arcsec)
        if i == 0 and wcs.wcs.lng == 0:
            # Helioprojective longitudes near 360 deg are small negative angles.
            v = (v + 648000.0) % 1296000.0 - 648000.0
        out.append(v)
    return np.column_stack(out)


def input_roll_deg(header):
    for key in ("CROTA2", "CROTA", "SC_ROLL"):
        if key in header:
            return float(header[key])
    return 0.0


def with_crota(header, roll):
    h = header.copy()
    matrix = {f"{m}{i}_{j}" for m in ("PC", "CD") for i in (1, 2) for j in (1, 2)}
    for key in list(h.keys()):
        if key in matrix or key.startswith("CROTA") or key == "SC_ROLL":
            del h[key]
    h["CROTA2"] = roll
    return h


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("products", nargs="+")
    p.add_argument("--input", required=True, help="the reference (chain origin) as read")
    args = p.parse_args()

    source = fits.getheader(args.input)
    roll = input_roll_deg(source)
    shape = (source["NAXIS2"], source["NAXIS1"])
    g = np.linspace(0, 1, 6)
    xy = np.array([(u * (shape[1] - 1), v * (shape[0] - 1)) for u in g for v in g])

    passed = failed = 0

    def verdict(ok, text):
        nonlocal passed, failed
        passed += ok
        failed += not ok
        print(f"{'ok  ' if ok else 'FAIL'} {text}")

    first = None
    for path in args.products:
        h = fits.getheader(path)
        stale = [k for k in ("SC_ROLL", "CROTA", "CROTA1", "CROTA2") if k in h]
        has_pc = all(f"PC{i}_{j}" in h for i in (1, 2) for j in (1, 2))
        verdict(not stale and has_pc, f"{path}: roll keys {stale or 'none'}, PCi_j {'present' if has_pc else 'missing'}")
        coords = world(celestial(h), xy)
        truth = world(celestial(with_crota(h, roll)), xy)
        err = np.abs(coords - truth).max()
        verdict(err < 1e-6, f"{path}: astropy's CROTA2 = {roll:g} reading differs by {err:.2e} arcsec")
        if first is None:
            first = (path, coords)
        else:
            d = np.abs(coords - first[1]).max()
            verdict(d < 1e-6, f"{path}: differs from {first[0]} by {d:.2e} arcsec")
        try:
            import astropy.units as u
            import sunpy.map

            def sunpy_coords(header):
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore")
                    m = sunpy.map.Map(np.zeros(shape), header)
                    c = m.pixel_to_world(xy[:, 0] * u.pix, xy[:, 1] * u.pix)
                return m, np.column_stack([c.Tx.to_value(u.arcsec), c.Ty.to_value(u.arcsec)])

            m, sun = sunpy_coords(h)
            _, sun_truth = sunpy_coords(with_crota(h, roll))
            d = np.abs(sun - sun_truth).max()
            r = m.rotation_matrix
            sunpy_roll = math.degrees(math.atan2(r[1, 0], r[0, 0]))
            dr = abs((sunpy_roll - roll + 180.0) % 360.0 - 180.0)
            verdict(
                d < 1e-6 and dr < 1e-9,
                f"{path}: sunpy roll {sunpy_roll:g} deg, coordinates {d:.2e} arcsec from sunpy's CROTA2 reading",
            )
        except ImportError:
            print(f"skip {path}: sunpy not installed")

    if abs((roll + 180.0) % 360.0 - 180.0) > 1.0 and first is not None:
        unrolled = world(celestial(with_crota(fits.getheader(first[0]), 0.0)), xy)
        d = np.abs(unrolled - first[1]).max()
        verdict(d > 1.0, f"the same header without the roll (as astropy reads {args.input}) differs by {d:.1f} arcsec")
    print(f"{passed} passed, {failed} failed")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
