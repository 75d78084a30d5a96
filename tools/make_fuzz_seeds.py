#!/usr/bin/env python3
"""Seed corpus for fuzz/fuzz_targets/fits_header.rs from the bundled real and malformed files.

For every file: its first header alone (a truncated file), and a small complete copy: the
raw header cards kept byte for byte (quirks such as out-of-order NAXIS cards survive), the
NAXISn values shrunk, and the first bytes of the real data as pixels. IRIS files keep their
per-frame table HDU (rows shrunk) so the cube clock path is exercised.

    python3 tools/make_fuzz_seeds.py   # writes fuzz/corpus/fits_header/seed-*
"""
import glob
import os
import re

BLOCK = 2880
OUT = os.path.join(os.path.dirname(__file__), "..", "fuzz", "corpus", "fits_header")
# Small axes: x, y, frames (a cube keeps 2 frames).
SMALL = {1: 5, 2: 4, 3: 2}


def headers(raw):
    """(header bytes incl. padding, data offset, data length) for each HDU."""
    out, off = [], 0
    while off < len(raw):
        end = None
        for b in range(off, len(raw), BLOCK):
            cards = [raw[i:i + 80] for i in range(b, min(b + BLOCK, len(raw)), 80)]
            if any(c[:8] == b"END     " for c in cards):
                end = b + BLOCK
                break
        if end is None:
            break
        head = raw[off:end]
        vals = {}
        for i in range(0, len(head), 80):
            c = head[i:i + 80].decode("ascii", "replace")
            m = re.match(r"^(BITPIX|NAXIS\d*|PCOUNT|GCOUNT)\s*=\s*([-+]?\d+)", c)
            if m:
                vals[m.group(1)] = int(m.group(2))
        n = vals.get("NAXIS", 0)
        size = abs(vals.get("BITPIX", 8)) // 8 * vals.get("GCOUNT", 1)
        elems = 1
        for k in range(1, n + 1):
            elems *= vals.get(f"NAXIS{k}", 0)
        size *= (elems if n else 0) + vals.get("PCOUNT", 0)
        out.append((head, end, size))
        off = end + (size + BLOCK - 1) // BLOCK * BLOCK
    return out


def shrink(head, hdu_index):
    """Rewrite NAXISn values (same card layout) to small ones."""
    cards = [bytearray(head[i:i + 80]) for i in range(0, len(head), 80)]
    small = {}
    for c in cards:
        m = re.match(rb"^NAXIS(\d)\s*=\s*(\d+)", bytes(c))
        if not m:
            continue
        k, v = int(m.group(1)), int(m.group(2))
        # The IRIS per-frame table keeps its columns (x) so TIME/EXPTIMES stay valid.
        new = v if (hdu_index > 0 and k == 1) else min(v, SMALL.get(k, 1))
        c[10:30] = f"{new:>20d}".encode()
        small[k] = new
    return b"".join(bytes(c) for c in cards), small


def main():
    os.makedirs(OUT, exist_ok=True)
    files = sorted(glob.glob("data/real/*.fits")) + sorted(glob.glob("data/malformed/*"))
    for path in files:
        raw = open(path, "rb").read()
        name = os.path.splitext(os.path.basename(path))[0][:48]
        hdus = headers(raw)
        if not hdus:
            open(os.path.join(OUT, f"seed-{name}-raw"), "wb").write(raw[:4096])
            continue
        open(os.path.join(OUT, f"seed-{name}-header"), "wb").write(hdus[0][0])
        small = b""
        for i, (head, data_off, _size) in enumerate(hdus):
            if b"XTENSION= 'TABLE" in head[:80]:
                continue  # ASCII table: not read by sunjitter
            new_head, axes = shrink(head, i)
            bitpix = int(re.search(rb"BITPIX\s*=\s*([-+]?\d+)", head).group(1))
            n = abs(bitpix) // 8
            for v in axes.values():
                n *= v
            data = raw[data_off:data_off + n]
            small += new_head + data + b"\0" * (-len(data) % BLOCK)
        open(os.path.join(OUT, f"seed-{name}-small"), "wb").write(small)
    # A header bomb and a tile-compressed header (pixels absent: the header is the point).
    card = lambda text: text.ljust(80).encode()
    bomb = b"".join(card(c) for c in [
        "SIMPLE  =                    T", "BITPIX  =                  -32", "NAXIS   =                    2",
        "NAXIS1  =           2000000000", "NAXIS2  =           2000000000", "END"])
    open(os.path.join(OUT, "seed-header-bomb"), "wb").write(bomb.ljust(BLOCK))
    primary = b"".join(card(c) for c in ["SIMPLE  =                    T", "BITPIX  =                    8",
                                         "NAXIS   =                    0", "EXTEND  =                    T", "END"])
    table = b"".join(card(c) for c in [
        "XTENSION= 'BINTABLE'", "BITPIX  =                    8", "NAXIS   =                    2",
        "NAXIS1  =                    8", "NAXIS2  =                    4", "PCOUNT  =                    0",
        "GCOUNT  =                    1", "TFIELDS =                    1", "TTYPE1  = 'COMPRESSED_DATA'",
        "TFORM1  = '1PB(0)  '", "ZIMAGE  =                    T", "ZBITPIX =                   16",
        "ZNAXIS  =                    2", "ZNAXIS1 =                    4", "ZNAXIS2 =                    4",
        "ZTILE1  =                    4", "ZTILE2  =                    1", "ZCMPTYPE= 'RICE_1  '",
        "CRPIX1  =                  2.5", "CRPIX2  =                  2.5", "CDELT1  =                  0.6",
        "CDELT2  =                  0.6", "DATE-OBS= '2011-02-15T00:00:00.34'", "END"])
    open(os.path.join(OUT, "seed-compressed-header"), "wb").write(
        primary.ljust(BLOCK) + table.ljust(BLOCK) + bytes(BLOCK))


if __name__ == "__main__":
    main()
