"""A small, fake but self-consistent run folder for the report tests.

Five 3D points seen by an orthographic camera that pans and tilts a little per
frame, rendered as bright blobs into 8 grey frames of 64 × 48 pixels.  Track 3
is occluded (predicted) in frame 3; track 4 is predicted in frame 5 and lost
from frame 6.  Everything is generated here with NumPy so the report tests do
not depend on the tracker or the factorization.
"""

from __future__ import annotations

import csv
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np

from kalmansfm.io.summary import (
    RunSummary,
    Similarity,
    ReconstructionMetrics,
    TrackingMetrics,
    TrackMetrics,
    TruthComparison,
    Versions,
    read_summary,
    summary_json,
)
from kalmansfm.tracking import TrackerSettings

N_FRAMES, WIDTH, HEIGHT = 8, 64, 48
TRACK_IDS = np.array([0, 1, 2, 3, 4])
SHAPE = np.array(
    [[-1.0, -1.0, 0.5], [1.0, -1.0, -0.5], [1.0, 1.0, 0.5], [-1.0, 1.0, -0.5], [0.0, 0.0, 1.2]]
)
SCALE_PX, CENTRE_PX = 14.0, np.array([32.0, 24.0])


def _rotation(pan_deg: float, tilt_deg: float) -> np.ndarray:
    a, b = np.radians(pan_deg), np.radians(tilt_deg)
    pan = np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])
    tilt = np.array([[1, 0, 0], [0, np.cos(b), -np.sin(b)], [0, np.sin(b), np.cos(b)]])
    return tilt @ pan


def camera_rotations() -> np.ndarray:
    """(F, 3, 3) world → camera rotations: 4° pan and 1° tilt per frame."""
    return np.stack([_rotation(4.0 * f, 1.0 * f) for f in range(N_FRAMES)])


def true_positions() -> np.ndarray:
    """(F, P, 2) orthographic projections of SHAPE."""
    rotations = camera_rotations()
    return SCALE_PX * np.einsum("fij,pj->fpi", rotations[:, :2], SHAPE) + CENTRE_PX


