"""A requested reconstruction that cannot be made is an exit code a script can see, with the run still written."""

from pathlib import Path

from kalmansfm.cli.main import main
from kalmansfm.io import read_summary

DATA = Path(__file__).resolve().parents[2] / ".." / "shared" / "data"


def test_a_static_camera_cannot_be_reconstructed_in_perspective_and_the_exit_code_says_so(tmp_path, capsys):
    out = tmp_path / "tree"
    code = main(["demo", "--input", str(DATA / "opencv_samples" / "tree.avi"), "--camera", "perspective", "--focal",
                 "600", "--out", str(out), "-q"])
    captured = capsys.readouterr()
    assert code == 1
    (line,) = captured.err.strip().splitlines()
    assert "no perspective reconstruction (degenerate scene" in line and str(out) in line
    summary = read_summary(out / "summary.json")
    assert summary.reconstruction is None and "degenerate scene" in summary.structure_error
    assert (out / "tracks.npz").is_file() and (out / "report.html").is_file()
