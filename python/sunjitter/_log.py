"""``read_log`` and ``summary``: MCAP logs as pandas DataFrames, and ``inspect``'s statistics."""

from __future__ import annotations

import json
import os
from collections.abc import Iterable
from typing import Any

from ._sunjitter import read_log as _read_log
from ._sunjitter import summary as _summary

#: ``DataFrame.attrs`` keys: the logs read, and their ``/log`` tally (``inspect --json``'s ``log``).
FILES_ATTR = "sunjitter_files"
LOG_ATTR = "sunjitter_log"
REFERENCES_ATTR = "sunjitter_references"


def _paths(paths: Any) -> list[str]:
    if isinstance(paths, (str, os.PathLike)):
        return [os.fspath(paths)]
    return [os.fspath(p) for p in paths]


def _column(name: str, cells: list[Any]) -> Any:
    import numpy as np
    import pandas as pd

    if name == "obs_time":
        times = pd.to_datetime(
            pd.Series([c or None for c in cells], dtype=object), utc=True, format="ISO8601"
        )
        return times.astype("datetime64[ns, UTC]")
    kinds = {type(c) for c in cells if c is not None}
    missing = any(c is None for c in cells)
    if kinds and kinds <= {bool}:
        return pd.Series(cells, dtype="boolean" if missing else bool)
    if kinds and kinds <= {int}:
        return pd.Series(cells, dtype="Int64" if missing else np.int64)
    if kinds <= {int, float}:
        return pd.Series([np.nan if c is None else c for c in cells], dtype=np.float64)
    return pd.Series(cells, dtype=object)


def read_log(path: str | os.PathLike[str] | Iterable[str | os.PathLike[str]]) -> Any:
    """A log (an ``--out`` directory, its ``.mcap`` segments, or several) as a pandas
    DataFrame: one row per frame, with every column of ``sunjitter inspect --csv`` (same names,
    same order, same values): ``log_time_ns``, the record's fields, nested objects flattened as
    ``header_residual_<field>`` and ``solar_rotation_<field>``, then any field a newer record
    adds. ``obs_time`` is a UTC datetime; empty cells are NaN (numbers) or None.

    Rows are grouped by channel and in time order, as ``inspect`` reads them; damaged or
    unfinished segments are read as far as they go (a warning on the ``sunjitter`` logger).

    >>> df = sunjitter.read_log("out/sji1400")
    >>> df.groupby("channel").chained_dx_arcsec.std()
    """
    import pandas as pd

    columns, values, files, log, references = _read_log(_paths(path))
    frame = pd.DataFrame({name: _column(name, cells) for name, cells in zip(columns, values)})
    frame = frame[columns] if columns else frame
    frame.attrs[FILES_ATTR] = files
    frame.attrs[LOG_ATTR] = log
    frame.attrs[REFERENCES_ATTR] = references
    return frame


def _cells(series: Any, name: str) -> list[Any]:
    import pandas as pd

    if name == "obs_time":
        return [None if pd.isna(t) else int(pd.Timestamp(t).value) for t in series]
    return [None if _missing(v) else v for v in series.astype(object).tolist()]


def _missing(value: Any) -> bool:
    import pandas as pd

    try:
        return bool(pd.isna(value))
    except (TypeError, ValueError):
        return False


def summary(df: Any) -> dict[str, Any]:
    """``sunjitter inspect --json``'s statistics of the frames in ``df`` (a :func:`read_log`
    DataFrame, or rows of one), computed by the same code: per channel the frame counts, RMS
    and peak-to-peak of each parameter (raw and chained), median σ, the jitter periodogram's
    peaks and the 5σ outliers; then ``consistency``: the models fitted, each channel's keyframe
    closures (from the log's ``/reference`` messages, kept with the DataFrame), and every two
    channels of one instrument compared. For a whole log it is ``inspect --json``'s document.

    >>> s = sunjitter.summary(df)
    >>> s["channels"][0]["chained"]["dx_px"]["rms"]
    """
    columns = [str(c) for c in df.columns]
    values = [_cells(df[c], c) for c in columns]
    files = list(df.attrs.get(FILES_ATTR, []))
    log = df.attrs.get(LOG_ATTR)
    references = df.attrs.get(REFERENCES_ATTR)
    return json.loads(_summary(columns, values, files, log, references))
