"""The published experiments: the fusion tasks of Thomas & Oliensis (Tasks 1-7), their
Monte Carlo consistency study, and the seed report's own polyhedron tracks.

They use the estimation and structure layers like any user would; nothing below imports them.
"""

from .consistency import ConsistencyResult, run_consistency, task2_consistency, task7_consistency
from .fusion_tasks import FusionTable, FusionTask, available_tasks, load_task, run_task
from .moving_camera import CameraPath, report_path
from .report_tracks import report_tracks
from .tables import fusion_table
from .task7 import Task7Result, simulate_task7, task7_table

__all__ = [
    "CameraPath",
    "ConsistencyResult",
    "FusionTable",
    "FusionTask",
    "Task7Result",
    "available_tasks",
    "fusion_table",
    "load_task",
    "report_path",
    "report_tracks",
    "run_consistency",
    "run_task",
    "simulate_task7",
    "task2_consistency",
    "task7_consistency",
    "task7_table",
]
