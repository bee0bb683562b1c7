"""FusionTable and its CSV / text formatting."""

import numpy as np
import pytest

from kalmansfm import InvalidInputError
from kalmansfm.experiments import FusionTable
from kalmansfm.report.tables import format_csv, format_text

HEADER_3D = (
    "iter,truth_x,truth_y,truth_z,meas_x,meas_y,meas_z,meas_std_x,meas_std_y,meas_std_z,"
    "kalman_x,kalman_y,kalman_z,kalman_std_x,kalman_std_y,kalman_std_z"
)


def _table(K, d, seed=0):
    rng = np.random.default_rng(seed)
    return FusionTable(7, "A 3D table", *(rng.normal(size=(K, d)) for _ in range(5)))


def test_csv_round_trips_every_value():
    t = _table(4, 3)
    lines = format_csv(t).splitlines()
    assert lines[0] == HEADER_3D and len(lines) == 5
    values = np.array([[float(v) for v in line.split(",")] for line in lines[1:]])
    np.testing.assert_array_equal(values[:, 0], [1, 2, 3, 4])
    np.testing.assert_array_equal(values[:, 1:4], t.truth)
    np.testing.assert_array_equal(values[:, 13:16], t.estimate_std)


def test_csv_spells_numbers_as_every_csv_of_the_package():
    from kalmansfm.io._csv import number

    t = FusionTable(7, "", [[10.0], [10.0]], [[0.1 + 0.2], [np.nan]], [[1.0], [1.0]], [[10.2], [10.05]], [[1.0], [0.5]])
    lines = format_csv(t).splitlines()
    assert lines[1] == f"1,10.0,{number(0.1 + 0.2)},1.0,10.2,1.0"
    assert lines[2] == "2,10.0,,1.0,10.05,0.5"  # no measurement: an empty cell, as in structure.csv


def test_csv_1d_header():
    assert format_csv(_table(2, 1)).splitlines()[0] == "iter,truth,meas,meas_std,kalman,kalman_std"


def test_text_3d_has_title_three_blocks_and_errors():
    t = FusionTable(4, "Task 4: title", [[0.0, 3.0, 4.0]], [[0.0, 6.0, 8.0]], [[1.0, 1.0, 1.0]],
                    [[0.0, 3.0, 5.0]], [[0.5, 0.5, 0.5]])
    text = format_text(t)
    lines = text.splitlines()
    assert lines[0] == "Task 4: title"
    assert "Coordinates" in lines and "Standard deviations" in lines
    errors = lines[-1].split("|")
    # measured error (0, 3, 4): range 10 - 5 = 5, |err| = 5; kalman error (0, 0, 1): range sqrt(34) - 5
    assert errors[1].split() == ["0.0000", "3.0000", "4.0000", "5.0000", "5.0000"]
    assert errors[2].split() == ["0.0000", "0.0000", "1.0000", f"{np.sqrt(34) - 5:.4f}", "1.0000"]
    # every line of a block has the same length: the columns are aligned
    block = lines[lines.index("Coordinates") + 2 : lines.index("Coordinates") + 4]
    assert len({len(line) for line in block}) == 1


def test_shapes_are_checked():
    with pytest.raises(InvalidInputError, match=r"FusionTable.estimate must have the shape of truth, \(2, 3\); got \(2, 1\)"):
        FusionTable(1, "", np.zeros((2, 3)), np.zeros((2, 3)), np.zeros((2, 3)), np.zeros((2, 1)), np.zeros((2, 3)))
    with pytest.raises(InvalidInputError, match=r"FusionTable.truth must have shape \(K, d\); got \(2,\)"):
        FusionTable(1, "", *(np.zeros(2) for _ in range(5)))
