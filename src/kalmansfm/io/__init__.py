"""Input and output: frames in; tracks and structure out (CSV, NPZ, PLY); atomic writes."""

from .atomic import OutputDirectory, atomic_write, output_directory

__all__ = ["OutputDirectory", "atomic_write", "output_directory"]
