"""``kalmansfm batch`` on a Dask LocalCluster: every sequence gets a row, results are attributed to
the input they came from, and a finished run is kept only when it was made from the same input."""

from pathlib import Path

import cv2
import numpy as np
import pytest

from kalmansfm.cli.main import main
from kalmansfm.errors import Interrupted, InvalidInputError
from kalmansfm.io import read_summary
from kalmansfm.io.tracks import read_tracks_npz
from kalmansfm.pipeline.batch import BatchRow, batch_summary_csv, folder_name, process_sequence, run_batch
from kalmansfm.scenes import render_scene, write_scene


@pytest.fixture(scope="module")
def batch(tmp_path_factory):
    root = tmp_path_factory.mktemp("batch")
    (root / "empty").mkdir()
    sequences = ["scene:1", "scene:2", str(root / "nope"), "scene:x", str(root / "empty"), "scene:1"]
    result = run_batch(sequences, root / "out", n_workers=2, n_frames=10)
    return root, result


def test_every_sequence_has_a_row_and_bad_ones_do_not_stop_the_others(batch):
    root, result = batch
    assert [r.status for r in result.rows] == ["ok", "ok", "failed", "failed", "failed", "failed"]
    assert "does not exist" in result.rows[2].error
    assert "scene:SEED with an integer seed" in result.rows[3].error
    assert "holds no image files" in result.rows[4].error
    assert result.rows[5].error == "sequence 'scene:1' is sequence 1 again"
    assert [Path(r.output).name for r in result.rows[:2]] == ["scene-1", "scene-2"]
    lines = result.summary_path.read_text().splitlines()
    assert lines[0] == "sequence,output,status,frames,tracks,fraction_tracked,residual_rms_px,seconds,error,warnings"
    assert len(lines) == 7
    # nothing was made for the sequences that could not run
    assert sorted(p.name for p in (root / "out").iterdir()) == ["batch_summary.csv", "scene-1", "scene-2"]


def test_dask_results_equal_the_sequential_run(batch, tmp_path):
    root, result = batch
    for row, seed in zip(result.rows[:2], (1, 2)):
        sequential = process_sequence(f"scene:{seed}", str(tmp_path / f"seq{seed}"), {"html": False, "n_frames": 10})
        assert sequential.status == "ok"
        a = read_tracks_npz(f"{row.output}/tracks.npz")
        b = read_tracks_npz(tmp_path / f"seq{seed}" / "tracks.npz")
        for key in ("positions", "covariances", "status", "track_ids"):
            np.testing.assert_array_equal(getattr(a, key), getattr(b, key))
        assert row.residual_rms_px == sequential.residual_rms_px


def test_a_rerun_with_the_same_options_skips_finished_sequences(batch):
    root, result = batch
    again = run_batch(["scene:2", "scene:1"], root / "out", n_workers=1, n_frames=10)
    assert [r.status for r in again.rows] == ["skipped", "skipped"]
    assert [r.residual_rms_px for r in again.rows] == [result.rows[1].residual_rms_px, result.rows[0].residual_rms_px]
    assert [r.warnings for r in again.rows] == [result.rows[1].warnings, result.rows[0].warnings]


def _image_folders(root: Path) -> dict[str, Path]:
    """hs/house/images and hs/hotel/images: two sequences whose folders have the same name."""
    folders = {}
    for seed, name in ((1, "house"), (2, "hotel")):
        folders[name] = root / "hs" / name / "images"
        write_scene(render_scene(n_frames=4 + seed, seed=seed), folders[name])
    return folders


def test_results_stay_with_their_input_when_the_order_changes_or_an_input_changes(tmp_path, capsys):
    """Issue 20.1: swapped inputs used to come back 'skipped' with each other's results."""
    folders = _image_folders(tmp_path)
    out = tmp_path / "bc"
    assert folder_name(str(folders["house"])) != folder_name(str(folders["hotel"]))
    assert main(["batch", str(folders["house"]), str(folders["hotel"]), "--out", str(out), "--workers", "1", "-q"]) == 0
    capsys.readouterr()
    assert main(["batch", str(folders["hotel"]), str(folders["house"]), "--out", str(out), "--workers", "1", "-q"]) == 0
    table = capsys.readouterr().out.splitlines()
    assert table[1].split()[:3] == [str(folders["hotel"]), "skipped", "6"]  # hotel: 6 frames
    assert table[2].split()[:3] == [str(folders["house"]), "skipped", "5"]  # house: 5 frames
    for name, frames in (("hotel", 6), ("house", 5)):
        summary = read_summary(out / folder_name(str(folders[name])) / "summary.json")
        assert summary.source.input == str(folders[name].resolve())
        assert summary.tracking.frames == frames

    # new content under the same path and file names (another scene): computed again, not skipped
    before = read_summary(out / folder_name(str(folders["house"])) / "summary.json").source
    write_scene(render_scene(n_frames=5, seed=3), folders["house"])
    result = run_batch([str(folders["house"]), str(folders["hotel"])], out, n_workers=1)
    assert [r.status for r in result.rows] == ["ok", "skipped"]
    after = read_summary(out / folder_name(str(folders["house"])) / "summary.json").source
    assert after.input == before.input and after.fingerprint != before.fingerprint


