"""Synthetic orthographic scenes with known shape and motion."""

from __future__ import annotations

import numpy as np


def random_rotation(rng: np.random.Generator) -> np.ndarray:
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))
    return q * np.sign(np.linalg.det(q))


def orthographic_scene(rng: np.random.Generator, frames: int = 12, points: int = 25, noise_px: float = 0.0):
    """(positions (F, P, 2), shape (P, 3), rotations (F, 3, 3)) of a rigid object seen orthographically."""
    shape = rng.normal(size=(points, 3)) * np.array([40.0, 30.0, 20.0])
    rotations = np.stack([random_rotation(rng) for _ in range(frames)])
    offsets = rng.uniform(100, 400, size=(frames, 1, 2))
    positions = np.einsum("fij,pj->fpi", rotations[:, :2], shape) + offsets
    positions += noise_px * rng.normal(size=positions.shape)
    return positions, shape, rotations
