"""``align`` against ``sunjitter align --json`` on the same images: every field, bit for bit
(all but the run's own ``elapsed_ms``, and the names where the inputs are not paths)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from astropy.io import fits

import sunjitter
from conftest import EIT_171, EIT_195, IRIS_1400, without

TIMING = ("elapsed_ms",)
NAMES = ("reference", "frame")


def same_but_names(got, expected, files) -> None:
    """``got`` is ``expected`` but for the run's time and the inputs' names, also where the
    message names a file (by its base name) as the result names the input."""
    want = without(expected, *TIMING, *NAMES)
    for path, name in zip(files, (got.reference, got.frame)):
        want["message"] = want["message"].replace(f"{path.name}:", f"{Path(name).name}:")
    assert without(got.to_dict(), *TIMING, *NAMES) == want


def test_cube_frames_by_path_give_the_command_lines_record(cli):
    ref, frame = f"{IRIS_1400}[0]", f"{IRIS_1400}[5]"
    expected = cli.json("align", ref, frame, "--json")
    got = sunjitter.align(ref, frame)
    assert without(got.to_dict(), *TIMING) == without(expected, *TIMING)
    assert got.status == "ok" and got.dx_px == expected["dx_px"]
    # Every field of the record is an attribute, in the record's order.
    assert got.fields == list(expected)
    for name, value in expected.items():
        if name not in TIMING:
            assert getattr(got, name) == value


def _file(path):
    with fits.open(path) as hdul:
        return hdul[0].data, hdul[0].header


def test_arrays_with_astropy_headers_give_the_files_record(cli):
    expected = cli.json("align", EIT_171, EIT_195, "--json")
    (ref, ref_header), (frame, frame_header) = _file(EIT_171), _file(EIT_195)
    got = sunjitter.align(ref, frame, reference_header=ref_header, frame_header=frame_header)
    same_but_names(got, expected, (EIT_171, EIT_195))
    assert (got.reference, got.frame) == ("<reference array>", "<frame array>")


def test_arrays_with_dict_headers_give_the_files_record(cli):
    expected = cli.json("align", EIT_171, EIT_195, "--json")
    (ref, ref_header), (frame, frame_header) = _file(EIT_171), _file(EIT_195)
    # Native float32 in C order: read in place.
    ref32 = np.ascontiguousarray(ref, dtype=np.float32)
    got = sunjitter.align(
        ref32, frame, reference_header=dict(ref_header), frame_header=dict(frame_header)
    )
    same_but_names(got, expected, (EIT_171, EIT_195))


def test_sunpy_maps_give_the_files_record(cli):
    import sunpy.map

    expected = cli.json("align", EIT_171, EIT_195, "--json")
    got = sunjitter.align(sunpy.map.Map(EIT_171), sunpy.map.Map(EIT_195))
    same_but_names(got, expected, (EIT_171, EIT_195))


def test_mixed_path_and_map(cli):
    import sunpy.map

    expected = cli.json("align", EIT_171, EIT_195, "--json")
    got = sunjitter.align(str(EIT_171), sunpy.map.Map(EIT_195))
    assert got.reference == str(EIT_171)
    same_but_names(got, expected, (EIT_171, EIT_195))


def test_cube_frames_read_as_maps_give_the_paths_record(cli, tmp_path):
    """``read_map`` gives a cube frame the 2-D header ``split_cube`` writes: the command line
    on those 2-D files and ``align`` on the Maps agree bit for bit."""
    maps = [sunjitter.read_map(f"{IRIS_1400}[{n}]") for n in (0, 7)]
    files = []
    for n, m in zip((0, 7), maps):
        path = tmp_path / f"f{n}.fits"
        fits.PrimaryHDU(m.data, m.fits_header).writeto(path)
        files.append(path)
    expected = cli.json("align", *files, "--json")
    got = sunjitter.align(*maps)
    assert (got.reference, got.frame) == (f"{IRIS_1400}[0]", f"{IRIS_1400}[7]")
    same_but_names(got, expected, files)
    # And the cube read directly: the same measurement to well within its σ.
    direct = sunjitter.align(f"{IRIS_1400}[0]", f"{IRIS_1400}[7]")
    for p in ("dx_px", "dy_px", "rotation_arcsec"):
        assert abs(getattr(got, p) - getattr(direct, p)) < 0.01 * getattr(direct, "sigma_" + p)


def test_a_failed_alignment_is_a_result_with_the_command_lines_reason(cli, tmp_path):
    header = fits.getheader(EIT_171)
    flat = np.full((128, 128), 7.0, dtype=np.float32)
    path = tmp_path / "flat.fits"
    fits.PrimaryHDU(flat, header).writeto(path)
    expected = cli.json("align", EIT_171, path, "--json")
    got = sunjitter.align(str(EIT_171), flat, frame_header=header)
    assert got.status == expected["status"] == "failed"
    assert got.message == expected["message"]
    assert got.dx_px is None and not got.ok
    assert "failed" in repr(got)


def test_the_result_reads_like_a_record():
    r = sunjitter.align(f"{IRIS_1400}[0]", f"{IRIS_1400}[3]")
    text = repr(r)
    assert text.startswith("AlignResult(status='ok', dx_px=") and "±" in text
    d = r.to_dict()
    d["dx_px"] = 99.0
    assert r.dx_px != 99.0  # a copy
    assert "sigma_dy_arcsec" in dir(r)
    with pytest.raises(AttributeError):
        r.no_such_field


def test_configuration_as_a_dict_or_a_file(cli, tmp_path):
    toml = tmp_path / "c.toml"
    toml.write_text('[engine]\nsolar_rotation = "none"\n')
    expected = cli.json("align", EIT_171, EIT_195, "--json", "--config", toml)
    by_file = sunjitter.align(EIT_171, EIT_195, config=toml)
    by_dict = sunjitter.align(EIT_171, EIT_195, config={"engine": {"solar_rotation": "none"}})
    assert without(by_file.to_dict(), *TIMING) == without(expected, *TIMING)
    assert without(by_dict.to_dict(), *TIMING) == without(expected, *TIMING)
    assert expected["solar_rotation"]["profile"] == "none"


def test_pixels_are_read_in_place_where_they_can_be():
    from sunjitter import _inputs

    native = np.zeros((4, 5), dtype=np.float32)
    assert _inputs.pixels(native, None, "frame") is native
    big_endian = native.astype(">f4")
    converted = _inputs.pixels(big_endian, None, "frame")
    assert converted is not big_endian and converted.dtype == np.float32
    strided = np.zeros((4, 10), dtype=np.float32)[:, ::2]
    assert _inputs.pixels(strided, None, "frame").flags.c_contiguous
    ints = np.array([[1, -5], [3, 4]], dtype=np.int16)
    blanked = _inputs.pixels(ints, {"BLANK": -5}, "frame")
    assert np.isnan(blanked[0, 1]) and blanked[1, 0] == 3.0


INTERRUPTED = r"""
import glob, os, signal, sys, threading, traceback
import numpy as np
from astropy.io import fits
import sunjitter

