"""Errors: Python exceptions of the documented classes, carrying the command line's line."""

from __future__ import annotations

import numpy as np
import pytest
from astropy.io import fits

import sunjitter
from conftest import EIT_171, IRIS_1400, NOT_FITS


def test_a_file_that_is_not_fits(cli):
    code, line = cli.error_line("align", EIT_171, NOT_FITS)
    assert code == 2
    with pytest.raises(sunjitter.BadInputError) as e:
        sunjitter.align(EIT_171, NOT_FITS)
    assert str(e.value) == line
    assert isinstance(e.value, ValueError) and isinstance(e.value, sunjitter.SunjitterError)


def test_a_missing_file(cli, tmp_path):
    missing = tmp_path / "nowhere.fits"
    code, line = cli.error_line("align", EIT_171, missing)
    assert code == 2
    with pytest.raises(FileNotFoundError) as e:
        sunjitter.align(EIT_171, missing)
    assert isinstance(e.value, sunjitter.InputNotFoundError)
    assert str(e.value) == line
    assert e.value.filename == str(missing) and e.value.errno == 2


def test_a_cube_without_its_frame_number(cli):
    code, line = cli.error_line("align", f"{IRIS_1400}[0]", IRIS_1400)
    assert code == 2
    with pytest.raises(sunjitter.BadInputError) as e:
        sunjitter.align(f"{IRIS_1400}[0]", IRIS_1400)
    assert str(e.value) == line and "name one as FILE[N]" in line


def test_a_log_directory_without_logs(cli, tmp_path):
    code, line = cli.error_line("inspect", tmp_path)
    assert code == 2
    with pytest.raises(sunjitter.BadInputError) as e:
        sunjitter.read_log(tmp_path)
    assert str(e.value) == line


def test_products_inside_the_log_are_refused(cli, tmp_path):
    out = tmp_path / "out"
    code, line = cli.error_line("replay", IRIS_1400, "--out", out, "--aligned", out / "products")
    assert code == 2
    with pytest.raises(sunjitter.SunjitterError) as e:
        sunjitter.replay(IRIS_1400, out=out, aligned=out / "products", progress=False)
    assert str(e.value) == line


def test_a_bad_configuration(cli, tmp_path):
    toml = tmp_path / "bad.toml"
    toml.write_text("[daemon]\nworkers = 0\n")
    code, line = cli.error_line("align", EIT_171, EIT_171, "--config", toml)
    assert code == 2
    with pytest.raises(sunjitter.UsageError) as e:
        sunjitter.align(EIT_171, EIT_171, config={"daemon": {"workers": 0}})
    assert str(e.value) == line
    with pytest.raises(sunjitter.UsageError, match="no_such_setting"):
        sunjitter.align(EIT_171, EIT_171, config={"engine": {"no_such_setting": 1}})


def test_arrays_that_cannot_be_images():
    header = fits.getheader(EIT_171)
    with pytest.raises(sunjitter.BadInputError, match="3-D"):
        sunjitter.align(EIT_171, np.zeros((2, 128, 128)), frame_header=header)
    with pytest.raises(sunjitter.BadInputError, match="NAXIS1 = 128"):
        sunjitter.align(EIT_171, np.zeros((128, 64), dtype=np.float32), frame_header=header)
    with pytest.raises(sunjitter.UsageError, match="frame_header="):
        sunjitter.align(EIT_171, np.zeros((128, 128)))
