"""The built-in synthetic scene: a textured polyhedron with corner markers, rendered with exact ground truth."""

from .files import write_scene
from .polyhedron import SCENARIOS, Occluder, Scene, render_scene

__all__ = ["SCENARIOS", "Occluder", "Scene", "render_scene", "write_scene"]
