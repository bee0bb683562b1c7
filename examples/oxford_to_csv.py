"""Convert an Oxford VGG multi-view dataset (Model House, Merton College I) to kalmansfm's files.

The VGG data (``../shared/data/oxford_model_house``, ``../shared/data/oxford_merton1``; see
their READMEs) give, per view, a corner list, a 3 × 4 camera matrix, and an n-view match
table whose row i links point i of the dataset's own 3-D reconstruction to a corner in each
view; :func:`kalmansfm.io.oxford.read_oxford` reads them.  This script writes

* ``tracks.csv`` — ``frame,track_id,x,y``: one row per matched corner; the track id is the
  row of the match table (= the index of the dataset's 3-D point), the frame the view number
  of the file names (house.00N → N, Merton 00N → N);
* ``cameras.csv`` — ``frame,p11,...,p34``: the view's camera matrix;
* ``points3d.csv`` — ``track_id,X,Y,Z``: the dataset's own 3-D points, for comparison.

Usage::

    python examples/oxford_to_csv.py ../shared/data/oxford_model_house out/house
    kalmansfm fuse out/house/tracks.csv --cameras out/house/cameras.csv --out out/house/fused
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from kalmansfm.io.cameras import cameras_csv
from kalmansfm.io.oxford import read_oxford
from kalmansfm.io.structure import structure_csv
from kalmansfm.io.tracks import observations_csv


def convert(folder: str | Path, out: str | Path) -> list[Path]:
    """Write tracks.csv, cameras.csv and points3d.csv for the dataset in ``folder`` into ``out``."""
    data = read_oxford(folder)
    target = Path(out)
    target.mkdir(parents=True, exist_ok=True)
    texts = {
        "tracks.csv": observations_csv(data.observations, data.cameras.frames),
        "cameras.csv": cameras_csv(data.cameras),
        "points3d.csv": structure_csv(np.arange(len(data.points)), data.points),
    }
    for name, text in texts.items():
        (target / name).write_text(text)
    return [target / name for name in texts]


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
