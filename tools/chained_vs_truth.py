#!/usr/bin/env python3
"""Chained translation of a replayed synthetic sequence against the injected truth.

usage: chained_vs_truth.py DIR/truth.csv OUT_DIR

DIR is what `sunjitter synth --out DIR` wrote (frames and `truth.csv`), OUT_DIR what
`sunjitter replay DIR --out OUT_DIR` wrote. Reads every /jitter/* message with the official
`mcap` reader, and compares `chained_dx_px` / `chained_dy_px` with the truth's motion since the
first frame (the origin itself left out). Prints the RMS error, the median chained σ and the fraction within 1σ.
"""
import csv
import glob
import json
import sys

import numpy as np
from mcap.reader import make_reader


def main():
    truth = {row['file']: row for row in csv.DictReader(open(sys.argv[1]))}
    messages = []
    for path in sorted(glob.glob(sys.argv[2] + '/*.mcap')):
        with open(path, 'rb') as f:
            for _, channel, message in make_reader(f).iter_messages():
                if channel.topic.startswith('/jitter/'):
                    messages.append(json.loads(message.data))
    messages.sort(key=lambda m: m['obs_time'])
    first = None
    errors, sigmas, statuses = [], [], {}
    for m in messages:
        t = truth[m['frame'].split('/')[-1]]
        statuses[m['status']] = statuses.get(m['status'], 0) + 1
        first = first or t
        # The first frame is the chain's origin (0 ± 0): nothing to compare.
        if m.get('chained_dx_px') is None or t is first:
            continue
        errors.append([m['chained_dx_px'] - (float(t['dx_px']) - float(first['dx_px'])),
                       m['chained_dy_px'] - (float(t['dy_px']) - float(first['dy_px']))])
        sigmas.append([m['sigma_chained_dx_px'], m['sigma_chained_dy_px']])
    errors, sigmas = np.array(errors), np.array(sigmas, dtype=float)
    print(f'frames {len(messages)}, statuses {statuses}, chained {len(errors)}')
    rms = np.sqrt(np.mean(errors ** 2, axis=0))
    within = 100 * np.mean(np.abs(errors) <= sigmas, axis=0)
    print('chained RMS error dx %.5f / dy %.5f px; median σ %.5f / %.5f px; within 1σ %.0f / %.0f %%'
          % (*rms, *np.nanmedian(sigmas, axis=0), *within))


if __name__ == '__main__':
    main()
