"""The one mechanism that owns a run folder (kalmansfm.io.atomic) and the record of what a run was made from."""

from __future__ import annotations

import errno
import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from kalmansfm.errors import Interrupted, InvalidInputError
from kalmansfm.io import RunSummary, summary_json
from kalmansfm.io import atomic
from kalmansfm.io.atomic import atomic_write, check_output_directory, output_directory
from kalmansfm.io.summary import run_source


def _a_dead_pid() -> int:
    """The id of a process that has finished (ids are reused only after many others)."""
    return int(subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"],
                              capture_output=True, text=True, check=True).stdout)


def _run(folder: Path, **files: str) -> None:
    """An earlier kalmansfm run in ``folder`` with ``files`` (name: text)."""
    folder.mkdir(parents=True)
    for name, text in files.items():
        (folder / name).write_text(text)
    (folder / "summary.json").write_text(summary_json(RunSummary("track", "earlier", files=(*files, "summary.json"))))


def _entries(parent: Path) -> list[str]:
    return sorted(p.name for p in parent.iterdir())


def test_a_run_is_built_beside_its_folder_and_replaces_the_earlier_run_whole(tmp_path):
    _run(tmp_path / "run", **{"old.csv": "old", "structure.png": "old picture"})
    (tmp_path / "run" / "report.html").write_text("the earlier report")
    (tmp_path / "run" / ".DS_Store").write_text("clutter")
    with output_directory(tmp_path / "run") as out:
        assert out.staging.parent == tmp_path and out.staging.name.startswith(".run.")
        out.write_text("new.csv", "new")
        assert (out.staging / "new.csv").read_text() == "new"
        assert _entries(tmp_path / "run") == [".DS_Store", "old.csv", "report.html", "structure.png", "summary.json"]
    assert _entries(tmp_path / "run") == ["new.csv"]
    assert _entries(tmp_path) == ["run"]


def test_a_failure_removes_the_staging_folder_and_the_parents_it_made(tmp_path):
    with pytest.raises(RuntimeError):
        with output_directory(tmp_path / "a" / "b" / "run") as out:
            out.write_text("x.csv", "x")
            raise RuntimeError("the computation failed")
    assert _entries(tmp_path) == []


def test_a_failure_leaves_the_earlier_run_byte_for_byte(tmp_path):
    _run(tmp_path / "run", **{"tracks.csv": "earlier"})
    before = {p.name: p.read_bytes() for p in (tmp_path / "run").iterdir()}
    with pytest.raises(KeyboardInterrupt):
        with output_directory(tmp_path / "run") as out:
            out.write_text("tracks.csv", "new")
            raise KeyboardInterrupt
    assert {p.name: p.read_bytes() for p in (tmp_path / "run").iterdir()} == before
    assert _entries(tmp_path) == ["run"]


def test_a_full_disk_is_raised_naming_the_file_being_written(tmp_path):
    with pytest.raises(OSError) as caught:
        with output_directory(tmp_path / "run") as out:
            out.file("frames/frame_000.png")
            raise OSError(errno.ENOSPC, "No space left on device")  # write() gives no file name
    assert caught.value.errno == errno.ENOSPC
    assert caught.value.filename == str(tmp_path / "run" / "frames" / "frame_000.png")
    with pytest.raises(OSError) as caught:
        with output_directory(tmp_path / "run") as out:
            raise PermissionError(errno.EACCES, "Permission denied", str(out.staging / "tracks.npz"))
    assert caught.value.filename == str(tmp_path / "run" / "tracks.npz")  # the name the user knows


@pytest.mark.parametrize(
    "make, message",
    [
        (lambda d: (d / "notes.txt").write_text("mine"), "is not empty and holds no kalmansfm run"),
        (lambda d: (d / "summary.json").write_text('{"not": "ours"}'), "is not empty and holds no kalmansfm run"),
        (lambda d: (_run(d / "r", **{"a.csv": "a"}), (d / "r" / "mine.txt").write_text("x")),
         "holds mine.txt, which its kalmansfm run did not write"),
    ],
)
def test_a_folder_that_is_not_a_kalmansfm_run_is_refused(tmp_path, make, message):
    folder = tmp_path / "out"
    folder.mkdir()
    make(folder)
    target = folder / "r" if (folder / "r").exists() else folder
    before = sorted(p.name for p in target.rglob("*"))
    with pytest.raises(InvalidInputError, match=message):
        with output_directory(target):
            pass
    assert sorted(p.name for p in target.rglob("*")) == before


def test_a_run_of_another_schema_version_is_replaced(tmp_path):
    folder = tmp_path / "run"
    folder.mkdir()
    (folder / "summary.json").write_text('{"command": "demo", "schema_version": 1, "input": "old"}')
    (folder / "tracks.csv").write_text("old")
    with output_directory(folder) as out:
        out.write_text("tracks.csv", "new")
    assert _entries(folder) == ["tracks.csv"]


