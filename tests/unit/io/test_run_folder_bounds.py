"""A run folder is read only inside itself: a listed name that leaves it is refused before anything is read."""

from __future__ import annotations

import os
import re
from pathlib import Path

import cv2
import numpy as np
import pytest

from kalmansfm.cli.main import main
from kalmansfm.errors import InvalidInputError
from kalmansfm.io import RunSummary, load_run, summary_json
from kalmansfm.io.run_folder import run_file


def _run(folder: Path, files: tuple[str, ...], **contents: bytes) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    for name, data in contents.items():
        (folder / name).write_bytes(data)
    (folder / "summary.json").write_text(summary_json(RunSummary("track", "x", files=(*files, "summary.json"))))
    return folder


def _snapshot(root: Path) -> dict[str, bytes]:
    return {p.relative_to(root).as_posix(): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


@pytest.fixture
def outside(tmp_path) -> Path:
    """A CSV beside the run folder that a hostile summary.json points at."""
    secret = tmp_path / "secret.csv"
    secret.write_text("track_id,X,Y,Z\n1,2,3,4\n")
    return secret


@pytest.mark.parametrize("listed, why", [
    ("{outside}", "a run names its files relative to its folder"),
    ("../secret.csv", "a run names its files relative to its folder"),
    ("frames/../../secret.csv", "a run names its files relative to its folder"),
    ("./structure.csv", "a run names its files relative to its folder"),
    ("frames//frame_000.png", "a run names its files relative to its folder"),
    ("structure.csv", "it leads to .*secret.csv, outside the folder"),  # a link to the outside file
    ("tracks.npz", "it is a named pipe \\(FIFO\\), not a file"),
])
def test_report_refuses_a_listed_name_that_leaves_the_folder_and_writes_nothing(tmp_path, outside, listed, why,
                                                                                capsys):
    run = _run(tmp_path / "run", (listed.format(outside=outside),))
    if listed == "structure.csv":
        (run / "structure.csv").symlink_to(outside)
    if listed == "tracks.npz":
        os.mkfifo(run / "tracks.npz")  # reading it would wait for ever
    before = _snapshot(tmp_path)

    assert main(["report", str(run), "--quiet"]) == 2

    err = capsys.readouterr().err.splitlines()
    assert len(err) == 1 and err[0].startswith(f"kalmansfm report: error: {run / 'summary.json'}: lists "), err
    assert re.search(why, err[0]), err[0]
    assert _snapshot(tmp_path) == before  # no report.html, nothing outside touched


def test_a_summary_json_that_is_a_link_to_the_outside_is_refused(tmp_path):
    elsewhere = _run(tmp_path / "elsewhere", ())
    (tmp_path / "run").mkdir()
    (tmp_path / "run" / "summary.json").symlink_to(elsewhere / "summary.json")
    with pytest.raises(InvalidInputError, match="summary.json: lists 'summary.json', which is not a file of the run"):
        load_run(tmp_path / "run")


def test_links_inside_the_folder_and_plain_names_are_read(tmp_path):
    run = _run(tmp_path / "run", ("structure.csv", "copy.csv"),
               **{"structure.csv": b"track_id,X,Y,Z\n1,2,3,4\n"})
    (run / "copy.csv").symlink_to(run / "structure.csv")
    assert run_file(run, "copy.csv") == run / "copy.csv"
    assert load_run(run).structure.track_ids.tolist() == [1]


def test_frames_of_a_run_whose_name_is_not_utf8_are_read(tmp_path):
    frame = np.arange(12, dtype=np.uint8).reshape(3, 4)
    _run(tmp_path / "run", ("frames/frame_000.png",))
    (tmp_path / "run" / "frames").mkdir()
    assert cv2.imwrite(str(tmp_path / "run" / "frames" / "frame_000.png"), frame)
    run = (tmp_path / "run").rename(tmp_path / os.fsdecode(b"run\xff"))  # OpenCV crashes on this name
    images = load_run(run).read_frames()
    assert len(images) == 1 and np.array_equal(images[0], frame)
