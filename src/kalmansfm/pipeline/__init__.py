"""One function per command: each ``kalmansfm`` subcommand is one call of this package.

=====================  ========================================================
command                library call
=====================  ========================================================
``kalmansfm demo``     :func:`run_demo` (frames → tracks → structure → report)
``kalmansfm track``    :func:`run_track`
``kalmansfm reconstruct``  :func:`run_reconstruct`
``kalmansfm fuse``     :func:`run_fuse` (known cameras; chunks on Dask on request)
``kalmansfm scene``    :func:`run_scene`
``kalmansfm batch``    :func:`run_batch` (:func:`run_demo` per sequence, on Dask)
``kalmansfm report``   :func:`kalmansfm.report.build_report`
``kalmansfm tables``   :func:`kalmansfm.experiments.fusion_table`
``kalmansfm consistency``  :func:`kalmansfm.experiments.run_consistency`
=====================  ========================================================
"""

from .batch import BatchResult, BatchRow, run_batch
from .demo import DemoRun, describe, run_demo
from .fuse import FuseRun, run_fuse
from .evaluate import compare_with_truth, factorize_tracks, reconstruction_metrics, tracking_metrics
from .reconstruct import ReconstructRun, read_tracks_for_factorization, run_reconstruct
from .requests import (
    Affine,
    Auto,
    DemoRequest,
    FuseRequest,
    Perspective,
    ReconstructRequest,
    TrackRequest,
)
from .scene import run_scene
from .track import TrackRun, run_track

__all__ = [
    "Affine",
    "Auto",
    "BatchResult",
    "BatchRow",
    "DemoRequest",
    "DemoRun",
    "FuseRequest",
    "FuseRun",
    "Perspective",
    "ReconstructRequest",
    "ReconstructRun",
    "TrackRequest",
    "TrackRun",
    "compare_with_truth",
    "describe",
    "factorize_tracks",
    "read_tracks_for_factorization",
    "run_batch",
    "run_demo",
    "run_fuse",
    "run_reconstruct",
    "run_scene",
    "run_track",
    "reconstruction_metrics",
    "tracking_metrics",
]
