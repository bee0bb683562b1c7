"""What the command line says is true even when its own output fails, and it never prints a traceback.

Issue 30: ``fuse … | head -c1`` and ``> /dev/full`` said "error: Broken pipe" / "No space left on
device" (exit 2) after the new results were swapped in; ``tables >&-`` exited 0 with nothing
written anywhere; ``consistency`` on an ASCII-only terminal crashed on σ; NumPy RuntimeWarnings
came before the error line; an overflow, an exhausted memory, a pipe or a device given as a file
were exit 1 or hung.
"""

from __future__ import annotations

import errno
import os
import subprocess
import sys
import warnings
from pathlib import Path

import cv2
import numpy as np
import pytest

from kalmansfm.cli import tables
from kalmansfm.cli.main import main
from kalmansfm.errors import InvalidInputError
from kalmansfm.io.cameras import cameras_csv
from kalmansfm.io.tracks import observations_csv
from kalmansfm.scenes.known_cameras import known_camera_scene
from kalmansfm.structure.geometry.pinhole import CameraSet

SRC = Path(__file__).resolve().parents[2] / "src"
ENV = {**os.environ, "PYTHONPATH": str(SRC)}


@pytest.fixture(scope="module")
def fuse_inputs(tmp_path_factory) -> Path:
    folder = tmp_path_factory.mktemp("fuse")
    s = known_camera_scene(points=30, views=4, pixel_std=0.5, seed=1)
    frames = np.arange(4)
    (folder / "cameras.csv").write_text(cameras_csv(CameraSet(s.cameras.matrices, frames)))
    (folder / "tracks.csv").write_text(observations_csv(s.observations, frames, np.arange(30)))
    return folder


def _fuse(inputs: Path, out: Path) -> list[str]:
    return ["fuse", str(inputs / "tracks.csv"), "--cameras", str(inputs / "cameras.csv"), "--out", str(out), "--quiet"]


class _Broken:
    """A standard output whose reader is gone (or whose disk is full)."""

    def __init__(self, number: int) -> None:
        self.number = number

    def write(self, text: str) -> int:
        raise OSError(self.number, os.strerror(self.number))

    def flush(self) -> None:
        raise OSError(self.number, os.strerror(self.number))


@pytest.mark.parametrize("number", [errno.EPIPE, errno.ENOSPC])
def test_results_written_but_not_printed_is_exit_0_and_says_so(fuse_inputs, tmp_path, monkeypatch, capsys, number):
    monkeypatch.setattr(sys, "stdout", _Broken(number))
    code = main(_fuse(fuse_inputs, tmp_path / "run"))
    err = capsys.readouterr().err.splitlines()
    assert code == 0
    assert err == [f"kalmansfm fuse: wrote {tmp_path / 'run'}; what it printed could not be written to standard "
                   f"output ({os.strerror(number)})"]
    assert (tmp_path / "run" / "summary.json").exists() and (tmp_path / "run" / "structure.csv").exists()


@pytest.mark.parametrize("stdout", [_Broken(errno.EPIPE), None], ids=["closed pipe", "closed descriptor"])
def test_output_that_is_only_printed_and_cannot_be_is_an_error(monkeypatch, capsys, stdout):
    monkeypatch.setattr(sys, "stdout", stdout)
    assert main(["tables", "--task", "1"]) == 2
    err = capsys.readouterr().err.splitlines()
    assert len(err) == 1 and err[0].startswith("kalmansfm tables: error: cannot write to standard output (")
    assert err[0].endswith("); no results were written")


def test_a_closed_stdout_after_a_run_folder_is_written_is_exit_0(fuse_inputs, tmp_path, monkeypatch, capsys):
    monkeypatch.setattr(sys, "stdout", None)  # what Python makes of a closed descriptor 1 (`>&-`)
    assert main(_fuse(fuse_inputs, tmp_path / "run")) == 0
    assert "standard output is closed" in capsys.readouterr().err
    assert (tmp_path / "run" / "summary.json").exists()


@pytest.mark.skipif(sys.platform == "win32", reason="pipes and /dev/full are POSIX")
def test_a_real_closed_pipe_and_a_full_disk_say_the_results_were_written(fuse_inputs, tmp_path):
    reader, writer = os.pipe()
    os.close(reader)  # `| head -c0`: nobody reads
    try:
        closed = subprocess.run([sys.executable, "-m", "kalmansfm", *_fuse(fuse_inputs, tmp_path / "a")],
                                stdout=writer, stderr=subprocess.PIPE, text=True, env=ENV, timeout=120)
    finally:
        os.close(writer)
    assert closed.returncode == 0, closed.stderr
    assert closed.stderr.splitlines() == [f"kalmansfm fuse: wrote {tmp_path / 'a'}; what it printed could not be "
                                          "written to standard output (Broken pipe)"]  # no "Exception ignored"
    if os.path.exists("/dev/full"):
        with open("/dev/full", "w") as full:
            result = subprocess.run([sys.executable, "-m", "kalmansfm", *_fuse(fuse_inputs, tmp_path / "b")],
                                    stdout=full, stderr=subprocess.PIPE, text=True, env=ENV, timeout=120)
        assert result.returncode == 0 and "(No space left on device)" in result.stderr
        assert len(result.stderr.splitlines()) == 1


