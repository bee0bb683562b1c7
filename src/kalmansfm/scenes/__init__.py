"""Built-in data: the synthetic polyhedron scene and the published fusion experiments."""

from .report_tracks import report_tracks

__all__ = ["report_tracks"]
