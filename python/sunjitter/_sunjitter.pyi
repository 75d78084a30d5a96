"""Type stubs of the extension module (the Rust side); users call the functions of
``sunjitter`` itself, which wrap these."""

import os
from typing import Any, Callable, TypedDict

import numpy as np
import numpy.typing as npt

__version__: str

Cards = list[tuple[str, bool | int | float | str]]
# A path spec ("FILE.fits", "FILE.fits[N]") or (C-contiguous float32 pixels, FITS header cards, name).
Side = str | tuple[npt.NDArray[np.float32], bytes, str]

class _ReplayConfig(TypedDict, total=False):
    config_path: str | os.PathLike[str]
    config_table: str

class ReplayOptions(_ReplayConfig):
    """``replay``'s settings (the configuration's keys only when one is given)."""

    reference: str | None
    recursive: bool
    aligned: str | os.PathLike[str] | None
    wcs_only: bool

class Alignment:
    """A measurement, with what its products need of the pair."""

    @property
    def shapes(self) -> tuple[tuple[int, int], tuple[int, int]]: ...
    def record_json(self) -> str: ...
    def registered(
        self, frame: npt.NDArray[np.float32], frame_header: bytes, name: str
    ) -> tuple[npt.NDArray[np.float32], Cards]: ...
    def corrected_pointing(
        self, frame_header: bytes, shape: tuple[int, int], name: str
    ) -> Cards: ...

def align(
    reference: Side,
    frame: Side,
    names: tuple[str, str],
    config_path: str | os.PathLike[str] | None = None,
    config_table: str | None = None,
) -> Alignment: ...
def read_frame(spec: str) -> tuple[npt.NDArray[np.float32], Cards]: ...
def read_log(
    paths: list[str],
) -> tuple[list[str], list[list[Any]], list[str], str, str]: ...
def summary(
    columns: list[str],
    values: list[list[Any]],
    files: list[str],
    log: str | None,
    references: str | None,
) -> str: ...
def replay(
    paths: list[str],
    out: str | os.PathLike[str],
    options: ReplayOptions,
    on_progress: Callable[[dict[str, int]], None] | None = None,
) -> str: ...
