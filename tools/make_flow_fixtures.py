#!/usr/bin/env python3
"""Make the optical-flow oracle fixtures in tests/data/flow/ from the real TRACE 171 image.

    python3 tools/make_flow_fixtures.py        # needs numpy, scipy, astropy, opencv-python-headless
    python3 tools/make_flow_fixtures.py --eval DIR
        # also write full-size (1024^2) warps of the TRACE image to DIR (not committed) for the
        # accuracy table of benches/flow.rs: SUNJITTER_FLOW_EVAL=DIR cargo bench --bench flow

What it writes (raw little-endian float32, row-major 256x256, described by fixtures.json):
  prev.f32        256x256 crop of data/real/trace_171_19980519T222143_1024.fits at
                  (x0, y0) = (384, 384), scaled to a mean of 1e4 (OpenCV adds 1e-3 to a
                  determinant that scales as intensity^4; at this level it is negligible).
  warp_next.f32   the same field after a known affine warp about the crop centre
                  (rotation 0.4 deg, scale 1.003, shift (+0.37, -0.61) px), resampled from the
                  full 1024^2 image with scipy.ndimage.map_coordinates(order=3) at float
                  coordinates (NOT cv2.warpAffine, which quantises positions to 1/32 px).
  shift_next.f32  the crop translated by (+0.30, -0.45) px, same resampling.
  cv_box_u/v.f32, cv_gauss_u/v.f32
                  cv2.calcOpticalFlowFarneback(prev, warp_next) with the box window and with
                  OPTFLOW_FARNEBACK_GAUSSIAN, parameters in fixtures.json.
Truth: next(p + d(p)) = prev(p), with d(p) = A (p - c) + c + t - p (A = s R(theta), rotation
counter-clockwise in (x right, y up), i.e. clockwise on screen with y down).
"""
import json
import pathlib

import cv2
import numpy as np
from astropy.io import fits
from scipy import ndimage

ROOT = pathlib.Path(__file__).resolve().parent.parent
SRC = ROOT / "data/real/trace_171_19980519T222143_1024.fits"
OUT = ROOT / "tests/data/flow"
X0, Y0, N = 384, 384, 256
MEAN = 1e4

ROT_DEG, SCALE, SHIFT = 0.4, 1.003, (0.37, -0.61)
PURE_SHIFT = (0.30, -0.45)
PARAMS = dict(pyr_scale=0.5, levels=3, winsize=33, iterations=10, poly_n=5, poly_sigma=1.1)


def affine(rot_deg, scale, shift):
    """2x2 matrix A acting on (x, y) pixel coords and translation t, about the crop centre."""
    th = np.deg2rad(rot_deg)
    # CCW in (x right, y up) = with y down: [[cos, sin], [-sin, cos]].
    a = scale * np.array([[np.cos(th), np.sin(th)], [-np.sin(th), np.cos(th)]])
    return a, np.asarray(shift, dtype=np.float64)


def warp_from_full(full, a, t):
    """next[q] = full[T^-1(q)] for crop pixels q, with T(p) = A (p - c) + c + t (crop coords)."""
    c = np.array([(N - 1) / 2.0, (N - 1) / 2.0])
    yy, xx = np.mgrid[0:N, 0:N].astype(np.float64)
    q = np.stack([xx.ravel(), yy.ravel()])  # (x, y)
    p = np.linalg.solve(a, q - (c + t)[:, None]) + c[:, None]
    coords = np.stack([p[1] + Y0, p[0] + X0])  # (row, col) in the full image
    return ndimage.map_coordinates(full, coords, order=3, mode="nearest").reshape(N, N)


# Full-size warps for the accuracy table: (name, rotation deg, scale, shift xy).
EVAL_CASES = [
    ("small", 0.1, 1.002, (0.37, -0.61)),
    ("large", 0.3, 0.998, (4.3, -3.7)),
    ("scale", 0.0, 1.01, (0.0, 0.0)),
    ("rotation", 0.5, 1.0, (0.0, 0.0)),
]


