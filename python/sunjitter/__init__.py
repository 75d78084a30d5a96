"""sunjitter: pointing jitter of solar telescopes, from Python.

The command line's Rust engine and pipeline, called directly (never the binary):

- :func:`align` one frame to one reference (paths, numpy arrays with headers, sunpy Maps),
- :func:`correct_pointing` and :func:`register`: a frame's Map with its WCS corrected, or
  resampled onto the reference's grid,
- :func:`replay` archived files into an MCAP log, :func:`read_log` a log as a pandas
  DataFrame (the columns of ``inspect --csv``), :func:`summary` its statistics,
- :func:`read_map` an image or cube frame as the engine reads it.

Errors are :class:`SunjitterError` subclasses (also ``ValueError`` or ``OSError``) carrying
the command line's one-line message. Log lines go to the ``logging`` logger ``sunjitter``.
See docs/python.md for a worked example.
"""

from ._sunjitter import __version__
from ._errors import (
    AlignmentFailedError,
    BadInputError,
    InputNotFoundError,
    OutputRefusedError,
    SunjitterError,
    SunjitterIOError,
    UsageError,
)
from ._align import AlignResult, align
from ._maps import correct_pointing, read_map, register
from ._log import read_log, summary
from ._replay import replay

__all__ = [
    "__version__",
    "align",
    "AlignResult",
    "correct_pointing",
    "register",
    "read_map",
    "replay",
    "read_log",
    "summary",
    "SunjitterError",
    "BadInputError",
    "UsageError",
    "AlignmentFailedError",
    "SunjitterIOError",
    "InputNotFoundError",
    "OutputRefusedError",
]
