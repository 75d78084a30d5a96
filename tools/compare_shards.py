#!/usr/bin/env python3
"""Compare a merged sharded run with a single-machine replay of the same inputs, read with
the official Python `mcap` reader (independent of sunjitter's own reader).

    python3 tools/compare_shards.py SINGLE_DIR MERGED_DIR [--shards N] [--min-within 0.95]

Checks, per /jitter/<channel> topic:
  - every frame of the single run is in the merged log exactly once, and nothing else is;
  - where a frame has the same reference (and kind) in both, its alignment numbers and its
    sequence are identical;
  - chained dx/dy are within 1 sigma (the single run's) of the single run's for at least
    --min-within of the frames that have a chained value in the single run;
  - the merged log's `sunjitter.merge` metadata names --shards shards.
Prints one summary line per channel; exit status 0 when everything holds, 1 otherwise.
"""

import argparse
import json
import sys
from pathlib import Path

from mcap.reader import make_reader

NUMBERS = ["scale", "rotation_arcsec", "dx_px", "dy_px", "sigma_scale",
           "sigma_rotation_arcsec", "sigma_dx_px", "sigma_dy_px", "similarity", "status",
           "sequence", "points", "inliers"]


def read(directory):
    """(frames by topic: list of message dicts, metadata records by name)."""
    topics, metadata = {}, {}
    files = sorted(Path(directory).glob("*.mcap"))
    if not files:
        sys.exit(f"compare_shards: {directory}: no *.mcap files")
    for path in files:
        with open(path, "rb") as f:
            reader = make_reader(f)
            for _schema, channel, message in reader.iter_messages():
                if channel.topic.startswith("/jitter/"):
                    topics.setdefault(channel.topic, []).append(json.loads(message.data))
            for record in reader.iter_metadata():
                metadata.setdefault(record.name, []).append(dict(record.metadata))
    return topics, metadata


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("single")
    ap.add_argument("merged")
    ap.add_argument("--shards", type=int)
    ap.add_argument("--min-within", type=float, default=0.95)
    args = ap.parse_args()
    single, _ = read(args.single)
    merged, meta = read(args.merged)
    failures = []
    if args.shards is not None:
        names = meta.get("sunjitter.merge", [])
        got = {len(json.loads(m.get("shards", "[]"))) for m in names}
        if got != {args.shards}:
            failures.append(f"sunjitter.merge metadata names {sorted(got)} shards, not {args.shards}")
    if set(single) != set(merged):
        failures.append(f"topics differ: {sorted(single)} vs {sorted(merged)}")
    for topic in sorted(single):
        one = {m["frame"]: m for m in single[topic]}
        many = merged.get(topic, [])
        keys = [m["frame"] for m in many]
        doubled = {k for k in keys if keys.count(k) > 1}
        if doubled:
            failures.append(f"{topic}: {len(doubled)} frames more than once, e.g. {sorted(doubled)[0]}")
        if set(keys) != set(one):
            failures.append(f"{topic}: frames differ: {len(set(one) - set(keys))} missing, "
                            f"{len(set(keys) - set(one))} extra")
        same_ref = identical = chained = within = 0
        for m in many:
            s = one.get(m["frame"])
            if s is None:
                continue
            if (s["reference"], s["reference_kind"]) == (m["reference"], m["reference_kind"]):
                same_ref += 1
                diff = [k for k in NUMBERS if s.get(k) != m.get(k)]
                if diff:
                    failures.append(f"{topic}: {m['frame']}: same reference, different {diff}")
                else:
                    identical += 1
            if s.get("chained_dx_px") is None:
                continue
            chained += 1
            ok = m.get("chained_dx_px") is not None and all(
                abs(m[f"chained_{a}_px"] - s[f"chained_{a}_px"])
                <= max(s[f"sigma_chained_{a}_px"], 1e-9) for a in ("dx", "dy"))
            within += ok
        frac = within / chained if chained else 1.0
        print(f"{topic}: {len(many)} frames (single run {len(one)}); same reference {same_ref}, "
              f"identical {identical}; chained within 1 sigma {within}/{chained} ({frac:.1%})")
        if frac < args.min_within:
            failures.append(f"{topic}: chained within 1 sigma for {frac:.1%} < {args.min_within:.0%}")
    for f in failures:
        print(f"compare_shards: {f}", file=sys.stderr)
    return 1 if failures else 0


if __name__ == "__main__":
    sys.exit(main())