def write_eval(out_dir):
    """prev.f32 (TRACE scaled to mean 1e4) and <case>_next.f32 + <case>.json per EVAL_CASES."""
    out = pathlib.Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    full = fits.getdata(SRC).astype(np.float64)
    full *= MEAN / full.mean()
    n = full.shape[0]
    c = (n - 1) / 2.0
    full.astype("<f4").tofile(out / "prev.f32")
    yy, xx = np.mgrid[0:n, 0:n].astype(np.float64)
    q = np.stack([xx.ravel(), yy.ravel()])
    for name, rot, scale, shift in EVAL_CASES:
        a, t = affine(rot, scale, shift)
        p = np.linalg.solve(a, q - (np.array([c, c]) + t)[:, None]) + c
        nxt = ndimage.map_coordinates(full, [p[1], p[0]], order=3, mode="nearest")
        nxt.reshape(n, n).astype("<f4").tofile(out / f"{name}_next.f32")
        (out / f"{name}.json").write_text(json.dumps(
            dict(size=n, matrix_xy=a.tolist(), shift_xy=list(t), center_xy=[c, c])))
    print(f"wrote {len(EVAL_CASES)} evaluation warps to {out}")


def main():
    import sys
    if len(sys.argv) == 3 and sys.argv[1] == "--eval":
        write_eval(sys.argv[2])
        return
    full = fits.getdata(SRC).astype(np.float64)
    crop = full[Y0:Y0 + N, X0:X0 + N]
    k = MEAN / crop.mean()
    full_s = full * k
    prev = (crop * k).astype(np.float32)

    a, t = affine(ROT_DEG, SCALE, SHIFT)
    warp_next = warp_from_full(full_s, a, t).astype(np.float32)
    ai, ti = affine(0.0, 1.0, PURE_SHIFT)
    shift_next = warp_from_full(full_s, ai, ti).astype(np.float32)

    OUT.mkdir(parents=True, exist_ok=True)
    files = {}

    def save(name, arr):
        arr = np.ascontiguousarray(arr, dtype="<f4")
        (OUT / name).write_bytes(arr.tobytes())
        files[name] = list(arr.shape)

    save("prev.f32", prev)
    save("warp_next.f32", warp_next)
    save("shift_next.f32", shift_next)
    p = PARAMS
    for tag, flags in (("box", 0), ("gauss", cv2.OPTFLOW_FARNEBACK_GAUSSIAN)):
        flow = cv2.calcOpticalFlowFarneback(
            prev, warp_next, None, p["pyr_scale"], p["levels"], p["winsize"],
            p["iterations"], p["poly_n"], p["poly_sigma"], flags)
        save(f"cv_{tag}_u.f32", flow[..., 0])
        save(f"cv_{tag}_v.f32", flow[..., 1])

    meta = dict(
        source=str(SRC.relative_to(ROOT)), crop_x0=X0, crop_y0=Y0, size=N, mean=MEAN,
        warp=dict(rotation_deg=ROT_DEG, scale=SCALE, shift_xy=list(SHIFT),
                  matrix_xy=a.tolist(), center_xy=[(N - 1) / 2.0] * 2),
        pure_shift_xy=list(PURE_SHIFT), opencv_params=p, opencv_version=cv2.__version__,
        files=files, dtype="<f4 row-major [y, x]",
        made_by="python3 tools/make_flow_fixtures.py")
    (OUT / "fixtures.json").write_text(json.dumps(meta, indent=1) + "\n")
    total = sum((OUT / f).stat().st_size for f in files)
    print(f"wrote {len(files)} arrays, {total / 1e6:.2f} MB, OpenCV {cv2.__version__}")

    # Figures the Rust test compares against (printed so they can be cited).
    c = np.array([(N - 1) / 2.0] * 2)
    yy, xx = np.mgrid[0:N, 0:N].astype(np.float64)
    tu = a[0, 0] * (xx - c[0]) + a[0, 1] * (yy - c[1]) + c[0] + t[0] - xx
    tv = a[1, 0] * (xx - c[0]) + a[1, 1] * (yy - c[1]) + c[1] + t[1] - yy
    m = p["winsize"]
    inner = (slice(m, N - m), slice(m, N - m))
    for tag in ("box", "gauss"):
        u = np.fromfile(OUT / f"cv_{tag}_u.f32", dtype="<f4").reshape(N, N)
        v = np.fromfile(OUT / f"cv_{tag}_v.f32", dtype="<f4").reshape(N, N)
        rms = np.sqrt(np.mean((u - tu)[inner] ** 2 + (v - tv)[inner] ** 2))
        print(f"OpenCV {tag}: RMS |flow - truth| in the interior = {rms:.4f} px")


if __name__ == "__main__":
    main()
