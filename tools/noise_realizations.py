#!/usr/bin/env python3
"""One known transform, many noise realisations: the spread of the refinement's answer against
the σ it reports, and against its cluster covariance alone.

usage: noise_realizations.py IMAGE N K [ORDER]

The frame is the image (hot pixels cleaned with the engine's rule) moved by a fixed similarity
(scale 1.002, rotation 0.004 rad, dx 1.37, dy −2.61 px; scipy `map_coordinates`, spline ORDER,
default 5); each realisation adds independent Gaussian noise of K × the background σ to both
and runs `sunjitter align` (env SUNJITTER: the binary; XARGS: extra arguments). The
refinement's own answer and its cluster covariance come from its debug line
(`SUNJITTER_LOG=sunjitter::engine::refine=debug`), so this also shows how much of the reported σ
is the cluster covariance and how much the self-test floor and interpolation check.

    python3 tools/noise_realizations.py data/real/aia_171_20110215T000000_128.fits 80 3
"""
import json
import os
import re
import subprocess
import sys
import tempfile

import numpy as np
from astropy.io import fits
from scipy import ndimage

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), 'other_instruments'))
from noise_limits import remove_hot_pixels  # noqa: E402
from truth_pairs import background_sigma  # noqa: E402

BIN = os.environ.get('SUNJITTER', 'target/release/sunjitter')
ANSI = re.compile(r'\x1b\[[0-9;]*m')


def main():
    img, n, k = sys.argv[1], int(sys.argv[2]), float(sys.argv[3])
    order = int(sys.argv[4]) if len(sys.argv) > 4 else 5
    with fits.open(img) as hl:
        hdr = hl[0].header.copy()
        ref = remove_hot_pixels(hl[0].data.astype(np.float64))[0]
    h, w = ref.shape
    c = ((w - 1) / 2, (h - 1) / 2)
    truth = np.array([1.002, 0.004, 1.37, -2.61])  # scale, rotation rad, dx, dy
    s, th, dx, dy = truth
    yy, xx = np.mgrid[0:h, 0:w].astype(float)
    px, py = xx - c[0] - dx, yy - c[1] - dy
    ct, st = np.cos(-th) / s, np.sin(-th) / s
    frame = ndimage.map_coordinates(ref, [st * px + ct * py + c[1], ct * px - st * py + c[0]],
                                    order=order, mode='nearest')
    sigma = k * background_sigma(ref)
    rng = np.random.default_rng(1)
    tmp = tempfile.mkdtemp(prefix='sunjitter_realizations_')
    rp, fp = f'{tmp}/ref.fits', f'{tmp}/frame.fits'
    refined, cluster, reported = [], [], []
    for _ in range(n):
        fits.PrimaryHDU((ref + rng.normal(0, sigma, ref.shape)).astype(np.float32),
                        hdr).writeto(rp, overwrite=True)
        fits.PrimaryHDU((frame + rng.normal(0, sigma, ref.shape)).astype(np.float32),
                        hdr).writeto(fp, overwrite=True)
        p = subprocess.run([BIN, 'align', rp, fp, '--json', '--config', os.path.join(os.path.dirname(os.path.abspath(__file__)), 'similarity.toml')]
                           + os.environ.get('XARGS', '').split(),
                           capture_output=True, text=True,
                           env=dict(os.environ, SUNJITTER_LOG='sunjitter::engine::refine=debug'))
        doc = json.loads(p.stdout)
        lines = [ln for ln in ANSI.sub('', p.stderr).splitlines()
                 if 'intensity refinement' in ln and 'refined=' in ln]
        if doc['status'] == 'failed' or not lines:
            print('skipped:', doc['status'], doc['message'][:120])
            continue
        field = lambda key: json.loads(re.search(key + r'=(\[[^\]]*\])', lines[-1]).group(1))  # noqa: E731
        refined.append(field('refined'))
        cluster.append(field('robust_sigma'))
        reported.append([doc['sigma_scale'], doc['sigma_rotation_arcsec'] / 206264.80624709636,
                         doc['sigma_dx_px'], doc['sigma_dy_px']])
    err = np.array(refined) - truth
    rms = lambda a: np.sqrt((np.array(a) ** 2).mean(0))  # noqa: E731
    cl, rep = rms(cluster), rms(reported)
    print(f'{img}: {len(err)} realisations, noise {k}× background, frames spline order {order}')
    print('param  bias       spread     cluster σ (spread/σ)   reported σ (spread/σ)  within 1σ')
    for i, name in enumerate(['scale', 'rot rad', 'dx px', 'dy px']):
        e = err[:, i]
        within = np.mean(np.abs(e) <= np.array(reported)[:, i])
        print(f'{name:7s}{e.mean():<11.3g}{e.std():<11.3g}{cl[i]:<10.3g}({e.std() / cl[i]:.2f})'
              f'        {rep[i]:<10.3g}({e.std() / rep[i]:.2f})       {within:.2f}')


if __name__ == '__main__':
    main()
