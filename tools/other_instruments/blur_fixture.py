#!/usr/bin/env python3
"""The blurred-frame fixture of tests/engine_blur.rs: the central 256² of the bundled TRACE image
(hot pixels cleaned as in noise_limits.py, CRPIX shifted) as the reference, and as the frame
the same moved by a known similarity (scipy quintic spline) and then blurred by a 0.8 px
Gaussian (scipy.ndimage.gaussian_filter), as seeing or defocus would.

    python3 tools/other_instruments/blur_fixture.py tests/data/trace_blurred_pair
"""
import json, os, sys
import numpy as np
from astropy.io import fits
from scipy import ndimage
sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), '..'))
from noise_limits import remove_hot_pixels  # noqa: E402

out = sys.argv[1]
root = os.path.join(os.path.dirname(os.path.abspath(__file__)), '..', '..')
hdu = fits.open(os.path.join(root, 'data/real/trace_171_19980519T222143_1024.fits'))[0]
hdr = hdu.header.copy()
ref = remove_hot_pixels(hdu.data.astype(float))[0][384:640, 384:640]
hdr['CRPIX1'] -= 384
hdr['CRPIX2'] -= 384
h, w = ref.shape
c = ((w - 1) / 2, (h - 1) / 2)
s, th, dx, dy, blur = 1.003, 0.006, 2.37, -1.61, 0.8
yy, xx = np.mgrid[0:h, 0:w].astype(float)
X, Y = xx - c[0] - dx, yy - c[1] - dy
ct, st = np.cos(th), np.sin(th)
coef = ndimage.spline_filter(ref, order=5, mode='mirror')
frame = ndimage.map_coordinates(coef, [(-st * X + ct * Y) / s + c[1], (ct * X + st * Y) / s + c[0]],
                                order=5, mode='mirror', prefilter=False)
frame = ndimage.gaussian_filter(frame, blur)
os.makedirs(out, exist_ok=True)
fits.PrimaryHDU(ref.astype(np.float32), hdr).writeto(f'{out}/ref.fits', overwrite=True)
fits.PrimaryHDU(frame.astype(np.float32), hdr).writeto(f'{out}/frame.fits', overwrite=True)
json.dump({'scale': s, 'rotation_arcsec': th * 180 / np.pi * 3600, 'dx_px': dx, 'dy_px': dy,
           'blur_sigma_px': blur}, open(f'{out}/truth.json', 'w'), indent=1)
