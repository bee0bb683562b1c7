"""``kalmansfm scene``: render the built-in sequence and write it with its ground truth."""

from __future__ import annotations

import os
from pathlib import Path

from ..io.atomic import check_output_directory
from ..scenes import Occluder, Scene, render_scene, write_scene

__all__ = ["run_scene"]


def run_scene(
    out_dir: str | os.PathLike[str],
    *,
    n_frames: int = 30,
    image_size: tuple[int, int] = (320, 240),
    seed: int = 0,
    pixel_noise_std: float = 2.0,
    occluder: Occluder | None = None,
    scenario: str = "default",
) -> tuple[Scene, list[Path]]:
    """Render the built-in scene (every option checked before the folder is touched) and write it to ``out_dir``.

    Returns the scene and the files written.

    Examples
    --------
    >>> import tempfile, pathlib
    >>> scene, files = run_scene(pathlib.Path(tempfile.mkdtemp()) / "s", n_frames=3)
    >>> scene.n_frames, len(files)
    (3, 8)
    """
    check_output_directory(out_dir)
    scene = render_scene(n_frames=n_frames, image_size=image_size, seed=seed, pixel_noise_std=pixel_noise_std,
                         occluder=occluder, scenario=scenario)
    return scene, write_scene(scene, out_dir)
