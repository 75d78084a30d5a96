"""Overhead of the Python package: ``sunjitter.align`` on two numpy arrays against the command
line ``sunjitter align A B --json`` on the same pair, run alternately, side by side.

    python python/benches/bench_align.py --size 4096 --repeats 7

Makes the pair with ``sunjitter synth --out DIR --frames 2 --size SIZE`` (kept in DIR), reads
it once with astropy into native float32 arrays, then times each run: the command line's wall
time (process start, reading the two files, the alignment, the JSON) and the package's
(``align`` on the arrays in memory; the arrays are read in place). Both keep no self-test
between runs (``SUNJITTER_CACHE_DIR=``), so every run is a first alignment to its reference.
The engine's own time (``elapsed_ms`` of the record) is shown for both as well.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from astropy.io import fits

import sunjitter

ROOT = Path(__file__).resolve().parents[2]


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", type=int, default=4096)
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--bin", type=Path, default=ROOT / "target" / "release" / "sunjitter")
    parser.add_argument("--dir", type=Path, default=None, help="where the pair is (made if missing)")
    args = parser.parse_args()

    work = args.dir or Path(tempfile.gettempdir()) / f"sunjitter-bench-pair-{args.size}"
    a, b = work / "synth_0000.fits", work / "synth_0001.fits"
    if not (a.is_file() and b.is_file()):
        subprocess.run([str(args.bin), "synth", "--out", str(work), "--frames", "2",
                        "--size", str(args.size)], check=True, capture_output=True)
    os.environ["SUNJITTER_CACHE_DIR"] = ""
    arrays = []
    for path in (a, b):
        with fits.open(path) as hdul:
            arrays.append((np.ascontiguousarray(hdul[0].data, dtype=np.float32), hdul[0].header.copy()))
    (ref, ref_header), (frame, frame_header) = arrays

    records = {}

    def cli() -> tuple[float, float, str]:
        started = time.perf_counter()
        done = subprocess.run([str(args.bin), "align", str(a), str(b), "--json"],
                              check=True, capture_output=True, text=True)
        wall = time.perf_counter() - started
        records["cli"] = json.loads(done.stdout)
        return wall, records["cli"]["elapsed_ms"] / 1e3, records["cli"]["status"]

    def package() -> tuple[float, float, str]:
        started = time.perf_counter()
        r = sunjitter.align(ref, frame, reference_header=ref_header, frame_header=frame_header)
        wall = time.perf_counter() - started
        records["python"] = r.to_dict()
        return wall, r.elapsed_ms / 1e3, r.status

    runs: dict[str, list[tuple[float, float, str]]] = {"cli": [], "python": []}
    package()  # the first call imports and warms what a session warms once
    for _ in range(args.repeats):
        runs["cli"].append(cli())
        runs["python"].append(package())
    median = {k: statistics.median(w for w, _, _ in v) for k, v in runs.items()}
    engine = {k: statistics.median(e for _, e, _ in v) for k, v in runs.items()}
    print(f"pair: {args.size}² ({a.name}, {b.name}), {args.repeats} runs each, alternating; "
          f"status {runs['python'][0][2]}")
    print(f"{'':34}{'wall median (min–max)':>26}{'engine (elapsed_ms) median':>30}")
    for k, label in (("cli", "sunjitter align A B --json"), ("python", "sunjitter.align(arrays)")):
        walls = [w for w, _, _ in runs[k]]
        print(f"{label:34}{median[k]:>10.3f} s ({min(walls):.3f}–{max(walls):.3f})"
              f"{engine[k]:>24.3f} s")
    print(f"python / cli: wall {median['python'] / median['cli']:.3f}, "
          f"engine {engine['python'] / engine['cli']:.3f}")
    numbers = [k for k in records["cli"] if k not in ("reference", "frame", "message", "elapsed_ms")]
    same = all(records["cli"][k] == records["python"][k] for k in numbers)
    print(f"same numbers as the command line: {'yes' if same else 'NO'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
