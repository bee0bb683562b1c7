"""``kalmansfm demo --camera perspective --focal F`` on a real clip: tracked, registered, reported."""

import shutil
from pathlib import Path

import pytest

from kalmansfm.cli.main import main
from kalmansfm.io import read_summary

HOTEL = Path(__file__).resolve().parents[2] / ".." / "shared" / "data" / "cmu_hotel" / "images"


@pytest.fixture(scope="module")
def clip(tmp_path_factory):
    """The first 16 frames of the CMU hotel sequence (a slice keeps the test short)."""
    folder = tmp_path_factory.mktemp("hotel")
    for k in range(16):
        shutil.copy(HOTEL / f"hotel.seq{k}.png", folder / f"frame_{k:03d}.png")
    return folder


def test_demo_reconstructs_a_real_clip_with_a_perspective_camera(clip, tmp_path, capsys):
    out = tmp_path / "run"
    assert main(["demo", "--input", str(clip), "--camera", "perspective", "--focal", "1000", "--out", str(out),
                 "--quiet"]) == 0
    printed = capsys.readouterr().out
    assert "perspective reconstruction: 16 of 16 frames registered" in printed
    p = read_summary(out / "summary.json").reconstruction
    assert p.registered_frames == 16 and p.reconstructed >= 150
    assert p.reprojection_rms_px < 1.0  # the tracker's sub-pixel positions fit one rigid perspective scene
    html = (out / "report.html").read_text()
    assert "calibrated cameras, unknown motion" in html and "reprojection RMS" in html


def test_perspective_demo_needs_a_sequence_and_a_focal_length(tmp_path, capsys):
    assert main(["demo", "--camera", "perspective", "--focal", "800", "--out", str(tmp_path / "run")]) == 2
    assert "needs your own sequence as --input" in capsys.readouterr().err
    assert not (tmp_path / "run").exists()
