"""``kalmansfm scene``: render the built-in sequence and write it with its ground truth."""

from __future__ import annotations

import os
from pathlib import Path

from ..io.atomic import check_output_directory
from ..scenes import (
    DEFAULT_SCENE_FRAMES,
    DEFAULT_SCENE_NOISE,
    DEFAULT_SCENE_SEED,
    DEFAULT_SCENE_SIZE,
    SCENARIOS,
    Occluder,
    Scene,
    render_scene,
    write_scene,
)

__all__ = ["run_scene"]


def run_scene(
    out_dir: str | os.PathLike[str],
    *,
    n_frames: int = DEFAULT_SCENE_FRAMES,
    image_size: tuple[int, int] = DEFAULT_SCENE_SIZE,
    seed: int = DEFAULT_SCENE_SEED,
    pixel_noise_std: float = DEFAULT_SCENE_NOISE,
    occluder: Occluder | None = None,
    scenario: str = SCENARIOS[0],
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
