"""Items of issue 30 that need a change in files the robustness branch does not own: each fails today.

Each test is ``xfail(strict=True)``: once the owner makes the change it passes, strict xfail turns
that into a failure, and the marker is removed.  The command line already refuses these cases in
one line (generic checks in ``cli/main.py`` and ``cli/_options.py``); what is missing is the
library's own check, with the argument's name, for API users and for a clearer message.
"""

from __future__ import annotations

import os
import sys

import numpy as np
import pytest

from kalmansfm.cli.main import main
from kalmansfm.errors import InvalidInputError
from kalmansfm.io import RunSummary, summary_json


@pytest.mark.xfail(strict=True, reason="report/html.py build_report: path.write_text(document, encoding='utf-8') "
                   "is strict; a run folder whose name is not UTF-8 needs errors='backslashreplace' there")
def test_report_of_a_run_folder_whose_name_is_not_utf8(tmp_path, capsys):
    run = tmp_path / os.fsdecode(b"run\xff")
    run.mkdir()
    (run / "summary.json").write_text(summary_json(RunSummary("track", "x", files=("summary.json",))))
    assert main(["report", str(run), "--quiet"]) == 0, capsys.readouterr().err
    assert (run / "report.html").exists()


@pytest.mark.xfail(strict=True, reason="structure/fusion/point_fusion.py FusionSettings accepts pixel_std=1e300, "
                   "which overflows later (OverflowError); it should refuse it with a range, as gate_radius does")
def test_fusion_settings_refuse_a_pixel_std_too_large_to_compute_with():
    from kalmansfm.structure.fusion.point_fusion import FusionSettings

    with pytest.raises(InvalidInputError, match="pixel_std"):
        FusionSettings(pixel_std=1e300)


@pytest.mark.xfail(strict=True, reason="io/intrinsics.py intrinsics_from_focal (and structure/geometry/triangulation.py "
                   "check_focal) accept focal 1e-300 and 1e300, which end as 'no frame pair gives an essential matrix' "
                   "after NumPy overflow warnings; a range such as 1e-3 … 1e7 px would name --focal")
@pytest.mark.parametrize("focal", [1e-300, 1e300])
def test_an_absurd_focal_length_is_refused_with_its_name(focal):
    from kalmansfm.io.intrinsics import intrinsics_from_focal

    with pytest.raises(InvalidInputError, match="focal"):
        intrinsics_from_focal(focal, (640, 480), 3)


@pytest.mark.xfail(strict=True, reason="estimation/kalman.py KalmanFilter allocates (N, n) states unchecked: N = 1e11 "
                   "raises NumPy's _ArrayMemoryError ('Unable to allocate 2.91 TiB'); it should say which argument "
                   "and how much memory, as render_scene does")
def test_a_kalman_filter_too_large_for_memory_is_refused_naming_its_argument():
    from kalmansfm.estimation import KalmanFilter, constant_velocity_2d

    model = constant_velocity_2d()
    with pytest.raises(InvalidInputError, match="x0|states|filters"):
        KalmanFilter(np.broadcast_to(np.zeros(4), (10**11, 4)), model.P0, model.F, model.H, model.Q, model.R)


@pytest.mark.skipif(sys.platform == "win32", reason="a folder given as a CSV")
@pytest.mark.xfail(strict=True, reason="io/tracks.py read_tracks and io/_csv.py read_rows say 'no such file' / "
                   "'(Is a directory)' for a folder; io.paths.path_problem and Path.is_dir give the words: "
                   "'… is a folder, not a file'")
def test_a_folder_given_as_a_tracks_file_is_called_a_folder(tmp_path):
    from kalmansfm.io.tracks import read_tracks

    with pytest.raises(InvalidInputError, match="is a folder, not a file"):
        read_tracks(tmp_path)


@pytest.mark.skipif(sys.platform == "win32", reason="the C locale is POSIX")
@pytest.mark.xfail(strict=True, reason="report/html.py writes the page with strict UTF-8: under LC_ALL=C a name such as "
                   "'dé' is 'd\\udcc3\\udca9' to Python; decoding names with os.fsencode(name).decode('utf-8', "
                   "'backslashreplace') where the page shows them would give 'dé' (today: exit 2, one line)")
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
