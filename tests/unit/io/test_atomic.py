"""The one mechanism that owns a run folder (kalmansfm.io.atomic) and the record of what a run was made from."""

from __future__ import annotations

import errno
import json
import logging
import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from kalmansfm.errors import Interrupted, InvalidInputError
from kalmansfm.io import RunSummary, summary_json
from kalmansfm.io import atomic
from kalmansfm.io._claims import Claim
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
        (folder / name).parent.mkdir(parents=True, exist_ok=True)
        (folder / name).write_text(text)
    (folder / "summary.json").write_text(summary_json(RunSummary("track", "earlier", files=(*files, "summary.json"))))


def _entries(parent: Path) -> list[str]:
    return sorted(p.name for p in parent.iterdir())


#: How a report of kalmansfm begins (report.html.render_report).
OUR_REPORT = '<!DOCTYPE html>\n<html lang="en"><head><title>t</title></head><body><header><h1>kalmansfm report</h1>'


def _proven_temporary(final: Path, pid: int, suffix: str = ".tmp", token: str = "0123456789abcdef") -> Path:
    """A temporary of ``final`` with the owner marker a kalmansfm process ``pid`` writes beside it."""
    made = Claim(final, pid, token)
    made.marker.write_text(json.dumps(made.record()))
    return made.temporary if suffix == ".tmp" else made.aside


def test_a_run_is_built_beside_its_folder_and_replaces_the_earlier_run_whole(tmp_path):
    _run(tmp_path / "run", **{"old.csv": "old", "structure.png": "old picture"})
    (tmp_path / "run" / "report.html").write_text(OUR_REPORT)
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
    (folder / "summary.json").write_text('{"command": "demo", "schema_version": 1, "input": "old", '
                                         '"files": ["tracks.csv", "summary.json"]}')
    (folder / "tracks.csv").write_text("old")
    with output_directory(folder) as out:
        out.write_text("tracks.csv", "new")
    assert _entries(folder) == ["tracks.csv"]


def test_a_summary_without_a_file_list_owns_only_itself(tmp_path):
    folder = tmp_path / "run"
    folder.mkdir()
    (folder / "summary.json").write_text('{"command": "demo", "schema_version": 1}')
    (folder / "thesis.tex").write_text("the user's")
    with pytest.raises(InvalidInputError, match="holds thesis.tex, which its kalmansfm run did not write"):
        check_output_directory(folder)


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
    staging = _proven_temporary(tmp_path / "run", dead)  # a staging folder of a killed run
    staging.mkdir()
    (staging / "tracks.csv").write_text("half")
    live = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    try:
        building = _proven_temporary(tmp_path / "run", live.pid, token="fedcba9876543210")  # another run, now
        building.mkdir()
        _run(tmp_path / "run", **{"tracks.csv": "earlier"})
        inside = _proven_temporary(tmp_path / "run" / "report.html", dead)  # a report a killed process wrote
        inside.write_text("half a report")
        with output_directory(tmp_path / "run") as out:
            out.write_text("tracks.csv", "new")
        assert _entries(tmp_path) == sorted([building.name, building.name[:-4] + ".owner", "run"])
        assert _entries(tmp_path / "run") == ["tracks.csv"]
    finally:
        live.kill()
        live.wait()


@pytest.mark.parametrize("name", [
    ".run.backup.tmp", ".run.12345.tmp", ".run.{dead}-0123abcd.tmp", ".run.{dead}-0123456789abcdef.tmp",
    ".run.{dead}-0123456789abcdef.previous.tmp",
])
@pytest.mark.parametrize("marker", ["none", "other content", "other host"])
def test_files_that_only_look_like_our_temporaries_are_never_touched(tmp_path, name, marker):
    dead = _a_dead_pid()
    look_alike = tmp_path / name.format(dead=dead)
    look_alike.mkdir()
    (look_alike / "precious.txt").write_text("the user's")
    made = Claim(tmp_path / "run", dead, "0123456789abcdef")
    if marker == "other content":
        made.marker.write_text(json.dumps({**made.record(), "token": "something else"}))
    elif marker == "other host":
        made.marker.write_text(json.dumps({**made.record(), "host": "another-machine"}))
    before = _entries(tmp_path)
    with output_directory(tmp_path / "run") as out:
        out.write_text("tracks.csv", "new")
    atomic_write(tmp_path / "run.csv", lambda p: p.write_text("x"))
    assert _entries(tmp_path) == sorted([*before, "run", "run.csv"])
    assert (look_alike / "precious.txt").read_text() == "the user's"


