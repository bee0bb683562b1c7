"""Input and output: frames in; tracks, structure, ground truth and the run summary out and back; atomic writes.

Everything that touches a file lives here, and dicts appear only here: the layers below
hand frozen records in and get frozen records back.
"""

from .atomic import OutputDirectory, atomic_write, output_directory
from .frames import FrameSource, read_frames
from .ground_truth import GroundTruth, ground_truth_files, read_ground_truth, read_ground_truth_tracks
from .run_folder import RunFolder, load_run
from .summary import RunSummary, read_summary, summary_json
from .tracks import read_points_csv, read_tracks, read_tracks_csv, read_tracks_npz, write_tracks_csv, write_tracks_npz

__all__ = [
    "FrameSource",
    "GroundTruth",
    "OutputDirectory",
    "RunFolder",
    "RunSummary",
    "atomic_write",
    "ground_truth_files",
    "load_run",
    "output_directory",
    "read_frames",
    "read_ground_truth",
    "read_ground_truth_tracks",
    "read_points_csv",
    "read_summary",
    "read_tracks",
    "read_tracks_csv",
    "read_tracks_npz",
    "summary_json",
    "write_tracks_csv",
    "write_tracks_npz",
]