pair = [fits.open(p)[0] for p in sys.argv[1:3]]
images = [(np.ascontiguousarray(h.data, dtype=np.float32), h.header) for h in pair]

def workers():
    names = []
    for comm in glob.glob("/proc/self/task/*/comm"):
        try:
            names.append(open(comm).read().strip())
        except OSError:
            pass
    return names.count("sunjitter align")

def align():
    return sunjitter.align(images[0][0], images[1][0],
                           reference_header=images[0][1], frame_header=images[1][1])

align()  # the engine's thread pool made (its threads may carry the worker's name)
before = workers()

def interrupt_once_the_engine_runs():
    while workers() <= before:
        pass
    os.kill(os.getpid(), signal.SIGINT)

threading.Thread(target=interrupt_once_the_engine_runs, daemon=True).start()
try:
    # The interrupter may miss a short alignment between two of its looks: it gets more.
    for _ in range(100):
        align()
    print("finished")
except KeyboardInterrupt as e:
    innermost = traceback.extract_tb(e.__traceback__)[-1]
    print("interrupted in:", innermost.line)
"""


def test_ctrl_c_interrupts_a_running_alignment(cli, tmp_path):
    """Ctrl-C while the engine runs raises KeyboardInterrupt from within the call (the
    engine's own thread finishes unseen), also when it comes just before the call ends."""
    import subprocess
    import sys

    cli.run("synth", "--out", tmp_path, "--frames", "2", "--size", "1024")
    script = tmp_path / "interrupted.py"
    script.write_text(INTERRUPTED)
    done = subprocess.run(
        [sys.executable, str(script), str(tmp_path / "synth_0000.fits"),
         str(tmp_path / "synth_0001.fits")],
        capture_output=True, text=True, cwd=tmp_path,
    )
    assert done.returncode == 0, done.stderr
    assert done.stdout.startswith("interrupted in:") and "_align(ref_arg" in done.stdout