@pytest.mark.skipif(sys.platform == "win32", reason="closing descriptor 1 in the child is POSIX")
def test_a_real_closed_stdout_is_an_error_when_the_output_is_only_printed():
    result = subprocess.run([sys.executable, "-m", "kalmansfm", "tables", "--task", "1"], preexec_fn=lambda: os.close(1),
                            stderr=subprocess.PIPE, text=True, env=ENV, timeout=120)
    assert result.returncode == 2
    assert result.stderr.splitlines() == ["kalmansfm tables: error: cannot write to standard output (standard output "
                                          "is closed); no results were written"]


def test_an_ascii_terminal_gets_sigma_spelt_out_and_a_name_that_is_not_utf8_its_own_bytes(fuse_inputs, tmp_path):
    ascii_only = subprocess.run([sys.executable, "-m", "kalmansfm", "consistency", "--task", "2", "--runs", "5",
                                 "--quiet"], capture_output=True, env={**ENV, "PYTHONIOENCODING": "ascii"}, timeout=120)
    assert ascii_only.returncode == 0, ascii_only.stderr
    assert b"within 1sigma" in ascii_only.stdout and ascii_only.stderr == b""
    out = tmp_path / os.fsdecode(b"run\xff")
    strict = subprocess.run([sys.executable, "-m", "kalmansfm", *_fuse(fuse_inputs, out)], capture_output=True,
                            env={**ENV, "PYTHONIOENCODING": "utf-8:strict"}, timeout=120)
    assert strict.returncode == 0, strict.stderr
    assert strict.stdout.splitlines()[-1] == b"wrote " + os.fsencode(out)


def _command(monkeypatch, body) -> None:
    """Make ``kalmansfm tables`` run ``body(args)`` instead of printing a table."""
    monkeypatch.setattr(tables, "run", body)


def test_runtime_warnings_are_dropped_before_an_error_line_and_one_line_each_after_success(monkeypatch, capsys):
    def overflow_then(outcome):
        def body(args):
            warnings.simplefilter("default")
            np.float64(1e308) * 10  # RuntimeWarning: overflow encountered in scalar multiply
            if outcome == "error":
                raise InvalidInputError("focal must be finite and > 0; got 1e300")
            return 0
        return body

    _command(monkeypatch, overflow_then("error"))
    assert main(["tables", "--task", "1"]) == 2
    assert capsys.readouterr().err.splitlines() == ["kalmansfm tables: error: focal must be finite and > 0; got 1e300"]
    _command(monkeypatch, overflow_then("success"))
    assert main(["tables", "--task", "1"]) == 0
    err = capsys.readouterr().err.splitlines()
    assert err == ["warning: overflow encountered in scalar multiply (test_main_output.py:"
                   + err[0].rsplit(":", 1)[-1]] and "RuntimeWarning" not in err[0]


@pytest.mark.parametrize("raised, argv, code, line", [
    (MemoryError(), ["tables", "--task", "7", "--focal", "1e300"], 2,
     "kalmansfm tables: error: not enough memory for this run; --focal 1e+300 is probably too large for this machine"),
    (MemoryError(), ["tables", "--task", "1"], 2,
     "kalmansfm tables: error: not enough memory for this run; an input file or an option is too large for this machine"),
    (OverflowError(34, "Numerical result out of range"), ["tables", "--task", "7", "--pixel-std", "1e300"], 2,
     "kalmansfm tables: error: --pixel-std 1e+300: too far from any sensible value to compute with (Numerical "
     "result out of range)"),
    (OverflowError("int too large"), ["tables", "--task", "1"], 1,
     "kalmansfm tables: unexpected error: OverflowError: int too large (rerun with --debug for the traceback)"),
])
def test_memory_and_overflow_are_one_line_naming_the_option_that_explains_them(monkeypatch, capsys, raised, argv, code,
                                                                                line):
    _command(monkeypatch, lambda args: (_ for _ in ()).throw(raised))
    assert main(argv) == code
    assert capsys.readouterr().err.splitlines() == [line]


C_LOCALE = {**ENV, "LC_ALL": "C", "PYTHONCOERCECLOCALE": "0", "PYTHONUTF8": "0"}  # file names read as ASCII


@pytest.mark.skipif(sys.platform == "win32", reason="the C locale is POSIX")
def test_a_non_ascii_path_under_the_c_locale_is_tracked_and_printed_as_typed(tmp_path):
    """Issue 30: OpenCV crashed (SIGSEGV, exit 139) on the escaped name Python makes of 'dé' under LC_ALL=C."""
    frames = tmp_path / "dé"
    frames.mkdir()
    for k in range(3):
        (frames / f"f{k}.png").write_bytes(cv2.imencode(".png", np.full((40, 50), 60 * k + 20, np.uint8))[1].tobytes())
    result = subprocess.run([sys.executable, "-m", "kalmansfm", "track", "dé", "--out", "tö", "--quiet"],
                            cwd=tmp_path, capture_output=True, env=C_LOCALE, timeout=120)
    assert result.returncode == 0, result.stderr
    assert result.stdout.rstrip().endswith("results in tö".encode()) and result.stderr == b""
    assert (tmp_path / "tö" / "summary.json").exists()
    missing = subprocess.run([sys.executable, "-m", "kalmansfm", "reconstruct", "ä.csv", "--out", "x"], cwd=tmp_path,
                             capture_output=True, env=C_LOCALE, timeout=120)
    assert missing.returncode == 2
    assert missing.stderr == "kalmansfm reconstruct: error: ä.csv: no such file\n".encode()  # the name as typed
