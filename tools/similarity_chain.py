#!/usr/bin/env python3
"""A sequence of one image moved by known similarities, and `previous` replays scored on it.

    python3 tools/similarity_chain.py make IMAGE.fits N SEED OUT_DIR
    python3 tools/similarity_chain.py score OUT_DIR/truth.csv REPLAY_DIR
    python3 tools/similarity_chain.py compare REPLAY_A REPLAY_B

make:    N frames, frame(p) = image(T_k^-1 p) with T_k(p) = s R(th) (p - c) + c + (dx, dy),
         c = ((W-1)/2, (H-1)/2), R counter-clockwise in (x = column, y = row); s within
         ±0.002, th within ±0.005 rad, dx and dy within ±3 px, drawn with SEED. Resampled by
         scipy's cubic B-spline (one order below the engine's model), no noise. DATE-OBS
         12 s apart; replay with `[engine] solar_rotation = "none"` (the frames do not turn).
score:   every `previous` alignment of REPLAY_DIR (read with the official `mcap` reader)
         against the truth of frame k relative to its reference j: T_k T_j^-1. Prints the
         RMS error, the RMS σ and the fractions within 1σ and 3σ for scale, rotation ″, dx,
         dy px.
compare: the same frames in two replays: ratio of σ (B/A) and |value B - value A| / σ_A.
"""
import csv
import glob
import json
import os
import sys

import numpy as np
from mcap.reader import make_reader


def make(image, n, seed, out):
    from astropy.io import fits
    from scipy import ndimage

    os.makedirs(out, exist_ok=True)
    with fits.open(image) as hdus:
        hdu = next(h for h in hdus if h.data is not None and h.data.ndim == 2)
        data, header = hdu.data.astype(np.float64), hdu.header.copy()
    h, w = data.shape
    c = np.array([(w - 1) / 2, (h - 1) / 2])
    filled = np.where(np.isfinite(data), data, np.nanmedian(data))
    coef = ndimage.spline_filter(filled, order=3)
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:h, 0:w].astype(float)
    rows = []
    for k in range(n):
        s = 1 + rng.uniform(-0.002, 0.002)
        th = rng.uniform(-0.005, 0.005)
        dx, dy = rng.uniform(-3, 3, 2)
        # T^-1(p) = R(-th) (p - c - d) / s + c
        px, py = xx - c[0] - dx, yy - c[1] - dy
        cos, sin = np.cos(-th) / s, np.sin(-th) / s
        sx, sy = cos * px - sin * py + c[0], sin * px + cos * py + c[1]
        frame = ndimage.map_coordinates(coef, [sy, sx], order=3, prefilter=False, mode='nearest')
        hk = header.copy()
        for key in ('BLANK', 'BSCALE', 'BZERO'):
            hk.pop(key, None)
        hk['DATE-OBS'] = '2024-05-01T12:%02d:%02d.000' % (k * 12 // 60, k * 12 % 60)
        name = 'chain_%03d.fits' % k
        fits.PrimaryHDU(frame.astype(np.float32), hk).writeto(os.path.join(out, name),
                                                              overwrite=True)
        rows.append(dict(frame=k, file=name, obs_time=hk['DATE-OBS'], dx_px=dx, dy_px=dy,
                         rotation_arcsec=np.degrees(th) * 3600, scale=s))
    with open(os.path.join(out, 'truth.csv'), 'w', newline='') as f:
        writer = csv.DictWriter(f, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)


def messages(replay):
    out = {}
    for path in sorted(glob.glob(replay + '/*.mcap')):
        with open(path, 'rb') as f:
            for _, channel, message in make_reader(f).iter_messages():
                if channel.topic.startswith('/jitter/'):
                    m = json.loads(message.data)
                    out[m['frame']] = m
    return out


KEYS = ['scale', 'rotation_arcsec', 'dx_px', 'dy_px']


def score(truth_csv, replay):
    truth = {row['file']: row for row in csv.DictReader(open(truth_csv))}
    a = lambda q: float(q['scale']) * np.exp(1j * np.radians(float(q['rotation_arcsec']) / 3600))
    d = lambda q: float(q['dx_px']) + 1j * float(q['dy_px'])
    errors, sigmas, statuses = [], [], {}
    for m in messages(replay).values():
        statuses[m['status']] = statuses.get(m['status'], 0) + 1
        if m.get('reference_kind') != 'previous' or m['status'] == 'failed':
            continue
        t, r = truth[m['frame'].split('/')[-1]], truth[m['reference'].split('/')[-1]]
        # T_k T_j^-1 (p) = (a_k / a_j) (p - c) + c + d_k - (a_k / a_j) d_j
        rel = a(t) / a(r)
        shift = d(t) - rel * d(r)
        expected = [abs(rel), np.degrees(np.angle(rel)) * 3600, shift.real, shift.imag]
        errors.append([m[k] - e for k, e in zip(KEYS, expected)])
        sigmas.append([m['sigma_' + k] for k in KEYS])
    e, s = np.array(errors), np.array(sigmas)
    z = np.abs(e) / s
    fmt = lambda v, f: ' / '.join(f % x for x in v)
    print('frames', len(e), 'statuses', statuses)
    print('RMS error ', fmt(np.sqrt((e ** 2).mean(0)), '%.3g'))
    print('RMS σ     ', fmt(np.sqrt((s ** 2).mean(0)), '%.3g'))
    print('within 1σ ', fmt(100 * (z < 1).mean(0), '%.0f %%'))
    print('within 3σ ', fmt(100 * (z < 3).mean(0), '%.0f %%'))


def compare(replay_a, replay_b):
    a, b = messages(replay_a), messages(replay_b)
    ratios, moved, changed = [], [], 0
    for frame, ma in a.items():
        mb = b[frame]
        changed += ma['status'] != mb['status']
        # The chain's origin (aligned to itself, σ 0) has nothing to compare.
        if ma.get('reference_kind') != 'previous' or mb.get('reference_kind') != 'previous':
            continue
        if ma['status'] == 'failed' or mb['status'] == 'failed':
            continue
        ratios.append([mb['sigma_' + k] / ma['sigma_' + k] for k in KEYS])
        moved.append([abs(mb[k] - ma[k]) / ma['sigma_' + k] for k in KEYS])
    r, v = np.array(ratios), np.array(moved)
    fmt = lambda x: ' / '.join('%.3f' % y for y in x)
    print('frames', len(a), 'status changes', changed, 'missing from B', len(set(a) - set(b)))
    print('σ B/A min   ', fmt(r.min(0)))
    print('σ B/A max   ', fmt(r.max(0)))
    print('σ B/A RMS   ', fmt(np.sqrt((r ** 2).mean(0))))
    print('|B - A|/σ_A max', fmt(v.max(0)))


if __name__ == '__main__':
    command, args = sys.argv[1], sys.argv[2:]
    if command == 'make':
        make(args[0], int(args[1]), int(args[2]), args[3])
    elif command == 'score':
        score(*args)
    elif command == 'compare':
        compare(*args)
    else:
        sys.exit(__doc__)
