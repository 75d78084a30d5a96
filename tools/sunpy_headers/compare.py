#!/usr/bin/env python3
"""Run `sunjitter info F --json` and `sunjitter info F` on every file in truth.json, compare
each field with sunpy's truth (the tolerances of tests/info.rs), and print disagreements.
Writes results.json (raw sunjitter output, rc, stderr and the list of disagreements per file).
"""
import json, subprocess, math, sys
from datetime import datetime
import os

# Where the built FITS files and the JSON results go.
WORK = os.environ.get("SUNPY_HEADERS_WORK", "sunpy_headers_work")
os.makedirs(WORK, exist_ok=True)
BIN = os.environ.get("SUNJITTER", "target/release/sunjitter")
TOL = dict(center=0.05, scale_rel=1e-6, roll=0.01, time_s=1e-3, rsun=0.01)


def run(args):
    p = subprocess.run([BIN] + args, capture_output=True, text=True, timeout=300)
    return p.returncode, p.stdout, p.stderr


def ptime(s):
    s = s.rstrip("Z")
    if "." in s:
        a, b = s.split(".")
        s = a + "." + (b + "000000")[:6]
    else:
        s += ".000000"
    return datetime.fromisoformat(s)


def angdiff(a, b):
    return (a - b + 180) % 360 - 180


def compare(sj, t):
    d = []
    if t.get("note"):
        d.append("[" + t["note"] + "]")
    if "map_error" in t:
        return [f"sunpy could not make a map: {t['map_error']}"]
    c, tc = sj["sun_center_px"], t.get("sun_center_px")
    if tc is not None and max(abs(c[0] - tc[0]), abs(c[1] - tc[1])) > TOL["center"]:
        d.append(f"sun_center_px sj={c} sunpy={[round(v, 4) for v in tc]} (d={c[0]-tc[0]:+.3f},{c[1]-tc[1]:+.3f})")
    if "sun_center_px_via_observer" in t:
        d.append(f"  [non-HPC frame {t['coord_frame']} {t['ctype']}: HPC(0,0) via observer -> {[round(v, 3) for v in t['sun_center_px_via_observer']]}]")
    s, ts = sj["plate_scale_arcsec"], t.get("plate_scale_arcsec")
    if ts and any(abs(a - b) > TOL["scale_rel"] * abs(b) for a, b in zip(s, ts)):
        d.append(f"plate_scale sj={s} sunpy={ts}")
    if t.get("rotation_deg") is not None and abs(angdiff(sj["rotation_deg"], t["rotation_deg"])) > TOL["roll"]:
        d.append(f"rotation_deg sj={sj['rotation_deg']} sunpy={t['rotation_deg']:.6f}")
    if sj["obs_time"] is None:
        d.append(f"obs_time sj=null sunpy={t.get('obs_time')}")
    elif t.get("obs_time"):
        dt = (ptime(sj["obs_time"]) - ptime(t["obs_time"])).total_seconds()
        if abs(dt) > TOL["time_s"]:
            d.append(f"obs_time sj={sj['obs_time']} sunpy ref_date={t['obs_time']} (d={dt:+.3f}s; sunpy .date={t.get('date')})")
    tr = t.get("rsun_arcsec")
    if sj["rsun_arcsec"] is None:
        if t.get("rsun_given"):
            d.append(f"rsun sj=null sunpy={tr}")
    elif tr is None or abs(sj["rsun_arcsec"] - tr) > TOL["rsun"]:
        d.append(f"rsun sj={sj['rsun_arcsec']} sunpy={tr} (sunpy given-by-header={t.get('rsun_given')})")
    te, se = t.get("exptime_s"), sj["exptime_s"]
    if (te is None) != (se is None) or (te is not None and abs(te - se) > 1e-6 * max(1, abs(te))):
        d.append(f"exptime sj={se} sunpy={te}")
    tw, sw = t.get("wavelength"), sj["wavelength"]
    if isinstance(tw, list):
        d.append(f"wavelength sj={sw} sunpy={tw} {t.get('waveunit')} (a band)")
        tw = None if sw is None else sw
    if (tw is None) != (sw is None) or (tw is not None and abs(tw - sw) > 1e-6 * max(1, abs(tw))):
        d.append(f"wavelength sj={sw} sunpy={tw} {t.get('waveunit')}")
    d.append(f"  [names: sj instrument={sj['instrument']!r} channel={sj['channel']!r} wl={sw}; sunpy instrument={t['instrument']!r} detector={t['detector']!r} nickname={t['nickname']!r} wl={tw} {t.get('waveunit')}]")
    return d


def main():
    truth = json.load(open(os.path.join(WORK, "truth.json")))
    results = {}
    for f, T in truth.items():
        rc, out, err = run(["info", f, "--json"])
        rc2, out2, err2 = run(["info", f])
        r = dict(source=T["source"], rc=rc, stderr=err.strip(), rc_human=rc2, stderr_human=err2.strip(),
                 human_lines=len(out2.splitlines()))
        issues = []
        if "panicked" in err + err2 or rc not in (0, 1, 2) or rc2 not in (0, 1, 2):
            issues.append(f"PANIC/odd rc: rc={rc} rc_human={rc2}")
        if rc != rc2:
            issues.append(f"json rc {rc} != human rc {rc2}")
        if rc != 0:
            nl = len([l for l in err.splitlines() if l.strip()])
            if nl != 1:
                issues.append(f"stderr has {nl} lines")
            r["frames"] = []
        else:
            sj = json.loads(out)
            r["sj"] = sj
            tf = T.get("frames", [])
            if len(sj) != len(tf):
                issues.append(f"frame count sj={len(sj)} sunpy/astropy image HDU slices={len(tf)}")
            for a, b in zip(sj, tf):
                issues.append(f"-- hdu {a['hdu']} frame {a['frame']}  ({a['width']}x{a['height']} bitpix {a['bitpix']})")
                issues += ["   " + x for x in compare(a, b)]
        r["issues"] = issues
        results[f] = r
        print(f"=== {T['source']}  rc={rc} rc_human={rc2}  {'ERR: ' + err.strip() if rc else ''}")
        for x in issues:
            print("   " + x)
    json.dump(results, open(os.path.join(WORK, "results.json"), "w"), indent=1)


if __name__ == "__main__":
    main()
