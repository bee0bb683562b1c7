"""The table of any task by number: Tasks 1-6 from the published measurements, Task 7 simulated."""

from __future__ import annotations

from ..errors import InvalidInputError
from .fusion_tasks import FusionTable, available_tasks, run_task
from ..structure.fusion.landmark import TASK7_DEFAULT_METHOD
from .task7 import DEFAULT_FOCAL, DEFAULT_PIXEL_NOISE_STD, task7_table

__all__ = ["SIMULATED_TASK", "fusion_table"]

#: The task that is simulated (structure from a moving camera) rather than read from the report.
SIMULATED_TASK = 7


def fusion_table(
    task: int,
    *,
    method: str = TASK7_DEFAULT_METHOD,
    seed: int = 0,
    focal: float = DEFAULT_FOCAL,
    pixel_noise_std: float = DEFAULT_PIXEL_NOISE_STD,
) -> FusionTable:
    """The report's table of Task ``task`` with the Kalman columns computed here.

    ``method``, ``seed``, ``focal`` and ``pixel_noise_std`` apply to Task 7 only.

    Examples
    --------
    >>> fusion_table(1).iterations, fusion_table(7, method="batch").dimension
    (30, 3)
    """
    published = available_tasks()
    if task == SIMULATED_TASK:
        return task7_table(method, seed, focal, pixel_noise_std)
    if task in published:
        return run_task(task)
    raise InvalidInputError(
        f"unknown task {task}; tasks {published[0]}-{published[-1]} (published tables) "
        f"and {SIMULATED_TASK} (simulated moving camera) are available"
    )
