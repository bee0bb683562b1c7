"""``kalmansfm batch`` on a 2-worker Dask LocalCluster: results equal the sequential run."""

import numpy as np
import pytest

from kalmansfm.pipeline.batch import process_sequence, run_batch
from kalmansfm.cli.main import main


@pytest.fixture(scope="module")
def batch(tmp_path_factory):
    root = tmp_path_factory.mktemp("batch")
    result = run_batch(["scene:1", "scene:2", str(root / "nope")], root / "out", n_workers=2, n_frames=10)
    return root, result


def test_every_sequence_has_a_row_and_a_bad_one_does_not_stop_the_others(batch):
    root, result = batch
    assert [r.status for r in result.rows] == ["ok", "ok", "failed"]
    assert "does not exist" in result.rows[2].error
    assert result.summary_path.read_text().splitlines()[0].startswith("sequence,output,status")
    assert len(result.summary_path.read_text().splitlines()) == 4


def test_dask_results_equal_the_sequential_run(batch, tmp_path):
    root, result = batch
    for row, seed in zip(result.rows[:2], (1, 2)):
        sequential = process_sequence(f"scene:{seed}", str(tmp_path / f"seq{seed}"), {"html": False, "n_frames": 10})
        assert sequential.status == "ok"
        a = np.load(f"{row.output}/tracks.npz")
        b = np.load(tmp_path / f"seq{seed}" / "tracks.npz")
        for key in ("positions", "covariances", "status", "track_ids"):
            np.testing.assert_array_equal(a[key], b[key])
        assert row.residual_rms_px == sequential.residual_rms_px


def test_rerun_skips_finished_sequences(batch, capsys):
    root, result = batch
    out = root / "out"
    code = main(["batch", "scene:1", "scene:2", "--out", str(out), "--quiet"])
    table = capsys.readouterr().out
    assert code == 0
    assert table.count("skipped") == 2
    assert f"{result.rows[0].residual_rms_px:.3f}" in table
