"""``kalmansfm fuse`` on a long sequence of short tracks (issue 29): read per observation, fused in blocks of tracks.

More views than :data:`kalmansfm.structure.fusion.blocks.ONE_BLOCK_VIEWS` send the tracks through the blocks; the
result must be the dense fusion's, and the points the scene's.
"""

from __future__ import annotations

import numpy as np

from kalmansfm.cli.main import main
from kalmansfm.io import read_summary
from kalmansfm.io.cameras import cameras_csv
from kalmansfm.io.structure import read_points_table
from kalmansfm.structure.fusion import fuse
from kalmansfm.structure.fusion.blocks import ONE_BLOCK_VIEWS
from kalmansfm.structure.geometry.pinhole import CameraSet


def _sliding_camera(frames: int, tracks: int, seed: int = 0):
    """A camera sliding sideways past a wall of points, each seen in 3–12 consecutive frames, 0.5 px noise."""
    rng = np.random.default_rng(seed)
    K = np.array([[800.0, 0, 320], [0, 800, 240], [0, 0, 1]])
    centres = np.stack([0.05 * np.arange(frames), np.zeros(frames), np.zeros(frames)], axis=1)
    cams = CameraSet.from_pose(K, np.broadcast_to(np.eye(3), (frames, 3, 3)), -centres)
    length = rng.integers(3, 13, size=tracks)
    start = rng.integers(0, frames - length + 1)
    depth = rng.uniform(4, 8, size=tracks)
    points = np.stack([0.05 * (start + length / 2) + rng.uniform(-1, 1, tracks), rng.uniform(-1, 1, tracks), depth], 1)
    obs = np.full((frames, tracks, 2), np.nan)
    for k in range(tracks):  # the scene, not the code under test
        f = np.arange(start[k], start[k] + length[k])
        h = cams.matrices[f] @ np.r_[points[k], 1.0]
        obs[f, k] = h[:, :2] / h[:, 2:] + rng.normal(scale=0.5, size=(f.size, 2))
    return cams, obs, points


def test_fuse_reads_and_fuses_a_long_sequence_in_blocks_as_the_dense_fusion_would(tmp_path):
    frames = ONE_BLOCK_VIEWS + 4
    cams, obs, points = _sliding_camera(frames, 400)
    f, t = np.nonzero(np.isfinite(obs[..., 0]))
    order = np.lexsort((t, f))
    rows = "".join(f"{a},{b},{x!r},{y!r}\n" for a, b, (x, y) in zip(f[order], t[order], obs[f[order], t[order]].tolist()))
    (tmp_path / "tracks.csv").write_text("frame,track_id,x,y\n" + rows)
    (tmp_path / "cameras.csv").write_text(cameras_csv(cams))
    out = tmp_path / "fused"
    assert main(["fuse", str(tmp_path / "tracks.csv"), "--cameras", str(tmp_path / "cameras.csv"), "--out", str(out),
                 "--no-plot", "--quiet"]) == 0
    table = read_points_table(out / "structure.csv")
    dense = fuse(obs, cams)
    ok = dense.reconstructed[table.track_ids]
    assert ok.sum() > 350
    np.testing.assert_allclose(table.points[ok], dense.points[table.track_ids[ok]], rtol=1e-6, atol=1e-6)
    error = np.linalg.norm(table.points[ok] - points[table.track_ids[ok]], axis=1)
    assert np.median(error) < 0.02 * np.mean(points[:, 2])
    summary = read_summary(out / "summary.json")
    assert summary.reconstruction.observations == np.isfinite(obs[..., 0]).sum()
