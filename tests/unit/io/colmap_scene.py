"""A small calibrated scene for the COLMAP tests: frames on an arc, points seen in some of them, exact projections."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from kalmansfm.io.colmap import ColmapModel, build_colmap_model
from kalmansfm.structure.geometry.pinhole import CameraSet, project_points

#: ../shared/data, found from any checkout (the main one or a worktree beside it).
DATA = next((p / "shared" / "data" for p in Path(__file__).resolve().parents if (p / "shared" / "data").is_dir()),
            Path("shared") / "data")


@dataclass(frozen=True)
class Scene:
    K: np.ndarray  # (F, 3, 3), kalmansfm pixels
    R: np.ndarray
    t: np.ndarray
    size: tuple[int, int]
    names: list[str]
    frames: np.ndarray  # (N,) observation frame index
    points_of: np.ndarray  # (N,) observation point index
    xy: np.ndarray  # (N, 2) kalmansfm pixels
    X: np.ndarray  # (P, 3)
    colours: np.ndarray
    errors: np.ndarray
    covariances: np.ndarray

    @property
    def centres(self) -> np.ndarray:
        return -np.einsum("fji,fj->fi", self.R, self.t)

    def model(self, **changes: object) -> ColmapModel:
        arguments = dict(colours=self.colours, errors=self.errors, covariances=self.covariances,
                         covariance_gauge="free-network gauge (test)")
        arguments.update(changes)
        return build_colmap_model(self.K, self.R, self.t, self.size, self.names, self.frames, self.points_of, self.xy,
                                  self.X, **arguments)


def make_scene(frames: int = 6, points: int = 120, seed: int = 0) -> Scene:
    rng = np.random.default_rng(seed)
    X = rng.normal(size=(points, 3)) + [0.0, 0.0, 0.5]
    angles = np.linspace(-0.5, 0.5, frames)
    centres = np.stack([6 * np.sin(angles), 0.3 * angles, -6 * np.cos(angles)], axis=1)
    # look at the origin: the optical axis from the centre to 0, then a small roll
    R = np.stack([Rotation.from_euler("y", -a).as_matrix() for a in angles])
    R = Rotation.from_rotvec(rng.normal(scale=0.02, size=(frames, 3))).as_matrix() @ R
    t = -np.einsum("fij,fj->fi", R, centres)
    K = np.array([[[800.0 + 7 * f, 0.0, 319.5 + f], [0.0, 805.0, 239.5], [0.0, 0.0, 1.0]] for f in range(frames)])
    K[frames // 2] = K[0]  # two frames share a camera
    pixels = project_points(CameraSet.from_pose(K, R, t), X).pixels
    seen = rng.random((frames, points)) < 0.7
    seen[:2] = True  # every point in at least two views
    f, p = np.nonzero(seen)
    xy = pixels[f, p] + rng.normal(scale=0.3, size=(len(f), 2))
    A = rng.normal(size=(points, 3, 3)) * 1e-3
    return Scene(K, R, t, (640, 480), [f"frame_{k:04d}.png" for k in range(frames)], f, p, xy, X,
                 rng.integers(0, 256, size=(points, 3)).astype(np.uint8), rng.uniform(0.1, 1.0, points),
                 A @ np.swapaxes(A, 1, 2) + np.eye(3) * 1e-8)
