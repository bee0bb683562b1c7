"""A first run on real footage, shared by the end-to-end tests: ``kalmansfm demo --input`` on 24 cmu_hotel frames."""

import contextlib
import io
import shutil
from dataclasses import dataclass
from pathlib import Path

import pytest

from kalmansfm.cli.main import main

HOTEL = Path(__file__).resolve().parents[3] / "shared" / "data" / "cmu_hotel" / "images"


@dataclass(frozen=True)
class CommandRun:
    out: Path
    printed: str


@pytest.fixture(scope="session")
def hotel_run(tmp_path_factory) -> CommandRun:
    """``kalmansfm demo --input FRAMES --out RUN --matcher search`` on cmu_hotel frames 0–23 (200 detected corners).

    The seed's search matcher ends more tracks after 2–3 frames than the default matcher does:
    the case of issue 16 (points at Z of thousands of pixels), which these tests keep in view.
    """
    folder = tmp_path_factory.mktemp("hotel")
    frames = folder / "frames"
    frames.mkdir()
    for k in range(24):
        shutil.copy(HOTEL / f"hotel.seq{k}.png", frames)
    out = folder / "run"
    printed = io.StringIO()
    with contextlib.redirect_stdout(printed):
        assert main(["demo", "--input", str(frames), "--out", str(out), "--matcher", "search", "--quiet"]) == 0
    return CommandRun(out, printed.getvalue())
