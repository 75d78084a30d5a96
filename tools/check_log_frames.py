#!/usr/bin/env python3
"""Count each channel's frames in a log with the Python package's reader and check the counts.

    python tools/check_log_frames.py OUT_DIR CHANNEL=N [CHANNEL=N ...]

Reads OUT_DIR (or .mcap files) with `sunjitter.read_log`, one row per frame, and exits 1 when
a channel does not have exactly N rows or a frame is there twice.
"""

import sys

import sunjitter


def main(argv):
    if len(argv) < 3 or not all("=" in a for a in argv[2:]):
        print(__doc__, file=sys.stderr)
        return 2
    df = sunjitter.read_log(argv[1])
    problems = []
    for expectation in argv[2:]:
        channel, count = expectation.split("=", 1)
        rows = df[df["channel"] == channel]
        if len(rows) != int(count):
            problems.append(f"{channel}: {len(rows)} frames, expected {count}")
        if not rows["frame"].is_unique:
            problems.append(f"{channel}: a frame logged twice")
    for p in problems:
        print(f"{argv[1]}: {p}", file=sys.stderr)
    print(f"{argv[1]}: " + ", ".join(f"{c}={n}" for c, n in df.groupby("channel").size().items()))
    return 1 if problems else 0


if __name__ == "__main__":
    sys.exit(main(sys.argv))
