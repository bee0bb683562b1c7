"""Helpers of the Oxford VGG golden tests: where the data are, and their conversion as a user would do it."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
DATA = ROOT / ".." / "shared" / "data"
DATASETS = ("oxford_model_house", "oxford_merton1")


def convert(name: str, out: Path) -> None:
    """Run the documented converter (examples/oxford_to_csv.py) on dataset ``name``, writing into ``out``."""
    subprocess.run([sys.executable, str(ROOT / "examples" / "oxford_to_csv.py"), str(DATA / name), str(out)],
                   check=True, capture_output=True)