def test_an_output_folder_holding_the_current_folder_is_refused_before_anything_changes(tmp_path, monkeypatch):
    (tmp_path / "a" / "b").mkdir(parents=True)
    stale = _proven_temporary(tmp_path / "a", _a_dead_pid())  # what a sweep would remove
    stale.mkdir()
    monkeypatch.chdir(tmp_path / "a" / "b")
    before = sorted(p.relative_to(tmp_path).as_posix() for p in tmp_path.rglob("*"))
    for out in ("..", str(tmp_path / "a"), ".", str(tmp_path)):
        with pytest.raises(InvalidInputError, match="is \\(or holds\\) the current folder"):
            with output_directory(out):
                pass
    assert sorted(p.relative_to(tmp_path).as_posix() for p in tmp_path.rglob("*")) == before


def test_an_earlier_run_left_aside_by_a_killed_swap_is_put_back(tmp_path):
    """kill -9 between 'earlier run aside' and 'new run in': the earlier run is still the result."""
    aside = _proven_temporary(tmp_path / "run", _a_dead_pid(), suffix=".previous.tmp")
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
    stale = _proven_temporary(tmp_path / "report.html", _a_dead_pid())
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


@pytest.mark.parametrize(
    "make, message",
    [
        (lambda d: (d / ".git").mkdir(), "is not empty and holds no kalmansfm run"),
        (lambda d: (d / ".env").write_text("SECRET=1"), "is not empty and holds no kalmansfm run"),
        (lambda d: (d / "keep").mkdir(), "is not empty and holds no kalmansfm run"),
        (lambda d: (_run(d / "r", **{"a.csv": "a"}), (d / "r" / ".git").mkdir()), "holds .git/, which its kalmansfm"),
        (lambda d: (_run(d / "r", **{"a.csv": "a"}), (d / "r" / ".notes").write_text("x")), "holds .notes, which"),
        (lambda d: (_run(d / "r", **{"a.csv": "a"}), (d / "r" / "mine.html").write_text("<p>my page</p>")),
         "holds mine.html, which its kalmansfm run did not write"),
        (lambda d: (_run(d / "r", **{"a.csv": "a"}), (d / "r" / "report.html").symlink_to(d / "elsewhere.html")),
         "holds report.html, which"),
        (lambda d: (_run(d / "r", **{"frames/f0.png": "a"}), (d / "r" / "frames" / "mine.png").write_text("x")),
         "holds frames/mine.png, which"),
        (lambda d: (_run(d / "r", **{"a.csv": "a"}), (d / "r" / "a.csv").unlink(), (d / "r" / "a.csv").mkdir(),
                    (d / "r" / "a.csv" / "x").write_text("x")), "holds a.csv/x, which"),
    ],
)
def test_hidden_files_and_files_the_run_did_not_list_are_not_ours(tmp_path, make, message):
    folder = tmp_path / "out"
    folder.mkdir()
    make(folder)
    target = folder / "r" if (folder / "r").exists() else folder
    before = sorted(p.relative_to(tmp_path).as_posix() for p in tmp_path.rglob("*"))
    with pytest.raises(InvalidInputError, match=message):
        with output_directory(target):
            pass
    assert sorted(p.relative_to(tmp_path).as_posix() for p in tmp_path.rglob("*")) == before


def test_the_litter_of_operating_systems_and_our_reports_go_with_the_run(tmp_path):
    (tmp_path / "empty").mkdir()
    (tmp_path / "empty" / ".DS_Store").write_bytes(b"\0\0\0\1Bud1")
    _run(tmp_path / "run", **{"frames/f0.png": "a"})
    (tmp_path / "run" / "frames" / "Thumbs.db").write_bytes(b"x")
    (tmp_path / "run" / "custom.html").write_text(OUR_REPORT + "<p>another --name</p>")
    for name in ("empty", "run"):
        with output_directory(tmp_path / name) as out:
            out.write_text("new.csv", "new")
        assert _entries(tmp_path / name) == ["new.csv"]


def test_a_failure_keeps_the_parent_folders_it_made_once_another_run_wrote_in_them(tmp_path):
    with pytest.raises(KeyboardInterrupt):
        with output_directory(tmp_path / "new" / "b") as out:
            out.write_text("x.csv", "x")
            with output_directory(tmp_path / "new" / "a") as other:  # another run, finished meanwhile
                other.write_text("y.csv", "y")
            raise KeyboardInterrupt
    assert _entries(tmp_path) == ["new"]
    assert _entries(tmp_path / "new") == ["a"]
    assert _entries(tmp_path / "new" / "a") == ["y.csv"]


