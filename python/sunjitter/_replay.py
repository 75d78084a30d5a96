"""``replay``: the command line's pipeline over archived files, with a progress bar."""

from __future__ import annotations

import json
import os
import warnings
from collections.abc import Iterable
from typing import Any

from . import _inputs
from ._log import read_log
from ._sunjitter import replay as _replay


def replay(
    inputs: str | os.PathLike[str] | Iterable[str | os.PathLike[str]],
    out: str | os.PathLike[str],
    *,
    reference: str | None = None,
    config: Any = None,
    recursive: bool = False,
    aligned: str | os.PathLike[str] | None = None,
    wcs_only: bool = False,
    progress: bool = True,
) -> Any:
    """Run ``sunjitter replay INPUTS… --out OUT`` and return the log as :func:`read_log` does.

    The same pipeline as the command line, writing the same MCAP log (the same records):
    ``inputs`` are FITS files, directories, globs or 3-D cubes; ``reference`` is the policy
    (``"keyframe"``, ``"previous"``, ``"fixed:FILE"``, ``"channel:NAME"``); ``config`` a TOML
    file or a dict of its tables; ``aligned=DIR`` writes each frame's product
    (``wcs_only=True``: the corrected header on the frame's own pixels). An ``out`` that holds
    this run's log resumes it. ``progress`` shows a tqdm bar (a widget in Jupyter).

    Ctrl-C stops it as SIGINT stops the command: the frames in hand are finished, the log is
    closed, ``KeyboardInterrupt`` is raised; running it again into the same ``out`` takes the rest.

    The DataFrame's ``attrs["sunjitter_replay"]`` holds the run's summary (what
    ``replay --json`` prints).

    >>> df = sunjitter.replay("data/real/iris_l2_20140329_140938_3860258481_SJI_1400_t000.fits",
    ...                       out="out/sji1400")
    """
    if isinstance(inputs, (str, os.PathLike)):
        inputs = [inputs]
    paths = [os.fspath(p) for p in inputs]
    bar = None

    def on_progress(p: dict[str, int]) -> None:
        nonlocal bar
        if bar is None:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                from tqdm.auto import tqdm
            bar = tqdm(total=p["total"], unit="frame", desc="replay", disable=not progress)
        bar.n = p["finished"]
        bar.set_postfix(
            ok=p["ok"], degraded=p["degraded"], failed=p["failed"], skipped=p["skipped"],
            refresh=False,
        )
        bar.refresh()

    try:
        summary = _replay(
            paths,
            os.fspath(out),
            {
                "reference": reference,
                "recursive": recursive,
                "aligned": None if aligned is None else os.fspath(aligned),
                "wcs_only": wcs_only,
                **_inputs.config_args(config),
            },
            on_progress=on_progress,
        )
    finally:
        if bar is not None:
            bar.close()
    frame = read_log(out)
    frame.attrs["sunjitter_replay"] = json.loads(summary)
    return frame
