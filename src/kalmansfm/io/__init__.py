"""Input and output: frames in; tracks and structure out (CSV, NPZ, PLY); atomic writes."""

from .atomic import OutputDirectory, atomic_write, output_directory
from .frames import FrameSource, read_frames
from .ground_truth import GroundTruth, read_ground_truth, read_ground_truth_tracks, write_scene
from .tracks import read_points_csv, read_tracks_csv, read_tracks_npz, write_tracks_csv, write_tracks_npz

__all__ = [
    "FrameSource",
    "GroundTruth",
    "OutputDirectory",
    "atomic_write",
    "output_directory",
    "read_frames",
    "read_ground_truth",
    "read_ground_truth_tracks",
    "read_points_csv",
    "read_tracks_csv",
    "read_tracks_npz",
    "write_scene",
    "write_tracks_csv",
    "write_tracks_npz",
]
