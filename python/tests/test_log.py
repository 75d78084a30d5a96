"""``replay``, ``read_log`` and ``summary`` against the command line: the same records in the
log, every column of ``inspect --csv`` with its values, ``inspect --json``'s statistics."""

from __future__ import annotations

import logging
import math

import pandas as pd
import pytest

import sunjitter
from conftest import IRIS_1400, IRIS_2796

SAME_RUN_EXCEPT = ("elapsed_ms",)


@pytest.fixture(scope="module")
def runs(tmp_path_factory, cli):
    """The two IRIS channels replayed by the package and by the command line."""
    base = tmp_path_factory.mktemp("runs")
    inputs = [str(IRIS_1400), str(IRIS_2796)]
    py_out, cli_out = base / "py", base / "cli"
    env = {"SUNJITTER_CACHE_DIR": str(base / "cache-cli")}
    cli.run("replay", *inputs, "--out", cli_out, env=env)
    import os
    os.environ["SUNJITTER_CACHE_DIR"] = str(base / "cache-py")
    df = sunjitter.replay(inputs, out=py_out, progress=False)
    return df, py_out, cli_out


def _cells_equal(a, b) -> bool:
    missing = lambda v: v is None or v is pd.NA or (isinstance(v, float) and math.isnan(v))
    if missing(a) or missing(b):
        return missing(a) and missing(b)
    return a == b


def test_replay_logs_the_command_lines_records(runs):
    df, py_out, cli_out = runs
    theirs = sunjitter.read_log(cli_out)
    assert list(df.columns) == list(theirs.columns)
    assert len(df) == len(theirs) == 54 + 72
    for column in df.columns:
        if column in SAME_RUN_EXCEPT:
            continue
        for a, b in zip(df[column], theirs[column]):
            assert _cells_equal(a, b), (column, a, b)
    assert df.attrs["sunjitter_replay"]["frames"] == 126


def test_read_log_has_every_column_of_inspect_csv_with_its_values(runs, cli, tmp_path):
    _, _, cli_out = runs
    csv = tmp_path / "series.csv"
    cli.run("inspect", cli_out, "--csv", csv)
    expected = pd.read_csv(csv, keep_default_na=False, na_values=[""], dtype={"message": str})
    got = sunjitter.read_log(cli_out)
    assert list(got.columns) == list(expected.columns)
    assert len(got) == len(expected)
    assert str(got["obs_time"].dtype) == "datetime64[ns, UTC]"
    assert (got["obs_time"] == pd.to_datetime(expected["obs_time"], utc=True)).all()
    for column in got.columns:
        if column == "obs_time":
            continue
        for a, b in zip(got[column], expected[column]):
            if isinstance(a, str) and a == "":
                a = None  # an empty text cell reads back as missing
            if isinstance(a, (bool,)) or str(got[column].dtype) == "boolean":
                b = None if _cells_equal(b, None) else (b in (True, "true"))
            assert _cells_equal(a, b), (column, a, b)
    assert got["sequence"].dtype == "int64"
    assert got["dx_px"].dtype == "float64"


def test_summary_is_inspects_statistics(runs, cli):
    _, _, cli_out = runs
    expected = cli.json("inspect", cli_out, "--json")
    df = sunjitter.read_log(cli_out)
    assert sunjitter.summary(df) == expected
    # A channel's rows alone: that channel's statistics.
    one = df[df["channel"] == "SJI_2796"]
    (channel,) = sunjitter.summary(one)["channels"]
    assert channel == next(c for c in expected["channels"] if c["channel"] == "SJI_2796")


# What `sunjitter.replay` passes with its defaults.
OPTIONS = {"reference": None, "recursive": False, "aligned": None, "wcs_only": False}


def test_progress_reaches_the_total_and_an_interrupted_run_resumes(tmp_path, cli, caplog):
    from sunjitter import _sunjitter

    out = tmp_path / "out"
    seen = []

    class Stop(KeyboardInterrupt):
        pass

    def on_progress(p):
        seen.append(p)
        if p["finished"] >= 5:
            raise Stop  # as Ctrl-C: the frames in hand are finished, the log closed

    with pytest.raises(Stop):
        _sunjitter.replay([str(IRIS_1400)], str(out), OPTIONS, on_progress=on_progress)
    partial = sunjitter.read_log(out)
    assert 5 <= len(partial) < 54
    seen.clear()
    with caplog.at_level(logging.WARNING, logger="sunjitter"):
        _sunjitter.replay([str(IRIS_1400)], str(out), OPTIONS, on_progress=seen.append)
    assert seen[-1]["finished"] == seen[-1]["total"]
    # The pipeline's warnings reach Python's logging: this cube's table is longer than it.
    assert any(
        "per-frame table has 540 rows for 54 frames" in r.getMessage()
        for r in caplog.records if r.name == "sunjitter"
    )
    whole = sunjitter.read_log(out)
    # Every frame once, none twice.
    assert sorted(whole["frame"]) == sorted(f"{IRIS_1400}[{n}]" for n in range(54))
    assert whole["frame"].is_unique
    # The resumed log reads as the command line's own uninterrupted run does.
    straight = tmp_path / "straight"
    cli.run("replay", IRIS_1400, "--out", straight)
    theirs = sunjitter.read_log(straight)
    # The measurements and the chain; a resumed chain's σ starts again from the σ logged.
    for column in ("frame", "dx_px", "dy_px", "sigma_dx_px", "rotation_arcsec", "chained_dx_px"):
        pd.testing.assert_series_equal(whole[column], theirs[column], check_exact=True)
