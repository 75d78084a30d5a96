#!/usr/bin/env python3
"""Turn every *.header file in sunpy's data/test tree into a FITS file sunjitter can read.

Mirrors sunpy.data.test.write_image_file_from_header_file: Header.fromtextfile, data of the
header's NAXISn shape (smooth pattern), dtype from BITPIX, written with do_not_scale_image_data.
Output: $SUNPY_HEADERS_WORK/fits/<relative path with / -> __>.fits ; manifest.json lists them.
"""
import json, os, re, sys, warnings
from pathlib import Path
import numpy as np
warnings.simplefilter("ignore")
import astropy.io.fits as fits
import sunpy
import os

# Where the built FITS files and the JSON results go.
WORK = os.environ.get("SUNPY_HEADERS_WORK", "sunpy_headers_work")
os.makedirs(WORK, exist_ok=True)

ROOT = Path(os.path.dirname(sunpy.__file__)) / "data" / "test"
OUT = Path(WORK, "fits")
OUT.mkdir(parents=True, exist_ok=True)
manifest = []
for hf in sorted(ROOT.rglob("*.header")):
    rel = hf.relative_to(ROOT).as_posix()
    name = rel.replace("/", "__")[: -len(".header")] + ".fits"
    dst = OUT / name
    rec = dict(source=rel, fits=str(dst))
    try:
        h = fits.Header.fromtextfile(hf)
        # commentary cards with tabs etc. cannot be written (lasco_c3): make them printable
        for key in ("HISTORY", "COMMENT"):
            if key in h:
                vals = [str(v) for v in h[key]]
                if any(any(ord(c) < 32 or ord(c) > 126 for c in v) for v in vals):
                    rec["note"] = f"non-printable chars in {key} replaced by spaces"
                    del h[key]
                    for v in vals:
                        h.add_history(re.sub(r"[^\x20-\x7e]", " ", v)) if key == "HISTORY" else h.add_comment(re.sub(r"[^\x20-\x7e]", " ", v))
        naxis = int(h.get("NAXIS", 0))
        shape = [int(h[f"NAXIS{i+1}"]) for i in range(naxis)]
        rec["shape"] = shape
        if naxis == 0:
            rec["error"] = "NAXIS=0"
        # smooth pattern: a Gaussian blob + gradient, scaled into the BITPIX range
        nd = shape[::-1]
        grids = np.meshgrid(*[np.linspace(-1, 1, n) for n in nd], indexing="ij")
        r2 = sum(g * g for g in grids)
        data = 100.0 * np.exp(-2 * r2) + 10.0 * grids[-1]
        bitpix = int(h.get("BITPIX", -32))
        dtype = fits.BITPIX2DTYPE[bitpix]
        if bitpix > 0:
            data = np.clip(np.round(data), 0, None)
        data = data.astype(dtype)
        hdu = fits.PrimaryHDU(data=data, header=h, do_not_scale_image_data=True, scale_back=True)
        hdu.writeto(dst, overwrite=True, output_verify="silentfix")
        # check the written header's BITPIX/NAXIS are what the text header said
        wh = fits.getheader(dst)
        rec["bitpix"] = wh["BITPIX"]
        rec["bitpix_ok"] = wh["BITPIX"] == bitpix and [wh[f"NAXIS{i+1}"] for i in range(wh["NAXIS"])] == shape
    except Exception as e:  # record, keep going
        rec["error"] = f"{type(e).__name__}: {e}"
    manifest.append(rec)
    print(rec)
json.dump(manifest, open(os.path.join(WORK, "manifest.json"), "w"), indent=1)

# gunzipped copies of the gzip-compressed test images (sunjitter does not read gzip; see report)
import gzip, shutil
for p in sorted(list(ROOT.rglob("*.gz"))):
    dst = OUT / ("gunzip__" + p.name[:-3].replace(".fit", ".fits").replace(".fitss", ".fits").replace(".fts", ".fits"))
    with gzip.open(p) as src, open(dst, "wb") as o:
        shutil.copyfileobj(src, o)
    print("gunzipped", p.name, "->", dst.name)
