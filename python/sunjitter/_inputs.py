"""What the Rust side is given: path specs, pixels with FITS headers, configuration."""

from __future__ import annotations

import json
import os
import warnings
from collections.abc import Mapping
from typing import Any

import numpy as np

from ._errors import UsageError

#: Keys of a sunpy ``MetaDict`` that are not header cards.
_NOT_CARDS = {"keycomments"}


def is_path(value: Any) -> bool:
    return isinstance(value, (str, os.PathLike))


def is_map(value: Any) -> bool:
    """A sunpy Map (duck-typed, so sunpy is imported only where it is used)."""
    return hasattr(value, "fits_header") and hasattr(value, "data") and hasattr(value, "meta")


def config_args(config: Any) -> dict[str, Any]:
    """``config``: None, a TOML file (str or path), or a mapping with the file's tables."""
    if config is None:
        return {}
    if is_path(config):
        return {"config_path": os.fspath(config)}
    if isinstance(config, Mapping):
        return {"config_table": json.dumps(config)}
    raise UsageError(
        f"config must be a TOML file's path or a dict of its tables, not {type(config).__name__}"
    )


def header_bytes(header: Any, what: str) -> bytes:
    """A FITS header (astropy ``Header``, or a mapping of keys to values) as its 80-character
    cards, read on the Rust side by the same parser as the files' headers."""
    from astropy.io import fits

    if isinstance(header, fits.Header):
        text = header.tostring()
    elif isinstance(header, Mapping):
        made = fits.Header()
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", fits.verify.VerifyWarning)
            for key, value in header.items():
                key = str(key).upper()
                if key.lower() in _NOT_CARDS:
                    continue
                if key in ("HISTORY", "COMMENT"):
                    lines = value.splitlines() if isinstance(value, str) else list(value)
                    for line in lines:
                        made.add_history(line) if key == "HISTORY" else made.add_comment(line)
                elif isinstance(value, (bool, int, float, str, np.generic)):
                    made[key] = value.item() if isinstance(value, np.generic) else value
            text = made.tostring()
    else:
        raise UsageError(
            f"{what} must be an astropy Header or a dict, not {type(header).__name__}"
        )
    return text.encode("latin-1", errors="replace")


def pixels(data: Any, header: Any, what: str) -> np.ndarray:
    """``data`` as a 2-D, C-contiguous, aligned float32 array: the array itself where it is
    one already (read in place, never copied), else a converted copy. Integer pixels equal to
    the header's ``BLANK`` become NaN, as the FITS reader makes them."""
    from ._errors import BadInputError

    array = np.asarray(data)
    if array.ndim != 2:
        raise BadInputError(f"{what}: the array is {array.ndim}-D; an image is 2-D (height, width)")
    if array.dtype.kind not in "fiu":
        raise BadInputError(f"{what}: the array holds {array.dtype}, not numbers")
    blank = None
    if array.dtype.kind in "iu" and header is not None:
        try:
            blank = header.get("BLANK") if hasattr(header, "get") else None
        except Exception:  # noqa: BLE001 - a header without BLANK
            blank = None
    converted = np.require(array, dtype=np.float32, requirements=["C", "A"])
    if blank is not None:
        converted = converted.copy() if converted is array else converted
        converted[array == blank] = np.nan
    return converted
