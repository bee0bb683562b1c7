"""Loading the fusion experiments shipped as package data."""

import numpy as np
import pytest

from kalmansfm import InvalidInputError
from kalmansfm.experiments.fusion_tasks import available_tasks, load_task, rotation_about_y, run_task


@pytest.mark.parametrize("number, rows, d", [(1, 30, 1), (2, 20, 1), (3, 20, 1), (4, 20, 3), (5, 20, 3), (6, 24, 3)])
def test_shapes_and_header_text(number, rows, d):
    task = load_task(number)
    assert task.number == number and task.title.startswith(f"Task {number}:")
    assert task.truth.shape == task.measurements.shape == task.measurement_std.shape == (rows, d)
    assert task.rotations.shape == (rows - 1, d, d) and task.translations.shape == (rows - 1, d)
    assert "Thomas and J. Oliensis" in task.description and "Units: metres" in task.description
    assert np.all(task.measurement_std > 0)
    np.testing.assert_allclose(task.rotations @ np.swapaxes(task.rotations, -1, -2), np.broadcast_to(np.eye(d), task.rotations.shape), atol=1e-15)


def test_documented_motions():
    np.testing.assert_array_equal(load_task(3).translations, np.ones((19, 1)))
    assert "walks exactly 1 m" in load_task(3).description
    C5 = load_task(5).rotations[0]
    axis = np.array([2.0, 3.0, 1.0]) / np.sqrt(14.0)
    np.testing.assert_allclose(C5 @ axis, axis, atol=1e-15)  # the axis is fixed
    np.testing.assert_allclose(np.trace(C5), -1.0, atol=1e-15)  # 1 + 2 cos(pi)
    assert "pi about the fixed unit axis n = (2, 3, 1)/sqrt(14)" in load_task(5).description
    t6 = load_task(6)
    np.testing.assert_allclose(t6.rotations[0], rotation_about_y(np.radians(1.0)))
    np.testing.assert_allclose(t6.rotations[1], rotation_about_y(np.radians(-1.0)))
    np.testing.assert_array_equal(t6.translations, np.tile([0.0, 0.0, 1.0], (23, 1)))


def test_covariances_are_diagonal_squares_of_the_std():
    task = load_task(4)
    np.testing.assert_array_equal(np.diagonal(task.measurement_covariances, axis1=1, axis2=2), task.measurement_std**2)
    assert np.count_nonzero(task.measurement_covariances) == 3 * 20


@pytest.mark.parametrize("bad", [9, 0, -1, 7, True, 1.0, "1"])
def test_unknown_task_is_a_one_line_input_error(bad):
    with pytest.raises(InvalidInputError, match=r"^unknown task .*; tasks 1–6 are available$"):
        load_task(bad)


def test_unknown_task_message_is_exact():
    with pytest.raises(InvalidInputError) as info:
        run_task(9)
    assert str(info.value) == "unknown task 9; tasks 1–6 are available"


def test_available_tasks():
    assert available_tasks() == [1, 2, 3, 4, 5, 6]


def test_run_task_equals_the_closed_form_mean():
    from kalmansfm import fuse_closed_form

    task = load_task(6)
    table = run_task(6)
    closed = fuse_closed_form(task.measurements, task.measurement_covariances, task.rotations, task.translations)
    np.testing.assert_allclose(table.estimate, closed.estimates, rtol=0, atol=1e-10)
    np.testing.assert_allclose(table.estimate_std, closed.standard_deviations, rtol=0, atol=1e-12)
    np.testing.assert_array_equal(table.truth, task.truth)
