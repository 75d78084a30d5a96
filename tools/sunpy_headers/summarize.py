#!/usr/bin/env python3
"""Compact per-file table from results.json + truth.json (markdown)."""
import json, re
import os

# Where the built FITS files and the JSON results go.
WORK = os.environ.get("SUNPY_HEADERS_WORK", "sunpy_headers_work")
os.makedirs(WORK, exist_ok=True)
r = json.load(open(os.path.join(WORK, "results.json"))); t = json.load(open(os.path.join(WORK, "truth.json")))
print("| file | sunpy class / instrument | sj rc | sj channel | disagreements (field names) |\n|---|---|---|---|---|")
for f, x in r.items():
    fr = t[f].get("frames") or [{}]
    cls = f"{fr[0].get('map_class','-')} / {fr[0].get('detector') or fr[0].get('instrument','')}" if fr[0] else "(no image HDU)"
    ch = x["sj"][0]["channel"] if x.get("sj") else "-"
    fields = sorted({m.group(1) for i in x["issues"] for m in [re.match(r"\s*(sun_center_px|plate_scale|rotation_deg|obs_time|rsun|exptime|wavelength|sunpy could not|frame count|PANIC|stderr)", i)] if m})
    err = x["stderr"].split(": ", 2)[-1] if x["rc"] else ""
    print(f"| {x['source']} | {cls} | {x['rc']} | {ch} | {', '.join(fields) or ('refused: ' + err if err else 'all agree')} |")
