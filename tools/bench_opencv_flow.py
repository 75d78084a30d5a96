#!/usr/bin/env python3
"""Time OpenCV's calcOpticalFlowFarneback on the same pairs as benches/flow.rs.

    python3 tools/bench_opencv_flow.py [--sizes 1024 2048 4096] [--repeat 5] [--threads 1 2]

Pair (mirrors make_pair in benches/flow.rs): TRACE 171 resized bilinearly to N^2 (pixel-centre
aligned, edge clamped), next = the same sampled at (x - 0.37, y + 0.61). Paper parameters:
pyr_scale 0.5, levels 5, winsize 101, iterations 10, poly_n 5, poly_sigma 1.1, box window.
Prints median and min-max wall time and the median CPU time (all threads) per size and
thread count; on a shared machine the CPU time is the load-independent figure.
"""
import argparse
import pathlib
import statistics
import time

import cv2
import numpy as np
from astropy.io import fits

ROOT = pathlib.Path(__file__).resolve().parent.parent
SRC = ROOT / "data/real/trace_171_19980519T222143_1024.fits"
SHIFT = (0.37, -0.61)


def bilinear(img, x, y):
    h, w = img.shape
    x = np.clip(x, 0, w - 1)
    y = np.clip(y, 0, h - 1)
    x0 = np.floor(x).astype(int)
    y0 = np.floor(y).astype(int)
    x1 = np.minimum(x0 + 1, w - 1)
    y1 = np.minimum(y0 + 1, h - 1)
    ax, ay = x - x0, y - y0
    top = img[y0, x0] * (1 - ax) + img[y0, x1] * ax
    bot = img[y1, x0] * (1 - ax) + img[y1, x1] * ax
    return top * (1 - ay) + bot * ay


def make_pair(src, n):
    r = src.shape[0] / n
    yy, xx = np.mgrid[0:n, 0:n].astype(np.float64)
    at = lambda x, y: bilinear(src, (x + 0.5) * r - 0.5, (y + 0.5) * r - 0.5)
    prev = at(xx, yy).astype(np.float32)
    nxt = at(xx - SHIFT[0], yy - SHIFT[1]).astype(np.float32)
    return prev, nxt


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--sizes", type=int, nargs="+", default=[1024, 2048])
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--threads", type=int, nargs="+", default=[1, 2])
    a = ap.parse_args()
    src = fits.getdata(SRC).astype(np.float64)
    print(f"OpenCV {cv2.__version__}, paper parameters (levels 5, winsize 101, 10 iterations, poly_n 5)")
    for n in a.sizes:
        prev, nxt = make_pair(src, n)
        for t in a.threads:
            cv2.setNumThreads(t)
            times, cpus = [], []
            for _ in range(a.repeat):
                t0, c0 = time.perf_counter(), time.process_time()
                f = cv2.calcOpticalFlowFarneback(prev, nxt, None, 0.5, 5, 101, 10, 5, 1.1, 0)
                times.append(time.perf_counter() - t0)
                cpus.append(time.process_time() - c0)
            c = f[n // 4:3 * n // 4, n // 4:3 * n // 4]
            print(f"{n}^2 threads={t}: median {statistics.median(times):.3f} s "
                  f"(min {min(times):.3f}, max {max(times):.3f}, n={len(times)}), "
                  f"CPU {statistics.median(cpus):.2f} s; "
                  f"median flow ({np.median(c[..., 0]):+.4f}, {np.median(c[..., 1]):+.4f}) px")


if __name__ == "__main__":
    main()
