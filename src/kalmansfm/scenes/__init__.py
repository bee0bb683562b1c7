"""Built-in data: the synthetic polyhedron scene and the published fusion experiments."""

from .polyhedron import SCENARIOS, Occluder, Scene, render_scene
from .report_tracks import report_tracks

__all__ = ["SCENARIOS", "Occluder", "Scene", "render_scene", "report_tracks"]
