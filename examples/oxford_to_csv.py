"""Convert an Oxford VGG multi-view dataset (Model House, Merton College I) to kalmansfm's files.

The VGG data (``../shared/data/oxford_model_house``, ``../shared/data/oxford_merton1``; see
their READMEs) give, per view, a corner list, a 3 × 4 camera matrix, and an n-view match
table whose row i links point i of the dataset's own 3-D reconstruction to a corner in each
view (``*`` = not seen).  This script writes

* ``tracks.csv`` — ``frame,track_id,x,y``: one row per matched corner; the track id is the
  row of the match table (= the index of the dataset's 3-D point), the frame the view number
  of the file names (house.00N → N, Merton 00N → N);
* ``cameras.csv`` — ``frame,p11,...,p34``: the view's camera matrix;
* ``points3d.csv`` — ``track_id,X,Y,Z``: the dataset's own 3-D points, for comparison.

Usage::

    python examples/oxford_to_csv.py ../shared/data/oxford_model_house out/house
    kalmansfm fuse out/house/tracks.csv --cameras out/house/cameras.csv --out out/house/fused

The two layouts differ only in where the files sit; both are recognised from the folder.
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from kalmansfm.io.cameras import cameras_csv
from kalmansfm.structure.pinhole import CameraSet


@dataclass(frozen=True)
class OxfordDataset:
    """A VGG dataset in kalmansfm's terms."""

    cameras: CameraSet
    observations: np.ndarray  # (V, N, 2), NaN where the point is not seen
    points: np.ndarray  # (N, 3), the dataset's reconstruction


def load_oxford(folder: str | Path) -> OxfordDataset:
    """Read a Model House or Merton College I folder."""
    root = Path(folder)
    if (root / "2D" / "house.nview-corners").is_file():  # Model House
        views = sorted(root.glob("3D/house.*.P"))
        corners = [root / "2D" / p.name.replace(".P", ".corners") for p in views]
        table, points = root / "2D" / "house.nview-corners", root / "3D" / "house.p3d"
        frames = [int(p.name.split(".")[1]) for p in views]
    elif (root / "2D" / "nview-corners").is_file():  # Merton College I
        views = sorted(root.glob("2D/*.P"))
        corners = [p.with_suffix(".corners") for p in views]
        table, points = root / "2D" / "nview-corners", root / "3D" / "p3d"
        frames = [int(p.stem) for p in views]
    else:
        raise SystemExit(f"{root}: not an Oxford VGG dataset folder (no nview-corners table)")
    P = np.stack([np.loadtxt(p) for p in views])
    match = np.genfromtxt(table, dtype=float, missing_values="*", filling_values=-1).astype(int)
    X = np.loadtxt(points)
    obs = np.full((len(views), len(X), 2), np.nan)
    for v, corner_file in enumerate(corners):  # one table column per view
        xy = np.loadtxt(corner_file)
        seen = match[:, v] >= 0
        obs[v, seen] = xy[match[seen, v]]
    return OxfordDataset(CameraSet.from_matrices(P, frames), obs, X)


def tracks_csv(dataset: OxfordDataset) -> str:
    """``frame,track_id,x,y`` rows of every observation, by frame then track."""
    v, n = np.nonzero(np.isfinite(dataset.observations[..., 0]))
    xy = dataset.observations[v, n]
    frames = dataset.cameras.frames[v]
    rows = [f"{f},{t},{x!r},{y!r}" for f, t, (x, y) in zip(frames, n, xy.tolist())]
    return "frame,track_id,x,y\n" + "\n".join(rows) + "\n"


def points_csv(dataset: OxfordDataset) -> str:
    """``track_id,X,Y,Z`` of the dataset's own points."""
    rows = [f"{i},{x!r},{y!r},{z!r}" for i, (x, y, z) in enumerate(dataset.points.tolist())]
    return "track_id,X,Y,Z\n" + "\n".join(rows) + "\n"


def convert(folder: str | Path, out: str | Path) -> list[Path]:
    """Write tracks.csv, cameras.csv and points3d.csv for the dataset in ``folder`` into ``out``."""
    dataset = load_oxford(folder)
    target = Path(out)
    target.mkdir(parents=True, exist_ok=True)
    written = []
    for name, text in (("tracks.csv", tracks_csv(dataset)), ("cameras.csv", cameras_csv(dataset.cameras)),
                       ("points3d.csv", points_csv(dataset))):
        (target / name).write_text(text)
        written.append(target / name)
    return written


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("dataset", help="the dataset folder, e.g. ../shared/data/oxford_model_house")
    parser.add_argument("out", help="folder for tracks.csv, cameras.csv and points3d.csv")
    args = parser.parse_args(argv)
    for path in convert(args.dataset, args.out):
        print(path)
    return 0


if __name__ == "__main__":
    sys.exit(main())
