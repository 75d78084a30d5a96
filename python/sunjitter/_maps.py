"""sunpy Maps: frames read as the engine reads them, and the products of a measurement."""

from __future__ import annotations

import os
import warnings
from typing import Any

from . import _inputs
from ._align import AlignResult, map_name
from ._errors import UsageError
from ._sunjitter import read_frame as _read_frame


def _header(cards: list[tuple[str, Any]]) -> Any:
    from astropy.io import fits

    header = fits.Header()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", fits.verify.VerifyWarning)
        for key, value in cards:
            if key == "HISTORY":
                header.add_history(value)
            elif key == "COMMENT":
                header.add_comment(value)
            else:
                header[key] = value
    return header


def _map(data: Any, cards: list[tuple[str, Any]]) -> Any:
    import sunpy.map

    return sunpy.map.Map(data, _header(cards))


def read_map(spec: str | os.PathLike[str]) -> Any:
    """One image, or frame N of a cube (``"FILE.fits[N]"``), as a sunpy Map, read as the
    engine reads it: float32 pixels (``BLANK`` and ``BSCALE``/``BZERO`` applied) and, for a cube
    frame, a 2-D header with the frame's own time, exposure and pointing (IRIS's per-frame
    table). ``SRCFILE``/``SRCFRAME`` name where it came from.

    >>> m = sunjitter.read_map("data/real/iris_l2_20140329_140938_3860258481_SJI_1400_t000.fits[3]")
    >>> m.meta["srcframe"], m.data.dtype
    (3, dtype('float32'))
    """
    data, cards = _read_frame(os.fspath(spec))
    return _map(data, cards)


def _check(frame_map: Any, result: AlignResult) -> None:
    if not _inputs.is_map(frame_map):
        raise UsageError(f"frame_map must be a sunpy Map, not {type(frame_map).__name__}")
    if not isinstance(result, AlignResult):
        raise UsageError(f"result must be sunjitter.align's result, not {type(result).__name__}")


def correct_pointing(frame_map: Any, result: AlignResult) -> Any:
    """``frame_map`` with its pointing corrected from the measurement ``result`` (of
    ``align(reference, frame_map)``): a new Map with the same pixels (not resampled, not
    copied) and a WCS under which each pixel has the world coordinates of the matching
    reference pixel, so a solar feature gets the coordinates the reference's header gives it.
    The analogue of aiapy's ``update_pointing``, from a measurement instead of a pointing table.

    Only the linear part of the WCS changes (``CRPIXi`` moves, ``CDELTi`` takes the scale,
    ``PCi_j`` the rotation; ``CRVALi``, ``CTYPEi``, ``CUNITi`` are the reference's), so this holds
    for any projection; cards that would still describe the old pointing (``XCEN``/``YCEN``,
    alternate WCS, ``SC_ROLL``, …) are dropped, and ``HISTORY`` says what was done. This is
    ``watch``/``replay --aligned DIR --wcs-only``'s product for one pair.

    Raises :class:`AlignmentFailedError` when the alignment failed.
    """
    _check(frame_map, result)
    cards = result._alignment.corrected_pointing(
        _inputs.header_bytes(frame_map.fits_header, "frame_map"),
        tuple(frame_map.data.shape),
        map_name(frame_map),
    )
    return _map(frame_map.data, cards)


def register(frame_map: Any, result: AlignResult) -> Any:
    """``frame_map`` resampled onto the reference's pixel grid through the measurement
    ``result`` (of ``align(reference, frame_map)``): what ``sunjitter align --aligned OUT.fits``
    writes, by the same code. Quintic B-spline, NaN where the frame has no data; the reference's
    WCS, the frame's other cards, ``HISTORY`` saying what was applied.

    Raises :class:`AlignmentFailedError` when the alignment failed.
    """
    _check(frame_map, result)
    header = frame_map.fits_header
    data = _inputs.pixels(frame_map.data, header, "frame_map")
    resampled, cards = result._alignment.registered(
        data, _inputs.header_bytes(header, "frame_map"), map_name(frame_map)
    )
    return _map(resampled, cards)
