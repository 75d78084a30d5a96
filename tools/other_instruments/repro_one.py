#!/usr/bin/env python3
"""Regenerate trial T of truth_pairs.py (IMAGE N SEED K) into DIR/ref.fits, DIR/frame.fits; print truth."""
import sys, numpy as np
sys.argv_saved = sys.argv
from truth_pairs import warp, background_sigma, ARCSEC
from astropy.io import fits
img, seed, k, T, d = sys.argv[1], int(sys.argv[2]), float(sys.argv[3]), int(sys.argv[4]), sys.argv[5]
import os; os.makedirs(d, exist_ok=True)
rng = np.random.default_rng(seed)
with fits.open(img) as hl:
    hdr = hl[0].header.copy(); ref = hl[0].data.astype(np.float64)
bg = background_sigma(ref)
for t in range(T + 1):
    s = rng.uniform(0.995, 1.005); th = rng.uniform(-0.01, 0.01); dx, dy = rng.uniform(-5, 5, 2)
    fr = warp(ref, s, th, dx, dy, t % 2 == 1)
    r = ref.copy()
    if k > 0:
        r = r + rng.normal(0, k * bg, r.shape); fr = fr + rng.normal(0, k * bg, fr.shape)
fits.PrimaryHDU(r.astype(np.float32), hdr).writeto(f'{d}/ref.fits', overwrite=True)
fits.PrimaryHDU(fr.astype(np.float32), hdr).writeto(f'{d}/frame.fits', overwrite=True)
print(dict(scale=s, rotation_arcsec=th * ARCSEC, dx_px=dx, dy_px=dy))
