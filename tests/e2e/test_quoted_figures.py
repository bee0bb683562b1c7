"""The figures the README and docs/perspective.md quote from real clips are recomputed here and must match.

Each quoted sentence is found by a pattern in the document and its numbers compared with a fresh run
of the command it describes, so a change in the tracker or the estimators that moves a figure fails
here until the document says the new one.
"""

import re
from pathlib import Path

import pytest

from kalmansfm.pipeline import Affine, DemoRequest, Perspective, run_demo
from kalmansfm.tracking import TrackerSettings

ROOT = Path(__file__).resolve().parents[2]
DATA = ROOT / ".." / "shared" / "data"
pytestmark = pytest.mark.slow


def _spaced(number: int) -> str:
    """A count as the docs print it: thin groups of three (9 321)."""
    return f"{number:,}".replace(",", " ")


def _text(name: str) -> str:
    return " ".join((ROOT / name).read_text(encoding="utf-8").split())  # line breaks as spaces


def test_the_static_clip_figures_of_the_readme(tmp_path):
    run = run_demo(DemoRequest(tmp_path / "tree", input=DATA / "opencv_samples" / "tree.avi", camera=Affine(),
                               html=False, save_frames=False))
    r = run.summary.reconstruction
    quoted = re.search(r"marks (\d+) of (\d+) points unreliable", _text("README.md"))
    assert quoted is not None, "README.md no longer quotes the tree.avi figures"
    # of the points that got a position, those marked unreliable
    assert (int(quoted.group(1)), int(quoted.group(2))) == (r.unreliable, r.reconstructed + r.unreliable)


@pytest.fixture(scope="module")
def hotel(tmp_path_factory):
    out = tmp_path_factory.mktemp("hotel")
    images = DATA / "cmu_hotel" / "images"

    def run(focal: float, matcher: str = "differential"):
        request = DemoRequest(out / f"{focal}-{matcher}", input=images, camera=Perspective(focal=focal),
                              tracker=TrackerSettings(matcher=matcher), html=False, save_frames=False)
        return run_demo(request).summary.reconstruction

    return run


def test_the_hotel_perspective_figures_of_docs_perspective(hotel):
    text = _text("docs/perspective.md")
    r = hotel(1000.0)
    main = re.search(r"all (\d+) frames registered, (\d+) of (\d+) points, \*\*reprojection RMS ([\d.]+) px\*\*, "
                     r"σ ([\d.]+) px, ([\d ]+) of ([\d ]+) observations inliers", text)
    assert main is not None, "docs/perspective.md no longer quotes the hotel figures"
    assert main.groups() == (str(r.registered_frames), str(r.reconstructed), str(r.points),
                             f"{r.reprojection_rms_px:.3f}", f"{r.noise_std:.3f}", _spaced(r.used),
                             _spaced(r.observations))
    search = hotel(1000.0, "search")
    quoted = re.search(r"with `--matcher search`'s tracks \(the default before issue 21\) (\d+) points, ([\d.]+) px, "
                       r"σ ([\d.]+) px, ([\d ]+) of ([\d ]+) inliers", text)
    assert quoted is not None
    assert quoted.groups() == (str(search.reconstructed), f"{search.reprojection_rms_px:.3f}",
                               f"{search.noise_std:.3f}", _spaced(search.used), _spaced(search.observations))
    short, long = hotel(500.0), hotel(2000.0)
    focal = re.search(r"500 px gives ([\d.]+) px \((\d+) points\), 2 000 px ([\d.]+) px \((\d+) points\)", text)
    assert focal is not None
    assert focal.groups() == (f"{short.reprojection_rms_px:.3f}", str(short.reconstructed),
                              f"{long.reprojection_rms_px:.3f}", str(long.reconstructed))
