#!/usr/bin/env python3
"""Known-truth pairs for sunjitter align.

usage: truth_pairs.py IMAGE.fits N SEED NOISE_K OUT.jsonl [--keep DIR]

frame(p) = ref(T^-1(p)),  T(p) = s R(th) (p - c) + c + (dx, dy),
c = ((W-1)/2, (H-1)/2), R counter-clockwise in (x = column right, y = row up).
scipy.ndimage.map_coordinates order=5 (env WARP_ORDER: another order) with prefilter. Even trials mode='nearest',
odd trials NaN outside the reference's support. NaN pixels of the input are filled
(nearest valid) before the spline and re-masked after.
NOISE_K > 0: independent Gaussian noise of K x background sigma added to BOTH images.
Background sigma: 16x16 blocks, RMS residual from a fitted quadratic, 10th percentile
(blocks with NaN or constant excluded).
"""
import sys, os, json, subprocess, tempfile, time
import numpy as np
from scipy import ndimage
from astropy.io import fits

BIN = os.environ.get('SUNJITTER', 'target/release/sunjitter')
ARCSEC = 180 / np.pi * 3600


def background_sigma(a, b=16):
    H, W = a.shape
    yy, xx = np.mgrid[0:b, 0:b].astype(float)
    yy = yy / b - 0.5; xx = xx / b - 0.5
    A = np.stack([np.ones(b * b), xx.ravel(), yy.ravel(), xx.ravel() ** 2, (xx * yy).ravel(),
                  yy.ravel() ** 2], 1)
    P = A @ np.linalg.pinv(A)
    res = []
    for i in range(0, H - b + 1, b):
        for j in range(0, W - b + 1, b):
            blk = a[i:i + b, j:j + b].ravel()
            if not np.all(np.isfinite(blk)) or np.ptp(blk) == 0:
                continue
            r = blk - P @ blk
            res.append(np.sqrt(np.sum(r * r) / (b * b - 6)))
    if not res:
        return float('nan')
    return float(np.percentile(res, 10))


def fill_nan(a):
    m = ~np.isfinite(a)
    if not m.any():
        return a, m
    idx = ndimage.distance_transform_edt(m, return_distances=False, return_indices=True)
    return a[tuple(idx)], m


def warp(ref, s, th, dx, dy, nan_outside):
    H, W = ref.shape
    cx, cy = (W - 1) / 2, (H - 1) / 2
    filled, m = fill_nan(ref)
    yy, xx = np.mgrid[0:H, 0:W].astype(np.float64)
    qx, qy = xx - cx - dx, yy - cy - dy
    c, sn = np.cos(th), np.sin(th)
    # R^-1 = R(-th)
    px = (c * qx + sn * qy) / s + cx
    py = (-sn * qx + c * qy) / s + cy
    out = ndimage.map_coordinates(filled.astype(np.float64), [py, px], order=int(os.environ.get('WARP_ORDER', '5')), prefilter=True,
                                  mode='nearest')
    bad = np.zeros_like(out, bool)
    if m.any():
        mw = ndimage.map_coordinates(m.astype(float), [py, px], order=1, mode='nearest')
        bad |= mw > 1e-6
    if nan_outside:
        bad |= (px < 0) | (px > W - 1) | (py < 0) | (py > H - 1)
    out[bad] = np.nan
    return out


def main():
    img, n, seed, k, outp = sys.argv[1], int(sys.argv[2]), int(sys.argv[3]), float(sys.argv[4]), sys.argv[5]
    keep = sys.argv[sys.argv.index('--keep') + 1] if '--keep' in sys.argv else None
    rng = np.random.default_rng(seed)
    with fits.open(img) as hl:
        hdr = hl[0].header.copy()
        ref = hl[0].data.astype(np.float64)
    bg = background_sigma(ref)
    tmp = os.path.join(tempfile.gettempdir(), f'sunjitter_pairs_{os.getpid()}')
    os.makedirs(tmp, exist_ok=True)
    if keep:
        os.makedirs(keep, exist_ok=True)
    fo = open(outp, 'w')
    for t in range(n):
        s = rng.uniform(0.995, 1.005)
        th = rng.uniform(-0.01, 0.01)
        dx, dy = rng.uniform(-5, 5, 2)
        nan_out = (t % 2 == 1)
        fr = warp(ref, s, th, dx, dy, nan_out)
        r = ref.copy()
        if k > 0:
            r = r + rng.normal(0, k * bg, r.shape)
            fr = fr + rng.normal(0, k * bg, fr.shape)
        rp, fp = f'{tmp}/ref.fits', f'{tmp}/frame_{t:02d}.fits'
        fits.PrimaryHDU(r.astype(np.float32), hdr).writeto(rp, overwrite=True)
        fits.PrimaryHDU(fr.astype(np.float32), hdr).writeto(fp, overwrite=True)
        if keep:
            os.replace(fp, f'{keep}/frame_{t:02d}.fits')
            fp = f'{keep}/frame_{t:02d}.fits'
            if k > 0:  # each trial has its own noisy reference
                os.replace(rp, f'{keep}/ref_{t:02d}.fits')
                rp = f'{keep}/ref_{t:02d}.fits'
        t0 = time.time()
        p = subprocess.run([BIN, 'align', rp, fp, '--json', '--config', os.path.join(os.path.dirname(os.path.abspath(__file__)), '..', 'similarity.toml')],
                           capture_output=True, text=True)
        wall = time.time() - t0
        rec = dict(trial=t, image=os.path.basename(img), noise_k=k, bg_sigma=bg, nan_outside=nan_out,
                   true=dict(scale=s, rotation_arcsec=th * ARCSEC, dx_px=dx, dy_px=dy),
                   rc=p.returncode, wall_s=wall, stderr=p.stderr[-2000:])
        try:
            rec['out'] = json.loads(p.stdout)
        except Exception:
            rec['out'] = None
            rec['stdout'] = p.stdout[-2000:]
        fo.write(json.dumps(rec) + '\n'); fo.flush()
        o = rec['out'] or {}
        print(f"t{t} rc={p.returncode} {o.get('status')} wall={wall:.1f}s "
              f"ds={(o.get('scale') or np.nan) - s:.2e} drot={(o.get('rotation_arcsec') or np.nan) - th * ARCSEC:.3f} "
              f"ddx={(o.get('dx_px') or np.nan) - dx:.4f} ddy={(o.get('dy_px') or np.nan) - dy:.4f}", flush=True)
    print('bg_sigma', bg)


if __name__ == '__main__':
    main()
