#!/usr/bin/env python3
"""Known-truth pairs between channels, aligned by `sunjitter align`: how far off, in σ.

Each frame is the image moved by a random similarity (scale 0.995–1.005, rotation ±0.01 rad,
shift ±3 px; scipy's `map_coordinates`, order 3 unless ORDER is set) or, with `--fourier`,
shifted only, by a phase ramp (band-limited). Its header says another wavelength
(WAVELNTH = 999), so the engine treats the pair as two channels and the flow's answer is
final. `--limb-gain G` multiplies the frame by 1 + G·exp(−((r/R − 1)/0.06)²) about the moved
disk (R from RSUN_OBS or RSUN and CDELT1): another channel's brighter limb.

    python3 tools/cross_channel_pairs.py IMAGE N SEED [--fourier] [--limb-gain G]
        [--binary target/release/sunjitter] [--config F.toml] [--keep DIR]

Prints per pair the error over σ (scale, rotation, dx, dy), then the RMSE, the bias, the RMS
of error/σ and its largest absolute value.
"""
import argparse
import json
import os
import subprocess
import sys
import tempfile

import numpy as np
from astropy.io import fits
from scipy import ndimage

ARCSEC_PER_RAD = 206264.80624709636


def moved(img, s, th, dx, dy, order):
    h, w = img.shape
    c = ((w - 1) / 2, (h - 1) / 2)
    yy, xx = np.indices((h, w), dtype=float)
    px, py = xx - c[0] - dx, yy - c[1] - dy
    ct, st = np.cos(th), np.sin(th)
    # p_frame = s R (p_ref - c) + c + d, so p_ref = R⁻¹ (p_frame - c - d) / s + c.
    rx = (ct * px + st * py) / s + c[0]
    ry = (-st * px + ct * py) / s + c[1]
    return ndimage.map_coordinates(img, [ry, rx], order=order, mode="nearest")


def shifted(img, dx, dy):
    h, w = img.shape
    ky = np.fft.fftfreq(h)[:, None]
    kx = np.fft.fftfreq(w)[None, :]
    mean = img.mean()
    f = np.fft.fft2(img - mean) * np.exp(-2j * np.pi * (kx * dx + ky * dy))
    return np.fft.ifft2(f).real + mean


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("image")
    ap.add_argument("n", type=int)
    ap.add_argument("seed", type=int)
    ap.add_argument("--fourier", action="store_true")
    ap.add_argument("--limb-gain", type=float, default=0.0)
    ap.add_argument("--binary", default="target/release/sunjitter")
    # Random similarities are what is measured: the similarity is always fitted.
    ap.add_argument("--config", default=os.path.join(os.path.dirname(os.path.abspath(__file__)),
                                                     "similarity.toml"))
    ap.add_argument("--keep")
    a = ap.parse_args()

    hdul = fits.open(a.image)
    img = hdul[0].data.astype(float)
    hdr = hdul[0].header
    h, w = img.shape
    c = ((w - 1) / 2, (h - 1) / 2)
    order = int(os.environ.get("ORDER", "3"))
    rng = np.random.default_rng(a.seed)
    out = a.keep or tempfile.mkdtemp(prefix="cross_channel_")
    os.makedirs(out, exist_ok=True)
    z, err = [], []
    for i in range(a.n):
        if a.fourier:
            s, th = 1.0, 0.0
            dx, dy = rng.uniform(-3, 3, 2)
            frame = shifted(img, dx, dy)
        else:
            s, th = rng.uniform(0.995, 1.005), rng.uniform(-0.01, 0.01)
            dx, dy = rng.uniform(-3, 3, 2)
            frame = moved(img, s, th, dx, dy, order)
        if a.limb_gain:
            rsun = hdr.get("RSUN_OBS", hdr.get("RSUN"))
            radius = rsun / abs(hdr["CDELT1"])
            sun = (hdr["CRPIX1"] - 1 - hdr["CRVAL1"] / hdr["CDELT1"],
                   hdr["CRPIX2"] - 1 - hdr["CRVAL2"] / hdr["CDELT2"])
            ct, st = np.cos(th), np.sin(th)
            qx = s * (ct * (sun[0] - c[0]) - st * (sun[1] - c[1])) + c[0] + dx
            qy = s * (st * (sun[0] - c[0]) + ct * (sun[1] - c[1])) + c[1] + dy
            yy, xx = np.indices((h, w), dtype=float)
            r = np.hypot(xx - qx, yy - qy) / (radius * s)
            frame = frame * (1 + a.limb_gain * np.exp(-((r - 1.0) / 0.06) ** 2))
        other = hdr.copy()
        other["WAVELNTH"] = 999
        path = os.path.join(out, f"frame_{i}.fits")
        fits.writeto(path, frame.astype(np.float32), other, overwrite=True)
        cmd = [a.binary, "align", a.image, path, "--json"] + (["--config", a.config] if a.config else [])
        r = json.loads(subprocess.run(cmd, capture_output=True, text=True).stdout)
        truth = np.array([s, th * ARCSEC_PER_RAD, dx, dy])
        if r["status"] == "failed":
            print(i, "failed:", r["message"])
            continue
        est = np.array([r["scale"], r["rotation_arcsec"], r["dx_px"], r["dy_px"]])
        sig = np.array([r["sigma_scale"], r["sigma_rotation_arcsec"], r["sigma_dx_px"], r["sigma_dy_px"]])
        e = est - truth
        z.append(e / sig)
        err.append(e)
        print(i, r["status"], " ".join(f"{v:+.2f}" for v in e / sig))
    if not z:
        sys.exit("no pair aligned")
    z, err = np.array(z), np.array(err)
    fmt = lambda v: " / ".join(f"{x:.3g}" for x in v)  # noqa: E731
    print("RMSE (scale / rotation ″ / dx / dy px):", fmt(np.sqrt((err**2).mean(0))))
    print("bias:", fmt(err.mean(0)))
    print("RMS of error/σ:", fmt(np.sqrt((z**2).mean(0))), "  largest |error|/σ:", fmt(np.abs(z).max(0)))


if __name__ == "__main__":
    main()
