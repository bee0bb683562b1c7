"""Write ``K.csv`` (frame,fx,fy,cx,cy,skew) from a cameras CSV by RQ decomposition of each 3 × 4 matrix.

For data that ship projection matrices but whose reconstruction you want to recover from the tracks
and the intrinsics alone (the Oxford VGG sets: ``examples/oxford_to_csv.py`` writes their cameras.csv).
K has a positive diagonal and K[2, 2] = 1 whatever the sign of the matrix (a mirrored frame only flips
the rotation).

Usage::

    python examples/oxford_to_csv.py ../shared/data/oxford_model_house out/house
    python examples/intrinsics_from_cameras.py out/house/cameras.csv out/house/K.csv
    kalmansfm reconstruct out/house/tracks.csv --camera perspective --intrinsics out/house/K.csv --out out/house/persp
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from kalmansfm.io.cameras import read_cameras
from kalmansfm.io.intrinsics import intrinsics_csv


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("cameras", type=Path, help="cameras CSV (either layout of kalmansfm.io.cameras)")
    parser.add_argument("out", type=Path, help="K.csv to write")
    args = parser.parse_args(argv)
    cameras = read_cameras(args.cameras)
    args.out.write_text(intrinsics_csv(cameras.frames, cameras.decompose().intrinsics))
    print(args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
