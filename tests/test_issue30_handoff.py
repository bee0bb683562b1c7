"""Items of issue 30 checked at the library: each refusal names its argument for API users too.

The command line refuses these cases in one line (generic checks in ``cli/main.py`` and
``cli/_options.py``); here the library itself says what is wrong, with the argument's name.
"""

from __future__ import annotations

import os
import sys

import numpy as np
import pytest

from kalmansfm.errors import InvalidInputError
from kalmansfm.io import RunSummary, summary_json


def test_report_of_a_run_folder_whose_name_is_not_utf8(tmp_path):
    import subprocess
    from pathlib import Path

    run = tmp_path / os.fsdecode(b"run\xff")
    run.mkdir()
    (run / "summary.json").write_text(summary_json(RunSummary("track", "x", files=("summary.json",))))
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[1] / "src")}
    # a subprocess: the command prints the name as its own bytes, which no str capture can hold
    result = subprocess.run([sys.executable, "-m", "kalmansfm", "report", os.fsencode(run), "--quiet"],
                            capture_output=True, env=env, timeout=120)
    assert result.returncode == 0, result.stderr
    assert result.stdout.strip().endswith(b"run\xff/report.html")
    assert (run / "report.html").exists() and b"run\\xff" in (run / "report.html").read_bytes()


def test_fusion_settings_refuse_a_pixel_std_too_large_to_compute_with():
    from kalmansfm.structure.fusion import FusionSettings

    with pytest.raises(InvalidInputError, match="pixel_std"):
        FusionSettings(pixel_std=1e300)


@pytest.mark.parametrize("focal", [1e-300, 1e300])
def test_an_absurd_focal_length_is_refused_with_its_name(focal):
    from kalmansfm.io.intrinsics import intrinsics_from_focal

    with pytest.raises(InvalidInputError, match="focal"):
        intrinsics_from_focal(focal, (640, 480), 3)


def test_a_kalman_filter_too_large_for_memory_is_refused_naming_its_argument():
    from kalmansfm.estimation import KalmanFilter, constant_velocity_2d

    model = constant_velocity_2d()
    with pytest.raises(InvalidInputError, match="x0|states|filters"):
        KalmanFilter(np.broadcast_to(np.zeros(4), (10**11, 4)), model.P0, model.F, model.H, model.Q, model.R)


@pytest.mark.skipif(sys.platform == "win32", reason="a folder given as a CSV")
def test_a_folder_given_as_a_tracks_file_is_called_a_folder(tmp_path):
    from kalmansfm.io.tracks import read_tracks

    with pytest.raises(InvalidInputError, match="is a folder, not a file"):
        read_tracks(tmp_path)


@pytest.mark.skipif(sys.platform == "win32", reason="the C locale is POSIX")
def test_demo_of_a_non_ascii_folder_under_the_c_locale_writes_its_report(tmp_path):
    import subprocess
    from pathlib import Path

    import cv2

    frames = tmp_path / "dé"
    frames.mkdir()
    for k in range(4):
        image = np.zeros((60, 80), np.uint8)
        image[10 + 2 * k:30 + 2 * k, 20 + 3 * k:40 + 3 * k] = 200
        (frames / f"f{k}.png").write_bytes(cv2.imencode(".png", image)[1].tobytes())
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[1] / "src"), "LC_ALL": "C",
           "PYTHONCOERCECLOCALE": "0", "PYTHONUTF8": "0"}
    result = subprocess.run([sys.executable, "-m", "kalmansfm", "demo", "--input", "dé", "--out", "dö", "--quiet"],
                            cwd=tmp_path, capture_output=True, env=env, timeout=300)
    assert result.returncode == 0, result.stderr
    assert (tmp_path / "dö" / "report.html").exists()
