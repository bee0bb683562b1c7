"""Ctrl-C and failures never destroy earlier results: exit code 130, one line, the old folder intact."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from kalmansfm.pipeline import demo as pipeline
from kalmansfm.cli.main import main
from kalmansfm.io.atomic import output_directory

SRC = Path(__file__).resolve().parents[2] / "src"


def _snapshot(root: Path) -> dict[str, bytes]:
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


@pytest.fixture(scope="module")
def earlier_run(tmp_path_factory) -> Path:
    """A finished demo run (8 frames, no report) that a second run will try to replace."""
    out = tmp_path_factory.mktemp("interrupt") / "run"
    pipeline.run_demo(out, n_frames=8, seed=3, html=False)
    return out


@pytest.fixture
def run_folder(earlier_run, tmp_path) -> Path:
    """A private copy of the earlier run, so that every test starts from the same folder."""
    copy = tmp_path / "run"
    for name, data in _snapshot(earlier_run).items():
        (copy / name).parent.mkdir(parents=True, exist_ok=True)
        (copy / name).write_bytes(data)
    return copy


@pytest.mark.parametrize("step", ["stage_tracking", "stage_structure", "factorize_tracks", "track"])
def test_ctrl_c_inside_the_pipeline_keeps_the_earlier_results(step, run_folder, monkeypatch, capsys):
    before = _snapshot(run_folder)

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(pipeline, step, interrupted)
    code = main(["demo", "--out", str(run_folder), "--frames", "5", "--seed", "1", "--quiet"])

    err = capsys.readouterr().err
    assert code == 130
    assert err.splitlines() == ["kalmansfm demo: interrupted; earlier results were left as they were"]
    assert _snapshot(run_folder) == before


def test_a_failure_while_writing_keeps_the_earlier_results(run_folder, monkeypatch, capsys):
    before = _snapshot(run_folder)

    def disk_full(*args, **kwargs):
        raise OSError(28, "No space left on device", str(run_folder / "structure.csv"))

    monkeypatch.setattr(pipeline, "stage_structure", disk_full)
    code = main(["demo", "--out", str(run_folder), "--frames", "5", "--seed", "1", "--quiet"])
    err = capsys.readouterr().err
    assert code == 2
    assert len(err.splitlines()) == 1 and "No space left on device" in err
    assert _snapshot(run_folder) == before


def test_ctrl_c_in_a_fresh_folder_leaves_nothing(tmp_path, monkeypatch, capsys):
    monkeypatch.setattr(pipeline, "stage_structure", lambda *a, **k: (_ for _ in ()).throw(KeyboardInterrupt))
    out = tmp_path / "new" / "run"
    assert main(["demo", "--out", str(out), "--frames", "5", "--quiet"]) == 130
    assert not (tmp_path / "new").exists()


def test_ctrl_c_during_the_renames_is_held_back_until_they_are_done(tmp_path, monkeypatch):
    folder = tmp_path / "run"
    folder.mkdir()
    for name in ("a.txt", "b.txt"):
        (folder / name).write_text("old")
    real_replace = os.replace

    def replace_then_signal(src, dst):
        real_replace(src, dst)
        os.kill(os.getpid(), signal.SIGINT)  # Ctrl-C right after each rename

    with pytest.raises(KeyboardInterrupt):
        with output_directory(folder) as out:
            out.write_text("a.txt", "new")
            out.write_text("b.txt", "new")
            monkeypatch.setattr(os, "replace", replace_then_signal)
    # not one old and one new file: the interrupt waited for the second rename
    assert {p.name: p.read_text() for p in folder.iterdir()} == {"a.txt": "new", "b.txt": "new"}


SLOW_WRITE = """
import sys, time
from pathlib import Path
import kalmansfm.pipeline.demo as pipeline
from kalmansfm.cli.main import main

real = pipeline.stage_structure
def slow_stage_structure(out, *args, **kwargs):
    names = real(out, *args, **kwargs)  # some new files are staged now
    Path(sys.argv[1]).write_text("writing")
    time.sleep(60)                      # ... and here comes Ctrl-C
    return names
pipeline.stage_structure = slow_stage_structure
sys.exit(main(["demo", "--out", sys.argv[2], "--frames", "5", "--seed", "1"]))
"""


@pytest.mark.skipif(sys.platform == "win32", reason="SIGINT to a child process is POSIX")
def test_sigint_to_a_real_process_while_it_writes(run_folder, tmp_path):
    before = _snapshot(run_folder)
    marker = tmp_path / "writing"
    process = subprocess.Popen(
        [sys.executable, "-c", SLOW_WRITE, str(marker), str(run_folder)],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
        env={**os.environ, "PYTHONPATH": str(SRC)},
    )
    deadline = time.monotonic() + 120
    while not marker.exists() and time.monotonic() < deadline and process.poll() is None:
        time.sleep(0.05)
    assert marker.exists(), process.communicate()
    staged = [p.name for p in run_folder.rglob("*.tmp")]
    assert staged, "the run should have staged new files by now"
    process.send_signal(signal.SIGINT)
    out, err = process.communicate(timeout=60)
    assert process.returncode == 130, err
    assert "Traceback" not in err
    assert err.rstrip("\n").splitlines()[-1] == "kalmansfm demo: interrupted; earlier results were left as they were"
    assert _snapshot(run_folder) == before


def test_ctrl_c_while_the_report_is_built_leaves_the_new_results_and_no_stale_report(run_folder, monkeypatch, capsys):
    """The results are committed before report.html is built; the earlier report must not stay beside them."""
    (run_folder / "report.html").write_text("<html>the earlier run's report</html>")
    before = _snapshot(run_folder)
    monkeypatch.setattr(pipeline, "build_report", lambda *a, **k: (_ for _ in ()).throw(KeyboardInterrupt))
    code = main(["demo", "--out", str(run_folder), "--frames", "5", "--seed", "1", "--quiet"])
    err = capsys.readouterr().err
    assert code == 130
    assert err.splitlines() == [
        f"kalmansfm demo: interrupted; the new results are in {run_folder}, without report.html; "
        f"run 'kalmansfm report {run_folder}'"
    ]
    after = _snapshot(run_folder)
    assert "report.html" not in after
    assert after["tracks.csv"] != before["tracks.csv"]  # 5 frames now, 8 before
    assert not [name for name in after if ".tmp" in name or name.startswith(".")]
