"""Input and output: frames in; tracks and structure out (CSV, NPZ, PLY); atomic writes."""

from .atomic import OutputDirectory, atomic_write, output_directory
from .ground_truth import GroundTruth, read_ground_truth, read_ground_truth_tracks, write_scene

__all__ = [
    "GroundTruth",
    "OutputDirectory",
    "atomic_write",
    "output_directory",
    "read_ground_truth",
    "read_ground_truth_tracks",
    "write_scene",
]
