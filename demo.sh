#!/usr/bin/env bash
# The main job on bundled real data: replay two IRIS slit-jaw channels (SJI 2796 aligned to
# the nearest-in-time SJI 1400 frame, SJI 1400 to its own rolling keyframe) into MCAP, then
# summarise the log and draw the jitter figure.
set -euo pipefail
cd "$(dirname "$0")"
out=${1:-out/demo}
rm -rf "$out"
echo "demo: building sunjitter (cargo build --release; the first build takes several minutes)" >&2
cargo build --release
bin="${CARGO_TARGET_DIR:-target}/release/sunjitter"
"$bin" replay \
  data/real/iris_l2_20140329_140938_3860258481_SJI_1400_t000.fits \
  data/real/iris_l2_20140329_140938_3860258481_SJI_2796_t000_deconvolved.fits \
  --config examples/demo.toml --out "$out"
"$bin" inspect "$out" --plot "$out/jitter.png" --csv "$out/jitter.csv"
echo "log: $out/*.mcap   figure: $out/jitter.png   series: $out/jitter.csv"
