import subprocess
import sys
from importlib.resources import files
from pathlib import Path

import numpy as np
import pytest

from kalmansfm.cli.main import main
from kalmansfm.io import read_summary

REPORT_CSV = Path(str(files("kalmansfm") / "data" / "report_polyhedron_tracks.csv"))


def test_reconstruct_writes_all_files(tmp_path, capsys):
    out = tmp_path / "run"
    assert main(["reconstruct", str(REPORT_CSV), "--out", str(out), "--quiet"]) == 0
    printed = capsys.readouterr().out
    assert "singular values: 1272, " in printed and "rank-3 residual: 2.88" in printed
    assert sorted(p.name for p in out.iterdir()) == [
        "motion.csv", "reconstruction.npz", "structure.csv", "structure.ply", "structure.png", "summary.json"]
    header = (out / "structure.csv").read_text().splitlines()[0]
    assert header == "track_id,X,Y,Z,cov_xx,cov_xy,cov_xz,cov_yy,cov_yz,cov_zz,views,reprojection_rms,status"
    structure = np.loadtxt(out / "structure.csv", delimiter=",", skiprows=1, usecols=range(12))
    assert structure.shape == (9, 12) and structure[:, 0].tolist() == list(range(1, 10))
    assert (structure[:, 10] == 30).all()  # every point seen in all 30 frames
    # seen equally often, the points' residual RMS combine into the run's rank-3 residual
    summary = read_summary(out / "summary.json")
    assert np.sqrt(np.mean(structure[:, 11] ** 2)) == pytest.approx(summary.reconstruction.reprojection_rms_px, rel=1e-9)
    motion = np.loadtxt(out / "motion.csv", delimiter=",", skiprows=1)
    assert motion.shape == (30, 9) and motion[0, 0] == 1
    assert summary.reconstruction.reprojection_rms_px == pytest.approx(2.88, abs=0.01)
    assert (out / "structure.png").read_bytes()[:4] == b"\x89PNG"


def test_reconstruct_uses_npz_weights(tmp_path, capsys):
    rng = np.random.default_rng(0)
    shape = rng.normal(size=(12, 3)) * 30
    rotations = [np.linalg.qr(rng.normal(size=(3, 3)))[0][:2] for _ in range(6)]
    positions = np.stack([shape @ r.T + 200 for r in rotations])
    status = np.ones((6, 12), int)
    status[0, :3] = 2
    cov = np.broadcast_to(np.eye(4), (6, 12, 4, 4)).copy()
    np.savez(tmp_path / "tracks.npz", positions=positions, status=status, covariances=cov, track_ids=np.arange(12))
    assert main(["reconstruct", str(tmp_path / "tracks.npz"), "--out", str(tmp_path / "o"), "--no-plot", "-q"]) == 0
    printed = capsys.readouterr().out
    assert "weighted by tracker std" in printed and "method: als" in printed
    assert float(printed.split("rank-3 residual: ")[1].split()[0]) < 1e-6


@pytest.mark.parametrize(
    ("content", "message"),
    [
        ("frame,track_id,x,y\n0,1,2,3\n0,2,oops,3\n", "line 3: x must be a number"),
        ("frame,track_id,x,y\n0,1,2,3\n1,1,2,3\n", "needs >= 3 frames"),
    ],
)
def test_bad_input_exit_2_and_nothing_written(tmp_path, content, message):
    bad = tmp_path / "bad.csv"
    bad.write_text(content)
    out = tmp_path / "never"
    proc = subprocess.run(
        [sys.executable, "-m", "kalmansfm", "reconstruct", str(bad), "--out", str(out), "--quiet"],
        capture_output=True, text=True, env={"PYTHONPATH": str(Path(__file__).resolve().parents[2] / "src")},
    )
    assert proc.returncode == 2, proc.stderr
    assert len(proc.stderr.strip().splitlines()) == 1 and message in proc.stderr
    assert not out.exists()