def test_mixed_good_and_bad_inputs_run_the_good_ones_and_exit_1(tmp_path, capsys):
    """Issue 16.5: one bad input is a failed row, not a stop before anything ran."""
    out = tmp_path / "out"
    code = main(["batch", "scene:4", str(tmp_path / "missing"), "--out", str(out), "--workers", "1", "-q"])
    table = capsys.readouterr().out
    assert code == 1
    assert "scene:4" in table and " ok " in table
    assert "failed" in table and "does not exist" in table
    assert read_summary(out / "scene-4" / "summary.json").tracking.frames == 30


def test_batch_shows_the_warnings_demo_shows(tmp_path, capsys):
    """Issue 16.5: a static camera (every frame the same) gets the same warnings in both commands."""
    still = tmp_path / "still"
    still.mkdir()
    frame = render_scene(n_frames=3, seed=5).frames[0]
    for k in range(6):
        cv2.imwrite(str(still / f"f{k}.png"), frame)
    assert main(["demo", "--input", str(still), "--out", str(tmp_path / "demo"), "-q"]) == 0
    demo_warnings = [line for line in capsys.readouterr().out.splitlines() if line.startswith("warning: ")]
    assert demo_warnings
    result = run_batch([str(still)], tmp_path / "batch", n_workers=1)
    assert [f"warning: {w}" for w in result.rows[0].warnings] == demo_warnings
    assert result.table().splitlines()[-len(demo_warnings):] == [f"{still}: {w}" for w in demo_warnings]


def test_an_unreachable_scheduler_is_one_message_and_nothing_is_written(tmp_path):
    out = tmp_path / "out"
    with pytest.raises(InvalidInputError, match=r"cannot use the Dask scheduler 'tcp://127\.0\.0\.1:1': "):
        run_batch(["scene:1"], out, scheduler="tcp://127.0.0.1:1", connect_timeout_s=1)
    assert not out.exists()


def test_ctrl_c_during_a_batch_says_what_finished(tmp_path, monkeypatch):
    import dask.distributed

    def interrupted(futures):
        raise KeyboardInterrupt

    monkeypatch.setattr(dask.distributed, "as_completed", interrupted)
    with pytest.raises(Interrupted, match=r"^[01] of 1 sequences finished \(their run folders are in .*out; "
                                          r"batch_summary\.csv was not written\); run the same command again") as caught:
        run_batch(["scene:1"], tmp_path / "out", n_workers=1)
    # the count is what is on disk once the cluster has stopped (the task may finish while it stops)
    whole = [p for p in (tmp_path / "out").iterdir() if (p / "summary.json").exists()]
    assert str(caught.value).startswith(f"{len(whole)} of 1")


def test_ctrl_c_counts_the_run_folders_that_were_swapped_in_even_before_their_rows_came_back(tmp_path, monkeypatch):
    """Issue 30: '0 of 2 finished' was said with 2 whole run folders on disk (their rows were not collected yet)."""
    import dask.distributed

    def finished_then_interrupted(futures):
        dask.distributed.wait(list(futures))  # both sequences finish on the workers ...
        raise KeyboardInterrupt               # ... and Ctrl-C comes before any row is collected

    monkeypatch.setattr(dask.distributed, "as_completed", finished_then_interrupted)
    with pytest.raises(Interrupted, match=r"^2 of 2 sequences finished"):
        run_batch(["scene:1", "scene:2"], tmp_path / "out", n_workers=1, n_frames=5, save_frames=False)
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == ["scene-1", "scene-2"]


def test_the_batch_summary_spells_numbers_as_every_csv_of_the_package():
    import csv
    import io

    rows = [BatchRow("scene:1", "out/scene-1", "ok", 30, 8, 2 / 3, 0.1 + 0.2, float("nan"), warnings=("a", "b")),
            BatchRow("x,y", "out/x", "failed", error='ValueError: "bad", really')]
    text = batch_summary_csv(rows)
    read = list(csv.DictReader(io.StringIO(text)))
    assert float(read[0]["fraction_tracked"]) == 2 / 3 and float(read[0]["residual_rms_px"]) == 0.1 + 0.2
    assert read[0]["seconds"] == ""  # no value: an empty cell (was 'nan')
    assert read[0]["warnings"] == "a | b" and read[1]["sequence"] == "x,y" and read[1]["error"] == 'ValueError: "bad", really'