def write_fake_run(
    folder: Path,
    *,
    ground_truth: bool = True,
    frames: bool = True,
    prerendered: bool = False,
    tables: bool = True,
    seed: int = 0,
) -> Path:
    """Write the fake run into ``folder`` (created) and return it."""
    rng = np.random.default_rng(seed)
    folder.mkdir(parents=True, exist_ok=True)
    truth = true_positions()
    n_points = len(TRACK_IDS)

    status = np.ones((N_FRAMES, n_points), dtype=np.int8)
    status[3, 3] = 2
    status[5, 4] = 2
    status[6:, 4] = 3
    positions = truth + rng.normal(scale=0.4, size=truth.shape)
    positions[7, 4] = np.nan
    velocities = np.gradient(positions, axis=0)
    states = np.concatenate([positions, velocities], axis=-1)
    variances = np.where(status == 2, 9.0, 2.0)
    covariances = np.zeros((N_FRAMES, n_points, 4, 4))
    covariances[..., 0, 0] = covariances[..., 1, 1] = variances
    covariances[..., 2, 2] = covariances[..., 3, 3] = 1.0
    covariances[..., 0, 1] = covariances[..., 1, 0] = 0.6 * variances * (TRACK_IDS == 1)  # one tilted gate
    covariances[7, 4] = np.nan  # no estimate once the track is gone
    states[7, 4] = np.nan
    np.savez(
        folder / "tracks.npz",
        positions=positions,
        states=states,
        covariances=covariances,
        status=status,
        track_ids=TRACK_IDS,
    )
    with (folder / "tracks.csv").open("w", newline="") as handle:
        writer = csv.writer(handle)
        writer.writerow(["frame", "track_id", "x", "y", "status"])
        for f in range(N_FRAMES):
            for p, track in enumerate(TRACK_IDS):
                writer.writerow([f, track, positions[f, p, 0], positions[f, p, 1], status[f, p]])

    if frames:
        (folder / "frames").mkdir(exist_ok=True)
        rows, cols = np.mgrid[0:HEIGHT, 0:WIDTH]
        for f in range(N_FRAMES):
            image = 40.0 + 20.0 * ((cols // 8 + rows // 8) % 2)
            for x, y in truth[f]:
                image += 180.0 * np.exp(-((cols - x) ** 2 + (rows - y) ** 2) / 3.0)
            cv2.imwrite(str(folder / "frames" / f"frame_{f:03d}.png"), np.clip(image, 0, 255).astype(np.uint8))

    rotations = camera_rotations()
    with (folder / "motion.csv").open("w", newline="") as handle:
        writer = csv.writer(handle)
        writer.writerow(["frame", "i_x", "i_y", "i_z", "j_x", "j_y", "j_z", "t_x", "t_y"])
        for f in range(N_FRAMES):
            writer.writerow([f, *rotations[f, 0], *rotations[f, 1], *CENTRE_PX])
    # the recovered shape: the truth in another scale and offset, plus noise
    recovered = SCALE_PX * SHAPE + rng.normal(scale=0.2, size=SHAPE.shape)
    with (folder / "structure.csv").open("w", newline="") as handle:
        writer = csv.writer(handle)
        writer.writerow(["track_id", "X", "Y", "Z"])
        writer.writerows([[t, *p] for t, p in zip(TRACK_IDS, recovered)])

    if ground_truth:
        with (folder / "ground_truth_tracks.csv").open("w", newline="") as handle:
            writer = csv.writer(handle)
            writer.writerow(["frame", "track_id", "x", "y", "visible"])
            for f in range(N_FRAMES):
                for p, track in enumerate(TRACK_IDS):
                    writer.writerow([f, track, truth[f, p, 0], truth[f, p, 1], int(not (f == 3 and p == 3))])
        with (folder / "ground_truth_points.csv").open("w", newline="") as handle:
            writer = csv.writer(handle)
            writer.writerow(["track_id", "X", "Y", "Z"])
            writer.writerows([[t, *p] for t, p in zip(TRACK_IDS, SHAPE)])

    if tables:
        (folder / "fusion_tables").mkdir(exist_ok=True)
        (folder / "fusion_tables" / "task1.csv").write_text("k,estimate,variance\n1,100.06,1.0\n2,100.38,0.5\n")

    if prerendered:
        gradient = np.tile(np.linspace(0, 255, 120, dtype=np.uint8), (40, 1))
        cv2.imwrite(str(folder / "covariance_trace.png"), gradient)
        cv2.imwrite(str(folder / "structure.png"), gradient.T.copy())

    errors = np.linalg.norm(positions - truth, axis=-1)
    files = ["tracks.npz", "tracks.csv", "motion.csv", "structure.csv"]
    files += [f"frames/frame_{f:03d}.png" for f in range(N_FRAMES)] if frames else []
    files += ["ground_truth_tracks.csv", "ground_truth_points.csv"] if ground_truth else []
    files += ["fusion_tables/task1.csv"] if tables else []
    files += ["covariance_trace.png", "structure.png"] if prerendered else []
    per_track = tuple(
        TrackMetrics(
            track_id=int(track),
            frames_measured=int((status[:, p] == 1).sum()),
            frames_predicted=int((status[:, p] == 2).sum()),
            lost_at=int(np.flatnonzero(status[:, p] == 3)[0]) if (status[:, p] == 3).any() else None,
            mean_std_px=float(np.sqrt(variances[:, p]).mean()),
        )
        for p, track in enumerate(TRACK_IDS)
    )
    truth_record = TruthComparison(
        tracking_rms_error_px=float(np.sqrt(np.nanmean(errors**2))),
        within_2px=float(np.nanmean(errors < 2.0)),
        visible_measured_fraction=float((status == 1).mean()),
        per_track_rms_error_px=tuple(float(np.sqrt(np.nanmean(errors[:, p] ** 2))) for p in range(n_points)),
        shape_error_pct=1.9,
        rotation_error_deg=tuple(0.1 * f for f in range(N_FRAMES)),
        alignment=Similarity(scale=1.0 / SCALE_PX, rotation=tuple(map(tuple, np.eye(3))), translation=(0.0, 0.0, 0.0)),
    )
    summary = RunSummary(
        command="kalmansfm demo --out fake",
        input="built-in scene (seed 0)" if ground_truth else "/data/<my video>.mp4",
        created="2024-01-02T03:04:05+00:00",
        versions=Versions(kalmansfm="0.1.0"),
        settings=TrackerSettings(window=7),
        timings_s=(("render", 0.12), ("track", 0.5), ("factorize", 0.01)),
        total_s=0.7,
        tracking=TrackingMetrics(
            frames=N_FRAMES,
            tracks=n_points,
            measured_fraction=float((status == 1).mean()),
            alive_in_last_frame=int(np.isin(status[-1], (1, 2)).sum()),
            survival_of_first_frame_tracks=float(np.isin(status[-1], (1, 2)).mean()),
            lost=1,
            mean_covariance_trace=tuple(float(v) for v in np.nanmean(np.trace(covariances, axis1=-2, axis2=-1), axis=1)),
            per_track=per_track,
        ),
        reconstruction=ReconstructionMetrics(
            kind="affine", method="als", camera_model="affine", frames=N_FRAMES, registered_frames=N_FRAMES,
            unregistered=(), points=n_points, reconstructed=n_points, unreliable=0, too_few_views=0, degenerate=0,
            behind_camera=0, observations=int((status == 1).sum()), used=int((status == 1).sum()), rejected=0,
            noise_std=1.1, noise_estimated=True, noise_unit="unit weight", noise_model="gaussian",
            degrees_of_freedom=40, reprojection_rms_px=0.41, median_point_std=0.3, median_centre_std=None,
            covariance_gauge="affine gauge", iterations=12,
            singular_values=(310.0, 220.0, 95.0, 1.2, 0.8, 0.5, 0.3, 0.2, 0.1, 0.05),
            weighted=True, smoothed=True,
            warnings=("track 4 was lost in frame 6; factorized the 4 complete tracks", "a<b & c"),
        ),
        truth=truth_record if ground_truth else None,
        files=tuple(files) + ("summary.json",),
    )
    (folder / "summary.json").write_text(summary_json(summary))
    return folder


def drop_files(folder: Path, *names: str) -> Path:
    """Delete files of the run and take them off its summary's list, as if the run had not written them."""
    summary = read_summary(folder / "summary.json")
    for name in names:
        (folder / name).unlink()
    kept = tuple(f for f in summary.files if f not in names)
    (folder / "summary.json").write_text(summary_json(replace(summary, files=kept)))
    return folder