def test_a_symbolic_link_as_output_folder_stays_a_link_and_leaves_nothing_beside_it(tmp_path):
    _run(tmp_path / "real" / "run", **{"a.csv": "old"})
    link = tmp_path / "latest"
    link.symlink_to(tmp_path / "real" / "run")
    with output_directory(link) as out:
        out.write_text("b.csv", "new")
    assert link.is_symlink() and _entries(link) == ["b.csv"]
    assert _entries(tmp_path) == ["latest", "real"] and _entries(tmp_path / "real") == ["run"]
    (tmp_path / "dangling").symlink_to(tmp_path / "nowhere")
    with pytest.raises(InvalidInputError, match="dangling is a symbolic link to .*nowhere, which does not exist"):
        check_output_directory(tmp_path / "dangling")


def test_a_file_that_appears_in_the_earlier_run_during_the_run_stops_the_swap(tmp_path):
    _run(tmp_path / "run", **{"a.csv": "old"})
    count = atomic.last_commit()[0]
    with pytest.raises(InvalidInputError, match="holds notes.txt, which .*the new results were not written"):
        with output_directory(tmp_path / "run") as out:
            out.write_text("a.csv", "new")
            (tmp_path / "run" / "notes.txt").write_text("written by the user while the run worked")
    assert {p.name: p.read_text() for p in (tmp_path / "run").iterdir()} == {
        "a.csv": "old", "notes.txt": "written by the user while the run worked",
        "summary.json": (tmp_path / "run" / "summary.json").read_text()}
    assert _entries(tmp_path) == ["run"] and atomic.last_commit()[0] == count


def test_a_run_swapped_in_by_another_process_at_the_same_moment_is_replaced_like_a_rerun(tmp_path, monkeypatch):
    real_rename = os.rename
    target = tmp_path / "run"
    other_runs = []

    def another_run_gets_in_first(src, dst):
        if Path(dst) == target and not other_runs:
            _run(tmp_path / "other", **{"b.csv": "the other run"})
            real_rename(tmp_path / "other", target)
            other_runs.append(target)
        real_rename(src, dst)

    with output_directory(target) as out:
        out.write_text("a.csv", "ours")
        monkeypatch.setattr(os, "rename", another_run_gets_in_first)
    assert other_runs and _entries(target) == ["a.csv"] and _entries(tmp_path) == ["run"]


def test_replacing_a_run_of_another_command_or_input_says_what_was_replaced(tmp_path, caplog):
    def summary(command: str, source: str) -> str:
        return summary_json(RunSummary(command, f"{source} as given", source=run_source(source, [], {}),
                                       created="2026-01-02T03:04:05+00:00", files=("summary.json",)))

    with output_directory(tmp_path / "run") as out:
        out.write_text("summary.json", summary("demo", "clip.avi"))
    with caplog.at_level(logging.WARNING, logger="kalmansfm"):
        with output_directory(tmp_path / "run") as out:  # the same command and input: nothing to say
            out.write_text("summary.json", summary("demo", "clip.avi"))
        assert caplog.messages == []
        with output_directory(tmp_path / "run") as out:
            out.write_text("summary.json", summary("fuse", "tracks.csv"))
    assert caplog.messages == [f"replaced {tmp_path / 'run'}: it held a demo run of clip.avi as given made "
                               "2026-01-02T03:04:05+00:00"]


def test_a_file_name_that_is_not_utf8_is_written_as_escapes(tmp_path):
    with output_directory(tmp_path / "run") as out:
        out.write_text("structure.ply", "comment made from " + os.fsdecode(b"clip\xff.avi") + "\n")
    assert (tmp_path / "run" / "structure.ply").read_text(encoding="utf-8") == "comment made from clip\\udcff.avi\n"


@pytest.mark.parametrize("writer", ["output_directory", "atomic_write"])
def test_ctrl_c_while_the_owner_marker_is_made_leaves_nothing(tmp_path, monkeypatch, writer):
    """Issue 30's sweep: a SIGINT between the marker and the clean-up left the marker and the staging folder."""
    real_claim = atomic.claim

    def claim_then_ctrl_c(final):
        made = real_claim(final)
        signal.raise_signal(signal.SIGINT)  # Python's handler runs at once: KeyboardInterrupt, unless held back
        return made

    monkeypatch.setattr(atomic, "claim", claim_then_ctrl_c)
    with pytest.raises(KeyboardInterrupt):
        if writer == "output_directory":
            with output_directory(tmp_path / "new" / "run") as out:
                out.write_text("a.csv", "never written")
        else:
            atomic_write(tmp_path / "report.html", lambda p: p.write_text("never written"))
    assert _entries(tmp_path) == []
