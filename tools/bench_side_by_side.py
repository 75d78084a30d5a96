#!/usr/bin/env python3
"""Ours vs OpenCV's calcOpticalFlowFarneback on the same FITS pair, same parameters, same run.

    cargo build --release --example bench_pair
    python3 tools/bench_side_by_side.py PREV.fits NEXT.fits [--repeat 3] [--threads 2]

e.g. on a synthetic full-disk pair: `sunjitter synth --out /tmp/s4096 --frames 2 --size 4096`,
then PREV=/tmp/s4096/synth_0000.fits NEXT=/tmp/s4096/synth_0001.fits.

OpenCV runs with the paper's parameters (pyr_scale 0.5, levels 5, winsize 101, iterations 10,
poly_n 5, poly_sigma 1.1, flags 0 = box window) on the whole float32 frame, as the paper does.
Ours (target/release/examples/bench_pair, same thread count through RAYON_NUM_THREADS):
flow_opencv_semantics (the same algorithm, whole frame), flow_engine (affine-window grid inside
the disk mask's bounding box, as the engine runs it) and align (the whole engine, default
configuration, cold: reference preparation and self-test included), align_kept (align again
with the same reference: its self-test read from where the first run kept it), align_per_frame (one
frame against a reference prepared beforehand, as the daemon runs), align_previous (NEXT against
a reference prepared from PREV, cold, as `replay --reference previous` runs every frame) and
align_cross (cold, PREV against NEXT made another channel's: Gaussian-blurred by 1.5 px, its
intensities bent by a power 0.8, WAVELNTH 999; written once beside --cross-dir). Each case runs
in its own process under /usr/bin/time, whose peak RSS is printed. The two sides alternate
repeat by repeat, so they see the same machine load. Farneback's cost does not depend on the
pixels' values, so every ratio is to OpenCV on PREV and NEXT. Ratios are printed for the median
wall time and for the median CPU time (all threads); on a shared machine the CPU ratio is the
load-independent one.
"""
import argparse
import json
import os
import pathlib
import statistics
import subprocess
import time

import tempfile

import cv2
import numpy as np
from astropy.io import fits
from scipy import ndimage

ROOT = pathlib.Path(__file__).resolve().parent.parent
OURS = ROOT / "target/release/examples/bench_pair"
CASES = ["flow_opencv_semantics", "flow_engine", "align", "align_kept", "align_per_frame",
         "align_previous", "align_cross"]


def cross_channel(next_path, out_dir):
    """NEXT as another channel shows it: blurred, intensities bent, another wavelength."""
    out = pathlib.Path(out_dir) / (pathlib.Path(next_path).stem + "_cross.fits")
    out.parent.mkdir(parents=True, exist_ok=True)
    if not out.exists():
        with fits.open(next_path) as hdul:
            img = hdul[0].data.astype(float)
            hdr = hdul[0].header.copy()
        img = ndimage.gaussian_filter(img, 1.5)
        lo = np.nanmin(img)
        img = (img - lo) ** 0.8 + lo
        hdr["WAVELNTH"] = 999
        fits.writeto(out, img.astype(np.float32), hdr, overwrite=True)
    return str(out)


def opencv_once(prev, nxt):
    c0, t0 = time.process_time(), time.perf_counter()
    cv2.calcOpticalFlowFarneback(prev, nxt, None, 0.5, 5, 101, 10, 5, 1.1, 0)
    return time.perf_counter() - t0, time.process_time() - c0


def ours_once(prev_path, next_path, cross_path, threads):
    """Every case in a process of its own: (wall s, CPU s, peak RSS GiB) by case."""
    env = dict(os.environ, RAYON_NUM_THREADS=str(threads))
    got = {}
    for case in CASES:
        r = subprocess.run(
            ["/usr/bin/time", "-f", "maxrss_kb %M", str(OURS), prev_path, next_path, "1", case,
             cross_path],
            env=env, check=True, capture_output=True, text=True,
        )
        d = json.loads(r.stdout.splitlines()[-1])
        rss = [line for line in r.stderr.splitlines() if line.startswith("maxrss_kb ")]
        got[case] = (d["wall_s"][0], d["cpu_s"][0], int(rss[-1].split()[1]) / 2**20)
    return got


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("prev")
    ap.add_argument("next")
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--cross-dir", default=tempfile.gettempdir())
    a = ap.parse_args()
    if not OURS.exists():
        raise SystemExit(f"{OURS} missing: cargo build --release --example bench_pair")
    prev = fits.getdata(a.prev).astype(np.float32)
    nxt = fits.getdata(a.next).astype(np.float32)
    cross = cross_channel(a.next, a.cross_dir)
    cv2.setNumThreads(a.threads)
    print(f"pair {prev.shape[1]}x{prev.shape[0]}, OpenCV {cv2.__version__}, {a.threads} threads, "
          f"load average {' '.join(open('/proc/loadavg').read().split()[:3])}")
    cv = []
    ours = {c: [] for c in CASES}
    for _ in range(a.repeat):
        cv.append(opencv_once(prev, nxt))
        for c, v in ours_once(a.prev, a.next, cross, a.threads).items():
            ours[c].append(v)
    med = lambda xs, i: statistics.median(x[i] for x in xs)
    rng = lambda xs, i: f"{min(x[i] for x in xs):.3f}-{max(x[i] for x in xs):.3f}"
    print(f"{'case':24} {'wall median':>11} {'(min-max)':>15} {'cpu median':>10} "
          f"{'peak RSS GiB':>12} {'wall ratio':>10} {'cpu ratio':>9}")
    print(f"{'opencv_farneback':24} {med(cv, 0):11.3f} {rng(cv, 0):>15} {med(cv, 1):10.3f}")
    for c in CASES:
        v = ours[c]
        print(f"{'ours_' + c:24} {med(v, 0):11.3f} {rng(v, 0):>15} {med(v, 1):10.3f} "
              f"{max(x[2] for x in v):12.2f} "
              f"{med(cv, 0) / med(v, 0):9.1f}x {med(cv, 1) / med(v, 1):8.1f}x")
    print(f"load average at end {' '.join(open('/proc/loadavg').read().split()[:3])}")


if __name__ == "__main__":
    main()
