#!/usr/bin/env python3
"""Band-limited sub-pixel shifts of a real image through `sunjitter align`.

usage: fourier_shifts.py IMAGE.fits [extra align arguments]

For each shift (dx, dy) in a fixed list, the frame is the image moved by the Fourier shift
theorem (numpy FFT of the image padded by whole-sample reflection to twice its size: the
shift a telescope's pointing makes of a well-sampled image), and, for comparison, by scipy's
cubic and quintic splines (`ndimage.shift`, mode 'mirror'). Prints the error of the answer
against the injected shift and the reported σ. Environment: SUNJITTER (binary; default
target/release/sunjitter).
"""
import json
import os
import subprocess
import sys
import tempfile

import numpy as np
from astropy.io import fits
from scipy import ndimage

BIN = os.environ.get('SUNJITTER', 'target/release/sunjitter')
SHIFTS = [(0.25, 0.0), (1.5, 0.1), (0.05, 0.0), (0.1, 0.45), (3.7, -2.2)]


def fourier_shift(a, dx, dy):
    h, w = a.shape
    p = np.pad(a, ((h // 2, h // 2), (w // 2, w // 2)), mode='symmetric')
    ky = np.fft.fftfreq(p.shape[0])[:, None]
    kx = np.fft.fftfreq(p.shape[1])[None, :]
    out = np.real(np.fft.ifft2(np.fft.fft2(p) * np.exp(-2j * np.pi * (kx * dx + ky * dy))))
    return out[h // 2:h // 2 + h, w // 2:w // 2 + w]


def main():
    img = sys.argv[1]
    hdr = fits.getheader(img)
    ref = fits.getdata(img).astype(float)
    tmp = tempfile.mkdtemp(prefix='sunjitter_fshift_')
    rp, fp = f'{tmp}/ref.fits', f'{tmp}/frame.fits'
    fits.PrimaryHDU(ref.astype(np.float32), hdr).writeto(rp, overwrite=True)
    print(f'{"dx":>5s} {"dy":>5s} {"frame":8s} {"status":8s} {"err dx":>10s} {"err dy":>10s} '
          f'{"σ dx":>8s} {"σ dy":>8s} {"|err|/σ":>8s}')
    for dx, dy in SHIFTS:
        frames = {'fourier': fourier_shift(ref, dx, dy)}
        for order in (3, 5):
            frames[f'spline{order}'] = ndimage.shift(ref, (dy, dx), order=order, mode='mirror')
        for name, frame in frames.items():
            fits.PrimaryHDU(frame.astype(np.float32), hdr).writeto(fp, overwrite=True)
            run = subprocess.run([BIN, 'align', rp, fp, '--json'] + sys.argv[2:],
                                 capture_output=True, text=True)
            o = json.loads(run.stdout)
            ex, ey = o['dx_px'] - dx, o['dy_px'] - dy
            sx, sy = o['sigma_dx_px'], o['sigma_dy_px']
            z = max(abs(ex) / sx, abs(ey) / sy)
            print(f'{dx:5.2f} {dy:5.2f} {name:8s} {o["status"]:8s} {ex:10.2e} {ey:10.2e} '
                  f'{sx:8.1e} {sy:8.1e} {z:8.2f}', flush=True)


if __name__ == '__main__':
    main()
