#!/usr/bin/env python3
"""Read a sunjitter log into a pandas DataFrame, one row per frame, and summarise it.

    pip install mcap zstandard pandas
    python3 examples/read_log.py OUT_DIR [--csv frames.csv] [--expect-frames SJI_1400=54 ...]

OUT_DIR is what `watch`/`replay --out` wrote (every *.mcap in it is a segment of one series);
single .mcap files work too. Columns: time (the frame's observation time, UTC), channel,
sequence, status, frame, dx/dy in px and arcsec with their 1-sigma, rotation and scale, and
the chained series (relative to the channel's first reference). Exit 1 when an
--expect-frames count does not hold.
"""

import argparse
import json
import sys
from pathlib import Path

import pandas as pd
from mcap.reader import make_reader

FIELDS = [
    "channel", "sequence", "status", "frame",
    "dx_px", "dy_px", "sigma_dx_px", "sigma_dy_px",
    "dx_arcsec", "dy_arcsec", "sigma_dx_arcsec", "sigma_dy_arcsec",
    "rotation_arcsec", "sigma_rotation_arcsec", "scale", "sigma_scale",
    "chained_dx_px", "chained_dy_px", "sigma_chained_dx_px", "sigma_chained_dy_px",
    "chained_dx_arcsec", "chained_dy_arcsec", "sigma_chained_dx_arcsec", "sigma_chained_dy_arcsec",
]


def read_log(*paths):
    """Every /jitter/<channel> message under `paths` as a DataFrame sorted by channel and time."""
    files = []
    for p in map(Path, paths):
        files.extend(sorted(p.glob("*.mcap")) if p.is_dir() else [p])
    rows = []
    for file in files:
        with open(file, "rb") as f:
            for _, channel, message in make_reader(f).iter_messages():
                if channel.topic.startswith("/jitter/"):
                    record = json.loads(message.data)
                    # Logs written before a field existed lack it: NaN, not an error.
                    rows.append([message.log_time] + [record.get(k) for k in FIELDS])
    df = pd.DataFrame(rows, columns=["time"] + FIELDS)
    df["time"] = pd.to_datetime(df["time"], unit="ns", utc=True)
    numeric = [k for k in FIELDS if k not in ("channel", "status", "frame")]
    df[numeric] = df[numeric].apply(pd.to_numeric)
    return df.sort_values(["channel", "time", "sequence"]).reset_index(drop=True)


def summary(df):
    """Per channel: frame counts by status, RMS of the shifts (arcsec) and median 1-sigma."""
    rms = lambda s: (s.dropna() ** 2).mean() ** 0.5
    g = df.groupby("channel")
    out = g["status"].value_counts().unstack(fill_value=0)
    out.insert(0, "frames", g.size())
    out["rms_dx_arcsec"] = g["dx_arcsec"].apply(rms)
    out["rms_dy_arcsec"] = g["dy_arcsec"].apply(rms)
    out["rms_chained_dx_arcsec"] = g["chained_dx_arcsec"].apply(rms)
    out["rms_chained_dy_arcsec"] = g["chained_dy_arcsec"].apply(rms)
    out["median_sigma_dx_arcsec"] = g["sigma_dx_arcsec"].median()
    return out


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("paths", nargs="+", help="log directories or .mcap files")
    ap.add_argument("--csv", help="also write the DataFrame here")
    ap.add_argument("--expect-frames", action="append", default=[], metavar="CHANNEL=N")
    args = ap.parse_args()

    df = read_log(*args.paths)
    pd.set_option("display.width", 200)
    print(f"{len(df)} frames, {df['channel'].nunique()} channels, "
          f"{df['time'].min()} to {df['time'].max()}")
    print(summary(df).round(4).to_string())
    if args.csv:
        df.to_csv(args.csv, index=False)

    problems = []
    counts = df["channel"].value_counts()
    for spec in args.expect_frames:
        name, _, n = spec.partition("=")
        if int(counts.get(name, 0)) != int(n):
            problems.append(f"{name}: {int(counts.get(name, 0))} frames, expected {n}")
    duplicated = df[df.duplicated(["channel", "frame"], keep=False)]
    if len(duplicated):
        problems.append(f"{len(duplicated)} rows name a frame twice")
    for p in problems:
        print(f"read_log: {p}", file=sys.stderr)
    return 1 if problems else 0


if __name__ == "__main__":
    sys.exit(main())
