"""``align``: one frame against one reference, and the result."""

from __future__ import annotations

import copy
import json
import os
from typing import Any

from . import _inputs
from ._errors import UsageError
from ._sunjitter import Alignment
from ._sunjitter import align as _align


class AlignResult:
    """Where the reference's content appears in the frame, with 1-σ errors.

    The fields are those of ``sunjitter align --json`` (the contract's record), as
    attributes and in :meth:`to_dict`: ``p_frame = s·R(θ)·(p_ref − c) + c + (dx, dy)``, with
    ``c`` the reference array's centre, 0-based pixels, ``x`` the column and ``y`` the row.
    Numbers are ``None`` where ``status`` is ``"failed"``; ``message`` says why a result is
    ``"degraded"`` or ``"failed"``. Fields the engine adds to its record appear here too.

    >>> cube = "data/real/iris_l2_20140329_140938_3860258481_SJI_1400_t000.fits"
    >>> r = sunjitter.align(f"{cube}[0]", f"{cube}[5]")
    >>> r.status, round(r.dx_px, 3), round(r.sigma_dx_px, 3)
    ('ok', -0.239, 0.049)
    """

    reference: str
    frame: str
    scale: float | None
    rotation_arcsec: float | None
    dx_px: float | None
    dy_px: float | None
    dx_arcsec: float | None
    dy_arcsec: float | None
    sigma_scale: float | None
    sigma_rotation_arcsec: float | None
    sigma_dx_px: float | None
    sigma_dy_px: float | None
    sigma_dx_arcsec: float | None
    sigma_dy_arcsec: float | None
    uabjm_sigma_scale: float | None
    uabjm_sigma_rotation_arcsec: float | None
    uabjm_sigma_dx_px: float | None
    uabjm_sigma_dy_px: float | None
    header_residual: dict[str, float] | None
    solar_rotation: dict[str, Any] | None
    points: int
    inliers: int
    residual_rms_px: float | None
    similarity: float | None
    status: str
    message: str
    elapsed_ms: float

    def __init__(self, alignment: Alignment) -> None:
        self._alignment = alignment
        self._record: dict[str, Any] = json.loads(alignment.record_json())

    def __getattr__(self, name: str) -> Any:
        record = self.__dict__.get("_record")
        if record is not None and name in record:
            return record[name]
        raise AttributeError(f"{type(self).__name__!r} has no field {name!r}")

    def __dir__(self) -> list[str]:
        return sorted(set(super().__dir__()) | set(self._record))

    @property
    def fields(self) -> list[str]:
        """The record's field names, in the record's order."""
        return list(self._record)

    @property
    def ok(self) -> bool:
        """Whether there is a result (``status`` is ``"ok"`` or ``"degraded"``)."""
        return self._record["status"] != "failed"

    def to_dict(self) -> dict[str, Any]:
        """The record as ``sunjitter align --json`` prints it (a copy)."""
        return copy.deepcopy(self._record)

    def __repr__(self) -> str:
        r = self._record

        def pm(value: str, sigma: str, unit: str = "") -> str:
            v, s = r.get(value), r.get(sigma)
            if v is None:
                return f"{value}=None"
            return f"{value}={v:.6g}{unit}" + (f" ± {s:.2g}" if s is not None else "")

        parts = [f"status={r['status']!r}"]
        if r.get("dx_px") is not None:
            parts += [
                pm("dx_px", "sigma_dx_px"),
                pm("dy_px", "sigma_dy_px"),
                pm("rotation_arcsec", "sigma_rotation_arcsec"),
                pm("scale", "sigma_scale"),
            ]
        parts += [f"reference={r['reference']!r}", f"frame={r['frame']!r}"]
        if r.get("message"):
            parts.append(f"message={r['message']!r}")
        return f"AlignResult({', '.join(parts)})"


def _side(value: Any, header: Any, which: str) -> tuple[Any, str]:
    """What the Rust side takes for one image, and its name in the record."""
    if _inputs.is_path(value):
        if header is not None:
            raise UsageError(f"{which}_header= is for arrays; {which} is a path")
        spec = os.fspath(value)
        return spec, spec
    if _inputs.is_map(value):
        if header is not None:
            raise UsageError(f"{which}_header= is for arrays; {which} is a Map with its own")
        header, name, value = value.fits_header, map_name(value), value.data
    else:
        if header is None:
            raise UsageError(
                f"{which} is an array: give its FITS header as {which}_header= "
                "(an astropy Header or a dict)"
            )
        name = f"<{which} array>"
    data = _inputs.pixels(value, header, which)
    return (data, _inputs.header_bytes(header, f"{which}_header"), name), name


def map_name(m: Any) -> str:
    """A Map's name in records: the frame it was read from (``FILE`` or ``FILE[N]``, as
    :func:`sunjitter.read_map` notes it), else ``<map>``."""
    meta = m.meta
    source = meta.get("srcfile")
    if source:
        frame = meta.get("srcframe")
        return f"{source}[{frame}]" if frame is not None else str(source)
    return "<map>"


def align(
    reference: Any,
    frame: Any,
    *,
    config: Any = None,
    reference_header: Any = None,
    frame_header: Any = None,
) -> AlignResult:
    """Align ``frame`` to ``reference``: shift, rotation and scale with 1-σ errors.

    Each of ``reference`` and ``frame`` is a FITS path (``"FILE.fits"``, or
    ``"FILE.fits[N]"`` for frame N of a cube), a sunpy Map, or a 2-D numpy array with its FITS
    header given as ``reference_header=`` / ``frame_header=`` (an astropy ``Header`` or a
    dict). The numbers are those of ``sunjitter align --json`` on the same images, bit for bit.

    Arrays are read where they lie when they are C-contiguous native float32 (other types are
    converted first); do not change them while ``align`` runs. The engine runs with the GIL
    released; Ctrl-C raises ``KeyboardInterrupt`` at once.

    ``config`` is a TOML file as the command line's ``--config`` (its ``[engine]`` table is
    used) or a dict of the same tables, e.g. ``{"engine": {"solar_rotation": "none"}}``.

    Raises :class:`BadInputError` (a file or array sunjitter cannot use),
    :class:`InputNotFoundError`, :class:`SunjitterIOError`, :class:`UsageError`.

    >>> import sunjitter
    >>> cube = "data/real/iris_l2_20140329_140938_3860258481_SJI_1400_t000.fits"
    >>> r = sunjitter.align(f"{cube}[0]", f"{cube}[1]")
    >>> r.status, r.fields[:4]
    ('ok', ['reference', 'frame', 'scale', 'rotation_arcsec'])
    """
    ref_arg, ref_name = _side(reference, reference_header, "reference")
    frame_arg, frame_name = _side(frame, frame_header, "frame")
    alignment = _align(ref_arg, frame_arg, (ref_name, frame_name), **_inputs.config_args(config))
    return AlignResult(alignment)
