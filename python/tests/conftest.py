"""Shared fixtures: the repository's real data and the command line built from the same
source, whose output is the reference the package is checked against."""

from __future__ import annotations

import json
import os
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
DATA = ROOT / "data" / "real"
IRIS_1400 = DATA / "iris_l2_20140329_140938_3860258481_SJI_1400_t000.fits"
IRIS_2796 = DATA / "iris_l2_20140329_140938_3860258481_SJI_2796_t000_deconvolved.fits"
EIT_171 = DATA / "eit_171_20040301T010016_128.fits"
EIT_195 = DATA / "eit_195_20040301T000010_128.fits"
AIA_171 = DATA / "aia_171_20110215T000000_128.fits"
NOT_FITS = ROOT / "data" / "malformed" / "not_actually_fits.fits"


def _binary() -> Path:
    """``SUNJITTER_BIN``, else the most recently built of target/{release,debug}/sunjitter."""
    if os.environ.get("SUNJITTER_BIN"):
        return Path(os.environ["SUNJITTER_BIN"])
    built = [p for p in (ROOT / "target" / d / "sunjitter" for d in ("release", "debug")) if p.is_file()]
    if not built:
        pytest.fail("no sunjitter binary: run `cargo build` first (or set SUNJITTER_BIN)")
    return max(built, key=lambda p: p.stat().st_mtime)


class Cli:
    """The command line, run as a user runs it."""

    def __init__(self, binary: Path) -> None:
        self.binary = binary

    def run(self, *args: str, check: bool = True, cwd: Path | None = None, env: dict | None = None):
        merged = dict(os.environ, **(env or {}))
        done = subprocess.run(
            [str(self.binary), *map(str, args)],
            capture_output=True, text=True, cwd=cwd, env=merged,
        )
        if check and done.returncode not in (0, 1):
            raise AssertionError(f"sunjitter {' '.join(map(str, args))}: {done.stderr}")
        return done

    def json(self, *args: str, **kw):
        return json.loads(self.run(*args, **kw).stdout)

    def error_line(self, *args: str) -> tuple[int, str]:
        """Exit code and the one error line (without its ``sunjitter: `` prefix)."""
        done = self.run(*args, check=False)
        lines = [l for l in done.stderr.splitlines() if l.startswith("sunjitter: ")]
        assert len(lines) == 1, done.stderr
        return done.returncode, lines[0].removeprefix("sunjitter: ")


@pytest.fixture(scope="session")
def cli() -> Cli:
    return Cli(_binary())


@pytest.fixture(autouse=True)
def _own_cache(tmp_path_factory, monkeypatch):
    """Self-tests kept in a cache of the session's own, shared by the package and the command
    line, so neither reads what an earlier run left."""
    cache = tmp_path_factory.getbasetemp() / "cache"
    monkeypatch.setenv("SUNJITTER_CACHE_DIR", str(cache))


def without(record: dict, *keys: str) -> dict:
    return {k: v for k, v in record.items() if k not in keys}
