"""Write ``K.csv`` and ``cameras.csv`` from a Middlebury multi-view ring's ``*_par.txt``.

The Middlebury rings (templeRing, dinoRing) publish, per image, ``name k11..k33 r11..r33 t1 t2 t3``
with x_cam = R X + t. ``K.csv`` is what ``reconstruct --camera perspective`` needs to recover the
cameras from the images alone; ``cameras.csv`` (the published cameras, intrinsics + pose layout) is
the truth to compare with, or the input of ``kalmansfm fuse --cameras``. Frame k is the k-th image
in natural order, as ``reconstruct`` numbers a folder of images.

Usage::

    python examples/middlebury_to_csv.py ../shared/data/middlebury_templering ring
    kalmansfm reconstruct ../shared/data/middlebury_templering/images --camera perspective \\
        --intrinsics ring/K.csv --out ring/run
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from kalmansfm.errors import InvalidInputError
from kalmansfm.io.cameras import pose_cameras_csv
from kalmansfm.io.intrinsics import intrinsics_csv
from kalmansfm.io.middlebury import read_middlebury_cameras


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("folder", type=Path, help="the dataset folder, holding one *_par.txt and images/")
    parser.add_argument("out", type=Path, help="folder to write K.csv and cameras.csv into")
    args = parser.parse_args(argv)
    found = sorted(args.folder.glob("*_par.txt"))
    if len(found) != 1:
        print(f"error: {args.folder}: expected one *_par.txt, found {len(found)}", file=sys.stderr)
        return 2
    try:
        cams = read_middlebury_cameras(found[0])  # in natural order of the names, as reconstruct reads a folder
    except InvalidInputError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    frames = np.arange(len(cams.names))
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "K.csv").write_text(intrinsics_csv(frames, cams.intrinsics), encoding="utf-8")
    (args.out / "cameras.csv").write_text(pose_cameras_csv(frames, cams.intrinsics, cams.rotations, cams.translations),
                                          encoding="utf-8")
    print(f"{args.out / 'K.csv'}, {args.out / 'cameras.csv'}: {len(cams.names)} images")
    return 0


if __name__ == "__main__":
    sys.exit(main())
