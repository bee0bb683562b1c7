"""``kalmansfm tables``."""

import os
import subprocess
import sys
from pathlib import Path

import pytest

from kalmansfm.cli.main import main

SRC = Path(__file__).resolve().parents[2] / "src"
HEADER_1D = "iter,truth,meas,meas_std,kalman,kalman_std"
HEADER_3D = (
    "iter,truth_x,truth_y,truth_z,meas_x,meas_y,meas_z,meas_std_x,meas_std_y,meas_std_z,"
    "kalman_x,kalman_y,kalman_z,kalman_std_x,kalman_std_y,kalman_std_z"
)


@pytest.mark.parametrize("number, rows", [(1, 30), (2, 20), (3, 20), (4, 20), (5, 20), (6, 24)])
def test_csv_header_and_row_count(capsys, number, rows):
    assert main(["tables", "--task", str(number), "--format", "csv"]) == 0
    out, err = capsys.readouterr()
    lines = out.splitlines()
    assert lines[0] == (HEADER_1D if number <= 3 else HEADER_3D)
    assert len(lines) == rows + 1
    assert [line.split(",")[0] for line in lines[1:]] == [str(k) for k in range(1, rows + 1)]
    assert err == ""


@pytest.mark.parametrize("number", [2, 5])
def test_text_is_the_default_and_has_the_title(capsys, number):
    assert main(["tables", "--task", str(number)]) == 0
    out = capsys.readouterr().out
    assert out.splitlines()[0].startswith(f"Task {number}:")
    assert "error" in out or "Errors" in out


def test_text_task2_shows_the_computed_estimate(capsys):
    main(["tables", "--task", "2"])
    row3 = capsys.readouterr().out.splitlines()[5].split()
    assert row3[0] == "3" and "37.6729" in row3 and "0.8095" in row3


@pytest.mark.parametrize("bad", ["9", "0"])
def test_unknown_task_exits_2_with_one_line(capsys, bad):
    assert main(["tables", "--task", bad]) == 2
    out, err = capsys.readouterr()
    assert out == ""
    assert err == (
        f"kalmansfm tables: error: unknown task {bad}; tasks 1-6 (published tables) "
        "and 7 (simulated moving camera) are available\n"
    )


def test_task7_prints_the_simulated_table_in_the_3d_columns(capsys):
    assert main(["tables", "--task", "7", "--format", "csv", "--seed", "3"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[0] == HEADER_3D and len(lines) == 25
    last = [float(v) for v in lines[-1].split(",")]
    truth, meas_std, kalman, kalman_std = last[1:4], last[7:10], last[10:13], last[13:16]
    # pairs at the report's magnitudes: single-pair std of metres to tens of metres, fused std below that
    assert all(k < m for k, m in zip(kalman_std, meas_std))
    assert all(abs(k - t) < 20 for k, t in zip(kalman, truth))
    assert main(["tables", "--task", "7", "--format", "csv", "--seed", "3", "--method", "batch"]) == 0
    batch = capsys.readouterr().out.splitlines()
    assert batch[0] == HEADER_3D and batch[1:] != lines[1:]


@pytest.mark.parametrize("argv", [["tables", "--task", "x"], ["tables", "--task", "1", "--format", "xml"], ["tables"]])
def test_usage_errors_exit_2_with_one_line(capsys, argv):
    with pytest.raises(SystemExit) as info:
        main(argv)
    assert info.value.code == 2
    err = capsys.readouterr().err
    assert len(err.splitlines()) == 1 and "Traceback" not in err


def test_module_entry_point_in_a_subprocess():
    env = {**os.environ, "PYTHONPATH": str(SRC)}
    done = subprocess.run(
        [sys.executable, "-m", "kalmansfm", "tables", "--task", "1"],
        capture_output=True, text=True, env=env, timeout=60, check=False,
    )
    assert done.returncode == 0, done.stderr
    assert done.stdout.splitlines()[0].startswith("Task 1:")
    assert len(done.stdout.splitlines()) == 3 + 30
