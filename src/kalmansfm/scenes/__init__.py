"""The built-in synthetic scene: a textured polyhedron with corner markers, rendered with exact ground truth."""

from .files import write_scene
from .polyhedron import (
    DEFAULT_SCENE_FRAMES,
    DEFAULT_SCENE_NOISE,
    DEFAULT_SCENE_SEED,
    DEFAULT_SCENE_SIZE,
    SCENARIOS,
    Occluder,
    Scene,
    render_scene,
)

__all__ = [
    "DEFAULT_SCENE_FRAMES",
    "DEFAULT_SCENE_NOISE",
    "DEFAULT_SCENE_SEED",
    "DEFAULT_SCENE_SIZE",
    "SCENARIOS",
    "Occluder",
    "Scene",
    "render_scene",
    "write_scene",
]