def test_the_current_folder_and_inputs_are_never_replaced(tmp_path, monkeypatch):
    _run(tmp_path / "run", **{"a.csv": "a"})
    monkeypatch.chdir(tmp_path / "run")
    with pytest.raises(InvalidInputError, match="is \\(or holds\\) the current folder"):
        check_output_directory(".")
    monkeypatch.chdir(tmp_path)
    (tmp_path / "frames").mkdir()
    with pytest.raises(InvalidInputError, match="is the input"):
        check_output_directory(tmp_path / "frames", inputs=[tmp_path / "frames"])
    with pytest.raises(InvalidInputError, match="lies inside the input"):
        check_output_directory(tmp_path / "frames" / "out", inputs=[str(tmp_path / "frames" / "*.png")])
    with pytest.raises(InvalidInputError, match="lies inside the output folder"):
        check_output_directory(tmp_path / "run", inputs=[tmp_path / "run" / "a.csv"])
    assert check_output_directory(tmp_path / "run2", inputs=[tmp_path / "run" / "a.csv"]) == tmp_path / "run2"


def test_temporaries_of_killed_runs_are_swept_and_a_live_run_is_left_alone(tmp_path):
    dead = _a_dead_pid()
    (tmp_path / f".run.{dead}-0123abcd.tmp").mkdir()  # a staging folder of a killed run
    (tmp_path / f".run.{dead}-0123abcd.tmp" / "tracks.csv").write_text("half")
    (tmp_path / ".run.1a2b3c4d.tmp").write_text("an older kalmansfm's temporary")
    live = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    try:
        (tmp_path / f".run.{live.pid}-89abcdef.tmp").mkdir()  # another process building this run now
        _run(tmp_path / "run", **{"tracks.csv": "earlier"})
        (tmp_path / "run" / ".tracks.csv.5f3e2a1b.tmp").write_text("a temporary file inside the run")
        with output_directory(tmp_path / "run") as out:
            out.write_text("tracks.csv", "new")
        assert _entries(tmp_path) == [f".run.{live.pid}-89abcdef.tmp", "run"]
        assert _entries(tmp_path / "run") == ["tracks.csv"]
    finally:
        live.kill()
        live.wait()


def test_an_earlier_run_left_aside_by_a_killed_swap_is_put_back(tmp_path):
    """kill -9 between 'earlier run aside' and 'new run in': the earlier run is still the result."""
    aside = tmp_path / f".run.{_a_dead_pid()}-0123abcd.previous.tmp"
    _run(aside, **{"tracks.csv": "earlier"})
    with pytest.raises(InvalidInputError):
        with output_directory(tmp_path / "run"):
            raise InvalidInputError("a bad input found once the run started")
    assert _entries(tmp_path) == ["run"]
    assert (tmp_path / "run" / "tracks.csv").read_text() == "earlier"


def test_sigterm_during_the_swap_waits_for_it(tmp_path, monkeypatch):
    def terminate(signum, frame):  # what the command line installs
        raise Interrupted(signal_number=signum)

    previous = signal.signal(signal.SIGTERM, terminate)
    real_rename = os.rename

    def rename_then_signal(src, dst):
        real_rename(src, dst)
        os.kill(os.getpid(), signal.SIGTERM)

    _run(tmp_path / "run", **{"a.csv": "old", "b.csv": "old"})
    count = atomic.last_commit()[0]
    try:
        with pytest.raises(Interrupted) as caught:
            with output_directory(tmp_path / "run") as out:
                out.write_text("a.csv", "new")
                out.write_text("b.csv", "new")
                monkeypatch.setattr(os, "rename", rename_then_signal)
    finally:
        signal.signal(signal.SIGTERM, previous)
    assert caught.value.signal_number == signal.SIGTERM
    assert {p.name: p.read_text() for p in (tmp_path / "run").iterdir()} == {"a.csv": "new", "b.csv": "new"}
    assert _entries(tmp_path) == ["run"]
    assert atomic.last_commit() == (count + 1, tmp_path / "run")


def test_atomic_write_sweeps_its_stale_temporaries_and_names_the_file_on_failure(tmp_path):
    stale = tmp_path / f".report.html.{_a_dead_pid()}-0123abcd.tmp"
    stale.write_text("half a report")
    atomic_write(tmp_path / "report.html", lambda p: p.write_text("<html></html>"))
    assert _entries(tmp_path) == ["report.html"]

    def disk_full(path):
        path.write_text("part")
        raise OSError(errno.ENOSPC, "No space left on device")

    with pytest.raises(OSError) as caught:
        atomic_write(tmp_path / "report.html", disk_full)
    assert caught.value.filename == str(tmp_path / "report.html")
    assert _entries(tmp_path) == ["report.html"]


def test_run_source_tells_inputs_apart_by_path_size_time_and_options(tmp_path):
    a = tmp_path / "a" / "f.png"
    a.parent.mkdir()
    a.write_bytes(b"12345")
    b = tmp_path / "b" / "f.png"
    b.parent.mkdir()
    b.write_bytes(b"12345")
    os.utime(b, ns=(a.stat().st_atime_ns, a.stat().st_mtime_ns))
    source = run_source(a.parent, [a], {"smooth": True})
    assert source == run_source(str(a.parent) + "/.", [a], {"smooth": True})
    assert source.input == str(a.parent.resolve()) and (source.files, source.total_bytes) == (1, 5)
    assert source != run_source(b.parent, [b], {"smooth": True})  # same bytes, another place
    assert source != run_source(a.parent, [a], {"smooth": False})
    os.utime(a, ns=(a.stat().st_atime_ns, a.stat().st_mtime_ns + 1))
    assert source != run_source(a.parent, [a], {"smooth": True})  # touched
