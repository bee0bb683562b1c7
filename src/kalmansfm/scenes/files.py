"""A rendered scene as a folder: its frames as PNG and its ground truth as CSV, with a ``summary.json``."""

from __future__ import annotations

import os
from pathlib import Path

from ..io.atomic import OutputDirectory, output_directory
from ..io.frames import stage_frames
from ..io.ground_truth import ground_truth_files
from ..io.summary import RunSummary, summary_json
from .polyhedron import Scene

__all__ = ["scene_description", "stage_ground_truth", "write_scene"]


def stage_ground_truth(out: OutputDirectory, scene: Scene) -> list[str]:
    """Stage the scene's ground-truth CSV files; returns their names."""
    files = ground_truth_files(scene.ground_truth())
    for name, text in files.items():
        out.write_text(name, text)
    return list(files)


def scene_description(scene: Scene) -> str:
    """How a run names the built-in scene it used, e.g. ``built-in scene (seed 0, 30 frames)``."""
    return f"built-in scene (seed {scene.parameters.get('seed')}, {scene.n_frames} frames)"


def write_scene(scene: Scene, path: str | os.PathLike[str]) -> list[Path]:
    """Write a scene's frames as PNG and its ground truth as CSV into the folder ``path``.

    The files appear together or not at all (see :func:`kalmansfm.io.output_directory`),
    with a ``summary.json`` that records the rendering parameters and lists them.

    Returns
    -------
    list of Path
        The files written.

    Examples
    --------
    >>> import tempfile, pathlib
    >>> from kalmansfm.io import read_ground_truth
    >>> from kalmansfm.scenes import render_scene
    >>> folder = pathlib.Path(tempfile.mkdtemp()) / "scene"
    >>> files = write_scene(render_scene(n_frames=3, pixel_noise_std=0.0), folder)
    >>> sorted(p.name for p in files)[:4]
    ['frame_000.png', 'frame_001.png', 'frame_002.png', 'ground_truth_motion.csv']
    >>> read_ground_truth(folder).positions.shape
    (3, 10, 2)
    """
    with output_directory(path) as out:
        names = stage_frames(out, list(scene.frames)) + stage_ground_truth(out, scene)
        summary = RunSummary(command="scene", input=scene_description(scene), scene=scene.parameters,
                             files=tuple(names) + ("summary.json",))
        out.write_text("summary.json", summary_json(summary))
    return [Path(path) / name for name in summary.files]
