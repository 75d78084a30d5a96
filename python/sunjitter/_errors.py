"""The exceptions sunjitter raises.

Each carries, as its message, the one line the command line prints for the same problem
(without the ``sunjitter:`` prefix): the file and what is wrong with it. They derive from the
built-in exception a Python user would catch for the same problem::

    SunjitterError                      every error of the package
    ├── BadInputError (ValueError)      an input sunjitter cannot use: not FITS, truncated, a
    │                                   header without the keys it needs, a cube frame that
    │                                   does not exist, an array and header that disagree
    ├── UsageError (ValueError)         arguments or configuration that cannot work
    ├── AlignmentFailedError (RuntimeError)
    │                                   a product asked of an alignment that failed
    └── SunjitterIOError (OSError)      a file that cannot be read or written
        ├── InputNotFoundError (FileNotFoundError)
        └── OutputRefusedError          an output that would overwrite an input or a log, or
                                        that another process holds

The command line exits with code 2 for ``BadInputError``, ``UsageError``,
``InputNotFoundError`` and ``OutputRefusedError``, and 1 for the others.
"""

from __future__ import annotations


class SunjitterError(Exception):
    """Base class of every error sunjitter raises."""


class BadInputError(SunjitterError, ValueError):
    """An input sunjitter cannot use (the file or array, and why)."""


class UsageError(SunjitterError, ValueError):
    """Arguments or configuration that cannot work."""


class AlignmentFailedError(SunjitterError, RuntimeError):
    """A product (a corrected or resampled map) asked of an alignment that failed."""


class SunjitterIOError(SunjitterError, OSError):
    """A file that cannot be read or written; ``filename`` names it, ``errno`` says why."""

    def __str__(self) -> str:
        return self.strerror if self.strerror is not None else super().__str__()


class InputNotFoundError(SunjitterIOError, FileNotFoundError):
    """An input file or directory that does not exist."""


class OutputRefusedError(SunjitterIOError):
    """An output refused before any work: it would overwrite an input or a log, or another
    process holds the output directory."""


__all__ = [
    "SunjitterError",
    "BadInputError",
    "UsageError",
    "AlignmentFailedError",
    "SunjitterIOError",
    "InputNotFoundError",
    "OutputRefusedError",
]
