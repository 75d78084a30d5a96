#!/usr/bin/env python3
"""Summarise truth_pairs.py jsonl files: RMSE, bias, RMS sigma, within 1/3 sigma, worst |err|/sigma."""
import sys, json
import numpy as np

P = ['scale', 'rotation_arcsec', 'dx_px', 'dy_px']
SIG = {'scale': 'sigma_scale', 'rotation_arcsec': 'sigma_rotation_arcsec', 'dx_px': 'sigma_dx_px',
       'dy_px': 'sigma_dy_px'}

for fn in sys.argv[1:]:
    recs = [json.loads(l) for l in open(fn)]
    print(f'### {fn}  (n={len(recs)}, bg_sigma={recs[0]["bg_sigma"]:.4g}, noise_k={recs[0]["noise_k"]})')
    st = {}
    for r in recs:
        o = r['out'] or {}
        key = (r['rc'], o.get('status'))
        st[key] = st.get(key, 0) + 1
    print('  rc/status counts:', st, ' max wall %.1fs, median %.1fs' % (
        max(r['wall_s'] for r in recs), np.median([r['wall_s'] for r in recs])))
    good = [r for r in recs if r['out'] and r['out'].get('scale') is not None]
    if not good:
        print('  no results with numbers')
    print('  | param | RMSE | bias | RMS σ | ≤1σ | ≤3σ | max |e|/σ |')
    for p in (P if good else []):
        e = np.array([r['out'][p] - r['true'][p] for r in good])
        s = np.array([r['out'][SIG[p]] for r in good])
        z = np.abs(e) / s
        print(f'  | {p} | {np.sqrt(np.mean(e**2)):.3g} | {np.mean(e):.3g} | {np.sqrt(np.mean(s**2)):.3g} | '
              f'{np.mean(z <= 1)*100:.0f}% | {np.mean(z <= 3)*100:.0f}% | {z.max():.2f} |')
    # per-subset: nearest vs nan outside
    for flag in (False, True):
        sub = [r for r in good if r['nan_outside'] == flag]
        if not sub:
            continue
        zz = [max(abs(r['out'][p] - r['true'][p]) / r['out'][SIG[p]] for p in P) for r in sub]
        print(f'  nan_outside={flag}: n={len(sub)}, max over params |e|/σ: median {np.median(zz):.2f}, max {max(zz):.2f}')
    conf = []
    for r in good:
        for p in P:
            z = abs(r['out'][p] - r['true'][p]) / r['out'][SIG[p]]
            if z > 5:
                conf.append((r['trial'], p, r['out'][p] - r['true'][p], r['out'][SIG[p]], z, r['out']['status']))
    if conf:
        print('  >5σ errors:')
        for c in conf:
            print('    trial %d %s err=%.3g σ=%.3g z=%.1f status=%s' % c)
    msgs = set()
    for r in recs:
        o = r['out'] or {}
        if o.get('status') != 'ok' or r['rc'] != 0:
            msgs.add((r['rc'], o.get('status'), o.get('message'), r['stderr'][-300:] if not o else ''))
    for m in msgs:
        print('  NON-OK:', m)
    # typical message
    print('  sample message:', (good[0]['out']['message'] if good else '')[:300])
